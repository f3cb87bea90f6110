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

use super::FilterError;
use crate::fft::fast_len;
use crate::sampling::Sampling;
use crate::ParamError;

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
    /// Normalised weights at 0, 1, ..., reach pitches.
    weights: Vec<f64>,
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
            return Err(FilterError::from(ParamError::new(
                "cutoff_um",
                cutoff_um,
                "a cutoff of at most 1e7 pitches",
            )));
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
            weights: weights[..=reach].iter().map(|w| w / sum).collect(),
            scratch_len,
        })
    }

    /// A line buffer and FFT scratch for [`AxisPass::convolve`].
    fn buffers(&self) -> (Vec<Complex32>, Vec<Complex32>) {
        let zero = Complex32::default();
        (
            vec![zero; self.fft_len],
            vec![zero; self.scratch_len.max(1)],
        )
    }

    /// The kernel's sum over the in-field samples at every position of a fully measured line
    /// (1 in the middle, about 1/2 at the ends).
    fn edge_support(&self) -> Vec<f32> {
        let w = &self.weights;
        let reach = w.len() - 1;
        (0..self.n)
            .map(|i| {
                let left = i.min(reach);
                let right = (self.n - 1 - i).min(reach);
                let s = w[0] + w[1..=left].iter().sum::<f64>() + w[1..=right].iter().sum::<f64>();
                s as f32
            })
            .collect()
    }

    /// Convolves the line in `buf[..n]` with the kernel, in place; `buf[n..]` is zeroed first
    /// (the padding that makes the circular convolution a linear one).
    fn convolve(&self, buf: &mut [Complex32], scratch: &mut [Complex32]) {
        buf[self.n..].fill(Complex32::default());
        self.forward.process_with_scratch(buf, scratch);
        for (b, &k) in buf.iter_mut().zip(&self.kernel_hat) {
            *b *= k;
        }
        self.inverse.process_with_scratch(buf, scratch);
    }
}

/// Columns per block of the column pass: a block's lines stay in cache between the gather,
/// the FFTs and the scatter.
const COLUMN_BLOCK: usize = 16;

/// A raw pointer to an output raster that column blocks write through, each its own columns.
#[derive(Clone, Copy)]
struct ColumnsOut(*mut f32);
// SAFETY: the column pass hands every block a disjoint set of columns, so no two threads write
// the same element, and the vectors outlive the parallel loop.
unsafe impl Send for ColumnsOut {}
unsafe impl Sync for ColumnsOut {}

impl ColumnsOut {
    /// Writes `v` at `i`.
    ///
    /// # Safety
    /// `i` is inside the raster and no other thread writes `i` (its column is this block's).
    unsafe fn write(self, i: usize, v: f32) {
        // SAFETY: as the caller promises.
        unsafe { *self.0.add(i) = v }
    }
}

/// An areal Gaussian filter planned for one grid and cutoff; apply it to any number of maps
/// of that grid (the robust filter applies it once per iteration).
pub struct GaussianFilter {
    grid: Sampling,
    cutoff_um: f64,
    rows_pass: AxisPass,
    cols_pass: AxisPass,
}

impl GaussianFilter {
    /// Plans the filter with cutoff `cutoff_um` (`lambda_c` or `lambda_s`, µm) for `grid`.
    pub fn new(grid: Sampling, cutoff_um: f64) -> Result<Self, FilterError> {
        grid.shape()
            .check(grid.rows().saturating_mul(grid.cols()))?;
        if !(cutoff_um.is_finite() && cutoff_um > 0.0) {
            return Err(FilterError::from(ParamError::new(
                "cutoff_um",
                cutoff_um,
                "a positive cutoff wavelength in µm",
            )));
        }
        let mut planner = FftPlanner::new();
        Ok(Self {
            grid,
            cutoff_um,
            rows_pass: AxisPass::new(&mut planner, grid.cols(), cutoff_um, grid.pitch_x_um())?,
            cols_pass: AxisPass::new(&mut planner, grid.rows(), cutoff_um, grid.pitch_y_um())?,
        })
    }

    /// The cutoff wavelength, µm.
    pub fn cutoff_um(&self) -> f64 {
        self.cutoff_um
    }

    /// The grid the filter was planned for.
    pub fn grid(&self) -> Sampling {
        self.grid
    }

    /// The Gaussian mean surface of `heights` (NaN = not measured; module doc for the
    /// end-effect and NaN rules).
    pub fn apply(&self, heights: &[f32]) -> Result<Vec<f32>, FilterError> {
        Ok(self.run(heights, None, MIN_SUPPORT, false)?.0)
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
        self.grid.shape().check(weights.len())?;
        let (mean, support) = self.run(heights, Some(weights), min_support, true)?;
        Ok(WeightedMean {
            mean,
            support: support.unwrap_or_default(),
        })
    }

    /// The weighted mean (weights `None`: 1 on every finite height) and, if asked, the support.
    fn run(
        &self,
        heights: &[f32],
        weights: Option<&[f32]>,
        min_support: f64,
        want_support: bool,
    ) -> Result<(Vec<f32>, Option<Vec<f32>>), FilterError> {
        let (rows, cols) = (self.grid.rows(), self.grid.cols());
        self.grid.shape().check(heights.len())?;
        let weight = |i: usize, z: f32| -> f32 {
            let w = weights.map_or(1.0, |w| w[i]);
            if z.is_finite() && w.is_finite() && w > 0.0 {
                w
            } else {
                0.0
            }
        };
        // Filter around the weighted mean height: f32 then keeps µm-scale detail even for
        // maps that sit tens of µm up.
        // Summed in fixed blocks, and the blocks in order, so the mean (and with it every
        // output bit) does not depend on how rayon splits the work.
        const BLOCK: usize = 1 << 14;
        let (sw, swz) = heights
            .par_chunks(BLOCK)
            .enumerate()
            .map(|(b, block)| {
                block
                    .iter()
                    .enumerate()
                    .fold((0.0, 0.0), |(sw, swz), (k, &z)| {
                        let w = f64::from(weight(b * BLOCK + k, z));
                        if w > 0.0 {
                            (sw + w, swz + w * f64::from(z))
                        } else {
                            (sw, swz)
                        }
                    })
            })
            .collect::<Vec<(f64, f64)>>()
            .into_iter()
            .fold((0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1));
        if sw <= 0.0 {
            return Err(FilterError::AllNan);
        }
        let offset = swz / sw;
        if weights.is_none() && sw == (rows * cols) as f64 {
            return Ok(self.run_complete(heights, offset, min_support, want_support));
        }

        // Pass 1, rows: (w (z - offset), w) as one complex line, convolved along x.
        let zero = Complex32::default();
        let mut a = vec![zero; rows * cols];
        a.par_chunks_mut(cols).enumerate().for_each_init(
            || self.rows_pass.buffers(),
            |(buf, scratch), (r, line)| {
                let mut any = false;
                for (c, b) in buf[..cols].iter_mut().enumerate() {
                    let i = r * cols + c;
                    let z = heights[i];
                    let w = weight(i, z);
                    any |= w > 0.0;
                    *b = Complex32::new(w * (f64::from(z) - offset) as f32, w);
                    if w == 0.0 {
                        b.re = 0.0;
                    }
                }
                // A row without any weight stays zero: skip its FFTs.
                if any {
                    self.rows_pass.convolve(buf, scratch);
                    line.copy_from_slice(&buf[..cols]);
                }
            },
        );

        // Pass 2, columns in blocks: gather, convolve along y, and write mean (and support)
        // straight into the outputs.
        let mut mean = vec![f32::NAN; rows * cols];
        let mut support = if want_support {
            vec![0.0f32; rows * cols]
        } else {
            Vec::new()
        };
        let mean_out = ColumnsOut(mean.as_mut_ptr());
        let support_out = want_support.then_some(ColumnsOut(support.as_mut_ptr()));
        let floor = min_support.max(1e-6) as f32;
        let n_blocks = cols.div_ceil(COLUMN_BLOCK);
        (0..n_blocks).into_par_iter().for_each_init(
            || {
                let (b, s) = self.cols_pass.buffers();
                (vec![b; COLUMN_BLOCK], s)
            },
            |(bufs, scratch), block| {
                let c0 = block * COLUMN_BLOCK;
                let width = COLUMN_BLOCK.min(cols - c0);
                for r in 0..rows {
                    for (k, v) in a[r * cols + c0..r * cols + c0 + width].iter().enumerate() {
                        bufs[k][r] = *v;
                    }
                }
                for buf in bufs.iter_mut().take(width) {
                    self.cols_pass.convolve(buf, scratch);
                }
                // Row by row, so each output row is written as one contiguous run.
                for r in 0..rows {
                    for (k, buf) in bufs.iter().take(width).enumerate() {
                        let i = r * cols + c0 + k;
                        let (z, v) = (heights[i], buf[r]);
                        let m = if z.is_finite() && v.im >= floor {
                            (f64::from(v.re / v.im) + offset) as f32
                        } else {
                            f32::NAN
                        };
                        // SAFETY: i < rows * cols = the outputs' length, and column c0 + k
                        // belongs to this block only (see ColumnsOut).
                        unsafe {
                            mean_out.write(i, m);
                            if let Some(s) = support_out {
                                s.write(i, v.im.max(0.0));
                            }
                        }
                    }
                }
            },
        );
        Ok((mean, want_support.then_some(support)))
    }

    /// [`Self::run`] for a fully measured map with unit weights: the support is the product of
    /// the two axes' in-field kernel sums, so only numerators are convolved, two real lines per
    /// complex FFT (half the FFTs and half the memory of the general case).
    fn run_complete(
        &self,
        heights: &[f32],
        offset: f64,
        min_support: f64,
        want_support: bool,
    ) -> (Vec<f32>, Option<Vec<f32>>) {
        let (rows, cols) = (self.grid.rows(), self.grid.cols());
        let zero = Complex32::default();
        // Pass 1: rows 2p and 2p + 1 as the real and imaginary part of line p.
        let pairs = rows.div_ceil(2);
        let mut a = vec![zero; pairs * cols];
        a.par_chunks_mut(cols).enumerate().for_each_init(
            || self.rows_pass.buffers(),
            |(buf, scratch), (p, line)| {
                let upper = &heights[2 * p * cols..(2 * p + 1) * cols];
                let lower = heights.get((2 * p + 1) * cols..(2 * p + 2) * cols);
                for (c, b) in buf[..cols].iter_mut().enumerate() {
                    let im = lower.map_or(0.0, |l| (f64::from(l[c]) - offset) as f32);
                    *b = Complex32::new((f64::from(upper[c]) - offset) as f32, im);
                }
                self.rows_pass.convolve(buf, scratch);
                line.copy_from_slice(&buf[..cols]);
            },
        );
        let support_y = self.cols_pass.edge_support();
        let support_x = self.rows_pass.edge_support();
        // Pass 2: columns 2q and 2q + 1 as one complex line, in blocks.
        let mut mean = vec![0.0f32; rows * cols];
        let mut support = if want_support {
            vec![0.0f32; rows * cols]
        } else {
            Vec::new()
        };
        let mean_out = ColumnsOut(mean.as_mut_ptr());
        let support_out = want_support.then_some(ColumnsOut(support.as_mut_ptr()));
        let floor = min_support.max(1e-6) as f32;
        (0..cols.div_ceil(COLUMN_BLOCK))
            .into_par_iter()
            .for_each_init(
                || {
                    let (b, s) = self.cols_pass.buffers();
                    (vec![b; COLUMN_BLOCK / 2], s)
                },
                |(bufs, scratch), block| {
                    let c0 = block * COLUMN_BLOCK;
                    let width = COLUMN_BLOCK.min(cols - c0);
                    let lines = width.div_ceil(2);
                    for r in 0..rows {
                        let row = &a[(r / 2) * cols + c0..(r / 2) * cols + c0 + width];
                        let pick = |v: &Complex32| if r % 2 == 0 { v.re } else { v.im };
                        for (q, buf) in bufs.iter_mut().take(lines).enumerate() {
                            let im = row.get(2 * q + 1).map_or(0.0, pick);
                            buf[r] = Complex32::new(pick(&row[2 * q]), im);
                        }
                    }
                    for buf in bufs.iter_mut().take(lines) {
                        self.cols_pass.convolve(buf, scratch);
                    }
                    for (r, &sy) in support_y.iter().enumerate() {
                        for k in 0..width {
                            let i = r * cols + c0 + k;
                            let v = bufs[k / 2][r];
                            let num = if k % 2 == 0 { v.re } else { v.im };
                            let den = sy * support_x[c0 + k];
                            let m = if den >= floor {
                                (f64::from(num / den) + offset) as f32
                            } else {
                                f32::NAN
                            };
                            // SAFETY: i < rows * cols = the outputs' length, and column
                            // c0 + k belongs to this block only (see ColumnsOut).
                            unsafe {
                                mean_out.write(i, m);
                                if let Some(s) = support_out {
                                    s.write(i, den);
                                }
                            }
                        }
                    }
                },
            );
        (mean, want_support.then_some(support))
    }
}

/// The ISO 16610-61 Gaussian mean surface of `heights` with cutoff `cutoff_um`: the L-filter's
/// output for `lambda_c`, the S-filter's output (the primary surface) for `lambda_s`.
pub fn gaussian_filter(
    heights: &[f32],
    grid: Sampling,
    cutoff_um: f64,
) -> Result<Vec<f32>, FilterError> {
    GaussianFilter::new(grid, cutoff_um)?.apply(heights)
}

/// The Gaussian weighted mean with weights `weights` ([`GaussianFilter::weighted_mean`]).
pub fn normalised_gaussian(
    heights: &[f32],
    weights: &[f32],
    grid: Sampling,
    cutoff_um: f64,
    min_support: f64,
) -> Result<WeightedMean, FilterError> {
    GaussianFilter::new(grid, cutoff_um)?.weighted_mean(heights, weights, min_support)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Shape;

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
        let g = Sampling::square(Shape::new(4, 5), 1.0).unwrap();
        assert!(GaussianFilter::new(g, 0.0).is_err());
        assert!(GaussianFilter::new(g, f64::NAN).is_err());
        assert!(GaussianFilter::new(g, 1e30).is_err());
        assert!(
            GaussianFilter::new(Sampling::square(Shape::new(0, 5), 1.0).unwrap(), 3.0).is_err()
        );
        assert!(Sampling::square(Shape::new(4, 5), -1.0).is_err());
        let f = GaussianFilter::new(g, 3.0).unwrap();
        assert!(f.apply(&[0.0; 19]).is_err());
        assert_eq!(f.apply(&[f32::NAN; 20]), Err(FilterError::AllNan));
    }

    #[test]
    fn the_complete_map_shortcut_equals_the_general_path() {
        // Odd sizes: the last row / column rides alone in its complex line.
        let g = Sampling::new(Shape::new(41, 29), 0.5, 0.7).unwrap();
        let h: Vec<f32> = (0..41 * 29)
            .map(|i| ((i % 29) as f32 * 0.4).sin() + ((i / 29) as f32 * 0.3).cos() + 50.0)
            .collect();
        let f = GaussianFilter::new(g, 9.0).unwrap();
        let fast = f.apply(&h).unwrap();
        let general = f
            .weighted_mean(&h, &vec![1.0; h.len()], MIN_SUPPORT)
            .unwrap();
        for (a, b) in fast.iter().zip(&general.mean) {
            assert!((a - b).abs() < 2e-5, "{a} vs {b}");
        }
        assert!((general.support[0] - general.support[g.cols() - 1]).abs() < 1e-6);
    }

    #[test]
    fn a_constant_stays_constant_to_the_edges_and_around_holes() {
        let g = Sampling::square(Shape::new(37, 53), 0.5).unwrap();
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
