//! The ISO 16610-61 areal Gaussian filter.
//!
//! Weighting function (ISO 16610-61, eq. 1, one axis):
//! `s(x) = exp(-pi (x / (alpha lambda_c))^2) / (alpha lambda_c)`, `alpha = sqrt(ln 2 / pi)`;
//! the areal one is `s(x) s(y)`, so the filter is two 1-D passes. Its amplitude transmission
//! is `exp(-pi (alpha lambda_c / lambda)^2)`: 50 % at `lambda = lambda_c`. As a sampled
//! Gaussian of standard deviation `sigma = alpha lambda_c / sqrt(2 pi)` it is what
//! `scipy.ndimage.gaussian_filter` computes with `sigma_px = alpha lambda_c / (sqrt(2 pi)
//! pitch)` ([`sigma_px`]), away from the edges.
//!
//! # Sampling and truncation
//! The weights are sampled at the pitch for `|x| <= lambda_c` (where `s` has fallen to
//! `exp(-pi / alpha^2) = 6.5e-7` of its peak) and normalised to sum 1.
//!
//! # End effects and missing points
//! The output at a point is the weighted mean over the *measured points of the field* only:
//! `out = sum(s w z) / sum(s w)` with `w = 1` for a measured point and 0 for a missing one or
//! one outside the map (the normalised Gaussian, ISO 16610-28's zeroth-order end-effect
//! correction). A constant surface is therefore kept exactly up to the edges and around holes;
//! a tilted plane is kept exactly where the support is symmetric (away from edges and holes)
//! and pulled towards the inside by `slope x (centroid shift of the weights)` near them, which
//! is why [`crate::filter::scale_limited`] removes the form before the L-filter.
//! `sum(s w)` is the point's *support* (1 = a full field); the output is NaN where the input is
//! not measured (the filter's value there would be an interpolation, not a measurement) and
//! where the support is below [`MIN_SUPPORT`]. Holes therefore never grow: every measured point
//! keeps a value.
//!
//! # Speed
//! Each 1-D pass is an FFT convolution per line (rustfft), zero-padded to a linear convolution;
//! numerator `s w z` and denominator `s w` ride together as the real and imaginary parts of
//! one complex line (the kernel is real and even, so its spectrum is real and the two never
//! mix). The cost is independent of `lambda_c`; lines run in parallel on rayon's pool.

use std::sync::Arc;

use rayon::prelude::*;
use rustfft::num_complex::Complex32;
use rustfft::{Fft, FftPlanner};

use super::{FilterError, Grid};
use crate::fft::fast_len;

/// `sqrt(ln 2 / pi)`: the constant of the Gaussian weighting function (ISO 16610-61).
pub const ALPHA: f64 = 0.469_718_639_349_825_8;

/// Support (the share of a full field's weights that fell on measured points) below which the
/// Gaussian filter's output is NaN. A map corner has 0.25; a point inside a hole-riddled
/// region can have less, and below 5 % its mean rests on a handful of points at the kernel's
/// rim.
pub const MIN_SUPPORT: f64 = 0.05;

/// The kernel spans at most this many pitches each side (a guard against absurd cutoffs).
const MAX_HALF_WIDTH: f64 = 1e7;

/// ISO 16610-61's weighting function `s(x)` (1/µm) at `x_um` for cutoff `cutoff_um`.
pub fn weighting_function(x_um: f64, cutoff_um: f64) -> f64 {
    let a = ALPHA * cutoff_um;
    (-std::f64::consts::PI * (x_um / a).powi(2)).exp() / a
}

/// The standard deviation in pixels of the Gaussian with cutoff `cutoff_um` sampled at
/// `pitch_um`: `alpha lambda_c / (sqrt(2 pi) pitch)` (what to hand `scipy.ndimage`).
pub fn sigma_px(cutoff_um: f64, pitch_um: f64) -> f64 {
    ALPHA * cutoff_um / ((2.0 * std::f64::consts::PI).sqrt() * pitch_um)
}

/// A weighted mean and its support, row-major like the input.
#[derive(Debug, Clone, PartialEq)]
pub struct WeightedMean {
    /// `sum(s w z) / sum(s w)`; NaN where the support is below the threshold asked for.
    pub mean: Vec<f32>,
    /// `sum(s w)` with `s` normalised to sum 1: 1 inside a fully measured field.
    pub support: Vec<f32>,
}

/// One axis of the separable filter for lines of `n` samples: the kernel's spectrum at the
/// padded length and the FFT plans.
struct AxisPass {
    n: usize,
    fft_len: usize,
    forward: Arc<dyn Fft<f32>>,
    inverse: Arc<dyn Fft<f32>>,
    /// Real spectrum of the centred kernel, already divided by `fft_len`.
    kernel_hat: Vec<f32>,
    scratch_len: usize,
}

impl AxisPass {
    fn new(
        planner: &mut FftPlanner<f32>,
        n: usize,
        cutoff_um: f64,
        pitch_um: f64,
    ) -> Result<Self, FilterError> {
        let half = (cutoff_um / pitch_um).ceil();
        if !(half.is_finite() && half <= MAX_HALF_WIDTH) {
            return Err(FilterError::BadValue {
                name: "cutoff_um",
                value: cutoff_um,
                expected: "a cutoff of at most 1e7 pitches",
            });
        }
        let half = (half as usize).max(1);
        let weights: Vec<f64> = (0..=half)
            .map(|j| weighting_function(j as f64 * pitch_um, cutoff_um))
            .collect();
        let sum = weights[0] + 2.0 * weights[1..].iter().sum::<f64>();
        // Taps further than n - 1 never meet a sample: leave them out of the padding.
        let reach = half.min(n.saturating_sub(1));
        let fft_len = fast_len(n + reach);
        let mut k = vec![Complex32::default(); fft_len];
        k[0].re = (weights[0] / sum) as f32;
        for (j, w) in weights.iter().enumerate().take(reach + 1).skip(1) {
            let w = (w / sum) as f32;
            k[j].re = w;
            k[fft_len - j].re = w;
        }
        let forward = planner.plan_fft_forward(fft_len);
        let inverse = planner.plan_fft_inverse(fft_len);
        forward.process(&mut k);
        let scale = 1.0 / fft_len as f32;
        let kernel_hat = k.iter().map(|c| c.re * scale).collect();
        let scratch_len = forward
            .get_inplace_scratch_len()
            .max(inverse.get_inplace_scratch_len());
        Ok(Self {
            n,
            fft_len,
            forward,
            inverse,
            kernel_hat,
            scratch_len,
        })
    }

    /// Convolves every line of `data` (lines of `n`) with the kernel, in place.
    fn run(&self, data: &mut [Complex32]) {
        let zero = Complex32::default();
        data.par_chunks_mut(self.n).for_each_init(
            || {
                (
                    vec![zero; self.fft_len],
                    vec![zero; self.scratch_len.max(1)],
                )
            },
            |(buf, scratch), line| {
                // A line without any weight stays zero: skip its FFTs.
                if line.iter().all(|v| v.im == 0.0 && v.re == 0.0) {
                    return;
                }
                buf[..self.n].copy_from_slice(line);
                buf[self.n..].fill(zero);
                self.forward.process_with_scratch(buf, scratch);
                for (b, &k) in buf.iter_mut().zip(&self.kernel_hat) {
                    *b *= k;
                }
                self.inverse.process_with_scratch(buf, scratch);
                line.copy_from_slice(&buf[..self.n]);
            },
        );
    }
}

/// `dst` (cols x rows) = transpose of `src` (rows x cols), in column bands so reads stay
/// contiguous and writes stay within a few cache lines per row.
fn transpose(src: &[Complex32], rows: usize, cols: usize, dst: &mut [Complex32]) {
    const BAND: usize = 16;
    dst.par_chunks_mut(BAND * rows)
        .enumerate()
        .for_each(|(b, band)| {
            let c0 = b * BAND;
            let width = band.len() / rows;
            for r in 0..rows {
                let line = &src[r * cols + c0..r * cols + c0 + width];
                for (k, &v) in line.iter().enumerate() {
                    band[k * rows + r] = v;
                }
            }
        });
}

/// An areal Gaussian filter planned for one grid and cutoff; apply it to any number of maps
/// of that grid (the robust filter applies it once per iteration).
pub struct GaussianFilter {
    grid: Grid,
    cutoff_um: f64,
    rows_pass: AxisPass,
    cols_pass: AxisPass,
}

impl GaussianFilter {
    /// Plans the filter with cutoff `cutoff_um` (`lambda_c` or `lambda_s`, µm) for `grid`.
    pub fn new(grid: Grid, cutoff_um: f64) -> Result<Self, FilterError> {
        grid.check(grid.rows.saturating_mul(grid.cols))?;
        if !(cutoff_um.is_finite() && cutoff_um > 0.0) {
            return Err(FilterError::BadValue {
                name: "cutoff_um",
                value: cutoff_um,
                expected: "a positive cutoff wavelength in µm",
            });
        }
        let mut planner = FftPlanner::new();
        Ok(Self {
            grid,
            cutoff_um,
            rows_pass: AxisPass::new(&mut planner, grid.cols, cutoff_um, grid.pitch_x_um)?,
            cols_pass: AxisPass::new(&mut planner, grid.rows, cutoff_um, grid.pitch_y_um)?,
        })
    }

    /// The cutoff wavelength, µm.
    pub fn cutoff_um(&self) -> f64 {
        self.cutoff_um
    }

    /// The grid the filter was planned for.
    pub fn grid(&self) -> Grid {
        self.grid
    }

    /// The Gaussian mean surface of `heights` (NaN = not measured; module doc for the
    /// end-effect and NaN rules).
    pub fn apply(&self, heights: &[f32]) -> Result<Vec<f32>, FilterError> {
        self.grid.check(heights.len())?;
        let weights: Vec<f32> = heights
            .par_iter()
            .map(|z| if z.is_finite() { 1.0 } else { 0.0 })
            .collect();
        let m = self.weighted_mean(heights, &weights, MIN_SUPPORT)?;
        Ok(m.mean)
    }

    /// `sum(s w z) / sum(s w)` over the field, for weights `w >= 0` (a point whose height is
    /// not finite counts with weight 0). The mean is NaN where `z` is not finite or where the
    /// support `sum(s w)` is below `min_support`.
    pub fn weighted_mean(
        &self,
        heights: &[f32],
        weights: &[f32],
        min_support: f64,
    ) -> Result<WeightedMean, FilterError> {
        let Grid { rows, cols, .. } = self.grid;
        self.grid.check(heights.len())?;
        self.grid.check(weights.len())?;
        // Filter around the weighted mean height: f32 then keeps µm-scale detail even for
        // maps that sit tens of µm up.
        let (sw, swz) = heights
            .par_iter()
            .zip(weights)
            .filter(|(z, w)| z.is_finite() && w.is_finite() && **w > 0.0)
            .map(|(&z, &w)| (f64::from(w), f64::from(w) * f64::from(z)))
            .reduce(|| (0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1));
        if sw <= 0.0 {
            return Err(FilterError::AllNan);
        }
        let offset = swz / sw;
        let mut a: Vec<Complex32> = heights
            .par_iter()
            .zip(weights)
            .map(|(&z, &w)| {
                if z.is_finite() && w.is_finite() && w > 0.0 {
                    Complex32::new(w * (f64::from(z) - offset) as f32, w)
                } else {
                    Complex32::default()
                }
            })
            .collect();
        self.rows_pass.run(&mut a);
        let mut t = vec![Complex32::default(); a.len()];
        transpose(&a, rows, cols, &mut t);
        self.cols_pass.run(&mut t);
        transpose(&t, cols, rows, &mut a);
        drop(t);
        let floor = min_support.max(1e-6) as f32;
        let (mean, support): (Vec<f32>, Vec<f32>) = a
            .par_iter()
            .zip(heights)
            .map(|(v, &z)| {
                let m = if z.is_finite() && v.im >= floor {
                    (f64::from(v.re / v.im) + offset) as f32
                } else {
                    f32::NAN
                };
                (m, v.im.max(0.0))
            })
            .unzip();
        Ok(WeightedMean { mean, support })
    }
}

/// The ISO 16610-61 Gaussian mean surface of `heights` with cutoff `cutoff_um`: the L-filter's
/// output for `lambda_c`, the S-filter's output (the primary surface) for `lambda_s`.
pub fn gaussian_filter(
    heights: &[f32],
    grid: Grid,
    cutoff_um: f64,
) -> Result<Vec<f32>, FilterError> {
    GaussianFilter::new(grid, cutoff_um)?.apply(heights)
}

/// The Gaussian weighted mean with weights `weights` ([`GaussianFilter::weighted_mean`]).
pub fn normalised_gaussian(
    heights: &[f32],
    weights: &[f32],
    grid: Grid,
    cutoff_um: f64,
    min_support: f64,
) -> Result<WeightedMean, FilterError> {
    GaussianFilter::new(grid, cutoff_um)?.weighted_mean(heights, weights, min_support)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn alpha_and_sigma() {
        let a = (std::f64::consts::LN_2 / std::f64::consts::PI).sqrt();
        assert!((ALPHA - a).abs() < 1e-15);
        // The weighting function integrates to 1.
        let dx = 0.01;
        let s: f64 = (-2000..=2000)
            .map(|i| weighting_function(i as f64 * dx, 8.0) * dx)
            .sum();
        assert!((s - 1.0).abs() < 1e-9, "{s}");
        // sigma = lambda_c sqrt(ln 2 / 2) / pi (the form surfalize 0.19 uses).
        let want = 80.0 * (std::f64::consts::LN_2 / 2.0).sqrt() / std::f64::consts::PI / 0.5;
        assert!((sigma_px(80.0, 0.5) - want).abs() < 1e-12);
    }

    #[test]
    fn refuses_bad_arguments() {
        let g = Grid::square(4, 5, 1.0);
        assert!(GaussianFilter::new(g, 0.0).is_err());
        assert!(GaussianFilter::new(g, f64::NAN).is_err());
        assert!(GaussianFilter::new(g, 1e30).is_err());
        assert!(GaussianFilter::new(Grid::square(0, 5, 1.0), 3.0).is_err());
        assert!(GaussianFilter::new(Grid::square(4, 5, -1.0), 3.0).is_err());
        let f = GaussianFilter::new(g, 3.0).unwrap();
        assert!(f.apply(&[0.0; 19]).is_err());
        assert_eq!(f.apply(&[f32::NAN; 20]), Err(FilterError::AllNan));
    }

    #[test]
    fn a_constant_stays_constant_to_the_edges_and_around_holes() {
        let g = Grid::square(37, 53, 0.5);
        let mut h = vec![4.25f32; 37 * 53];
        for r in 10..20 {
            h[r * 53 + 20..r * 53 + 31].fill(f32::NAN);
        }
        let out = gaussian_filter(&h, g, 6.0).unwrap();
        for (o, z) in out.iter().zip(&h) {
            if z.is_nan() {
                assert!(o.is_nan());
            } else {
                assert!((o - 4.25).abs() < 1e-5, "{o}");
            }
        }
    }
}
