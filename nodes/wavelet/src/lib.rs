//! surfstream-wavelet: the algorithms of the wavelet node, as plain functions over in-memory
//! row-major rasters (no IPC, no globals; files only for spills, below).
//!
//! * [`wavedec2`] / [`waverec2`]: multilevel 2-D discrete wavelet transform with PyWavelets'
//!   semantics (coefficient layout, lengths, border modes, odd-size trimming), for the
//!   orthogonal wavelets db1..db10, sym2..sym10, coif1..coif5 with PyWavelets' own filter
//!   values ([`Wavelet`]), in [`Mode::Symmetric`] or [`Mode::Periodization`]. f64 throughout;
//!   parity with PyWavelets 1.9.0 is tested to 1e-12 relative against stored golden files.
//! * [`separate_map`]: the separation of a whole map as the node's final pass and the
//!   `separate` verb run it (one function for both): streamed ([`separate_streamed`], band by
//!   band, rows to a [`SeparationSink`]) for a named wavelet at a fixed / default level, in
//!   memory ([`analyse`]) for the base by RMSE and the level by minimum energy, an ISO filter
//!   ([`filter_separation`]) otherwise; its summary is a typed [`MapSummary`].
//! * [`separate`]: datum / roughness separation of a height map in memory (f32, NaN = not
//!   measured): datum = approximation-only reconstruction at a level chosen by
//!   [`default_level`], roughness = heights - datum. The test oracle of the streamed pass.
//! * [`filter_separation`]: the same split by an ISO 16610 filter (Gaussian or robust
//!   Gaussian L-filter, `surfstream_core::filter`), the node's `method = "gaussian"` /
//!   `"robust-gaussian"`; [`equivalent_cutoff_um`]: the wavelet level's cutoff wavelength.
//! * [`pool`]: NaN-aware max / mean block pooling; [`pooling_bias`]: what it does to the mean,
//!   Sa, Sq and Sz.
//! * The paper's selections: [`energy_curve`] / [`level_by_min_energy`] (level, Fig. 13) and
//!   [`rmse_per_base`] (base, eq. 10: it ranks round-off, see the `select` module).
//!
//! Heavy loops run in parallel on rayon's global pool.
//!
//! ```
//! use surfstream_wavelet::{pool, separate, Mode, PoolOp, Wavelet};
//!
//! let (rows, cols) = (64, 80);
//! let heights: Vec<f32> = (0..rows * cols)
//!     .map(|i| 0.01 * (i % cols) as f32 + ((i / cols) as f32).sin())
//!     .collect();
//! let sym5 = Wavelet::by_name("sym5").expect("built-in wavelet");
//! let s = separate(&heights, rows, cols, &sym5, Mode::Symmetric, None)?;
//! // Level 8 by default, clamped to dwt_max_level(64, 10) = floor(log2(64 / 9)) = 2.
//! assert_eq!(s.level, 2);
//! let p = pool(&s.roughness, rows, cols, 4, PoolOp::Max)?;
//! assert_eq!((p.rows, p.cols), (16, 20));
//! # Ok::<(), surfstream_wavelet::WaveletError>(())
//! ```
//!
//! Not for: the ISO 16610 filters themselves (surfstream-core's `filter`; this crate runs them
//! as separation methods), meshing (surfstream-mesher) or judging the model against the
//! measurement (Table 6, surfstream-core's `deviation`). Files only where memory is bounded:
//! the streamed pass keeps levels larger than 8 MiB in spill files and hands its outputs row by
//! row to a [`SeparationSink`], and the live mirror spills chunks under a memory budget.

mod dwt;
mod error;
mod filters;
pub mod final_pass;
pub mod live;
pub mod method;
pub mod options;
mod pool;
mod select;
mod separate;
pub mod stream;
mod wavelet;

pub use dwt::{wavedec2, waverec2, Coeffs2, Details2, MAX_LEVEL};
pub use error::{Result, WaveletError};
pub use final_pass::{
    separate_map, FilterSummary, MapSummary, SeparatedMap, SeparationSink, WaveletSummary,
};
pub use live::{
    final_separation, final_separation_with, FinalRequest, FinalSeparation, FinalSummary,
    LivePatches, LiveSeparation,
};
pub use method::{
    equivalent_cutoff_um, filter_separation, level_lowered_warning, FilterSeparation,
    SeparationKind, SeparationMethod,
};
pub use options::{
    default_base, final_pass_streams, OptionError, SeparationSettings, WaveletConfig,
};
pub use pool::{pool, PoolOp, Pooled};
pub use select::{
    analyse, energy_curve, height_stats, level_by_min_energy, pooling_bias, rmse_per_base,
    Analysis, BaseChoice, BaseRmse, EnergyPoint, HeightStats, LevelChoice, PoolingBias,
    SeparationChoices,
};
pub use separate::{default_level, fill_invalid, separate, Separation, DEFAULT_LEVEL};
pub use stream::{energy_curve_streamed, separate_streamed, StreamError, StreamOptions};
pub use wavelet::{dwt_coeff_len, dwt_max_level, Mode, Wavelet};
#[cfg(feature = "node")]
pub mod node;
#[cfg(feature = "node")]
pub mod ports;
