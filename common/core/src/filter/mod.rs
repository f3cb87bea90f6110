//! ISO 16610 areal filters and form removal, shared by the wavelet node (as separation
//! methods) and the CLI verbs.
//!
//! * [`gaussian`]: the ISO 16610-61 areal Gaussian filter (S-filter with `lambda_s`, L-filter
//!   with `lambda_c`), separable, by FFT, with end effects and missing points handled by
//!   normalising the weights over the measured points in the field.
//! * [`robust`]: the ISO 16610-71 robust Gaussian regression filter (zeroth order, Tukey
//!   biweight, iteratively reweighted).
//! * [`form`]: least-squares plane and polynomial form, and the S-F / S-L chain
//!   ([`form::scale_limited`]).
//!
//! Every function takes a row-major `f32` raster (µm, NaN = not measured) and its [`Grid`],
//! returns new rasters, and reports bad arguments as [`FilterError`] (never a panic).

pub mod form;
pub mod gaussian;
pub mod robust;

use thiserror::Error;

pub use form::{fit_polynomial, scale_limited, LFilter, PolynomialForm, ScaleLimited, MAX_ORDER};
pub use gaussian::{
    gaussian_filter, normalised_gaussian, sigma_px, weighting_function, GaussianFilter,
    WeightedMean, ALPHA, MIN_SUPPORT,
};
pub use robust::{robust_gaussian_filter, RobustFit, RobustSettings, TUKEY_C};

/// The sampling of a raster: its size and pitch.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Grid {
    pub rows: usize,
    pub cols: usize,
    /// Spacing along columns (x), µm.
    pub pitch_x_um: f64,
    /// Spacing along rows (y), µm.
    pub pitch_y_um: f64,
}

impl Grid {
    /// A `rows x cols` grid with the same pitch along x and y.
    pub fn square(rows: usize, cols: usize, pitch_um: f64) -> Grid {
        Grid {
            rows,
            cols,
            pitch_x_um: pitch_um,
            pitch_y_um: pitch_um,
        }
    }

    /// Checks that `len` values fill this grid and that the pitch is a positive number.
    pub fn check(&self, len: usize) -> Result<(), FilterError> {
        if self.rows == 0 || self.cols == 0 {
            return Err(FilterError::Empty {
                rows: self.rows,
                cols: self.cols,
            });
        }
        if self.rows.checked_mul(self.cols) != Some(len) {
            return Err(FilterError::SizeMismatch {
                len,
                rows: self.rows,
                cols: self.cols,
            });
        }
        for (name, p) in [
            ("pitch_x_um", self.pitch_x_um),
            ("pitch_y_um", self.pitch_y_um),
        ] {
            if !(p.is_finite() && p > 0.0) {
                return Err(FilterError::BadValue {
                    name,
                    value: p,
                    expected: "a positive pitch in µm",
                });
            }
        }
        Ok(())
    }
}

/// What the filters refuse.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum FilterError {
    #[error("empty raster: {rows} x {cols}")]
    Empty { rows: usize, cols: usize },
    #[error("buffer holds {len} values but the raster is {rows} x {cols}")]
    SizeMismatch {
        len: usize,
        rows: usize,
        cols: usize,
    },
    #[error("{name} = {value}: expected {expected}")]
    BadValue {
        name: &'static str,
        value: f64,
        expected: &'static str,
    },
    #[error("the height map has no finite value")]
    AllNan,
    #[error("{needed} measured points are needed to fit a polynomial of order {order}, the map has {have}")]
    TooFewPoints {
        order: usize,
        needed: usize,
        have: usize,
    },
}
