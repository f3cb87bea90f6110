//! The ISO 16610-71 robust Gaussian regression filter, zeroth order.
//!
//! Iteratively reweighted Gaussian regression (ISO 16610-71, built on ISO 16610-31):
//!
//! 1. `m_0` = the Gaussian mean surface ([`super::gaussian`]: every measured point weight 1).
//! 2. residuals `r = z - m_k`; scale `c = 4.4478 median(|r|)` (4.4478 = 3 x 1.4826: three
//!    standard deviations of a Gaussian residual, estimated robustly);
//! 3. Tukey's biweight `delta = (1 - (r/c)^2)^2` for `|r| < c`, else 0 (missing points: 0);
//! 4. `m_{k+1} = sum(s delta z) / sum(s delta)`, the Gaussian regression of order 0 with the
//!    weights `s delta`; repeat from 2 until the mean moves less than `tolerance x median(|r|)`
//!    anywhere, or `max_iterations`.
//!
//! Order: zeroth (a locally weighted mean). The standard also defines order 2, which follows
//! curved form better near the edges; order 0 is the one whose weights are separable, so each
//! iteration is one FFT Gaussian pass and the filter stays fast on large maps. Remove the form
//! first ([`super::form`]) as with the plain L-filter.
//!
//! Points rejected as outliers (delta = 0) still get a mean value (from their neighbours);
//! missing points stay NaN. Where every neighbour of a measured point was rejected (support
//! below 1e-6), the previous iteration's mean is kept.

use rayon::prelude::*;

use super::gaussian::{GaussianFilter, MIN_SUPPORT};
use super::FilterError;
use crate::sampling::Sampling;
use crate::ParamError;

/// Tukey biweight scale factor: `c = TUKEY_C x median(|r|)`.
pub const TUKEY_C: f64 = 4.4478;

/// How the robust filter iterates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RobustSettings {
    /// `lambda_c`, µm.
    pub cutoff_um: f64,
    /// Iteration limit (ISO 16610-71 leaves it to the implementation).
    pub max_iterations: usize,
    /// Stop when no mean value moves more than this fraction of `median(|r|)`.
    pub tolerance: f64,
}

impl RobustSettings {
    /// Cutoff `cutoff_um`, at most 30 iterations, tolerance 1e-3.
    pub fn new(cutoff_um: f64) -> Self {
        Self {
            cutoff_um,
            max_iterations: 30,
            tolerance: 1e-3,
        }
    }
}

/// The robust mean surface and how it was reached.
#[derive(Debug, Clone, PartialEq)]
pub struct RobustFit {
    /// The robust Gaussian mean surface, NaN where the input is not measured.
    pub mean: Vec<f32>,
    /// The final biweights `delta` (0 = rejected or missing).
    pub weights: Vec<f32>,
    /// Reweighting iterations done after the plain Gaussian pass.
    pub iterations: usize,
    /// True when the tolerance was met (false: stopped at `max_iterations`).
    pub converged: bool,
    /// The last scale `c`, µm.
    pub c_um: f64,
}

/// The median of `|z - m|` over the points where both are finite; 0 if there are none.
fn median_abs_residual(heights: &[f32], mean: &[f32]) -> f64 {
    let residual = |i: usize| {
        let (z, m) = (heights[i], mean[i]);
        if z.is_finite() && m.is_finite() {
            z - m
        } else {
            f32::NAN
        }
    };
    crate::order::median_magnitude(heights.len().min(mean.len()), residual).map_or(0.0, f64::from)
}

/// The ISO 16610-71 robust Gaussian regression filter (zeroth order; module doc) of `heights`.
pub fn robust_gaussian_filter(
    heights: &[f32],
    grid: Sampling,
    settings: &RobustSettings,
) -> Result<RobustFit, FilterError> {
    if !(settings.tolerance.is_finite() && settings.tolerance > 0.0) {
        return Err(FilterError::from(ParamError::new(
            "tolerance",
            settings.tolerance,
            "a positive fraction",
        )));
    }
    let filter = GaussianFilter::new(grid, settings.cutoff_um)?;
    let valid: Vec<f32> = heights
        .par_iter()
        .map(|z| if z.is_finite() { 1.0 } else { 0.0 })
        .collect();
    // The plain Gaussian pass also decides, once, which points have too little support.
    let mut mean = filter.weighted_mean(heights, &valid, MIN_SUPPORT)?.mean;
    let mut weights = valid;
    let (mut iterations, mut converged, mut c_um) = (0, false, 0.0);
    while iterations < settings.max_iterations {
        let mad = median_abs_residual(heights, &mean);
        c_um = TUKEY_C * mad;
        if mad <= 0.0 {
            // The mean already passes through every point: nothing to reweight.
            converged = true;
            break;
        }
        weights = heights
            .par_iter()
            .zip(&mean)
            .map(|(&z, &m)| {
                let u = f64::from(z - m) / c_um;
                if z.is_finite() && m.is_finite() && u.abs() < 1.0 {
                    ((1.0 - u * u) * (1.0 - u * u)) as f32
                } else {
                    0.0
                }
            })
            .collect();
        let next = filter.weighted_mean(heights, &weights, 1e-6)?.mean;
        iterations += 1;
        let limit = (settings.tolerance * mad) as f32;
        let moved = mean
            .par_iter_mut()
            .zip(next)
            .map(|(m, n)| {
                // Keep NaN where the plain pass said "too little support"; keep the previous
                // value where every neighbour was rejected.
                if m.is_nan() || n.is_nan() {
                    return 0.0f32;
                }
                let d = (n - *m).abs();
                *m = n;
                d
            })
            .reduce(|| 0.0, f32::max);
        if moved <= limit {
            converged = true;
            break;
        }
    }
    Ok(RobustFit {
        mean,
        weights,
        iterations,
        converged,
        c_um,
    })
}
