//! The fusion node's state and decisions, without IPC: tiles and registrations arrive in any
//! order; each tile is placed at its registered position as soon as both are in, strictly in
//! acquisition order (so the panorama is the same under `launch` and `run`), and the changed
//! region goes downstream as a panorama patch. At end of scan the whole panorama is published
//! (and written) once.
//!
//! Every tile is kept until the end of the scan, on disk: once placed, its heights go to a
//! spill file ([`crate::TileSpill`]) and only its header stays in memory. If the matcher sends
//! revised, globally solved registrations (flag FINAL), the final panorama is re-rendered from
//! all tiles at those positions, read back one at a time (tiles without a FINAL registration
//! keep their streaming one); otherwise the streaming panorama is final. The overlap quality
//! ([`crate::overlap_quality_streamed`]) is scored on the final panorama, again reading the
//! tiles back as the pairs need them.
//!
//! Memory: the panorama's accumulator chunks ([`crate::Panorama`], 8 bytes per touched pixel)
//! plus the tiles waiting for their registration. With a budget
//! ([`StreamingFusion::set_memory_budget`]) the chunks beyond it spill to disk, so the
//! fusion's own memory stays about constant whatever the scan size; the final panorama frame
//! (4 bytes per pixel, f32) is the one whole-panorama allocation left.

use std::collections::BTreeMap;
use std::path::PathBuf;

use anyhow::{anyhow, bail, Result};
use surfstream_core::frame::{flags, FrameHeader, FrameKind, HeightMap, TileRegistration};
use surfstream_core::raster::{RasterView, Shape};
use surfstream_core::record::{PanoramaSummary, PanoramaTiles, PlacedTile, PANORAMA_TILES};
use surfstream_core::{Pitch, Sampling};
use surfstream_io::output::{NpyHeights, OutputWriter, SurfaceOutput};

use crate::{
    overlap_quality_streamed, BlendParams, FusionMethod, PairQuality, Panorama, PlaneCorrection,
    TileFootprint, TileInput, TileSpill, WaveletFusion,
};

/// Decimation of the latest-wins preview patches.
pub const PREVIEW_STEP: usize = 4;

/// How tiles are blended.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FusionSettings {
    pub method: FusionMethod,
    /// The wavelet fusion's parameters (used when `method` is wavelet).
    pub wavelet: WaveletFusion,
    /// Weight ramp from a tile's border, px; `None`: half the tile, so the weights are
    /// exactly linear across any overlap up to 50 % (the paper's gradual in-and-out).
    pub ramp_px: Option<f64>,
}

impl FusionSettings {
    fn blend_params(&self, tile: &FrameHeader) -> BlendParams {
        match (self.method, self.ramp_px) {
            (FusionMethod::Average | FusionMethod::Wavelet, _) => BlendParams::average(),
            (_, Some(r)) => BlendParams::from_overlap_px(r, r),
            _ => BlendParams::from_overlap_px(tile.width as f64 / 2.0, tile.height as f64 / 2.0),
        }
    }
}

/// A received tile at a registration's position and plane; errors when the frame's payload
/// does not match its declared size.
fn tile_input<'a>(tile: &'a HeightMap, reg: &TileRegistration) -> Result<TileInput<'a>> {
    let h = &tile.header;
    let shape = Shape::new(h.height as usize, h.width as usize);
    let heights = RasterView::new(&tile.heights, shape)
        .map_err(|e| anyhow!("fusion: tile {}: {e}", h.tile_index))?;
    Ok(TileInput {
        index: h.tile_index,
        heights,
        x_um: reg.x_um,
        y_um: reg.y_um,
        plane: PlaneCorrection {
            piston_um: reg.piston_um,
            tilt_x_um_per_px: reg.tilt_x_um_per_px,
            tilt_y_um_per_px: reg.tilt_y_um_per_px,
        },
        z_offset_um: h.z_offset_um,
    })
}

/// One placed tile's output: the changed region, and every `PREVIEW_STEP`-th pixel of it for
/// latest-wins subscribers.
#[derive(Debug, Clone)]
pub struct PanoramaPatch {
    pub patch: HeightMap,
    pub preview: HeightMap,
}

/// The end of scan's output.
#[derive(Debug, Clone)]
pub struct FinalPanorama {
    /// The whole panorama, flag FINAL.
    pub panorama: HeightMap,
    pub report: FinalReport,
}

/// What the end of scan reports.
#[derive(Debug, Clone)]
pub struct FinalReport {
    /// Size, place, offset and invalid pixels of the panorama.
    pub summary: PanoramaSummary,
    pub pairs: Vec<PairQuality>,
    /// Re-rendered from FINAL registrations.
    pub rerendered: bool,
    /// Files written (empty without a writer).
    pub files: Vec<String>,
}

/// A placed tile: its header and where its heights are in the spill file.
#[derive(Debug, Clone, Copy)]
struct SpilledTile {
    header: FrameHeader,
    offset: u64,
    len: usize,
}

/// The panorama of one scan as tiles and registrations stream in.
#[derive(Debug)]
pub struct StreamingFusion {
    settings: FusionSettings,
    tiles: BTreeMap<u32, HeightMap>,
    registrations: BTreeMap<u32, TileRegistration>,
    /// Tiles already placed, with the registration they were placed at (kept, on disk, for
    /// the final re-render and the overlap quality).
    placed: BTreeMap<u32, (SpilledTile, TileRegistration)>,
    spill: TileSpill,
    /// Memory budget of the panorama's chunks (bytes) and the folder of the spill files.
    budget_bytes: Option<usize>,
    spill_dir: Option<PathBuf>,
    /// Also write `panorama.zarr` when the panorama has at least this many pixels.
    zarr_min_px: Option<usize>,
    /// FINAL (globally solved) registrations from the matcher.
    final_registrations: BTreeMap<u32, TileRegistration>,
    next: u32,
    panorama: Option<Panorama>,
    /// The chunk statistics of the final panorama, kept when [`StreamingFusion::finish`]
    /// frees its chunks.
    final_chunk_stats: Option<crate::ChunkStats>,
    /// Tile index and acquisition time of the last placed tile.
    last: (u32, u64),
}

impl StreamingFusion {
    pub fn new(settings: FusionSettings) -> Self {
        Self {
            settings,
            tiles: BTreeMap::new(),
            registrations: BTreeMap::new(),
            placed: BTreeMap::new(),
            spill: TileSpill::new(None),
            budget_bytes: None,
            spill_dir: None,
            zarr_min_px: None,
            final_registrations: BTreeMap::new(),
            next: 0,
            panorama: None,
            final_chunk_stats: None,
            last: (0, 0),
        }
    }

    pub fn settings(&self) -> &FusionSettings {
        &self.settings
    }

    /// Keep at most about `bytes` of panorama chunks in memory (`None`: no limit), and put the
    /// spill files (chunks beyond the budget, placed tiles) in `spill_dir` (default: the
    /// system temp folder). Set before the first tile. The panorama does not depend on it.
    pub fn set_memory_budget(&mut self, bytes: Option<usize>, spill_dir: Option<PathBuf>) {
        self.budget_bytes = bytes;
        self.spill = TileSpill::new(spill_dir.clone());
        self.spill_dir = spill_dir;
    }

    /// With a writer, also write the panorama as a Zarr v3 store (`panorama.zarr`,
    /// [`crate::zarr`]) when it has at least `min_px` pixels (`Some(0)`: always); `None`:
    /// never.
    pub fn set_zarr_min_px(&mut self, min_px: Option<usize>) {
        self.zarr_min_px = min_px;
    }

    /// Chunk statistics of the panorama (see [`crate::ChunkStats`]).
    pub fn chunk_stats(&self) -> Option<crate::ChunkStats> {
        self.panorama
            .as_ref()
            .map(|p| p.chunk_stats())
            .or(self.final_chunk_stats)
    }

    fn new_panorama(&self, pitch: Pitch, params: BlendParams) -> Result<Panorama> {
        let mut p = Panorama::new(pitch, params)?;
        if self.settings.method == FusionMethod::Wavelet {
            p.set_wavelet_fusion(Some(self.settings.wavelet));
        }
        p.set_memory_budget_bytes(self.budget_bytes, self.spill_dir.clone());
        Ok(p)
    }

    /// A placed tile read back from the spill file.
    fn load(&self, t: &SpilledTile) -> crate::Result<HeightMap> {
        Ok(HeightMap {
            header: t.header,
            heights: self.spill.read(t.offset, t.len)?,
        })
    }

    /// Keeps a tile until its registration is in.
    pub fn add_tile(&mut self, tile: HeightMap) -> Result<()> {
        if tile.header.kind() != Some(FrameKind::Tile) {
            bail!(
                "fusion: input 'tiles' carries {:?} frames, expected tiles",
                tile.header.kind()
            );
        }
        self.tiles.insert(tile.header.tile_index, tile);
        Ok(())
    }

    /// Keeps a streaming registration, or a FINAL (globally solved) one for the end of scan.
    pub fn add_registration(&mut self, reg: TileRegistration) {
        if reg.has(flags::FINAL) {
            self.final_registrations.insert(reg.tile_index, reg);
        } else {
            self.registrations.insert(reg.tile_index, reg);
        }
    }

    /// Number of FINAL registrations received.
    pub fn final_registrations(&self) -> usize {
        self.final_registrations.len()
    }

    /// Places every tile whose registration is in, in index order, and returns their patches.
    pub fn place_ready(&mut self) -> Result<Vec<PanoramaPatch>> {
        let mut patches = Vec::new();
        while let (Some(tile), Some(reg)) = (
            self.tiles.get(&self.next),
            self.registrations.get(&self.next),
        ) {
            let h = tile.header;
            if self.panorama.is_none() {
                let pitch = h
                    .pitch()
                    .map_err(|e| anyhow!("fusion: tile {}: {e}", h.tile_index))?;
                let p = self.new_panorama(pitch, self.settings.blend_params(&h))?;
                self.panorama = Some(p);
            }
            let Some(pano) = self.panorama.as_mut() else {
                bail!("fusion: no panorama"); // just set
            };
            let region = pano.place(tile_input(tile, reg)?)?;
            let (ox, oy) = pano.region_origin_um(&region);
            let heights = pano.try_extract(region)?;
            let at = Sampling::of(Shape::new(region.height, region.width), pano.pitch())
                .with_origin(ox, oy)?;
            let header = FrameHeader {
                kind: FrameKind::PanoramaPatch as u32,
                flags: reg.flags & flags::PLACED_BY_STAGE,
                tile_index: h.tile_index,
                tile_row: h.tile_row,
                tile_col: h.tile_col,
                z_offset_um: pano.z_offset_um(),
                t_acquired_ns: h.t_acquired_ns,
                ..FrameHeader::at(&at)
            };
            let preview = decimate(&header, &heights, PREVIEW_STEP);
            patches.push(PanoramaPatch {
                patch: HeightMap { header, heights },
                preview,
            });
            self.last = (h.tile_index, h.t_acquired_ns);
            if let (Some(tile), Some(reg)) = (
                self.tiles.remove(&self.next),
                self.registrations.remove(&self.next),
            ) {
                let offset = self.spill.write(&tile.heights)?;
                let kept = SpilledTile {
                    header: tile.header,
                    offset,
                    len: tile.heights.len(),
                };
                self.placed.insert(self.next, (kept, reg));
            }
            self.next += 1;
        }
        Ok(patches)
    }

    /// Tile index and acquisition time of the last placed tile: what end-of-scan markers carry.
    pub fn last_tile(&self) -> (u32, u64) {
        self.last
    }

    /// The final panorama once both inputs ended: re-rendered from FINAL registrations when
    /// there are any, scored by overlap, written as `panorama` (.npy absolute f64 + .png) when
    /// a writer is given. Errors when a tile or a registration is missing its partner.
    pub fn finish(&mut self, files: Option<&mut OutputWriter>) -> Result<FinalPanorama> {
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
        let pano = self
            .panorama
            .as_ref()
            .ok_or_else(|| anyhow!("fusion: the scan had no tiles"))?;
        // The globally solved positions, where the matcher sent them.
        let positions: Vec<(SpilledTile, TileRegistration)> = self
            .placed
            .iter()
            .map(|(k, (t, reg))| (*t, *self.final_registrations.get(k).unwrap_or(reg)))
            .collect();
        let rerendered = !self.final_registrations.is_empty();
        if rerendered {
            // Placed one by one in index order, read back one at a time: the same result, bit
            // for bit, as rendering from all tiles in memory ([`crate::render_panorama`]). The
            // streaming panorama goes first, so the two never take memory at once.
            let (pitch, params, wavelet) =
                (pano.pitch(), *pano.params(), pano.wavelet_fusion().copied());
            self.panorama = None;
            let mut fresh = self.new_panorama(pitch, params)?;
            fresh.set_wavelet_fusion(wavelet);
            for (t, reg) in &positions {
                let tile = self.load(t)?;
                fresh.place(tile_input(&tile, reg)?)?;
                surfstream_core::liveness::beat();
            }
            self.panorama = Some(fresh);
        }
        let Some(final_pano) = self.panorama.as_ref() else {
            bail!("fusion: no panorama"); // set above
        };
        let footprints: Vec<TileFootprint> = positions
            .iter()
            .map(|(t, reg)| TileFootprint {
                index: t.header.tile_index,
                x_um: reg.x_um,
                y_um: reg.y_um,
                cols: t.header.width as usize,
                rows: t.header.height as usize,
            })
            .collect();
        let pairs = overlap_quality_streamed(final_pano, &footprints, |k| {
            let (t, reg) = &positions[k];
            surfstream_core::liveness::beat();
            let tile = self.load(t)?;
            let input = tile_input(&tile, reg).map_err(|e| crate::FusionError::Spill {
                message: e.to_string(),
            })?;
            final_pano.resample_alone(input)
        })?;
        let r = final_pano.to_raster();
        // The accumulators are not needed past this point: free them (the budget's worth of
        // chunks) before the frame is written and sent.
        self.final_chunk_stats = Some(final_pano.chunk_stats());
        self.panorama = None;
        let mut written = Vec::new();
        let (rows, cols) = (r.heights.rows(), r.heights.cols());
        let at =
            Sampling::of(r.heights.shape(), r.pitch).with_origin(r.origin_x_um, r.origin_y_um)?;
        let invalid = r.heights.values().iter().filter(|z| z.is_nan()).count();
        let summary = PanoramaSummary {
            width_px: cols,
            height_px: rows,
            origin_x_um: at.origin_x_um(),
            origin_y_um: at.origin_y_um(),
            pitch_x_um: at.pitch_x_um(),
            pitch_y_um: at.pitch_y_um(),
            z_offset_um: r.z_offset_um,
            invalid_px: invalid,
        };
        if let Some(w) = files {
            // The pitch travels with panorama.npy (its sidecar panorama.npy.json).
            w.set_pitch_um(at.pitch_x_um(), at.pitch_y_um());
            w.write_surface(&SurfaceOutput {
                name: "panorama",
                heights: r.heights.view(),
                z_offset_um: r.z_offset_um,
                npy: NpyHeights::Absolute,
                title: "panorama (um)",
                x3p_pitch_um: None,
            })?;
            written = w.files().to_vec();
            if self.zarr_min_px.is_some_and(|min| rows * cols >= min) {
                written.push(crate::zarr::write_zarr_abs(
                    w.dir(),
                    "panorama",
                    r.heights.values(),
                    &at,
                    r.z_offset_um,
                )?);
            }
            // Where each tile lies, for the mesher's tolerance search (Table 6's regions),
            // before the final panorama that starts it is sent.
            write_panorama_tiles(w.dir(), summary, &footprints)?;
            written.push(PANORAMA_TILES.into());
        }
        let header = FrameHeader {
            kind: FrameKind::Panorama as u32,
            flags: flags::FINAL,
            tile_index: self.last.0,
            z_offset_um: r.z_offset_um,
            t_acquired_ns: self.last.1,
            ..FrameHeader::at(&at)
        };
        Ok(FinalPanorama {
            panorama: HeightMap {
                header,
                heights: r.heights.into_values(),
            },
            report: FinalReport {
                summary,
                pairs,
                rerendered,
                files: written,
            },
        })
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

/// `panorama.tiles.json` ([`PanoramaTiles`]) in `dir`: the final panorama's grid and every
/// tile's final position and size, in tile index order.
fn write_panorama_tiles(
    dir: &std::path::Path,
    panorama: PanoramaSummary,
    footprints: &[TileFootprint],
) -> Result<()> {
    let mut tiles: Vec<PlacedTile> = footprints
        .iter()
        .map(|f| PlacedTile {
            index: f.index,
            x_um: f.x_um,
            y_um: f.y_um,
            width_px: f.cols,
            height_px: f.rows,
        })
        .collect();
    tiles.sort_by_key(|t| t.index);
    let record = PanoramaTiles { panorama, tiles };
    let path = dir.join(PANORAMA_TILES);
    surfstream_core::fsutil::write_atomic(&path, |w| {
        serde_json::to_writer_pretty(&mut *w, &record)?;
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const PITCH: f64 = 0.5;

    fn settings() -> FusionSettings {
        FusionSettings {
            method: FusionMethod::Gradual,
            wavelet: WaveletFusion::default(),
            ramp_px: None,
        }
    }

    fn tile(index: u32, v: f32) -> HeightMap {
        HeightMap {
            header: FrameHeader {
                kind: FrameKind::Tile as u32,
                tile_index: index,
                width: 32,
                height: 24,
                pitch_x_um: PITCH,
                pitch_y_um: PITCH,
                t_acquired_ns: 100 + u64::from(index),
                ..Default::default()
            },
            heights: (0..32 * 24).map(|i| v + (i % 7) as f32 * 0.1).collect(),
        }
    }

    fn reg(index: u32, col: f64, flags: u32) -> TileRegistration {
        TileRegistration {
            tile_index: index,
            x_um: col * PITCH,
            flags,
            ..Default::default()
        }
    }

    #[test]
    fn tiles_are_placed_in_index_order_whatever_the_arrival_order() {
        let mut f = StreamingFusion::new(settings());
        f.add_tile(tile(1, 2.0)).unwrap();
        f.add_registration(reg(1, 16.0, 0));
        assert!(f.place_ready().unwrap().is_empty(), "tile 0 is not in yet");
        f.add_registration(reg(0, 0.0, 0));
        f.add_tile(tile(0, 1.0)).unwrap();
        let patches = f.place_ready().unwrap();
        let idx: Vec<u32> = patches.iter().map(|p| p.patch.header.tile_index).collect();
        assert_eq!(idx, [0, 1]);
        let p = &patches[1];
        assert_eq!((p.patch.header.width, p.patch.header.height), (32, 24));
        assert_eq!(p.patch.header.origin_x_um, 8.0);
        assert_eq!((p.preview.header.width, p.preview.header.height), (8, 6));
        assert!(p.preview.header.has(flags::PREVIEW));
        assert_eq!(f.last_tile(), (1, 101));

        let dir = tempfile::tempdir().unwrap();
        let mut w = OutputWriter::new(dir.path());
        let done = f.finish(Some(&mut w)).unwrap();
        assert_eq!(done.panorama.header.width, 48);
        assert!(done.panorama.header.has(flags::FINAL));
        assert!(!done.report.rerendered);
        assert_eq!(
            done.report.files,
            ["panorama.npy", "panorama.png", PANORAMA_TILES]
        );
        let text = std::fs::read_to_string(dir.path().join(PANORAMA_TILES)).unwrap();
        let tiles: PanoramaTiles = serde_json::from_str(&text).unwrap();
        assert_eq!(tiles.panorama, done.report.summary);
        let at: Vec<(u32, f64, usize, usize)> = (tiles.tiles.iter())
            .map(|t| (t.index, t.x_um, t.width_px, t.height_px))
            .collect();
        assert_eq!(at, [(0, 0.0, 32, 24), (1, 8.0, 32, 24)]);
        assert_eq!(done.report.pairs.len(), 1);
    }

    #[test]
    fn final_registrations_re_render_and_unmatched_inputs_are_errors() {
        let mut f = StreamingFusion::new(settings());
        f.add_tile(tile(0, 1.0)).unwrap();
        f.add_registration(reg(0, 0.0, 0));
        f.place_ready().unwrap();
        f.add_registration(reg(0, 2.0, flags::FINAL));
        let done = f.finish(None).unwrap();
        assert!(done.report.rerendered);
        assert_eq!(done.panorama.header.origin_x_um, 1.0);
        assert!(done.report.files.is_empty());

        f.add_registration(reg(5, 0.0, flags::FINAL));
        assert!(f.finish(None).is_err());
        let mut g = StreamingFusion::new(settings());
        g.add_tile(tile(0, 1.0)).unwrap();
        assert!(g.finish(None).is_err());
        let mut not_a_tile = tile(1, 0.0);
        not_a_tile.header.kind = FrameKind::Datum as u32;
        assert!(g.add_tile(not_a_tile).is_err());
        assert!(StreamingFusion::new(settings()).finish(None).is_err());
    }

    #[test]
    fn a_budget_spills_but_the_final_panorama_and_scores_stay_the_same() {
        let (w, h) = (600usize, 500usize);
        let big = |index: u32| HeightMap {
            header: FrameHeader {
                kind: FrameKind::Tile as u32,
                tile_index: index,
                width: w as u32,
                height: h as u32,
                pitch_x_um: PITCH,
                pitch_y_um: PITCH,
                ..Default::default()
            },
            heights: (0..w * h)
                .map(|i| {
                    let (r, c) = ((i / w) as f32, (i % w) as f32);
                    (0.013 * c).sin() + (0.021 * r).cos() + index as f32 * 1e-3
                })
                .collect(),
        };
        let at = |index: u32, col: f64, row: f64, flags: u32| TileRegistration {
            tile_index: index,
            x_um: col * PITCH,
            y_um: row * PITCH,
            flags,
            ..Default::default()
        };
        let spill = tempfile::tempdir().unwrap();
        let run = |budget: Option<usize>| {
            let mut f = StreamingFusion::new(settings());
            f.set_memory_budget(budget, Some(spill.path().into()));
            let grid = [(0.0, 0.0), (540.0, 0.0), (540.0, 450.0), (0.0, 450.0)];
            for (k, &(c, r)) in grid.iter().enumerate() {
                f.add_tile(big(k as u32)).unwrap();
                f.add_registration(at(k as u32, c, r, 0));
                f.place_ready().unwrap();
            }
            // The global solve moves two tiles by a fraction of a pixel: a re-render.
            f.add_registration(at(1, 540.4, 0.3, flags::FINAL));
            f.add_registration(at(3, -0.2, 450.6, flags::FINAL));
            let done = f.finish(None).unwrap();
            (done, f.chunk_stats().unwrap())
        };
        let (whole, ws) = run(None);
        let (spilled, ss) = run(Some(crate::CHUNK_BYTES));
        assert!(whole.report.rerendered && spilled.report.rerendered);
        assert_eq!(ws.spills, 0);
        assert!(ss.spills > 0, "{ss:?}");
        let bits = |m: &HeightMap| m.heights.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert_eq!(whole.panorama.header.width, spilled.panorama.header.width);
        assert_eq!(bits(&whole.panorama), bits(&spilled.panorama));
        assert_eq!(whole.report.pairs, spilled.report.pairs);
        assert_eq!(whole.report.pairs.len(), 6);
        // And the same as rendering from all tiles held in memory.
        let tiles: Vec<HeightMap> = (0..4).map(big).collect();
        let regs = [
            at(0, 0.0, 0.0, 0),
            at(1, 540.4, 0.3, 0),
            at(2, 540.0, 450.0, 0),
            at(3, -0.2, 450.6, 0),
        ];
        let inputs: Vec<TileInput<'_>> = tiles
            .iter()
            .zip(&regs)
            .map(|(t, r)| tile_input(t, r).unwrap())
            .collect();
        let reference = crate::render(
            Pitch::square(PITCH).unwrap(),
            &inputs,
            settings().blend_params(&tiles[0].header),
        )
        .unwrap();
        let ref_bits: Vec<u32> = reference
            .heights
            .values()
            .iter()
            .map(|v| v.to_bits())
            .collect();
        assert_eq!(bits(&whole.panorama), ref_bits);
    }
}
