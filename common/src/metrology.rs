//! ISO 25178-2 height and hybrid parameters, plane levelling, SIM (the reference study's
//! eq. 12) and the model-vs-measurement deviation of its Table 6.
//!
//! Conventions (the parity reference is surfalize 0.19.2, see ../shared/notes/formats.md):
//! z = the valid (non-NaN) heights, N their count, c = z - mean(z); nothing is levelled or
//! filtered implicitly ([`level_plane`] is the explicit step).
//! - Sa = sum|c| / N; Sq = sqrt(sum c^2 / N); Sp = max c; Sv = |min c|; Sz = Sp + Sv;
//!   Ssk = (sum c^3 / N) / Sq^3; Sku = (sum c^4 / N) / Sq^4 (not excess).
//! - Sdq = sqrt(mean (dz/dx)^2 + mean (dz/dy)^2), forward differences, each mean over its own
//!   count; a difference takes part only when both its points are valid.
//! - Sdr = (A / A_proj - 1) * 100 %, A = the mean of the two diagonal triangulations of each
//!   grid cell. With NaN, only cells whose four corners are valid count (A_proj is theirs):
//!   Sdr and Sdq need a filled grid to mean what ISO says; on data with holes they describe
//!   the measured part only.
//!
//! Sums: each row is summed in four independent lanes (short, so the error stays ~1e-15
//! relative) and rows are combined with Neumaier's compensated summation; naive f64 sums over
//! 1e7 points drift past 1e-9 relative. Rows run in parallel (rayon); the result does not
//! depend on the thread count (rows are combined in a fixed order).

use rayon::prelude::*;
use serde::Serialize;

/// Neumaier's compensated sum.
#[derive(Debug, Clone, Copy, Default)]
struct Compensated {
    sum: f64,
    comp: f64,
}

impl Compensated {
    fn add(&mut self, v: f64) {
        let t = self.sum + v;
        if self.sum.abs() >= v.abs() {
            self.comp += (self.sum - t) + v;
        } else {
            self.comp += (v - t) + self.sum;
        }
        self.sum = t;
    }
    fn value(self) -> f64 {
        self.sum + self.comp
    }
}

/// The nine parameters; heights in um, Sdq dimensionless, Sdr in %.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Params {
    #[serde(rename = "Sa")]
    pub sa: f64,
    #[serde(rename = "Sq")]
    pub sq: f64,
    #[serde(rename = "Sp")]
    pub sp: f64,
    #[serde(rename = "Sv")]
    pub sv: f64,
    #[serde(rename = "Sz")]
    pub sz: f64,
    #[serde(rename = "Ssk")]
    pub ssk: f64,
    #[serde(rename = "Sku")]
    pub sku: f64,
    #[serde(rename = "Sdq")]
    pub sdq: f64,
    #[serde(rename = "Sdr")]
    pub sdr: f64,
}

impl Params {
    /// Name (ISO 25178) and value, in the order Sa Sq Sp Sv Sz Ssk Sku Sdq Sdr.
    pub fn named(&self) -> [(&'static str, f64); 9] {
        [
            ("Sa", self.sa),
            ("Sq", self.sq),
            ("Sp", self.sp),
            ("Sv", self.sv),
            ("Sz", self.sz),
            ("Ssk", self.ssk),
            ("Sku", self.sku),
            ("Sdq", self.sdq),
            ("Sdr", self.sdr),
        ]
    }
}

/// Why parameters could not be computed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MetrologyError {
    #[error("height map has {found} values, expected {rows} x {cols}")]
    Shape {
        rows: usize,
        cols: usize,
        found: usize,
    },
    #[error("no valid (non-NaN) height")]
    NoValidPoint,
    #[error("pitch {x_um} x {y_um} um: expected finite positive values")]
    BadPitch { x_um: f64, y_um: f64 },
    #[error("the two maps differ in shape: {a_rows} x {a_cols} vs {b_rows} x {b_cols}")]
    ShapeMismatch {
        a_rows: usize,
        a_cols: usize,
        b_rows: usize,
        b_cols: usize,
    },
}

/// A height map borrowed for computing: row-major `rows x cols`, um, NaN = not measured.
#[derive(Debug, Clone, Copy)]
pub struct Grid<'a> {
    pub heights_um: &'a [f64],
    pub rows: usize,
    pub cols: usize,
    pub pitch_x_um: f64,
    pub pitch_y_um: f64,
}

impl<'a> Grid<'a> {
    pub fn new(
        heights_um: &'a [f64],
        rows: usize,
        cols: usize,
        pitch_x_um: f64,
        pitch_y_um: f64,
    ) -> Result<Self, MetrologyError> {
        if rows.checked_mul(cols) != Some(heights_um.len()) {
            return Err(MetrologyError::Shape {
                rows,
                cols,
                found: heights_um.len(),
            });
        }
        if !(pitch_x_um.is_finite()
            && pitch_x_um > 0.0
            && pitch_y_um.is_finite()
            && pitch_y_um > 0.0)
        {
            return Err(MetrologyError::BadPitch {
                x_um: pitch_x_um,
                y_um: pitch_y_um,
            });
        }
        Ok(Self {
            heights_um,
            rows,
            cols,
            pitch_x_um,
            pitch_y_um,
        })
    }

    fn row(&self, r: usize) -> &'a [f64] {
        &self.heights_um[r * self.cols..(r + 1) * self.cols]
    }
}

/// Lane-wise sum of a row: four independent accumulators (vectorises; short chains).
#[inline]
#[allow(clippy::needless_range_loop)] // lane-major indexing is the point here
fn lanes<const K: usize>(n: usize, mut f: impl FnMut(usize) -> [f64; K]) -> [f64; K] {
    let mut acc = [[0.0f64; 4]; K];
    let full = n / 4 * 4;
    let mut i = 0;
    while i < full {
        for l in 0..4 {
            let v = f(i + l);
            for k in 0..K {
                acc[k][l] += v[k];
            }
        }
        i += 4;
    }
    let mut out = [0.0; K];
    for k in 0..K {
        out[k] = (acc[k][0] + acc[k][1]) + (acc[k][2] + acc[k][3]);
    }
    for j in full..n {
        let v = f(j);
        for k in 0..K {
            out[k] += v[k];
        }
    }
    out
}

/// Per-row partial sums combined in row order with compensation (deterministic).
#[allow(clippy::needless_range_loop)]
fn row_sums<const K: usize>(rows: usize, f: impl Fn(usize) -> [f64; K] + Sync) -> [f64; K] {
    let per_row: Vec<[f64; K]> = (0..rows).into_par_iter().map(&f).collect();
    let mut acc = [Compensated::default(); K];
    for s in &per_row {
        for k in 0..K {
            acc[k].add(s[k]);
        }
    }
    acc.map(Compensated::value)
}

/// Count, mean, min and max of the valid heights.
fn moments0(g: &Grid) -> Result<(f64, f64, f64, f64), MetrologyError> {
    let per_row: Vec<(f64, f64, f64, f64)> = (0..g.rows)
        .into_par_iter()
        .map(|r| {
            let row = g.row(r);
            let [n, s] = lanes(row.len(), |i| {
                let z = row[i];
                if z.is_nan() {
                    [0.0, 0.0]
                } else {
                    [1.0, z]
                }
            });
            let (lo, hi) = row
                .iter()
                .filter(|z| !z.is_nan())
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &z| {
                    (lo.min(z), hi.max(z))
                });
            (n, s, lo, hi)
        })
        .collect();
    let (mut n, mut s) = (0.0, Compensated::default());
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for &(rn, rs, rlo, rhi) in &per_row {
        n += rn;
        s.add(rs);
        lo = lo.min(rlo);
        hi = hi.max(rhi);
    }
    if n == 0.0 {
        return Err(MetrologyError::NoValidPoint);
    }
    let mean0 = s.value() / n;
    // One refinement step: the mean of the residuals removes the rounding of the first mean.
    let [corr] = row_sums(g.rows, |r| {
        let row = g.row(r);
        lanes(row.len(), |i| {
            let z = row[i];
            [if z.is_nan() { 0.0 } else { z - mean0 }]
        })
    });
    Ok((n, mean0 + corr / n, lo, hi))
}

/// The height parameters Sa Sq Sp Sv Sz Ssk Sku (um; Ssk, Sku dimensionless) over the valid
/// points, about their mean.
pub fn height_params(g: &Grid) -> Result<[f64; 7], MetrologyError> {
    let (n, mean, lo, hi) = moments0(g)?;
    let [s1, s2, s3, s4] = row_sums(g.rows, |r| {
        let row = g.row(r);
        lanes(row.len(), |i| {
            let z = row[i];
            let c = if z.is_nan() { 0.0 } else { z - mean };
            let c2 = c * c;
            [c.abs(), c2, c2 * c, c2 * c2]
        })
    });
    let sq = (s2 / n).sqrt();
    let (sp, sv) = (hi - mean, (lo - mean).abs());
    // A constant surface has Sq = 0: skewness and kurtosis are undefined (NaN), as in surfalize.
    Ok([
        s1 / n,
        sq,
        sp,
        sv,
        sp + sv,
        (s3 / n) / (sq * sq * sq),
        (s4 / n) / (sq * sq * sq * sq),
    ])
}

/// Sdq and Sdr (%). NaN when no difference / no whole cell is valid.
pub fn hybrid_params(g: &Grid) -> (f64, f64) {
    let (px, py) = (g.pitch_x_um, g.pitch_y_um);
    let cell = px * py;
    let cell2 = cell * cell;
    // Per row r: [sum (dz/dx)^2, count x, sum (dz/dy)^2 to row r+1, count y, Sdr excess, cells].
    let [sx, nx, sy, ny, excess, cells] = row_sums(g.rows, |r| {
        let a = g.row(r);
        let [sx, nx] = lanes(g.cols.saturating_sub(1), |i| {
            let d = (a[i + 1] - a[i]) / px;
            if d.is_nan() {
                [0.0, 0.0]
            } else {
                [d * d, 1.0]
            }
        });
        if r + 1 >= g.rows {
            return [sx, nx, 0.0, 0.0, 0.0, 0.0];
        }
        let b = g.row(r + 1);
        let [sy, ny] = lanes(g.cols, |i| {
            let d = (b[i] - a[i]) / py;
            if d.is_nan() {
                [0.0, 0.0]
            } else {
                [d * d, 1.0]
            }
        });
        // Cell (r, i): corners a[i], a[i+1], b[i], b[i+1]. Four triangles (both diagonals), each
        // |n| = sqrt(leg terms + (px py)^2); excess |n| - px py = legs / (|n| + px py), summed
        // directly so flat surfaces do not cancel catastrophically.
        let [e, c] = lanes(g.cols.saturating_sub(1), |i| {
            let zx_a = (a[i + 1] - a[i]) * py;
            let zx_b = (b[i + 1] - b[i]) * py;
            let zy_l = (b[i] - a[i]) * px;
            let zy_r = (b[i + 1] - a[i + 1]) * px;
            let (bx, tx, ly, ry) = (zx_a * zx_a, zx_b * zx_b, zy_l * zy_l, zy_r * zy_r);
            let ex = |legs: f64| legs / ((legs + cell2).sqrt() + cell);
            let v = ex(bx + ly) + ex(bx + ry) + ex(tx + ry) + ex(tx + ly);
            if v.is_nan() {
                [0.0, 0.0]
            } else {
                [v, 1.0]
            }
        });
        [sx, nx, sy, ny, e, c]
    });
    let sdq = if nx + ny == 0.0 {
        f64::NAN
    } else {
        let mx = if nx > 0.0 { sx / nx } else { 0.0 };
        let my = if ny > 0.0 { sy / ny } else { 0.0 };
        (mx + my).sqrt()
    };
    // Each cell's area ratio - 1 = (sum of the four excesses / 4) / (px py).
    let sdr = if cells == 0.0 {
        f64::NAN
    } else {
        excess / (4.0 * cell) / cells * 100.0
    };
    (sdq, sdr)
}

/// All nine parameters.
pub fn params(g: &Grid) -> Result<Params, MetrologyError> {
    let [sa, sq, sp, sv, sz, ssk, sku] = height_params(g)?;
    let (sdq, sdr) = hybrid_params(g);
    Ok(Params {
        sa,
        sq,
        sp,
        sv,
        sz,
        ssk,
        sku,
        sdq,
        sdr,
    })
}

/// The least-squares plane z = a + b x + c y through the valid points (x = col * pitch_x,
/// y = row * pitch_y, um), as (a, b, c); fitted on centred coordinates for conditioning.
pub fn fit_plane(g: &Grid) -> Result<(f64, f64, f64), MetrologyError> {
    let (n, zmean, _, _) = moments0(g)?;
    let [sx, sy] = row_sums(g.rows, |r| {
        let row = g.row(r);
        let y = r as f64;
        lanes(row.len(), |i| {
            if row[i].is_nan() {
                [0.0, 0.0]
            } else {
                [i as f64, y]
            }
        })
    });
    let (xm, ym) = (sx / n, sy / n);
    let [sxx, sxy, syy, sxz, syz] = row_sums(g.rows, |r| {
        let row = g.row(r);
        let y = r as f64 - ym;
        lanes(row.len(), |i| {
            let z = row[i];
            if z.is_nan() {
                [0.0; 5]
            } else {
                let x = i as f64 - xm;
                let dz = z - zmean;
                [x * x, x * y, y * y, x * dz, y * dz]
            }
        })
    });
    let det = sxx * syy - sxy * sxy;
    // Points on one line (or one point): the plane's slope across the line is undetermined;
    // take the least-squares fit along the direction that has extent.
    let (bx, by) = if det.abs() > 1e-12 * (sxx * syy).max(f64::MIN_POSITIVE) {
        ((sxz * syy - syz * sxy) / det, (syz * sxx - sxz * sxy) / det)
    } else if sxx > 0.0 {
        (sxz / sxx, 0.0)
    } else if syy > 0.0 {
        (0.0, syz / syy)
    } else {
        (0.0, 0.0)
    };
    // Per-pixel slopes to per-um slopes; intercept at pixel (0, 0).
    let (b, c) = (bx / g.pitch_x_um, by / g.pitch_y_um);
    let a = zmean - bx * xm - by * ym;
    Ok((a, b, c))
}

/// The heights minus their least-squares plane (NaN stays NaN).
pub fn level_plane(g: &Grid) -> Result<Vec<f64>, MetrologyError> {
    let (a, b, c) = fit_plane(g)?;
    let (bx, by) = (b * g.pitch_x_um, c * g.pitch_y_um);
    let mut out = vec![0.0; g.heights_um.len()];
    out.par_chunks_mut(g.cols.max(1))
        .enumerate()
        .for_each(|(r, o)| {
            let row = g.row(r);
            let base = a + by * r as f64;
            for (i, (o, &z)) in o.iter_mut().zip(row).enumerate() {
                *o = z - (base + bx * i as f64);
            }
        });
    Ok(out)
}

/// SIM, the reference study's eq. 12 as we read it: the normalised (zero-mean) cross-correlation
/// of two maps of the same shape, sum (a - mean a)(b - mean b) / sqrt(sum (a - mean a)^2 *
/// sum (b - mean b)^2), over the pixels valid in both; 1 = identical up to offset and scale.
/// NaN when either map is constant there.
pub fn sim(a: &[f64], b: &[f64]) -> Result<f64, MetrologyError> {
    if a.len() != b.len() {
        return Err(MetrologyError::ShapeMismatch {
            a_rows: 1,
            a_cols: a.len(),
            b_rows: 1,
            b_cols: b.len(),
        });
    }
    let both = |i: usize| !a[i].is_nan() && !b[i].is_nan();
    let chunk = 4096;
    let chunks = a.len().div_ceil(chunk);
    let range = |c: usize| c * chunk..((c + 1) * chunk).min(a.len());
    let [n, sa, sb] = row_sums(chunks, |c| {
        let mut s = [0.0; 3];
        for i in range(c) {
            if both(i) {
                s[0] += 1.0;
                s[1] += a[i];
                s[2] += b[i];
            }
        }
        s
    });
    if n == 0.0 {
        return Err(MetrologyError::NoValidPoint);
    }
    let (ma, mb) = (sa / n, sb / n);
    let [sab, saa, sbb] = row_sums(chunks, |c| {
        let mut s = [0.0; 3];
        for i in range(c) {
            if both(i) {
                let (x, y) = (a[i] - ma, b[i] - mb);
                s[0] += x * y;
                s[1] += x * x;
                s[2] += y * y;
            }
        }
        s
    });
    Ok(sab / (saa * sbb).sqrt())
}

/// RMS of a - b over the pixels valid in both (um), with the number of such pixels.
pub fn rms_difference(a: &[f64], b: &[f64]) -> Result<(f64, usize), MetrologyError> {
    if a.len() != b.len() {
        return Err(MetrologyError::ShapeMismatch {
            a_rows: 1,
            a_cols: a.len(),
            b_rows: 1,
            b_cols: b.len(),
        });
    }
    let chunk = 4096;
    let [n, s] = row_sums(a.len().div_ceil(chunk), |c| {
        let mut s = [0.0; 2];
        for i in c * chunk..((c + 1) * chunk).min(a.len()) {
            let d = a[i] - b[i];
            if !d.is_nan() {
                s[0] += 1.0;
                s[1] += d * d;
            }
        }
        s
    });
    if n == 0.0 {
        return Err(MetrologyError::NoValidPoint);
    }
    Ok(((s / n).sqrt(), n as usize))
}
