//! Power spectral density of the heights: the areal PSD and its radial (azimuthal) average.
//!
//! Areal PSD, um^4: P(fx, fy) = |DFT(c)|^2 px py / (rows cols), c = heights minus the mean of the
//! valid points, so that the sum of P over the frequency grid times its cell (1 / (cols px)) x
//! (1 / (rows py)) is Sq^2 (Parseval). No window. NaN: gaps are filled with the mean (c = 0)
//! and P is multiplied by points / valid points, which keeps that integral equal to Sq^2 of the
//! valid points; a gap still spreads power over the spectrum (its edges are steps), so read
//! the PSD of a map with large holes with care.
//!
//! Radial PSD: the mean of P over annuli |f| in [(k - 1/2) df, (k + 1/2) df), df = the coarser
//! of the two frequency steps, k = 1 up to the Nyquist radius of the coarser direction (no
//! partial annuli from the corners of the frequency rectangle); reported as (wavelength 1 /
//! (k df) in um, power in um^4).

use rayon::prelude::*;

use super::spatial::centred;
use super::spectrum::spectrum2;
use super::{Grid, MetrologyError};
use crate::raster::RasterView;

/// The 2-D DFT of a real field (rows x cols, row-major, no NaN) on the half plane
/// kx = 0..cols/2: rows x (cols/2 + 1), unnormalised; rows in parallel. For a caller that
/// prepares the field its own way (the report windows it before its log-binned PSD).
pub fn real_dft2_half_plane(
    field: &[f64],
    rows: usize,
    cols: usize,
) -> Vec<rustfft::num_complex::Complex<f64>> {
    spectrum2(field, rows, cols)
}

/// The areal PSD on the half plane kx = 0..cols/2 (the other half is its point mirror).
#[derive(Debug, Clone)]
pub struct ArealPsd {
    /// rows x (cols/2 + 1), row ky = 0..rows (frequencies ky / (rows py), ky > rows/2 negative).
    pub values_um4: Vec<f64>,
    pub rows: usize,
    pub half_cols: usize,
    /// Frequency steps (1/um).
    pub df_x: f64,
    pub df_y: f64,
    cols: usize,
}

impl ArealPsd {
    /// The areal PSD of `g` (see the module documentation).
    pub fn of(g: &Grid) -> Result<Self, MetrologyError> {
        let (c, valid) = centred(g)?;
        let spec = spectrum2(&c, g.rows(), g.cols());
        let n = (g.rows() * g.cols()) as f64;
        let scale = g.pitch_x_um() * g.pitch_y_um() / n * (n / valid as f64);
        Ok(Self {
            values_um4: spec.par_iter().map(|v| v.norm_sqr() * scale).collect(),
            rows: g.rows(),
            half_cols: g.cols() / 2 + 1,
            df_x: 1.0 / (g.cols() as f64 * g.pitch_x_um()),
            df_y: 1.0 / (g.rows() as f64 * g.pitch_y_um()),
            cols: g.cols(),
        })
    }

    /// (fx, fy) in 1/um of the sample at (ky, kx).
    pub fn frequency(&self, ky: usize, kx: usize) -> (f64, f64) {
        let ky_s = if ky <= self.rows / 2 {
            ky as f64
        } else {
            ky as f64 - self.rows as f64
        };
        (kx as f64 * self.df_x, ky_s * self.df_y)
    }

    /// The radial average: (wavelength um, power um^4), longest wavelength first.
    pub fn radial(&self) -> Vec<(f64, f64)> {
        let df = self.df_x.max(self.df_y);
        let f_max = (self.df_x * (self.cols / 2) as f64).min(self.df_y * (self.rows / 2) as f64);
        let bins = (f_max / df).floor() as usize;
        let mut sum = vec![0.0; bins + 1];
        let mut count = vec![0.0; bins + 1];
        for ky in 0..self.rows {
            for kx in 0..self.half_cols {
                let (fx, fy) = self.frequency(ky, kx);
                let k = ((fx * fx + fy * fy).sqrt() / df).round() as usize;
                if k == 0 || k > bins {
                    continue;
                }
                let weight = if kx == 0 || (self.cols.is_multiple_of(2) && kx == self.cols / 2) {
                    1.0
                } else {
                    2.0
                };
                sum[k] += weight * self.values_um4[ky * self.half_cols + kx];
                count[k] += weight;
            }
        }
        (1..=bins)
            .filter(|&k| count[k] > 0.0)
            .map(|k| (1.0 / (k as f64 * df), sum[k] / count[k]))
            .collect()
    }
}

/// The radial PSD of a height map (um, NaN = not measured) with square pixels of `pitch_um`:
/// (wavelength um, power um^4), longest wavelength first. For the report's plot.
pub fn radial_psd(
    view: RasterView<'_, f64>,
    pitch_um: f64,
) -> Result<Vec<(f64, f64)>, MetrologyError> {
    let g = Grid::new(view.values(), view.rows(), view.cols(), pitch_um, pitch_um)?;
    Ok(ArealPsd::of(&g)?.radial())
}
