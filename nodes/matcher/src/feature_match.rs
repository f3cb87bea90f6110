//! The reference study's feature registration: detect (Harris or SIFT) in the nominal overlap
//! plus the stage-error margin, match by NCC (its equation 1) with the two-way check, then a
//! RANSAC translation; see the crate documentation for what each method does.
//!
//! Conventions as in [`crate::register`]: the offset is b's pixel (0, 0) minus a's, so a
//! feature at `pa` in a and its match at `pb` in b give the displacement `pa - pb`, which
//! equals the offset for a correct match.

use serde::{Deserialize, Serialize};

use crate::detector::{bad, DetectorImage, DetectorParams, Rect};
use crate::harris::{harris_corners, parabola_peak, HarrisParams};
use crate::raster::{validate_offset, InputError};
use crate::register::{PairRegistration, Rejection};
use crate::sift::{sift_keypoints, SiftParams, DESCRIPTOR_LEN};
use surfstream_core::raster::RasterView;

/// Which detector and matcher.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FeatureMethod {
    /// Harris corners, NCC windows (eq. 1), two-way check, RANSAC translation: the paper's
    /// recipe.
    Harris,
    /// SIFT key points, descriptors matched by distance with Lowe's ratio test and the
    /// two-way check, RANSAC translation.
    Sift,
}

impl FeatureMethod {
    /// The method's name in graph files and reports.
    pub fn name(&self) -> &'static str {
        match self {
            FeatureMethod::Harris => "harris",
            FeatureMethod::Sift => "sift",
        }
    }
}

/// Parameters of [`register_pair_features`].
#[derive(Debug, Clone, PartialEq)]
pub struct FeatureParams {
    pub method: FeatureMethod,
    /// Height map -> detector input.
    pub detector: DetectorParams,
    pub harris: HarrisParams,
    pub sift: SiftParams,
    /// Half side of the NCC windows, px ((2 r + 1)^2 pixels). 5: a window must lie inside both
    /// tiles, so on a 30 px overlap a 21 x 21 window leaves a 10 px band to match in; on the
    /// anchors' 576 pairs (examples/features_scan.rs) Harris answered 74 % of the pairs with
    /// r = 10, 84 % with r = 7 and 87 % with r = 5, none wrong by more than 2 px.
    pub window_radius_px: usize,
    /// Harris: smallest NCC of a mutual best match.
    pub min_ncc: f64,
    /// SIFT: Lowe's ratio, best distance over second best.
    pub sift_ratio: f64,
    /// The stage error bound, px: detection covers the nominal overlap grown by this margin,
    /// and a match whose displacement differs from the nominal offset by more (along x or y)
    /// is not considered.
    pub search_px: f64,
    /// A match is a RANSAC inlier when its displacement lies within this distance of the
    /// translation, px.
    pub inlier_radius_px: f64,
    /// Fewest inliers of an accepted translation.
    pub min_inliers: usize,
    /// A rival translation (more than twice the inlier radius away) with at least this fraction
    /// of the best one's inliers makes the answer ambiguous (periodic textures).
    pub ambiguity_fraction: f64,
}

impl Default for FeatureParams {
    fn default() -> Self {
        FeatureParams {
            method: FeatureMethod::Harris,
            detector: DetectorParams::default(),
            harris: HarrisParams::default(),
            sift: SiftParams::default(),
            window_radius_px: 5,
            min_ncc: 0.7,
            sift_ratio: 0.8,
            search_px: 15.0,
            inlier_radius_px: 1.5,
            min_inliers: 4,
            ambiguity_fraction: 0.7,
        }
    }
}

/// The measured share of a SIFT key point's footprint (the part outside the detection region
/// counts as not measured) below which it is dropped; see [`FeatureParams::for_method`].
pub const SIFT_MIN_SUPPORT_VALID: f64 = 0.5;

impl FeatureParams {
    /// The defaults for one method.
    /// The defaults for `method`; SIFT accepts key points with half their footprint measured
    /// ([`SIFT_MIN_SUPPORT_VALID`]).
    pub fn for_method(method: FeatureMethod) -> Self {
        let mut p = FeatureParams {
            method,
            ..Default::default()
        };
        if method == FeatureMethod::Sift {
            // A SIFT footprint (9 px across at the finest scale, growing with it) spans much
            // of a 22-66 px overlap strip: requiring 90 % of it measured and inside the strip
            // left 0-3 matches on most pairs (58 % of the anchor pairs within 0.5 px); half
            // of it gives 98 %, with no pair wrong by more than 2 px (0.3 did no better).
            p.detector.min_support_valid = SIFT_MIN_SUPPORT_VALID;
        }
        p
    }

    /// Checks ranges; the error names the parameter.
    pub fn validate(&self) -> Result<(), InputError> {
        self.detector.validate()?;
        self.harris.validate()?;
        self.sift.validate()?;
        if !(2..=100).contains(&self.window_radius_px) {
            return Err(bad("window_radius_px", "must be in 2..=100"));
        }
        if !(self.min_ncc.is_finite() && (-1.0..=1.0).contains(&self.min_ncc)) {
            return Err(bad("min_ncc", "must be in [-1, 1]"));
        }
        if !(self.sift_ratio.is_finite() && self.sift_ratio > 0.0 && self.sift_ratio <= 1.0) {
            return Err(bad("sift_ratio", "must be in (0, 1]"));
        }
        if !(self.search_px.is_finite() && (0.0..=10_000.0).contains(&self.search_px)) {
            return Err(bad("search_px", "must be in [0, 10000]"));
        }
        if !(self.inlier_radius_px.is_finite() && self.inlier_radius_px > 0.0) {
            return Err(bad("inlier_radius_px", "must be finite and > 0"));
        }
        if self.min_inliers == 0 {
            return Err(bad("min_inliers", "must be >= 1"));
        }
        if !(self.ambiguity_fraction.is_finite() && self.ambiguity_fraction > 0.0) {
            return Err(bad("ambiguity_fraction", "must be finite and > 0"));
        }
        Ok(())
    }
}

/// One two-way match.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FeatureMatch {
    /// Feature position in tile a, px.
    pub a_px: [f64; 2],
    /// Feature position in tile b, px.
    pub b_px: [f64; 2],
    /// `a_px - b_px`: the offset this match votes for, px.
    pub displacement_px: [f64; 2],
    /// The same refined to sub-pixel by the window NCC (see [`refine_displacement`]); equal
    /// to `displacement_px` when the shifted windows are not all valid.
    pub refined_px: [f64; 2],
    /// NCC (eq. 1) of the two windows; `None` when a window is not all valid (SIFT only).
    pub ncc: Option<f64>,
    /// The ranking score: the NCC for Harris, the descriptors' cosine similarity for SIFT.
    pub score: f64,
    /// Whether RANSAC kept it.
    pub inlier: bool,
}

/// Everything [`register_pair_features`] measured for one pair.
#[derive(Debug, Clone, PartialEq)]
pub struct FeatureRegistration {
    /// The answer, in the type the phase-correlation path returns.
    pub registration: PairRegistration,
    pub method: FeatureMethod,
    /// Features detected in a's and in b's region.
    pub features: [usize; 2],
    /// Matches considered before the two-way check (one per feature of a with a candidate).
    pub one_way_matches: usize,
    /// The two-way matches, best score first (RANSAC's input).
    pub matches: Vec<FeatureMatch>,
    /// RANSAC inliers.
    pub inliers: usize,
    /// Residual rotation of b against a from the inliers by a least-squares similarity fit,
    /// degrees (the stage does not rotate: this measures how well that holds).
    pub rotation_deg: Option<f64>,
    /// Scale of the same fit (1 = none).
    pub scale: Option<f64>,
}

/// NCC of two equally long windows, the paper's equation 1:
/// `sum (a - mean a)(b - mean b) / sqrt(sum (a - mean a)^2 sum (b - mean b)^2)`, over the
/// pixel pairs where both windows are measured (a NaN on either side removes the pair, means
/// included). `None` for different lengths, fewer than 3 such pairs, or a flat window.
pub fn ncc_eq1(a: &[f32], b: &[f32]) -> Option<f64> {
    if a.len() != b.len() {
        return None;
    }
    let pairs = || {
        a.iter()
            .zip(b)
            .filter(|(x, y)| x.is_finite() && y.is_finite())
            .map(|(x, y)| (*x as f64, *y as f64))
    };
    let n = pairs().count();
    if n < 3 {
        return None;
    }
    let (sa, sb) = pairs().fold((0.0, 0.0), |acc, (x, y)| (acc.0 + x, acc.1 + y));
    let (ma, mb) = (sa / n as f64, sb / n as f64);
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (x, y) in pairs() {
        let (dx, dy) = (x - ma, y - mb);
        sab += dx * dy;
        saa += dx * dx;
        sbb += dy * dy;
    }
    let den = (saa * sbb).sqrt();
    let v = sab / den;
    (den > 0.0 && v.is_finite()).then_some(v)
}

/// The two-way (mutual best) check on a sparse score table: `scores[i]` lists `(j, score)`
/// for the candidates j of feature i of a. A pair (i, j) survives when j is i's best and i
/// is j's best, and its score is at least `min_score`. Returns `(i, j, score)`, in i order.
pub fn mutual_best(scores: &[Vec<(usize, f64)>], min_score: f64) -> Vec<(usize, usize, f64)> {
    let n_b = scores
        .iter()
        .flat_map(|row| row.iter().map(|(j, _)| j + 1))
        .max()
        .unwrap_or(0);
    let mut best_for_b: Vec<Option<(usize, f64)>> = vec![None; n_b];
    for (i, row) in scores.iter().enumerate() {
        for &(j, s) in row {
            if best_for_b[j].is_none_or(|(_, bs)| s > bs) {
                best_for_b[j] = Some((i, s));
            }
        }
    }
    let mut out = Vec::new();
    for (i, row) in scores.iter().enumerate() {
        let best = row
            .iter()
            .copied()
            .fold(None::<(usize, f64)>, |acc, (j, s)| match acc {
                Some((_, bs)) if bs >= s => acc,
                _ => Some((j, s)),
            });
        if let Some((j, s)) = best {
            if s >= min_score && best_for_b[j].is_some_and(|(bi, _)| bi == i) {
                out.push((i, j, s));
            }
        }
    }
    out
}

/// A translation found by [`ransac_translation`].
#[derive(Debug, Clone, PartialEq)]
pub struct TranslationFit {
    /// Mean of the inlier displacements, px.
    pub translation_px: [f64; 2],
    /// Inlier flag per input displacement.
    pub inliers: Vec<bool>,
    /// Inliers of the best rival hypothesis more than twice the radius away (0 when none).
    pub rival_inliers: usize,
    /// That rival's translation.
    pub rival_px: Option<[f64; 2]>,
}

/// 1-point RANSAC for a pure translation: every displacement is a hypothesis (a translation
/// has one degree of freedom per axis, so one match fixes it; with a few hundred matches
/// trying them all is cheaper than the sampled iteration bound and deterministic); the one
/// with most displacements within `radius_px` wins (ties: larger summed score), then the
/// translation is the mean of its inliers and the inliers are re-selected around it, twice.
/// `None` without displacements.
pub fn ransac_translation(
    displacements: &[[f64; 2]],
    scores: &[f64],
    radius_px: f64,
) -> Option<TranslationFit> {
    if displacements.is_empty() || scores.len() != displacements.len() {
        return None;
    }
    let r2 = radius_px * radius_px;
    let support = |t: [f64; 2]| {
        let mut n = 0usize;
        let mut s = 0.0;
        for (d, sc) in displacements.iter().zip(scores) {
            if dist2(*d, t) <= r2 {
                n += 1;
                s += sc;
            }
        }
        (n, s)
    };
    let hyps: Vec<(usize, f64)> = displacements.iter().map(|d| support(*d)).collect();
    let mut best = 0;
    for k in 1..hyps.len() {
        if hyps[k].0 > hyps[best].0 || (hyps[k].0 == hyps[best].0 && hyps[k].1 > hyps[best].1) {
            best = k;
        }
    }
    let mut t = displacements[best];
    let mut inliers = vec![false; displacements.len()];
    for _ in 0..3 {
        let mut sum = [0.0; 2];
        let mut n = 0usize;
        for (k, d) in displacements.iter().enumerate() {
            inliers[k] = dist2(*d, t) <= r2;
            if inliers[k] {
                sum[0] += d[0];
                sum[1] += d[1];
                n += 1;
            }
        }
        if n == 0 {
            break;
        }
        t = [sum[0] / n as f64, sum[1] / n as f64];
    }
    for (k, d) in displacements.iter().enumerate() {
        inliers[k] = dist2(*d, t) <= r2;
    }
    let far = 4.0 * r2;
    let mut rival: Option<(usize, [f64; 2])> = None;
    for (k, d) in displacements.iter().enumerate() {
        if dist2(*d, t) > far && rival.is_none_or(|(n, _)| hyps[k].0 > n) {
            rival = Some((hyps[k].0, *d));
        }
    }
    Some(TranslationFit {
        translation_px: t,
        inliers,
        rival_inliers: rival.map_or(0, |r| r.0),
        rival_px: rival.map(|r| r.1),
    })
}

fn dist2(a: [f64; 2], b: [f64; 2]) -> f64 {
    (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)
}

/// Least-squares similarity `a ~ s R(theta) b + t` over point pairs (Umeyama's closed form in
/// 2-D): `(theta_rad, s)`. `None` with fewer than 2 pairs or coincident points.
pub fn similarity_fit(a: &[[f64; 2]], b: &[[f64; 2]]) -> Option<(f64, f64)> {
    if a.len() != b.len() || a.len() < 2 {
        return None;
    }
    let n = a.len() as f64;
    let ma = [
        a.iter().map(|p| p[0]).sum::<f64>() / n,
        a.iter().map(|p| p[1]).sum::<f64>() / n,
    ];
    let mb = [
        b.iter().map(|p| p[0]).sum::<f64>() / n,
        b.iter().map(|p| p[1]).sum::<f64>() / n,
    ];
    let (mut c, mut s, mut bb) = (0.0, 0.0, 0.0);
    for (pa, pb) in a.iter().zip(b) {
        let (ax, ay) = (pa[0] - ma[0], pa[1] - ma[1]);
        let (bx, by) = (pb[0] - mb[0], pb[1] - mb[1]);
        c += ax * bx + ay * by;
        s += ay * bx - ax * by;
        bb += bx * bx + by * by;
    }
    if bb <= 1e-12 {
        return None;
    }
    let theta = s.atan2(c);
    let scale = (c * c + s * s).sqrt() / bb;
    Some((theta, scale))
}

/// An NCC window of `signal`: its raw values (NaN = not measured) and, when every pixel is
/// measured, the zero-mean unit-norm copy that turns eq. 1 into one dot product.
struct Window {
    raw: Vec<f32>,
    unit: Option<Vec<f32>>,
}

/// The window of half side `r` centred on image pixel (cx, cy), or `None` when the feature's
/// support rule fails ([`DetectorImage::support_ok`]) or the window is flat.
fn window(img: &DetectorImage, cx: i64, cy: i64, r: usize) -> Option<Window> {
    let r = r as i64;
    if !img.support_ok(cx, cy, r) {
        return None;
    }
    let side = (2 * r + 1) as usize;
    let mut raw = Vec::with_capacity(side * side);
    for y in cy - r..=cy + r {
        let row = y as usize * img.width;
        raw.extend_from_slice(&img.signal[row + (cx - r) as usize..=row + (cx + r) as usize]);
    }
    let valid: Vec<f64> = raw
        .iter()
        .filter(|v| v.is_finite())
        .map(|v| *v as f64)
        .collect();
    let mean = valid.iter().sum::<f64>() / valid.len().max(1) as f64;
    let norm = valid.iter().map(|x| (x - mean).powi(2)).sum::<f64>().sqrt();
    if !(norm > 1e-12 && norm.is_finite()) {
        return None;
    }
    let unit = (valid.len() == raw.len()).then(|| {
        raw.iter()
            .map(|x| ((*x as f64 - mean) / norm) as f32)
            .collect()
    });
    Some(Window { raw, unit })
}

/// Eq. 1 between two windows: one dot product when both are fully measured, else over the
/// measured pixel pairs.
fn window_ncc(a: &Window, b: &Window) -> Option<f64> {
    match (&a.unit, &b.unit) {
        (Some(x), Some(y)) => Some(dot(x, y)),
        _ => ncc_eq1(&a.raw, &b.raw),
    }
}

fn dot(a: &[f32], b: &[f32]) -> f64 {
    a.iter().zip(b).map(|(x, y)| (x * y) as f64).sum()
}

/// Sub-pixel displacement of a match: the NCC of a's window against b's windows one pixel
/// left, right, up and down of b's feature, a 3-point parabola along x and along y. Integer
/// feature positions (rounded) are refined, so the result does not depend on the detector's
/// own sub-pixel estimate. `None` when a shifted window is not all valid.
pub fn refine_displacement(
    a: &DetectorImage,
    b: &DetectorImage,
    a_px: [f64; 2],
    b_px: [f64; 2],
    r: usize,
) -> Option<[f64; 2]> {
    let (ax, ay) = (
        a_px[0].round() as i64 - a.origin_x as i64,
        a_px[1].round() as i64 - a.origin_y as i64,
    );
    let (bx, by) = (
        b_px[0].round() as i64 - b.origin_x as i64,
        b_px[1].round() as i64 - b.origin_y as i64,
    );
    let wa = window(a, ax, ay, r)?;
    let at = |dx: i64, dy: i64| window(b, bx + dx, by + dy, r).and_then(|wb| window_ncc(&wa, &wb));
    let c = at(0, 0)?;
    let l = at(-1, 0)?;
    let rr = at(1, 0)?;
    let u = at(0, -1)?;
    let d = at(0, 1)?;
    // A neighbour above the centre means the integer match was not the NCC maximum: keep it
    // unrefined rather than extrapolate.
    if l > c || rr > c || u > c || d > c {
        return None;
    }
    let dx = parabola_peak(l as f32, c as f32, rr as f32);
    let dy = parabola_peak(u as f32, c as f32, d as f32);
    let a_int = [a_px[0].round(), a_px[1].round()];
    let b_ref = [b_px[0].round() + dx, b_px[1].round() + dy];
    Some([a_int[0] - b_ref[0], a_int[1] - b_ref[1]])
}

/// Regions of a and b to detect in: the nominal overlap (from the rounded nominal offset)
/// grown by `margin_px`, clipped to each tile. `None` when the nominal overlap is empty.
pub fn detection_regions(
    a: (usize, usize),
    b: (usize, usize),
    nominal_offset_px: [f64; 2],
    margin_px: f64,
) -> Option<(Rect, Rect, [usize; 2])> {
    let (dx, dy) = (
        nominal_offset_px[0].round() as i64,
        nominal_offset_px[1].round() as i64,
    );
    let (aw, ah, bw, bh) = (a.0 as i64, a.1 as i64, b.0 as i64, b.1 as i64);
    let (ox0, ox1) = (dx.max(0), (dx + bw).min(aw));
    let (oy0, oy1) = (dy.max(0), (dy + bh).min(ah));
    if ox1 <= ox0 || oy1 <= oy0 {
        return None;
    }
    let m = margin_px.ceil() as i64;
    let clip = |v: i64, hi: i64| v.clamp(0, hi) as usize;
    let ra = Rect {
        x0: clip(ox0 - m, aw),
        y0: clip(oy0 - m, ah),
        x1: clip(ox1 + m, aw),
        y1: clip(oy1 + m, ah),
    };
    let rb = Rect {
        x0: clip(ox0 - dx - m, bw),
        y0: clip(oy0 - dy - m, bh),
        x1: clip(ox1 - dx + m, bw),
        y1: clip(oy1 - dy + m, bh),
    };
    Some((ra, rb, [(ox1 - ox0) as usize, (oy1 - oy0) as usize]))
}

/// A detected point: tile position and, for SIFT, its descriptor.
type Detected = ([f64; 2], Option<[f32; DESCRIPTOR_LEN]>);

struct Feat {
    pos: [f64; 2],
    window: Option<Window>,
    descriptor: Option<[f32; DESCRIPTOR_LEN]>,
}

fn rejected(
    method: FeatureMethod,
    rejection: Rejection,
    overlap_px: [usize; 2],
    features: [usize; 2],
) -> FeatureRegistration {
    FeatureRegistration {
        registration: PairRegistration::rejected(rejection, overlap_px),
        method,
        features,
        one_way_matches: 0,
        matches: Vec::new(),
        inliers: 0,
        rotation_deg: None,
        scale: None,
    }
}

/// Registers tile `b` against tile `a` near `nominal_offset_px` (b's pixel (0, 0) minus a's,
/// px, (x, y)) with Harris or SIFT features. Never panics on input: an invalid offset or
/// invalid parameters give a rejected registration with [`Rejection::InvalidInput`].
pub fn register_pair_features(
    a: RasterView<'_, f32>,
    b: RasterView<'_, f32>,
    nominal_offset_px: [f64; 2],
    params: &FeatureParams,
) -> FeatureRegistration {
    let method = params.method;
    let invalid = |e: InputError| rejected(method, Rejection::InvalidInput(e), [0, 0], [0, 0]);
    if let Err(e) = validate_offset(nominal_offset_px).and_then(|_| params.validate()) {
        return invalid(e);
    }
    // Step 1: the regions.
    let Some((ra, rb, overlap_px)) = detection_regions(
        (a.cols(), a.rows()),
        (b.cols(), b.rows()),
        nominal_offset_px,
        params.search_px,
    ) else {
        return rejected(
            method,
            Rejection::NoOverlap {
                overlap_px: [0, 0],
                min_side_px: 1,
            },
            [0, 0],
            [0, 0],
        );
    };
    // Steps 2-3: detector input and features.
    let (ia, ib) = match detector_images(a, b, (ra, rb), params) {
        Ok(v) => v,
        Err(e) => return invalid(e),
    };
    let (fa, fb) = match (
        region_features(&ia, ra, params),
        region_features(&ib, rb, params),
    ) {
        (Ok(x), Ok(y)) => (x, y),
        (Err(e), _) | (_, Err(e)) => return invalid(e),
    };
    let features = [fa.len(), fb.len()];
    if fa.is_empty() || fb.is_empty() {
        let rms = rms(&ia.signal);
        return rejected(
            method,
            Rejection::Featureless { rms_um: rms },
            overlap_px,
            features,
        );
    }
    // Steps 4-5: two-way matches, refined, then the translation.
    let (mutual, one_way) = two_way_matches(&fa, &fb, nominal_offset_px, params);
    let matches = refined_matches(&mutual, (&fa, &fb), (&ia, &ib), params.window_radius_px);
    let mut out = rejected(method, Rejection::NoCandidate, overlap_px, features);
    out.one_way_matches = one_way;
    fit_translation(&mut out, matches, nominal_offset_px, params);
    out
}

/// Step 2: the detector images of both tiles: the detection regions plus context for the
/// band-pass, so that the low-pass near a region's border is the same in both tiles (crops
/// cut at different places of the part would otherwise high-pass the same texture
/// differently).
fn detector_images(
    a: RasterView<'_, f32>,
    b: RasterView<'_, f32>,
    (ra, rb): (Rect, Rect),
    params: &FeatureParams,
) -> Result<(DetectorImage, DetectorImage), InputError> {
    let context =
        (3.0 * params.detector.highpass_sigma_px).ceil() as usize + params.window_radius_px + 1;
    let grow = |q: Rect, w: usize, h: usize| Rect {
        x0: q.x0.saturating_sub(context),
        y0: q.y0.saturating_sub(context),
        x1: (q.x1 + context).min(w),
        y1: (q.y1 + context).min(h),
    };
    match (
        DetectorImage::from_region(a, grow(ra, a.cols(), a.rows()), &params.detector),
        DetectorImage::from_region(b, grow(rb, b.cols(), b.rows()), &params.detector),
    ) {
        (Ok(x), Ok(y)) => Ok((x, y)),
        (Err(e), _) | (_, Err(e)) => Err(e),
    }
}

/// Step 3: the Harris corners or SIFT keypoints of `img` inside the detection region, each
/// with its NCC window of the band-passed heights (when fully supported).
fn region_features(
    img: &DetectorImage,
    region: Rect,
    params: &FeatureParams,
) -> Result<Vec<Feat>, InputError> {
    let detected: Vec<Detected> = match params.method {
        FeatureMethod::Harris => harris_corners(img, &params.harris)?
            .into_iter()
            .map(|c| ([c.x, c.y], None))
            .collect(),
        FeatureMethod::Sift => sift_keypoints(img, &params.sift)?
            .into_iter()
            .map(|k| ([k.x, k.y], Some(k.descriptor)))
            .collect(),
    };
    let r = params.window_radius_px;
    Ok(detected
        .into_iter()
        .filter(|(p, _)| {
            p[0] >= region.x0 as f64
                && p[0] < region.x1 as f64
                && p[1] >= region.y0 as f64
                && p[1] < region.y1 as f64
        })
        .map(|(pos, descriptor)| Feat {
            pos,
            window: window(
                img,
                pos[0].round() as i64 - img.origin_x as i64,
                pos[1].round() as i64 - img.origin_y as i64,
                r,
            ),
            descriptor,
        })
        .collect())
}

/// Step 4: the two-way matches `(i in a, j in b, score)` among pairs whose displacement is
/// within `search_px` of nominal (Harris: window NCC >= `min_ncc`; SIFT: descriptor
/// similarity and Lowe's ratio test), and how many of a's features had any candidate.
fn two_way_matches(
    fa: &[Feat],
    fb: &[Feat],
    nominal_offset_px: [f64; 2],
    params: &FeatureParams,
) -> (Vec<(usize, usize, f64)>, usize) {
    let gate = |pa: [f64; 2], pb: [f64; 2]| {
        (pa[0] - pb[0] - nominal_offset_px[0]).abs() <= params.search_px
            && (pa[1] - pb[1] - nominal_offset_px[1]).abs() <= params.search_px
    };
    let mut table: Vec<Vec<(usize, f64)>> = vec![Vec::new(); fa.len()];
    match params.method {
        FeatureMethod::Harris => {
            for (i, f) in fa.iter().enumerate() {
                let Some(wa) = &f.window else { continue };
                for (j, g) in fb.iter().enumerate() {
                    if let (true, Some(wb)) = (gate(f.pos, g.pos), &g.window) {
                        if let Some(v) = window_ncc(wa, wb) {
                            table[i].push((j, v));
                        }
                    }
                }
            }
            let one_way = table.iter().filter(|t| !t.is_empty()).count();
            (mutual_best(&table, params.min_ncc), one_way)
        }
        FeatureMethod::Sift => {
            // Score = cosine similarity of unit descriptors (1 - d^2 / 2): larger is closer.
            for (i, f) in fa.iter().enumerate() {
                let Some(da) = &f.descriptor else { continue };
                for (j, g) in fb.iter().enumerate() {
                    if let (true, Some(db)) = (gate(f.pos, g.pos), &g.descriptor) {
                        table[i].push((j, dot(da, db)));
                    }
                }
            }
            let one_way = table.iter().filter(|t| !t.is_empty()).count();
            // Lowe's ratio test on distances, forward: the best must be clearly closer than
            // the second best (a lone candidate passes).
            let ratio2 = params.sift_ratio * params.sift_ratio;
            let pass: Vec<bool> = table
                .iter()
                .map(|row| {
                    let mut d: Vec<f64> =
                        row.iter().map(|(_, s)| (2.0 - 2.0 * s).max(0.0)).collect();
                    d.sort_by(f64::total_cmp);
                    match d.len() {
                        0 => false,
                        1 => true,
                        _ => d[0] < ratio2 * d[1],
                    }
                })
                .collect();
            let m = mutual_best(&table, -1.0)
                .into_iter()
                .filter(|(i, _, _)| pass[*i])
                .collect();
            (m, one_way)
        }
    }
}

/// Step 5a: each two-way match with its sub-pixel refined displacement, best score first.
fn refined_matches(
    mutual: &[(usize, usize, f64)],
    (fa, fb): (&[Feat], &[Feat]),
    (ia, ib): (&DetectorImage, &DetectorImage),
    r: usize,
) -> Vec<FeatureMatch> {
    let mut matches: Vec<FeatureMatch> = mutual
        .iter()
        .map(|&(i, j, score)| {
            let (pa, pb) = (fa[i].pos, fb[j].pos);
            let displacement = [pa[0] - pb[0], pa[1] - pb[1]];
            let ncc = match (&fa[i].window, &fb[j].window) {
                (Some(wa), Some(wb)) => window_ncc(wa, wb),
                _ => None,
            };
            FeatureMatch {
                a_px: pa,
                b_px: pb,
                displacement_px: displacement,
                refined_px: refine_displacement(ia, ib, pa, pb, r).unwrap_or(displacement),
                ncc,
                score,
                inlier: false,
            }
        })
        .collect();
    matches.sort_by(|x, y| y.score.total_cmp(&x.score));
    matches
}

/// Step 5b: the translation by 1-point RANSAC over the refined displacements, the residual
/// rotation and scale of the inliers, and the decision (too few inliers, an ambiguous rival
/// translation, or accepted), written into `out` (which starts as "no candidate").
fn fit_translation(
    out: &mut FeatureRegistration,
    mut matches: Vec<FeatureMatch>,
    nominal_offset_px: [f64; 2],
    params: &FeatureParams,
) {
    let r = params.window_radius_px;
    let disp: Vec<[f64; 2]> = matches.iter().map(|m| m.refined_px).collect();
    let scores: Vec<f64> = matches.iter().map(|m| m.score).collect();
    let Some(fit) = ransac_translation(&disp, &scores, params.inlier_radius_px) else {
        out.matches = matches;
        return;
    };
    for (m, inl) in matches.iter_mut().zip(&fit.inliers) {
        m.inlier = *inl;
    }
    let inl: Vec<&FeatureMatch> = matches.iter().filter(|m| m.inlier).collect();
    let n_in = inl.len();
    let mean_ncc = {
        let v: Vec<f64> = inl.iter().filter_map(|m| m.ncc).collect();
        if v.is_empty() {
            inl.iter().map(|m| m.score).sum::<f64>() / n_in.max(1) as f64
        } else {
            v.iter().sum::<f64>() / v.len() as f64
        }
    };
    let pa: Vec<[f64; 2]> = inl.iter().map(|m| m.a_px).collect();
    let pb: Vec<[f64; 2]> = inl
        .iter()
        .map(|m| [m.a_px[0] - m.refined_px[0], m.a_px[1] - m.refined_px[1]])
        .collect();
    let sim = similarity_fit(&pa, &pb);
    out.inliers = n_in;
    out.rotation_deg = sim.map(|s| s.0.to_degrees());
    out.scale = sim.map(|s| s.1);
    let t = fit.translation_px;
    let reg = &mut out.registration;
    reg.ncc = mean_ncc;
    reg.shift_from_nominal_px = Some([t[0] - nominal_offset_px[0], t[1] - nominal_offset_px[1]]);
    reg.peak_ratio = if fit.rival_inliers == 0 {
        1000.0
    } else {
        (n_in as f64 / fit.rival_inliers as f64).min(1000.0)
    };
    reg.valid_overlap_px = n_in * (2 * r + 1) * (2 * r + 1);
    if n_in < params.min_inliers {
        reg.rejection = Some(Rejection::NoCandidate);
    } else if fit.rival_inliers >= params.min_inliers
        && fit.rival_inliers as f64 >= params.ambiguity_fraction * n_in as f64
    {
        let rival = fit.rival_px.unwrap_or(t);
        let rival_ncc = {
            let r2 = params.inlier_radius_px.powi(2);
            let v: Vec<f64> = matches
                .iter()
                .filter(|m| dist2(m.refined_px, rival) <= r2)
                .map(|m| m.ncc.unwrap_or(m.score))
                .collect();
            v.iter().sum::<f64>() / v.len().max(1) as f64
        };
        reg.rejection = Some(Rejection::Ambiguous {
            best_ncc: mean_ncc,
            rival_ncc,
            rival_shift_px: [
                rival[0] - nominal_offset_px[0],
                rival[1] - nominal_offset_px[1],
            ],
        });
    } else {
        reg.rejection = None;
        reg.offset_px = Some(t);
    }
    out.matches = matches;
}

fn rms(v: &[f32]) -> f64 {
    let (mut s, mut n) = (0.0, 0usize);
    for x in v.iter().filter(|x| x.is_finite()) {
        s += (*x as f64).powi(2);
        n += 1;
    }
    if n == 0 {
        0.0
    } else {
        (s / n as f64).sqrt()
    }
}

impl FeatureRegistration {
    /// Why the pair was not registered, in words the report can carry (the [`Rejection`]
    /// variants are phase correlation's; `NoCandidate` here means "no consistent
    /// translation").
    pub fn reason(&self) -> Option<String> {
        let rej = self.registration.rejection.as_ref()?;
        Some(match rej {
            Rejection::NoCandidate => format!(
                "{} inliers of {} two-way matches ({} and {} features): no consistent translation",
                self.inliers,
                self.matches.len(),
                self.features[0],
                self.features[1]
            ),
            Rejection::Featureless { .. } => format!(
                "no features ({} in a, {} in b) in the overlap",
                self.features[0], self.features[1]
            ),
            other => other.to_string(),
        })
    }
}

impl FeatureRegistration {
    /// The per-pair report (run.json `pairs[].features`): counts, residual rotation and, when
    /// `truth` is given, r and AP against it.
    pub fn report(
        &self,
        truth: Option<&surfstream_core::record::MatchQuality>,
    ) -> surfstream_core::record::FeaturePairRecord {
        surfstream_core::record::FeaturePairRecord {
            method: self.method.name().to_string(),
            features_a: self.features[0],
            features_b: self.features[1],
            one_way_matches: self.one_way_matches,
            two_way_matches: self.matches.len(),
            inliers: self.inliers,
            rotation_deg: self.rotation_deg,
            scale: self.scale,
            reason: self.reason(),
            truth: truth.copied(),
        }
    }
}
