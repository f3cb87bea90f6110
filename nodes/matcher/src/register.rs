//! Pairwise registration: phase correlation on the nominal overlap, NCC verification of the
//! candidate peaks, sub-pixel refinement and the decision to answer or to refuse.

use rayon::prelude::*;
use rustfft::num_complex::Complex32;
use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::fft2::Fft2;
use crate::ncc::{ncc_at, ncc_in, ncc_stencil, overlap_in_a, LevelledTile};
use crate::plane::{PlaneCorrection, PlaneSums};
use crate::raster::{validate_offset, InputError};
use crate::refine::refine_offset;
use surfstream_core::fft::fast_len;
use surfstream_core::raster::RasterView;

/// Apodisation applied to each overlap crop before the FFT.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum Window {
    /// No window (rectangular).
    Rectangular,
    /// Full cosine (Hann) window.
    Hann,
    /// Tukey window: flat centre, cosine tapers over `alpha / 2` of the length at each end
    /// (`alpha = 1` is Hann, `alpha = 0` rectangular).
    Tukey { alpha: f64 },
}

/// How the chosen integer offset is refined to sub-pixel precision. Every estimator works
/// separately along x and y from three samples of a correlation surface: the peak and its two
/// neighbours.
///
/// The `Ncc*` estimators use the NCC of the levelled heights (valid pixels only, one common
/// set of a's pixels for all samples) at the integer offset and its four neighbours, after
/// stepping to the NCC maximum if a neighbour is higher. The `Phase*` estimators run a second
/// phase correlation on the actual overlap at the chosen integer offset (so the window no
/// longer biases the peak towards the nominal offset, with dropouts filled when
/// `fill_dropouts`) and fit its peak. `examples/accuracy.rs` compares them; see the crate
/// documentation for the numbers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum SubPixel {
    /// No refinement: integer offsets.
    None,
    /// Gaussian (parabola on the logarithms) through the NCC samples. The default: the best
    /// or close to the best on every synthetic surface measured, and the cheapest.
    NccGaussian,
    /// Parabola through the NCC samples.
    NccParabolic,
    /// Gaussian through the second-pass phase-correlation peak.
    PhaseGaussian,
    /// Parabola through the second-pass phase-correlation peak.
    PhaseParabolic,
    /// Foroosh et al. (2002) on the second-pass phase-correlation peak: the peak of a
    /// Dirichlet (sinc) kernel, `d = c1 / (c1 + c0)` towards the larger neighbour.
    PhaseForoosh,
}

/// The 1-D three-point peak model.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum PeakFit {
    Parabolic,
    Gaussian,
    Foroosh,
}

/// Parameters of [`register_pair`]. The defaults were tuned on the crate's synthetic tests
/// (`examples/accuracy.rs`, `tests/registration.rs`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct PhaseParams {
    /// Smallest NCC (levelled heights, actual overlap) of an accepted registration. True
    /// matches measure 0.85-0.99 on the synthetic tests (noise up to 10 % of the roughness,
    /// 30 % dropouts), unrelated overlaps below 0.1.
    pub min_ncc: f64,
    /// Smallest NCC of an answer below `min_ncc` that is still accepted because it stands out:
    /// a round peak (roundness at least 0.3) whose NCC is at least `distinct_ncc_ratio` times
    /// every other candidate's. A strip holding one or two isolated features in noise (a
    /// polished plane with a few pits at 10 % overlap) measures 0.16-0.48 at the true offset
    /// with every other candidate below 0.05; unrelated overlaps measure below 0.05 throughout
    /// (`scripts/bench_sparse.py`). 1 or more disables it.
    pub min_ncc_distinct: f64,
    /// See `min_ncc_distinct`.
    pub distinct_ncc_ratio: f64,
    /// Largest accepted |shift from nominal| per axis, px.
    pub max_shift_px: f64,
    /// The shift limit along an axis is also at most this fraction of the overlap extent
    /// along that axis.
    pub max_shift_fraction: f64,
    /// Smallest width and height of the nominal overlap, px.
    pub min_overlap_side_px: usize,
    /// Smallest number of valid pixels in each overlap crop and of valid pixel pairs in the
    /// NCC of the chosen offset.
    pub min_valid_px: usize,
    /// Smallest fraction of valid pixels in each overlap crop.
    pub min_valid_fraction: f64,
    /// Number of correlation peaks verified by NCC.
    pub candidates: usize,
    /// A rival candidate (at least 3 px from the best) whose NCC is within this margin of the
    /// best, and whose correlation peak is at least `rival_peak_fraction` of the best's, makes
    /// the answer ambiguous (periodic or ridge-like textures).
    pub ambiguity_margin: f64,
    /// See `ambiguity_margin`. The peak condition keeps noise maxima that happen to sit on the
    /// broad NCC hill of a smooth surface from counting as rivals.
    pub rival_peak_fraction: f64,
    /// Smallest accepted roundness of the NCC peak: the ratio of the smaller to the larger
    /// curvature (eigenvalues of the Hessian from the 3 x 3 NCC samples around the chosen
    /// offset). A ridge (roundness near 0) means the texture does not fix the offset along it
    /// (1-D textures such as gratings or a strong lay); rough surfaces measure 0.3-1.
    pub min_peak_roundness: f64,
    /// Window applied to each crop before the FFT.
    pub window: Window,
    /// Gaussian weighting of the normalised cross-power spectrum, expressed as the standard
    /// deviation (px) of the resulting blur of the correlation peak; 0 disables it. It damps
    /// the noise-dominated high frequencies that whitening would otherwise amplify.
    pub peak_sigma_px: f64,
    /// Sub-pixel estimator.
    pub subpixel: SubPixel,
    /// For the `Phase*` estimators: fill dropouts with the average of their valid
    /// neighbourhood instead of 0 in the second pass (zero-filled dropouts act as strong
    /// white noise there).
    pub fill_dropouts: bool,
    /// Refine an accepted pair's offset by Lucas-Kanade on the smoothed heights of the overlap
    /// (piston and tilt solved with it; [`crate::refine`]) and report its covariance. The
    /// NCC's answer stays when the refinement fails or moves more than 1 px.
    pub lucas_kanade: bool,
}

impl Default for PhaseParams {
    fn default() -> Self {
        PhaseParams {
            min_ncc: 0.5,
            min_ncc_distinct: 0.15,
            distinct_ncc_ratio: 3.0,
            max_shift_px: 30.0,
            max_shift_fraction: 0.45,
            min_overlap_side_px: 8,
            min_valid_px: 1024,
            min_valid_fraction: 0.2,
            candidates: 5,
            ambiguity_margin: 0.1,
            rival_peak_fraction: 0.5,
            min_peak_roundness: 0.05,
            window: Window::Tukey { alpha: 0.5 },
            peak_sigma_px: 1.0,
            subpixel: SubPixel::NccGaussian,
            fill_dropouts: true,
            lucas_kanade: true,
        }
    }
}

impl PhaseParams {
    /// Checks ranges; the error names the parameter.
    pub fn validate(&self) -> Result<(), InputError> {
        let bad = |name: &str, reason: &str| {
            Err(InputError::InvalidParameter {
                name: name.to_string(),
                reason: reason.to_string(),
            })
        };
        if !(self.min_ncc.is_finite() && self.min_ncc <= 1.0) {
            return bad("min_ncc", "must be a finite number <= 1");
        }
        if !(self.min_ncc_distinct.is_finite() && self.min_ncc_distinct > 0.0) {
            return bad("min_ncc_distinct", "must be finite and > 0");
        }
        if !(self.distinct_ncc_ratio.is_finite() && self.distinct_ncc_ratio >= 1.0) {
            return bad("distinct_ncc_ratio", "must be finite and >= 1");
        }
        if !(self.max_shift_px.is_finite() && self.max_shift_px >= 0.0) {
            return bad("max_shift_px", "must be finite and >= 0");
        }
        if !(self.max_shift_fraction > 0.0 && self.max_shift_fraction <= 0.5) {
            return bad("max_shift_fraction", "must be in (0, 0.5]");
        }
        if self.min_overlap_side_px < 3 {
            return bad("min_overlap_side_px", "must be >= 3");
        }
        if !(0.0..=1.0).contains(&self.min_valid_fraction) {
            return bad("min_valid_fraction", "must be in [0, 1]");
        }
        if self.candidates == 0 || self.candidates > 1000 {
            return bad("candidates", "must be in 1..=1000");
        }
        if !(self.ambiguity_margin.is_finite() && self.ambiguity_margin >= 0.0) {
            return bad("ambiguity_margin", "must be finite and >= 0");
        }
        if !(self.rival_peak_fraction.is_finite() && self.rival_peak_fraction >= 0.0) {
            return bad("rival_peak_fraction", "must be finite and >= 0");
        }
        if !(self.min_peak_roundness.is_finite() && self.min_peak_roundness <= 1.0) {
            return bad("min_peak_roundness", "must be a finite number <= 1");
        }
        if !(self.peak_sigma_px.is_finite() && (0.0..=100.0).contains(&self.peak_sigma_px)) {
            return bad("peak_sigma_px", "must be in [0, 100]");
        }
        if let Window::Tukey { alpha } = self.window {
            if !(0.0..=1.0).contains(&alpha) {
                return bad("window.alpha", "must be in [0, 1]");
            }
        }
        Ok(())
    }
}

/// Why a pair was not registered.
#[derive(Debug, Clone, PartialEq, Error, Serialize, Deserialize)]
pub enum Rejection {
    #[error("invalid input: {0}")]
    InvalidInput(InputError),
    #[error("nominal overlap {overlap_px:?} px is smaller than {min_side_px} px on a side")]
    NoOverlap {
        overlap_px: [usize; 2],
        min_side_px: usize,
    },
    #[error("only {valid_px} valid pixels in the overlap, {required_px} required")]
    TooFewValidPixels { valid_px: usize, required_px: usize },
    #[error("overlap is featureless after levelling (rms {rms_um} um)")]
    Featureless { rms_um: f64 },
    #[error("no correlation peak with enough actual overlap")]
    NoCandidate,
    #[error("best NCC {ncc:.3} is below {min_ncc:.3}")]
    LowNcc { ncc: f64, min_ncc: f64 },
    #[error(
        "ambiguous: a rival shift {rival_shift_px:?} px has NCC {rival_ncc:.3}, best {best_ncc:.3}"
    )]
    Ambiguous {
        best_ncc: f64,
        rival_ncc: f64,
        /// The rival's shift from the nominal offset, px.
        rival_shift_px: [f64; 2],
    },
    #[error(
        "the NCC peak is a ridge (roundness {roundness:.3} < {min_roundness:.3}): the texture \
         does not fix the offset along it"
    )]
    NotLocalized { roundness: f64, min_roundness: f64 },
    #[error("shift from nominal {shift_px:?} px exceeds the limit {limit_px:?} px")]
    ShiftTooLarge {
        shift_px: [f64; 2],
        limit_px: [f64; 2],
    },
}

/// One verified correlation peak.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Candidate {
    /// Integer offset (b origin minus a origin), px.
    pub offset_px: [i64; 2],
    /// Height of the phase-correlation peak (1 = perfect match of all frequencies).
    pub peak: f64,
    /// NCC of the levelled heights over the actual overlap at this offset (-1 if too few pairs).
    pub ncc: f64,
    /// Valid pixel pairs the NCC used.
    pub valid_px: usize,
}

/// One distinct NCC maximum of an ambiguous pair (see
/// [`PhaseCorrelator::register_with_alternatives`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Alternative {
    /// Sub-pixel offset (b's pixel (0, 0) minus a's, px, (x, y)).
    pub offset_px: [f64; 2],
    /// NCC at the integer maximum.
    pub ncc: f64,
    /// Roundness of the NCC peak (see [`PhaseParams::min_peak_roundness`]).
    pub roundness: f64,
}

/// The answer of [`register_pair`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PairRegistration {
    /// Measured offset (b's pixel (0, 0) minus a's, px, (x, y)); `None` when rejected.
    pub offset_px: Option<[f64; 2]>,
    /// NCC of the chosen candidate (0 when none was measured).
    pub ncc: f64,
    /// Correlation peak of the chosen candidate over the best other peak (0 when none was
    /// measured, capped at 1000).
    pub peak_ratio: f64,
    /// Roundness of the NCC peak at the chosen offset (see
    /// [`PhaseParams::min_peak_roundness`]; 0 when not measured).
    pub peak_roundness: f64,
    /// The best candidate's offset minus the nominal offset, px, also when it was rejected.
    pub shift_from_nominal_px: Option<[f64; 2]>,
    /// Width and height of the nominal overlap rectangle, px.
    pub overlap_px: [usize; 2],
    /// Valid pixel pairs in the NCC of the chosen candidate.
    pub valid_overlap_px: usize,
    /// Why there is no offset; `None` when `offset_px` is `Some`.
    pub rejection: Option<Rejection>,
    /// The verified candidates, best NCC first.
    pub candidates: Vec<Candidate>,
    /// For a pair refused because its NCC peak is a ridge (or an ambiguous row of maxima along
    /// one line), the one direction the texture does fix: the global solve uses it as a
    /// one-direction constraint. `None` otherwise (and for every accepted pair).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub directional: Option<DirectionalOffset>,
    /// Covariance of `offset_px`, px^2, rows (x, y), when the Lucas-Kanade refinement gave it
    /// ([`PhaseParams::lucas_kanade`]); `None` otherwise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub covariance_px2: Option<[[f64; 2]; 2]>,
}

/// The offset of a pair known across a feature only: a lone scratch or a straight flank makes
/// an NCC ridge, whose top is fixed across it (along `normal`) and free along it.
/// `normal . (position(b) - position(a)) = normal . offset_px`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DirectionalOffset {
    /// A point on the ridge top (b's pixel (0, 0) minus a's, px, (x, y)); only its component
    /// along `normal` is measured.
    pub offset_px: [f64; 2],
    /// Unit vector across the ridge (the Hessian's direction of largest curvature).
    pub normal: [f64; 2],
    /// Curvature of ln NCC across the ridge and along it, 1/px^2 (eigenvalues of minus the
    /// Hessian of the 3 x 3 samples' logarithms): the peak's information in each direction.
    pub curvature_per_px2: [f64; 2],
    /// NCC at the ridge point.
    pub ncc: f64,
}

impl PairRegistration {
    /// No answer, for `rejection`: every measure zero, no candidates.
    pub(crate) fn rejected(rejection: Rejection, overlap_px: [usize; 2]) -> Self {
        PairRegistration {
            offset_px: None,
            ncc: 0.0,
            peak_ratio: 0.0,
            peak_roundness: 0.0,
            shift_from_nominal_px: None,
            overlap_px,
            valid_overlap_px: 0,
            rejection: Some(rejection),
            candidates: Vec::new(),
            directional: None,
            covariance_px2: None,
        }
    }

    /// Whether the pair was registered.
    pub fn is_accepted(&self) -> bool {
        self.offset_px.is_some()
    }
}

/// Registers tile `b` against tile `a` near `nominal_offset_px` (b's pixel (0, 0) minus a's,
/// px, (x, y)). One-shot convenience: builds a [`PhaseCorrelator`] for this call. Streams of
/// pairs should keep one correlator and call [`PhaseCorrelator::register`], which reuses FFT
/// plans and buffers.
pub fn register_pair(
    a: RasterView<'_, f32>,
    b: RasterView<'_, f32>,
    nominal_offset_px: [f64; 2],
    params: &PhaseParams,
) -> PairRegistration {
    PhaseCorrelator::new().register(a, b, nominal_offset_px, params)
}

/// Phase correlation with cached FFT plans and reusable buffers: keep one per thread (or per
/// node) and register every pair through it.
pub struct PhaseCorrelator {
    fft: Fft2,
    work: Vec<Complex32>,
    spec: Vec<Complex32>,
    surface: Vec<f32>,
}

impl Default for PhaseCorrelator {
    fn default() -> Self {
        Self::new()
    }
}

/// Overlap geometry implied by an offset, rounded to whole pixels.
#[derive(Debug, Clone, Copy)]
struct Geometry {
    /// Rounded offset.
    ndx: i64,
    ndy: i64,
    /// Overlap rectangle in a's coordinates.
    x0: usize,
    y0: usize,
    w: usize,
    h: usize,
}

impl Geometry {
    /// The same-size crops `(x0, y0, w, h)` of a and of b.
    fn rects(&self) -> (Rect, Rect) {
        (
            (self.x0, self.y0, self.w, self.h),
            (
                (self.x0 as i64 - self.ndx) as usize,
                (self.y0 as i64 - self.ndy) as usize,
                self.w,
                self.h,
            ),
        )
    }
}

/// A crop `(x0, y0, w, h)` of a tile.
type Rect = (usize, usize, usize, usize);

fn geometry(a: &RasterView<'_, f32>, b: &RasterView<'_, f32>, offset_px: [f64; 2]) -> Geometry {
    let ndx = offset_px[0].round() as i64;
    let ndy = offset_px[1].round() as i64;
    let x0 = ndx.max(0);
    let x1 = (ndx + b.cols() as i64).min(a.cols() as i64);
    let y0 = ndy.max(0);
    let y1 = (ndy + b.rows() as i64).min(a.rows() as i64);
    Geometry {
        ndx,
        ndy,
        x0: x0 as usize,
        y0: y0 as usize,
        w: (x1 - x0).max(0) as usize,
        h: (y1 - y0).max(0) as usize,
    }
}

/// Statistics of a prepared crop.
struct CropStats {
    valid: usize,
    rms_um: f64,
    /// The reference height the crop's sums were taken relative to.
    ref_um: f64,
    energy: f64,
    plane: PlaneCorrection,
}

impl PhaseCorrelator {
    pub fn new() -> Self {
        PhaseCorrelator {
            fft: Fft2::new(),
            work: Vec::new(),
            spec: Vec::new(),
            surface: Vec::new(),
        }
    }

    /// See [`register_pair`].
    pub fn register(
        &mut self,
        a: RasterView<'_, f32>,
        b: RasterView<'_, f32>,
        nominal_offset_px: [f64; 2],
        params: &PhaseParams,
    ) -> PairRegistration {
        self.register_with_alternatives(a, b, nominal_offset_px, params)
            .0
    }

    /// [`PhaseCorrelator::register`], and for a pair rejected as [`Rejection::Ambiguous`] the
    /// distinct NCC maxima (best first) that pass every other check, when there are at least
    /// two: the global solve ([`crate::global::solve_positions_with_alternatives`]) can pick
    /// the one consistent with the rest of the scan. Empty otherwise.
    pub fn register_with_alternatives(
        &mut self,
        a: RasterView<'_, f32>,
        b: RasterView<'_, f32>,
        nominal_offset_px: [f64; 2],
        params: &PhaseParams,
    ) -> (PairRegistration, Vec<Alternative>) {
        let mut alternatives = Vec::new();
        let reg = self.register_inner(a, b, nominal_offset_px, params, &mut alternatives);
        (reg, alternatives)
    }

    /// The steps of a pairwise registration (the crate documentation's 1-5): the nominal
    /// overlap's crops correlated, candidates verified by NCC, the best refined to sub-pixel,
    /// then the decision. An ambiguous pair's usable maxima go to `alternatives`.
    fn register_inner(
        &mut self,
        a: RasterView<'_, f32>,
        b: RasterView<'_, f32>,
        nominal_offset_px: [f64; 2],
        params: &PhaseParams,
        alternatives: &mut Vec<Alternative>,
    ) -> PairRegistration {
        let checked = validate_offset(nominal_offset_px).and_then(|_| params.validate());
        if let Err(e) = checked {
            return PairRegistration::rejected(Rejection::InvalidInput(e), [0, 0]);
        }
        let g = geometry(&a, &b, nominal_offset_px);
        let overlap_px = [g.w, g.h];
        let verified = self.correlate_nominal_overlap(&a, &b, &g, params).and_then(
            |(stats_a, stats_b, pw, ph)| {
                self.verified_candidates(a, b, &g, (&stats_a, &stats_b), (pw, ph), params)
            },
        );
        let (mut cands, lev_a, lev_b) = match verified {
            Ok(v) => v,
            Err(rejection) => return PairRegistration::rejected(rejection, overlap_px),
        };
        within_stage_range(&mut cands, nominal_offset_px, params);
        let peak_ratio = peak_ratio(&cands);

        // The NCC peak around the best candidate, then the sub-pixel refinement. Each tile is
        // levelled again on the actual overlap at the best offset: the nominal crops are
        // different parts of the surface when the stage error is a large fraction of a narrow
        // overlap, and their planes then differ by a slope that shifts the NCC peak (0.4 px
        // on 22 px overlaps of a wavy specimen).
        let (lev_a, lev_b) = relevelled(a, b, cands[0].offset_px).unwrap_or((lev_a, lev_b));
        let (mut peak, mut lev_a, mut lev_b) = settled_peak(a, b, cands[0].offset_px, lev_a, lev_b);
        // The candidates are ranked by the NCC at their integer offsets; a rival's own
        // maximum may be the higher one once both are climbed (a ridge's maxima, or a periodic
        // alias ranked first): the answer is the highest maximum.
        if let Some(k) = higher_rival(a, b, &cands, &peak, params) {
            // A rival was relevelled at its offset to be one, so this succeeds.
            if let Some((la, lb)) = relevelled(a, b, cands[k].offset_px) {
                let c = cands.remove(k);
                cands.insert(0, c);
                (peak, lev_a, lev_b) = settled_peak(a, b, c.offset_px, la, lb);
            }
        }
        let best = cands[0];
        if peak.roundness >= params.min_peak_roundness && peak.roundness < RIDGE_MAX_ROUNDNESS {
            // A 3 x 3 stencil cannot tell a sharp slanted ridge from a peak: its roundness
            // reads 0.06-0.07 on a lone scratch, whose 2-D answer is then 3-4 px wrong along
            // it. The fall-off farther out along the weak direction can.
            let far = far_roundness(&lev_a, &lev_b, &peak);
            if far < RIDGE_FAR_ROUNDNESS {
                peak.roundness = far;
            }
        }
        let (int_offset, frac) = self.subpixel(&a, &b, &peak, params);
        let (ncc, valid_overlap_px) = if int_offset == best.offset_px {
            (best.ncc, best.valid_px)
        } else {
            ncc_at(&lev_a, &lev_b, int_offset[0], int_offset[1])
        };
        let offset = [
            int_offset[0] as f64 + frac[0],
            int_offset[1] as f64 + frac[1],
        ];
        let shift = [
            offset[0] - nominal_offset_px[0],
            offset[1] - nominal_offset_px[1],
        ];
        let mut out = PairRegistration {
            offset_px: None,
            ncc,
            peak_ratio,
            peak_roundness: peak.roundness,
            shift_from_nominal_px: Some(shift),
            overlap_px,
            valid_overlap_px,
            rejection: None,
            candidates: cands.clone(),
            directional: None,
            covariance_px2: None,
        };
        let limit = shift_limit_px(params, overlap_px);
        let mut line = Vec::new();
        out.rejection = self.decide(
            (&a, &b),
            nominal_offset_px,
            params,
            (&cands, &peak),
            (ncc, valid_overlap_px),
            (shift, limit),
            (alternatives, &mut line),
        );
        match &out.rejection {
            None => {
                out.offset_px = Some(offset);
                if params.lucas_kanade {
                    if let Some(r) = refine_offset(a, b, offset) {
                        out.offset_px = Some(r.offset_px);
                        out.covariance_px2 = Some(r.covariance_px2);
                    }
                }
            }
            Some(Rejection::NotLocalized { .. }) | Some(Rejection::Ambiguous { .. }) => {
                out.directional =
                    directional_offset(&peak, &line, nominal_offset_px, params, limit);
                if out.directional.is_some() {
                    // The maxima along the ridge are one answer, not several to choose from.
                    alternatives.clear();
                }
            }
            Some(_) => {}
        }
        out
    }

    /// Step 1-2: the phase correlation of the nominal overlap's crops (into `self.surface`)
    /// and their statistics; refused when the overlap is too small, has too few valid pixels
    /// or is featureless. Returns both crops' statistics and the padded size.
    fn correlate_nominal_overlap(
        &mut self,
        a: &RasterView<'_, f32>,
        b: &RasterView<'_, f32>,
        g: &Geometry,
        params: &PhaseParams,
    ) -> Result<(CropStats, CropStats, usize, usize), Rejection> {
        let (w, h) = (g.w, g.h);
        if w < params.min_overlap_side_px || h < params.min_overlap_side_px {
            return Err(Rejection::NoOverlap {
                overlap_px: [w, h],
                min_side_px: params.min_overlap_side_px,
            });
        }
        let (rect_a, rect_b) = g.rects();
        let (stats_a, stats_b, pw, ph) = self.correlate(a, b, rect_a, rect_b, params, false);
        let required = params
            .min_valid_px
            .max((params.min_valid_fraction * (w * h) as f64).ceil() as usize)
            .max(3);
        let valid = stats_a.valid.min(stats_b.valid);
        if valid < required {
            return Err(Rejection::TooFewValidPixels {
                valid_px: valid,
                required_px: required,
            });
        }
        for s in [&stats_a, &stats_b] {
            // A plane (or a constant) within f32 rounding of its height.
            if s.rms_um <= 1e-6 * (1.0 + s.ref_um.abs()) || s.energy <= 0.0 {
                return Err(Rejection::Featureless { rms_um: s.rms_um });
            }
        }
        Ok((stats_a, stats_b, pw, ph))
    }

    /// Step 3: the strongest local maxima of the correlation surface with at least half the
    /// crop overlapping, each verified by the NCC of the levelled tiles at its integer offset;
    /// best NCC first. Also returns the tiles levelled by their crops' planes.
    fn verified_candidates<'a>(
        &self,
        a: RasterView<'a, f32>,
        b: RasterView<'a, f32>,
        g: &Geometry,
        (stats_a, stats_b): (&CropStats, &CropStats),
        (pw, ph): (usize, usize),
        params: &PhaseParams,
    ) -> Result<(Vec<Candidate>, LevelledTile<'a>, LevelledTile<'a>), Rejection> {
        let peaks = local_maxima(
            &self.surface,
            pw,
            ph,
            (g.w / 2) as i64,
            (g.h / 2) as i64,
            params.candidates,
        );
        if peaks.is_empty() {
            return Err(Rejection::NoCandidate);
        }
        let (rect_a, rect_b) = g.rects();
        let lev_a = LevelledTile::new(a, rect_a, &stats_a.plane);
        let lev_b = LevelledTile::new(b, rect_b, &stats_b.plane);
        let min_pairs = params.min_valid_px.max(3);
        let mut cands: Vec<Candidate> = peaks
            .par_iter()
            .map(|&(peak, tx, ty)| {
                let off = [g.ndx + tx, g.ndy + ty];
                let (ncc, n) = ncc_at(&lev_a, &lev_b, off[0], off[1]);
                Candidate {
                    offset_px: off,
                    peak: peak as f64,
                    ncc: if n >= min_pairs { ncc } else { -1.0 },
                    valid_px: n,
                }
            })
            .collect();
        cands.sort_by(|p, q| q.ncc.total_cmp(&p.ncc).then(q.peak.total_cmp(&p.peak)));
        Ok((cands, lev_a, lev_b))
    }

    /// Step 4: the integer offset and sub-pixel fraction of the NCC peak by the chosen method.
    fn subpixel(
        &mut self,
        a: &RasterView<'_, f32>,
        b: &RasterView<'_, f32>,
        peak: &NccPeak,
        params: &PhaseParams,
    ) -> ([i64; 2], [f64; 2]) {
        match params.subpixel {
            SubPixel::None => (peak.offset_px, [0.0, 0.0]),
            SubPixel::NccGaussian => (peak.offset_px, peak.fit(PeakFit::Gaussian)),
            SubPixel::NccParabolic => (peak.offset_px, peak.fit(PeakFit::Parabolic)),
            SubPixel::PhaseGaussian => {
                self.refine_phase(a, b, peak.offset_px, PeakFit::Gaussian, params)
            }
            SubPixel::PhaseParabolic => {
                self.refine_phase(a, b, peak.offset_px, PeakFit::Parabolic, params)
            }
            SubPixel::PhaseForoosh => {
                self.refine_phase(a, b, peak.offset_px, PeakFit::Foroosh, params)
            }
        }
    }

    /// Step 5: why the refined answer (the NCC at it, its shift from nominal) is refused, in
    /// order: low NCC, ambiguous (then the usable maxima go to `alternatives`), not
    /// localised, shift beyond the limit, a clearly better match beyond the limit. `None`:
    /// accepted.
    #[allow(clippy::too_many_arguments)]
    fn decide(
        &mut self,
        (a, b): (&RasterView<'_, f32>, &RasterView<'_, f32>),
        nominal_offset_px: [f64; 2],
        params: &PhaseParams,
        (cands, peak): (&[Candidate], &NccPeak),
        (ncc, valid_overlap_px): (f64, usize),
        (shift, limit): ([f64; 2], [f64; 2]),
        (alternatives, rival_peaks): (&mut Vec<Alternative>, &mut Vec<[i64; 2]>),
    ) -> Option<Rejection> {
        let best = cands[0];
        // The answer's own overlap: a peak far from nominal can leave too few samples in common
        // even when the nominal overlap had enough (named as such, not as a low NCC).
        let required_px = params.min_valid_px.max(3);
        if valid_overlap_px < required_px {
            return Some(Rejection::TooFewValidPixels {
                valid_px: valid_overlap_px,
                required_px,
            });
        }
        if ncc < params.min_ncc && !stands_out(ncc, cands, peak, params) {
            return Some(Rejection::LowNcc {
                ncc,
                min_ncc: params.min_ncc,
            });
        }
        let rivals = rivals(*a, *b, cands, peak, params);
        rival_peaks.extend(rivals.iter().map(|(_, q)| q.offset_px));
        if let Some((r, _)) = rivals.first() {
            // The distinct maxima that would each pass every other check are kept for the
            // global solve, which may pick the one consistent with the rest of the scan.
            alternatives.extend(usable_maxima(
                peak,
                &rivals,
                nominal_offset_px,
                params,
                limit,
            ));
            return Some(Rejection::Ambiguous {
                best_ncc: best.ncc,
                rival_ncc: r.ncc,
                rival_shift_px: shift_from(r.offset_px, nominal_offset_px),
            });
        }
        if peak.roundness.is_nan() || peak.roundness < params.min_peak_roundness {
            return Some(Rejection::NotLocalized {
                roundness: peak.roundness,
                min_roundness: params.min_peak_roundness,
            });
        }
        // A shift that brings the tiles closer than nominal only widens their overlap: there
        // the fraction-of-overlap limit guards against nothing, and the stage error alone
        // bounds it. On sparse 10 % sets this refused true shifts of 7.8 px on a 16 px strip
        // (the links that held a tile, which the stage then placed 4-5 px off).
        let widening =
            |k: usize| nominal_offset_px[k].abs() >= 1.0 && shift[k] * nominal_offset_px[k] < 0.0;
        let beyond = |k: usize| {
            let lim = if widening(k) {
                params.max_shift_px
            } else {
                limit[k]
            };
            shift[k].abs() > lim
        };
        if beyond(0) || beyond(1) {
            return Some(Rejection::ShiftTooLarge {
                shift_px: shift,
                limit_px: limit,
            });
        }
        self.better_beyond_limit(a, b, nominal_offset_px, params, limit, peak.c[1][1])
            .map(|beyond| Rejection::ShiftTooLarge {
                shift_px: beyond,
                limit_px: limit,
            })
    }

    /// The shift from nominal of a clearly better match beyond the shift limit, if any.
    ///
    /// On a narrow overlap the limit (a fraction of the overlap) is tighter than the stage
    /// error allowed (`max_shift_px`), and the true offset may lie between the two. The nominal
    /// crops then barely share any surface at the true offset, and on a periodic texture they
    /// show one of its aliases instead (8.9 px wrong on a 22 px strip of the benchmark's
    /// grating). So along each axis where the limit binds, the overlap is grown by
    /// `max_shift_px` and correlated once more; a peak beyond the limit whose NCC maximum beats
    /// the answer's (`ncc`, the plane-removed NCC at its peak) by [`BEYOND_LIMIT_MARGIN`] means
    /// the answer is an alias, and the pair gets none.
    fn better_beyond_limit(
        &mut self,
        a: &RasterView<'_, f32>,
        b: &RasterView<'_, f32>,
        nominal_offset_px: [f64; 2],
        params: &PhaseParams,
        limit: [f64; 2],
        ncc: f64,
    ) -> Option<[f64; 2]> {
        let grow = params.max_shift_px.ceil();
        let mut grown = nominal_offset_px;
        let mut any = false;
        for k in 0..2 {
            let along = if k == 0 { a.cols() } else { a.rows() } as f64;
            let n = nominal_offset_px[k];
            // Only an axis the tiles are offset along (the overlap is partial) can grow.
            if limit[k] < params.max_shift_px && n.abs() >= 1.0 && n.abs() < along {
                grown[k] = n - grow * n.signum();
                any = true;
            }
        }
        if !any {
            return None;
        }
        let g = geometry(a, b, grown);
        if g.w < params.min_overlap_side_px || g.h < params.min_overlap_side_px {
            return None;
        }
        let (rect_a, rect_b) = g.rects();
        let (_, _, pw, ph) = self.correlate(a, b, rect_a, rect_b, params, false);
        let peaks = local_maxima(
            &self.surface,
            pw,
            ph,
            (g.w / 2) as i64,
            (g.h / 2) as i64,
            params.candidates,
        );
        peaks.into_iter().find_map(|(_, tx, ty)| {
            let off = [g.ndx + tx, g.ndy + ty];
            let shift = shift_from(off, nominal_offset_px);
            let beyond = (0..2).any(|k| shift[k].abs() > limit[k]);
            let allowed = (0..2).all(|k| shift[k].abs() <= params.max_shift_px);
            if !(beyond && allowed) {
                return None;
            }
            let (la, lb) = relevelled(*a, *b, off)?;
            let (rp, _, _) = settled_peak(*a, *b, off, la, lb);
            let end = shift_from(rp.offset_px, nominal_offset_px);
            let still_beyond = (0..2).any(|k| end[k].abs() > limit[k]);
            (still_beyond && rp.c[1][1] > ncc + BEYOND_LIMIT_MARGIN).then_some(end)
        })
    }

    /// Levels, windows and transforms the same-size crops `rect_a` of a and `rect_b` of b: the
    /// spectrum of `a + i b` is left transposed (`[kx][ky]`, `pw x ph`) in `self.spec`.
    fn spectrum(
        &mut self,
        a: &RasterView<'_, f32>,
        b: &RasterView<'_, f32>,
        rect_a: Rect,
        rect_b: Rect,
        params: &PhaseParams,
        fill: bool,
    ) -> (CropStats, CropStats, usize, usize) {
        let (w, h) = (rect_a.2, rect_a.3);
        let (pw, ph) = (fast_len(w), fast_len(h));
        let n_pad = pw * ph;
        self.work.clear();
        self.work.resize(n_pad, Complex32::new(0.0, 0.0));
        self.spec.clear();
        self.spec.resize(n_pad, Complex32::new(0.0, 0.0));
        let wx = window(w, params.window);
        let wy = window(h, params.window);
        let stats_a = prepare_crop(a, rect_a, &wx, &wy, &mut self.work, pw, false, fill);
        let stats_b = prepare_crop(b, rect_b, &wx, &wy, &mut self.work, pw, true, fill);
        self.fft
            .forward_transposed(&mut self.work, &mut self.spec, ph, pw);
        (stats_a, stats_b, pw, ph)
    }

    /// Phase correlation of the crops `rect_a` of a and `rect_b` of b into `self.surface`
    /// (`ph x pw`, circular; index (tx, ty) = shift of b's content relative to a's).
    fn correlate(
        &mut self,
        a: &RasterView<'_, f32>,
        b: &RasterView<'_, f32>,
        rect_a: Rect,
        rect_b: Rect,
        params: &PhaseParams,
        fill: bool,
    ) -> (CropStats, CropStats, usize, usize) {
        let (stats_a, stats_b, pw, ph) = self.spectrum(a, b, rect_a, rect_b, params, fill);
        let eps = 1e-7 * (stats_a.energy * stats_b.energy).sqrt();
        cross_power(
            &self.spec,
            &mut self.work,
            pw,
            ph,
            eps as f32,
            params.peak_sigma_px,
        );
        self.fft
            .inverse_from_transposed(&mut self.work, &mut self.spec, ph, pw);
        let norm = 1.0 / (pw * ph) as f32;
        self.surface.clear();
        self.surface.extend(self.spec.iter().map(|c| c.re * norm));
        (stats_a, stats_b, pw, ph)
    }

    /// Second-pass phase correlation on the actual overlap at the integer `offset_px`: the
    /// residual shift is then below a pixel, so the window no longer pulls the peak towards
    /// the crop centre. Returns the integer offset of the peak and its sub-pixel part.
    fn refine_phase(
        &mut self,
        a: &RasterView<'_, f32>,
        b: &RasterView<'_, f32>,
        offset_px: [i64; 2],
        fit: PeakFit,
        params: &PhaseParams,
    ) -> ([i64; 2], [f64; 2]) {
        let g = geometry(a, b, [offset_px[0] as f64, offset_px[1] as f64]);
        if g.w < 3 || g.h < 3 {
            return (offset_px, [0.0, 0.0]);
        }
        let (rect_a, rect_b) = g.rects();
        let (_, _, pw, ph) = self.correlate(a, b, rect_a, rect_b, params, params.fill_dropouts);
        let s = &self.surface;
        let at = |tx: i64, ty: i64| -> f64 {
            s[ty.rem_euclid(ph as i64) as usize * pw + tx.rem_euclid(pw as i64) as usize] as f64
        };
        // The peak is now within a pixel of zero shift.
        let mut best = (f64::NEG_INFINITY, 0i64, 0i64);
        for ty in -1..=1i64 {
            for tx in -1..=1i64 {
                let v = at(tx, ty);
                if v > best.0 {
                    best = (v, tx, ty);
                }
            }
        }
        let (c0, tx, ty) = best;
        (
            [offset_px[0] + tx, offset_px[1] + ty],
            [
                fit_peak(at(tx - 1, ty), c0, at(tx + 1, ty), fit),
                fit_peak(at(tx, ty - 1), c0, at(tx, ty + 1), fit),
            ],
        )
    }
}

/// Largest distance (px) of an ambiguous pair's rival maximum from the line along the ridge
/// through the best one for the rivals to count as the same ridge.
const RIDGE_LINE_PX: f64 = 1.5;

/// Largest roundness of a peak treated as a ridge when its rivals lie along it: the
/// near-ridge peaks that pass `min_peak_roundness` (0.05) but sit on a row of equal maxima.
const RIDGE_MAX_ROUNDNESS: f64 = 0.3;

/// The one-direction answer of a pair refused as a ridge or as ambiguous (`rival_peaks`: the
/// rivals' NCC maxima): the top of the NCC ridge across it. `None` unless the peak is concave
/// across, every rival lies on the ridge line through it (within [`RIDGE_LINE_PX`]; a row of
/// maxima across the ridge is a periodic texture's aliases, not one ridge), and the shift
/// across stays within the shift limit.
fn directional_offset(
    peak: &NccPeak,
    rival_peaks: &[[i64; 2]],
    nominal_offset_px: [f64; 2],
    params: &PhaseParams,
    limit: [f64; 2],
) -> Option<DirectionalOffset> {
    let c = &peak.c;
    let ncc = c[1][1];
    if ncc.is_nan() || ncc < params.min_ncc {
        return None;
    }
    if !rival_peaks.is_empty() && peak.roundness > RIDGE_MAX_ROUNDNESS {
        return None;
    }
    let (g, [across, along], n) = peak_axes(c)?;
    for o in rival_peaks {
        let d = [
            (o[0] - peak.offset_px[0]) as f64,
            (o[1] - peak.offset_px[1]) as f64,
        ];
        if (d[0] * n[0] + d[1] * n[1]).abs() > RIDGE_LINE_PX {
            return None;
        }
    }
    // The top across the ridge from the integer maximum: the quadric along `normal`.
    let t = (g[0] * n[0] + g[1] * n[1]) / across;
    if !(t.is_finite() && t.abs() <= 1.0) {
        return None;
    }
    let offset_px = [
        peak.offset_px[0] as f64 + t * n[0],
        peak.offset_px[1] as f64 + t * n[1],
    ];
    // The shift limit applies to the shift across (the one measured), as in `decide`.
    let s =
        (offset_px[0] - nominal_offset_px[0]) * n[0] + (offset_px[1] - nominal_offset_px[1]) * n[1];
    for k in 0..2 {
        let sk = s * n[k];
        let widening = nominal_offset_px[k].abs() >= 1.0 && sk * nominal_offset_px[k] < 0.0;
        let lim = if widening {
            params.max_shift_px
        } else {
            limit[k]
        };
        if sk.abs() > lim {
            return None;
        }
    }
    Some(DirectionalOffset {
        offset_px,
        normal: n,
        curvature_per_px2: [across, along],
        ncc,
    })
}

/// Whether an answer whose NCC is below `min_ncc` is accepted all the same (see
/// [`PhaseParams::min_ncc_distinct`]): a round peak far above every other candidate at least
/// 3 px from it.
fn stands_out(ncc: f64, cands: &[Candidate], peak: &NccPeak, params: &PhaseParams) -> bool {
    let runner_up = cands
        .iter()
        .filter(|c| chebyshev(c.offset_px, peak.offset_px) >= 3)
        .map(|c| c.ncc)
        .fold(0.0, f64::max);
    ncc >= params.min_ncc_distinct
        && peak.roundness >= RIDGE_MAX_ROUNDNESS
        && ncc >= params.distinct_ncc_ratio * runner_up
}

/// The quadric of ln NCC (the Gaussian model of the sub-pixel fit; NCC itself when a sample
/// is not positive) through the 3 x 3 samples: its gradient, its curvatures (eigenvalues of
/// minus the Hessian, larger first) and the unit direction of the larger. `None` unless the
/// larger curvature is positive.
fn peak_axes(c: &[[f64; 3]; 3]) -> Option<([f64; 2], [f64; 2], [f64; 2])> {
    let logs = c.iter().flatten().all(|&v| v > 0.0);
    let f = |r: usize, k: usize| if logs { c[r][k].ln() } else { c[r][k] };
    let g = [0.5 * (f(1, 2) - f(1, 0)), 0.5 * (f(2, 1) - f(0, 1))];
    // Minus the Hessian: positive curvature where the peak falls off.
    let p = -(f(1, 0) - 2.0 * f(1, 1) + f(1, 2));
    let q = -(f(0, 1) - 2.0 * f(1, 1) + f(2, 1));
    let r = -0.25 * (f(2, 2) + f(0, 0) - f(0, 2) - f(2, 0));
    let mean = 0.5 * (p + q);
    let disc = (0.25 * (p - q) * (p - q) + r * r).sqrt();
    let (across, along) = (mean + disc, mean - disc);
    if !(across.is_finite() && across > 0.0) {
        return None;
    }
    // Eigenvector of the larger eigenvalue of [[p, r], [r, q]].
    let n = if r.abs() > 1e-12 * across {
        [across - q, r]
    } else if p >= q {
        [1.0, 0.0]
    } else {
        [0.0, 1.0]
    };
    let len = n[0].hypot(n[1]);
    Some((g, [across, along], [n[0] / len, n[1] / len]))
}

/// A peak whose [`far_roundness`] is below this is a ridge whatever its stencil says. A lone
/// scratch measures 0.000 there (`tests/sparse.rs`); the probed peaks of
/// `scripts/bench_sparse.py` 0.011-0.42, and with this threshold no set there changes.
const RIDGE_FAR_ROUNDNESS: f64 = 0.02;

/// Distances (px) along the peak's weak direction at which [`far_roundness`] samples the NCC.
const FAR_PROBES_PX: [f64; 2] = [2.0, 3.0];

/// The roundness of the NCC peak measured 2-3 px out along its weak direction: the curvature
/// of ln NCC there (from its fall-off at integer offsets on both sides, the part due to their
/// rounding off the ridge line removed by the stencil's quadric across) over the curvature
/// across. All samples use one region of a (the overlap common to every probe), so a change
/// of the overlap with the shift does not read as texture. The peak's own roundness when the
/// probes cannot be taken.
fn far_roundness(a: &LevelledTile<'_>, b: &LevelledTile<'_>, peak: &NccPeak) -> f64 {
    let Some((g, [across, _], n)) = peak_axes(&peak.c) else {
        return peak.roundness;
    };
    let t = [-n[1], n[0]];
    let mut probes: Vec<[i64; 2]> = Vec::new();
    for k in FAR_PROBES_PX {
        for sign in [-1.0, 1.0] {
            probes.push([
                (sign * k * t[0]).round() as i64,
                (sign * k * t[1]).round() as i64,
            ]);
        }
    }
    let at = |p: [i64; 2]| [peak.offset_px[0] + p[0], peak.offset_px[1] + p[1]];
    let mut region = overlap_in_a(a, b, peak.offset_px[0], peak.offset_px[1]);
    for &p in &probes {
        let o = overlap_in_a(a, b, at(p)[0], at(p)[1]);
        region = [
            region[0].max(o[0]),
            region[1].min(o[1]),
            region[2].max(o[2]),
            region[3].min(o[3]),
        ];
    }
    if region[1] - region[0] < 3 || region[3] - region[2] < 3 {
        return peak.roundness;
    }
    let (c0, n0) = ncc_in(a, b, peak.offset_px[0], peak.offset_px[1], region);
    if c0.is_nan() || c0 <= 0.0 || n0 < 3 {
        return peak.roundness;
    }
    let g_n = g[0] * n[0] + g[1] * n[1];
    let mut sum = 0.0;
    for &p in &probes {
        let (c, m) = ncc_in(a, b, at(p)[0], at(p)[1], region);
        if m < 3 {
            return peak.roundness;
        }
        // A probe that falls to zero or below: the peak is no ridge.
        if c.is_nan() || c <= 0.0 {
            return 1.0;
        }
        let pf = [p[0] as f64, p[1] as f64];
        let across_px = pf[0] * n[0] + pf[1] * n[1];
        let along_px = pf[0] * t[0] + pf[1] * t[1];
        // What the quadric across predicts for the probe's offset off the ridge line.
        let expected = g_n * across_px - 0.5 * across * across_px * across_px;
        let drop = expected - (c / c0).ln();
        sum += 2.0 * drop / (along_px * along_px);
    }
    let curvature_along = sum / probes.len() as f64;
    if std::env::var_os("SURFSTREAM_DEBUG_RIDGE").is_some() {
        eprintln!(
            "far_roundness: stencil {:.3} far {:.3} across {:.3}",
            peak.roundness,
            curvature_along / across,
            across
        );
    }
    (curvature_along / across).clamp(0.0, 1.0)
}

/// The best candidate's correlation peak over the strongest other one (capped at 1000).
fn peak_ratio(cands: &[Candidate]) -> f64 {
    let best = cands[0];
    let others_peak = cands[1..]
        .iter()
        .map(|c| c.peak)
        .fold(f64::NEG_INFINITY, f64::max);
    if others_peak > 0.0 {
        (best.peak / others_peak).min(1000.0)
    } else {
        1000.0
    }
}

/// The largest accepted shift from nominal along x and y, px: `max_shift_px`, or a fraction
/// of the overlap extent along that axis when smaller.
fn shift_limit_px(params: &PhaseParams, overlap_px: [usize; 2]) -> [f64; 2] {
    [
        params
            .max_shift_px
            .min(params.max_shift_fraction * overlap_px[0] as f64),
        params
            .max_shift_px
            .min(params.max_shift_fraction * overlap_px[1] as f64),
    ]
}

/// Drops the candidates that no climb can bring within `max_shift_px` of the nominal offset
/// (the stage error's bound: an answer there is refused whatever its NCC). On a periodic
/// texture seen through a full-width strip, an alias 80 px along the strip scored as the best
/// candidate or as a rival and cost the pair its true answer (the pills specimen,
/// docs/registration.md). Nothing is dropped unless a candidate within reach scores within
/// `ambiguity_margin` of the best: a true shift beyond the bound, far better than anything
/// within it, is still found and refused with its measured shift (which tells the user to
/// raise `max_shift_px`).
fn within_stage_range(
    cands: &mut Vec<Candidate>,
    nominal_offset_px: [f64; 2],
    params: &PhaseParams,
) {
    let reach = params.max_shift_px + MAX_CLIMB_STEPS as f64;
    let inside = |c: &Candidate| {
        let s = shift_from(c.offset_px, nominal_offset_px);
        s[0].abs() <= reach && s[1].abs() <= reach
    };
    let top = cands.first().map_or(f64::NEG_INFINITY, |c| c.ncc);
    if cands
        .iter()
        .any(|c| inside(c) && c.ncc >= top - params.ambiguity_margin)
    {
        cands.retain(inside);
    }
}

/// The index of the rival (see [`rivals`]) whose climbed NCC maximum is higher than the
/// best's (`peak`), the highest if several.
fn higher_rival(
    a: RasterView<'_, f32>,
    b: RasterView<'_, f32>,
    cands: &[Candidate],
    peak: &NccPeak,
    params: &PhaseParams,
) -> Option<usize> {
    let best = rivals(a, b, cands, peak, params)
        .into_iter()
        .filter(|(_, q)| q.c[1][1] > peak.c[1][1])
        .max_by(|p, q| p.1.c[1][1].total_cmp(&q.1.c[1][1]))?;
    cands.iter().position(|c| c.offset_px == best.0.offset_px)
}

/// Rivals of the best candidate: other correlation peaks at least 3 px away with similar NCC
/// and peak. Each is climbed to its own NCC maximum first: one that ends on the best's
/// maximum (`peak`) is the same hill (a smooth surface puts several correlation maxima on one
/// broad NCC hill), not a rival.
fn rivals(
    a: RasterView<'_, f32>,
    b: RasterView<'_, f32>,
    cands: &[Candidate],
    peak: &NccPeak,
    params: &PhaseParams,
) -> Vec<(Candidate, NccPeak)> {
    let best = cands[0];
    let mut rivals: Vec<(Candidate, NccPeak)> = Vec::new();
    for c in &cands[1..] {
        let d = chebyshev(c.offset_px, best.offset_px);
        if !(d >= 3
            && c.ncc >= best.ncc - params.ambiguity_margin
            && c.peak >= params.rival_peak_fraction * best.peak)
        {
            continue;
        }
        let (rp, _, _) = match relevelled(a, b, c.offset_px) {
            Some((la, lb)) => settled_peak(a, b, c.offset_px, la, lb),
            None => continue,
        };
        let same_hill = chebyshev(rp.offset_px, peak.offset_px) <= 1
            || rivals
                .iter()
                .any(|(_, q)| chebyshev(rp.offset_px, q.offset_px) <= 1);
        if !same_hill && rp.c[1][1] >= peak.c[1][1] - params.ambiguity_margin {
            rivals.push((*c, rp));
        }
    }
    rivals
}

/// An ambiguous pair's maxima (the best's, then the rivals') that would each pass every
/// other check, refined like the answer; empty unless at least two are (one is no choice).
fn usable_maxima(
    peak: &NccPeak,
    rivals: &[(Candidate, NccPeak)],
    nominal_offset_px: [f64; 2],
    params: &PhaseParams,
    limit: [f64; 2],
) -> Vec<Alternative> {
    let fit = match params.subpixel {
        SubPixel::None => None,
        SubPixel::NccParabolic => Some(PeakFit::Parabolic),
        _ => Some(PeakFit::Gaussian),
    };
    let mut peaks = vec![peak];
    peaks.extend(rivals.iter().map(|(_, q)| q));
    let mut usable = Vec::new();
    for q in peaks {
        let frac = fit.map_or([0.0, 0.0], |f| q.fit(f));
        let off = [
            q.offset_px[0] as f64 + frac[0],
            q.offset_px[1] as f64 + frac[1],
        ];
        let sh = [off[0] - nominal_offset_px[0], off[1] - nominal_offset_px[1]];
        let ok = q.c[1][1] >= params.min_ncc
            && q.roundness >= params.min_peak_roundness
            && sh[0].abs() <= limit[0]
            && sh[1].abs() <= limit[1];
        if ok {
            usable.push(Alternative {
                offset_px: off,
                ncc: q.c[1][1],
                roundness: q.roundness,
            });
        }
    }
    if usable.len() < 2 {
        usable.clear();
    }
    usable
}

/// Both tiles levelled by the least-squares planes of their actual overlap when b's origin
/// sits at `offset_px` in a's coordinates; `None` when the overlap is empty or has fewer than
/// three valid pixels in either tile.
fn relevelled<'a>(
    a: RasterView<'a, f32>,
    b: RasterView<'a, f32>,
    offset_px: [i64; 2],
) -> Option<(LevelledTile<'a>, LevelledTile<'a>)> {
    let g = geometry(&a, &b, [offset_px[0] as f64, offset_px[1] as f64]);
    if g.w == 0 || g.h == 0 {
        return None;
    }
    let (rect_a, rect_b) = g.rects();
    let fit = |t: &RasterView<'_, f32>, rect: Rect| -> Option<PlaneCorrection> {
        let (x0, y0, w, h) = rect;
        let cx = (w as f64 - 1.0) * 0.5;
        let cy = (h as f64 - 1.0) * 0.5;
        let z_ref = (0..h)
            .flat_map(|r| t.row(y0 + r)[x0..x0 + w].iter())
            .find(|v| v.is_finite())
            .copied()?;
        let mut sums = PlaneSums::default();
        for r in 0..h {
            sums.add_row_offset(r as f64 - cy, -cx, &t.row(y0 + r)[x0..x0 + w], z_ref);
        }
        if sums.count() < 3 {
            return None;
        }
        let (mut plane, _, _) = sums.solve()?;
        plane.piston_um += z_ref as f64;
        Some(plane)
    };
    let pa = fit(&a, rect_a)?;
    let pb = fit(&b, rect_b)?;
    Some((
        LevelledTile::new(a, rect_a, &pa),
        LevelledTile::new(b, rect_b, &pb),
    ))
}

/// How much better (NCC) a match beyond the shift limit must be to void the answer within it
/// ([`PhaseCorrelator::better_beyond_limit`]): the aliases of a periodic texture score within
/// a few hundredths of each other, so only a clearly better match says the answer is one.
const BEYOND_LIMIT_MARGIN: f64 = 0.03;

/// Relevelling rounds in [`settled_peak`]; the peak moved at most twice on the benchmark's
/// periodic tiles.
const MAX_RELEVELS: usize = 3;

/// [`ncc_peak`] from `start` with the tiles levelled on the actual overlap at `start`
/// (`lev_a`, `lev_b`), then again levelled on the overlap at the peak found, until the peak
/// stays put. The levelling plane belongs to one overlap: fitted at a start 3 px off on a
/// 32 px strip of a smooth grating, it moves the NCC maximum by 1-2 px towards the start.
fn settled_peak<'a>(
    a: RasterView<'a, f32>,
    b: RasterView<'a, f32>,
    start: [i64; 2],
    mut lev_a: LevelledTile<'a>,
    mut lev_b: LevelledTile<'a>,
) -> (NccPeak, LevelledTile<'a>, LevelledTile<'a>) {
    let mut at = start;
    let mut peak = ncc_peak(&lev_a, &lev_b, at);
    for _ in 0..MAX_RELEVELS {
        if peak.offset_px == at {
            break;
        }
        let Some((la, lb)) = relevelled(a, b, peak.offset_px) else {
            break;
        };
        (lev_a, lev_b) = (la, lb);
        at = peak.offset_px;
        peak = ncc_peak(&lev_a, &lev_b, at);
    }
    (peak, lev_a, lev_b)
}

/// The NCC peak near a candidate: the integer offset and the 3 x 3 NCC samples around it.
struct NccPeak {
    offset_px: [i64; 2],
    /// `c[1 + dy][1 + dx]` = NCC at `offset_px + (dx, dy)`.
    c: [[f64; 3]; 3],
    /// Smaller over larger curvature of the peak, in [0, 1]; 0 unless both are concave.
    roundness: f64,
}

impl NccPeak {
    /// Sub-pixel offset: the stationary point of the quadric (on the logarithms for the
    /// Gaussian model) through the 3 x 3 samples, cross term included; the three samples along
    /// x and along y separately where that quadric has no maximum.
    ///
    /// The cross term matters on sparse texture: a lone scratch or an elongated feature gives
    /// an NCC peak elongated along a slant, where fitting x and y apart finds the ridge's
    /// crossing of the sample row instead of its top (0.34 px rms on polished lay with
    /// scratches, 0.07 px with the cross term; `scripts/bench_sparse.py`, docs/registration.md).
    fn fit(&self, fit: PeakFit) -> [f64; 2] {
        let c = &self.c;
        if let Some(d) = fit_peak_2d(c, fit) {
            return d;
        }
        [
            fit_peak(c[1][0], c[1][1], c[1][2], fit),
            fit_peak(c[0][1], c[1][1], c[2][1], fit),
        ]
    }
}

/// The maximum of the quadric through the 3 x 3 samples `c[dy + 1][dx + 1]` by central
/// differences (gradient and Hessian, cross term from the corners), on `ln c` for the
/// Gaussian model when every sample is positive. `None` when the Hessian is not negative
/// definite or the maximum lies more than a pixel out.
fn fit_peak_2d(c: &[[f64; 3]; 3], fit: PeakFit) -> Option<[f64; 2]> {
    let logs = fit == PeakFit::Gaussian && c.iter().flatten().all(|&v| v > 0.0);
    let f = |r: usize, k: usize| if logs { c[r][k].ln() } else { c[r][k] };
    let gx = 0.5 * (f(1, 2) - f(1, 0));
    let gy = 0.5 * (f(2, 1) - f(0, 1));
    let hxx = f(1, 0) - 2.0 * f(1, 1) + f(1, 2);
    let hyy = f(0, 1) - 2.0 * f(1, 1) + f(2, 1);
    let hxy = 0.25 * (f(2, 2) + f(0, 0) - f(0, 2) - f(2, 0));
    let det = hxx * hyy - hxy * hxy;
    if !(hxx < 0.0 && hyy < 0.0 && det > 0.0) {
        return None;
    }
    let dx = -(hyy * gx - hxy * gy) / det;
    let dy = -(hxx * gy - hxy * gx) / det;
    (dx.is_finite() && dy.is_finite() && dx.abs() <= 1.0 && dy.abs() <= 1.0).then_some([dx, dy])
}

/// Steps the NCC climb may take from a correlation peak. On textures that are smooth at the
/// pixel scale across a narrow overlap (a grating seen through a 22-32 px strip) the windowed
/// phase-correlation peak sits up to 3-4 px from the NCC maximum; 3 steps stopped short there
/// (1.7 px errors on periodic_x3p). Candidates are at least 3 px apart, so 8 steps cannot walk
/// far past a rival's hill, and the shift limit still applies to where the climb ends.
const MAX_CLIMB_STEPS: usize = 8;

/// Climbs (at most [`MAX_CLIMB_STEPS`]) from the integer `offset_px` to the offset whose NCC
/// beats its four neighbours and samples the NCC on the 3 x 3 offsets around it. All samples
/// use the same pixels of a (the overlap shrunk by 1 px), so the change of the overlap with the
/// shift does not leak into the peak shape.
fn ncc_peak(a: &LevelledTile<'_>, b: &LevelledTile<'_>, offset_px: [i64; 2]) -> NccPeak {
    let mut off = offset_px;
    let mut steps = 0;
    loop {
        let ov = overlap_in_a(a, b, off[0], off[1]);
        let region = [ov[0] + 1, ov[1] - 1, ov[2] + 1, ov[3] - 1];
        if region[1] <= region[0] || region[3] <= region[2] {
            return NccPeak {
                offset_px: off,
                c: [[0.0; 3]; 3],
                roundness: 0.0,
            };
        }
        let c = ncc_stencil(a, b, off, region);
        let c0 = c[1][1];
        let (xm, xp, ym, yp) = (c[1][0], c[1][2], c[0][1], c[2][1]);
        let step = [(xm, -1, 0), (xp, 1, 0), (ym, 0, -1), (yp, 0, 1)]
            .into_iter()
            .filter(|s| s.0 > c0)
            .max_by(|p, q| p.0.total_cmp(&q.0));
        if let Some((_, dx, dy)) = step {
            if steps < MAX_CLIMB_STEPS {
                off = [off[0] + dx, off[1] + dy];
                steps += 1;
                continue;
            }
        }
        // Curvatures: eigenvalues of minus the Hessian (second differences).
        let hxx = xm - 2.0 * c0 + xp;
        let hyy = ym - 2.0 * c0 + yp;
        let hxy = (c[2][2] + c[0][0] - c[0][2] - c[2][0]) * 0.25;
        let (p, q, r) = (-hxx, -hyy, -hxy);
        let mean = 0.5 * (p + q);
        let disc = (0.25 * (p - q) * (p - q) + r * r).sqrt();
        let (l_max, l_min) = (mean + disc, mean - disc);
        let roundness = if l_max > 0.0 && l_min > 0.0 {
            l_min / l_max
        } else {
            0.0
        };
        return NccPeak {
            offset_px: off,
            c,
            roundness,
        };
    }
}

/// The shift of the integer offset `offset_px` from the nominal offset, px.
fn shift_from(offset_px: [i64; 2], nominal_offset_px: [f64; 2]) -> [f64; 2] {
    [
        offset_px[0] as f64 - nominal_offset_px[0],
        offset_px[1] as f64 - nominal_offset_px[1],
    ]
}

/// Chebyshev distance between two integer offsets, px.
fn chebyshev(p: [i64; 2], q: [i64; 2]) -> i64 {
    (p[0] - q[0]).abs().max((p[1] - q[1]).abs())
}

/// Window coefficients for `n` samples.
fn window(n: usize, kind: Window) -> Vec<f32> {
    let alpha = match kind {
        Window::Rectangular => 0.0,
        Window::Hann => 1.0,
        Window::Tukey { alpha } => alpha,
    };
    if n < 2 || alpha <= 0.0 {
        return vec![1.0; n];
    }
    let m = (n - 1) as f64;
    let edge = alpha * m / 2.0;
    (0..n)
        .map(|i| {
            let x = i as f64;
            let d = x.min(m - x);
            if d >= edge {
                1.0
            } else {
                (0.5 * (1.0 - (std::f64::consts::PI * d / edge).cos())) as f32
            }
        })
        .collect()
}

/// Levels the crop `rect = (x0, y0, w, h)` of `tile` by its least-squares plane and writes it
/// windowed into the real (`imag == false`) or imaginary part of `buf` (row stride `stride`).
/// NaN becomes 0 after levelling, or with `fill` the average of its valid neighbours (see
/// [`fill_dropouts`]).
#[allow(clippy::too_many_arguments)]
fn prepare_crop(
    tile: &RasterView<'_, f32>,
    rect: (usize, usize, usize, usize),
    wx: &[f32],
    wy: &[f32],
    buf: &mut [Complex32],
    stride: usize,
    imag: bool,
    fill: bool,
) -> CropStats {
    let (x0, y0, w, h) = rect;
    let cx = (w as f64 - 1.0) * 0.5;
    let cy = (h as f64 - 1.0) * 0.5;
    // Heights relative to one sample of the crop keep the f64 sums well conditioned (and a
    // constant crop exactly zero).
    let z_ref = (0..h)
        .flat_map(|r| tile.row(y0 + r)[x0..x0 + w].iter())
        .find(|v| v.is_finite())
        .copied()
        .unwrap_or(0.0);
    let mut sums = PlaneSums::default();
    for r in 0..h {
        sums.add_row_offset(r as f64 - cy, -cx, &tile.row(y0 + r)[x0..x0 + w], z_ref);
    }
    let valid = sums.count();
    let (mut plane, rms) = match sums.solve() {
        Some((p, _, rms)) => (p, rms),
        None => (PlaneCorrection::ZERO, 0.0),
    };
    plane.piston_um += z_ref as f64;
    // Plane value at crop pixel (r, c): p + tx * (c - cx) + ty * (r - cy).
    let txc: Vec<f32> = (0..w)
        .map(|c| (plane.tilt_x_um_per_px * (c as f64 - cx)) as f32)
        .collect();
    let mut line = vec![0.0f32; w];
    for r in 0..h {
        let row = &tile.row(y0 + r)[x0..x0 + w];
        let base = (plane.piston_um + plane.tilt_y_um_per_px * (r as f64 - cy)) as f32;
        let wr = wy[r];
        for (((o, &z), &t), &wc) in line.iter_mut().zip(row).zip(&txc).zip(wx) {
            let v = (z - base - t) * (wr * wc);
            // NaN stays NaN through the arithmetic.
            *o = if v.is_finite() { v } else { 0.0 };
        }
        let out = &mut buf[r * stride..r * stride + w];
        if imag {
            for (o, &v) in out.iter_mut().zip(&line) {
                o.im = v;
            }
        } else {
            for (o, &v) in out.iter_mut().zip(&line) {
                o.re = v;
            }
        }
    }
    // Scale for the cross-power threshold only: sum of squares of the windowed crop.
    let mean_w2 = wx.iter().map(|v| v * v).sum::<f32>() as f64 / w as f64
        * wy.iter().map(|v| v * v).sum::<f32>() as f64
        / h as f64;
    let energy = rms * rms * valid as f64 * mean_w2;
    if fill && valid < w * h {
        fill_dropouts(tile, rect, buf, stride, imag);
    }
    CropStats {
        valid,
        rms_um: rms,
        ref_um: z_ref as f64,
        energy,
        plane,
    }
}

/// Fills the dropouts of a prepared crop in `buf` with the binomial-weighted (5 x 5) average
/// of their valid neighbours (normalised convolution, computed only at dropouts); dropouts
/// with less than half of the kernel weight valid around them (inside large holes) stay 0.
/// The window varies little over 2 px, so averaging windowed values is accurate enough.
fn fill_dropouts(
    tile: &RasterView<'_, f32>,
    rect: (usize, usize, usize, usize),
    buf: &mut [Complex32],
    stride: usize,
    imag: bool,
) {
    const K: [f32; 5] = [1.0, 4.0, 6.0, 4.0, 1.0];
    const MIN_WEIGHT: f32 = 0.5 * 256.0;
    let (x0, y0, w, h) = rect;
    for r in 0..h {
        let row = &tile.row(y0 + r)[x0..x0 + w];
        if row.iter().all(|v| v.is_finite()) {
            continue;
        }
        let r0 = r.saturating_sub(2);
        let r1 = (r + 3).min(h);
        for c in 0..w {
            if row[c].is_finite() {
                continue;
            }
            let c0 = c.saturating_sub(2);
            let c1 = (c + 3).min(w);
            let (mut num, mut den) = (0.0f32, 0.0f32);
            for rr in r0..r1 {
                let kr = K[rr + 2 - r];
                let src = &tile.row(y0 + rr)[x0 + c0..x0 + c1];
                let vals = &buf[rr * stride + c0..rr * stride + c1];
                for (i, (&z, v)) in src.iter().zip(vals).enumerate() {
                    if z.is_finite() {
                        let k = kr * K[c0 + i + 2 - c];
                        num += k * if imag { v.im } else { v.re };
                        den += k;
                    }
                }
            }
            if den >= MIN_WEIGHT {
                let v = num / den;
                let o = &mut buf[r * stride + c];
                if imag {
                    o.im = v;
                } else {
                    o.re = v;
                }
            }
        }
    }
}

/// From the transposed spectrum `z = FFT(a + i b)` (`[kx][ky]`, `pw x ph`) writes the
/// normalised cross-power spectrum `FA conj(FB) / |FA conj(FB)|`, Gaussian-weighted when
/// `sigma > 0`, into `out` (same layout).
fn cross_power(z: &[Complex32], out: &mut [Complex32], pw: usize, ph: usize, eps: f32, sigma: f64) {
    let gauss = |n: usize| -> Vec<f32> {
        (0..n)
            .map(|k| {
                if sigma <= 0.0 {
                    return 1.0;
                }
                let kk = if k <= n / 2 {
                    k as f64
                } else {
                    k as f64 - n as f64
                };
                let f = kk / n as f64;
                (-2.0 * std::f64::consts::PI.powi(2) * sigma * sigma * f * f).exp() as f32
            })
            .collect()
    };
    let gx = gauss(pw);
    let gy = gauss(ph);
    let bin = |zk: Complex32, zm: Complex32, gk: f32| -> Complex32 {
        let zm = zm.conj();
        let fa = (zk + zm) * 0.5;
        // FB = (zk - zm) / (2i)
        let d = (zk - zm) * 0.5;
        let fb = Complex32::new(d.im, -d.re);
        let p = fa * fb.conj();
        let mag = (p.re * p.re + p.im * p.im).sqrt();
        if mag > eps {
            p * (gk / mag)
        } else {
            Complex32::new(0.0, 0.0)
        }
    };
    // The result is Hermitian (a and b are real): compute rows kx <= pw / 2, mirror the rest.
    let half = pw / 2 + 1;
    let (lo, hi) = out.split_at_mut(half * ph);
    lo.par_chunks_mut(ph).enumerate().for_each(|(kx, line)| {
        let kxm = (pw - kx) % pw;
        let zrow = &z[kx * ph..(kx + 1) * ph];
        let zmrow = &z[kxm * ph..(kxm + 1) * ph];
        let g = gx[kx];
        line[0] = bin(zrow[0], zmrow[0], g * gy[0]);
        // ky >= 1 pairs with ph - ky: read backwards.
        for (((o, &zk), &zm), &gk) in line[1..]
            .iter_mut()
            .zip(&zrow[1..])
            .zip(zmrow[1..].iter().rev())
            .zip(&gy[1..])
        {
            *o = bin(zk, zm, g * gk);
        }
    });
    let lo = &*lo;
    hi.par_chunks_mut(ph).enumerate().for_each(|(i, line)| {
        let kxm = pw - (half + i);
        let src = &lo[kxm * ph..(kxm + 1) * ph];
        line[0] = src[0].conj();
        for (o, s) in line[1..].iter_mut().zip(src[1..].iter().rev()) {
            *o = s.conj();
        }
    });
}

/// The `k` strongest local maxima of the circular surface `s` (`ph x pw`) within
/// |tx| <= range_x, |ty| <= range_y, at least 3 px apart (Chebyshev). Returns (value, tx, ty).
fn local_maxima(
    s: &[f32],
    pw: usize,
    ph: usize,
    range_x: i64,
    range_y: i64,
    k: usize,
) -> Vec<(f32, i64, i64)> {
    let keep = (4 * k).max(16);
    let wrap = |t: i64, n: usize| -> usize { t.rem_euclid(n as i64) as usize };
    let mut top: Vec<(f32, i64, i64)> = Vec::with_capacity(keep + 1);
    let mut floor = f32::NEG_INFINITY;
    for ty in -range_y..=range_y {
        let r = wrap(ty, ph);
        let rm = wrap(ty - 1, ph);
        let rp = wrap(ty + 1, ph);
        for tx in -range_x..=range_x {
            let c = wrap(tx, pw);
            let v = s[r * pw + c];
            if v.is_nan() || v <= floor {
                continue;
            }
            let cm = wrap(tx - 1, pw);
            let cp = wrap(tx + 1, pw);
            let is_max = v > s[r * pw + cm]
                && v >= s[r * pw + cp]
                && v > s[rm * pw + cm]
                && v > s[rm * pw + c]
                && v > s[rm * pw + cp]
                && v >= s[rp * pw + cm]
                && v >= s[rp * pw + c]
                && v >= s[rp * pw + cp];
            if !is_max {
                continue;
            }
            let pos = top.partition_point(|e| e.0 >= v);
            top.insert(pos, (v, tx, ty));
            if top.len() > keep {
                top.pop();
            }
            if top.len() == keep {
                floor = top[keep - 1].0;
            }
        }
    }
    let mut out: Vec<(f32, i64, i64)> = Vec::with_capacity(k);
    for p in top {
        if out
            .iter()
            .all(|q| (q.1 - p.1).abs().max((q.2 - p.2).abs()) >= 3)
        {
            out.push(p);
            if out.len() == k {
                break;
            }
        }
    }
    out
}

/// Offset of the true peak from the middle of three samples (minus, centre, plus), in
/// [-1, 1].
fn fit_peak(cm: f64, c0: f64, cp: f64, fit: PeakFit) -> f64 {
    let parabolic = || {
        let den = cm - 2.0 * c0 + cp;
        if den < 0.0 {
            0.5 * (cm - cp) / den
        } else {
            0.0
        }
    };
    let d = match fit {
        PeakFit::Parabolic => parabolic(),
        PeakFit::Gaussian => {
            if cm > 0.0 && c0 > 0.0 && cp > 0.0 {
                let (lm, l0, lp) = (cm.ln(), c0.ln(), cp.ln());
                let den = lm - 2.0 * l0 + lp;
                if den < 0.0 {
                    0.5 * (lm - lp) / den
                } else {
                    0.0
                }
            } else {
                parabolic()
            }
        }
        PeakFit::Foroosh => {
            if cp >= cm {
                if cp > 0.0 && c0 > 0.0 {
                    cp / (cp + c0)
                } else {
                    parabolic()
                }
            } else if cm > 0.0 && c0 > 0.0 {
                -cm / (cm + c0)
            } else {
                parabolic()
            }
        }
    };
    if d.is_finite() {
        d.clamp(-1.0, 1.0)
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn windows_have_expected_shape() {
        let h = window(9, Window::Hann);
        assert!(h[0].abs() < 1e-6 && (h[4] - 1.0).abs() < 1e-6);
        let t = window(100, Window::Tukey { alpha: 0.5 });
        assert!(t[0].abs() < 1e-6 && t[50] == 1.0 && t[30] == 1.0 && t[10] < 1.0);
        assert!(window(5, Window::Rectangular).iter().all(|&v| v == 1.0));
    }

    #[test]
    fn refine_recovers_gaussian_peak() {
        for &d in &[-0.4, -0.1, 0.0, 0.25, 0.49] {
            let g = |x: f64| (-(x - d) * (x - d) / 2.0).exp();
            let est = fit_peak(g(-1.0), g(0.0), g(1.0), PeakFit::Gaussian);
            assert!((est - d).abs() < 1e-9, "{est} vs {d}");
        }
    }

    #[test]
    fn refine_recovers_sinc_peak_with_foroosh() {
        let sinc = |x: f64| {
            if x.abs() < 1e-12 {
                1.0
            } else {
                (std::f64::consts::PI * x).sin() / (std::f64::consts::PI * x)
            }
        };
        for &d in &[-0.4, -0.1, 0.2, 0.45] {
            let est = fit_peak(sinc(-1.0 - d), sinc(-d), sinc(1.0 - d), PeakFit::Foroosh);
            assert!((est - d).abs() < 1e-9, "{est} vs {d}");
        }
    }
}
