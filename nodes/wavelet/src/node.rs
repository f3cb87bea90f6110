//! The wavelet node: datum / roughness separation and pooling of the growing panorama.
//!
//! Live: every wake-up applies the arrived panorama patches to a local mirror (cheap copies),
//! then separates once, over the changed region plus a margin, at the level that window
//! supports, and publishes datum / roughness / pooled patches flagged PREVIEW. The work is
//! bounded by the window, not the panorama. A level-8 sym5 datum depends on ~2300 px around
//! each pixel, so live patches are approximations by construction.
//! Final: the exact pass over the whole final panorama, identical to the batch computation
//! ([`crate::separate`]), published with FINAL and written to the out dir.

use anyhow::{anyhow, bail, Result};
use serde::Deserialize;
use serde_json::json;
use surfstream_core::frame::{flags, FrameHeader, FrameKind, HeightMap};
use surfstream_io::preview::{write_preview_png, PreviewOptions};
use surfstream_runtime::graph::NodeContext;
use surfstream_runtime::node::{Input, NodeLogic, Outbox};

use crate::{
    analyse, default_level, pool, separate, BaseChoice, LevelChoice, Mode, PoolOp, Wavelet,
};

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

/// A region in mirror-grid pixels (may start left of / above the first patch).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Rect {
    x0: i64,
    y0: i64,
    w: usize,
    h: usize,
}

impl Rect {
    fn union(self, o: Rect) -> Rect {
        let x0 = self.x0.min(o.x0);
        let y0 = self.y0.min(o.y0);
        let x1 = (self.x0 + self.w as i64).max(o.x0 + o.w as i64);
        let y1 = (self.y0 + self.h as i64).max(o.y0 + o.h as i64);
        Rect {
            x0,
            y0,
            w: (x1 - x0) as usize,
            h: (y1 - y0) as usize,
        }
    }
    fn intersect(self, o: Rect) -> Option<Rect> {
        let x0 = self.x0.max(o.x0);
        let y0 = self.y0.max(o.y0);
        let x1 = (self.x0 + self.w as i64).min(o.x0 + o.w as i64);
        let y1 = (self.y0 + self.h as i64).min(o.y0 + o.h as i64);
        (x1 > x0 && y1 > y0).then(|| Rect {
            x0,
            y0,
            w: (x1 - x0) as usize,
            h: (y1 - y0) as usize,
        })
    }
    fn expand(self, m: i64) -> Rect {
        Rect {
            x0: self.x0 - m,
            y0: self.y0 - m,
            w: self.w + 2 * m as usize,
            h: self.h + 2 * m as usize,
        }
    }
}

/// The panorama as far as patches told it: a raster that grows in any direction.
struct Mirror {
    anchor_um: [f64; 2],
    pitch_um: [f64; 2],
    z_offset_um: f64,
    /// What patches have covered so far.
    extent: Rect,
    /// What `data` holds: the extent plus slack, so growth is amortised and the work per
    /// tile does not grow with the panorama.
    alloc: Rect,
    data: Vec<f32>,
}

impl Rect {
    fn contains(&self, o: &Rect) -> bool {
        o.x0 >= self.x0
            && o.y0 >= self.y0
            && o.x0 + o.w as i64 <= self.x0 + self.w as i64
            && o.y0 + o.h as i64 <= self.y0 + self.h as i64
    }
}

impl Mirror {
    fn new(h: &FrameHeader) -> Self {
        Mirror {
            anchor_um: [h.origin_x_um, h.origin_y_um],
            pitch_um: [h.pitch_x_um, h.pitch_y_um],
            z_offset_um: h.z_offset_um,
            extent: Rect {
                x0: 0,
                y0: 0,
                w: 0,
                h: 0,
            },
            alloc: Rect {
                x0: 0,
                y0: 0,
                w: 0,
                h: 0,
            },
            data: Vec::new(),
        }
    }

    fn rect_of(&self, h: &FrameHeader) -> Rect {
        Rect {
            x0: ((h.origin_x_um - self.anchor_um[0]) / self.pitch_um[0]).round() as i64,
            y0: ((h.origin_y_um - self.anchor_um[1]) / self.pitch_um[1]).round() as i64,
            w: h.width as usize,
            h: h.height as usize,
        }
    }

    /// Copies a patch in, growing the mirror as needed; returns the patch's rect.
    fn apply(&mut self, h: &FrameHeader, heights: &[f32]) -> Result<Rect> {
        if (h.pitch_x_um - self.pitch_um[0]).abs() > 1e-9 * self.pitch_um[0]
            || (h.z_offset_um - self.z_offset_um).abs() > 0.0
        {
            bail!(
                "wavelet: panorama patch {} changes pitch or z offset mid-scan",
                h.sequence
            );
        }
        let r = self.rect_of(h);
        self.extent = if self.data.is_empty() {
            r
        } else {
            self.extent.union(r)
        };
        if !self.alloc.contains(&self.extent) {
            // Grow by half of the current size (at least the patch) on every side that needs it.
            let need = self.extent;
            let (sx, sy) = ((need.w / 2).max(r.w) as i64, (need.h / 2).max(r.h) as i64);
            let old = self.alloc;
            let mut grown_rect = if self.data.is_empty() {
                need
            } else {
                old.union(need)
            };
            if !self.data.is_empty() {
                if need.x0 < old.x0 {
                    grown_rect.x0 -= sx;
                    grown_rect.w += sx as usize;
                }
                if need.y0 < old.y0 {
                    grown_rect.y0 -= sy;
                    grown_rect.h += sy as usize;
                }
                if need.x0 + need.w as i64 > old.x0 + old.w as i64 {
                    grown_rect.w += sx as usize;
                }
                if need.y0 + need.h as i64 > old.y0 + old.h as i64 {
                    grown_rect.h += sy as usize;
                }
            }
            let mut grown = vec![f32::NAN; grown_rect.w * grown_rect.h];
            if !self.data.is_empty() {
                let (dx, dy) = (
                    (old.x0 - grown_rect.x0) as usize,
                    (old.y0 - grown_rect.y0) as usize,
                );
                for row in 0..old.h {
                    let src = &self.data[row * old.w..(row + 1) * old.w];
                    let at = (row + dy) * grown_rect.w + dx;
                    grown[at..at + old.w].copy_from_slice(src);
                }
            }
            self.data = grown;
            self.alloc = grown_rect;
        }
        let (dx, dy) = (
            (r.x0 - self.alloc.x0) as usize,
            (r.y0 - self.alloc.y0) as usize,
        );
        for row in 0..r.h {
            let at = (row + dy) * self.alloc.w + dx;
            self.data[at..at + r.w].copy_from_slice(&heights[row * r.w..(row + 1) * r.w]);
        }
        Ok(r)
    }

    fn extract(&self, r: Rect) -> Vec<f32> {
        let (dx, dy) = (
            (r.x0 - self.alloc.x0) as usize,
            (r.y0 - self.alloc.y0) as usize,
        );
        let mut out = Vec::with_capacity(r.w * r.h);
        for row in 0..r.h {
            let at = (row + dy) * self.alloc.w + dx;
            out.extend_from_slice(&self.data[at..at + r.w]);
        }
        out
    }

    fn header_for(&self, r: Rect, kind: FrameKind, scale: usize) -> FrameHeader {
        FrameHeader {
            kind: kind as u32,
            width: r.w.div_ceil(scale) as u32,
            height: r.h.div_ceil(scale) as u32,
            pitch_x_um: self.pitch_um[0] * scale as f64,
            pitch_y_um: self.pitch_um[1] * scale as f64,
            origin_x_um: self.anchor_um[0] + r.x0 as f64 * self.pitch_um[0],
            origin_y_um: self.anchor_um[1] + r.y0 as f64 * self.pitch_um[1],
            z_offset_um: self.z_offset_um,
            ..Default::default()
        }
    }
}

pub struct WaveletNode {
    /// The base of live passes (sym5 when the final base is chosen by RMSE).
    wavelet: Wavelet,
    base: BaseChoice,
    mode: Mode,
    /// Level of live passes (the default when the final level is chosen by energy).
    level: Option<usize>,
    level_choice: LevelChoice,
    pool: usize,
    pool_op: PoolOp,
    live: bool,
    live_margin_px: usize,
    write_files: bool,
    out_dir: std::path::PathBuf,
    mirror: Option<Mirror>,
    dirty: Option<Rect>,
    /// Oldest acquisition time and latest tile among the patches not yet served.
    trace: Option<(u32, u64)>,
    final_panorama: Option<HeightMap>,
    ended: bool,
    done: bool,
    live_patches: u64,
    summary: serde_json::Value,
}

pub fn build(ctx: &NodeContext) -> Result<Box<dyn NodeLogic + Send>> {
    let p: Params = ctx.params()?;
    let at = || format!("graph '{}', node '{}'", ctx.graph_name, ctx.node_id);
    let base = if p.wavelet.trim().eq_ignore_ascii_case("auto") {
        BaseChoice::MinRmse
    } else {
        BaseChoice::Named(Wavelet::by_name(&p.wavelet).ok_or_else(|| {
            anyhow!(
                "{}: wavelet = {:?}: expected db1..db10, sym2..sym10, coif1..coif5 or \"auto\"",
                at(),
                p.wavelet
            )
        })?)
    };
    let wavelet = match base {
        BaseChoice::Named(w) => w,
        BaseChoice::MinRmse => Wavelet::by_name("sym5").ok_or_else(|| anyhow!("sym5 missing"))?,
    };
    let level_choice = match p.level {
        None => LevelChoice::Default,
        Some(LevelParam::Level(0)) => bail!(
            "{}: level = 0: expected a decomposition level of at least 1, or \"auto\"",
            at()
        ),
        Some(LevelParam::Level(l)) => LevelChoice::Fixed(l),
        Some(LevelParam::Named(n)) if n.trim().eq_ignore_ascii_case("auto") => {
            LevelChoice::MinEnergy
        }
        Some(LevelParam::Named(n)) => bail!(
            "{}: level = {n:?}: expected a decomposition level >= 1 or \"auto\"",
            at()
        ),
    };
    let mode = Mode::by_name(&p.mode).ok_or_else(|| {
        anyhow!(
            "{}: mode = {:?}: expected \"symmetric\" or \"periodization\"",
            at(),
            p.mode
        )
    })?;
    let Some(pool_op) = PoolOp::by_name(&p.pool_op) else {
        bail!(
            "{}: pool_op = {:?}: expected \"max\" or \"mean\"",
            at(),
            p.pool_op
        )
    };
    if p.pool == 0 {
        bail!("{}: pool = 0: expected a block size of at least 1 px", at());
    }
    Ok(Box::new(WaveletNode {
        wavelet,
        base,
        mode,
        level: match level_choice {
            LevelChoice::Fixed(l) => Some(l),
            _ => None,
        },
        level_choice,
        pool: p.pool,
        pool_op,
        live: p.live,
        live_margin_px: p.live_margin_px,
        write_files: p.write_files,
        out_dir: ctx.out_dir.clone(),
        mirror: None,
        dirty: None,
        trace: None,
        final_panorama: None,
        ended: false,
        done: false,
        live_patches: 0,
        summary: serde_json::Value::Null,
    }))
}

impl WaveletNode {
    /// One live pass over the changed region (plus margin) of the mirror.
    fn live_pass(&mut self, out: &mut Outbox) -> Result<()> {
        let (Some(m), Some(dirty), Some((tile, t_acq))) =
            (&self.mirror, self.dirty.take(), self.trace.take())
        else {
            return Ok(());
        };
        let Some(window) = dirty.expand(self.live_margin_px as i64).intersect(m.extent) else {
            return Ok(());
        };
        let heights = m.extract(window);
        if heights.iter().all(|z| z.is_nan()) {
            return Ok(());
        }
        // A window too small for even level 1 gets no live update; the final pass covers it.
        let Ok(level) = default_level(window.h, window.w, &self.wavelet, self.level) else {
            return Ok(());
        };
        let sep = separate(
            &heights,
            window.h,
            window.w,
            &self.wavelet,
            self.mode,
            Some(level),
        )?;
        let crop = |v: &[f32]| -> Vec<f32> {
            let (dx, dy) = (
                (dirty.x0 - window.x0) as usize,
                (dirty.y0 - window.y0) as usize,
            );
            let mut c = Vec::with_capacity(dirty.w * dirty.h);
            for row in 0..dirty.h {
                let at = (row + dy) * window.w + dx;
                c.extend_from_slice(&v[at..at + dirty.w]);
            }
            c
        };
        let stamp = |mut h: FrameHeader| {
            h.flags |= flags::PREVIEW;
            h.tile_index = tile;
            h.t_acquired_ns = t_acq;
            h
        };
        out.send_frame(
            "datum",
            HeightMap {
                header: stamp(m.header_for(dirty, FrameKind::Datum, 1)),
                heights: crop(&sep.datum),
            },
        );
        out.send_frame(
            "roughness",
            HeightMap {
                header: stamp(m.header_for(dirty, FrameKind::Roughness, 1)),
                heights: crop(&sep.roughness),
            },
        );
        // Pooled blocks stay aligned to the mirror's grid so live patches tile seamlessly.
        let b = self.pool as i64;
        let x0 = dirty.x0.div_euclid(b) * b;
        let y0 = dirty.y0.div_euclid(b) * b;
        let aligned = Rect {
            x0,
            y0,
            w: ((dirty.x0 + dirty.w as i64 - x0) as usize).div_ceil(self.pool) * self.pool,
            h: ((dirty.y0 + dirty.h as i64 - y0) as usize).div_ceil(self.pool) * self.pool,
        };
        if let Some(a) = aligned.intersect(m.extent) {
            let p = pool(&m.extract(a), a.h, a.w, self.pool, self.pool_op)?;
            let mut h = stamp(m.header_for(a, FrameKind::Pooled, self.pool));
            h.width = p.cols as u32;
            h.height = p.rows as u32;
            out.send_frame(
                "pooled",
                HeightMap {
                    header: h,
                    heights: p.heights,
                },
            );
        }
        self.live_patches += 1;
        Ok(())
    }

    /// The exact pass over the final panorama.
    fn final_pass(&mut self, out: &mut Outbox) -> Result<()> {
        let pano = self
            .final_panorama
            .take()
            .ok_or_else(|| anyhow!("wavelet: end of scan without a final panorama"))?;
        let h = pano.header;
        let (rows, cols) = (h.height as usize, h.width as usize);
        let analysis = analyse(
            &pano.heights,
            rows,
            cols,
            self.base,
            self.level_choice,
            self.mode,
            self.pool,
            self.pool_op,
        )?;
        let summary = analysis.summary();
        let wavelet = analysis.wavelet;
        let (sep, pooled) = (analysis.separation, analysis.pooled);
        let mk = |kind: FrameKind| FrameHeader {
            kind: kind as u32,
            flags: flags::FINAL,
            ..h
        };
        let mut ph = mk(FrameKind::Pooled);
        ph.width = pooled.cols as u32;
        ph.height = pooled.rows as u32;
        ph.pitch_x_um *= self.pool as f64;
        ph.pitch_y_um *= self.pool as f64;
        let mut files = Vec::new();
        if self.write_files {
            use surfstream_io::npy::{write_npy_f32, write_npy_f64};
            // datum and pooled carry the panorama's f64 offset (absolute heights, f64 files);
            // roughness is relative by nature and stays f32.
            let absolute = |v: &[f32]| -> Vec<f64> {
                v.iter().map(|&z| f64::from(z) + h.z_offset_um).collect()
            };
            write_npy_f64(
                self.out_dir.join("datum.npy"),
                &absolute(&sep.datum),
                rows,
                cols,
            )?;
            write_npy_f32(
                self.out_dir.join("roughness.npy"),
                &sep.roughness,
                rows,
                cols,
            )?;
            write_npy_f64(
                self.out_dir.join("pooled.npy"),
                &absolute(&pooled.heights),
                pooled.rows,
                pooled.cols,
            )?;
            for (name, data, r, c, title) in [
                (
                    "datum.png",
                    &sep.datum,
                    rows,
                    cols,
                    format!("datum, {} level {} (um)", wavelet.name(), sep.level),
                ),
                (
                    "roughness.png",
                    &sep.roughness,
                    rows,
                    cols,
                    "roughness (um)".to_string(),
                ),
                (
                    "pooled.png",
                    &pooled.heights,
                    pooled.rows,
                    pooled.cols,
                    format!("pooled {0}x{0} (um)", self.pool),
                ),
            ] {
                let opts = PreviewOptions {
                    title: Some(title),
                    ..Default::default()
                };
                write_preview_png(self.out_dir.join(name), data, r, c, &opts)?;
            }
            files = vec![
                "datum.npy",
                "roughness.npy",
                "pooled.npy",
                "datum.png",
                "roughness.png",
                "pooled.png",
            ];
        }
        let mut summary = summary;
        if let Some(o) = summary.as_object_mut() {
            o.insert("level_requested".into(), json!(self.level));
            o.insert("panorama_px".into(), json!([cols, rows]));
            o.insert("files".into(), json!(files));
        }
        self.summary = summary;
        out.send_frame(
            "datum",
            HeightMap {
                header: mk(FrameKind::Datum),
                heights: sep.datum,
            },
        );
        out.send_frame(
            "roughness",
            HeightMap {
                header: mk(FrameKind::Roughness),
                heights: sep.roughness,
            },
        );
        out.send_frame(
            "pooled",
            HeightMap {
                header: ph,
                heights: pooled.heights,
            },
        );
        for port in ["datum", "roughness", "pooled"] {
            out.end_frames(port, h.tile_index, h.t_acquired_ns);
        }
        self.done = true;
        Ok(())
    }
}

impl NodeLogic for WaveletNode {
    fn on_input(&mut self, port: &str, input: Input<'_>, _: &mut Outbox) -> Result<()> {
        let Input::Frame(f) = input else {
            bail!("wavelet: input '{port}' must carry frames")
        };
        let h = f.header;
        if h.has(flags::END_OF_SCAN) {
            self.ended = true;
            return Ok(());
        }
        match h.kind() {
            Some(FrameKind::PanoramaPatch) => {
                let m = self.mirror.get_or_insert_with(|| Mirror::new(h));
                let r = m.apply(h, f.heights)?;
                self.dirty = Some(self.dirty.map_or(r, |d| d.union(r)));
                let t = self
                    .trace
                    .map_or(h.t_acquired_ns, |(_, t)| t.min(h.t_acquired_ns));
                self.trace = Some((h.tile_index, t));
            }
            Some(FrameKind::Panorama) => self.final_panorama = Some(f.to_owned()),
            other => {
                bail!("wavelet: input '{port}' carries {other:?} frames, expected panorama patches")
            }
        }
        Ok(())
    }

    fn on_drained(&mut self, out: &mut Outbox) -> Result<()> {
        // Live patches of the last tiles go out first; the final pass runs on the next call.
        if self.live && self.dirty.is_some() {
            self.live_pass(out)?;
        } else if self.ended && !self.done {
            self.final_pass(out)?;
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

#[cfg(test)]
mod tests {
    use super::*;

    fn patch(x0: i64, y0: i64, w: u32, h: u32, v: f32) -> (FrameHeader, Vec<f32>) {
        let hd = FrameHeader {
            kind: FrameKind::PanoramaPatch as u32,
            width: w,
            height: h,
            pitch_x_um: 0.5,
            pitch_y_um: 0.5,
            origin_x_um: 10.0 + x0 as f64 * 0.5,
            origin_y_um: 20.0 + y0 as f64 * 0.5,
            ..Default::default()
        };
        (hd, vec![v; (w * h) as usize])
    }

    #[test]
    fn mirror_grows_in_every_direction_and_keeps_content() {
        let (h0, z0) = patch(0, 0, 4, 3, 1.0);
        let mut m = Mirror::new(&h0);
        m.apply(&h0, &z0).unwrap();
        for (x0, y0, v) in [(-5, 0, 2.0), (0, -4, 3.0), (6, 5, 4.0), (2, 1, 5.0)] {
            let (h, z) = patch(x0, y0, 4, 3, v);
            let r = m.apply(&h, &z).unwrap();
            assert_eq!(m.extract(r), z);
        }
        assert_eq!(
            m.extent,
            Rect {
                x0: -5,
                y0: -4,
                w: 15,
                h: 12
            }
        );
        assert!(m.alloc.contains(&m.extent));
        // The first patch survives where nothing overwrote it; untouched pixels stay NaN.
        assert_eq!(
            m.extract(Rect {
                x0: 0,
                y0: 0,
                w: 2,
                h: 1
            }),
            vec![1.0, 1.0]
        );
        assert!(m.extract(Rect {
            x0: 9,
            y0: -4,
            w: 1,
            h: 1
        })[0]
            .is_nan());
    }
}
