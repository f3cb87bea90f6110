//! The fusion node: maps tile and registration frames to [`StreamingFusion`] calls, sends each
//! placed tile's panorama patch (and its decimated preview), and at end of scan the final
//! panorama, written to the out dir.

use anyhow::{bail, Result};
use surfstream_core::frame::flags;
use surfstream_core::record::{self, FusionMemory, FusionReport};
use surfstream_io::output::OutputWriter;
use surfstream_runtime::graph::NodeContext;
use surfstream_runtime::node::{Input, NodeLogic, Outbox};

use crate::config::FusionConfig;
use crate::stream::{FinalPanorama, FinalReport, StreamingFusion};

const PANORAMA: &str = "panorama";
const PREVIEW: &str = "preview";

pub struct FusionNode {
    fusion: StreamingFusion,
    chunk_budget_bytes: Option<usize>,
    files: Option<OutputWriter>,
    tiles_ended: bool,
    registrations_ended: bool,
    patches: u64,
    result: Option<FinalReport>,
}

/// The node's parameters checked as [`build`] checks them, with nothing built.
pub fn check(ctx: &NodeContext) -> Result<()> {
    ctx.settings(FusionConfig::settings).map(drop)
}

pub fn build(ctx: &NodeContext) -> Result<Box<dyn NodeLogic + Send>> {
    let (config, settings) = ctx.settings(FusionConfig::settings)?;
    let mut fusion = StreamingFusion::new(settings);
    let memory = &ctx.memory;
    let chunk_budget_bytes = memory.panorama_chunks_bytes().map(|b| b as usize);
    fusion.set_memory_budget(chunk_budget_bytes, Some(memory.spill_dir.clone()));
    fusion.set_zarr_min_px(config.zarr.min_px());
    Ok(Box::new(FusionNode {
        fusion,
        chunk_budget_bytes,
        files: config.write_files.then(|| OutputWriter::new(&ctx.out_dir)),
        tiles_ended: false,
        registrations_ended: false,
        patches: 0,
        result: None,
    }))
}

impl NodeLogic for FusionNode {
    fn on_input(&mut self, port: &str, input: Input<'_>, _: &mut Outbox) -> Result<()> {
        match (port, input) {
            ("tiles", Input::Frame(f)) if f.header.has(flags::END_OF_SCAN) => {
                self.tiles_ended = true
            }
            ("tiles", Input::Frame(f)) => self.fusion.add_tile(f.to_owned())?,
            ("registrations", Input::Registration(r)) if r.has(flags::END_OF_SCAN) => {
                self.registrations_ended = true
            }
            ("registrations", Input::Registration(r)) => self.fusion.add_registration(*r),
            _ => bail!("fusion: unexpected message on input '{port}'"),
        }
        Ok(())
    }

    fn on_drained(&mut self, out: &mut Outbox) -> Result<()> {
        let patches = self.fusion.place_ready()?;
        // The last tiles' patches go out first; the final pass runs on the next call.
        if patches.is_empty() && self.has_pending_work() {
            let FinalPanorama { panorama, report } = self.fusion.finish(self.files.as_mut())?;
            let (tile, t_acq) = self.fusion.last_tile();
            out.send_frame(PANORAMA, panorama);
            out.end_frames(PANORAMA, tile, t_acq);
            out.end_frames(PREVIEW, tile, t_acq);
            self.result = Some(report);
        }
        for p in patches {
            out.send_frame(PREVIEW, p.preview);
            out.send_frame(PANORAMA, p.patch);
            self.patches += 1;
        }
        Ok(())
    }

    fn has_pending_work(&self) -> bool {
        self.tiles_ended && self.registrations_ended && self.result.is_none()
    }

    fn finished(&self) -> bool {
        self.result.is_some()
    }

    fn report(&self) -> anyhow::Result<serde_json::Value> {
        let r = self.result.as_ref();
        Ok(record::to_value(&FusionReport {
            method: self.fusion.settings().method.name().into(),
            patches: self.patches,
            panorama: r.map(|r| r.summary),
            files: r.map_or(Vec::new(), |r| r.files.clone()),
            rerendered_from_final_registrations: r.is_some_and(|r| r.rerendered),
            final_registrations: self.fusion.final_registrations() as u64,
            ssim: "Wang et al. 2004 (paper eq. 7): 11x11 Gaussian window, sigma 1.5, K1 0.01, K2 0.03, L = height range of the overlap; SSIM(fused, each tile) over pixels both tiles measured".into(),
            fusion_pairs: r.map_or(Vec::new(), |r| r.pairs.clone()),
            memory: FusionMemory {
                chunk_px: crate::CHUNK_PX,
                chunk_budget_bytes: self.chunk_budget_bytes.map(|b| b as u64),
                chunks: record::to_value(&self.fusion.chunk_stats())?,
            },
        })?)
    }
}
