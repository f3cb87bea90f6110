//! Piston and tilt: least-squares planes over valid pixels, and the z alignment of a tile
//! against its already-levelled neighbours.

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};
use thiserror::Error;

use surfstream_core::raster::{RasterView, Shape};

use crate::raster::{validate_offset, InputError};
use surfstream_core::avx2_dispatch;
/// The correction convention is the workspace's one: [`surfstream_core::PlaneCorrection`].
pub use surfstream_core::PlaneCorrection;
use wide::f32x8;

/// Which model the least-squares fit could support.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum PlaneModel {
    /// Piston and both tilts.
    Full,
    /// The samples lie on a thin strip: piston and the tilt along the strip; the tilt across
    /// the strip is set to zero (it is not observable).
    AlongStrip,
    /// Too few samples or all at one point: piston only.
    PistonOnly,
}

/// The result of [`estimate_plane_report`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PlaneEstimate {
    pub correction: PlaneCorrection,
    pub model: PlaneModel,
    /// Number of pixel pairs the fit used.
    pub samples: usize,
    /// RMS of the height differences after the fit (um).
    pub rms_residual_um: f64,
}

/// Why no plane could be estimated.
#[derive(Debug, Clone, PartialEq, Error, Serialize, Deserialize)]
pub enum PlaneError {
    #[error("invalid input: {0}")]
    Input(#[from] InputError),
    #[error("no valid overlapping pixels with any neighbour")]
    NoOverlap,
}

/// Smallest standard deviation (px) of the sample positions across their principal axis for
/// which the tilt across that axis is still fitted.
const MIN_SPREAD_PX: f64 = 2.0;

/// Running sums of a least-squares plane `z = p + tx * x + ty * y`; x, y in pixels relative to
/// the tile centre.
#[derive(Debug, Default, Clone, Copy)]
pub(crate) struct PlaneSums {
    n: f64,
    sx: f64,
    sy: f64,
    sxx: f64,
    sxy: f64,
    syy: f64,
    sz: f64,
    sxz: f64,
    syz: f64,
    szz: f64,
}

impl PlaneSums {
    #[inline]
    pub(crate) fn add(&mut self, x: f64, y: f64, z: f64) {
        self.n += 1.0;
        self.sx += x;
        self.sy += y;
        self.sxx += x * x;
        self.sxy += x * y;
        self.syy += y * y;
        self.sz += z;
        self.sxz += x * z;
        self.syz += y * z;
        self.szz += z * z;
    }

    /// Adds the sums of one row at height `y`, whose samples have x = `x0 + i` for the valid
    /// (finite) entries `z[i]`. Faster than per-pixel `add` for whole rows.
    pub(crate) fn add_row(&mut self, y: f64, x0: f64, z: &[f32]) {
        self.add_row_offset(y, x0, z, 0.0);
    }

    /// [`Self::add_row`] of `z[i] - z_ref`. Branch-free f32 lanes so the loop vectorises; the
    /// per-row lane sums are exact enough for rows of a few thousand pixels and are promoted to
    /// f64 before they are combined.
    pub(crate) fn add_row_offset(&mut self, y: f64, x0: f64, z: &[f32], z_ref: f32) {
        let t = row_sums_all_finite(z, z_ref).unwrap_or_else(|| row_sums_masked(z, z_ref));
        // Sums over x' = x0 + x.
        let [n, sxi, sxxi, sz, sxzi, szz] = t;
        let sx = n * x0 + sxi;
        let sxx = n * x0 * x0 + 2.0 * x0 * sxi + sxxi;
        let sxz = x0 * sz + sxzi;
        self.n += n;
        self.sx += sx;
        self.sy += y * n;
        self.sxx += sxx;
        self.sxy += y * sx;
        self.syy += y * y * n;
        self.sz += sz;
        self.sxz += sxz;
        self.syz += y * sz;
        self.szz += szz;
    }

    pub(crate) fn merge(&mut self, o: &PlaneSums) {
        self.n += o.n;
        self.sx += o.sx;
        self.sy += o.sy;
        self.sxx += o.sxx;
        self.sxy += o.sxy;
        self.syy += o.syy;
        self.sz += o.sz;
        self.sxz += o.sxz;
        self.syz += o.syz;
        self.szz += o.szz;
    }

    pub(crate) fn count(&self) -> usize {
        self.n as usize
    }

    /// Solves for `(piston, tilt_x, tilt_y)` at x = y = 0, the model used and the RMS residual.
    /// `None` without samples.
    pub(crate) fn solve(&self) -> Option<(PlaneCorrection, PlaneModel, f64)> {
        if self.n < 1.0 {
            return None;
        }
        let n = self.n;
        let (mx, my, mz) = (self.sx / n, self.sy / n, self.sz / n);
        // Centred second moments.
        let cxx = (self.sxx / n - mx * mx).max(0.0);
        let cyy = (self.syy / n - my * my).max(0.0);
        let cxy = self.sxy / n - mx * my;
        let cxz = self.sxz / n - mx * mz;
        let cyz = self.syz / n - my * mz;
        let czz = (self.szz / n - mz * mz).max(0.0);

        // Principal spreads of the sample positions.
        let tr = cxx + cyy;
        let det = cxx * cyy - cxy * cxy;
        let disc = ((tr * tr * 0.25) - det).max(0.0).sqrt();
        let l1 = tr * 0.5 + disc;
        let l2 = (tr * 0.5 - disc).max(0.0);

        let piston_only = |mz: f64| {
            (
                PlaneCorrection {
                    piston_um: mz,
                    ..PlaneCorrection::ZERO
                },
                PlaneModel::PistonOnly,
                czz.sqrt(),
            )
        };
        if n < 3.0 || l1 < MIN_SPREAD_PX * MIN_SPREAD_PX {
            return Some(piston_only(mz));
        }
        if l2 >= MIN_SPREAD_PX * MIN_SPREAD_PX {
            // Full fit: the 3x3 normal equations, solved by Cholesky.
            let m = Matrix3::new(
                self.n, self.sx, self.sy, self.sx, self.sxx, self.sxy, self.sy, self.sxy, self.syy,
            );
            let rhs = Vector3::new(self.sz, self.sxz, self.syz);
            if let Some(chol) = m.cholesky() {
                let sol = chol.solve(&rhs);
                if sol.iter().all(|v| v.is_finite()) {
                    let var = ((self.szz - sol.dot(&rhs)) / n).max(0.0);
                    return Some((
                        PlaneCorrection {
                            piston_um: sol[0],
                            tilt_x_um_per_px: sol[1],
                            tilt_y_um_per_px: sol[2],
                        },
                        PlaneModel::Full,
                        var.sqrt(),
                    ));
                }
            }
        }
        // Thin strip (or a failed factorisation): tilt along the principal axis u only.
        let (ux, uy) = if cxy.abs() > 1e-12 * l1 {
            let (vx, vy) = (l1 - cyy, cxy);
            let norm = (vx * vx + vy * vy).sqrt();
            (vx / norm, vy / norm)
        } else if cxx >= cyy {
            (1.0, 0.0)
        } else {
            (0.0, 1.0)
        };
        // Along u: variance of s = u.(p - m) is l1, covariance with z is ux*cxz + uy*cyz.
        let t = (ux * cxz + uy * cyz) / l1;
        if !t.is_finite() {
            return Some(piston_only(mz));
        }
        let (tx, ty) = (t * ux, t * uy);
        let var = (czz - t * (ux * cxz + uy * cyz)).max(0.0);
        Some((
            PlaneCorrection {
                piston_um: mz - tx * mx - ty * my,
                tilt_x_um_per_px: tx,
                tilt_y_um_per_px: ty,
            },
            PlaneModel::AlongStrip,
            var.sqrt(),
        ))
    }
}

avx2_dispatch! {
/// [n, sum x, sum x^2, sum z, sum x z, sum z^2] over the finite `z[i] - z_ref`, x = i, when
/// every value is finite (checked on the sums: a NaN or infinity propagates into them), else
/// `None`. Three lanes instead of six and no masks: most rows of a measurement have no
/// dropout.
fn row_sums_all_finite(z: &[f32], z_ref: f32) -> Option<[f64; 6]> {
    let mut acc = [f32x8::ZERO; 3];
    let mut xs = f32x8::new([0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]);
    let (z8, tail) = z.as_chunks::<8>();
    let zr = f32x8::splat(z_ref);
    for ch in z8 {
        let v = f32x8::new(*ch) - zr;
        acc[0] += v;
        acc[1] += v * xs;
        acc[2] += v * v;
        xs += f32x8::splat(8.0);
    }
    let acc = acc.map(|v| v.to_array());
    let mut t = acc.map(|a| a.iter().map(|&v| v as f64).sum::<f64>());
    let i0 = z.len() - tail.len();
    for (l, &v) in tail.iter().enumerate() {
        let x = (i0 + l) as f64;
        let v = (v - z_ref) as f64;
        t[0] += v;
        t[1] += v * x;
        t[2] += v * v;
    }
    if !t.iter().all(|v| v.is_finite()) {
        return None;
    }
    let n = z.len() as f64;
    Some([
        n,
        n * (n - 1.0) * 0.5,
        (n - 1.0) * n * (2.0 * n - 1.0) / 6.0,
        t[0],
        t[1],
        t[2],
    ])
}
}

avx2_dispatch! {
/// [`row_sums_all_finite`] for rows with invalid (non-finite) values: branch-free masked
/// f32 lanes, promoted to f64 per row.
fn row_sums_masked(z: &[f32], z_ref: f32) -> [f64; 6] {
    const L: usize = 8;
    let mut acc = [[0.0f32; L]; 6];
    let mut xs = [0.0f32; L];
    for (l, x) in xs.iter_mut().enumerate() {
        *x = l as f32;
    }
    let mut chunks = z.chunks_exact(L);
    for ch in chunks.by_ref() {
        for l in 0..L {
            let v = ch[l] - z_ref;
            let ok = v.is_finite();
            let m = if ok { 1.0 } else { 0.0 };
            let v = if ok { v } else { 0.0 };
            let x = xs[l];
            acc[0][l] += m;
            acc[1][l] += m * x;
            acc[2][l] += m * x * x;
            acc[3][l] += v;
            acc[4][l] += v * x;
            acc[5][l] += v * v;
            xs[l] = x + L as f32;
        }
    }
    let mut t = [0.0f64; 6];
    for (k, a) in acc.iter().enumerate() {
        t[k] = a.iter().map(|&v| v as f64).sum();
    }
    let i0 = z.len() - chunks.remainder().len();
    for (l, &v) in chunks.remainder().iter().enumerate() {
        if v.is_finite() {
            let x = (i0 + l) as f64;
            let v = (v - z_ref) as f64;
            t[0] += 1.0;
            t[1] += x;
            t[2] += x * x;
            t[3] += v;
            t[4] += v * x;
            t[5] += v * v;
        }
    }
    t
}
}

/// The least-squares plane of one raster over its valid pixels, as a [`PlaneCorrection`]
/// (subtracting it levels the raster). `None` when no plane fits (too few valid pixels).
pub fn fit_plane(raster: RasterView<'_, f32>) -> Option<PlaneCorrection> {
    let (cx, cy) = Shape::new(raster.rows(), raster.cols()).centre_px();
    let mut sums = PlaneSums::default();
    for row in 0..raster.rows() {
        sums.add_row(row as f64 - cy, -cx, raster.row(row));
    }
    sums.solve().map(|(p, _, _)| p)
}

/// Bilinear sample of `r` at (x, y) px; `None` outside the raster or when a corner with
/// non-zero weight is NaN.
#[inline]
pub(crate) fn sample_bilinear(r: &RasterView<'_, f32>, x: f64, y: f64) -> Option<f64> {
    if !(x >= 0.0 && y >= 0.0 && x <= (r.cols() - 1) as f64 && y <= (r.rows() - 1) as f64) {
        return None;
    }
    let x0 = x.floor() as usize;
    let y0 = y.floor() as usize;
    let fx = x - x0 as f64;
    let fy = y - y0 as f64;
    let x1 = (x0 + 1).min(r.cols() - 1);
    let y1 = (y0 + 1).min(r.rows() - 1);
    let w = r.cols();
    let h = r.values();
    let mut acc = 0.0;
    for (xi, yi, wt) in [
        (x0, y0, (1.0 - fx) * (1.0 - fy)),
        (x1, y0, fx * (1.0 - fy)),
        (x0, y1, (1.0 - fx) * fy),
        (x1, y1, fx * fy),
    ] {
        if wt > 0.0 {
            let v = h[yi * w + xi];
            if !v.is_finite() {
                return None;
            }
            acc += wt * v as f64;
        }
    }
    Some(acc)
}

/// The piston and tilt of tile `b` relative to its already-levelled neighbours.
///
/// Each neighbour comes with the offset of b relative to it (b's pixel (0, 0) minus the
/// neighbour's pixel (0, 0), px, (x, y)) and the correction already applied to it. For every
/// valid pixel of b that falls inside a neighbour, the neighbour is sampled bilinearly
/// (NaN-aware) and `diff = b - (neighbour - correction)` enters one least-squares plane fit over
/// all neighbours at once. Subtracting the returned correction from b brings it to the
/// neighbours' level.
///
/// When the overlapping pixels lie on a thin strip (spread across it below 2 px, e.g. a
/// one-pixel overlap) the tilt across the strip is not observable: the fit falls back to the
/// piston and the tilt along the strip, with zero tilt across it. With fewer than three samples
/// or all at one spot it returns the piston only. [`estimate_plane_report`] says which model
/// was used.
///
/// `None` for invalid input or when no neighbour overlaps a valid pixel of b.
pub fn estimate_plane(
    b: RasterView<'_, f32>,
    neighbours: &[(RasterView<'_, f32>, [f64; 2], PlaneCorrection)],
) -> Option<PlaneCorrection> {
    estimate_plane_report(b, neighbours)
        .ok()
        .map(|e| e.correction)
}

/// [`estimate_plane`] with the model used, the sample count and the residual, or the reason
/// there is no estimate.
pub fn estimate_plane_report(
    b: RasterView<'_, f32>,
    neighbours: &[(RasterView<'_, f32>, [f64; 2], PlaneCorrection)],
) -> Result<PlaneEstimate, PlaneError> {
    for (_, off, _) in neighbours {
        validate_offset(*off)?;
    }
    let (cx, cy) = Shape::new(b.rows(), b.cols()).centre_px();
    let mut sums = PlaneSums::default();
    for (nb, off, corr) in neighbours {
        let [ox, oy] = *off;
        // b pixel (r, c) sits at neighbour position (c + ox, r + oy).
        let c_lo = (-ox).ceil().max(0.0);
        let c_hi = ((nb.cols() - 1) as f64 - ox)
            .floor()
            .min((b.cols() - 1) as f64);
        let r_lo = (-oy).ceil().max(0.0);
        let r_hi = ((nb.rows() - 1) as f64 - oy)
            .floor()
            .min((b.rows() - 1) as f64);
        if c_lo > c_hi || r_lo > r_hi {
            continue;
        }
        let (c_lo, c_hi, r_lo, r_hi) = (c_lo as usize, c_hi as usize, r_lo as usize, r_hi as usize);
        let mut local = PlaneSums::default();
        for r in r_lo..=r_hi {
            let brow = b.row(r);
            let yn = r as f64 + oy;
            for (c, &zb) in brow.iter().enumerate().take(c_hi + 1).skip(c_lo) {
                if !zb.is_finite() {
                    continue;
                }
                let xn = c as f64 + ox;
                if let Some(zn) = sample_bilinear(nb, xn, yn) {
                    let zn = zn - corr.at(yn, xn, Shape::new(nb.rows(), nb.cols()));
                    local.add(c as f64 - cx, r as f64 - cy, zb as f64 - zn);
                }
            }
        }
        sums.merge(&local);
    }
    let samples = sums.count();
    let (correction, model, rms_residual_um) = sums.solve().ok_or(PlaneError::NoOverlap)?;
    Ok(PlaneEstimate {
        correction,
        model,
        samples,
        rms_residual_um,
    })
}
