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
//! Every function takes a row-major `f32` raster (µm, NaN = not measured) and its
//! [`Sampling`](crate::Sampling),
//! returns new rasters, and reports bad arguments as [`FilterError`] (never a panic).

pub mod form;
pub mod gaussian;
pub mod robust;

use thiserror::Error;

use crate::{ParamError, ShapeError};

pub use form::{fit_polynomial, scale_limited, LFilter, PolynomialForm, ScaleLimited, MAX_ORDER};
pub use gaussian::{
    gaussian_filter, normalised_gaussian, sigma_px, weighting_function, GaussianFilter,
    WeightedMean, ALPHA, MIN_SUPPORT,
};
pub use robust::{robust_gaussian_filter, RobustFit, RobustSettings, TUKEY_C};

/// What the filters refuse.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum FilterError {
    #[error(transparent)]
    Shape(#[from] ShapeError),
    #[error(transparent)]
    Param(#[from] ParamError),
    #[error("the height map has no finite value")]
    AllNan,
    #[error("{needed} measured points are needed to fit a polynomial of order {order}, the map has {have}")]
    TooFewPoints {
        order: usize,
        needed: usize,
        have: usize,
    },
}
