//! SIFT key points and descriptors (Lowe 2004, "Distinctive image features from
//! scale-invariant keypoints"), on the stretched detector image.
//!
//! 1. **Scale space.** The image is doubled (bilinear, `upsample`, as Lowe's section 3.3
//!    recommends: it quadruples the stable key points) and blurred to `sigma0` (1.6, the input
//!    assumed blurred by 0.5 px). Each octave holds `intervals + 3` Gaussian images whose
//!    sigmas grow by `2^(1 / intervals)`; the next octave starts from the image at twice the
//!    octave's base sigma, taken at every second pixel.
//! 2. **DoG extrema.** Differences of adjacent Gaussians; a candidate is a maximum or minimum
//!    of its 26 neighbours in space and scale, above half the contrast threshold.
//! 3. **Localisation.** A quadratic (second-order Taylor) fit of the DoG in x, y and scale,
//!    iterated up to 5 times while the offset exceeds half a sample; then the contrast
//!    `|D(x^)| >= contrast_threshold / intervals` and the edge test
//!    `tr(H)^2 / det(H) < (r + 1)^2 / r` with `r = edge_ratio` (10) on the 2 x 2 spatial
//!    Hessian.
//! 4. **Orientation.** A 36-bin histogram of gradient directions within 3 x 1.5 sigma,
//!    weighted by magnitude and a Gaussian of 1.5 sigma, smoothed; every peak within 80 % of
//!    the highest gives a key point, its angle refined by a parabola through three bins.
//! 5. **Descriptor.** 4 x 4 cells of 8 orientation bins (128 values) over a square of
//!    `3 sigma` per cell, rotated to the key point's orientation, each gradient spread by
//!    trilinear interpolation over the two nearest cells in x, in y and the two nearest
//!    orientation bins, weighted by a Gaussian of half the descriptor width; then normalised to
//!    unit length, clipped at 0.2 and normalised again.
//!
//! Dropouts: every Gaussian image is a normalised convolution (valid values and validity
//! mask blurred alike, then divided), and a key point is dropped when its pixel is not
//! measured or when less than `min_support_valid` of its descriptor footprint (the rotated
//! square's circumscribed radius, plus the gradient stencil) is, the part outside the image
//! counting as not measured ([`crate::detector::DetectorImage::support_ok_clipped`]); the
//! orientation histogram and the descriptor skip samples outside the image, as OpenCV's
//! border handling lets key points near the edge of a narrow overlap strip live.

use crate::detector::{bad, gaussian_blur, DetectorImage};
use crate::raster::InputError;

/// Parameters of [`sift_keypoints`].
#[derive(Debug, Clone, PartialEq)]
pub struct SiftParams {
    /// Intervals (scales) per octave.
    pub intervals: usize,
    /// Blur of the base image of the first octave, px of that octave.
    pub sigma0: f64,
    /// Contrast threshold on the [0, 1] image, divided by `intervals` (Lowe: 0.03, OpenCV 0.04).
    pub contrast_threshold: f64,
    /// Edge ratio r of the principal curvatures.
    pub edge_ratio: f64,
    /// Double the image first.
    pub upsample: bool,
    /// Keep at most this many key points (highest |DoG| first).
    pub max_keypoints: usize,
}

impl Default for SiftParams {
    fn default() -> Self {
        SiftParams {
            intervals: 3,
            sigma0: 1.6,
            contrast_threshold: 0.04,
            edge_ratio: 10.0,
            upsample: true,
            max_keypoints: 2000,
        }
    }
}

impl SiftParams {
    /// Checks ranges; the error names the parameter.
    pub fn validate(&self) -> Result<(), InputError> {
        if !(1..=10).contains(&self.intervals) {
            return Err(bad("sift.intervals", "must be in 1..=10"));
        }
        if !(self.sigma0.is_finite() && (0.5..=10.0).contains(&self.sigma0)) {
            return Err(bad("sift.sigma0", "must be in [0.5, 10]"));
        }
        if !(self.contrast_threshold.is_finite() && (0.0..1.0).contains(&self.contrast_threshold)) {
            return Err(bad("sift.contrast_threshold", "must be in [0, 1)"));
        }
        if !(self.edge_ratio.is_finite() && self.edge_ratio > 1.0) {
            return Err(bad("sift.edge_ratio", "must be > 1"));
        }
        if self.max_keypoints == 0 || self.max_keypoints > 1_000_000 {
            return Err(bad("sift.max_keypoints", "must be in 1..=1000000"));
        }
        Ok(())
    }
}

/// Length of a SIFT descriptor.
pub const DESCRIPTOR_LEN: usize = 128;
const D: usize = 4;
const N_BINS: usize = 8;
const ORI_BINS: usize = 36;
const ORI_PEAK_RATIO: f32 = 0.8;
const ORI_SIG_FCTR: f64 = 1.5;
const ORI_RADIUS: f64 = 3.0 * ORI_SIG_FCTR;
const DESCR_SCL_FCTR: f64 = 3.0;
const DESCR_MAG_THR: f32 = 0.2;
const BORDER: usize = 5;
const MAX_INTERP_STEPS: usize = 5;

/// One SIFT key point in tile pixels.
#[derive(Debug, Clone, PartialEq)]
pub struct Keypoint {
    /// Position, tile px (sub-pixel).
    pub x: f64,
    pub y: f64,
    /// Scale (blur sigma), tile px.
    pub sigma_px: f64,
    /// Orientation, radians (image axes: x right, y down).
    pub angle_rad: f64,
    /// |DoG| at the interpolated extremum.
    pub response: f64,
    /// Unit-length, clipped descriptor.
    pub descriptor: [f32; DESCRIPTOR_LEN],
}

struct Img {
    w: usize,
    h: usize,
    v: Vec<f32>,
}

impl Img {
    #[inline]
    fn at(&self, x: usize, y: usize) -> f32 {
        self.v[y * self.w + x]
    }
}

/// SIFT key points of a detector image, in tile pixel coordinates, strongest first.
pub fn sift_keypoints(
    image: &DetectorImage,
    params: &SiftParams,
) -> Result<Vec<Keypoint>, InputError> {
    params.validate()?;
    if image.valid_px == 0 {
        return Ok(Vec::new());
    }
    // Normalised convolution throughout: blur the valid values and the validity mask alike
    // and divide, so a dropout is absent from every Gaussian image rather than a number.
    let (mut base, mut base_mask) = image.values_and_mask();
    let (mut w, mut h) = (image.width, image.height);
    // Scale of a base-image pixel in tile pixels.
    let mut px = 1.0;
    let mut assumed_blur = 0.5;
    if params.upsample {
        base = upsample2(&base, w, h);
        base_mask = upsample2(&base_mask, w, h);
        w *= 2;
        h *= 2;
        px = 0.5;
        assumed_blur = 1.0;
    }
    let min_side = w.min(h);
    if min_side < 2 * BORDER + 3 {
        return Ok(Vec::new());
    }
    let s = params.intervals;
    let n_oct = ((min_side as f64).log2().floor() as i64 - 2).max(1) as usize;
    let k = 2f64.powf(1.0 / s as f64);
    // Incremental blurs within an octave.
    let mut sig = vec![params.sigma0];
    for i in 1..s + 3 {
        let prev = params.sigma0 * k.powi(i as i32 - 1);
        let total = prev * k;
        sig.push((total * total - prev * prev).sqrt());
    }
    let first = (params.sigma0 * params.sigma0 - assumed_blur * assumed_blur)
        .max(0.01)
        .sqrt();
    let mut cur = (
        gaussian_blur(&base, w, h, first),
        gaussian_blur(&base_mask, w, h, first),
        w,
        h,
    );
    let mut keypoints = Vec::new();
    for o in 0..n_oct {
        let (cw, ch) = (cur.2, cur.3);
        if cw.min(ch) < 2 * BORDER + 3 {
            break;
        }
        // (blurred values, blurred mask) per scale.
        let mut sums = vec![(cur.0, cur.1)];
        for sg in sig.iter().skip(1) {
            let (lv, lm) = &sums[sums.len() - 1];
            let next = (
                gaussian_blur(lv, cw, ch, *sg),
                gaussian_blur(lm, cw, ch, *sg),
            );
            sums.push(next);
        }
        let gauss: Vec<Img> = sums
            .iter()
            .map(|(v, m)| Img {
                w: cw,
                h: ch,
                v: v.iter()
                    .zip(m)
                    .map(|(v, m)| if *m > 1e-3 { v / m } else { 0.0 })
                    .collect(),
            })
            .collect();
        let dog: Vec<Img> = gauss
            .windows(2)
            .map(|p| Img {
                w: p[0].w,
                h: p[0].h,
                v: p[1].v.iter().zip(&p[0].v).map(|(a, b)| a - b).collect(),
            })
            .collect();
        let scale = px * (1u64 << o) as f64;
        find_extrema(&dog, &gauss, o, scale, image, params, &mut keypoints);
        // Next octave: the sums at twice the base sigma, every second pixel.
        let (sv, sm) = &sums[s];
        let (nw, nh) = (cw / 2, ch / 2);
        if nw == 0 || nh == 0 {
            break;
        }
        let mut v = Vec::with_capacity(nw * nh);
        let mut m = Vec::with_capacity(nw * nh);
        for y in 0..nh {
            for x in 0..nw {
                v.push(sv[2 * y * cw + 2 * x]);
                m.push(sm[2 * y * cw + 2 * x]);
            }
        }
        cur = (v, m, nw, nh);
    }
    keypoints.sort_by(|a, b| b.response.total_cmp(&a.response));
    keypoints.truncate(params.max_keypoints);
    Ok(keypoints)
}

fn upsample2(img: &[f32], w: usize, h: usize) -> Vec<f32> {
    let (w2, h2) = (2 * w, 2 * h);
    let mut out = vec![0f32; w2 * h2];
    for y in 0..h2 {
        let fy = y as f32 * 0.5;
        let y0 = (fy.floor() as usize).min(h - 1);
        let y1 = (y0 + 1).min(h - 1);
        let ty = fy - y0 as f32;
        for x in 0..w2 {
            let fx = x as f32 * 0.5;
            let x0 = (fx.floor() as usize).min(w - 1);
            let x1 = (x0 + 1).min(w - 1);
            let tx = fx - x0 as f32;
            let top = img[y0 * w + x0] * (1.0 - tx) + img[y0 * w + x1] * tx;
            let bot = img[y1 * w + x0] * (1.0 - tx) + img[y1 * w + x1] * tx;
            out[y * w2 + x] = top * (1.0 - ty) + bot * ty;
        }
    }
    out
}

#[allow(clippy::too_many_arguments)]
fn find_extrema(
    dog: &[Img],
    gauss: &[Img],
    octave: usize,
    scale: f64,
    image: &DetectorImage,
    params: &SiftParams,
    out: &mut Vec<Keypoint>,
) {
    let s = params.intervals;
    let (w, h) = (dog[0].w, dog[0].h);
    let prelim = (0.5 * params.contrast_threshold / s as f64) as f32;
    for layer in 1..=s {
        let (prev, curr, next) = (&dog[layer - 1], &dog[layer], &dog[layer + 1]);
        for y in BORDER..h - BORDER {
            for x in BORDER..w - BORDER {
                let v = curr.at(x, y);
                if v.abs() <= prelim {
                    continue;
                }
                let mut is_max = true;
                let mut is_min = true;
                for img in [prev, curr, next] {
                    for yy in y - 1..=y + 1 {
                        for xx in x - 1..=x + 1 {
                            if std::ptr::eq(img, curr) && xx == x && yy == y {
                                continue;
                            }
                            let o = img.at(xx, yy);
                            is_max &= v >= o;
                            is_min &= v <= o;
                        }
                    }
                    if !is_max && !is_min {
                        break;
                    }
                }
                if !(is_max && v > 0.0 || is_min && v < 0.0) {
                    continue;
                }
                if let Some(kp) = localize(dog, x, y, layer, params) {
                    make_keypoints(kp, gauss, octave, scale, image, params, out);
                }
            }
        }
    }
}

/// An interpolated extremum: position in octave pixels, layer (fractional), |DoG|.
struct Extremum {
    x: f64,
    y: f64,
    xi: usize,
    yi: usize,
    layer: usize,
    layer_f: f64,
    response: f64,
}

fn localize(
    dog: &[Img],
    mut x: usize,
    mut y: usize,
    mut layer: usize,
    params: &SiftParams,
) -> Option<Extremum> {
    let s = params.intervals;
    let (w, h) = (dog[0].w, dog[0].h);
    let mut off = [0f64; 3];
    let mut grad = [0f64; 3];
    let mut converged = false;
    for _ in 0..MAX_INTERP_STEPS {
        let (p, c, n) = (&dog[layer - 1], &dog[layer], &dog[layer + 1]);
        let v = c.at(x, y) as f64;
        let dx = (c.at(x + 1, y) - c.at(x - 1, y)) as f64 * 0.5;
        let dy = (c.at(x, y + 1) - c.at(x, y - 1)) as f64 * 0.5;
        let ds = (n.at(x, y) - p.at(x, y)) as f64 * 0.5;
        let dxx = c.at(x + 1, y) as f64 + c.at(x - 1, y) as f64 - 2.0 * v;
        let dyy = c.at(x, y + 1) as f64 + c.at(x, y - 1) as f64 - 2.0 * v;
        let dss = n.at(x, y) as f64 + p.at(x, y) as f64 - 2.0 * v;
        let dxy = (c.at(x + 1, y + 1) - c.at(x - 1, y + 1) - c.at(x + 1, y - 1)
            + c.at(x - 1, y - 1)) as f64
            * 0.25;
        let dxs = (n.at(x + 1, y) - n.at(x - 1, y) - p.at(x + 1, y) + p.at(x - 1, y)) as f64 * 0.25;
        let dys = (n.at(x, y + 1) - n.at(x, y - 1) - p.at(x, y + 1) + p.at(x, y - 1)) as f64 * 0.25;
        let hm = nalgebra::Matrix3::new(dxx, dxy, dxs, dxy, dyy, dys, dxs, dys, dss);
        let g = nalgebra::Vector3::new(dx, dy, ds);
        let sol = hm.lu().solve(&g)?;
        off = [-sol[0], -sol[1], -sol[2]];
        grad = [dx, dy, ds];
        if off.iter().all(|o| o.abs() < 0.5) {
            converged = true;
            break;
        }
        if off.iter().any(|o| !o.is_finite() || o.abs() > 1e6) {
            return None;
        }
        let nx = x as i64 + off[0].round() as i64;
        let ny = y as i64 + off[1].round() as i64;
        let nl = layer as i64 + off[2].round() as i64;
        if nl < 1
            || nl > s as i64
            || nx < BORDER as i64
            || ny < BORDER as i64
            || nx >= (w - BORDER) as i64
            || ny >= (h - BORDER) as i64
        {
            return None;
        }
        x = nx as usize;
        y = ny as usize;
        layer = nl as usize;
    }
    if !converged {
        return None;
    }
    let c = &dog[layer];
    let v = c.at(x, y) as f64;
    let contrast = v + 0.5 * (grad[0] * off[0] + grad[1] * off[1] + grad[2] * off[2]);
    if contrast.abs() < params.contrast_threshold / s as f64 {
        return None;
    }
    // Edge response: principal curvature ratio from the spatial Hessian.
    let dxx = c.at(x + 1, y) as f64 + c.at(x - 1, y) as f64 - 2.0 * v;
    let dyy = c.at(x, y + 1) as f64 + c.at(x, y - 1) as f64 - 2.0 * v;
    let dxy = (c.at(x + 1, y + 1) - c.at(x - 1, y + 1) - c.at(x + 1, y - 1) + c.at(x - 1, y - 1))
        as f64
        * 0.25;
    let tr = dxx + dyy;
    let det = dxx * dyy - dxy * dxy;
    let r = params.edge_ratio;
    if det <= 0.0 || tr * tr * r >= (r + 1.0) * (r + 1.0) * det {
        return None;
    }
    Some(Extremum {
        x: x as f64 + off[0],
        y: y as f64 + off[1],
        xi: x,
        yi: y,
        layer,
        layer_f: layer as f64 + off[2],
        response: contrast.abs(),
    })
}

#[allow(clippy::too_many_arguments)]
fn make_keypoints(
    e: Extremum,
    gauss: &[Img],
    _octave: usize,
    scale: f64,
    image: &DetectorImage,
    params: &SiftParams,
    out: &mut Vec<Keypoint>,
) {
    let sigma_oct = params.sigma0 * 2f64.powf(e.layer_f / params.intervals as f64);
    // The descriptor's footprint, in octave pixels, decides whether the point is usable.
    let hist_width = DESCR_SCL_FCTR * sigma_oct;
    let radius_oct = hist_width * std::f64::consts::SQRT_2 * (D as f64 + 1.0) * 0.5 + 1.0;
    let (tx, ty) = (e.x * scale, e.y * scale);
    let r_tile = (radius_oct * scale).ceil() as i64 + 1;
    let (cx, cy) = (tx.round() as i64, ty.round() as i64);
    if !image.support_ok_clipped(cx, cy, r_tile) {
        return;
    }
    let img = &gauss[e.layer];
    for angle in orientations(img, e.xi, e.yi, sigma_oct) {
        let Some(descriptor) = descriptor(img, e.x, e.y, angle, sigma_oct) else {
            continue;
        };
        out.push(Keypoint {
            x: image.origin_x as f64 + tx,
            y: image.origin_y as f64 + ty,
            sigma_px: sigma_oct * scale,
            angle_rad: angle,
            response: e.response,
            descriptor,
        });
    }
}

/// Dominant gradient orientations around (x, y) of a Gaussian image at scale `sigma`.
fn orientations(img: &Img, x: usize, y: usize, sigma: f64) -> Vec<f64> {
    let radius = (ORI_RADIUS * sigma).round() as i64;
    let wsig = ORI_SIG_FCTR * sigma;
    let mut hist = [0f32; ORI_BINS];
    for i in -radius..=radius {
        let yy = y as i64 + i;
        if yy <= 0 || yy >= img.h as i64 - 1 {
            continue;
        }
        for j in -radius..=radius {
            let xx = x as i64 + j;
            if xx <= 0 || xx >= img.w as i64 - 1 {
                continue;
            }
            let (xu, yu) = (xx as usize, yy as usize);
            let dx = (img.at(xu + 1, yu) - img.at(xu - 1, yu)) as f64;
            let dy = (img.at(xu, yu + 1) - img.at(xu, yu - 1)) as f64;
            let wgt = (-((i * i + j * j) as f64) / (2.0 * wsig * wsig)).exp();
            let mag = (dx * dx + dy * dy).sqrt();
            let ang = dy.atan2(dx).rem_euclid(std::f64::consts::TAU);
            let bin = ((ang / std::f64::consts::TAU * ORI_BINS as f64).round() as usize) % ORI_BINS;
            hist[bin] += (wgt * mag) as f32;
        }
    }
    // Smooth with [1 4 6 4 1] / 16, circularly.
    let mut sm = [0f32; ORI_BINS];
    for (b, v) in sm.iter_mut().enumerate() {
        let at = |d: i64| hist[(b as i64 + d).rem_euclid(ORI_BINS as i64) as usize];
        *v = (at(-2) + at(2)) / 16.0 + (at(-1) + at(1)) * 4.0 / 16.0 + at(0) * 6.0 / 16.0;
    }
    let max = sm.iter().copied().fold(0f32, f32::max);
    let mut angles = Vec::new();
    if max <= 0.0 {
        return angles;
    }
    for b in 0..ORI_BINS {
        let l = sm[(b + ORI_BINS - 1) % ORI_BINS];
        let r = sm[(b + 1) % ORI_BINS];
        let v = sm[b];
        if v > l && v > r && v >= ORI_PEAK_RATIO * max {
            let d = 0.5 * (l - r) as f64 / (l - 2.0 * v + r) as f64;
            let bin = (b as f64 + d).rem_euclid(ORI_BINS as f64);
            angles.push(bin / ORI_BINS as f64 * std::f64::consts::TAU);
        }
    }
    angles
}

/// The 128-d descriptor at (x, y) (octave px) with orientation `angle` (radians).
fn descriptor(img: &Img, x: f64, y: f64, angle: f64, sigma: f64) -> Option<[f32; DESCRIPTOR_LEN]> {
    let hist_width = DESCR_SCL_FCTR * sigma;
    let radius = (hist_width * std::f64::consts::SQRT_2 * (D as f64 + 1.0) * 0.5).round() as i64;
    let (cos_t, sin_t) = (angle.cos() / hist_width, angle.sin() / hist_width);
    let exp_scale = -1.0 / (D as f64 * D as f64 * 0.5);
    let bins_per_rad = N_BINS as f64 / std::f64::consts::TAU;
    let (xi, yi) = (x.round() as i64, y.round() as i64);
    // (D + 2) x (D + 2) x (N + 2) histogram: the border cells catch the interpolation spill.
    let mut hist = vec![0f32; (D + 2) * (D + 2) * (N_BINS + 2)];
    let at = |r: usize, c: usize, o: usize| (r * (D + 2) + c) * (N_BINS + 2) + o;
    for i in -radius..=radius {
        for j in -radius..=radius {
            // Sample offsets relative to the sub-pixel key point, rotated into its frame.
            let (px, py) = ((xi + j) as f64 - x, (yi + i) as f64 - y);
            let c_rot = px * cos_t + py * sin_t;
            let r_rot = -px * sin_t + py * cos_t;
            let rbin = r_rot + D as f64 / 2.0 - 0.5;
            let cbin = c_rot + D as f64 / 2.0 - 0.5;
            if !(rbin > -1.0 && rbin < D as f64 && cbin > -1.0 && cbin < D as f64) {
                continue;
            }
            let (xx, yy) = (xi + j, yi + i);
            if xx <= 0 || yy <= 0 || xx >= img.w as i64 - 1 || yy >= img.h as i64 - 1 {
                // The caller checked the footprint against the image; an octave's last
                // column can still fall short by one after halving.
                continue;
            }
            let (xu, yu) = (xx as usize, yy as usize);
            let dx = (img.at(xu + 1, yu) - img.at(xu - 1, yu)) as f64;
            let dy = (img.at(xu, yu + 1) - img.at(xu, yu - 1)) as f64;
            let mag =
                (dx * dx + dy * dy).sqrt() * ((c_rot * c_rot + r_rot * r_rot) * exp_scale).exp();
            let obin = (dy.atan2(dx) - angle).rem_euclid(std::f64::consts::TAU) * bins_per_rad;
            let (r0, c0, o0) = (rbin.floor(), cbin.floor(), obin.floor());
            let (dr, dc, dobin) = (rbin - r0, cbin - c0, obin - o0);
            let (r0, c0) = ((r0 + 1.0) as usize, (c0 + 1.0) as usize);
            let o0 = (o0 as usize) % N_BINS;
            for (ri, wr) in [(0, 1.0 - dr), (1, dr)] {
                for (ci, wc) in [(0, 1.0 - dc), (1, dc)] {
                    for (oi, wo) in [(0, 1.0 - dobin), (1, dobin)] {
                        let o = (o0 + oi) % N_BINS;
                        hist[at(r0 + ri, c0 + ci, o)] += (mag * wr * wc * wo) as f32;
                    }
                }
            }
        }
    }
    let mut desc = [0f32; DESCRIPTOR_LEN];
    for r in 0..D {
        for c in 0..D {
            for o in 0..N_BINS {
                desc[(r * D + c) * N_BINS + o] = hist[at(r + 1, c + 1, o)];
            }
        }
    }
    let norm = desc.iter().map(|v| v * v).sum::<f32>().sqrt();
    if !(norm > 0.0 && norm.is_finite()) {
        return None;
    }
    let thr = DESCR_MAG_THR * norm;
    desc.iter_mut().for_each(|v| *v = v.min(thr));
    let norm = desc.iter().map(|v| v * v).sum::<f32>().sqrt();
    if norm <= 0.0 || !norm.is_finite() {
        return None;
    }
    desc.iter_mut().for_each(|v| *v /= norm);
    Some(desc)
}
