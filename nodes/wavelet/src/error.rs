//! The crate's error type: every bad size or argument is reported, never a panic.

use surfstream_core::raster::{Shape, ShapeError};
use thiserror::Error;

/// What can go wrong in this crate. All variants come from the caller's arguments (sizes,
/// levels, coefficient shapes, all-NaN maps); the algorithms themselves do not fail.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum WaveletError {
    /// A raster has a zero dimension, or its buffer does not hold `rows * cols` values.
    #[error(transparent)]
    Shape(#[from] ShapeError),

    /// The map is too small for even one useful decomposition level with this wavelet: its
    /// smaller side must be at least `2 * (filter_len - 1)` samples (`dwt_max_level >= 1`).
    #[error(
        "{rows} x {cols} map is too small for a level-1 {wavelet} decomposition \
         (the smaller side needs at least {min_side} samples)"
    )]
    TooSmall {
        rows: usize,
        cols: usize,
        wavelet: &'static str,
        min_side: usize,
    },

    /// Coefficient arrays handed to `waverec2` do not fit together.
    #[error("incompatible coefficient shapes: {0}")]
    CoeffShape(String),

    /// Every pixel of the map is NaN (or infinite): there is nothing to separate.
    #[error("the height map has no finite value")]
    AllNan,

    /// A decomposition level above [`crate::MAX_LEVEL`] was asked for.
    #[error("decomposition level {level} is above the supported maximum {max}")]
    LevelTooHigh { level: usize, max: usize },

    /// The pooling block size is zero.
    #[error("pooling block size must be at least 1")]
    ZeroBlock,
}

/// Result with [`WaveletError`].
pub type Result<T> = std::result::Result<T, WaveletError>;

/// Check that `len == rows * cols` and that neither dimension is zero.
pub(crate) fn check_raster(len: usize, rows: usize, cols: usize) -> Result<()> {
    Ok(Shape::new(rows, cols).check(len)?)
}
