//! The growing panorama: a canvas on a fixed grid that tiles are resampled onto and blended
//! into, one at a time, as the scan proceeds.

use std::collections::HashSet;
use std::path::PathBuf;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use surfstream_core::canvas::{amortised_growth, GridRect};
use surfstream_core::raster::{Raster, Shape};
use surfstream_core::{ParamError, Pitch};

use crate::chunks::{ChunkStats, ChunkStore, CHUNK_PX};
use crate::error::{FusionError, Result};
use crate::input::{BlendParams, TileInput};
use crate::method::{fuse_wavelet_in, WaveletFusion};
use crate::resample::{AxisPlan, Resampler, MAX_OFFSET_PX};

/// A rectangle of canvas pixels: columns `x0 .. x0 + width`, rows `y0 .. y0 + height`.
///
/// Canvas pixel coordinates are indices into the current canvas. When the canvas grows left
/// or up, existing content moves to larger indices, so a `Region` is valid until the next
/// [`Panorama::place`]; to locate it for good, take [`Panorama::region_origin_um`] at once.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Region {
    pub x0: usize,
    pub y0: usize,
    pub width: usize,
    pub height: usize,
}

impl Region {
    /// Number of pixels, `width * height`.
    pub fn len(&self) -> usize {
        self.width * self.height
    }

    /// True when the region holds no pixel.
    pub fn is_empty(&self) -> bool {
        self.width == 0 || self.height == 0
    }
}

/// A height raster with its place in scan coordinates: the whole panorama, or one tile
/// resampled onto its grid.
#[derive(Debug, Clone, PartialEq)]
pub struct PlacedRaster {
    /// Heights in um relative to `z_offset_um`, rows along y; NaN = no data. 0 x 0 when
    /// nothing was placed.
    pub heights: Raster<f32>,
    /// Scan position (um) of the centre of pixel (0, 0).
    pub origin_x_um: f64,
    pub origin_y_um: f64,
    /// The canvas grid's pitch (the raster's shape is `heights`').
    pub pitch: Pitch,
    /// Absolute height (um) that `heights` are relative to.
    pub z_offset_um: f64,
}

/// The first tile's origin and z offset: the canvas grid and the canvas z are anchored there.
#[derive(Debug, Clone, Copy)]
struct Anchor {
    x_um: f64,
    y_um: f64,
    z_offset_um: f64,
}

impl Anchor {
    fn of(tile: &TileInput<'_>) -> Self {
        Self {
            x_um: tile.x_um,
            y_um: tile.y_um,
            z_offset_um: tile.z_offset_um,
        }
    }
}

/// Default limit on the canvas size: 2^31 px (16 GiB of accumulators when fully touched). A
/// 30 x 30 scan of 1024 px tiles at 10 % overlap with growth headroom fits; a position given
/// in the wrong unit does not, and fails with an error instead of exhausting memory.
pub const DEFAULT_MAX_CANVAS_PX: usize = 1 << 31;

/// The growing panorama.
///
/// Per canvas pixel it keeps two f32 accumulators: the weight sum `sum(w)` and the running
/// weighted mean `sum(w z) / sum(w)` (updated as `m += w / (W + w) * (z - m)` in f64, stored
/// in f32). That is the blend of the paper's eq. (5) with the same 8 bytes per pixel as a pair
/// of f32 sums, but a constant surface stays exactly constant and heights keep full f32
/// precision however many tiles overlap. Pixels with weight 0 have no data (NaN on output).
///
/// Memory: 8 bytes per touched pixel, in chunks of [`CHUNK_PX`]^2 ([`crate::chunks`]): the
/// canvas rectangle is bookkeeping only, chunks exist where tiles landed, and with a budget
/// ([`Panorama::set_memory_budget_bytes`]) the least recently touched chunks live in a spill
/// file instead of memory, with the same result bit for bit.
#[derive(Debug, Clone)]
pub struct Panorama {
    pitch: Pitch,
    params: BlendParams,
    max_canvas_px: usize,
    /// Set by the first placed tile.
    anchor: Option<Anchor>,
    /// The grid rectangle of the canvas (empty before the first tile): what canvas pixel
    /// coordinates ([`Region`]) are relative to. Growing it moves no data.
    rect: GridRect,
    /// Running weighted mean and weight sum (0 = no data) per grid pixel, in chunks.
    store: ChunkStore,
    /// Union of the footprints of all placed tiles.
    content: Option<GridRect>,
    placed: HashSet<u32>,
    /// `reserve_um` hint [x_min, y_min, x_max, y_max] waiting for the anchor.
    reserved_um: Option<[f64; 4]>,
    /// Wavelet fusion (eq. 6) instead of the weighted mean; see [`Panorama::set_wavelet_fusion`].
    wavelet: Option<WaveletFusion>,
}

impl Panorama {
    /// An empty panorama on a grid of the given pitch. The grid is anchored by the first
    /// placed tile: canvas pixel centres lie at `x = first.x_um + k * pitch.x_um()` (likewise
    /// y). A pitch and not a [`surfstream_core::Sampling`]: the canvas's shape grows with the
    /// tiles and its origin is the first tile's.
    pub fn new(pitch: Pitch, params: BlendParams) -> Result<Self> {
        params.validate()?;
        Ok(Self {
            pitch,
            params,
            max_canvas_px: DEFAULT_MAX_CANVAS_PX,
            anchor: None,
            rect: GridRect::default(),
            store: ChunkStore::default(),
            content: None,
            placed: HashSet::new(),
            reserved_um: None,
            wavelet: None,
        })
    }

    /// Fuse overlaps by wavelet fusion (paper eq. 6, [`crate::method`]) instead of the
    /// weighted mean of the blend parameters; `None` restores the weighted mean. Set it before
    /// the first tile. With wavelet fusion the weight accumulator counts the tiles per pixel.
    pub fn set_wavelet_fusion(&mut self, wavelet: Option<WaveletFusion>) {
        self.wavelet = wavelet;
    }

    /// The wavelet fusion parameters, if that is the method.
    pub fn wavelet_fusion(&self) -> Option<&WaveletFusion> {
        self.wavelet.as_ref()
    }

    /// Change the limit on the canvas size in pixels (default [`DEFAULT_MAX_CANVAS_PX`]).
    pub fn set_max_canvas_px(&mut self, max_px: usize) {
        self.max_canvas_px = max_px;
    }

    /// Keep at most about `bytes` of the accumulator chunks in memory, the rest in a spill
    /// file in `spill_dir` (default the system temp folder); `None`: no limit. Any budget
    /// gives the same panorama bit for bit.
    pub fn set_memory_budget_bytes(&mut self, bytes: Option<usize>, spill_dir: Option<PathBuf>) {
        self.store.set_budget_bytes(bytes);
        self.store.set_spill_dir(spill_dir);
    }

    /// Chunk counts, spills and reloads so far.
    pub fn chunk_stats(&self) -> ChunkStats {
        self.store.stats()
    }

    /// The limit on the canvas size in pixels.
    pub fn max_canvas_px(&self) -> usize {
        self.max_canvas_px
    }

    /// The blend parameters.
    pub fn params(&self) -> &BlendParams {
        &self.params
    }

    /// The canvas grid's pitch.
    pub fn pitch(&self) -> Pitch {
        self.pitch
    }

    /// Absolute height (um) that the canvas heights are relative to: the first tile's
    /// `z_offset_um`; 0 before any tile is placed.
    pub fn z_offset_um(&self) -> f64 {
        self.anchor.map_or(0.0, |a| a.z_offset_um)
    }

    /// Canvas width in pixels (allocated extent, including growth headroom).
    pub fn width(&self) -> usize {
        self.canvas().cols()
    }

    /// Canvas height in pixels (allocated extent, including growth headroom).
    pub fn height(&self) -> usize {
        self.canvas().rows()
    }

    /// The grid rectangle the canvas covers.
    fn canvas(&self) -> GridRect {
        self.rect
    }

    /// Number of tiles placed so far.
    pub fn tiles_placed(&self) -> usize {
        self.placed.len()
    }

    /// Scan position (um) of the centre of canvas pixel (0, 0); (0, 0) before any tile.
    pub fn canvas_origin_um(&self) -> (f64, f64) {
        let c = self.canvas();
        self.grid_to_um(c.x0, c.y0)
    }

    /// Scan position (um) of the centre of a region's first pixel in the current canvas.
    pub fn region_origin_um(&self, region: &Region) -> (f64, f64) {
        let (x, y) = self.canvas_origin_um();
        (
            x + region.x0 as f64 * self.pitch.x_um(),
            y + region.y0 as f64 * self.pitch.y_um(),
        )
    }

    /// The bounding box of all placed tiles' footprints in canvas pixels; `None` when empty.
    pub fn content_region(&self) -> Option<Region> {
        self.content.map(|c| self.to_region(&c))
    }

    /// Pre-size the canvas to cover pixel centres in `[x_min_um, x_max_um] x [y_min_um,
    /// y_max_um]` (scan coordinates), e.g. the nominal extent of the whole scan, so that a scan
    /// staying inside never reallocates (no latency spike from growth). Called before the
    /// first tile, it takes effect when that tile anchors the grid. It is a hint: a rectangle
    /// beyond the size limit is ignored, and tiles outside it still grow the canvas.
    pub fn reserve_um(
        &mut self,
        x_min_um: f64,
        y_min_um: f64,
        x_max_um: f64,
        y_max_um: f64,
    ) -> Result<()> {
        for (field, value) in [
            ("x_min_um", x_min_um),
            ("y_min_um", y_min_um),
            ("x_max_um", x_max_um),
            ("y_max_um", y_max_um),
        ] {
            if !value.is_finite() {
                return Err(FusionError::from(ParamError::new(
                    field,
                    value,
                    "a finite scan position in um",
                )));
            }
        }
        if x_max_um < x_min_um || y_max_um < y_min_um {
            let (field, value) = if x_max_um < x_min_um {
                ("x_max_um", x_max_um)
            } else {
                ("y_max_um", y_max_um)
            };
            return Err(FusionError::from(ParamError::new(
                field,
                value,
                "max >= min",
            )));
        }
        let rect = [x_min_um, y_min_um, x_max_um, y_max_um];
        if self.rect.is_empty() {
            self.reserved_um = Some(rect);
            return Ok(());
        }
        if let Some(g) = self.grid_rect_um(&rect) {
            if !self.canvas().contains(&g) {
                let wanted = self.canvas().union(&g);
                if wanted.area().is_some_and(|a| a <= self.max_canvas_px) {
                    // Cannot fail: `wanted` fits the limit.
                    self.reallocate(wanted, wanted, 0)?;
                }
            }
        }
        Ok(())
    }

    /// Grid pixels whose centres lie in an um rectangle [x_min, y_min, x_max, y_max]; `None`
    /// before the anchor is known or when it is absurdly far from it.
    fn grid_rect_um(&self, r: &[f64; 4]) -> Option<GridRect> {
        let a = self.anchor?;
        let to_grid = |um: f64, origin: f64, pitch: f64, up: bool| {
            let px = (um - origin) / pitch;
            let px = if up { px.ceil() } else { px.floor() };
            (-MAX_OFFSET_PX..=MAX_OFFSET_PX)
                .contains(&px)
                .then_some(px as i64)
        };
        Some(GridRect {
            x0: to_grid(r[0], a.x_um, self.pitch.x_um(), true)?,
            y0: to_grid(r[1], a.y_um, self.pitch.y_um(), true)?,
            x1: to_grid(r[2], a.x_um, self.pitch.x_um(), false)? + 1,
            y1: to_grid(r[3], a.y_um, self.pitch.y_um(), false)? + 1,
        })
        .filter(|g| g.x1 > g.x0 && g.y1 > g.y0)
    }

    fn grid_to_um(&self, gx: i64, gy: i64) -> (f64, f64) {
        match self.anchor {
            Some(a) => (
                a.x_um + gx as f64 * self.pitch.x_um(),
                a.y_um + gy as f64 * self.pitch.y_um(),
            ),
            None => (0.0, 0.0),
        }
    }

    /// Grid rectangle (inside the canvas) to canvas pixel coordinates.
    fn to_region(&self, r: &GridRect) -> Region {
        let c = self.canvas();
        Region {
            x0: (r.x0 - c.x0) as usize,
            y0: (r.y0 - c.y0) as usize,
            width: r.cols(),
            height: r.rows(),
        }
    }

    /// Where a (validated) tile lands on the grid anchored at `anchor`.
    fn plan(&self, tile: &TileInput<'_>, anchor: &Anchor) -> Result<(AxisPlan, AxisPlan)> {
        let offset_x_px = (tile.x_um - anchor.x_um) / self.pitch.x_um();
        let offset_y_px = (tile.y_um - anchor.y_um) / self.pitch.y_um();
        for (field, value, offset_px) in [
            ("x_um", tile.x_um, offset_x_px),
            ("y_um", tile.y_um, offset_y_px),
        ] {
            // Also refuses an infinite offset (a huge finite position over a small pitch).
            if !(-MAX_OFFSET_PX..=MAX_OFFSET_PX).contains(&offset_px) {
                return Err(FusionError::PositionOutOfRange {
                    index: tile.index,
                    field,
                    value,
                    offset_px,
                    max_px: MAX_OFFSET_PX,
                });
            }
        }
        Ok((
            AxisPlan::new(
                offset_x_px,
                tile.heights.cols(),
                self.params.effective_ramp_x_px(),
            ),
            AxisPlan::new(
                offset_y_px,
                tile.heights.rows(),
                self.params.effective_ramp_y_px(),
            ),
        ))
    }

    fn footprint(x: &AxisPlan, y: &AxisPlan) -> GridRect {
        GridRect {
            x0: x.start,
            y0: y.start,
            x1: x.start + x.len as i64,
            y1: y.start + y.len as i64,
        }
    }

    /// Make the canvas cover `need`, keeping its content. Growth is amortised: a side that must
    /// move out moves by at least the tile's size or half the canvas, whichever is more, so a
    /// scan of n tiles reallocates O(log n) times and never copies more than a constant
    /// multiple of the final canvas in total.
    fn ensure_covers(&mut self, need: GridRect, index: u32) -> Result<()> {
        if self.rect.is_empty() {
            let wanted = match self.reserved_um {
                Some(r) => self.grid_rect_um(&r).map_or(need, |g| g.union(&need)),
                None => need,
            };
            self.reallocate(wanted, need, index)?;
            self.reserved_um = None;
            return Ok(());
        }
        let cur = self.canvas();
        if cur.contains(&need) {
            return Ok(());
        }
        let padded = amortised_growth(cur, need);
        self.reallocate(padded, cur.union(&need), index)
    }

    /// Move the canvas to `wanted`, or to `minimal` if `wanted` exceeds the size limit.
    fn reallocate(&mut self, wanted: GridRect, minimal: GridRect, index: u32) -> Result<()> {
        let fits = |r: &GridRect| r.area().is_some_and(|a| a <= self.max_canvas_px);
        let new = if fits(&wanted) {
            wanted
        } else if fits(&minimal) {
            minimal
        } else {
            return Err(FusionError::CanvasTooLarge {
                index,
                width: minimal.cols(),
                height: minimal.rows(),
                max_px: self.max_canvas_px,
            });
        };
        // Bookkeeping only: chunks are created where tiles land.
        self.rect = new;
        Ok(())
    }

    /// Resample a tile onto the canvas at its final position, correct its plane, move it into
    /// the canvas's z and blend it in. Returns the canvas pixels it changed (its footprint).
    ///
    /// The footprint is the canvas pixels whose centres lie inside the hull of the tile's pixel
    /// centres: `width x height` pixels when the tile sits on the grid, one fewer column (row)
    /// when its x (y) offset has a fractional part.
    ///
    /// On error the panorama is unchanged.
    pub fn place(&mut self, tile: TileInput<'_>) -> Result<Region> {
        tile.validate()?;
        if self.placed.contains(&tile.index) {
            return Err(FusionError::DuplicateTile { index: tile.index });
        }
        let anchor = self.anchor.unwrap_or_else(|| Anchor::of(&tile));
        let (x, y) = self.plan(&tile, &anchor)?;
        let footprint = Self::footprint(&x, &y);
        if x.len == 0 || y.len == 0 {
            // A one-pixel-wide tile at a fractional offset covers no canvas pixel centre.
            self.anchor = Some(anchor);
            self.placed.insert(tile.index);
            return Ok(Region::default());
        }
        // The anchor is committed only together with the canvas: on error nothing changes.
        let previous_anchor = self.anchor.replace(anchor);
        if let Err(e) = self.ensure_covers(footprint, tile.index) {
            self.anchor = previous_anchor;
            return Err(e);
        }
        self.placed.insert(tile.index);
        self.content = Some(match self.content {
            Some(c) => c.union(&footprint),
            None => footprint,
        });

        let (cols, rows) = (tile.heights.cols(), tile.heights.rows());
        let centre_x = (cols - 1) as f64 / 2.0;
        let tilt_x = tile.plane.tilt_x_um_per_px;
        let resampler = Resampler {
            // The hot loops index the raw samples.
            heights: tile.heights.values(),
            width: cols,
            height: rows,
            col_term_um: (0..cols)
                .map(|c| -(tilt_x * (c as f64 - centre_x)))
                .collect(),
            piston_um: tile.plane.piston_um,
            tilt_y_um_per_px: tile.plane.tilt_y_um_per_px,
            dz_um: tile.z_offset_um - anchor.z_offset_um,
            x,
            y,
        };
        let region = self.to_region(&footprint);
        if let Some(wf) = self.wavelet {
            self.place_wavelet(&resampler, region, &wf, tile.index)?;
            return Ok(region);
        }
        // One task per chunk the footprint touches: pixels are independent, so the result does
        // not depend on the thread count, the schedule or the chunking (bit for bit).
        self.store.for_each_mut(&footprint, |cr, chunk| {
            let Some(part) = cr.intersect(&footprint) else {
                return;
            };
            let n = part.cols();
            let i0 = (part.x0 - footprint.x0) as usize;
            for gy in part.y0..part.y1 {
                let j = (gy - footprint.y0) as usize;
                let at = (gy - cr.y0) as usize * CHUNK_PX + (part.x0 - cr.x0) as usize;
                resampler.blend_span(
                    j,
                    i0,
                    &mut chunk.mean[at..at + n],
                    &mut chunk.weight[at..at + n],
                );
            }
        })?;
        Ok(region)
    }

    /// Wavelet fusion of a resampled tile into its footprint `region` (eq. 6): the tile's
    /// values and the canvas's current values over the footprint are fused by
    /// [`fuse_wavelet`]; pixels the tile does not measure keep the canvas's value.
    fn place_wavelet(
        &mut self,
        resampler: &Resampler<'_>,
        region: Region,
        wf: &WaveletFusion,
        index: u32,
    ) -> Result<()> {
        let w = region.width;
        let mut tile_z = vec![0.0f32; region.len()];
        let mut tile_w = vec![0.0f32; region.len()];
        tile_z
            .par_chunks_mut(w)
            .zip(tile_w.par_chunks_mut(w))
            .enumerate()
            .with_min_len(8)
            .for_each(|(j, (z, wt))| resampler.blend_row(j, z, wt));
        for (z, &wt) in tile_z.iter_mut().zip(&tile_w) {
            if wt <= 0.0 {
                *z = f32::NAN;
            }
        }
        let canvas_z = self.extract(region);
        // Whether the canvas has data just outside the footprint: there the tile's edge is a
        // seam the feathering must close. The footprint's one-pixel ring, clipped to the canvas.
        let (cw, ch) = (self.width() as isize, self.height() as isize);
        let ring = self.to_grid(&region).expand(1);
        let (_, ring_weight) = self.store.read_rect(&ring)?;
        let ring_cols = ring.cols() as isize;
        let canvas_beyond = |r: isize, c: isize| {
            let (y, x) = (region.y0 as isize + r, region.x0 as isize + c);
            (0..ch).contains(&y)
                && (0..cw).contains(&x)
                && ring_weight[((r + 1) * ring_cols + c + 1) as usize] > 0.0
        };
        let fused = fuse_wavelet_in(&canvas_z, &tile_z, region.height, w, wf, canvas_beyond)
            .map_err(|e| FusionError::WaveletFusion {
                index,
                message: e.to_string(),
            })?;
        let footprint = self.to_grid(&region);
        self.store.for_each_mut(&footprint, |cr, chunk| {
            let Some(part) = cr.intersect(&footprint) else {
                return;
            };
            for gy in part.y0..part.y1 {
                for gx in part.x0..part.x1 {
                    let k = (gy - footprint.y0) as usize * w + (gx - footprint.x0) as usize;
                    if tile_w[k] > 0.0 {
                        let at = (gy - cr.y0) as usize * CHUNK_PX + (gx - cr.x0) as usize;
                        chunk.mean[at] = fused[k];
                        chunk.weight[at] += 1.0;
                    }
                }
            }
        })?;
        Ok(())
    }

    /// The tile resampled alone onto this panorama's grid (no blending, plane and z applied as
    /// in [`Panorama::place`]): what this tile contributes, for overlap quality. Before any tile
    /// is placed the tile anchors its own grid.
    pub fn resample_alone(&self, tile: TileInput<'_>) -> Result<PlacedRaster> {
        let mut alone = Panorama::new(self.pitch, BlendParams::average())?;
        alone.anchor = self.anchor;
        alone.max_canvas_px = self.max_canvas_px;
        alone.place(tile)?;
        Ok(alone.to_raster())
    }

    /// Canvas pixel coordinates to grid indices.
    fn to_grid(&self, region: &Region) -> GridRect {
        GridRect {
            x0: self.rect.x0 + region.x0 as i64,
            y0: self.rect.y0 + region.y0 as i64,
            x1: self.rect.x0 + (region.x0 + region.width) as i64,
            y1: self.rect.y0 + (region.y0 + region.height) as i64,
        }
    }

    /// Where a tile at (`x_um`, `y_um`) with `cols` x `rows` samples lands on this canvas, as
    /// [`Panorama::resample_alone`] would place it: the first covered pixel in canvas pixel
    /// coordinates (negative when left of / above the canvas) and the covered size. `None`
    /// before the anchor is set, for a position out of range, or when it covers no pixel.
    pub fn footprint_px(
        &self,
        x_um: f64,
        y_um: f64,
        cols: usize,
        rows: usize,
    ) -> Option<(i64, i64, usize, usize)> {
        let anchor = self.anchor?;
        if cols == 0 || rows == 0 {
            return None;
        }
        let ox = (x_um - anchor.x_um) / self.pitch.x_um();
        let oy = (y_um - anchor.y_um) / self.pitch.y_um();
        if !(-MAX_OFFSET_PX..=MAX_OFFSET_PX).contains(&ox)
            || !(-MAX_OFFSET_PX..=MAX_OFFSET_PX).contains(&oy)
        {
            return None;
        }
        let x = AxisPlan::new(ox, cols, self.params.effective_ramp_x_px());
        let y = AxisPlan::new(oy, rows, self.params.effective_ramp_y_px());
        (x.len > 0 && y.len > 0)
            .then(|| (x.start - self.rect.x0, y.start - self.rect.y0, x.len, y.len))
    }

    /// Blended heights of a region (um relative to [`Panorama::z_offset_um`]), row-major;
    /// NaN where no tile has data and for pixels outside the canvas. Panics only if a spilled
    /// chunk cannot be read back (see [`Panorama::try_extract`]).
    pub fn extract(&self, region: Region) -> Vec<f32> {
        match self.try_extract(region) {
            Ok(v) => v,
            Err(e) => panic!("panorama: {e}"),
        }
    }

    /// [`Panorama::extract`], with an error when a spilled chunk cannot be read back.
    pub fn try_extract(&self, region: Region) -> Result<Vec<f32>> {
        let mut out = vec![f32::NAN; region.len()];
        let (cw, ch) = (self.width(), self.height());
        if region.is_empty() || region.x0 >= cw || region.y0 >= ch {
            return Ok(out);
        }
        let x_end = region.x0.saturating_add(region.width).min(cw);
        let y_end = region.y0.saturating_add(region.height).min(ch);
        let inside = Region {
            x0: region.x0,
            y0: region.y0,
            width: x_end - region.x0,
            height: y_end - region.y0,
        };
        // One band of chunk rows at a time: the accumulators are read (from memory or the
        // spill file, each chunk once) for that band only, so extracting the whole panorama
        // costs its f32 output plus one band, not two more whole-panorama buffers.
        let grid = self.to_grid(&inside);
        let c = crate::CHUNK_PX as i64;
        let n = inside.width;
        let mut y0 = grid.y0;
        while y0 < grid.y1 {
            let y1 = ((y0.div_euclid(c) + 1) * c).min(grid.y1);
            let band = GridRect { y0, y1, ..grid };
            surfstream_core::liveness::beat();
            let (mean, weight) = self.store.read_rect(&band)?;
            let first = (y0 - grid.y0) as usize;
            let out_band = &mut out[first * region.width..(y1 - grid.y0) as usize * region.width];
            for (out_row, (m_row, w_row)) in out_band
                .chunks_mut(region.width)
                .zip(mean.chunks(n).zip(weight.chunks(n)))
            {
                for ((o, &m), &w) in out_row.iter_mut().zip(m_row).zip(w_row) {
                    if w > 0.0 {
                        *o = m;
                    }
                }
            }
            y0 = y1;
        }
        Ok(out)
    }

    /// The whole panorama, trimmed to the bounding box of the placed tiles' footprints. An
    /// empty panorama gives a 0 x 0 raster.
    pub fn to_raster(&self) -> PlacedRaster {
        let (region, origin) = match self.content {
            Some(c) => (self.to_region(&c), self.grid_to_um(c.x0, c.y0)),
            None => (Region::default(), (0.0, 0.0)),
        };
        let shape = Shape::new(region.height, region.width);
        // `extract` gives exactly `shape.len()` values, so only an empty panorama is refused:
        // it becomes the 0 x 0 raster.
        let heights = Raster::new(self.extract(region), shape)
            .unwrap_or_else(|_| Raster::filled(Shape::default(), f32::NAN));
        PlacedRaster {
            heights,
            origin_x_um: origin.0,
            origin_y_um: origin.1,
            pitch: self.pitch,
            z_offset_um: self.z_offset_um(),
        }
    }
}

/// Re-render a panorama from final tile positions (end of scan, after a global solve moved
/// tiles). Tiles are placed in increasing `index` order (the slice order does not matter), so
/// the result equals placing them one by one in that order and taking
/// [`Panorama::to_raster`], bit for bit. The canvas is sized once from all footprints instead
/// of growing.
pub fn render(pitch: Pitch, tiles: &[TileInput<'_>], params: BlendParams) -> Result<PlacedRaster> {
    Ok(render_panorama(pitch, tiles, params, None)?.to_raster())
}

/// [`render`] with an optional wavelet fusion, returning the panorama itself (for
/// [`crate::overlap_quality`]). Equals placing the tiles one by one in index order.
pub fn render_panorama(
    pitch: Pitch,
    tiles: &[TileInput<'_>],
    params: BlendParams,
    wavelet: Option<WaveletFusion>,
) -> Result<Panorama> {
    let mut pano = Panorama::new(pitch, params)?;
    pano.set_wavelet_fusion(wavelet);
    let mut order: Vec<&TileInput<'_>> = tiles.iter().collect();
    // Stable: equal indices keep their slice order (and then fail as duplicates in place()).
    order.sort_by_key(|t| t.index);
    let first = order.first().ok_or(FusionError::NoTiles)?;
    // Validated (with all the others) in the loop below, before anything is planned.
    let anchor = Anchor::of(first);
    let mut need: Option<GridRect> = None;
    for tile in &order {
        tile.validate()?;
        let (x, y) = pano.plan(tile, &anchor)?;
        if x.len == 0 || y.len == 0 {
            continue;
        }
        let fp = Panorama::footprint(&x, &y);
        let union = need.map_or(fp, |n| n.union(&fp));
        if union.area().is_none_or(|a| a > pano.max_canvas_px) {
            return Err(FusionError::CanvasTooLarge {
                index: tile.index,
                width: union.cols(),
                height: union.rows(),
                max_px: pano.max_canvas_px,
            });
        }
        need = Some(union);
    }
    if let Some(need) = need {
        pano.ensure_covers(need, first.index)?;
    }
    for tile in order {
        pano.place(*tile)?;
    }
    Ok(pano)
}
