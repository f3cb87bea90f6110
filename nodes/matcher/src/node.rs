//! The matcher node: registers each arriving tile against its already-placed grid neighbours
//! and publishes one [`TileRegistration`] per tile, in acquisition order.
//!
//! A tile's position is its placed neighbour's position plus the measured offset (averaged over
//! accepted links, weighted by NCC). With no trustworthy link it keeps its stage position
//! relative to its placed neighbours (the stage's own offset between them) and is flagged
//! `placed_by: "stage"`. The plane correction (piston, tilt) levels it onto its neighbours.

use std::collections::BTreeMap;

use anyhow::{bail, Result};
use serde::Deserialize;
use serde_json::json;
use surfstream_common::frame::{flags, placed_by, FrameKind, TileRegistration};
use surfstream_common::graph::NodeContext;
use surfstream_common::node::{Input, NodeLogic, Outbox};

use crate::{estimate_plane, PhaseCorrelator, PhaseParams, PlaneCorrection, RasterRef};

const OUT: &str = "registrations";

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Params {
    /// Registration method; this build has phase correlation ("phase"; "auto" = the best).
    #[serde(default = "auto")]
    method: String,
    /// Lowest NCC of the overlap at the chosen shift for a link to be trusted.
    min_ncc: Option<f64>,
    /// Largest accepted deviation from the stage's nominal offset, px.
    max_shift_px: Option<f64>,
}

fn auto() -> String {
    "auto".into()
}

/// A tile that later tiles may register against.
struct PlacedTile {
    index: u32,
    row: u32,
    width: usize,
    height: usize,
    heights: Vec<f32>,
    stage_um: [f64; 2],
    position_um: [f64; 2],
    plane: PlaneCorrection,
}

/// A tile waiting for `on_drained`.
struct PendingTile {
    index: u32,
    row: u32,
    col: u32,
    width: usize,
    height: usize,
    pitch_um: [f64; 2],
    stage_um: [f64; 2],
    t_acquired_ns: u64,
    heights: Vec<f32>,
}

pub struct MatcherNode {
    params: PhaseParams,
    method: String,
    correlator: PhaseCorrelator,
    pending: Vec<PendingTile>,
    placed: BTreeMap<(u32, u32), PlacedTile>,
    ended: bool,
    done: bool,
    last: (u32, u64),
    tiles_report: Vec<serde_json::Value>,
    pairs_report: Vec<serde_json::Value>,
}

pub fn build(ctx: &NodeContext) -> Result<Box<dyn NodeLogic + Send>> {
    let p: Params = ctx.params()?;
    if !matches!(p.method.as_str(), "auto" | "phase") {
        bail!(
            "graph '{}', node '{}': method = {:?}: expected \"auto\" or \"phase\" (feature matchers come later)",
            ctx.graph_name,
            ctx.node_id,
            p.method
        );
    }
    let mut params = PhaseParams::default();
    if let Some(v) = p.min_ncc {
        params.min_ncc = v;
    }
    if let Some(v) = p.max_shift_px {
        params.max_shift_px = v;
    }
    params
        .validate()
        .map_err(|e| anyhow::anyhow!("graph '{}', node '{}': {e}", ctx.graph_name, ctx.node_id))?;
    Ok(Box::new(MatcherNode {
        params,
        method: "phase".into(),
        correlator: PhaseCorrelator::new(),
        pending: Vec::new(),
        placed: BTreeMap::new(),
        ended: false,
        done: false,
        last: (0, 0),
        tiles_report: Vec::new(),
        pairs_report: Vec::new(),
    }))
}

impl MatcherNode {
    fn register(&mut self, t: PendingTile) -> TileRegistration {
        let pitch = t.pitch_um;
        let b = RasterRef {
            heights: &t.heights,
            width: t.width,
            height: t.height,
        };
        // Grid neighbours already placed: left/right, up/down.
        let keys = [
            (t.row, t.col.wrapping_sub(1)),
            (t.row, t.col + 1),
            (t.row.wrapping_sub(1), t.col),
            (t.row + 1, t.col),
        ];
        let mut votes = Vec::new();
        let mut stage_votes = Vec::new();
        let mut tried = 0;
        for key in keys {
            let Some(a) = self.placed.get(&key) else {
                continue;
            };
            tried += 1;
            let nominal = [
                (t.stage_um[0] - a.stage_um[0]) / pitch[0],
                (t.stage_um[1] - a.stage_um[1]) / pitch[1],
            ];
            let ar = RasterRef {
                heights: &a.heights,
                width: a.width,
                height: a.height,
            };
            let r = self.correlator.register(ar, b, nominal, &self.params);
            let direction = if a.row == t.row {
                "horizontal"
            } else {
                "vertical"
            };
            self.pairs_report.push(json!({
                "a": a.index, "b": t.index, "direction": direction,
                "nominal_offset_px": nominal,
                "offset_px": r.offset_px,
                "ncc": r.ncc, "peak_ratio": r.peak_ratio,
                "accepted": r.offset_px.is_some(),
                "reason": r.rejection.as_ref().map(|e| e.to_string()),
            }));
            stage_votes.push([
                a.position_um[0] + nominal[0] * pitch[0],
                a.position_um[1] + nominal[1] * pitch[1],
            ]);
            if let Some(off) = r.offset_px {
                let w = r.ncc.max(1e-3);
                votes.push((
                    w,
                    [
                        a.position_um[0] + off[0] * pitch[0],
                        a.position_um[1] + off[1] * pitch[1],
                    ],
                ));
            }
        }
        let (position_um, how) = if let Some(p) = weighted_mean(&votes) {
            (p, placed_by::REGISTRATION)
        } else if let Some(p) =
            weighted_mean(&stage_votes.iter().map(|p| (1.0, *p)).collect::<Vec<_>>())
        {
            (
                p,
                if tried == 0 {
                    placed_by::REGISTRATION
                } else {
                    placed_by::STAGE
                },
            )
        } else {
            // The first tile defines the scan frame: its stage position.
            (t.stage_um, placed_by::REGISTRATION)
        };
        // Level onto the placed neighbours, at the final relative positions.
        let neighbours: Vec<_> = keys
            .iter()
            .filter_map(|k| self.placed.get(k))
            .map(|a| {
                (
                    RasterRef {
                        heights: &a.heights,
                        width: a.width,
                        height: a.height,
                    },
                    [
                        (position_um[0] - a.position_um[0]) / pitch[0],
                        (position_um[1] - a.position_um[1]) / pitch[1],
                    ],
                    a.plane,
                )
            })
            .collect();
        let plane = if neighbours.is_empty() {
            PlaneCorrection::default()
        } else {
            estimate_plane(b, &neighbours).unwrap_or_default()
        };
        let quality = votes.iter().map(|v| v.0).fold(0.0, f64::max);
        let reg = TileRegistration {
            tile_index: t.index,
            placed_by: how,
            flags: if how == placed_by::STAGE {
                flags::PLACED_BY_STAGE
            } else {
                0
            },
            links_accepted: votes.len() as u32,
            links_tried: tried,
            x_um: position_um[0],
            y_um: position_um[1],
            piston_um: plane.piston_um,
            tilt_x_um_per_px: plane.tilt_x_um_per_px,
            tilt_y_um_per_px: plane.tilt_y_um_per_px,
            quality,
            t_acquired_ns: t.t_acquired_ns,
            ..Default::default()
        };
        self.tiles_report.push(json!({
            "index": t.index, "row": t.row, "col": t.col,
            "x_um": position_um[0], "y_um": position_um[1],
            "placed_by": if how == placed_by::STAGE { "stage" } else { "registration" },
            "links_accepted": votes.len(), "links_tried": tried, "quality": quality,
            "piston_um": plane.piston_um, "tilt_x_um_per_px": plane.tilt_x_um_per_px,
            "tilt_y_um_per_px": plane.tilt_y_um_per_px,
        }));
        // Later tiles only look back one grid row: drop what no neighbour can need.
        let row = t.row;
        self.placed.retain(|_, p| p.row + 1 >= row);
        self.placed.insert(
            (t.row, t.col),
            PlacedTile {
                index: t.index,
                row: t.row,
                width: t.width,
                height: t.height,
                heights: t.heights,
                stage_um: t.stage_um,
                position_um,
                plane,
            },
        );
        reg
    }
}

fn weighted_mean(votes: &[(f64, [f64; 2])]) -> Option<[f64; 2]> {
    let w: f64 = votes.iter().map(|v| v.0).sum();
    (w > 0.0).then(|| {
        let x = votes.iter().map(|v| v.0 * v.1[0]).sum::<f64>() / w;
        let y = votes.iter().map(|v| v.0 * v.1[1]).sum::<f64>() / w;
        [x, y]
    })
}

impl NodeLogic for MatcherNode {
    fn on_input(&mut self, port: &str, input: Input<'_>, _: &mut Outbox) -> Result<()> {
        let Input::Frame(f) = input else {
            bail!("matcher: input '{port}' carries registrations, expected tiles")
        };
        if f.header.has(flags::END_OF_SCAN) {
            self.ended = true;
            self.last = (f.header.tile_index, f.header.t_acquired_ns);
            return Ok(());
        }
        if f.header.kind() != Some(FrameKind::Tile) {
            bail!(
                "matcher: input '{port}' carries {:?} frames, expected tiles",
                f.header.kind()
            );
        }
        let h = f.header;
        self.pending.push(PendingTile {
            index: h.tile_index,
            row: h.tile_row,
            col: h.tile_col,
            width: h.width as usize,
            height: h.height as usize,
            pitch_um: [h.pitch_x_um, h.pitch_y_um],
            stage_um: [h.origin_x_um, h.origin_y_um],
            t_acquired_ns: h.t_acquired_ns,
            heights: f.heights.to_vec(),
        });
        Ok(())
    }

    fn on_drained(&mut self, out: &mut Outbox) -> Result<()> {
        for t in std::mem::take(&mut self.pending) {
            let reg = self.register(t);
            out.send_registration(OUT, reg);
        }
        if self.ended && !self.done {
            out.end_registrations(OUT, self.last.0, self.last.1);
            self.done = true;
        }
        Ok(())
    }

    fn finished(&self) -> bool {
        self.done
    }

    fn report(&self) -> serde_json::Value {
        json!({ "method": self.method, "tiles": self.tiles_report, "pairs": self.pairs_report })
    }
}
