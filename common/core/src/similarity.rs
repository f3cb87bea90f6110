//! Structural similarity (SSIM) of two height maps, NaN-aware.
//!
//! The paper's eq. (7) is Wang, Bovik, Sheikh & Simoncelli (2004), "Image quality assessment:
//! from error visibility to structural similarity", eq. (13):
//!
//! `SSIM(x, y) = (2 mu_x mu_y + C1)(2 sigma_xy + C2) / ((mu_x^2 + mu_y^2 + C1)(sigma_x^2 + sigma_y^2 + C2))`
//!
//! with the paper's constants: local statistics under an 11 x 11 circular-symmetric Gaussian
//! window of standard deviation 1.5 px (normalised to sum 1), `C1 = (K1 L)^2`, `C2 = (K2 L)^2`,
//! `K1 = 0.01`, `K2 = 0.03`. `L` is the dynamic range: for 8-bit images Wang uses 255; height
//! maps have no fixed range, so [`ssim`] takes it from the data (max - min over the pixels
//! valid in both maps) unless the caller passes one. The mean SSIM (MSSIM, eq. 17) averages
//! the map over every window that lies entirely inside the image (no padding at the borders,
//! like Wang's reference code's 'valid' filtering).
//!
//! Non-measured pixels: a pixel takes part only where both maps are finite. Inside a window
//! the Gaussian weights of those pixels are renormalised to sum 1; a window whose valid pixels
//! carry less than half of the Gaussian weight is left out of the mean (too little data to say
//! anything). On NaN-free input this is exactly Wang's MSSIM.

use std::fmt;

/// Window side (px), Gaussian sigma (px) and constants of Wang et al. (2004).
pub const WINDOW_PX: usize = 11;
pub const SIGMA_PX: f64 = 1.5;
pub const K1: f64 = 0.01;
pub const K2: f64 = 0.03;
/// A window enters the mean only if its valid pixels carry at least this share of the weight.
pub const MIN_VALID_WEIGHT: f64 = 0.5;

/// Why SSIM could not be computed.
#[derive(Debug, Clone, PartialEq)]
pub enum SsimError {
    /// The two maps, or a map and its stated shape, disagree.
    Shape {
        what: &'static str,
        expected: usize,
        found: usize,
    },
    /// A side is shorter than the 11 px window.
    TooSmall { rows: usize, cols: usize },
    /// No window has enough pixels valid in both maps.
    NoValidWindow,
    /// The dynamic range given is not finite and positive.
    BadRange(f64),
}

impl fmt::Display for SsimError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            SsimError::Shape {
                what,
                expected,
                found,
            } => write!(f, "ssim: {what} has {found} values, expected {expected}"),
            SsimError::TooSmall { rows, cols } => write!(
                f,
                "ssim: map of {rows} x {cols} px is smaller than the {WINDOW_PX} x {WINDOW_PX} px window"
            ),
            SsimError::NoValidWindow => write!(
                f,
                "ssim: no {WINDOW_PX} x {WINDOW_PX} window has enough pixels measured in both maps"
            ),
            SsimError::BadRange(l) => {
                write!(
                    f,
                    "ssim: dynamic range {l}: expected a finite number > 0 (um)"
                )
            }
        }
    }
}

impl std::error::Error for SsimError {}

/// The mean SSIM and what it was computed over.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ssim {
    /// Mean SSIM over the windows used, in [-1, 1]; 1 = identical.
    pub mssim: f64,
    /// Number of windows that entered the mean.
    pub windows: usize,
    /// The dynamic range L used for C1 and C2 (um).
    pub range_um: f64,
}

/// The normalised 1-D Gaussian (the 2-D window is its outer product, so the filtering is
/// separable).
fn gaussian_1d() -> [f64; WINDOW_PX] {
    let mut g = [0.0; WINDOW_PX];
    let c = (WINDOW_PX / 2) as f64;
    for (i, v) in g.iter_mut().enumerate() {
        let d = i as f64 - c;
        *v = (-d * d / (2.0 * SIGMA_PX * SIGMA_PX)).exp();
    }
    let s: f64 = g.iter().sum();
    g.iter_mut().for_each(|v| *v /= s);
    g
}

/// Mean SSIM of `a` and `b` (row-major `rows x cols`, NaN / inf = not measured). `range_um`
/// is L; `None` takes max - min of the pixels valid in both (1.0 if that is 0: two constant
/// maps).
pub fn ssim(
    a: &[f32],
    b: &[f32],
    rows: usize,
    cols: usize,
    range_um: Option<f64>,
) -> Result<Ssim, SsimError> {
    let n = rows * cols;
    for (what, v) in [("first map", a), ("second map", b)] {
        if v.len() != n {
            return Err(SsimError::Shape {
                what,
                expected: n,
                found: v.len(),
            });
        }
    }
    if rows < WINDOW_PX || cols < WINDOW_PX {
        return Err(SsimError::TooSmall { rows, cols });
    }
    let range = match range_um {
        Some(l) if l.is_finite() && l > 0.0 => l,
        Some(l) => return Err(SsimError::BadRange(l)),
        None => {
            let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
            for (&x, &y) in a.iter().zip(b) {
                if x.is_finite() && y.is_finite() {
                    for v in [x as f64, y as f64] {
                        lo = lo.min(v);
                        hi = hi.max(v);
                    }
                }
            }
            if hi > lo {
                hi - lo
            } else {
                1.0
            }
        }
    };
    let c1 = (K1 * range).powi(2);
    let c2 = (K2 * range).powi(2);
    // Centre the data on a common value, so the variances below do not cancel in f64 when the
    // heights sit far from zero.
    let shift = a
        .iter()
        .zip(b)
        .find(|(x, y)| x.is_finite() && y.is_finite())
        .map_or(0.0, |(&x, _)| x as f64);

    // Six masked moments, filtered along rows ('valid': out width cols - 10), then columns.
    let g = gaussian_1d();
    let ow = cols - WINDOW_PX + 1;
    let oh = rows - WINDOW_PX + 1;
    let mut horiz = vec![[0.0f64; 6]; rows * ow];
    let mut line = vec![[0.0f64; 6]; cols];
    for r in 0..rows {
        for (c, m) in line.iter_mut().enumerate() {
            let (x, y) = (a[r * cols + c], b[r * cols + c]);
            *m = if x.is_finite() && y.is_finite() {
                let (x, y) = (x as f64 - shift, y as f64 - shift);
                [1.0, x, y, x * x, y * y, x * y]
            } else {
                [0.0; 6]
            };
        }
        for c in 0..ow {
            let mut acc = [0.0f64; 6];
            for (k, &gk) in g.iter().enumerate() {
                let m = &line[c + k];
                for q in 0..6 {
                    acc[q] += gk * m[q];
                }
            }
            horiz[r * ow + c] = acc;
        }
    }
    let mut sum = 0.0f64;
    let mut windows = 0usize;
    for r in 0..oh {
        for c in 0..ow {
            let mut s = [0.0f64; 6];
            for (k, &gk) in g.iter().enumerate() {
                let m = &horiz[(r + k) * ow + c];
                for q in 0..6 {
                    s[q] += gk * m[q];
                }
            }
            let w = s[0];
            if w < MIN_VALID_WEIGHT {
                continue;
            }
            let (mx, my) = (s[1] / w, s[2] / w);
            // Weighted (biased) local moments, as Wang's reference code computes them.
            let vx = (s[3] / w - mx * mx).max(0.0);
            let vy = (s[4] / w - my * my).max(0.0);
            let cxy = s[5] / w - mx * my;
            // mu is shift-invariant only in the luminance term: restore the true means there.
            let (ux, uy) = (mx + shift, my + shift);
            let v = ((2.0 * ux * uy + c1) * (2.0 * cxy + c2))
                / ((ux * ux + uy * uy + c1) * (vx + vy + c2));
            sum += v;
            windows += 1;
        }
    }
    if windows == 0 {
        return Err(SsimError::NoValidWindow);
    }
    Ok(Ssim {
        mssim: sum / windows as f64,
        windows,
        range_um: range,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn texture(rows: usize, cols: usize, seed: u32) -> Vec<f32> {
        let mut s = seed.wrapping_mul(2654435761).wrapping_add(1);
        (0..rows * cols)
            .map(|i| {
                s ^= s << 13;
                s ^= s >> 17;
                s ^= s << 5;
                let (r, c) = ((i / cols) as f32, (i % cols) as f32);
                (0.3 * r).sin() + (0.2 * c).cos() + (s % 1000) as f32 / 2000.0
            })
            .collect()
    }

    #[test]
    fn identical_maps_score_one() {
        let a = texture(40, 33, 1);
        let s = ssim(&a, &a, 40, 33, None).unwrap();
        assert!((s.mssim - 1.0).abs() < 1e-12, "{}", s.mssim);
        assert_eq!(s.windows, 30 * 23);
    }

    #[test]
    fn matches_a_direct_evaluation_of_wang_eq_13() {
        // One window (11 x 11 input): the mean is the formula evaluated once with the
        // Gaussian-weighted moments, computed here the slow, obvious way.
        let a = texture(11, 11, 2);
        let b = texture(11, 11, 3);
        let g = gaussian_1d();
        let (mut mx, mut my) = (0.0, 0.0);
        for r in 0..11 {
            for c in 0..11 {
                let w = g[r] * g[c];
                mx += w * a[r * 11 + c] as f64;
                my += w * b[r * 11 + c] as f64;
            }
        }
        let (mut vx, mut vy, mut cxy) = (0.0, 0.0, 0.0);
        for r in 0..11 {
            for c in 0..11 {
                let w = g[r] * g[c];
                let (dx, dy) = (a[r * 11 + c] as f64 - mx, b[r * 11 + c] as f64 - my);
                vx += w * dx * dx;
                vy += w * dy * dy;
                cxy += w * dx * dy;
            }
        }
        let l = 2.0;
        let (c1, c2) = ((0.01 * l) * (0.01 * l), (0.03 * l) * (0.03 * l));
        let want =
            ((2.0 * mx * my + c1) * (2.0 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2));
        let got = ssim(&a, &b, 11, 11, Some(l)).unwrap();
        assert_eq!(got.windows, 1);
        assert!((got.mssim - want).abs() < 1e-12, "{} vs {want}", got.mssim);
        assert!(got.mssim < 0.9, "different textures are not similar");
    }

    #[test]
    fn nan_pixels_are_left_out_not_propagated() {
        let a = texture(30, 30, 4);
        let mut b = a.clone();
        // Holes in one map only: where both are measured the maps agree, so SSIM stays 1.
        for i in (0..900).step_by(7) {
            b[i] = f32::NAN;
        }
        let s = ssim(&a, &b, 30, 30, None).unwrap();
        assert!((s.mssim - 1.0).abs() < 1e-12, "{}", s.mssim);
        // A big hole removes the windows it dominates.
        let mut c = a.clone();
        for r in 0..30 {
            for v in &mut c[r * 30..r * 30 + 20] {
                *v = f32::NAN;
            }
        }
        let s = ssim(&a, &c, 30, 30, None).unwrap();
        assert!(s.mssim.is_finite() && s.windows < 400);
        let all_nan = vec![f32::NAN; 900];
        assert_eq!(
            ssim(&a, &all_nan, 30, 30, None),
            Err(SsimError::NoValidWindow)
        );
    }

    #[test]
    fn noise_lowers_the_score_and_bad_input_is_an_error() {
        let a = texture(32, 32, 5);
        let noisy: Vec<f32> = a
            .iter()
            .zip(texture(32, 32, 9))
            .map(|(x, n)| x + 0.5 * n)
            .collect();
        let s = ssim(&a, &noisy, 32, 32, None).unwrap().mssim;
        assert!(s < 0.99 && s > 0.0, "{s}");
        assert!(matches!(
            ssim(&a, &a[..10], 32, 32, None),
            Err(SsimError::Shape { .. })
        ));
        assert!(matches!(
            ssim(&a[..100], &a[..100], 10, 10, None),
            Err(SsimError::TooSmall { .. })
        ));
        assert!(matches!(
            ssim(&a, &a, 32, 32, Some(f64::NAN)),
            Err(SsimError::BadRange(_))
        ));
    }
}
