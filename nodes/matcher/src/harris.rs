//! Harris corners (the reference study's Appendix A; Harris & Stephens 1988).
//!
//! On the stretched detector image ([`DetectorImage::values`]):
//! 1. gradients Ix, Iy by central differences;
//! 2. the structure tensor M = G_sigma * [Ix^2, IxIy; IxIy, Iy^2], a Gaussian window of
//!    `window_sigma_px`;
//! 3. the response R = det M - k (tr M)^2 with `k` in 0.04..0.06 (0.04 by default): R > 0 at
//!    corners (two large eigenvalues), R < 0 on edges (one), |R| small on flat ground;
//! 4. a threshold `R > relative_threshold * max R` (and R > 0);
//! 5. non-maximum suppression: a corner is the strict maximum of R over the
//!    `(2 nms_radius_px + 1)^2` square around it;
//! 6. the `max_corners` strongest survive, each located to sub-pixel by a 3-point parabola of
//!    R along x and along y.
//!
//! Dropouts: the structure tensor is a normalised convolution over measured gradients only,
//! and a corner is dropped when its pixel is not measured, when less than
//! `min_support_valid` of its support (the gradient stencil grown by the window's 3-sigma
//! radius) is, or when the support leaves the image (see [`crate::detector`]).

use crate::detector::{bad, gaussian_blur, DetectorImage};
use crate::raster::InputError;

/// Parameters of [`harris_corners`].
#[derive(Debug, Clone, PartialEq)]
pub struct HarrisParams {
    /// Harris' k, 0.04..=0.06.
    pub k: f64,
    /// Sigma of the Gaussian window of the structure tensor, px.
    pub window_sigma_px: f64,
    /// Keep responses above this fraction of the largest response in the image.
    pub relative_threshold: f64,
    /// Half side of the non-maximum suppression square, px.
    pub nms_radius_px: usize,
    /// Keep at most this many corners (strongest first).
    pub max_corners: usize,
}

impl Default for HarrisParams {
    fn default() -> Self {
        HarrisParams {
            k: 0.04,
            window_sigma_px: 1.5,
            relative_threshold: 0.001,
            nms_radius_px: 3,
            max_corners: 400,
        }
    }
}

impl HarrisParams {
    /// Checks ranges; the error names the parameter.
    pub fn validate(&self) -> Result<(), InputError> {
        if !(0.04..=0.06).contains(&self.k) {
            return Err(bad("harris.k", "must be in 0.04..=0.06"));
        }
        if !(self.window_sigma_px.is_finite() && (0.3..=20.0).contains(&self.window_sigma_px)) {
            return Err(bad("harris.window_sigma_px", "must be in [0.3, 20]"));
        }
        if !(self.relative_threshold.is_finite() && (0.0..1.0).contains(&self.relative_threshold)) {
            return Err(bad("harris.relative_threshold", "must be in [0, 1)"));
        }
        if self.nms_radius_px == 0 || self.nms_radius_px > 50 {
            return Err(bad("harris.nms_radius_px", "must be in 1..=50"));
        }
        if self.max_corners == 0 || self.max_corners > 100_000 {
            return Err(bad("harris.max_corners", "must be in 1..=100000"));
        }
        Ok(())
    }
}

/// One corner, in tile pixels (sub-pixel), with its Harris response.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Corner {
    pub x: f64,
    pub y: f64,
    pub response: f64,
}

/// The Harris response R = det M - k tr^2 M of every pixel, with the structure tensor as a
/// normalised convolution: only gradients whose central-difference stencil is measured
/// (`mask` 1) enter, and each window sum is divided by the window weight they carry. Returns
/// R and that weight (1 = the whole window measured); R is 0 where the weight is 0.
pub fn harris_response(
    img: &[f32],
    mask: &[f32],
    w: usize,
    h: usize,
    params: &HarrisParams,
) -> (Vec<f32>, Vec<f32>) {
    let mut ixx = vec![0f32; w * h];
    let mut iyy = vec![0f32; w * h];
    let mut ixy = vec![0f32; w * h];
    let mut gm = vec![0f32; w * h];
    for y in 1..h.saturating_sub(1) {
        for x in 1..w.saturating_sub(1) {
            let i = y * w + x;
            if mask[i + 1] * mask[i - 1] * mask[i + w] * mask[i - w] == 0.0 {
                continue;
            }
            let gx = 0.5 * (img[i + 1] - img[i - 1]);
            let gy = 0.5 * (img[i + w] - img[i - w]);
            ixx[i] = gx * gx;
            iyy[i] = gy * gy;
            ixy[i] = gx * gy;
            gm[i] = 1.0;
        }
    }
    let s = params.window_sigma_px;
    let (a, b, c, wt) = (
        gaussian_blur(&ixx, w, h, s),
        gaussian_blur(&iyy, w, h, s),
        gaussian_blur(&ixy, w, h, s),
        gaussian_blur(&gm, w, h, s),
    );
    let k = params.k as f32;
    let r = (0..w * h)
        .map(|i| {
            if wt[i] <= 1e-6 {
                return 0.0;
            }
            let (a, b, c) = (a[i] / wt[i], b[i] / wt[i], c[i] / wt[i]);
            a * b - c * c - k * (a + b) * (a + b)
        })
        .collect();
    (r, wt)
}

/// Harris corners of a detector image, strongest first, in tile pixel coordinates.
pub fn harris_corners(
    image: &DetectorImage,
    params: &HarrisParams,
) -> Result<Vec<Corner>, InputError> {
    params.validate()?;
    let (w, h) = (image.width, image.height);
    if image.valid_px == 0 || w < 3 || h < 3 {
        return Ok(Vec::new());
    }
    let (img, mask) = image.values_and_mask();
    let (r, weight) = harris_response(&img, &mask, w, h, params);
    // Support: the central-difference stencil (1 px) grown by the window's truncation radius.
    let support = 1 + (3.0 * params.window_sigma_px).ceil() as i64;
    let min_weight = image.min_support_valid as f32;
    let usable = |x: i64, y: i64| {
        weight[y as usize * w + x as usize] >= min_weight && image.support_ok(x, y, support)
    };
    let max_r = (0..w * h)
        .filter(|i| usable((i % w) as i64, (i / w) as i64))
        .map(|i| r[i])
        .fold(0f32, f32::max);
    if max_r <= 0.0 {
        return Ok(Vec::new());
    }
    let threshold = (params.relative_threshold as f32 * max_r).max(f32::MIN_POSITIVE);
    let nr = params.nms_radius_px as i64;
    let mut corners = Vec::new();
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            let v = r[y * w + x];
            if v <= threshold {
                continue;
            }
            let (xi, yi) = (x as i64, y as i64);
            let mut is_max = true;
            'nms: for yy in (yi - nr).max(0)..=(yi + nr).min(h as i64 - 1) {
                for xx in (xi - nr).max(0)..=(xi + nr).min(w as i64 - 1) {
                    if (xx, yy) == (xi, yi) {
                        continue;
                    }
                    let o = r[yy as usize * w + xx as usize];
                    // Ties go to the earlier pixel in scan order, so a plateau gives one corner.
                    if o > v || (o == v && (yy, xx) < (yi, xi)) {
                        is_max = false;
                        break 'nms;
                    }
                }
            }
            if !is_max || !usable(xi, yi) {
                continue;
            }
            let i = y * w + x;
            let dx = parabola_peak(r[i - 1], v, r[i + 1]);
            let dy = parabola_peak(r[i - w], v, r[i + w]);
            corners.push(Corner {
                x: image.origin_x as f64 + x as f64 + dx,
                y: image.origin_y as f64 + y as f64 + dy,
                response: v as f64,
            });
        }
    }
    corners.sort_by(|a, b| b.response.total_cmp(&a.response));
    corners.truncate(params.max_corners);
    Ok(corners)
}

/// Vertex of the parabola through (-1, a), (0, b), (1, c), clamped to [-0.5, 0.5].
pub(crate) fn parabola_peak(a: f32, b: f32, c: f32) -> f64 {
    let (a, b, c) = (a as f64, b as f64, c as f64);
    let den = a - 2.0 * b + c;
    if den >= 0.0 || !den.is_finite() {
        return 0.0;
    }
    (0.5 * (a - c) / den).clamp(-0.5, 0.5)
}
