//! Height map -> detector input: the image the Harris and SIFT detectors see.
//!
//! Corner and blob detectors expect an image whose contrast is texture, not form: a height map
//! carries piston, tilt and long-wavelength form that dwarf the roughness, and NaN dropouts.
//! [`DetectorImage::from_region`] converts one rectangle of a tile in three documented steps:
//!
//! 1. **Levelling**: the least-squares plane over the region's valid pixels is subtracted
//!    (piston and tilt differ from tile to tile; [`crate::fit_plane`]).
//! 2. **Band-pass**: a NaN-aware Gaussian low-pass (normalised convolution: the blur of the
//!    valid heights divided by the blur of the validity mask, sigma `highpass_sigma_px`) is
//!    subtracted, so waviness longer than a few sigma does not steer the detectors, and the
//!    heights are first smoothed the same way with `smoothing_sigma_px`, so that instrument
//!    noise at the pixel scale does not either (on the smooth specimen with 10 % noise the
//!    Harris windows otherwise correlate below 0.7 and no pair is matched). The result is
//!    [`DetectorImage::signal`] (um), what NCC windows are cut from.
//! 3. **Robust stretch**: the signal is clipped to its `clip_percentiles` (1st and 99th by
//!    default) and mapped linearly onto [0, 1], so one spike or scratch does not set the
//!    contrast: [`DetectorImage::values`], what the detectors threshold.
//!
//! NaN never enters a detector or a descriptor as a number. Invalid pixels stay NaN in both
//! images; every filter runs as a normalised convolution (the blur of the valid values
//! divided by the blur of the validity mask), so a dropout is neither a zero nor a guess but
//! simply absent from the weighted means; and a feature is dropped when less than
//! `min_support_valid` (90 %) of its support is measured (the structure-tensor window for
//! Harris, the descriptor footprint for SIFT, each NCC window) or when its own pixel is not
//! ([`DetectorImage::valid_fraction`], an integral image of the invalid pixels). Requiring a
//! fully measured support instead loses almost every feature on tiles with 0.5 % scattered
//! single-pixel dropouts (a 21 x 21 window is then clean with probability 0.11): measured on
//! the anchors' noisy sets, where it left 40 % of the pairs answered.

use surfstream_core::raster::{Raster, RasterView, Shape};

use crate::plane::fit_plane;
use crate::raster::InputError;

/// A rectangle of tile pixels, `x0 <= x < x1`, `y0 <= y < y1`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Rect {
    pub x0: usize,
    pub y0: usize,
    pub x1: usize,
    pub y1: usize,
}

impl Rect {
    /// Width in px.
    pub fn width(&self) -> usize {
        self.x1.saturating_sub(self.x0)
    }
    /// Height in px.
    pub fn height(&self) -> usize {
        self.y1.saturating_sub(self.y0)
    }
    /// Whether the rectangle holds no pixel.
    pub fn is_empty(&self) -> bool {
        self.width() == 0 || self.height() == 0
    }
    /// The whole of a `width x height` raster.
    pub fn full(width: usize, height: usize) -> Rect {
        Rect {
            x0: 0,
            y0: 0,
            x1: width,
            y1: height,
        }
    }
}

/// Parameters of the conversion.
#[derive(Debug, Clone, PartialEq)]
pub struct DetectorParams {
    /// Sigma of the Gaussian low-pass subtracted (px); 0 disables the high-pass.
    pub highpass_sigma_px: f64,
    /// Sigma of the Gaussian smoothing applied first (px); 0 disables it.
    pub smoothing_sigma_px: f64,
    /// Lower and upper percentile of the signal mapped onto 0 and 1.
    pub clip_percentiles: [f64; 2],
    /// Smallest measured fraction of a feature's support (see the module documentation).
    pub min_support_valid: f64,
}

impl Default for DetectorParams {
    fn default() -> Self {
        DetectorParams {
            highpass_sigma_px: 8.0,
            smoothing_sigma_px: 1.0,
            clip_percentiles: [1.0, 99.0],
            min_support_valid: 0.9,
        }
    }
}

impl DetectorParams {
    /// Checks ranges; the error names the parameter.
    pub fn validate(&self) -> Result<(), InputError> {
        if !(self.highpass_sigma_px.is_finite() && (0.0..=1000.0).contains(&self.highpass_sigma_px))
        {
            return Err(bad("highpass_sigma_px", "must be in [0, 1000]"));
        }
        if !(self.smoothing_sigma_px.is_finite()
            && (0.0..=100.0).contains(&self.smoothing_sigma_px))
        {
            return Err(bad("smoothing_sigma_px", "must be in [0, 100]"));
        }
        let [lo, hi] = self.clip_percentiles;
        if !(lo.is_finite() && hi.is_finite() && 0.0 <= lo && lo < hi && hi <= 100.0) {
            return Err(bad(
                "clip_percentiles",
                "must be two percentiles 0 <= low < high <= 100",
            ));
        }
        if !(self.min_support_valid.is_finite() && (0.0..=1.0).contains(&self.min_support_valid)) {
            return Err(bad("min_support_valid", "must be in [0, 1]"));
        }
        Ok(())
    }
}

pub(crate) fn bad(name: &str, reason: &str) -> InputError {
    InputError::InvalidParameter {
        name: name.to_string(),
        reason: reason.to_string(),
    }
}

/// One rectangle of a tile, ready for the detectors. Pixel (i, j) of the images is tile pixel
/// (origin_x + j, origin_y + i).
#[derive(Debug, Clone)]
pub struct DetectorImage {
    /// Tile column of the image's column 0.
    pub origin_x: usize,
    /// Tile row of the image's row 0.
    pub origin_y: usize,
    pub width: usize,
    pub height: usize,
    /// Levelled, high-passed heights, um; NaN = not measured.
    pub signal: Vec<f32>,
    /// The signal stretched onto [0, 1]; NaN = not measured.
    pub values: Vec<f32>,
    /// Valid pixels in the region.
    pub valid_px: usize,
    /// Smallest measured fraction of a feature's support.
    pub min_support_valid: f64,
    /// Integral image of invalid pixels, `(width + 1) x (height + 1)`.
    invalid_sum: Vec<u32>,
}

impl DetectorImage {
    /// Converts `region` of tile `r` (clipped to the tile). An empty region or one without
    /// valid pixels gives an image with `valid_px == 0`, on which no detector finds anything.
    pub fn from_region(
        r: RasterView<'_, f32>,
        region: Rect,
        params: &DetectorParams,
    ) -> Result<DetectorImage, InputError> {
        params.validate()?;
        let region = Rect {
            x0: region.x0.min(r.cols()),
            y0: region.y0.min(r.rows()),
            x1: region.x1.min(r.cols()),
            y1: region.y1.min(r.rows()),
        };
        let (w, h) = (region.width(), region.height());
        let mut crop = Vec::with_capacity(w * h);
        for row in region.y0..region.y1 {
            crop.extend_from_slice(&r.row(row)[region.x0..region.x1]);
        }
        let valid_px = crop.iter().filter(|v| v.is_finite()).count();
        // Infinite heights are as unusable as NaN: mark them NaN once, here.
        for v in crop.iter_mut() {
            if !v.is_finite() {
                *v = f32::NAN;
            }
        }
        let mut signal = crop;
        if valid_px >= 3 {
            let view = RasterView::new(&signal, Shape::new(h, w))?;
            if let Some(plane) = fit_plane(view) {
                let mut levelled = Raster::new(signal, Shape::new(h, w))?;
                plane.apply(&mut levelled);
                signal = levelled.into_values();
            }
        }
        if params.smoothing_sigma_px > 0.0 && valid_px > 0 {
            let smooth = nan_aware_blur(&signal, w, h, params.smoothing_sigma_px);
            for (s, m) in signal.iter_mut().zip(&smooth) {
                if s.is_finite() {
                    *s = *m;
                }
            }
        }
        if params.highpass_sigma_px > 0.0 && valid_px > 0 {
            let low = nan_aware_blur(&signal, w, h, params.highpass_sigma_px);
            for (s, l) in signal.iter_mut().zip(&low) {
                if s.is_finite() {
                    *s -= *l;
                }
            }
        }
        let values = stretch(&signal, params.clip_percentiles);
        let invalid_sum = integral_invalid(&signal, w, h);
        Ok(DetectorImage {
            origin_x: region.x0,
            origin_y: region.y0,
            width: w,
            height: h,
            signal,
            values,
            valid_px,
            min_support_valid: params.min_support_valid,
            invalid_sum,
        })
    }

    /// The measured fraction of the box of image pixels `x0 ..= x1`, `y0 ..= y1`; 0 when the
    /// box is empty or leaves the image.
    pub fn valid_fraction(&self, x0: i64, y0: i64, x1: i64, y1: i64) -> f64 {
        if x0 < 0 || y0 < 0 || x1 >= self.width as i64 || y1 >= self.height as i64 {
            return 0.0;
        }
        if x1 < x0 || y1 < y0 {
            return 0.0;
        }
        let s = self.width + 1;
        let (x0, y0, x1, y1) = (x0 as usize, y0 as usize, x1 as usize + 1, y1 as usize + 1);
        let invalid = self.invalid_sum[y1 * s + x1] + self.invalid_sum[y0 * s + x0]
            - self.invalid_sum[y0 * s + x1]
            - self.invalid_sum[y1 * s + x0];
        let area = ((x1 - x0) * (y1 - y0)) as f64;
        1.0 - invalid as f64 / area
    }

    /// Whether a feature at image pixel (x, y) with a square support of half side `r` may be
    /// kept: the pixel is measured and at least `min_support_valid` of the support is, all of
    /// it inside the image.
    pub fn support_ok(&self, x: i64, y: i64, r: i64) -> bool {
        self.valid_fraction(x, y, x, y) == 1.0
            && self.valid_fraction(x - r, y - r, x + r, y + r) >= self.min_support_valid
    }

    /// [`Self::support_ok`] for a support that may leave the image: the part outside counts
    /// as not measured. For SIFT descriptors, whose footprint (9 px at the finest scale) is
    /// wider than much of a 22-66 px overlap strip; the descriptor skips what is outside.
    pub fn support_ok_clipped(&self, x: i64, y: i64, r: i64) -> bool {
        if self.valid_fraction(x, y, x, y) != 1.0 {
            return false;
        }
        // The part of the box outside the image counts as not measured.
        let clip_x = |v: i64| v.clamp(0, self.width as i64 - 1);
        let clip_y = |v: i64| v.clamp(0, self.height as i64 - 1);
        let (x0, y0, x1, y1) = (clip_x(x - r), clip_y(y - r), clip_x(x + r), clip_y(y + r));
        let inside = ((x1 - x0 + 1) * (y1 - y0 + 1)) as f64;
        let side = (2 * r + 1) as f64;
        self.valid_fraction(x0, y0, x1, y1) * inside / (side * side) >= self.min_support_valid
    }

    /// The stretched values with invalid pixels set to 0, and the validity mask (1 / 0):
    /// the two inputs of a normalised convolution.
    pub(crate) fn values_and_mask(&self) -> (Vec<f32>, Vec<f32>) {
        self.values
            .iter()
            .map(|v| if v.is_finite() { (*v, 1.0) } else { (0.0, 0.0) })
            .unzip()
    }
}

/// The signal clipped to the percentiles and mapped onto [0, 1] (NaN stays NaN).
fn stretch(signal: &[f32], percentiles: [f64; 2]) -> Vec<f32> {
    let mut finite: Vec<f32> = signal.iter().copied().filter(|v| v.is_finite()).collect();
    if finite.is_empty() {
        return vec![f32::NAN; signal.len()];
    }
    let n = finite.len();
    let at = |p: f64| (((p / 100.0) * (n - 1) as f64).round() as usize).min(n - 1);
    let (lo_i, hi_i) = (at(percentiles[0]), at(percentiles[1]));
    let lo = *finite.select_nth_unstable_by(lo_i, f32::total_cmp).1;
    let hi = *finite.select_nth_unstable_by(hi_i, f32::total_cmp).1;
    let span = hi - lo;
    signal
        .iter()
        .map(|&v| {
            if !v.is_finite() {
                f32::NAN
            } else if span > 0.0 {
                ((v - lo) / span).clamp(0.0, 1.0)
            } else {
                0.5
            }
        })
        .collect()
}

fn integral_invalid(signal: &[f32], w: usize, h: usize) -> Vec<u32> {
    let s = w + 1;
    let mut sum = vec![0u32; s * (h + 1)];
    for y in 0..h {
        let mut row_acc = 0u32;
        for x in 0..w {
            row_acc += u32::from(!signal[y * w + x].is_finite());
            sum[(y + 1) * s + x + 1] = sum[y * s + x + 1] + row_acc;
        }
    }
    sum
}

/// A normalised 1-D Gaussian kernel, truncated at `ceil(3 sigma)` (at least radius 1).
pub(crate) fn gaussian_kernel(sigma: f64) -> Vec<f32> {
    let radius = ((3.0 * sigma).ceil() as usize).max(1);
    let mut k: Vec<f64> = (0..=2 * radius)
        .map(|i| {
            let d = i as f64 - radius as f64;
            (-0.5 * d * d / (sigma * sigma)).exp()
        })
        .collect();
    let total: f64 = k.iter().sum();
    k.iter_mut().for_each(|v| *v /= total);
    k.into_iter().map(|v| v as f32).collect()
}

/// Separable Gaussian blur of a NaN-free image, borders replicated.
pub(crate) fn gaussian_blur(img: &[f32], w: usize, h: usize, sigma: f64) -> Vec<f32> {
    if sigma <= 0.0 {
        return img.to_vec();
    }
    let k = gaussian_kernel(sigma);
    let r = (k.len() / 2) as i64;
    let mut tmp = vec![0f32; w * h];
    for y in 0..h {
        let line = &img[y * w..(y + 1) * w];
        for x in 0..w {
            let mut acc = 0f32;
            for (i, kv) in k.iter().enumerate() {
                let xx = (x as i64 + i as i64 - r).clamp(0, w as i64 - 1) as usize;
                acc += kv * line[xx];
            }
            tmp[y * w + x] = acc;
        }
    }
    let mut out = vec![0f32; w * h];
    for (i, kv) in k.iter().enumerate() {
        for y in 0..h {
            let yy = (y as i64 + i as i64 - r).clamp(0, h as i64 - 1) as usize;
            let src = &tmp[yy * w..(yy + 1) * w];
            let dst = &mut out[y * w..(y + 1) * w];
            for (d, s) in dst.iter_mut().zip(src) {
                *d += kv * s;
            }
        }
    }
    out
}

/// Normalised convolution: blur(valid heights) / blur(validity), NaN where no valid pixel
/// contributes.
fn nan_aware_blur(img: &[f32], w: usize, h: usize, sigma: f64) -> Vec<f32> {
    let vals: Vec<f32> = img
        .iter()
        .map(|v| if v.is_finite() { *v } else { 0.0 })
        .collect();
    let mask: Vec<f32> = img
        .iter()
        .map(|v| if v.is_finite() { 1.0 } else { 0.0 })
        .collect();
    let bv = gaussian_blur(&vals, w, h, sigma);
    let bm = gaussian_blur(&mask, w, h, sigma);
    bv.iter()
        .zip(&bm)
        .map(|(v, m)| if *m > 1e-6 { v / m } else { f32::NAN })
        .collect()
}
