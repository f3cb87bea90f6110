//! Pairwise registration: phase correlation on the nominal overlap, NCC verification of the
//! candidate peaks, sub-pixel refinement and the decision to answer or to refuse.

use rayon::prelude::*;
use rustfft::num_complex::Complex32;
use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::fft2::{fast_len, Fft2};
use crate::plane::{PlaneCorrection, PlaneSums};
use crate::raster::{validate_offset, InputError, RasterRef};

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

/// How the integer correlation peak is refined to sub-pixel precision (separately along x and
/// y, from the peak and its two neighbours on the correlation surface).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum SubPixel {
    /// No refinement: integer shifts.
    None,
    /// Vertex of the parabola through the three samples.
    Parabolic,
    /// Vertex of the Gaussian through the three samples (parabola on their logarithms).
    Gaussian,
    /// Foroosh et al. (2002): the peak of a Dirichlet (sinc) kernel,
    /// `d = c1 / (c1 + c0)` towards the larger neighbour.
    Foroosh,
    /// Weighted least-squares fit of the cross-power phase slope on the re-cropped pair (no
    /// correlation-surface fit).
    PhasePlane,
}

/// Parameters of [`register_pair`]. The defaults were tuned on the crate's synthetic tests
/// (see the crate documentation).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct PhaseParams {
    /// Smallest NCC (levelled heights, actual overlap) of an accepted registration.
    pub min_ncc: f64,
    /// Largest accepted |shift from nominal| per axis, px.
    pub max_shift_px: f64,
    /// The shift limit along an axis is also at most this fraction of the overlap extent
    /// along that axis.
    pub max_shift_fraction: f64,
    /// Smallest width and height of the nominal overlap, px.
    pub min_overlap_side_px: usize,
    /// Smallest number of valid pixels in each overlap crop and of valid pixel pairs in the
    /// NCC of the chosen shift.
    pub min_valid_px: usize,
    /// Smallest fraction of valid pixels in each overlap crop.
    pub min_valid_fraction: f64,
    /// Number of correlation peaks verified by NCC.
    pub candidates: usize,
    /// A rival candidate (at least 3 px from the best) whose NCC is within this margin of the
    /// best, and whose correlation peak is at least `rival_peak_fraction` of the best's, makes
    /// the answer ambiguous.
    pub ambiguity_margin: f64,
    /// See `ambiguity_margin`.
    pub rival_peak_fraction: f64,
    /// Window applied to each crop before the FFT.
    pub window: Window,
    /// Gaussian weighting of the normalised cross-power spectrum, expressed as the standard
    /// deviation (px) of the resulting blur of the correlation peak; 0 disables it. It damps
    /// the noise-dominated high frequencies and gives the peak a Gaussian shape.
    pub peak_sigma_px: f64,
    /// Regularised whitening: the cross-power is divided by `|P| + whitening_floor * mean|P|`
    /// instead of `|P|`, so that weak (noise-dominated) frequencies are damped instead of
    /// amplified to unit weight. 0 is the classic phase correlation.
    pub whitening_floor: f64,
    /// Sub-pixel estimator.
    pub subpixel: SubPixel,
    /// In the sub-pixel pass, fill dropouts with the average of their valid neighbourhood
    /// instead of 0 (zero-filled dropouts act as strong white noise).
    pub fill_dropouts: bool,
}

impl Default for PhaseParams {
    fn default() -> Self {
        PhaseParams {
            min_ncc: 0.5,
            max_shift_px: 30.0,
            max_shift_fraction: 0.45,
            min_overlap_side_px: 8,
            min_valid_px: 1024,
            min_valid_fraction: 0.2,
            candidates: 5,
            ambiguity_margin: 0.1,
            rival_peak_fraction: 0.5,
            window: Window::Tukey { alpha: 0.5 },
            peak_sigma_px: 1.0,
            whitening_floor: 0.0,
            subpixel: SubPixel::Gaussian,
            fill_dropouts: true,
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
        if !(self.peak_sigma_px.is_finite() && (0.0..=100.0).contains(&self.peak_sigma_px)) {
            return bad("peak_sigma_px", "must be in [0, 100]");
        }
        if !(self.whitening_floor.is_finite() && self.whitening_floor >= 0.0) {
            return bad("whitening_floor", "must be finite and >= 0");
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
}

impl PairRegistration {
    fn rejected(rejection: Rejection, overlap_px: [usize; 2]) -> Self {
        PairRegistration {
            offset_px: None,
            ncc: 0.0,
            peak_ratio: 0.0,
            shift_from_nominal_px: None,
            overlap_px,
            valid_overlap_px: 0,
            rejection: Some(rejection),
            candidates: Vec::new(),
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
    a: RasterRef<'_>,
    b: RasterRef<'_>,
    nominal_offset_px: [f64; 2],
    params: &PhaseParams,
) -> PairRegistration {
    PhaseCorrelator::new().register(a, b, nominal_offset_px, params)
}

/// A tile levelled on the fly by the plane fitted to its crop: the plane at (row, col) is
/// `row_term[row] + col_term[col]`.
struct LevelledTile<'a> {
    tile: RasterRef<'a>,
    row_term: Vec<f32>,
    col_term: Vec<f32>,
}

impl<'a> LevelledTile<'a> {
    /// `plane` as fitted on the crop `rect` (crop-centred coordinates), extended to the tile.
    fn new(tile: RasterRef<'a>, rect: (usize, usize, usize, usize), plane: &PlaneCorrection) -> Self {
        let (x0, y0, w, h) = rect;
        let cx = x0 as f64 + (w as f64 - 1.0) * 0.5;
        let cy = y0 as f64 + (h as f64 - 1.0) * 0.5;
        LevelledTile {
            tile,
            row_term: (0..tile.height)
                .map(|r| (plane.piston_um + plane.tilt_y_um_per_px * (r as f64 - cy)) as f32)
                .collect(),
            col_term: (0..tile.width)
                .map(|c| (plane.tilt_x_um_per_px * (c as f64 - cx)) as f32)
                .collect(),
        }
    }
}

/// Phase correlation with cached FFT plans and reusable buffers. Not `Sync`; keep one per
/// thread.
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

/// Overlap geometry derived from the rounded nominal offset.
#[derive(Debug, Clone, Copy)]
struct Geometry {
    /// Rounded nominal offset.
    ndx: i64,
    ndy: i64,
    /// Overlap rectangle in a's coordinates.
    x0: usize,
    y0: usize,
    w: usize,
    h: usize,
}

fn geometry(a: &RasterRef<'_>, b: &RasterRef<'_>, nominal: [f64; 2]) -> Geometry {
    let ndx = nominal[0].round() as i64;
    let ndy = nominal[1].round() as i64;
    let x0 = ndx.max(0);
    let x1 = (ndx + b.width as i64).min(a.width as i64);
    let y0 = ndy.max(0);
    let y1 = (ndy + b.height as i64).min(a.height as i64);
    Geometry {
        ndx,
        ndy,
        x0: x0.max(0) as usize,
        y0: y0.max(0) as usize,
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
        a: RasterRef<'_>,
        b: RasterRef<'_>,
        nominal_offset_px: [f64; 2],
        params: &PhaseParams,
    ) -> PairRegistration {
        let checked = a
            .validate()
            .and_then(|_| b.validate())
            .and_then(|_| validate_offset(nominal_offset_px))
            .and_then(|_| params.validate());
        if let Err(e) = checked {
            return PairRegistration::rejected(Rejection::InvalidInput(e), [0, 0]);
        }
        let g = geometry(&a, &b, nominal_offset_px);
        let overlap_px = [g.w, g.h];
        if g.w < params.min_overlap_side_px || g.h < params.min_overlap_side_px {
            return PairRegistration::rejected(
                Rejection::NoOverlap {
                    overlap_px,
                    min_side_px: params.min_overlap_side_px,
                },
                overlap_px,
            );
        }
        let (w, h) = (g.w, g.h);
        // Candidate search range: at least half the crop overlaps.
        let range_x = (w / 2) as i64;
        let range_y = (h / 2) as i64;

        // Pass 1: crops at the rounded nominal offset; a at (x0, y0), b at (x0 - ndx, y0 - ndy).
        let rect_a = (g.x0, g.y0, w, h);
        let rect_b = (
            (g.x0 as i64 - g.ndx) as usize,
            (g.y0 as i64 - g.ndy) as usize,
            w,
            h,
        );
        let (stats_a, stats_b, pw, ph) = self.correlate(&a, &b, rect_a, rect_b, params, false);
        let area = w * h;
        let required = params
            .min_valid_px
            .max((params.min_valid_fraction * area as f64).ceil() as usize)
            .max(3);
        let valid = stats_a.valid.min(stats_b.valid);
        if valid < required {
            return PairRegistration::rejected(
                Rejection::TooFewValidPixels {
                    valid_px: valid,
                    required_px: required,
                },
                overlap_px,
            );
        }
        for s in [&stats_a, &stats_b] {
            // A plane (or constant) within f32 rounding of its height.
            if s.rms_um <= 1e-6 * (1.0 + s.ref_um.abs()) || s.energy <= 0.0 {
                return PairRegistration::rejected(
                    Rejection::Featureless { rms_um: s.rms_um },
                    overlap_px,
                );
            }
        }

        // Candidates: strongest local maxima, verified by NCC at their integer offsets.
        let peaks = local_maxima(
            &self.surface,
            pw,
            ph,
            range_x,
            range_y,
            params.candidates,
        );
        if peaks.is_empty() {
            return PairRegistration::rejected(Rejection::NoCandidate, overlap_px);
        }
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
        let best = cands[0];
        let others_peak = cands[1..]
            .iter()
            .map(|c| c.peak)
            .fold(f64::NEG_INFINITY, f64::max);
        let peak_ratio = if others_peak > 0.0 {
            (best.peak / others_peak).min(1000.0)
        } else {
            1000.0
        };

        // Sub-pixel refinement.
        let (fx, fy) = self.subpixel(&a, &b, best.offset_px, g, pw, ph, params);
        let offset = [best.offset_px[0] as f64 + fx, best.offset_px[1] as f64 + fy];
        let shift = [
            offset[0] - nominal_offset_px[0],
            offset[1] - nominal_offset_px[1],
        ];
        let mut out = PairRegistration {
            offset_px: None,
            ncc: best.ncc,
            peak_ratio,
            shift_from_nominal_px: Some(shift),
            overlap_px,
            valid_overlap_px: best.valid_px,
            rejection: None,
            candidates: cands.clone(),
        };

        if best.valid_px < min_pairs || best.ncc < params.min_ncc {
            out.rejection = Some(Rejection::LowNcc {
                ncc: best.ncc,
                min_ncc: params.min_ncc,
            });
            return out;
        }
        let rival = cands[1..].iter().find(|c| {
            let d = (c.offset_px[0] - best.offset_px[0])
                .abs()
                .max((c.offset_px[1] - best.offset_px[1]).abs());
            d >= 3
                && c.ncc >= best.ncc - params.ambiguity_margin
                && c.peak >= params.rival_peak_fraction * best.peak
        });
        if let Some(r) = rival {
            out.rejection = Some(Rejection::Ambiguous {
                best_ncc: best.ncc,
                rival_ncc: r.ncc,
                rival_shift_px: [
                    r.offset_px[0] as f64 - nominal_offset_px[0],
                    r.offset_px[1] as f64 - nominal_offset_px[1],
                ],
            });
            return out;
        }
        let limit = [
            params
                .max_shift_px
                .min(params.max_shift_fraction * w as f64),
            params
                .max_shift_px
                .min(params.max_shift_fraction * h as f64),
        ];
        if shift[0].abs() > limit[0] || shift[1].abs() > limit[1] {
            out.rejection = Some(Rejection::ShiftTooLarge {
                shift_px: shift,
                limit_px: limit,
            });
            return out;
        }
        out.offset_px = Some(offset);
        out
    }
}

impl PhaseCorrelator {
    /// Levels, windows and transforms the `w x h` crops `rect_a` of a and `rect_b` of b: the
    /// spectrum of `a + i b` is left transposed (`[kx][ky]`, `pw x ph`) in `self.spec`.
    fn spectrum(
        &mut self,
        a: &RasterRef<'_>,
        b: &RasterRef<'_>,
        rect_a: (usize, usize, usize, usize),
        rect_b: (usize, usize, usize, usize),
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
    /// (`ph x pw`, circular, index = shift of b's content relative to a's).
    fn correlate(
        &mut self,
        a: &RasterRef<'_>,
        b: &RasterRef<'_>,
        rect_a: (usize, usize, usize, usize),
        rect_b: (usize, usize, usize, usize),
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
            params.whitening_floor,
        );
        self.fft
            .inverse_from_transposed(&mut self.work, &mut self.spec, ph, pw);
        let norm = 1.0 / (pw * ph) as f32;
        self.surface.clear();
        self.surface.extend(self.spec.iter().map(|c| c.re * norm));
        (stats_a, stats_b, pw, ph)
    }

    /// Sub-pixel part of the offset whose integer part is `offset_px`. A second phase
    /// correlation on the actual overlap at the integer offset brings the residual shift below
    /// half a pixel, so the window no longer pulls the peak towards the crop's centre; the
    /// estimator then fits the peak near zero shift. Falls back to the pass-1 surface if the
    /// re-crop is degenerate.
    #[allow(clippy::too_many_arguments)]
    fn subpixel(
        &mut self,
        a: &RasterRef<'_>,
        b: &RasterRef<'_>,
        offset_px: [i64; 2],
        g: Geometry,
        pw: usize,
        ph: usize,
        params: &PhaseParams,
    ) -> (f64, f64) {
        if params.subpixel == SubPixel::None {
            return (0.0, 0.0);
        }
        let g2 = geometry(a, b, [offset_px[0] as f64, offset_px[1] as f64]);
        if g2.w < 3 || g2.h < 3 {
            let tx = offset_px[0] - g.ndx;
            let ty = offset_px[1] - g.ndy;
            return refine(&self.surface, pw, ph, tx, ty, params.subpixel);
        }
        let rect_a = (g2.x0, g2.y0, g2.w, g2.h);
        let rect_b = (
            (g2.x0 as i64 - g2.ndx) as usize,
            (g2.y0 as i64 - g2.ndy) as usize,
            g2.w,
            g2.h,
        );
        if params.subpixel == SubPixel::PhasePlane {
            let (_, _, pw2, ph2) =
                self.spectrum(a, b, rect_a, rect_b, params, params.fill_dropouts);
            return phase_plane(&self.spec, pw2, ph2);
        }
        let (_, _, pw2, ph2) =
            self.correlate(a, b, rect_a, rect_b, params, params.fill_dropouts);
        // The peak is now within one pixel of zero shift.
        let mut best = (f32::NEG_INFINITY, 0i64, 0i64);
        for ty in -1..=1i64 {
            for tx in -1..=1i64 {
                let v = self.surface[ty.rem_euclid(ph2 as i64) as usize * pw2
                    + tx.rem_euclid(pw2 as i64) as usize];
                if v > best.0 {
                    best = (v, tx, ty);
                }
            }
        }
        let (fx, fy) = refine(&self.surface, pw2, ph2, best.1, best.2, params.subpixel);
        (best.1 as f64 + fx, best.2 as f64 + fy)
    }
}

/// Sub-pixel shift from the slope of the cross-power phase: from the transposed spectrum
/// `z = FFT(a + i b)` of two crops aligned to within about a pixel, fits
/// `arg(FA conj(FB)) = -2 pi (fx sx + fy sy)` by least squares weighted by `|FA conj(FB)|`,
/// coarse to fine (frequency bands up to 1/8, then 1/4, then 3/8 cycles per pixel), each
/// step fitting the residual phase after removing the current estimate so that it never
/// wraps.
fn phase_plane(z: &[Complex32], pw: usize, ph: usize) -> (f64, f64) {
    let tau = std::f64::consts::TAU;
    let (mut sx, mut sy) = (0.0f64, 0.0f64);
    for band in [0.125, 0.25, 0.375, 0.375] {
        let kx_max = (band * pw as f64) as i64;
        let ky_max = (band * ph as f64) as i64;
        // Rows kx in [-kx_max, kx_max] of the transposed layout.
        let sums = (-kx_max..=kx_max)
            .into_par_iter()
            .map(|kxs| {
                let kx = kxs.rem_euclid(pw as i64) as usize;
                let kxm = (pw - kx) % pw;
                let fx = kxs as f64 / pw as f64;
                let zrow = &z[kx * ph..(kx + 1) * ph];
                let zmrow = &z[kxm * ph..(kxm + 1) * ph];
                let mut acc = [0.0f64; 5];
                for kys in -ky_max..=ky_max {
                    if kxs == 0 && kys == 0 {
                        continue;
                    }
                    let ky = kys.rem_euclid(ph as i64) as usize;
                    let kym = (ph - ky) % ph;
                    let fy = kys as f64 / ph as f64;
                    let zk = zrow[ky];
                    let zm = zmrow[kym].conj();
                    let fa = (zk + zm) * 0.5;
                    let d = (zk - zm) * 0.5;
                    let fb = Complex32::new(d.im, -d.re);
                    let p = fa * fb.conj();
                    let wgt = (p.re * p.re + p.im * p.im).sqrt() as f64;
                    if !(wgt > 0.0) {
                        continue;
                    }
                    // Residual phase after removing the current estimate.
                    let ramp = tau * (fx * sx + fy * sy);
                    let (sn, cs) = ramp.sin_cos();
                    let (pr, pi) = (p.re as f64, p.im as f64);
                    let r = (pi * cs + pr * sn).atan2(pr * cs - pi * sn);
                    // r = -tau * (fx dx + fy dy)
                    acc[0] += wgt * fx * fx;
                    acc[1] += wgt * fx * fy;
                    acc[2] += wgt * fy * fy;
                    acc[3] += wgt * fx * r;
                    acc[4] += wgt * fy * r;
                }
                acc
            })
            .reduce(
                || [0.0f64; 5],
                |mut u, v| {
                    for (x, y) in u.iter_mut().zip(v) {
                        *x += y;
                    }
                    u
                },
            );
        let [a11, a12, a22, b1, b2] = sums;
        let det = a11 * a22 - a12 * a12;
        if !(det > 0.0) {
            break;
        }
        let dx = -(a22 * b1 - a12 * b2) / (det * tau);
        let dy = -(a11 * b2 - a12 * b1) / (det * tau);
        if !(dx.is_finite() && dy.is_finite()) {
            break;
        }
        sx += dx;
        sy += dy;
    }
    (sx.clamp(-1.5, 1.5), sy.clamp(-1.5, 1.5))
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
    tile: &RasterRef<'_>,
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
            // NaN stays NaN through the arithmetic: v - v is 0 only for finite values.
            *o = if (v - v) == 0.0 { v } else { 0.0 };
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
    tile: &RasterRef<'_>,
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
/// normalised cross-power spectrum `FA conj(FB) / |FA conj(FB)|`, optionally Gaussian-weighted,
/// into `out` (same layout).
#[allow(clippy::too_many_arguments)]
fn cross_power(
    z: &[Complex32],
    out: &mut [Complex32],
    pw: usize,
    ph: usize,
    eps: f32,
    sigma: f64,
    floor_fraction: f64,
) {
    let gauss = |n: usize| -> Vec<f32> {
        (0..n)
            .map(|k| {
                if sigma <= 0.0 {
                    return 1.0;
                }
                let kk = if k <= n / 2 { k as f64 } else { k as f64 - n as f64 };
                let f = kk / n as f64;
                (-2.0 * std::f64::consts::PI.powi(2) * sigma * sigma * f * f).exp() as f32
            })
            .collect()
    };
    let gx = gauss(pw);
    let gy = gauss(ph);
    // The result is Hermitian (a and b are real): compute rows kx <= pw / 2, mirror the rest.
    let half = pw / 2 + 1;
    let (lo, hi) = out.split_at_mut(half * ph);
    // 1. The raw cross-power FA conj(FB), and the sum of its magnitudes.
    let bin = |zk: Complex32, zm: Complex32| -> Complex32 {
        let zm = zm.conj();
        let fa = (zk + zm) * 0.5;
        // FB = (zk - zm) / (2i)
        let d = (zk - zm) * 0.5;
        let fb = Complex32::new(d.im, -d.re);
        fa * fb.conj()
    };
    let sum_mag: f64 = lo
        .par_chunks_mut(ph)
        .enumerate()
        .map(|(kx, line)| {
            let kxm = (pw - kx) % pw;
            let zrow = &z[kx * ph..(kx + 1) * ph];
            let zmrow = &z[kxm * ph..(kxm + 1) * ph];
            line[0] = bin(zrow[0], zmrow[0]);
            // ky >= 1 pairs with ph - ky, read backwards.
            for ((o, &zk), &zm) in line[1..]
                .iter_mut()
                .zip(&zrow[1..])
                .zip(zmrow[1..].iter().rev())
            {
                *o = bin(zk, zm);
            }
            // Rows 0 < kx < pw / 2 stand for two rows of the full spectrum.
            let weight = if kx == 0 || 2 * kx == pw { 1.0 } else { 2.0 };
            weight * line.iter().map(|p| p.norm() as f64).sum::<f64>()
        })
        .sum();
    // 2. Normalise: |P| + floor, the floor a fraction of the mean magnitude.
    let floor = (floor_fraction * sum_mag / (pw * ph) as f64).max(eps as f64) as f32;
    lo.par_chunks_mut(ph).enumerate().for_each(|(kx, line)| {
        let g = gx[kx];
        for (p, &gk) in line.iter_mut().zip(&gy) {
            let mag = (p.re * p.re + p.im * p.im).sqrt();
            *p = if mag > eps {
                *p * (g * gk / (mag + floor))
            } else {
                Complex32::new(0.0, 0.0)
            };
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
            if !(v > floor) {
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

/// NCC of the levelled heights of a and b over their actual overlap when b's origin sits at
/// `(dx, dy)` in a's coordinates; valid pairs only. Returns (ncc, pairs).
fn ncc_at(a: &LevelledTile<'_>, b: &LevelledTile<'_>, dx: i64, dy: i64) -> (f64, usize) {
    let (wa, ha) = (a.tile.width as i64, a.tile.height as i64);
    let (wb, hb) = (b.tile.width as i64, b.tile.height as i64);
    let x0 = dx.max(0);
    let x1 = (dx + wb).min(wa);
    let y0 = dy.max(0);
    let y1 = (dy + hb).min(ha);
    if x1 <= x0 || y1 <= y0 {
        return (0.0, 0);
    }
    let (xa0, xa1) = (x0 as usize, x1 as usize);
    let (xb0, xb1) = ((x0 - dx) as usize, (x1 - dx) as usize);
    let mut acc = [0.0f64; 6];
    for ya in y0..y1 {
        let yb = (ya - dy) as usize;
        let ya = ya as usize;
        let row = row_sums(
            &a.tile.row(ya)[xa0..xa1],
            &a.col_term[xa0..xa1],
            a.row_term[ya],
            &b.tile.row(yb)[xb0..xb1],
            &b.col_term[xb0..xb1],
            b.row_term[yb],
        );
        for (t, v) in acc.iter_mut().zip(row) {
            *t += v as f64;
        }
    }
    let [n, sa, sb, saa, sbb, sab] = acc;
    if n < 2.0 {
        return (0.0, n as usize);
    }
    let va = saa - sa * sa / n;
    let vb = sbb - sb * sb / n;
    let cov = sab - sa * sb / n;
    let den = (va * vb).sqrt();
    let ncc = if den > 0.0 && den.is_finite() {
        (cov / den).clamp(-1.0, 1.0)
    } else {
        0.0
    };
    (ncc, n as usize)
}

/// [n, sum a, sum b, sum a^2, sum b^2, sum ab] of the levelled rows `a = za - (ra + ca)`,
/// `b = zb - (rb + cb)` over pairs valid (finite) in both; branch-free lanes so the compiler
/// vectorises it.
#[inline]
fn row_sums(za: &[f32], ca: &[f32], ra: f32, zb: &[f32], cb: &[f32], rb: f32) -> [f32; 6] {
    const L: usize = 8;
    let mut acc = [[0.0f32; L]; 6];
    let lane = |acc: &mut [[f32; L]; 6], l: usize, za: f32, ca: f32, zb: f32, cb: f32| {
        let a = za - (ra + ca);
        let b = zb - (rb + cb);
        // x - x is 0 exactly for finite x, NaN otherwise.
        let oka = (a - a) == 0.0;
        let okb = (b - b) == 0.0;
        let ma = if oka { 1.0 } else { 0.0 };
        let mb = if okb { 1.0 } else { 0.0 };
        let a = if oka { a } else { 0.0 };
        let b = if okb { b } else { 0.0 };
        let am = a * mb;
        let bm = b * ma;
        acc[0][l] += ma * mb;
        acc[1][l] += am;
        acc[2][l] += bm;
        acc[3][l] += a * am;
        acc[4][l] += b * bm;
        acc[5][l] += a * b;
    };
    let n = za.len();
    let chunks = n / L;
    for k in 0..chunks {
        let o = k * L;
        let (za, ca, zb, cb) = (&za[o..o + L], &ca[o..o + L], &zb[o..o + L], &cb[o..o + L]);
        for l in 0..L {
            lane(&mut acc, l, za[l], ca[l], zb[l], cb[l]);
        }
    }
    for i in chunks * L..n {
        lane(&mut acc, 0, za[i], ca[i], zb[i], cb[i]);
    }
    let mut out = [0.0f32; 6];
    for (o, a) in out.iter_mut().zip(&acc) {
        *o = a.iter().sum();
    }
    out
}

/// Sub-pixel offsets (fx, fy) of the peak at integer shift (tx, ty) of the circular surface.
fn refine(s: &[f32], pw: usize, ph: usize, tx: i64, ty: i64, method: SubPixel) -> (f64, f64) {
    let at = |x: i64, y: i64| -> f64 {
        let c = x.rem_euclid(pw as i64) as usize;
        let r = y.rem_euclid(ph as i64) as usize;
        s[r * pw + c] as f64
    };
    let c0 = at(tx, ty);
    let fx = refine_1d(at(tx - 1, ty), c0, at(tx + 1, ty), method);
    let fy = refine_1d(at(tx, ty - 1), c0, at(tx, ty + 1), method);
    (fx, fy)
}

/// Offset of the true peak from the middle of three samples (minus, centre, plus), in
/// [-1, 1].
fn refine_1d(cm: f64, c0: f64, cp: f64, method: SubPixel) -> f64 {
    let parabolic = || {
        let den = cm - 2.0 * c0 + cp;
        if den < 0.0 {
            0.5 * (cm - cp) / den
        } else {
            0.0
        }
    };
    let d = match method {
        SubPixel::None => 0.0,
        SubPixel::Parabolic | SubPixel::PhasePlane => parabolic(),
        SubPixel::Gaussian => {
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
        SubPixel::Foroosh => {
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
            let est = refine_1d(g(-1.0), g(0.0), g(1.0), SubPixel::Gaussian);
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
            let est = refine_1d(sinc(-1.0 - d), sinc(-d), sinc(1.0 - d), SubPixel::Foroosh);
            assert!((est - d).abs() < 1e-9, "{est} vs {d}");
        }
    }

    #[test]
    fn ncc_of_identical_tiles_is_one_and_ignores_plane_and_nan() {
        let (w, h) = (40, 30);
        let mut za: Vec<f32> = (0..w * h).map(|i| ((i * 37) % 17) as f32).collect();
        let mut zb: Vec<f32> = za
            .iter()
            .enumerate()
            .map(|(i, v)| v + 3.0 + 0.01 * (i % w) as f32)
            .collect();
        za[5] = f32::NAN;
        zb[77] = f32::NAN;
        let ta = RasterRef::new(&za, w, h).expect("valid");
        let tb = RasterRef::new(&zb, w, h).expect("valid");
        let rect = (0, 0, w, h);
        let la = LevelledTile::new(ta, rect, &PlaneCorrection::ZERO);
        let plane_b = PlaneCorrection {
            piston_um: 3.0 + 0.01 * (w as f64 - 1.0) / 2.0,
            tilt_x_um_per_px: 0.01,
            tilt_y_um_per_px: 0.0,
        };
        let lb = LevelledTile::new(tb, rect, &plane_b);
        let (ncc, n) = ncc_at(&la, &lb, 0, 0);
        assert_eq!(n, w * h - 2);
        assert!((ncc - 1.0).abs() < 1e-6, "{ncc}");
        // Shifted by 3 px: overlap shrinks accordingly.
        let (_, n3) = ncc_at(&la, &lb, 3, -2);
        assert!(n3 <= (w - 3) * (h - 2));
    }
}
