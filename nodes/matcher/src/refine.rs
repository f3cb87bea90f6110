//! Lucas-Kanade refinement of a pair's offset on the heights of the overlap, with the
//! offset's covariance.
//!
//! The NCC's 3 x 3 stencil fit is exact on a clean Gaussian-like peak, but on a sparse strip
//! in white noise the sampled NCC surface carries the noise's own sharp peak: on the real cut
//! "sur-uncompressed 10 % noisy" (docs/registration.md) pairs accepted at NCC 0.61-0.99 were
//! 0.48-1.09 px off. Here the offset `d` (b's pixel (0, 0) minus a's) is found by Gauss-Newton
//! on the heights themselves: `b(x - d) = a(x) + piston + tilt_x x + tilt_y y` over the
//! overlap, the tiles' own piston and tilt being unknowns too. Both tiles are first smoothed by
//! a Gaussian of [`SMOOTH_SIGMA_PX`]: unsmoothed, the gradients are mostly noise, which biases
//! the answer and makes the covariance 2-10 times smaller than the answers' scatter (measured
//! on that cut with a NumPy prototype, 8 noise draws per pair).
//!
//! The covariance is the residual variance times the inverse of the normal matrix (the
//! offset's block), inflated by the number of pixels one smoothed noise sample spans
//! ([`CORRELATED_PX`]): residuals of smoothed noise are not independent.

use nalgebra::{SMatrix, SVector};
use surfstream_core::raster::RasterView;

/// Standard deviation of the Gaussian the heights are smoothed by, px.
pub const SMOOTH_SIGMA_PX: f64 = 1.0;

/// Radius of the smoothing kernel, px.
const KERNEL_RADIUS: usize = 3;

/// Pixels kept clear of every tile edge, px: the smoothing there would see a cut kernel in one
/// tile and a whole one in the other.
const EDGE_PX: f64 = 2.0;

/// Pixels whose smoothed noise is correlated: 1 + 4 pi sigma^2 (the area of the Gaussian's
/// autocorrelation). With it the predicted standard deviations matched the measured scatter of
/// the answers on the noisy real cut within a factor 1.5 (8 noise draws per pair).
const CORRELATED_PX: f64 = 1.0 + 4.0 * std::f64::consts::PI * SMOOTH_SIGMA_PX * SMOOTH_SIGMA_PX;

/// Gauss-Newton iterations at most. The two tiles' mean gradient is not the residual's exact
/// Jacobian, so along a weakly fixed direction the iteration converges linearly (the step
/// shrinks by 0.7 per iteration on the noisy real cut): up to 20 iterations were needed there.
const MAX_ITERATIONS: usize = 30;

/// The refinement is given up when it moves farther than this from its start, px: it then
/// disagrees with the NCC's answer, which stays.
pub const MAX_MOVE_PX: f64 = 1.0;

/// The iteration has settled when its step is below this, px (at a step ratio of 0.7 the
/// remaining error is about twice the last step).
const CONVERGED_PX: f64 = 1e-3;

/// Smallest number of samples in the refinement.
const MIN_SAMPLES: usize = 64;

/// A refined offset.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Refinement {
    /// b's pixel (0, 0) minus a's, px, (x, y).
    pub offset_px: [f64; 2],
    /// Covariance of `offset_px`, px^2, rows (x, y).
    pub covariance_px2: [[f64; 2]; 2],
    /// Samples used.
    pub samples: usize,
}

impl Refinement {
    /// The standard deviation along the offset's worst-known direction, px (the square root of
    /// the covariance's larger eigenvalue).
    pub fn worst_sd_px(&self) -> f64 {
        worst_sd_px(self.covariance_px2)
    }
}

/// The square root of the larger eigenvalue of a 2 x 2 covariance `c` (px^2): the standard
/// deviation along the worst-known direction, px.
pub fn worst_sd_px(c: [[f64; 2]; 2]) -> f64 {
    let mean = 0.5 * (c[0][0] + c[1][1]);
    let disc = (0.25 * (c[0][0] - c[1][1]).powi(2) + c[0][1] * c[1][0]).sqrt();
    (mean + disc).max(0.0).sqrt()
}

/// A tile region smoothed by a Gaussian of [`SMOOTH_SIGMA_PX`], NaN where the tile is not
/// measured; normalised convolution, so missing points do not bleed into the others.
struct Smoothed {
    x0: usize,
    y0: usize,
    w: usize,
    h: usize,
    z: Vec<f64>,
}

impl Smoothed {
    fn new(t: &RasterView<'_, f32>, x0: usize, y0: usize, w: usize, h: usize) -> Self {
        let k: Vec<f64> = (0..=2 * KERNEL_RADIUS)
            .map(|i| {
                let d = i as f64 - KERNEL_RADIUS as f64;
                (-0.5 * d * d / (SMOOTH_SIGMA_PX * SMOOTH_SIGMA_PX)).exp()
            })
            .collect();
        let r = KERNEL_RADIUS as i64;
        // Pass along x over rows y0 - r .. y0 + h + r (within the tile), then along y.
        let ya = (y0 as i64 - r).max(0) as usize;
        let yb = ((y0 + h) as i64 + r).min(t.rows() as i64) as usize;
        let mut sx = vec![0.0; (yb - ya) * w];
        let mut wx = vec![0.0; (yb - ya) * w];
        for y in ya..yb {
            let row = t.row(y);
            for x in 0..w {
                let (mut s, mut ws) = (0.0, 0.0);
                for (i, kv) in k.iter().enumerate() {
                    let xx = (x0 + x) as i64 + i as i64 - r;
                    if xx < 0 || xx >= t.cols() as i64 {
                        continue;
                    }
                    let v = row[xx as usize];
                    if v.is_finite() {
                        s += kv * v as f64;
                        ws += kv;
                    }
                }
                sx[(y - ya) * w + x] = s;
                wx[(y - ya) * w + x] = ws;
            }
        }
        let mut z = vec![f64::NAN; w * h];
        for y in 0..h {
            let own = t.row(y0 + y);
            for x in 0..w {
                if !own[x0 + x].is_finite() {
                    continue;
                }
                let (mut s, mut ws) = (0.0, 0.0);
                for (i, kv) in k.iter().enumerate() {
                    let yy = (y0 + y) as i64 + i as i64 - r;
                    if yy < ya as i64 || yy >= yb as i64 {
                        continue;
                    }
                    let j = (yy as usize - ya) * w + x;
                    s += kv * sx[j];
                    ws += kv * wx[j];
                }
                if ws > 0.0 {
                    z[y * w + x] = s / ws;
                }
            }
        }
        Smoothed { x0, y0, w, h, z }
    }

    /// The height at tile pixel (x, y), NaN outside the region or where not measured.
    fn at(&self, x: i64, y: i64) -> f64 {
        let (xr, yr) = (x - self.x0 as i64, y - self.y0 as i64);
        if xr < 0 || yr < 0 || xr >= self.w as i64 || yr >= self.h as i64 {
            return f64::NAN;
        }
        self.z[yr as usize * self.w + xr as usize]
    }

    /// Keys' cubic convolution (a = -1/2) at the tile point (x, y), with its gradient; `None`
    /// where any of the 4 x 4 samples is missing.
    fn cubic(&self, x: f64, y: f64) -> Option<(f64, [f64; 2])> {
        let (ix, iy) = (x.floor(), y.floor());
        let (fx, fy) = (x - ix, y - iy);
        let (wx, dx) = keys(fx);
        let (wy, dy) = keys(fy);
        let (mut v, mut gx, mut gy) = (0.0, 0.0, 0.0);
        for j in 0..4 {
            for i in 0..4 {
                let z = self.at(ix as i64 - 1 + i as i64, iy as i64 - 1 + j as i64);
                if !z.is_finite() {
                    return None;
                }
                v += wy[j] * wx[i] * z;
                gx += wy[j] * dx[i] * z;
                gy += dy[j] * wx[i] * z;
            }
        }
        Some((v, [gx, gy]))
    }
}

/// Keys' cubic weights for the samples at -1, 0, 1, 2 around a point `t` in [0, 1) past the
/// second, and their derivatives in `t`.
fn keys(t: f64) -> ([f64; 4], [f64; 4]) {
    let a = -0.5;
    let near = |s: f64| ((a + 2.0) * s - (a + 3.0)) * s * s + 1.0;
    let near_d = |s: f64| (3.0 * (a + 2.0) * s - 2.0 * (a + 3.0)) * s;
    let far = |s: f64| ((a * s - 5.0 * a) * s + 8.0 * a) * s - 4.0 * a;
    let far_d = |s: f64| (3.0 * a * s - 10.0 * a) * s + 8.0 * a;
    // Distances of the samples from the point: 1 + t, t, 1 - t, 2 - t.
    (
        [far(1.0 + t), near(t), near(1.0 - t), far(2.0 - t)],
        [far_d(1.0 + t), near_d(t), -near_d(1.0 - t), -far_d(2.0 - t)],
    )
}

/// Refines `offset_px` (b's pixel (0, 0) minus a's, px, (x, y)) on the heights of the overlap;
/// `None` when the overlap is too small, the system is singular, the iteration does not settle
/// or it moves more than [`MAX_MOVE_PX`] from the start.
pub fn refine_offset(
    a: RasterView<'_, f32>,
    b: RasterView<'_, f32>,
    offset_px: [f64; 2],
) -> Option<Refinement> {
    if !(offset_px[0].is_finite() && offset_px[1].is_finite()) {
        return None;
    }
    let (wa, ha) = (a.cols() as f64, a.rows() as f64);
    let (wb, hb) = (b.cols() as f64, b.rows() as f64);
    // Samples at a's integer pixels whose b point stays EDGE_PX inside b for any offset within
    // MAX_MOVE_PX of the start, and EDGE_PX inside a.
    let m = EDGE_PX + MAX_MOVE_PX;
    let xa = (offset_px[0] + m).ceil().max(EDGE_PX);
    let xb = (offset_px[0] + wb - 1.0 - m)
        .floor()
        .min(wa - 1.0 - EDGE_PX);
    let ya = (offset_px[1] + m).ceil().max(EDGE_PX);
    let yb = (offset_px[1] + hb - 1.0 - m)
        .floor()
        .min(ha - 1.0 - EDGE_PX);
    if !(xb >= xa + 2.0 && yb >= ya + 2.0) {
        return None;
    }
    let (xa, xb, ya, yb) = (xa as usize, xb as usize, ya as usize, yb as usize);
    let sa = Smoothed::new(&a, xa - 1, ya - 1, xb - xa + 3, yb - ya + 3);
    // b's region: the a region moved by the offset, with room for the move and the 4 x 4 taps.
    let bx0 = ((xa as f64 - offset_px[0] - MAX_MOVE_PX).floor() - 2.0).max(0.0) as usize;
    let by0 = ((ya as f64 - offset_px[1] - MAX_MOVE_PX).floor() - 2.0).max(0.0) as usize;
    let bx1 = ((xb as f64 - offset_px[0] + MAX_MOVE_PX).ceil() + 3.0).min(wb) as usize;
    let by1 = ((yb as f64 - offset_px[1] + MAX_MOVE_PX).ceil() + 3.0).min(hb) as usize;
    if bx1 <= bx0 || by1 <= by0 {
        return None;
    }
    let sb = Smoothed::new(&b, bx0, by0, bx1 - bx0, by1 - by0);
    let cx = 0.5 * (xa + xb) as f64;
    let cy = 0.5 * (ya + yb) as f64;
    // The samples are chosen once: a's pixels whose b point has its whole interpolation support
    // measured for every offset the iteration may reach (the corners of the move box bound
    // it). A set that changed with the offset (a dropout entering a sample's support) made the
    // iteration cycle between two answers 0.02 px apart on the bench's pills.
    let m = MAX_MOVE_PX;
    let mut samples: Vec<(f64, f64, f64, Option<[f64; 2]>)> = Vec::new();
    for y in ya..=yb {
        for x in xa..=xb {
            let za = sa.at(x as i64, y as i64);
            if !za.is_finite() {
                continue;
            }
            let (bx, by) = (x as f64 - offset_px[0], y as f64 - offset_px[1]);
            let supported = [(-m, -m), (-m, m), (m, -m), (m, m)]
                .iter()
                .all(|&(dx, dy)| sb.cubic(bx + dx, by + dy).is_some());
            if !supported {
                continue;
            }
            let gax = 0.5 * (sa.at(x as i64 + 1, y as i64) - sa.at(x as i64 - 1, y as i64));
            let gay = 0.5 * (sa.at(x as i64, y as i64 + 1) - sa.at(x as i64, y as i64 - 1));
            let ga = (gax.is_finite() && gay.is_finite()).then_some([gax, gay]);
            samples.push((x as f64, y as f64, za, ga));
        }
    }
    if samples.len() < MIN_SAMPLES {
        return None;
    }
    let mut d = offset_px;
    for _ in 0..MAX_ITERATIONS {
        // Unknowns: the offset's change (x, y), piston, tilt x, tilt y (per px).
        let mut n = SMatrix::<f64, 5, 5>::zeros();
        let mut rhs = SVector::<f64, 5>::zeros();
        let mut rr = 0.0;
        let mut count = 0usize;
        for &(x, y, za, ga) in &samples {
            let (zb, gb) = sb.cubic(x - d[0], y - d[1])?;
            // The gradient of both tiles (b's interpolated, a's by central differences)
            // halves the noise in it.
            let g = ga.map_or(gb, |ga| [0.5 * (gb[0] + ga[0]), 0.5 * (gb[1] + ga[1])]);
            let j = SVector::<f64, 5>::new(g[0], g[1], 1.0, x - cx, y - cy);
            let r = zb - za;
            n += j * j.transpose();
            rhs += j * r;
            rr += r * r;
            count += 1;
        }
        if count < MIN_SAMPLES {
            return None;
        }
        let chol = n.cholesky()?;
        let theta = chol.solve(&rhs);
        let step = [theta[0], theta[1]];
        if !(step[0].is_finite() && step[1].is_finite()) {
            return None;
        }
        // Clamp a wild step (a near-singular system far from the answer).
        let big = step[0].abs().max(step[1].abs());
        if std::env::var_os("SURFSTREAM_DEBUG_LK").is_some() {
            eprintln!("lk: d {d:?} step {step:?} count {count}");
        }
        let scale = if big > 0.5 { 0.5 / big } else { 1.0 };
        d = [d[0] + scale * step[0], d[1] + scale * step[1]];
        if (d[0] - offset_px[0]).abs() > MAX_MOVE_PX || (d[1] - offset_px[1]).abs() > MAX_MOVE_PX {
            return None;
        }
        if big < CONVERGED_PX {
            // The residual of the linearised fit at the solution: rr - theta . rhs.
            let dof = count.saturating_sub(5).max(1) as f64;
            let s2 = ((rr - theta.dot(&rhs)).max(0.0) / dof) * CORRELATED_PX;
            let inv = chol.inverse();
            let cov = [
                [s2 * inv[(0, 0)], s2 * inv[(0, 1)]],
                [s2 * inv[(1, 0)], s2 * inv[(1, 1)]],
            ];
            if !(cov[0][0] > 0.0 && cov[1][1] > 0.0) {
                return None;
            }
            return Some(Refinement {
                offset_px: d,
                covariance_px2: cov,
                samples: count,
            });
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use surfstream_core::raster::Shape;

    #[test]
    fn keys_weights_sum_to_one_and_interpolate() {
        for t in [0.0, 0.25, 0.5, 0.9] {
            let (w, dw) = keys(t);
            assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-12);
            assert!(dw.iter().sum::<f64>().abs() < 1e-12);
            // A line is reproduced, and its slope.
            let v: f64 = (0..4).map(|i| w[i] * (i as f64 - 1.0)).sum();
            let s: f64 = (0..4).map(|i| dw[i] * (i as f64 - 1.0)).sum();
            assert!((v - t).abs() < 1e-12, "{t}: {v}");
            assert!((s - 1.0).abs() < 1e-12, "{t}: {s}");
        }
    }

    /// A smooth field of bumps sampled at (x + ox, y + oy).
    fn tile(n: usize, ox: f64, oy: f64, plane: [f64; 3]) -> Vec<f32> {
        let mut v = Vec::with_capacity(n * n);
        for y in 0..n {
            for x in 0..n {
                let (u, w) = (x as f64 + ox, y as f64 + oy);
                let z = (0.21 * u).sin() * (0.17 * w).cos() + 0.5 * (0.11 * u + 0.07 * w).sin();
                v.push((z + plane[0] + plane[1] * x as f64 + plane[2] * y as f64) as f32);
            }
        }
        v
    }

    #[test]
    fn a_known_offset_is_found_with_piston_and_tilt() {
        let n = 64;
        let a = tile(n, 0.0, 0.0, [0.0, 0.0, 0.0]);
        let truth = [40.3, 2.7];
        let b = tile(n, truth[0], truth[1], [0.3, 0.002, -0.003]);
        let sh = Shape::new(n, n);
        let (va, vb) = (
            RasterView::new(&a, sh).unwrap(),
            RasterView::new(&b, sh).unwrap(),
        );
        let r = refine_offset(va, vb, [40.0, 3.0]).expect("refined");
        assert!(
            (r.offset_px[0] - truth[0]).abs() < 0.01 && (r.offset_px[1] - truth[1]).abs() < 0.01,
            "{:?}",
            r.offset_px
        );
        assert!(r.worst_sd_px() < 0.01, "{}", r.worst_sd_px());
    }
}
