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
        let (y0, x0) = (y.floor(), x.floor());
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
        if edges.is_empty() {
            return (f64::NAN, f64::NAN);
        }
        let (px, py) = (self.pitch_x_um, self.pitch_y_um);
        let lengths: Vec<f64> = edges
            .par_iter()
            .map(|&(ey, ex)| {
                let dist = ((ey as f64 * py).powi(2) + (ex as f64 * px).powi(2)).sqrt();
                let n = (2 * ey.abs().max(ex.abs())).max(4) as usize;
                let mut prev = (0.0, self.at(0, 0));
                for k in 1..=n {
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
            })
            .collect();
        let lo = lengths.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = lengths.iter().copied().fold(0.0, f64::max);
        (lo, if touches { f64::NAN } else { lo / hi })
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
            let ky_s = if ky <= rows / 2 {
                ky as f64
            } else {
                ky as f64 - rows as f64
            };
            let fy = ky_s / (rows as f64 * g.pitch_y_um());
            for kx in 0..h {
                // Columns 1..cols/2 stand for their conjugate mirror too (same |F|, same angle
                // mod 180); column 0 and, for even cols, column cols/2 hold both signs already.
                let weight = if kx == 0 || (cols.is_multiple_of(2) && kx == cols / 2) {
                    1.0
                } else {
                    2.0
                };
                let fx = kx as f64 / (cols as f64 * g.pitch_x_um());
                let theta = fy.atan2(fx).to_degrees().rem_euclid(180.0);
                let b = ((theta / step_deg) as usize).min(bins - 1);
                acc[b] += weight * spec[ky * h + kx].norm();
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
