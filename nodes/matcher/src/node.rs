//! The matcher node: feeds each arriving tile to [`ScanRegistration`] and publishes one
//! [`surfstream_core::TileRegistration`] per tile, in acquisition order; at end of scan it
//! runs the global solve once ([`ScanRegistration::finish`]) and publishes one more
//! registration per tile, flagged [`flags::FINAL`], before the end-of-scan marker. The
//! decisions live in [`crate::scan`].

use anyhow::{anyhow, bail, Result};
use surfstream_core::frame::{flags, FrameKind};
use surfstream_core::raster::{Raster, Shape};
use surfstream_runtime::graph::NodeContext;
use surfstream_runtime::node::{Input, NodeLogic, Outbox};

use crate::pair_log::PairLog;
use crate::params::MatcherConfig;
use crate::scan::{ScanRegistration, ScanTile};

const OUT: &str = "registrations";

pub struct MatcherNode {
    scan: ScanRegistration,
    /// Tiles received since the last drain, registered then (receive eagerly, compute lazily).
    pending: Vec<ScanTile>,
    ended: bool,
    done: bool,
    /// The end-of-scan marker's tile index and acquisition time, passed on.
    last: (u32, u64),
    /// Each pair's streaming record as it is decided (the live view reads it), and how many
    /// of the scan's pairs it holds.
    pair_log: PairLog,
    pairs_logged: usize,
}

/// The node's parameters checked as [`build`] checks them, with nothing built.
pub fn check(ctx: &NodeContext) -> Result<()> {
    scan_params(ctx).map(drop)
}

fn scan_params(ctx: &NodeContext) -> Result<crate::ScanParams> {
    let scan_params = |c: &MatcherConfig| c.scan_params(&ctx.out_dir).map_err(|e| e.to_string());
    Ok(ctx.settings(scan_params)?.1)
}

pub fn build(ctx: &NodeContext) -> Result<Box<dyn NodeLogic + Send>> {
    let mut params = scan_params(ctx)?;
    // Placed tiles spill where the run's memory plan says (the out dir, beside the outputs).
    params.spill_dir = Some(ctx.memory.spill_dir.clone());
    let pair_log = PairLog::new(&ctx.out_dir, &ctx.node_id);
    Ok(Box::new(MatcherNode {
        scan: ScanRegistration::new(params),
        pending: Vec::new(),
        ended: false,
        done: false,
        last: (0, 0),
        pair_log,
        pairs_logged: 0,
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
            pitch: h
                .pitch()
                .map_err(|e| anyhow!("matcher: tile {}: {e}", h.tile_index))?,
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
            let pairs = self.scan.streaming_pairs().skip(self.pairs_logged);
            self.pairs_logged += pairs.len();
            self.pair_log
                .append(pairs)
                .map_err(|e| anyhow!("matcher: {e}"))?;
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

    fn report(&self) -> anyhow::Result<serde_json::Value> {
        Ok(self.scan.report()?)
    }
}
