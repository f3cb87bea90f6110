//! The crate's error type.

use thiserror::Error;

/// Everything that can go wrong in the simulated stage: invalid parameters and specimens that
/// do not fit the scan. Each message names the parameter (or the quantity), the value that was
/// given and what was expected.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum ReplayError {
    /// A parameter is out of its valid range.
    #[error("invalid {section} parameter `{field}` = {value}: expected {expected}")]
    InvalidParam {
        /// `"specimen"` or `"stage"`.
        section: &'static str,
        /// The parameter's name as written in a graph file.
        field: &'static str,
        /// The value that was given, formatted.
        value: String,
        /// What would have been accepted.
        expected: String,
    },
    /// The raster would be too large to synthesise or hold.
    #[error("{what} of {height_px} x {width_px} px (rows x cols) is too large: expected {limit}")]
    TooLarge {
        /// What was too large (e.g. "specimen for a 40 x 40 scan").
        what: String,
        /// Width in pixels.
        width_px: usize,
        /// Height in pixels.
        height_px: usize,
        /// The limit that was exceeded, in words.
        limit: String,
    },
    /// A height buffer's length does not match its stated shape.
    #[error("height buffer: {0}")]
    Shape(#[from] surfstream_core::raster::ShapeError),
    /// The specimen does not match the scan plan (too small, or a different pixel pitch).
    #[error("specimen does not fit the scan plan: {0}")]
    SpecimenMismatch(String),
}

/// `Result` with [`ReplayError`].
pub type Result<T> = std::result::Result<T, ReplayError>;

/// Builds an [`ReplayError::InvalidParam`].
pub(crate) fn invalid(
    section: &'static str,
    field: &'static str,
    value: impl std::fmt::Display,
    expected: impl Into<String>,
) -> ReplayError {
    ReplayError::InvalidParam {
        section,
        field,
        value: value.to_string(),
        expected: expected.into(),
    }
}
