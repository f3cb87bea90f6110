//! The wavelet node: maps frames to [`LiveSeparation`] and [`final_separation`] calls.
//!
//! Panorama patches go into the live separation as they arrive; each wake-up publishes one
//! live pass over what changed (flag PREVIEW). At end of scan the final panorama gets the
//! exact pass, published with FINAL and written to the out dir.

use anyhow::{anyhow, bail, Result};
use serde::Deserialize;
use serde_json::json;
use surfstream_core::frame::{flags, FrameKind, HeightMap};
use surfstream_io::output::OutputWriter;
use surfstream_runtime::graph::NodeContext;
use surfstream_runtime::node::{Input, NodeLogic, Outbox};

use crate::live::{final_separation, LiveSeparation, SeparationSettings};
use crate::LevelChoice;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Params {
    /// A base name, or "auto": minimum reconstruction RMSE (eq. 10; it ranks round-off).
    #[serde(default = "sym5")]
    wavelet: String,
    /// Decomposition level of the datum (clamped to the largest useful level of the
    /// panorama), or "auto": minimum approximation energy proportion (Fig. 13).
    level: Option<LevelParam>,
    #[serde(default = "symmetric")]
    mode: String,
    /// Pooling block, px.
    #[serde(default = "four")]
    pool: usize,
    /// "max" (the paper) or "mean".
    #[serde(default = "max")]
    pool_op: String,
    /// Publish live (preview) patches while tiles arrive.
    #[serde(default = "yes")]
    live: bool,
    /// Context around the changed region for a live patch, px.
    #[serde(default = "margin")]
    live_margin_px: usize,
    #[serde(default = "yes")]
    write_files: bool,
}

/// A level as a TOML number or a string ("auto").
#[derive(Deserialize)]
#[serde(untagged)]
enum LevelParam {
    Level(usize),
    Named(String),
}

fn sym5() -> String {
    "sym5".into()
}
fn symmetric() -> String {
    "symmetric".into()
}
fn four() -> usize {
    4
}
fn max() -> String {
    "max".into()
}
fn yes() -> bool {
    true
}
fn margin() -> usize {
    256
}

pub struct WaveletNode {
    settings: SeparationSettings,
    live: LiveSeparation,
    /// Publish live passes (patches are applied either way: that also checks them).
    publish_live: bool,
    files: Option<OutputWriter>,
    final_panorama: Option<HeightMap>,
    ended: bool,
    done: bool,
    live_patches: u64,
    summary: serde_json::Value,
}

pub fn build(ctx: &NodeContext) -> Result<Box<dyn NodeLogic + Send>> {
    let p: Params = ctx.params()?;
    let at = format!("graph '{}', node '{}'", ctx.graph_name, ctx.node_id);
    let level = match &p.level {
        None => Ok(LevelChoice::Default),
        Some(LevelParam::Level(l)) => l.to_string().parse(),
        Some(LevelParam::Named(n)) => n.parse(),
    }
    .map_err(|e| anyhow!("{at}: level = {e}"))?;
    if p.pool == 0 {
        bail!("{at}: pool = 0: expected a block size of at least 1 px");
    }
    let settings = SeparationSettings {
        base: p
            .wavelet
            .parse()
            .map_err(|e| anyhow!("{at}: wavelet = {e}"))?,
        level,
        mode: p.mode.parse().map_err(|e| anyhow!("{at}: mode = {e}"))?,
        pool_block: p.pool,
        pool_op: p
            .pool_op
            .parse()
            .map_err(|e| anyhow!("{at}: pool_op = {e}"))?,
    };
    Ok(Box::new(WaveletNode {
        live: LiveSeparation::new(&settings, p.live_margin_px)?,
        settings,
        publish_live: p.live,
        files: p.write_files.then(|| OutputWriter::new(&ctx.out_dir)),
        final_panorama: None,
        ended: false,
        done: false,
        live_patches: 0,
        summary: serde_json::Value::Null,
    }))
}

impl NodeLogic for WaveletNode {
    fn on_input(&mut self, port: &str, input: Input<'_>, _: &mut Outbox) -> Result<()> {
        let Input::Frame(f) = input else {
            bail!("wavelet: input '{port}' must carry frames")
        };
        if f.header.has(flags::END_OF_SCAN) {
            self.ended = true;
            return Ok(());
        }
        match f.header.kind() {
            Some(FrameKind::PanoramaPatch) => self.live.apply_patch(f.header, f.heights)?,
            Some(FrameKind::Panorama) => self.final_panorama = Some(f.to_owned()),
            other => {
                bail!("wavelet: input '{port}' carries {other:?} frames, expected panorama patches")
            }
        }
        Ok(())
    }

    fn on_drained(&mut self, out: &mut Outbox) -> Result<()> {
        // Live patches of the last tiles go out first; the final pass runs on the next call.
        if self.publish_live && self.live.has_changes() {
            if let Some(p) = self.live.live_pass()? {
                out.send_frame("datum", p.datum);
                out.send_frame("roughness", p.roughness);
                if let Some(pooled) = p.pooled {
                    out.send_frame("pooled", pooled);
                }
                self.live_patches += 1;
            }
        } else if self.ended && !self.done {
            let pano = self
                .final_panorama
                .take()
                .ok_or_else(|| anyhow!("wavelet: end of scan without a final panorama"))?;
            let f = final_separation(&self.settings, &pano, self.files.as_mut())?;
            self.summary = f.summary;
            out.send_frame("datum", f.datum);
            out.send_frame("roughness", f.roughness);
            out.send_frame("pooled", f.pooled);
            for port in ["datum", "roughness", "pooled"] {
                out.end_frames(port, pano.header.tile_index, pano.header.t_acquired_ns);
            }
            self.done = true;
        }
        Ok(())
    }

    fn has_pending_work(&self) -> bool {
        self.ended && !self.done
    }

    fn finished(&self) -> bool {
        self.done
    }

    fn report(&self) -> serde_json::Value {
        json!({ "live_patches": self.live_patches, "final": self.summary })
    }
}
