//! Acquiring one tile: resampling the specimen at the tile's true pose and degrading it like
//! the instrument does.

use rand::Rng;
use rand_distr::{Distribution, Poisson, StandardNormal};

use crate::rng::{domain, stream};
use crate::specimen::SpecimenSurface;
use crate::stage::{StageParams, TilePlan};

/// Largest number of dropout blobs drawn for one tile (a guard against absurd means).
const MAX_BLOBS: u64 = 10_000;

/// Keys cubic convolution kernel with a = -0.5 (Catmull-Rom).
fn keys(s: f64) -> f64 {
    let s = s.abs();
    if s <= 1.0 {
        (1.5 * s - 2.5) * s * s + 1.0
    } else if s < 2.0 {
        ((-0.5 * s + 2.5) * s - 4.0) * s + 2.0
    } else {
        0.0
    }
}

/// The non-zero taps (integer offset from `floor(x)`, weight) of a bicubic sample at `x`.
/// At an integer `x` this is the single tap (0, 1.0), so sampling is an exact copy.
fn taps(x: f64) -> (i64, Vec<(i64, f32)>) {
    let base = x.floor();
    let t = x - base;
    let taps = [
        (-1, keys(1.0 + t)),
        (0, keys(t)),
        (1, keys(1.0 - t)),
        (2, keys(2.0 - t)),
    ]
    .into_iter()
    .filter(|&(_, w)| w != 0.0)
    .map(|(o, w)| (o, w as f32))
    .collect();
    (base as i64, taps)
}

/// Bicubic (Keys, a = -0.5) sample of the specimen at sub-pixel (x, y) = (column, row).
/// NaN if the interpolation support leaves the specimen or touches a NaN.
pub fn sample_bicubic<S: SpecimenSurface + ?Sized>(specimen: &S, x: f64, y: f64) -> f32 {
    let mut out = [f32::NAN];
    resample_window(specimen, x, y, 1, 1, &mut out);
    out[0]
}

/// Resamples the `width x height` window whose pixel (0, 0) sits at specimen position
/// (x0, y0), writing row-major into `out`. The fractional part is the same for every pixel, so
/// the bicubic weights are computed once and applied separably (rows, then columns). Pixels
/// whose support leaves the specimen are NaN.
fn resample_window<S: SpecimenSurface + ?Sized>(
    specimen: &S,
    x0: f64,
    y0: f64,
    width: usize,
    height: usize,
    out: &mut [f32],
) {
    out.fill(f32::NAN);
    if !(x0.is_finite() && y0.is_finite()) || width == 0 || height == 0 {
        return;
    }
    // Far outside: nothing to sample (also keeps the i64 arithmetic below in range).
    let shape = specimen.shape();
    let limit = 4.0 * (shape.cols.max(shape.rows) + width.max(height)) as f64;
    if x0.abs() > limit || y0.abs() > limit {
        return;
    }
    let (ix, tx) = taps(x0);
    let (iy, ty) = taps(y0);
    let (sw, sh) = (shape.cols as i64, shape.rows as i64);
    let (w, h) = (width as i64, height as i64);
    let ox_min = tx.iter().map(|t| t.0).min().unwrap_or(0);
    let ox_max = tx.iter().map(|t| t.0).max().unwrap_or(0);
    let oy_min = ty.iter().map(|t| t.0).min().unwrap_or(0);
    let oy_max = ty.iter().map(|t| t.0).max().unwrap_or(0);
    // Output columns j whose whole x support lies inside: 0 <= ix + j + ox_min and
    // ix + j + ox_max <= sw - 1.
    let j_lo = (-(ix + ox_min)).clamp(0, w);
    let j_hi = (sw - 1 - ix - ox_max + 1).clamp(j_lo, w);
    if j_lo >= j_hi {
        return;
    }
    let (j_lo, j_hi) = (j_lo as usize, j_hi as usize);
    // Horizontal pass over the specimen rows iy + oy_min ..= iy + h - 1 + oy_max, read as one
    // block of the columns the taps need (ix + j_lo + ox_min ..= ix + j_hi - 1 + ox_max).
    let temp_rows = (h + oy_max - oy_min) as usize;
    let mut temp = vec![f32::NAN; temp_rows * width];
    let col0 = (ix + j_lo as i64 + ox_min) as usize;
    let src_w = j_hi - j_lo + (ox_max - ox_min) as usize;
    let row_lo = (iy + oy_min).clamp(0, sh);
    let row_hi = (iy + oy_min + temp_rows as i64).clamp(row_lo, sh);
    let mut src = vec![0f32; (row_hi - row_lo) as usize * src_w];
    specimen.read_block(col0, row_lo as usize, src_w, &mut src);
    for (r, trow) in temp.chunks_exact_mut(width).enumerate() {
        let sy = iy + oy_min + r as i64;
        if sy < row_lo || sy >= row_hi {
            continue;
        }
        let at = (sy - row_lo) as usize * src_w;
        let srow = &src[at..at + src_w];
        let seg = &mut trow[j_lo..j_hi];
        seg.fill(0.0);
        for &(ox, wx) in &tx {
            let start = (ox - ox_min) as usize;
            for (t, s) in seg.iter_mut().zip(&srow[start..start + (j_hi - j_lo)]) {
                *t += wx * s;
            }
        }
    }
    // Vertical pass.
    for (i, orow) in out.chunks_exact_mut(width).enumerate() {
        let sy_lo = iy + i as i64 + oy_min;
        let sy_hi = iy + i as i64 + oy_max;
        if sy_lo < 0 || sy_hi >= sh {
            continue;
        }
        let seg = &mut orow[j_lo..j_hi];
        seg.fill(0.0);
        for &(oy, wy) in &ty {
            let r = (i as i64 + oy - oy_min) as usize;
            let trow = &temp[r * width + j_lo..r * width + j_hi];
            for (o, t) in seg.iter_mut().zip(trow) {
                *o += wy * t;
            }
        }
    }
}

/// Acquires one tile: the specimen resampled (bicubic, Keys a = -0.5) on the tile's pixel grid
/// at its true sub-pixel origin, plus piston and tilt (`tilt_x * xn + tilt_y * yn`, with
/// `xn = (j - (w - 1) / 2) / w` and likewise `yn`, i.e. -0.5 .. 0.5 across the tile), plus white
/// noise, with NaN dropouts (isolated pixels and elliptical blobs).
///
/// Returns `tile_width * tile_height` heights in micrometres, row-major. Every random number
/// comes from streams keyed by (`params.seed`, `tile.index`): tiles can be acquired in any
/// order, in parallel, with identical results. Pixels whose interpolation support leaves the
/// specimen are NaN (cannot happen for a plan whose [`crate::ScanPlan::check_specimen`]
/// passed). Never panics.
pub fn acquire_tile<S: SpecimenSurface + ?Sized>(
    specimen: &S,
    tile: &TilePlan,
    params: &StageParams,
) -> Vec<f32> {
    let (w, h) = params.tile_shape_px();
    let Some(n) = w.checked_mul(h) else {
        return Vec::new();
    };
    let mut out = vec![f32::NAN; n];
    let [x0, y0] = tile.true_origin_px;
    resample_window(specimen, x0, y0, w, h, &mut out);
    if w == 0 || h == 0 {
        return out;
    }
    add_pose(&mut out, w, h, tile);
    let index = tile.index as u64;
    if params.noise_um > 0.0 && params.noise_um.is_finite() {
        let mut rng = stream(params.seed, domain::TILE_NOISE, index);
        let sigma = params.noise_um as f32;
        for v in out.iter_mut() {
            let z: f32 = StandardNormal.sample(&mut rng);
            *v += sigma * z;
        }
    }
    drop_pixels(&mut out, params.dropout_fraction, params.seed, index);
    drop_blobs(&mut out, w, h, params, index);
    out
}

/// Adds piston and tilt.
fn add_pose(out: &mut [f32], w: usize, h: usize, tile: &TilePlan) {
    if tile.piston_um == 0.0 && tile.tilt_x_um == 0.0 && tile.tilt_y_um == 0.0 {
        return;
    }
    let cx = (w as f64 - 1.0) / 2.0;
    let cy = (h as f64 - 1.0) / 2.0;
    let plane_x: Vec<f64> = (0..w)
        .map(|j| tile.tilt_x_um * (j as f64 - cx) / w as f64)
        .collect();
    for (i, row) in out.chunks_exact_mut(w).enumerate() {
        let base = tile.piston_um + tile.tilt_y_um * (i as f64 - cy) / h as f64;
        for (v, px) in row.iter_mut().zip(&plane_x) {
            *v += (base + px) as f32;
        }
    }
}

/// Sets a `fraction` of the pixels to NaN, independently per pixel (geometric gaps, so the
/// cost scales with the number of dropouts, not of pixels).
fn drop_pixels(out: &mut [f32], fraction: f64, seed: u64, index: u64) {
    if fraction.is_nan() || fraction <= 0.0 {
        return;
    }
    if fraction >= 1.0 {
        out.fill(f32::NAN);
        return;
    }
    let mut rng = stream(seed, domain::TILE_DROPOUT, index);
    let log_q = (1.0 - fraction).ln();
    let mut pos = 0usize;
    loop {
        let u: f64 = 1.0 - rng.gen::<f64>(); // (0, 1]
        let gap = (u.ln() / log_q).floor();
        if gap.is_nan() || gap >= out.len() as f64 {
            return;
        }
        pos = pos.saturating_add(gap as usize);
        match out.get_mut(pos) {
            Some(v) => *v = f32::NAN,
            None => return,
        }
        pos += 1;
    }
}

/// Sets a Poisson number of random ellipses to NaN.
fn drop_blobs(out: &mut [f32], w: usize, h: usize, params: &StageParams, index: u64) {
    let mean = params.dropout_blobs_mean;
    let [rmin, rmax] = params.blob_radius_px;
    if !(mean > 0.0 && mean.is_finite() && rmin > 0.0 && rmin <= rmax && rmax.is_finite()) {
        return;
    }
    let Ok(poisson) = Poisson::new(mean) else {
        return;
    };
    let mut rng = stream(params.seed, domain::TILE_BLOBS, index);
    let count = (poisson.sample(&mut rng) as u64).min(MAX_BLOBS);
    for _ in 0..count {
        let cx = rng.gen_range(0.0..w as f64);
        let cy = rng.gen_range(0.0..h as f64);
        let rx = if rmax > rmin {
            rng.gen_range(rmin..rmax)
        } else {
            rmin
        };
        let ry = if rmax > rmin {
            rng.gen_range(rmin..rmax)
        } else {
            rmin
        };
        let theta = rng.gen_range(0.0..std::f64::consts::PI);
        let (s, c) = theta.sin_cos();
        let r = rx.max(ry);
        let x_lo = (cx - r).floor().max(0.0) as usize;
        let x_hi = ((cx + r).ceil().max(0.0) as usize).min(w - 1);
        let y_lo = (cy - r).floor().max(0.0) as usize;
        let y_hi = ((cy + r).ceil().max(0.0) as usize).min(h - 1);
        for y in y_lo..=y_hi {
            for x in x_lo..=x_hi {
                let dx = x as f64 - cx;
                let dy = y as f64 - cy;
                let u = dx * c + dy * s;
                let v = -dx * s + dy * c;
                if (u / rx).powi(2) + (v / ry).powi(2) <= 1.0 {
                    if let Some(p) = out.get_mut(y * w + x) {
                        *p = f32::NAN;
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_kernel_partition_of_unity() {
        for k in 0..=20 {
            let t = k as f64 / 20.0;
            let s = keys(1.0 + t) + keys(t) + keys(1.0 - t) + keys(2.0 - t);
            assert!((s - 1.0).abs() < 1e-12, "t = {t}: sum {s}");
        }
        assert_eq!(keys(0.0), 1.0);
        assert_eq!(keys(1.0), 0.0);
        assert_eq!(keys(2.0), 0.0);
    }

    #[test]
    fn integer_position_is_a_single_tap() {
        let (base, t) = taps(7.0);
        assert_eq!(base, 7);
        assert_eq!(t, vec![(0, 1.0)]);
        let (base, t) = taps(-2.25);
        assert_eq!(base, -3);
        assert_eq!(t.len(), 4);
    }
}
