//! The matcher node: feeds each arriving tile to [`ScanRegistration`] and publishes one
//! [`surfstream_core::TileRegistration`] per tile, in acquisition order; at end of scan it
//! runs the global solve once ([`ScanRegistration::finish`]) and publishes one more
//! registration per tile, flagged [`flags::FINAL`], before the end-of-scan marker. The
//! decisions live in [`crate::scan`].

use anyhow::{anyhow, bail, Result};
use serde::Deserialize;
use surfstream_core::frame::{flags, FrameKind};
use surfstream_core::raster::{Raster, Shape};
use surfstream_runtime::graph::NodeContext;
use surfstream_runtime::node::{Input, NodeLogic, Outbox};

use crate::scan::{ScanParams, ScanRegistration, ScanTile};
use crate::{FeatureMethod, FeatureParams};

const OUT: &str = "registrations";

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Params {
    /// Registration method: "auto" (= "phase": phase correlation with NCC-verified
    /// candidates), "harris" or "sift" (the reference study's feature matchers).
    #[serde(default = "auto")]
    method: String,
    /// Lowest NCC of the overlap at the chosen shift for a link to be trusted.
    min_ncc: Option<f64>,
    /// Largest accepted deviation from the stage's nominal offset, px.
    max_shift_px: Option<f64>,
    /// Standard deviation of the stage positions, px: the weight of the prior in the global
    /// solve (5).
    stage_sigma_px: Option<f64>,
    /// A link disagreeing with the global solve by more than this (px) is removed (1).
    outlier_px: Option<f64>,
    /// A ground_truth.json (make_tiles.py's, or the simulated stage's truth.json; relative to
    /// the output directory): with a feature method, r and MAP against it (crate::efficiency).
    truth: Option<String>,
}

fn auto() -> String {
    "auto".into()
}

pub struct MatcherNode {
    scan: ScanRegistration,
    /// Tiles received since the last drain, registered then (receive eagerly, compute lazily).
    pending: Vec<ScanTile>,
    ended: bool,
    done: bool,
    /// The end-of-scan marker's tile index and acquisition time, passed on.
    last: (u32, u64),
}

pub fn build(ctx: &NodeContext) -> Result<Box<dyn NodeLogic + Send>> {
    let p: Params = ctx.params()?;
    let where_ = || format!("graph '{}', node '{}'", ctx.graph_name, ctx.node_id);
    let mut params = ScanParams {
        features: match p.method.as_str() {
            "auto" | "phase" => None,
            "harris" => Some(FeatureParams::for_method(FeatureMethod::Harris)),
            "sift" => Some(FeatureParams::for_method(FeatureMethod::Sift)),
            m => bail!(
                "{}: method = {m:?}: expected \"auto\", \"phase\", \"harris\" or \"sift\"",
                where_()
            ),
        },
        truth: p.truth.map(|t| ctx.out_dir.join(t)),
        ..ScanParams::default()
    };
    if let Some(v) = p.min_ncc {
        params.phase.min_ncc = v;
    }
    if let Some(v) = p.max_shift_px {
        params.phase.max_shift_px = v;
    }
    params
        .phase
        .validate()
        .map_err(|e| anyhow!("{}: {e}", where_()))?;
    for (name, value, field) in [
        (
            "stage_sigma_px",
            p.stage_sigma_px,
            &mut params.solve.stage_sigma_px,
        ),
        ("outlier_px", p.outlier_px, &mut params.solve.outlier_px),
    ] {
        if let Some(v) = value {
            if !(v.is_finite() && v > 0.0) {
                bail!("{}: {name} = {v}: expected a number > 0", where_());
            }
            *field = v;
        }
    }
    Ok(Box::new(MatcherNode {
        scan: ScanRegistration::new(params),
        pending: Vec::new(),
        ended: false,
        done: false,
        last: (0, 0),
    }))
}

impl NodeLogic for MatcherNode {
    fn on_input(&mut self, port: &str, input: Input<'_>, _: &mut Outbox) -> Result<()> {
        let Input::Frame(f) = input else {
            bail!("matcher: input '{port}' carries registrations, expected tiles")
        };
        let h = f.header;
        if h.has(flags::END_OF_SCAN) {
            self.ended = true;
            self.last = (h.tile_index, h.t_acquired_ns);
            return Ok(());
        }
        if h.kind() != Some(FrameKind::Tile) {
            bail!(
                "matcher: input '{port}' carries {:?} frames, expected tiles",
                h.kind()
            );
        }
        let shape = Shape::new(h.height as usize, h.width as usize);
        let tile = ScanTile {
            index: h.tile_index,
            row: h.tile_row,
            col: h.tile_col,
            pitch_um: [h.pitch_x_um, h.pitch_y_um],
            stage_um: [h.origin_x_um, h.origin_y_um],
            t_acquired_ns: h.t_acquired_ns,
            heights: Raster::new(f.heights.to_vec(), shape)
                .map_err(|e| anyhow!("matcher: tile {}: {e}", h.tile_index))?,
        };
        tile.validate().map_err(|e| anyhow!("matcher: {e}"))?;
        self.pending.push(tile);
        Ok(())
    }

    fn on_drained(&mut self, out: &mut Outbox) -> Result<()> {
        for t in std::mem::take(&mut self.pending) {
            let reg = self.scan.register(t).map_err(|e| anyhow!("matcher: {e}"))?;
            out.send_registration(OUT, reg);
        }
        if self.ended && !self.done {
            for reg in self.scan.finish().map_err(|e| anyhow!("matcher: {e}"))? {
                out.send_registration(OUT, reg);
            }
            out.end_registrations(OUT, self.last.0, self.last.1);
            self.done = true;
        }
        Ok(())
    }

    fn finished(&self) -> bool {
        self.done
    }

    fn report(&self) -> serde_json::Value {
        self.scan.report()
    }
}
