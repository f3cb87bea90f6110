//! surfstream-matcher: registration of overlapping height-map tiles (DESIGN.md §8,
//! "registration": phase correlation, NCC verification, per-tile z alignment).
//!
//! An optical profiler scans a part as a serpentine of overlapping tiles; each tile comes with
//! a nominal stage position (a few pixels off), its own piston and tilt, noise and NaN
//! dropouts. This crate measures where a tile really sits relative to a placed neighbour, and
//! how to bring its heights to its neighbours' level. Plain functions over borrowed rasters,
//! and one stateful type for a whole scan ([`ScanRegistration`]): no IPC, no globals; the files
//! it touches are an optional truth file for scoring feature matches, the spill of the placed
//! tiles it does not keep resident and the pair log (`nodes/<id>.pairs.jsonl`, [`pair_log`]).
//!
//! Conventions (DESIGN.md §2): heights are f32 micrometres, row-major, rows grow with y,
//! columns with x, NaN = not measured. Offsets are `[x, y]` in pixels: the position of tile
//! b's pixel (0, 0) minus tile a's pixel (0, 0).
//!
//! # A whole scan: [`ScanRegistration`] (the node's logic)
//!
//! Tiles go in as the stage delivers them ([`ScanTile`]: index, grid row/column, stage
//! position, heights); each is registered against its already-placed grid neighbours with the
//! chosen method and gets a streaming [`surfstream_core::TileRegistration`] (placed by
//! registration, or by the stage and flagged when no link is trusted, and levelled onto its
//! neighbours). [`ScanRegistration::finish`] runs the global solve (below) and returns the FINAL
//! placement of every tile; [`ScanRegistration::report`] is the node's run.json entry. The
//! method ([`ScanParams`], the node's `method` parameter) is `"auto"` (= `"phase"`, phase
//! correlation, below), `"harris"` or `"sift"` (the reference study's feature matchers).
//! `src/node.rs` only turns frames into these calls.
//!
//! # Pairwise registration: [`register_pair`], [`PhaseCorrelator`]
//!
//! 1. **Crops.** The nominal overlap rectangle (from the rounded nominal offset) is cut from
//!    both tiles. Each crop is levelled by its own least-squares plane over its valid pixels
//!    (piston and tilt do not matter), NaN is set to 0 after levelling, and a Tukey window
//!    (alpha 0.5) suppresses the edges. Both crops are zero-padded to a 2-3-5-smooth size and
//!    transformed together in one complex FFT (a in the real part, b in the imaginary part).
//!    [`PhaseCorrelator`] keeps the FFT plans and buffers, so a stream of pairs pays no
//!    planning or allocation.
//! 2. **Phase correlation.** The normalised cross-power spectrum, weighted by a Gaussian that
//!    blurs the correlation peak by `peak_sigma_px` (1 px): the weighting damps the
//!    noise-dominated high frequencies that whitening would amplify (it matters with heavy
//!    dropouts: without it some pairs at 30 % NaN are lost).
//! 3. **Candidates.** The 5 strongest local maxima of the correlation surface (at least 3 px
//!    apart, shifts up to half the crop) are each verified by the NCC of the levelled heights
//!    over the actual overlap at that integer offset (valid pixel pairs only, the full tiles
//!    beyond the crop). The best NCC wins.
//! 4. **Sub-pixel.** From the winner, a climb (up to 8 steps) to the integer maximum of the
//!    NCC, then the NCC on the 3 x 3 offsets around it (one common set of a's pixels) and a
//!    3-point Gaussian fit along x and along y ([`SubPixel::NccGaussian`]). Each of these NCCs
//!    removes both sides' least-squares plane over that offset's own pixel pairs: a plane
//!    fitted at another offset pulls the maximum towards that offset on narrow overlaps of
//!    surfaces smooth at the pixel scale (1-2 px on the benchmark's grating). This measured best: the
//!    NCC is NaN-aware without any filling and unbiased by the window, whereas a fit on the
//!    phase-correlation peak (even after a second, re-centred pass) suffers on surfaces that
//!    are smooth at the pixel scale, where whitening amplifies noise and dropouts. The
//!    alternatives stay selectable; `examples/accuracy.rs` compares them (below).
//! 5. **Decision.** No answer rather than a wrong one ([`Rejection`]): overlap smaller than
//!    8 px on a side, fewer valid pixels than 1024 or 20 % of the overlap, a featureless
//!    (planar) overlap, NCC below `min_ncc` (0.5; true matches measure 0.93-0.99 on the tests,
//!    unrelated or noise pairs below 0.2), an ambiguous match (a rival candidate at least 3 px
//!    away with NCC within 0.1 of the best and a correlation peak at least half the best's,
//!    whose own NCC climb ends on a different maximum, as on periodic textures; the distinct
//!    maxima go to the global solve, which takes the one consistent with the scan:
//!    [`global::solve_positions_with_alternatives`]), a peak that is a ridge (NCC curvature ratio below 0.05: 1-D
//!    textures fix no offset along their lines), or a shift from nominal beyond
//!    `max_shift_px` (30 px) or 45 % of the overlap extent along that axis.
//!
//! # The paper's feature matchers: [`register_pair_features`] (`method = "harris" | "sift"`)
//!
//! The reference study's registration, selectable in the node and `surfstream stitch
//! --method`; it returns the same [`PairRegistration`] as phase correlation, so the global
//! solve and z alignment are shared. Per pair:
//!
//! 1. **Regions.** Detection covers the nominal overlap grown by `search_px` (15 px, the stage
//!    error bound) in each tile; the conversion sees that region plus context for the filters.
//! 2. **Detector input** ([`detector`]): least-squares plane removed, band-pass (NaN-aware
//!    Gaussian smoothing sigma 1 px minus a NaN-aware low-pass sigma 8 px), then a robust
//!    stretch (1st..99th percentile onto [0, 1]). NaN never enters a filter as a number
//!    (normalised convolutions); a feature whose pixel is unmeasured or whose support is less
//!    than 90 % measured is dropped.
//! 3. **Features.** `harris` ([`harris`]): structure tensor with a Gaussian window (sigma
//!    1.5 px), R = det - k tr^2 with k = 0.04, threshold 0.001 max R, 7 x 7 non-maximum
//!    suppression, at most 400 corners, sub-pixel by parabola. `sift` ([`sift`]): Lowe 2004:
//!    doubled image, 3 scales per octave from sigma 1.6, DoG extrema, quadratic sub-pixel /
//!    sub-scale location, contrast 0.04 / 3 and edge ratio 10 tests, 36-bin orientation
//!    histogram (peaks within 80 %), 4 x 4 x 8 descriptor with trilinear binning,
//!    normalise-clip(0.2)-renormalise.
//! 4. **Matching** ([`feature_match`]). Only pairs whose displacement (position in a minus
//!    position in b) is within `search_px` of the nominal offset are candidates. `harris`:
//!    the NCC of the paper's equation 1 between 11 x 11 windows of the band-passed heights
//!    ([`feature_match::ncc_eq1`], over measured pixel pairs), then the two-way check (i's best
//!    is j and j's best is i) and NCC >= 0.7. `sift`: descriptor distance, Lowe's ratio test
//!    (0.8) and the same two-way check; the score is the descriptors' cosine similarity.
//! 5. **Sub-pixel and RANSAC.** Each two-way match is refined by a 3-point parabola of the
//!    window NCC one pixel either side of b's feature in x and y; then 1-point RANSAC for a
//!    pure translation (every match a hypothesis, inlier radius 1.5 px, at least 4 inliers);
//!    the offset is the mean of the inliers' refined displacements. A rival translation more
//!    than 3 px away with 70 % of the inliers makes the pair ambiguous (periodic textures).
//!    The residual rotation (and scale) of b against a comes from a least-squares similarity
//!    fit over the inliers and is reported: the stage does not rotate, so it measures how
//!    well that holds (median 0.02-0.03 deg on the anchors' sets).
//! 6. **Efficiency r (eq. 2) and MAP (eq. 3)** ([`efficiency`]) against truth when the node
//!    has `truth = "PATH"` (a `ground_truth.json`; [`ScanTruth`]): a match is correct when its
//!    unrefined displacement is within 1 px of the true offset; r = correct / two-way
//!    matches; AP = mean over the correct matches of the precision at their rank (ranked by
//!    score); MAP = mean AP over pairs. run.json carries `pairs[].features` (counts, inliers,
//!    rotation, r, AP) and `global.features` (mean r, MAP). `surfstream stitch` passes the
//!    `ground_truth.json` beside `scan.toml` automatically; a graph with the simulated stage
//!    can set `matcher.truth = "truth.json"` (relative paths are resolved against the output
//!    directory, where the stage writes it before the scan starts; the file is read at end
//!    of scan).
//!
//! Measured pair by pair on the anchors' 72 sets (576 pairs; `examples/features_scan.rs`,
//! raw pair estimates, before the global solve): see the README's registration section.
//!
//! # Global solve: [`solve_positions`], [`solve_planes`]
//!
//! At end of scan [`ScanRegistration::finish`] places every tile from all accepted pair offsets
//! at once (weighted least squares, stage positions as a weak prior, inconsistent links removed
//! one by one, ambiguous pairs resolved by consistency with the rest of the scan; a tile left
//! without a kept link is placed by the stage and flagged) and levels every tile by one
//! least-squares fit of piston and tilt over all overlaps of the scan, the first tile held as
//! gauge. See [`global`] for the model; `tests/global.rs` checks both against a synthetic
//! scan's truth.
//!
//! # Z alignment while streaming: [`estimate_plane`]
//!
//! The piston and tilt of a tile relative to already-levelled neighbours: one least-squares
//! plane (3 x 3 normal equations, Cholesky) of `b - (neighbour - its correction)` over all
//! overlapping valid pixels of all neighbours, the neighbours sampled bilinearly at b's pixel
//! positions (a sample needs its contributing corners valid). See [`PlaneCorrection`] for the
//! convention and [`estimate_plane_report`] for the thin-strip fallback (piston and the tilt
//! along the strip when the samples spread less than 2 px across it).
//!
//! # Measured accuracy and speed
//!
//! Synthetic surface (tests/support): band-limited self-affine roughness, rms 1 um, sampled at
//! exact sub-pixel offsets by the Fourier shift theorem; per-tile piston +-5 um and tilt
//! +-0.005 um/px, white noise, random dropouts plus three round holes (radius 5-30 px), 3 px
//! (sigma) stage error. Error = max over x and y of |measured - true| offset, 60 pairs per row
//! at 256 px and 12 at 1024 px (10, 20, 30 % overlap, horizontal and vertical neighbours),
//! `cargo run --release -p surfstream-matcher --example accuracy`:
//!
//! | tiles | surface (corr. length) | noise, dropouts | rms error | max error |
//! |---|---|---|---|---|
//! | 256 px | 40 px (smooth) | 0.05 um, 5 % | 0.032 px | 0.14 px (10 % overlap), 0.05 px (20-30 %) |
//! | 256 px | 40 px (smooth) | 0.1 um, 30 % | 0.033 px | 0.14 px (10 %), 0.05 px (20-30 %) |
//! | 256 px | 5 px (rough) | 0.05 um, 5 % | 0.010 px | 0.027 px |
//! | 1024 px | 40 px | 0.05 um, 5 % | 0.007 px | 0.010 px |
//! | 1024 px | 40 px | 0.1 um, 30 % | 0.007 px | 0.010 px |
//!
//! On the same pairs the second-pass phase-correlation fits measure: Gaussian 0.036 / 0.10 /
//! 0.012 / 0.004 / 0.039 px rms (rows as above), parabolic 0.03-0.11 px, Foroosh 0.2-0.4 px
//! (the windowed, Gaussian-weighted peak is not the sinc that Foroosh's formula assumes).
//!
//! Speed, `examples/bench_pair.rs`, 1024 x 1024 tiles, one rayon thread, reused correlator,
//! CPU time per pair on a shared 2-core machine: 4-7 ms at 10 %, 9-13 ms at 20 % and 15-19 ms
//! at 30 % overlap (the wide-strip layouts, horizontal neighbours, are the slower ones). The
//! 2-thread pool was no faster there. [`register_pair`] builds the plans and buffers per call:
//! under 1 ms more.
//!
//! # Not for
//!
//! Blending the tiles or writing the panorama (surfstream-fusion): this crate measures where
//! each tile sits and how to level it, and says so in its registrations and report.

pub mod detector;
pub mod efficiency;
pub mod feature_match;
mod fft2;
pub mod global;
pub mod harris;
mod ncc;
pub mod pair_log;
pub mod params;
pub mod plane;
pub mod raster;
pub mod refine;
pub mod register;
pub mod scan;
pub mod sift;

pub use detector::{DetectorImage, DetectorParams, Rect};
pub use efficiency::{match_quality, MatchQuality, RankedMatch};
pub use feature_match::{
    register_pair_features, FeatureMatch, FeatureMethod, FeatureParams, FeatureRegistration,
};
pub use global::{
    solve_planes, solve_planes_in, solve_positions, solve_positions_anisotropic,
    solve_scan_positions, AnisotropicLink, GlobalSolution, Link, LinkOutcome, PlaneSolution,
    PlaneTiles, SolveError, SolveParams,
};
pub use harris::{harris_corners, Corner, HarrisParams};
pub use params::{MatcherConfig, RegistrationMethod};
pub use plane::{
    estimate_plane, estimate_plane_report, fit_plane, PlaneCorrection, PlaneError, PlaneEstimate,
    PlaneModel,
};
pub use raster::InputError;
pub use register::{
    register_pair, Candidate, DirectionalOffset, PairRegistration, PhaseCorrelator, PhaseParams,
    Rejection, SubPixel, Window,
};
pub use scan::{ScanError, ScanParams, ScanRegistration, ScanTile};
pub use sift::{sift_keypoints, Keypoint, SiftParams};
/// The truth file reader lives with the other file formats; re-exported for the examples.
pub use surfstream_io::truth::{ScanTruth, TruthError};
#[cfg(feature = "node")]
pub mod node;
#[cfg(feature = "node")]
pub mod ports;
