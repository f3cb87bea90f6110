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

use serde::Serialize;
use surfstream_core::similarity::{ssim, WINDOW_PX};

use crate::error::Result;
use crate::input::TileInput;
use crate::panorama::{Panorama, PlacedRaster, Region};

/// SSIM of one overlap.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PairQuality {
    /// Tile indices, `tile_a < tile_b`.
    pub tile_a: u32,
    pub tile_b: u32,
    /// Overlap rectangle in panorama pixels.
    pub width_px: usize,
    pub height_px: usize,
    /// Pixels of the rectangle both tiles measured.
    pub valid_px: usize,
    /// SSIM(fused, tile a), SSIM(fused, tile b) over the overlap, and their mean.
    pub ssim_a: f64,
    pub ssim_b: f64,
    pub ssim_mean: f64,
}

/// SSIM of every scored overlap of `tiles` in the (final) panorama `pano`, ordered by
/// (tile_a, tile_b).
pub fn overlap_quality(pano: &Panorama, tiles: &[TileInput<'_>]) -> Result<Vec<PairQuality>> {
    let Some(content) = pano.content_region() else {
        return Ok(Vec::new());
    };
    let (cx, cy) = pano.canvas_origin_um();
    let (px, py) = pano.pitch_um();
    // Each tile alone and where it sits in canvas pixels.
    let mut alone: Vec<(u32, PlacedRaster, i64, i64)> = Vec::with_capacity(tiles.len());
    for t in tiles {
        let r = pano.resample_alone(*t)?;
        if r.heights.shape().is_empty() {
            continue;
        }
        let gx = ((r.origin_x_um - cx) / px).round() as i64;
        let gy = ((r.origin_y_um - cy) / py).round() as i64;
        alone.push((t.index, r, gx, gy));
    }
    alone.sort_by_key(|a| a.0);
    let mut out = Vec::new();
    for (i, (ia, ra, ax, ay)) in alone.iter().enumerate() {
        for (ib, rb, bx, by) in &alone[i + 1..] {
            let x0 = (*ax).max(*bx).max(content.x0 as i64);
            let y0 = (*ay).max(*by).max(content.y0 as i64);
            let x1 = (ax + ra.heights.cols() as i64).min(bx + rb.heights.cols() as i64);
            let y1 = (ay + ra.heights.rows() as i64).min(by + rb.heights.rows() as i64);
            if x1 - x0 < WINDOW_PX as i64 || y1 - y0 < WINDOW_PX as i64 {
                continue;
            }
            let region = Region {
                x0: x0 as usize,
                y0: y0 as usize,
                width: (x1 - x0) as usize,
                height: (y1 - y0) as usize,
            };
            let fused = pano.extract(region);
            let crop = |r: &PlacedRaster, gx: i64, gy: i64| -> Vec<f32> {
                let mut v = Vec::with_capacity(region.len());
                for row in 0..region.height {
                    let sr = (y0 - gy) as usize + row;
                    let sc = (x0 - gx) as usize;
                    v.extend_from_slice(&r.heights.row(sr)[sc..][..region.width]);
                }
                v
            };
            let mut za = crop(ra, *ax, *ay);
            let mut zb = crop(rb, *bx, *by);
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
                tile_a: *ia,
                tile_b: *ib,
                width_px: w,
                height_px: h,
                valid_px,
                ssim_a: sa.mssim,
                ssim_b: sb.mssim,
                ssim_mean: 0.5 * (sa.mssim + sb.mssim),
            });
        }
    }
    Ok(out)
}
