//! surfstream-matcher: registration of overlapping height-map tiles.
//!
//! An optical profiler scans a part as a serpentine of overlapping tiles; each tile comes with
//! a nominal stage position (a few pixels off), its own piston and tilt, noise and NaN
//! dropouts. This crate measures where a tile really sits relative to a placed neighbour and
//! how to bring its heights to the neighbours' level. Plain functions over borrowed rasters:
//! no IPC, no files, no globals.
//!
//! Conventions (DESIGN.md §2): heights are f32 micrometres, row-major, rows grow with y,
//! columns with x, NaN = not measured. Offsets are `[x, y]` in pixels: the position of tile
//! b's pixel (0, 0) minus tile a's pixel (0, 0).
//!
//! # Pairwise registration ([`register_pair`], [`PhaseCorrelator`])
//!
//! 1. The nominal overlap rectangle (from the rounded nominal offset) is cropped from both
//!    tiles. Each crop is levelled by its least-squares plane over valid pixels (so piston and
//!    tilt do not matter), NaN is set to 0 after levelling, and a Tukey window (alpha 0.5)
//!    suppresses the edges. Both crops are zero-padded to a 2-3-5-smooth size and transformed
//!    together in one complex FFT (a in the real part, b in the imaginary part).
//! 2. The normalised cross-power spectrum is weighted by a Gaussian that blurs the
//!    correlation peak by `peak_sigma_px` (1 px): it damps the noise-dominated high
//!    frequencies (white noise, dropouts) and gives the peak a Gaussian shape.
//! 3. The 5 strongest local maxima of the correlation surface (at least 3 px apart, shifts up
//!    to half the crop) are each verified by the NCC of the levelled heights over the actual
//!    overlap at that integer shift (valid pixel pairs only, full tiles beyond the crop). The
//!    best NCC wins.
//! 4. Sub-pixel refinement: a 3-point Gaussian fit along x and y on the correlation surface
//!    at the winning peak. With the Gaussian spectral weighting this measured best of the
//!    estimators offered ([`SubPixel`]): see the numbers below.
//! 5. The answer is refused ([`Rejection`]) rather than risked: too small an overlap, too few
//!    valid pixels, a featureless overlap, NCC below `min_ncc` (0.5), an ambiguous match (a
//!    rival peak at least 3 px away whose NCC is within 0.1 of the best and whose correlation
//!    peak is at least half the best's, as on periodic textures), or a shift from nominal
//!    beyond `max_shift_px` (30 px) or 45 % of the overlap extent along that axis.
//!
//! # Z alignment ([`estimate_plane`])
//!
//! The piston and tilt of a tile relative to already-levelled neighbours: one least-squares
//! plane of `b - (neighbour - its correction)` over all overlapping valid pixels of all
//! neighbours, the neighbours sampled bilinearly at b's pixel positions. See
//! [`PlaneCorrection`] for the convention and [`estimate_plane_report`] for the thin-strip
//! fallback.
//!
//! # Accuracy and speed
//!
//! Measured on the synthetic tests (band-limited self-affine surface, rms 1 um, exact
//! Fourier sub-pixel shifts, piston/tilt, white noise, NaN dropouts); the numbers are in the
//! integration tests and `examples/bench_pair.rs`.

mod fft2;
mod ncc;
pub mod plane;
pub mod raster;
pub mod register;

pub use plane::{
    estimate_plane, estimate_plane_report, fit_plane, PlaneCorrection, PlaneError, PlaneEstimate,
    PlaneModel,
};
pub use raster::{InputError, RasterRef};
pub use register::{
    register_pair, Candidate, PairRegistration, PhaseCorrelator, PhaseParams, Rejection, SubPixel,
    Window,
};
pub mod node;
