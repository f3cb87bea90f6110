//! Borrowed height rasters and input validation.

use serde::{Deserialize, Serialize};
use surfstream_core::raster::ShapeError;
use thiserror::Error;

/// A borrowed height map: `width * height` heights in micrometres, row-major, rows grow with y,
/// columns with x. NaN marks a pixel that was not measured.
#[derive(Debug, Clone, Copy)]
pub struct RasterRef<'a> {
    pub heights: &'a [f32],
    pub width: usize,
    pub height: usize,
}

/// Why an input was refused. Every public entry point validates its rasters and parameters
/// first and reports one of these instead of panicking.
#[derive(Debug, Clone, PartialEq, Error, Serialize, Deserialize)]
pub enum InputError {
    #[error("raster has zero size ({width} x {height} px)")]
    ZeroSize { width: usize, height: usize },
    #[error("raster of {width} x {height} px needs {expected} heights, got {actual}")]
    SliceLength {
        width: usize,
        height: usize,
        expected: usize,
        actual: usize,
    },
    #[error("offset ({x_px}, {y_px}) px is not finite")]
    NonFiniteOffset { x_px: f64, y_px: f64 },
    #[error("offset ({x_px}, {y_px}) px is too large to be a tile offset")]
    OffsetOutOfRange { x_px: f64, y_px: f64 },
    #[error("invalid parameter {name}: {reason}")]
    InvalidParameter { name: String, reason: String },
}

impl From<ShapeError> for InputError {
    fn from(e: ShapeError) -> Self {
        match e {
            ShapeError::Empty(shape) => InputError::ZeroSize {
                width: shape.cols,
                height: shape.rows,
            },
            ShapeError::Length {
                shape,
                expected,
                found,
            } => InputError::SliceLength {
                width: shape.cols,
                height: shape.rows,
                expected,
                actual: found,
            },
        }
    }
}

impl<'a> RasterRef<'a> {
    /// A validated raster: `heights.len() == width * height`, both sizes non-zero.
    pub fn new(heights: &'a [f32], width: usize, height: usize) -> Result<Self, InputError> {
        let r = RasterRef {
            heights,
            width,
            height,
        };
        r.validate()?;
        Ok(r)
    }

    /// Checks the size invariants of a raster built as a struct literal.
    pub fn validate(&self) -> Result<(), InputError> {
        if self.width == 0 || self.height == 0 {
            return Err(InputError::ZeroSize {
                width: self.width,
                height: self.height,
            });
        }
        let expected = self.width.checked_mul(self.height);
        if expected != Some(self.heights.len()) {
            return Err(InputError::SliceLength {
                width: self.width,
                height: self.height,
                expected: expected.unwrap_or(usize::MAX),
                actual: self.heights.len(),
            });
        }
        Ok(())
    }

    /// One row of heights. The caller guarantees `row < height` and a validated raster.
    #[inline]
    pub(crate) fn row(&self, row: usize) -> &'a [f32] {
        &self.heights[row * self.width..(row + 1) * self.width]
    }
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
