//! Form removal by least squares, and the S-F / S-L chain of ISO 25178-2.
//!
//! [`fit_polynomial`] fits `sum c_ij u^i v^j` over `i + j <= order` (order 1 = plane) to the
//! measured points, in normalised coordinates `u = (x - x_centre) / x_half`, `v` likewise
//! (`x = col x pitch_x`, the map's centre and half extent, so `u, v` lie in [-1, 1] and the
//! normal equations stay well conditioned up to [`MAX_ORDER`]). The normal matrix is built
//! from the separable moments `sum u^a v^b`, so a fit costs `O(order)` per point, and solved
//! by SVD (nalgebra).
//!
//! [`scale_limited`]: primary surface = S-filter(`lambda_s`) of the map; S-F surface = primary
//! - form; S-L surface = S-F - L-filter(`lambda_c`) of S-F, the L-filter Gaussian or robust.

use nalgebra::{DMatrix, DVector};
use rayon::prelude::*;

use super::gaussian::gaussian_filter;
use super::robust::{robust_gaussian_filter, RobustSettings};
use super::FilterError;
use crate::sampling::Sampling;
use crate::ParamError;

/// Highest polynomial order [`fit_polynomial`] accepts.
pub const MAX_ORDER: usize = 10;

/// A fitted polynomial form.
#[derive(Debug, Clone, PartialEq)]
pub struct PolynomialForm {
    pub order: usize,
    /// `(i, j)`: the powers of `u` and `v` of each coefficient, in the order of `coefficients`
    /// (by total degree, then by falling power of `u`: 1, u, v, u², uv, v², ...).
    pub terms: Vec<(usize, usize)>,
    /// µm, against the normalised coordinates.
    pub coefficients: Vec<f64>,
    /// The centre of the map (µm from pixel (0, 0)) and its half extent (µm): `u = (x -
    /// centre_um[0]) / half_extent_um[0]`, `v = (y - centre_um[1]) / half_extent_um[1]`.
    pub centre_um: [f64; 2],
    pub half_extent_um: [f64; 2],
    /// RMS of the residuals over the measured points, µm.
    pub residual_rms_um: f64,
}

/// The `u` (or `v`) coordinate of every column (row) of a line of `n` samples, and the
/// centre and half extent in µm.
fn axis(n: usize, pitch_um: f64) -> (Vec<f64>, f64, f64) {
    let centre = (n as f64 - 1.0) / 2.0 * pitch_um;
    let half = ((n as f64 - 1.0) / 2.0 * pitch_um).max(pitch_um);
    let u = (0..n)
        .map(|k| (k as f64 * pitch_um - centre) / half)
        .collect();
    (u, centre, half)
}

fn terms(order: usize) -> Vec<(usize, usize)> {
    (0..=order)
        .flat_map(|d| (0..=d).rev().map(move |i| (i, d - i)))
        .collect()
}

fn powers(x: f64, n: usize) -> Vec<f64> {
    let mut p = vec![0.0; n + 1];
    fill_powers(x, &mut p);
    p
}

/// `out[k] = x^k` by repeated multiplication (the order [`powers`] has always used).
fn fill_powers(x: f64, out: &mut [f64]) {
    let mut v = 1.0;
    for o in out {
        *o = v;
        v *= x;
    }
}

/// The least-squares polynomial of total order `order` (1 = plane) through the measured points
/// of `heights`.
pub fn fit_polynomial(
    heights: &[f32],
    grid: Sampling,
    order: usize,
) -> Result<PolynomialForm, FilterError> {
    grid.shape().check(heights.len())?;
    if order > MAX_ORDER {
        return Err(FilterError::from(ParamError::new(
            "form_order",
            order as f64,
            "a polynomial order from 0 to 10",
        )));
    }
    let (rows, cols) = (grid.rows(), grid.cols());
    let (u, cx, hx) = axis(cols, grid.pitch_x_um());
    let (v, cy, hy) = axis(rows, grid.pitch_y_um());
    let terms = terms(order);
    let have = heights.par_iter().filter(|z| z.is_finite()).count();
    if have < terms.len() {
        return Err(FilterError::TooFewPoints {
            order,
            needed: terms.len(),
            have,
        });
    }
    // Moments: s[a][b] = sum u^a v^b (a, b <= 2 order), t[i][j] = sum z u^i v^j (<= order).
    let m2 = 2 * order + 1;
    let m1 = order + 1;
    let (s, t) = heights
        .par_chunks(cols)
        .zip(&v)
        .map(|(line, &vr)| {
            let mut su = vec![0.0f64; m2];
            let mut zu = vec![0.0f64; m1];
            for (&z, &uc) in line.iter().zip(&u) {
                if !z.is_finite() {
                    continue;
                }
                let z = f64::from(z);
                let mut p = 1.0;
                for a in 0..m2 {
                    su[a] += p;
                    if a < m1 {
                        zu[a] += z * p;
                    }
                    p *= uc;
                }
            }
            let vp = powers(vr, 2 * order);
            let mut s = vec![0.0f64; m2 * m2];
            let mut t = vec![0.0f64; m1 * m1];
            for b in 0..m2 {
                for a in 0..m2 {
                    s[a * m2 + b] = su[a] * vp[b];
                }
            }
            for j in 0..m1 {
                for i in 0..m1 {
                    t[i * m1 + j] = zu[i] * vp[j];
                }
            }
            (s, t)
        })
        // Rows' moments collected in row order and added in that order: rayon's reduce
        // pairs them as the threads happen to split the work, which made the fit (and every
        // filtered map) differ in its last bits from run to run.
        .collect::<Vec<_>>()
        .into_iter()
        .fold(
            (vec![0.0; m2 * m2], vec![0.0; m1 * m1]),
            |(mut s, mut t), (s2, t2)| {
                s.iter_mut().zip(s2).for_each(|(a, b)| *a += b);
                t.iter_mut().zip(t2).for_each(|(a, b)| *a += b);
                (s, t)
            },
        );
    let n = terms.len();
    let normal = DMatrix::from_fn(n, n, |p, q| {
        let ((i, j), (k, l)) = (terms[p], terms[q]);
        s[(i + k) * m2 + (j + l)]
    });
    let rhs = DVector::from_fn(n, |p, _| {
        let (i, j) = terms[p];
        t[i * m1 + j]
    });
    let coefficients = normal
        .svd(true, true)
        .solve(&rhs, 1e-12)
        .map_err(|_| FilterError::TooFewPoints {
            order,
            needed: n,
            have,
        })?
        .iter()
        .copied()
        .collect();
    let mut form = PolynomialForm {
        order,
        terms,
        coefficients,
        centre_um: [cx, cy],
        half_extent_um: [hx, hy],
        residual_rms_um: 0.0,
    };
    let surface = form.evaluate(grid);
    // Rows summed in parallel, added in row order (the same bits whatever the threads).
    let ss: f64 = heights
        .par_chunks(cols)
        .zip(surface.par_chunks(cols))
        .map(|(line, fit)| {
            line.iter()
                .zip(fit)
                .filter(|(z, _)| z.is_finite())
                .map(|(&z, &f)| (f64::from(z) - f).powi(2))
                .sum::<f64>()
        })
        .collect::<Vec<f64>>()
        .iter()
        .sum();
    form.residual_rms_um = (ss / have as f64).sqrt();
    Ok(form)
}

impl PolynomialForm {
    /// The form's height at `(x_um, y_um)` (µm from pixel (0, 0)).
    pub fn at(&self, x_um: f64, y_um: f64) -> f64 {
        let u = (x_um - self.centre_um[0]) / self.half_extent_um[0];
        let v = (y_um - self.centre_um[1]) / self.half_extent_um[1];
        let (pu, pv) = (powers(u, self.order), powers(v, self.order));
        self.terms
            .iter()
            .zip(&self.coefficients)
            .map(|(&(i, j), c)| c * pu[i] * pv[j])
            .sum()
    }

    /// The form on every point of `grid`, f64, row-major.
    pub fn evaluate(&self, grid: Sampling) -> Vec<f64> {
        let cols = grid.cols();
        let pu = self.column_powers(grid);
        let mut out = vec![0.0f64; grid.rows() * cols];
        out.par_chunks_mut(cols.max(1))
            .enumerate()
            .for_each(|(r, line)| self.row_into(grid, &pu, r, line));
        out
    }

    /// `heights - form` (NaN stays NaN).
    pub fn remove(&self, heights: &[f32], grid: Sampling) -> Vec<f32> {
        let cols = grid.cols();
        let pu = self.column_powers(grid);
        let mut out = vec![0.0f32; heights.len()];
        out.par_chunks_mut(cols.max(1))
            .zip(heights.par_chunks(cols.max(1)))
            .enumerate()
            .for_each_init(
                || vec![0.0f64; cols],
                |form, (r, (line, z))| {
                    self.row_into(grid, &pu, r, form);
                    for ((o, &z), &f) in line.iter_mut().zip(z).zip(form.iter()) {
                        *o = (f64::from(z) - f) as f32;
                    }
                },
            );
        out
    }

    /// The powers `u^0 .. u^order` of every column, `order + 1` per column.
    fn column_powers(&self, grid: Sampling) -> Vec<f64> {
        let width = self.order + 1;
        let mut pu = vec![0.0f64; grid.cols() * width];
        for (c, line) in pu.chunks_mut(width).enumerate() {
            let u = (c as f64 * grid.pitch_x_um() - self.centre_um[0]) / self.half_extent_um[0];
            fill_powers(u, line);
        }
        pu
    }

    /// Row `r` of the form into `out`: the same arithmetic as [`PolynomialForm::at`] at every
    /// point (the same bits), with the powers tabulated per column and per row: `at` per pixel
    /// allocated two vectors per pixel, a third of a filtered map's time.
    fn row_into(&self, grid: Sampling, pu: &[f64], r: usize, out: &mut [f64]) {
        let width = self.order + 1;
        let v = (r as f64 * grid.pitch_y_um() - self.centre_um[1]) / self.half_extent_um[1];
        let mut pv = vec![0.0f64; width];
        fill_powers(v, &mut pv);
        for (o, pu) in out.iter_mut().zip(pu.chunks(width)) {
            *o = self
                .terms
                .iter()
                .zip(&self.coefficients)
                .map(|(&(i, j), c)| c * pu[i] * pv[j])
                .sum();
        }
    }
}

/// The L-filter of the S-F -> S-L step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum LFilter {
    /// ISO 16610-61 Gaussian.
    Gaussian,
    /// ISO 16610-71 robust Gaussian regression (zeroth order).
    Robust,
}

/// The surfaces of the S-F / S-L chain, row-major, µm, NaN = not measured.
#[derive(Debug, Clone, PartialEq)]
pub struct ScaleLimited {
    pub form: PolynomialForm,
    /// S-filtered map minus its form.
    pub sf: Vec<f32>,
    /// The L-filter's output on the S-F surface (`None` without `lambda_c`).
    pub l_mean: Option<Vec<f32>>,
    /// S-F minus `l_mean` (`None` without `lambda_c`).
    pub sl: Option<Vec<f32>>,
}

/// Primary surface (S-filter `lambda_s_um`, none if `None`), minus the polynomial form of
/// `form_order`, gives S-F; minus its L-filter (`lambda_c_um`, if given) gives S-L.
pub fn scale_limited(
    heights: &[f32],
    grid: Sampling,
    form_order: usize,
    lambda_s_um: Option<f64>,
    lambda_c_um: Option<f64>,
    l_filter: LFilter,
) -> Result<ScaleLimited, FilterError> {
    grid.shape().check(heights.len())?;
    if let (Some(ls), Some(lc)) = (lambda_s_um, lambda_c_um) {
        if lc <= ls {
            return Err(FilterError::from(ParamError::new(
                "lambda_c_um",
                lc,
                "a cutoff longer than lambda_s",
            )));
        }
    }
    let primary = match lambda_s_um {
        Some(ls) => gaussian_filter(heights, grid, ls)?,
        None => heights.to_vec(),
    };
    let form = fit_polynomial(&primary, grid, form_order)?;
    let sf = form.remove(&primary, grid);
    drop(primary);
    let l_mean = match lambda_c_um {
        Some(lc) => Some(match l_filter {
            LFilter::Gaussian => gaussian_filter(&sf, grid, lc)?,
            LFilter::Robust => robust_gaussian_filter(&sf, grid, &RobustSettings::new(lc))?.mean,
        }),
        None => None,
    };
    let sl = l_mean
        .as_ref()
        .map(|m| sf.par_iter().zip(m).map(|(s, m)| s - m).collect());
    Ok(ScaleLimited {
        form,
        sf,
        l_mean,
        sl,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `evaluate` and `remove` tabulate the powers; they must give `at`'s bits at every point.
    #[test]
    fn tabulated_form_is_at_bit_for_bit() {
        let (rows, cols) = (23, 37);
        let grid = Sampling::new(crate::raster::Shape::new(rows, cols), 0.8148, 1.1)
            .expect("valid sampling");
        let heights: Vec<f32> = (0..rows * cols)
            .map(|k| {
                let (r, c) = ((k / cols) as f32, (k % cols) as f32);
                if k % 17 == 0 {
                    f32::NAN
                } else {
                    0.3 * r - 0.2 * c + 0.01 * r * c + (0.7 * r).sin()
                }
            })
            .collect();
        for order in [0, 1, 3, 6] {
            let form = fit_polynomial(&heights, grid, order).expect("fit");
            let surface = form.evaluate(grid);
            let removed = form.remove(&heights, grid);
            for r in 0..rows {
                for c in 0..cols {
                    let at = form.at(c as f64 * grid.pitch_x_um(), r as f64 * grid.pitch_y_um());
                    let k = r * cols + c;
                    assert_eq!(
                        surface[k].to_bits(),
                        at.to_bits(),
                        "order {order} ({r}, {c})"
                    );
                    let want = (f64::from(heights[k]) - at) as f32;
                    assert!(
                        removed[k].to_bits() == want.to_bits()
                            || (want.is_nan() && removed[k].is_nan()),
                        "order {order} ({r}, {c})"
                    );
                }
            }
        }
    }
}
