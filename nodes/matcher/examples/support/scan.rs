//! A scan directory for the examples, through the replay node's own reader
//! (`surfstream_replay::scan_dir::load_scan`), with the grid-neighbour pairs and the nominal
//! offsets the stage positions imply; and the median the examples report.

use std::path::Path;

use anyhow::Result;
use surfstream_core::raster::{RasterView, Shape};
use surfstream_core::Pitch;
use surfstream_replay::scan_dir::{load_scan, LoadedTile};

pub struct Scan {
    pub tiles: Vec<LoadedTile>,
    pub pitch: Pitch,
    /// Every tile's shape (the scan's one tile size).
    pub shape: Shape,
}

impl Scan {
    pub fn load(path: &Path) -> Result<Scan> {
        let s = load_scan(path)?;
        Ok(Scan {
            tiles: s.tiles,
            pitch: s.scan.pitch,
            shape: Shape::new(s.tile_height_px, s.tile_width_px),
        })
    }

    /// Tile `i`'s heights; an error when a file's heights do not fill the scan's tile shape.
    pub fn raster(&self, i: usize) -> Result<RasterView<'_, f32>> {
        Ok(RasterView::new(&self.tiles[i].heights_um, self.shape)?)
    }

    /// Grid-neighbour pairs (a, b), a < b (acquisition indices).
    pub fn neighbour_pairs(&self) -> Vec<(usize, usize)> {
        let mut pairs = Vec::new();
        for (b, tb) in self.tiles.iter().enumerate() {
            for (a, ta) in self.tiles.iter().enumerate().take(b) {
                if ta.entry.row.abs_diff(tb.entry.row) + ta.entry.col.abs_diff(tb.entry.col) == 1 {
                    pairs.push((a, b));
                }
            }
        }
        pairs
    }

    /// Tile `i`'s stage position, px.
    pub fn stage_px(&self, i: usize) -> [f64; 2] {
        let e = &self.tiles[i].entry;
        [
            e.stage_x_um / self.pitch.x_um(),
            e.stage_y_um / self.pitch.y_um(),
        ]
    }

    /// b's nominal offset from a, px.
    pub fn nominal_offset_px(&self, a: usize, b: usize) -> [f64; 2] {
        let (pa, pb) = (self.stage_px(a), self.stage_px(b));
        [pb[0] - pa[0], pb[1] - pa[1]]
    }
}

/// The median (upper middle for an even count); NaN for no samples.
pub fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}
