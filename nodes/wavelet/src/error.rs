//! The crate's error type: every bad size or argument is reported, never a panic.

use thiserror::Error;

/// What can go wrong in this crate. All variants come from the caller's arguments (sizes,
/// levels, coefficient shapes, all-NaN maps); the algorithms themselves do not fail.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum WaveletError {
    /// A raster has a zero dimension.
    #[error("empty raster: {rows} x {cols}")]
    Empty { rows: usize, cols: usize },

    /// The buffer length does not equal `rows * cols` (or `rows * cols` overflows).
    #[error("buffer holds {len} values but the raster is {rows} x {cols}")]
    SizeMismatch {
        len: usize,
        rows: usize,
        cols: usize,
    },

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
    if rows == 0 || cols == 0 {
        return Err(WaveletError::Empty { rows, cols });
    }
    match rows.checked_mul(cols) {
        Some(n) if n == len => Ok(()),
        _ => Err(WaveletError::SizeMismatch { len, rows, cols }),
    }
}
