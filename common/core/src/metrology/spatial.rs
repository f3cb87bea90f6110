//! Spatial parameters, ISO 25178-2 §4.3: Sal and Str from the autocorrelation function (ACF),
//! Std from the angular amplitude spectrum.
//!
//! ACF: f_ACF(tx, ty) = mean over the valid pairs of c(x, y) c(x + tx, y + ty), c = heights
//! minus the mean of the valid points: the linear (zero-padded, not circular) estimator with
//! each lag divided by its own number of pairs (the unbiased estimator surfalize 0.19.2 uses).
//! NaN: a pair counts only when both points are valid (the pair count is the autocorrelation of
//! the validity mask; lags with no valid pair are NaN).
//!
//! Sal and Str (threshold s = 0.2 of f_ACF(0, 0), ISO 25178-3): the region of lags connected
//! to 0 (4-neighbours) where f_ACF > s f_ACF(0); for every lag just outside it, the ray from 0
//! to that lag is followed (bilinear interpolation, 2 samples per pixel) to the first point
//! where f_ACF falls to s f_ACF(0), refined linearly between samples. Sal = the shortest of
//! these decay lengths (um), Str = shortest / longest. When the region reaches the border of
//! the lag plane the slowest decay is not inside the measurement: Str is NaN (undefined), Sal
//! is still the fastest decay. No decay anywhere: both NaN.
//!
//! Std (degrees, 0 <= Std < 180): the direction of the largest angular amplitude density
//! f_AAD(theta) = the sum of |F(fx, fy)| over the DFT samples whose frequency vector points
//! at theta (bins of `STD_STEP_DEG`, lower bin edge reported), frequencies in 1/um so the
//! angle is right for any pitch. The angle is counter-clockwise from +x towards +y in scan
//! coordinates (y grows with the row index). surfalize measures it with y pointing up the
//! displayed image (row 0 on top), i.e. towards -y: for the same array its angle is
//! 180 - ours (mod 180, within one bin). A lay of ridges along y (heights varying along x)
//! gives Std = 0. NaN: the spectrum of the mean-filled map (gaps set to the mean).

use std::sync::atomic::{AtomicU64, Ordering as AtomicOrdering};

use rayon::prelude::*;
use serde::Serialize;

use super::spectrum::{correlation_half_plane, spectrum2_of};
use super::{Grid, MetrologyError};

/// ISO 25178-3 default threshold of Sal / Str.
pub const ACF_THRESHOLD: f64 = 0.2;
/// Angular bin of Std (degrees).
pub const STD_STEP_DEG: f64 = 0.5;

/// Sal, Str, Std.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SpatialParams {
    /// Autocorrelation length (um).
    #[serde(rename = "Sal")]
    pub sal: f64,
    /// Texture aspect ratio (0..1]; NaN when the slowest decay leaves the measurement.
    #[serde(rename = "Str")]
    pub str_: f64,
    /// Texture direction (degrees).
    #[serde(rename = "Std")]
    pub std: f64,
}

/// The heights centred on the mean of the valid points, gaps 0, with the valid count.
pub(crate) fn centred(g: &Grid) -> Result<(Vec<f64>, usize), MetrologyError> {
    let mean = super::height_params_mean(g)?;
    let c: Vec<f64> = g
        .heights_um
        .par_iter()
        .map(|&z| if z.is_nan() { 0.0 } else { z - mean })
        .collect();
    let n = g.heights_um.par_iter().filter(|z| !z.is_nan()).count();
    Ok((c, n))
}

/// [`centred`] without holding it: its rows written on demand, with the valid count.
struct CentredRows<'a> {
    z: &'a [f64],
    cols: usize,
    mean: f64,
    valid: usize,
}

impl<'a> CentredRows<'a> {
    fn of(g: &Grid<'a>) -> Result<Self, MetrologyError> {
        Ok(Self {
            z: g.heights_um,
            cols: g.cols(),
            mean: super::height_params_mean(g)?,
            valid: g.heights_um.par_iter().filter(|z| !z.is_nan()).count(),
        })
    }

    /// Row r of [`centred`]'s field into `buf` (cols values).
    fn row(&self, r: usize, buf: &mut [f64]) {
        let (cols, mean) = (self.cols, self.mean);
        for (o, &z) in buf.iter_mut().zip(&self.z[r * cols..(r + 1) * cols]) {
            *o = if z.is_nan() { 0.0 } else { z - mean };
        }
    }
}

/// The autocorrelation function over lags ty = -(rows-1)..=(rows-1), tx = -(cols-1)..=(cols-1)
/// (um^2); stored as the half plane ty >= 0 (f_ACF(-t) = f_ACF(t)).
#[derive(Debug, Clone)]
pub struct Acf {
    pub rows: usize,
    pub cols: usize,
    pub pitch_x_um: f64,
    pub pitch_y_um: f64,
    half: Vec<f64>,
}

impl Acf {
    /// The ACF of `g` (see the module documentation).
    pub fn of(g: &Grid) -> Result<Self, MetrologyError> {
        let c = CentredRows::of(g)?;
        let n = c.valid;
        let (rows, cols) = (g.rows(), g.cols());
        let mut half = correlation_half_plane(&|r, buf: &mut [f64]| c.row(r, buf), rows, cols);
        let w = 2 * cols - 1;
        if n == rows * cols {
            half.par_chunks_mut(w).enumerate().for_each(|(ty, row)| {
                for (i, v) in row.iter_mut().enumerate() {
                    let tx = (i as isize - (cols as isize - 1)).unsigned_abs();
                    *v /= ((rows - ty) * (cols - tx)) as f64;
                }
            });
        } else {
            let z = g.heights_um;
            let mask = |r: usize, buf: &mut [f64]| {
                for (o, &z) in buf.iter_mut().zip(&z[r * cols..(r + 1) * cols]) {
                    *o = if z.is_nan() { 0.0 } else { 1.0 };
                }
            };
            let pairs = correlation_half_plane(&mask, rows, cols);
            half.par_iter_mut()
                .zip(pairs.par_iter())
                .for_each(|(v, &k)| {
                    let k = k.round();
                    *v = if k >= 1.0 { *v / k } else { f64::NAN };
                });
        }
        Ok(Self {
            rows,
            cols,
            pitch_x_um: g.pitch_x_um(),
            pitch_y_um: g.pitch_y_um(),
            half,
        })
    }

    /// f_ACF at lag (ty rows, tx cols); NaN outside the lag plane.
    pub fn at(&self, ty: isize, tx: isize) -> f64 {
        let (ty, tx) = if ty < 0 { (-ty, -tx) } else { (ty, tx) };
        let (r, c) = (self.rows as isize, self.cols as isize);
        if ty >= r || tx <= -c || tx >= c {
            return f64::NAN;
        }
        self.half[ty as usize * (2 * self.cols - 1) + (tx + c - 1) as usize]
    }

    fn bilinear(&self, y: f64, x: f64) -> f64 {
        let (y0, x0) = (floor_lag(y), floor_lag(x));
        let (fy, fx) = (y - y0, x - x0);
        let (y0, x0) = (y0 as isize, x0 as isize);
        let v = |dy: isize, dx: isize| self.at(y0 + dy, x0 + dx);
        let top = if fx == 0.0 {
            v(0, 0)
        } else {
            v(0, 0) * (1.0 - fx) + v(0, 1) * fx
        };
        if fy == 0.0 {
            return top;
        }
        let bot = if fx == 0.0 {
            v(1, 0)
        } else {
            v(1, 0) * (1.0 - fx) + v(1, 1) * fx
        };
        top * (1.0 - fy) + bot * fy
    }

    /// (Sal um, Str) at threshold `s` (fraction of f_ACF(0)).
    pub fn sal_str(&self, s: f64) -> (f64, f64) {
        let thr = s * self.at(0, 0);
        if thr.is_nan() {
            return (f64::NAN, f64::NAN);
        }
        let (edges, touches) = self.region_edges(thr);
        if edges.is_empty() {
            return (f64::NAN, f64::NAN);
        }
        let (px, py) = (self.pitch_x_um, self.pitch_y_um);
        let dist =
            |(ey, ex): (isize, isize)| ((ey as f64 * py).powi(2) + (ex as f64 * px).powi(2)).sqrt();
        if !touches {
            // Str needs the longest decay as well as the shortest: every ray in full.
            let lengths: Vec<f64> = edges
                .par_iter()
                .map(|&e| self.decay_length(e, dist(e), thr, f64::INFINITY))
                .collect();
            let lo = lengths.iter().copied().fold(f64::INFINITY, f64::min);
            let hi = lengths.iter().copied().fold(0.0, f64::max);
            return (lo, lo / hi);
        }
        // Only the shortest decay is wanted (Str is undefined): the rays nearest to 0 first,
        // each left as soon as it can no longer be the shortest (see `decay_length`): the
        // same minimum as over every ray in full.
        let mut by_dist: Vec<(f64, (isize, isize))> = edges.iter().map(|&e| (dist(e), e)).collect();
        by_dist.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
        const FIRST: usize = 64;
        let mut lo = f64::INFINITY;
        for &(d, e) in by_dist.iter().take(FIRST) {
            lo = lo.min(self.decay_length(e, d, thr, lo));
        }
        // Lengths are >= 0: their bits order as they do.
        let best = AtomicU64::new(lo.to_bits());
        by_dist.par_iter().skip(FIRST).for_each(|&(d, e)| {
            let bound = f64::from_bits(best.load(AtomicOrdering::Relaxed));
            let len = self.decay_length(e, d, thr, bound);
            best.fetch_min(len.to_bits(), AtomicOrdering::Relaxed);
        });
        (f64::from_bits(best.into_inner()), f64::NAN)
    }

    /// The lags just outside the region of lags connected to 0 (4-neighbours) where f_ACF >
    /// `thr`, and whether the region reaches the border of the lag plane.
    fn region_edges(&self, thr: f64) -> (Vec<(isize, isize)>, bool) {
        let (ry, rx) = (self.rows as isize - 1, self.cols as isize - 1);
        let (h, w) = ((2 * ry + 1) as usize, (2 * rx + 1) as usize);
        let idx = |y: isize, x: isize| (y + ry) as usize * w + (x + rx) as usize;
        // Seen (in the region or on its edge), one bit per lag.
        let mut seen = vec![0u64; (h * w).div_ceil(64)];
        let mut see = |i: usize| {
            let (word, bit) = (i / 64, 1u64 << (i % 64));
            let new = seen[word] & bit == 0;
            seen[word] |= bit;
            new
        };
        let mut stack = vec![(0isize, 0isize)];
        see(idx(0, 0));
        let mut edges = Vec::new();
        let mut touches = false;
        while let Some((y, x)) = stack.pop() {
            if y.abs() == ry || x.abs() == rx {
                touches = true;
            }
            for (dy, dx) in [(-1, 0), (1, 0), (0, -1), (0, 1)] {
                let (ny, nx) = (y + dy, x + dx);
                if ny.abs() > ry || nx.abs() > rx {
                    continue;
                }
                if !see(idx(ny, nx)) {
                    continue;
                }
                if self.at(ny, nx) > thr {
                    stack.push((ny, nx));
                } else {
                    edges.push((ny, nx));
                }
            }
        }
        (edges, touches)
    }

    /// The decay length (um) along the ray from lag 0 to lag `e`, `dist` um long: the first
    /// point where the bilinear f_ACF falls to `thr`, refined linearly between the samples
    /// (2 per pixel); `dist` when it does not fall. The crossing after a sample t0 above the
    /// threshold is at (t0 + f (t - t0)) dist with 0 < f <= 1, never shorter than t0 dist:
    /// once that reaches `bound` the ray is left and infinity returned (it cannot be shorter
    /// than `bound`).
    fn decay_length(&self, (ey, ex): (isize, isize), dist: f64, thr: f64, bound: f64) -> f64 {
        let n = (2 * ey.abs().max(ex.abs())).max(4) as usize;
        let mut prev = (0.0, self.at(0, 0));
        for k in 1..=n {
            if prev.0 * dist >= bound {
                return f64::INFINITY;
            }
            let t = k as f64 / n as f64;
            let v = self.bilinear(t * ey as f64, t * ex as f64);
            if v <= thr {
                let (t0, v0) = prev;
                let f = if v0 > v { (v0 - thr) / (v0 - v) } else { 1.0 };
                return (t0 + f * (t - t0)) * dist;
            }
            prev = (t, v);
        }
        dist
    }
}

/// `v.floor()` for a lag (|v| far below 2^53) without the library call the baseline x86-64
/// target makes of `floor` (no SSE4.1 round): the truncation, one down for negative
/// fractions. The same value, so the same interpolation.
#[inline(always)]
fn floor_lag(v: f64) -> f64 {
    let t = v as i64 as f64;
    if t > v {
        t - 1.0
    } else {
        t
    }
}

/// The angular amplitude density in bins of `step_deg` (lower edges 0..180), from the DFT of
/// the centred (mean-filled) heights.
pub fn angular_amplitude(g: &Grid, step_deg: f64) -> Result<Vec<(f64, f64)>, MetrologyError> {
    let c = CentredRows::of(g)?;
    Ok(angular_from_spectrum(
        &spectrum2_of(&|r, buf: &mut [f64]| c.row(r, buf), g.rows(), g.cols()),
        g,
        step_deg,
    ))
}

pub(crate) fn angular_from_spectrum(
    spec: &[rustfft::num_complex::Complex<f64>],
    g: &Grid,
    step_deg: f64,
) -> Vec<(f64, f64)> {
    let (rows, cols) = (g.rows(), g.cols());
    let h = cols / 2 + 1;
    let bins = (180.0 / step_deg).ceil() as usize;
    let per_row: Vec<Vec<f64>> = (0..rows)
        .into_par_iter()
        .map(|ky| {
            let mut acc = vec![0.0; bins];
            let bin = |kx: usize| angular_bin(g, ky, kx, step_deg, bins);
            // Along a row the angle is monotone in kx (fy fixed, fx growing): a run of equal
            // bins is found by galloping and bisection, so atan2 is evaluated about twice per
            // bin boundary crossed instead of once per sample. The sums are the same, taken in
            // the same order (kx ascending within the row).
            let mut k = 0;
            while k < h {
                let b = bin(k);
                let (mut last, mut step) = (k, 1);
                let mut beyond = loop {
                    let t = last + step;
                    if t >= h {
                        break h;
                    }
                    if bin(t) != b {
                        break t;
                    }
                    last = t;
                    step *= 2;
                };
                while beyond - last > 1 {
                    let mid = last + (beyond - last) / 2;
                    if bin(mid) == b {
                        last = mid;
                    } else {
                        beyond = mid;
                    }
                }
                for kx in k..=last {
                    acc[b] += angular_weight(cols, kx) * spec[ky * h + kx].norm();
                }
                k = last + 1;
            }
            acc
        })
        .collect();
    let mut total = vec![0.0; bins];
    for row in &per_row {
        for (t, v) in total.iter_mut().zip(row) {
            *t += v;
        }
    }
    total
        .into_iter()
        .enumerate()
        .map(|(i, v)| (i as f64 * step_deg, v))
        .collect()
}

/// The weight of half-spectrum column kx: columns 1..cols/2 stand for their conjugate mirror
/// too (same |F|, same angle mod 180); column 0 and, for even cols, column cols/2 hold both
/// signs already.
fn angular_weight(cols: usize, kx: usize) -> f64 {
    if kx == 0 || (cols.is_multiple_of(2) && kx == cols / 2) {
        1.0
    } else {
        2.0
    }
}

/// The angular bin of DFT sample (ky, kx): the direction of its frequency vector (1/um), mod
/// 180 degrees, in bins of `step_deg`.
fn angular_bin(g: &Grid, ky: usize, kx: usize, step_deg: f64, bins: usize) -> usize {
    let rows = g.rows();
    let ky_s = if ky <= rows / 2 {
        ky as f64
    } else {
        ky as f64 - rows as f64
    };
    let fy = ky_s / (rows as f64 * g.pitch_y_um());
    let fx = kx as f64 / (g.cols() as f64 * g.pitch_x_um());
    let theta = fy.atan2(fx).to_degrees().rem_euclid(180.0);
    ((theta / step_deg) as usize).min(bins - 1)
}

/// Std from an angular density: the lower edge of its largest bin (first on ties).
pub(crate) fn std_from_angular(a: &[(f64, f64)]) -> f64 {
    let mut best = (f64::NEG_INFINITY, f64::NAN);
    for &(t, v) in a {
        if v > best.0 {
            best = (v, t);
        }
    }
    best.1
}

/// Sal, Str and Std of `g`.
pub fn spatial_params(g: &Grid) -> Result<SpatialParams, MetrologyError> {
    let acf = Acf::of(g)?;
    let (sal, str_) = acf.sal_str(ACF_THRESHOLD);
    // The lag plane (twice the map) goes before the spectrum is made.
    drop(acf);
    let std = std_from_angular(&angular_amplitude(g, STD_STEP_DEG)?);
    Ok(SpatialParams { sal, str_, std })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Heights of a wavy, tilted surface with noise (xorshift), rows x cols.
    fn surface(rows: usize, cols: usize, tilt: f64, seed: u64) -> Vec<f64> {
        let mut state = seed | 1;
        (0..rows * cols)
            .map(|k| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                let noise = (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5;
                let (r, c) = ((k / cols) as f64, (k % cols) as f64);
                (0.21 * c + 0.05 * r).sin()
                    + 0.6 * (0.07 * c - 0.13 * r).cos()
                    + tilt * (c + 0.3 * r)
                    + 0.3 * noise
            })
            .collect()
    }

    /// The angular density, one atan2 per DFT sample: the reference the run search must equal.
    fn angular_per_sample(g: &Grid, step_deg: f64) -> Vec<f64> {
        let c = CentredRows::of(g).unwrap();
        let spec = spectrum2_of(&|r, buf: &mut [f64]| c.row(r, buf), g.rows(), g.cols());
        let (rows, cols) = (g.rows(), g.cols());
        let h = cols / 2 + 1;
        let bins = (180.0 / step_deg).ceil() as usize;
        let mut total = vec![0.0; bins];
        for ky in 0..rows {
            let mut acc = vec![0.0; bins];
            for kx in 0..h {
                let b = angular_bin(g, ky, kx, step_deg, bins);
                acc[b] += angular_weight(cols, kx) * spec[ky * h + kx].norm();
            }
            for (t, v) in total.iter_mut().zip(&acc) {
                *t += v;
            }
        }
        total
    }

    /// Bin runs found by bisection give the per-sample sums bit for bit: odd and even sizes,
    /// square and non-square pitches, a coarse and the default step.
    #[test]
    fn angular_runs_equal_per_sample_bins() {
        for &(rows, cols, px, py) in &[(64, 64, 1.0, 1.0), (61, 90, 0.4, 1.3), (128, 37, 2.0, 0.5)]
        {
            let z = surface(rows, cols, 0.0, (rows * cols) as u64);
            let g = Grid::new(&z, rows, cols, px, py).unwrap();
            for step in [STD_STEP_DEG, 7.0] {
                let fast: Vec<u64> = angular_amplitude(&g, step)
                    .unwrap()
                    .iter()
                    .map(|p| p.1.to_bits())
                    .collect();
                let each: Vec<u64> = angular_per_sample(&g, step)
                    .iter()
                    .map(|v| v.to_bits())
                    .collect();
                assert_eq!(
                    fast, each,
                    "{rows} x {cols}, pitch {px} x {py}, step {step}"
                );
            }
        }
    }

    /// Sal from rays left early (Str undefined) is the minimum over every ray in full, to the
    /// bit; and a region inside the plane still gives Str from every ray.
    #[test]
    fn early_left_rays_give_the_full_minimum() {
        let mut touched = 0;
        for &(rows, cols, px, py, tilt) in &[
            (96, 96, 1.0, 1.0, 0.08),
            (70, 120, 0.5, 1.5, 0.05),
            (96, 96, 1.0, 1.0, 0.0),
        ] {
            let z = surface(rows, cols, tilt, 7 + rows as u64);
            let g = Grid::new(&z, rows, cols, px, py).unwrap();
            let acf = Acf::of(&g).unwrap();
            let thr = ACF_THRESHOLD * acf.at(0, 0);
            let (edges, touches) = acf.region_edges(thr);
            assert!(!edges.is_empty());
            let full: Vec<f64> = edges
                .iter()
                .map(|&(ey, ex)| {
                    let d = ((ey as f64 * py).powi(2) + (ex as f64 * px).powi(2)).sqrt();
                    acf.decay_length((ey, ex), d, thr, f64::INFINITY)
                })
                .collect();
            let lo = full.iter().copied().fold(f64::INFINITY, f64::min);
            let hi = full.iter().copied().fold(0.0, f64::max);
            let (sal, str_) = acf.sal_str(ACF_THRESHOLD);
            assert_eq!(sal.to_bits(), lo.to_bits(), "{rows} x {cols} tilt {tilt}");
            if touches {
                touched += 1;
                assert!(str_.is_nan());
            } else {
                assert_eq!(str_.to_bits(), (lo / hi).to_bits());
            }
        }
        assert!(
            touched >= 1,
            "no case reached the border: the early exit went untested"
        );
    }

    /// The floor without the library call is floor.
    #[test]
    fn floor_lag_is_floor() {
        for v in [
            -3.5,
            -3.0,
            -0.25,
            -0.0,
            0.0,
            0.25,
            1.0,
            2.999,
            1e6 + 0.5,
            -1e6 - 0.5,
        ] {
            assert_eq!(floor_lag(v), v.floor(), "{v}");
        }
    }
}
