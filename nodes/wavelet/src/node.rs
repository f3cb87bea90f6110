//! The wavelet node: maps frames to [`LiveSeparation`] and [`final_separation`] calls.
//!
//! Panorama patches go into the live separation as they arrive; each wake-up publishes one
//! live pass over what changed (flag PREVIEW). The final panorama gets the exact pass as it
//! arrives, on the received frame itself (no copy: under `launch` it is read from shared
//! memory, under `run` from the fusion's own buffer), written to the out dir and published
//! with FINAL; the end-of-scan markers follow at end of scan. The whole datum / roughness
//! frames are built and published only when the graph wires a consumer to that port (the
//! demo wires only `pooled`): the streamed final pass never holds them otherwise.

use anyhow::{anyhow, bail, Result};
use surfstream_core::frame::{flags, FrameKind, FrameView};
use surfstream_core::record::{self, WaveletReport};
use surfstream_io::output::OutputWriter;
use surfstream_runtime::graph::NodeContext;
use surfstream_runtime::node::{Input, NodeLogic, Outbox};

use crate::live::{final_separation_with, FinalRequest, FinalSummary, LiveSeparation};
use crate::options::{SeparationSettings, WaveletConfig};
use crate::stream::StreamOptions;

pub struct WaveletNode {
    settings: SeparationSettings,
    live: LiveSeparation,
    /// Publish live passes (patches are applied either way: that also checks them).
    publish_live: bool,
    files: Option<OutputWriter>,
    /// Consumers are wired to `datum` / `roughness`.
    publish_datum: bool,
    publish_roughness: bool,
    /// Level stores of the streamed final pass go beside the outputs (the staging out dir).
    spill_dir: std::path::PathBuf,
    /// The final panorama's tile index and acquisition time, once its pass has run (the
    /// end-of-scan markers carry them).
    final_stamp: Option<(u32, u64)>,
    ended: bool,
    done: bool,
    live_patches: u64,
    summary: Option<FinalSummary>,
}

/// The node's parameters checked as [`build`] checks them, with nothing built.
pub fn check(ctx: &NodeContext) -> Result<()> {
    ctx.settings(WaveletConfig::settings).map(drop)
}

pub fn build(ctx: &NodeContext) -> Result<Box<dyn NodeLogic + Send>> {
    let (p, settings) = ctx.settings(WaveletConfig::settings)?;
    let wired = |port: &str| {
        ctx.outputs
            .iter()
            .any(|o| o.port == port && o.subscribers > 0)
    };
    let mut live = LiveSeparation::new(&settings, p.live_margin_px)?;
    let memory = &ctx.memory;
    if let Some(bytes) = memory.live_mirror_bytes() {
        live.limit_mirror(bytes, memory.spill_dir.clone());
    }
    Ok(Box::new(WaveletNode {
        publish_datum: wired("datum"),
        publish_roughness: wired("roughness"),
        spill_dir: memory.spill_dir.clone(),
        live,
        settings,
        publish_live: p.live,
        files: p.write_files.then(|| OutputWriter::new(&ctx.out_dir)),
        final_stamp: None,
        ended: false,
        done: false,
        live_patches: 0,
        summary: None,
    }))
}

impl WaveletNode {
    /// The exact pass over the final panorama, borrowed from the input; its frames go out now.
    fn final_pass(&mut self, pano: FrameView<'_>, out: &mut Outbox) -> Result<()> {
        if self.final_stamp.is_some() {
            bail!("wavelet: a second final panorama in one scan");
        }
        let request = FinalRequest {
            files: self.files.as_mut(),
            publish_datum: self.publish_datum,
            publish_roughness: self.publish_roughness,
            stream: StreamOptions {
                spill_dir: Some(self.spill_dir.clone()),
                ..StreamOptions::default()
            },
        };
        let f = final_separation_with(&self.settings, pano, request)?;
        self.summary = Some(f.summary);
        if let Some(datum) = f.datum {
            out.send_frame("datum", datum);
        }
        if let Some(roughness) = f.roughness {
            out.send_frame("roughness", roughness);
        }
        out.send_frame("pooled", f.pooled);
        self.final_stamp = Some((pano.header.tile_index, pano.header.t_acquired_ns));
        Ok(())
    }

    /// One live pass over what changed, published (when live passes are on).
    fn publish_live_pass(&mut self, out: &mut Outbox) -> Result<()> {
        if !(self.publish_live && self.live.has_changes()) {
            return Ok(());
        }
        if let Some(p) = self.live.live_pass()? {
            out.send_frame("datum", p.datum);
            out.send_frame("roughness", p.roughness);
            if let Some(pooled) = p.pooled {
                out.send_frame("pooled", pooled);
            }
            self.live_patches += 1;
        }
        Ok(())
    }
}

impl NodeLogic for WaveletNode {
    fn on_input(&mut self, port: &str, input: Input<'_>, out: &mut Outbox) -> Result<()> {
        let Input::Frame(f) = input else {
            bail!("wavelet: input '{port}' must carry frames")
        };
        if f.header.has(flags::END_OF_SCAN) {
            self.ended = true;
            return Ok(());
        }
        match f.header.kind() {
            Some(FrameKind::PanoramaPatch) => self.live.apply_patch(f.header, f.heights)?,
            Some(FrameKind::Panorama) => {
                // The last live patches go out now and the live mirror (an f32 copy of the
                // panorama in chunks) is freed before the final pass: the node never holds
                // both, and it never copies the final panorama.
                self.publish_live_pass(out)?;
                self.live.release_mirror();
                self.final_pass(f, out)?;
            }
            other => {
                bail!("wavelet: input '{port}' carries {other:?} frames, expected panorama patches")
            }
        }
        Ok(())
    }

    fn on_drained(&mut self, out: &mut Outbox) -> Result<()> {
        // Live patches of the last tiles go out first; then the end-of-scan markers.
        if self.publish_live && self.live.has_changes() {
            self.publish_live_pass(out)?;
        } else if self.ended && !self.done {
            let (tile, t_ns) = self
                .final_stamp
                .ok_or_else(|| anyhow!("wavelet: end of scan without a final panorama"))?;
            for port in ["datum", "roughness", "pooled"] {
                out.end_frames(port, tile, t_ns);
            }
            self.done = true;
        }
        Ok(())
    }

    fn has_pending_work(&self) -> bool {
        // Under a budget a large changed region is served in bands, one per pass: the next
        // band goes out without waiting for input.
        (self.ended && !self.done) || (self.publish_live && self.live.has_changes())
    }

    fn finished(&self) -> bool {
        self.done
    }

    fn report(&self) -> anyhow::Result<serde_json::Value> {
        Ok(record::to_value(&WaveletReport {
            live_patches: self.live_patches,
            final_pass: self.summary.clone(),
        })?)
    }
}
