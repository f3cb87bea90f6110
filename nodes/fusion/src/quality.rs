//! Quality of every overlap: SSIM (paper eq. 7) between the fused panorama and each of the
//! two tiles that overlap there.
//!
//! For a pair of tiles (i, j) whose footprints on the panorama grid intersect, the overlap is
//! the intersection rectangle restricted to pixels both tiles measured. There the fused
//! panorama is compared with tile i and with tile j, each resampled alone onto the same grid
//! ([`Panorama::resample_alone`]: plane, z and sub-pixel position as placed), by
//! [`surfstream_core::similarity::ssim`] (Wang et al. 2004: 11 x 11 Gaussian window,
//! sigma 1.5, K1 = 0.01, K2 = 0.03, L = the height range over the overlap). `ssim_mean` is
//! the mean of the two: how well the fused overlap keeps the structure of both measurements.
//! Overlaps smaller than the 11 px window in either direction are not scored.

use std::collections::HashMap;

use surfstream_core::similarity::{ssim, WINDOW_PX};

use crate::error::Result;
use crate::input::TileInput;
use crate::panorama::{Panorama, PlacedRaster, Region};

/// SSIM of one overlap: a record of the fusion's report (run.json readers share it).
pub use surfstream_core::record::PairQuality;

/// Where a tile sits, without its heights: what pairing the overlaps needs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TileFootprint {
    pub index: u32,
    pub x_um: f64,
    pub y_um: f64,
    pub cols: usize,
    pub rows: usize,
}

impl TileFootprint {
    pub fn of(t: &TileInput<'_>) -> Self {
        Self {
            index: t.index,
            x_um: t.x_um,
            y_um: t.y_um,
            cols: t.heights.cols(),
            rows: t.heights.rows(),
        }
    }
}

/// SSIM of every scored overlap of `tiles` in the (final) panorama `pano`, ordered by
/// (tile_a, tile_b).
pub fn overlap_quality(pano: &Panorama, tiles: &[TileInput<'_>]) -> Result<Vec<PairQuality>> {
    let footprints: Vec<TileFootprint> = tiles.iter().map(TileFootprint::of).collect();
    overlap_quality_streamed(pano, &footprints, |k| pano.resample_alone(tiles[k]))
}

/// [`overlap_quality`] with the tiles resampled on demand: `alone(k)` gives tile
/// `footprints[k]` resampled alone onto `pano`'s grid ([`Panorama::resample_alone`]). Pairs
/// are found from the footprints; each tile is resampled once, cut into its crops over the
/// overlaps still to score, and dropped: in a serpentine scan about two rows of overlap strips
/// are in memory at once (a few MB), not tiles. The result is the same as
/// [`overlap_quality`]'s.
pub fn overlap_quality_streamed(
    pano: &Panorama,
    footprints: &[TileFootprint],
    mut alone: impl FnMut(usize) -> Result<PlacedRaster>,
) -> Result<Vec<PairQuality>> {
    let Some(content) = pano.content_region() else {
        return Ok(Vec::new());
    };
    // Each tile's place in canvas pixels, in index order (stable for equal indices).
    let mut placed: Vec<(usize, u32, i64, i64, usize, usize)> = footprints
        .iter()
        .enumerate()
        .filter_map(|(k, f)| {
            pano.footprint_px(f.x_um, f.y_um, f.cols, f.rows)
                .map(|(gx, gy, w, h)| (k, f.index, gx, gy, w, h))
        })
        .collect();
    placed.sort_by_key(|p| p.1);
    // The scored pairs (positions in `placed`) and their overlap rectangles.
    let mut pairs: Vec<(usize, usize, Region)> = Vec::new();
    for (i, &(_, _, ax, ay, aw, ah)) in placed.iter().enumerate() {
        for (j, &(_, _, bx, by, bw, bh)) in placed.iter().enumerate().skip(i + 1) {
            let x0 = ax.max(bx).max(content.x0 as i64);
            let y0 = ay.max(by).max(content.y0 as i64);
            let x1 = (ax + aw as i64).min(bx + bw as i64);
            let y1 = (ay + ah as i64).min(by + bh as i64);
            if x1 - x0 < WINDOW_PX as i64 || y1 - y0 < WINDOW_PX as i64 {
                continue;
            }
            let region = Region {
                x0: x0 as usize,
                y0: y0 as usize,
                width: (x1 - x0) as usize,
                height: (y1 - y0) as usize,
            };
            pairs.push((i, j, region));
        }
    }
    // Each tile is resampled once, at its first pair, and only its crops over the overlaps
    // still to score are kept (strips of about the overlap's size), not the resampled tile.
    let mut pairs_of: Vec<Vec<usize>> = vec![Vec::new(); placed.len()];
    for (p, &(i, j, _)) in pairs.iter().enumerate() {
        pairs_of[i].push(p);
        pairs_of[j].push(p);
    }
    let crop = |r: &PlacedRaster, gx: i64, gy: i64, region: &Region| -> Vec<f32> {
        let (x0, y0) = (region.x0 as i64, region.y0 as i64);
        let mut v = Vec::with_capacity(region.len());
        for row in 0..region.height {
            let sr = (y0 - gy) as usize + row;
            let sc = (x0 - gx) as usize;
            v.extend_from_slice(&r.heights.row(sr)[sc..][..region.width]);
        }
        v
    };
    let mut crops: HashMap<(usize, usize), Vec<f32>> = HashMap::new();
    let mut out = Vec::new();
    for (p, &(i, j, region)) in pairs.iter().enumerate() {
        for k in [i, j] {
            if crops.contains_key(&(p, k)) {
                continue;
            }
            let r = alone(placed[k].0)?;
            let (gx, gy) = (placed[k].2, placed[k].3);
            for &q in pairs_of[k].iter().filter(|&&q| q >= p) {
                crops.insert((q, k), crop(&r, gx, gy, &pairs[q].2));
            }
        }
        let (ia, ib) = (placed[i].1, placed[j].1);
        let fused = pano.try_extract(region)?;
        let (Some(mut za), Some(mut zb)) = (crops.remove(&(p, i)), crops.remove(&(p, j))) else {
            continue; // inserted just above
        };
        // Score only where both measured: each side loses the other's holes.
        let mut valid_px = 0;
        for (a, b) in za.iter_mut().zip(zb.iter_mut()) {
            if a.is_finite() && b.is_finite() {
                valid_px += 1;
            } else {
                *a = f32::NAN;
                *b = f32::NAN;
            }
        }
        let (h, w) = (region.height, region.width);
        let (Ok(sa), Ok(sb)) = (ssim(&fused, &za, h, w, None), ssim(&fused, &zb, h, w, None))
        else {
            continue; // no window with enough data in both: nothing to score
        };
        out.push(PairQuality {
            tile_a: ia,
            tile_b: ib,
            width_px: w,
            height_px: h,
            valid_px,
            ssim_a: sa.mssim,
            ssim_b: sb.mssim,
            ssim_mean: 0.5 * (sa.mssim + sb.mssim),
        });
    }
    Ok(out)
}
