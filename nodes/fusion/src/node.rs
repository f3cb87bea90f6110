//! The fusion node: places each tile at its registered position as soon as both the tile and
//! its registration are in, publishes the changed region as a panorama patch, and at end of
//! scan publishes (and writes) the whole panorama once.
//!
//! Tiles are placed strictly in acquisition order, whatever order the two inputs arrive in,
//! so the panorama is the same under `launch` and `run`.
//!
//! The node keeps every tile until the end of the scan. If the matcher publishes revised,
//! globally solved registrations (flag FINAL) before its end of scan, the final panorama is
//! re-rendered from all tiles at those positions (tiles without a FINAL registration keep
//! their streaming one); otherwise the streaming panorama is final. The report carries the
//! SSIM of every overlap of the final panorama (`fusion_pairs`, see
//! [`crate::overlap_quality`]).

use std::collections::BTreeMap;

use anyhow::{anyhow, bail, Result};
use serde::Deserialize;
use serde_json::json;
use surfstream_core::frame::{flags, FrameHeader, FrameKind, HeightMap, TileRegistration};
use surfstream_io::preview::{write_preview_png, PreviewOptions};
use surfstream_runtime::graph::NodeContext;
use surfstream_runtime::node::{Input, NodeLogic, Outbox};

use surfstream_wavelet::Wavelet;

use crate::{
    overlap_quality, render_panorama, BlendParams, FusionMethod, PairQuality, Panorama,
    PlaneCorrection, TileInput, WaveletFusion,
};

/// A received tile at a registration's position and plane.
fn tile_input<'a>(tile: &'a HeightMap, reg: &TileRegistration) -> TileInput<'a> {
    let h = &tile.header;
    TileInput {
        index: h.tile_index,
        heights: &tile.heights,
        width: h.width as usize,
        height: h.height as usize,
        x_um: reg.x_um,
        y_um: reg.y_um,
        plane: PlaneCorrection {
            piston_um: reg.piston_um,
            tilt_x_um_per_px: reg.tilt_x_um_per_px,
            tilt_y_um_per_px: reg.tilt_y_um_per_px,
        },
        z_offset_um: h.z_offset_um,
    }
}

const PANORAMA: &str = "panorama";
const PREVIEW: &str = "preview";
/// Decimation of the latest-wins preview patches.
const PREVIEW_STEP: usize = 4;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Params {
    /// "gradual" (the paper's gradual in-and-out, eq. 5), "average" (eq. 4) or "wavelet"
    /// (eq. 6).
    #[serde(default = "gradual")]
    method: String,
    /// Wavelet of the wavelet fusion (default sym5).
    wavelet: Option<String>,
    /// Decomposition levels of the wavelet fusion (default 2, clamped to the overlap).
    wavelet_level: Option<usize>,
    /// Weight ramp length from a tile's border, px. Default: half the tile, so the weights are
    /// exactly linear across any overlap up to 50 % (the paper's gradual in-and-out).
    ramp_px: Option<f64>,
    /// Write panorama.npy and panorama.png into the out dir.
    #[serde(default = "yes")]
    write_files: bool,
}

fn gradual() -> String {
    "gradual".into()
}
fn yes() -> bool {
    true
}

pub struct FusionNode {
    method: FusionMethod,
    wavelet: Option<WaveletFusion>,
    ramp_px: Option<f64>,
    write_files: bool,
    out_dir: std::path::PathBuf,
    tiles: BTreeMap<u32, HeightMap>,
    registrations: BTreeMap<u32, TileRegistration>,
    /// Tiles already placed, with the registration they were placed at (kept for the final
    /// re-render and the overlap quality).
    placed: BTreeMap<u32, (HeightMap, TileRegistration)>,
    /// FINAL (globally solved) registrations from the matcher.
    final_registrations: BTreeMap<u32, TileRegistration>,
    pairs: Vec<PairQuality>,
    rerendered: bool,
    next: u32,
    panorama: Option<Panorama>,
    tiles_ended: bool,
    registrations_ended: bool,
    done: bool,
    last: (u32, u64),
    patches: u64,
    files: Vec<String>,
    summary: serde_json::Value,
}

pub fn build(ctx: &NodeContext) -> Result<Box<dyn NodeLogic + Send>> {
    let p: Params = ctx.params()?;
    let Some(method) = FusionMethod::by_name(&p.method) else {
        bail!(
            "graph '{}', node '{}': method = {:?}: expected \"gradual\", \"average\" or \"wavelet\"",
            ctx.graph_name,
            ctx.node_id,
            p.method
        );
    };
    let mut wf = WaveletFusion::default();
    if let Some(name) = &p.wavelet {
        wf.wavelet = Wavelet::by_name(name).ok_or_else(|| {
            anyhow!(
                "graph '{}', node '{}': wavelet = {name:?}: expected one of db1..db10, sym2..sym10, coif1..coif5",
                ctx.graph_name,
                ctx.node_id
            )
        })?;
    }
    if let Some(level) = p.wavelet_level {
        if !(1..=surfstream_wavelet::MAX_LEVEL).contains(&level) {
            bail!(
                "graph '{}', node '{}': wavelet_level = {level}: expected 1..={}",
                ctx.graph_name,
                ctx.node_id,
                surfstream_wavelet::MAX_LEVEL
            );
        }
        wf.level = level;
    }
    if let Some(r) = p.ramp_px {
        if !(r.is_finite() && r > 0.0) {
            bail!(
                "graph '{}', node '{}': ramp_px = {r}: expected > 0 px",
                ctx.graph_name,
                ctx.node_id
            );
        }
    }
    Ok(Box::new(FusionNode {
        method,
        wavelet: (method == FusionMethod::Wavelet).then_some(wf),
        ramp_px: p.ramp_px,
        write_files: p.write_files,
        out_dir: ctx.out_dir.clone(),
        tiles: BTreeMap::new(),
        registrations: BTreeMap::new(),
        placed: BTreeMap::new(),
        final_registrations: BTreeMap::new(),
        pairs: Vec::new(),
        rerendered: false,
        next: 0,
        panorama: None,
        tiles_ended: false,
        registrations_ended: false,
        done: false,
        last: (0, 0),
        patches: 0,
        files: Vec::new(),
        summary: serde_json::Value::Null,
    }))
}

impl FusionNode {
    fn ended(&self) -> bool {
        self.tiles_ended && self.registrations_ended
    }

    fn blend_params(&self, tile: &FrameHeader) -> BlendParams {
        match (self.method, self.ramp_px) {
            (FusionMethod::Average | FusionMethod::Wavelet, _) => BlendParams::average(),
            (_, Some(r)) => BlendParams::from_overlap_px(r, r),
            _ => BlendParams::from_overlap_px(tile.width as f64 / 2.0, tile.height as f64 / 2.0),
        }
    }

    /// Places every tile whose registration is in, in index order; returns how many.
    fn place_ready(&mut self, out: &mut Outbox) -> Result<usize> {
        let mut placed = 0;
        while let (Some(tile), Some(reg)) = (
            self.tiles.get(&self.next),
            self.registrations.get(&self.next),
        ) {
            let h = tile.header;
            if self.panorama.is_none() {
                let mut pano = Panorama::new(h.pitch_x_um, h.pitch_y_um, self.blend_params(&h))?;
                pano.set_wavelet_fusion(self.wavelet);
                self.panorama = Some(pano);
            }
            let pano = self
                .panorama
                .as_mut()
                .ok_or_else(|| anyhow!("no panorama"))?;
            let region = pano.place(tile_input(tile, reg))?;
            let (ox, oy) = pano.region_origin_um(&region);
            let heights = pano.extract(region);
            let (px, py) = pano.pitch_um();
            let header = FrameHeader {
                kind: FrameKind::PanoramaPatch as u32,
                flags: reg.flags & flags::PLACED_BY_STAGE,
                tile_index: h.tile_index,
                tile_row: h.tile_row,
                tile_col: h.tile_col,
                width: region.width as u32,
                height: region.height as u32,
                pitch_x_um: px,
                pitch_y_um: py,
                origin_x_um: ox,
                origin_y_um: oy,
                z_offset_um: pano.z_offset_um(),
                t_acquired_ns: h.t_acquired_ns,
                ..Default::default()
            };
            out.send_frame(PREVIEW, decimate(&header, &heights, PREVIEW_STEP));
            out.send_frame(PANORAMA, HeightMap { header, heights });
            self.patches += 1;
            self.last = (h.tile_index, h.t_acquired_ns);
            if let (Some(tile), Some(reg)) = (
                self.tiles.remove(&self.next),
                self.registrations.remove(&self.next),
            ) {
                self.placed.insert(self.next, (tile, reg));
            }
            self.next += 1;
            placed += 1;
        }
        Ok(placed)
    }

    fn finish(&mut self, out: &mut Outbox) -> Result<()> {
        if let Some(k) = self.tiles.keys().next() {
            bail!("fusion: tile {k} never received its registration (registrations ended)");
        }
        if let Some(k) = self.registrations.keys().next() {
            bail!("fusion: registration for tile {k} has no tile (tiles ended)");
        }
        if let Some(k) = self
            .final_registrations
            .keys()
            .find(|k| !self.placed.contains_key(k))
        {
            bail!("fusion: FINAL registration for tile {k}, which never arrived");
        }
        let (pairs, r, rerendered) = {
            let pano = self
                .panorama
                .as_ref()
                .ok_or_else(|| anyhow!("fusion: the scan had no tiles"))?;
            // The globally solved positions, where the matcher sent them.
            let inputs: Vec<TileInput<'_>> = self
                .placed
                .iter()
                .map(|(k, (tile, reg))| {
                    tile_input(tile, self.final_registrations.get(k).unwrap_or(reg))
                })
                .collect();
            let rerendered = if self.final_registrations.is_empty() {
                None
            } else {
                let (px, py) = pano.pitch_um();
                Some(render_panorama(
                    px,
                    py,
                    &inputs,
                    *pano.params(),
                    pano.wavelet_fusion().copied(),
                )?)
            };
            let pano = rerendered.as_ref().unwrap_or(pano);
            (
                overlap_quality(pano, &inputs)?,
                pano.to_raster(),
                rerendered.is_some(),
            )
        };
        self.pairs = pairs;
        self.rerendered = rerendered;
        if self.write_files {
            // Absolute heights in f64: the frame's f32 are relative to its f64 offset, and a
            // file must not lose the offset (nor the precision f32 keeps near zero).
            let npy = self.out_dir.join("panorama.npy");
            let absolute: Vec<f64> = r
                .heights
                .iter()
                .map(|&h| f64::from(h) + r.z_offset_um)
                .collect();
            surfstream_io::npy::write_npy_f64(&npy, &absolute, r.height, r.width)?;
            let png = self.out_dir.join("panorama.png");
            let opts = PreviewOptions {
                title: Some("panorama (um)".into()),
                ..Default::default()
            };
            write_preview_png(&png, &r.heights, r.height, r.width, &opts)?;
            self.files = vec!["panorama.npy".into(), "panorama.png".into()];
        }
        let invalid = r.heights.iter().filter(|z| z.is_nan()).count();
        self.summary = json!({
            "width_px": r.width, "height_px": r.height,
            "origin_x_um": r.origin_x_um, "origin_y_um": r.origin_y_um,
            "pitch_x_um": r.pitch_x_um, "pitch_y_um": r.pitch_y_um,
            "z_offset_um": r.z_offset_um, "invalid_px": invalid,
        });
        let header = FrameHeader {
            kind: FrameKind::Panorama as u32,
            flags: flags::FINAL,
            tile_index: self.last.0,
            width: r.width as u32,
            height: r.height as u32,
            pitch_x_um: r.pitch_x_um,
            pitch_y_um: r.pitch_y_um,
            origin_x_um: r.origin_x_um,
            origin_y_um: r.origin_y_um,
            z_offset_um: r.z_offset_um,
            t_acquired_ns: self.last.1,
            ..Default::default()
        };
        out.send_frame(
            PANORAMA,
            HeightMap {
                header,
                heights: r.heights,
            },
        );
        out.end_frames(PANORAMA, self.last.0, self.last.1);
        out.end_frames(PREVIEW, self.last.0, self.last.1);
        self.done = true;
        Ok(())
    }
}

/// Every `step`-th pixel of a patch: a cheap live view for latest-wins subscribers.
fn decimate(header: &FrameHeader, heights: &[f32], step: usize) -> HeightMap {
    let (w, h) = (header.width as usize, header.height as usize);
    let (dw, dh) = (w.div_ceil(step), h.div_ceil(step));
    let mut out = Vec::with_capacity(dw * dh);
    for r in (0..h).step_by(step) {
        out.extend(heights[r * w..(r + 1) * w].iter().step_by(step));
    }
    let mut hd = *header;
    hd.width = dw as u32;
    hd.height = dh as u32;
    hd.pitch_x_um *= step as f64;
    hd.pitch_y_um *= step as f64;
    hd.flags |= flags::PREVIEW;
    HeightMap {
        header: hd,
        heights: out,
    }
}

impl NodeLogic for FusionNode {
    fn on_input(&mut self, port: &str, input: Input<'_>, _: &mut Outbox) -> Result<()> {
        match (port, input) {
            ("tiles", Input::Frame(f)) => {
                if f.header.has(flags::END_OF_SCAN) {
                    self.tiles_ended = true;
                } else if f.header.kind() == Some(FrameKind::Tile) {
                    self.tiles.insert(f.header.tile_index, f.to_owned());
                } else {
                    bail!(
                        "fusion: input 'tiles' carries {:?} frames, expected tiles",
                        f.header.kind()
                    );
                }
            }
            ("registrations", Input::Registration(r)) => {
                if r.has(flags::END_OF_SCAN) {
                    self.registrations_ended = true;
                } else if r.has(flags::FINAL) {
                    self.final_registrations.insert(r.tile_index, *r);
                } else {
                    self.registrations.insert(r.tile_index, *r);
                }
            }
            _ => bail!("fusion: unexpected message on input '{port}'"),
        }
        Ok(())
    }

    fn on_drained(&mut self, out: &mut Outbox) -> Result<()> {
        // The last tiles' patches go out first; the final pass runs on the next call.
        if self.place_ready(out)? == 0 && self.ended() && !self.done {
            self.finish(out)?;
        }
        Ok(())
    }

    fn has_pending_work(&self) -> bool {
        self.ended() && !self.done
    }

    fn finished(&self) -> bool {
        self.done
    }

    fn report(&self) -> serde_json::Value {
        json!({
            "method": self.method.name(),
            "patches": self.patches,
            "panorama": self.summary,
            "files": self.files,
            "rerendered_from_final_registrations": self.rerendered,
            "final_registrations": self.final_registrations.len(),
            "ssim": "Wang et al. 2004 (paper eq. 7): 11x11 Gaussian window, sigma 1.5, K1 0.01, K2 0.03, L = height range of the overlap; SSIM(fused, each tile) over pixels both tiles measured",
            "fusion_pairs": self.pairs,
        })
    }
}
