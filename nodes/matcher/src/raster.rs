//! Input validation: why an input was refused.
//!
//! Tiles are borrowed as `surfstream_core::raster::RasterView<f32>` (heights in micrometres,
//! `rows x cols`, row-major, NaN = not measured), whose constructor already refuses a shape
//! that does not match its samples; [`InputError`] wraps that refusal beside the matcher's own.

use serde::{Deserialize, Serialize};
use surfstream_core::raster::ShapeError;
use thiserror::Error;

/// Why an input was refused. Every public entry point validates its offsets and parameters
/// first and reports one of these instead of panicking; a raster's shape was checked when its
/// `RasterView` was built, and the `ShapeError` from there is wrapped as it is.
#[derive(Debug, Clone, PartialEq, Error, Serialize, Deserialize)]
pub enum InputError {
    #[error("raster: {0}")]
    Shape(#[from] ShapeError),
    #[error("offset ({x_px}, {y_px}) px is not finite")]
    NonFiniteOffset { x_px: f64, y_px: f64 },
    #[error("offset ({x_px}, {y_px}) px is too large to be a tile offset")]
    OffsetOutOfRange { x_px: f64, y_px: f64 },
    #[error("invalid parameter {name}: {reason}")]
    InvalidParameter { name: String, reason: String },
}

/// Checks that an offset in pixels is finite and small enough that integer arithmetic on it
/// cannot overflow.
pub(crate) fn validate_offset(offset_px: [f64; 2]) -> Result<(), InputError> {
    let [x_px, y_px] = offset_px;
    if !x_px.is_finite() || !y_px.is_finite() {
        return Err(InputError::NonFiniteOffset { x_px, y_px });
    }
    const LIMIT_PX: f64 = 1e12;
    if x_px.abs() > LIMIT_PX || y_px.abs() > LIMIT_PX {
        return Err(InputError::OffsetOutOfRange { x_px, y_px });
    }
    Ok(())
}
