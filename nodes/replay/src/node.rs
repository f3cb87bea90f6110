//! The replay node: the graph's source of tiles, from a simulated stage, a scan directory or
//! an MCAP recording, paced like the instrument or as fast as possible.
//!
//! A shell: the source and its pacing are [`crate::source::open_source`] and
//! [`crate::run::StageRun`]; this file writes the truth (and the specimen when asked) beside
//! the outputs and maps the run's tiles to frames on the `tiles` port.

use std::collections::BTreeMap;
use std::time::Instant;

use anyhow::{anyhow, bail, Context, Result};
use surfstream_core::frame::monotonic_ns;
use surfstream_core::record::{self, ReplayReport, ScanRecord, SourceTile};
use surfstream_runtime::graph::NodeContext;
use surfstream_runtime::node::{Input, NodeLogic, Outbox};

use crate::run::StageRun;
use crate::source::{err_in, open_source};
use crate::truth_for;

const PORT: &str = "tiles";

pub struct ReplayNode {
    run: StageRun,
    done: bool,
    scan: ScanRecord,
    tiles: Vec<SourceTile>,
}

/// The node's parameters checked cheaply, before anything is started: the simulated stage's
/// plan and specimen settings (not the specimen itself), the pacing, that a scan or recording
/// path is a regular file, and a scan's manifest as its loader reads it (no tile is read). A
/// scan whose heights will be taken as um is said here, once.
pub fn check(ctx: &NodeContext) -> Result<()> {
    // Errors name the graph and the node as every node's do (the launcher adds the file).
    let config = crate::Config::from_table(&ctx.params).map_err(|e| err_in(ctx, e))?;
    config.check().map_err(|e| err_in(ctx, e))?;
    if let crate::Config::Scan(scan) = &config {
        let listing = crate::scan_dir::ManifestListing::read(&scan.manifest())?;
        if listing.heights_assumed_um() {
            eprintln!(
                "stitch: warning: {}: no [scan] height_unit and the tiles carry none (.npy/.xyz): heights taken as um",
                listing.path.display()
            );
        }
    }
    Ok(())
}

/// Builds the node from its graph parameters.
pub fn build(ctx: &NodeContext) -> Result<Box<dyn NodeLogic + Send>> {
    let source = open_source(ctx)?;
    if let Some(plan) = source.run.plan() {
        // The truth beside the outputs, so users and tests can score the result.
        std::fs::create_dir_all(&ctx.out_dir)
            .with_context(|| format!("{}: cannot create", ctx.out_dir.display()))?;
        let truth_path = ctx.out_dir.join("truth.json");
        let mut truth = truth_for(plan);
        truth.specimen.roughness_period_px = source.specimen().and_then(|s| s.period_px());
        surfstream_core::fsutil::write_atomic(&truth_path, |w| {
            serde_json::to_writer_pretty(w, &truth)
                .map_err(|e| anyhow!("{}: {e}", truth_path.display()))
        })?;
    }
    if let (true, Some(specimen)) = (source.save_specimen, source.specimen()) {
        // The whole virtual part, so a test or a user can compare the panorama with it (a
        // periodic specimen is rendered for it: 4 B per specimen pixel, only when asked).
        let specimen = specimen
            .to_specimen()
            .map_err(|e| anyhow!("save_specimen: {e}"))?;
        let path = ctx.out_dir.join("specimen.npy");
        surfstream_io::npy::write_npy_f32(
            &path,
            &specimen.heights,
            specimen.shape.rows,
            specimen.shape.cols,
        )?;
        // The specimen is sampled at the stage's pitch from the scan origin: its pitch travels in
        // the sidecar, so `params` or `convert` of it measure in um, not at an assumed 1 um.
        surfstream_io::sidecar::write_sidecar(
            &path,
            &surfstream_io::sidecar::NpyGeometry {
                pitch_x_um: specimen.pitch_um,
                pitch_y_um: specimen.pitch_um,
                origin_um: None,
            },
        )?;
    }
    Ok(Box::new(ReplayNode {
        run: source.run,
        done: false,
        scan: source.scan,
        tiles: source.tiles,
    }))
}

impl NodeLogic for ReplayNode {
    fn on_input(&mut self, port: &str, _: Input<'_>, _: &mut Outbox) -> Result<()> {
        bail!("the replay node has no inputs (got a message on '{port}')")
    }

    fn on_drained(&mut self, _: &mut Outbox) -> Result<()> {
        Ok(())
    }

    fn next_wakeup(&self) -> Option<Instant> {
        if self.done {
            return None;
        }
        // Done but not yet ended (no tile at all): wake now to send the end of scan.
        Some(
            self.run
                .next_due(Instant::now())
                .unwrap_or_else(Instant::now),
        )
    }

    fn on_timer(&mut self, out: &mut Outbox) -> Result<()> {
        match self.run.next_tile(Instant::now()) {
            Some(mut tile) => {
                tile.frame.header.t_acquired_ns = monotonic_ns();
                out.send_frame(PORT, tile.frame);
                if tile.last {
                    out.end_frames(PORT, tile.index as u32, monotonic_ns());
                    self.done = true;
                }
            }
            None => {
                out.end_frames(PORT, 0, monotonic_ns());
                self.done = true;
            }
        }
        Ok(())
    }

    fn finished(&self) -> bool {
        self.done
    }

    fn report(&self) -> anyhow::Result<serde_json::Value> {
        Ok(record::to_value(&ReplayReport {
            scan: self.scan.clone(),
            tiles: self.tiles.clone(),
            sent: BTreeMap::from([(PORT.to_string(), self.run.sent() as u64)]),
        })?)
    }
}
