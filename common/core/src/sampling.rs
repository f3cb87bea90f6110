//! Where a raster's samples lie: its [`Shape`], its [`Pitch`] along x and y and the scan
//! position of pixel (0, 0) (DESIGN §2: x along columns, y along rows, µm). A [`Pitch`] is
//! checked once, when it is made ([`Pitch::new`], the one finite-and-positive check), so a
//! function holding one, or a [`Sampling`] built on one, never re-checks it.
//!
//! [`Sampling`] travels with samples that carry no shape of their own (a slice and its rows x
//! cols); a bare [`Pitch`] travels where the shape is already held elsewhere (a
//! [`crate::Raster`] or [`crate::RasterView`] beside it, a panorama that grows), so no two
//! copies of a shape can disagree.
//!
//! [`ParamError`] is the one "a number is out of its domain" error: the field, what was found
//! and what was expected. The crates' errors wrap it (and [`crate::ShapeError`]) instead of
//! each spelling their own.

use serde::{Deserialize, Serialize};

use crate::raster::Shape;

/// A parameter outside its domain: `{field} = {found}: expected {expected}`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{field} = {found}: expected {expected}")]
pub struct ParamError {
    /// The parameter's name as the user wrote it (a graph key, a struct field).
    pub field: &'static str,
    /// The value given, formatted.
    pub found: String,
    /// What would have been accepted.
    pub expected: &'static str,
}

impl ParamError {
    pub fn new(field: &'static str, found: impl std::fmt::Display, expected: &'static str) -> Self {
        Self {
            field,
            found: found.to_string(),
            expected,
        }
    }
}

/// What a [`Pitch`] must be.
pub const PITCH_EXPECTED: &str = "a finite positive pitch in µm";

/// The spacing of a raster's columns (`x_um`, along x) and rows (`y_um`, along y), each finite
/// and > 0: made only by [`Pitch::new`], which checks.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pitch {
    x_um: f64,
    y_um: f64,
}

impl Pitch {
    /// The one check of a pitch: each of `pitch_x_um`, `pitch_y_um` finite and > 0; the error
    /// names the first that is not.
    pub fn new(pitch_x_um: f64, pitch_y_um: f64) -> Result<Self, ParamError> {
        for (field, p) in [("pitch_x_um", pitch_x_um), ("pitch_y_um", pitch_y_um)] {
            if !(p.is_finite() && p > 0.0) {
                return Err(ParamError::new(field, p, PITCH_EXPECTED));
            }
        }
        Ok(Self {
            x_um: pitch_x_um,
            y_um: pitch_y_um,
        })
    }

    /// The same pitch along x and y.
    pub fn square(pitch_um: f64) -> Result<Self, ParamError> {
        Self::new(pitch_um, pitch_um)
    }

    /// Spacing of columns (along x), µm.
    pub fn x_um(&self) -> f64 {
        self.x_um
    }
    /// Spacing of rows (along y), µm.
    pub fn y_um(&self) -> f64 {
        self.y_um
    }
    /// `[x_um, y_um]`.
    pub fn um(&self) -> [f64; 2] {
        [self.x_um, self.y_um]
    }
    /// The smaller of the two spacings, µm.
    pub fn min_um(&self) -> f64 {
        self.x_um.min(self.y_um)
    }
    /// The area one sample stands for, µm².
    pub fn cell_area_um2(&self) -> f64 {
        self.x_um * self.y_um
    }

    /// The pitch of every `factor`-th sample (a decimated or block-pooled raster), checked
    /// again: a huge pitch times a huge factor may overflow.
    pub fn times(self, factor: usize) -> Result<Self, ParamError> {
        Self::new(self.x_um * factor as f64, self.y_um * factor as f64)
    }
}

/// The sampling of a raster: `shape` (rows along y, cols along x), the spacing of columns
/// (`pitch_x_um`) and of rows (`pitch_y_um`), both finite and > 0, and the scan position of
/// pixel (0, 0) (`origin_x_um`, `origin_y_um`, finite; 0 unless given).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "SamplingFields", into = "SamplingFields")]
pub struct Sampling {
    shape: Shape,
    pitch: Pitch,
    origin_x_um: f64,
    origin_y_um: f64,
}

/// The serialized form (flat, as it always was), checked by [`Sampling::new`] on the way in.
#[derive(Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct SamplingFields {
    shape: Shape,
    pitch_x_um: f64,
    pitch_y_um: f64,
    #[serde(default)]
    origin_x_um: f64,
    #[serde(default)]
    origin_y_um: f64,
}

impl From<Sampling> for SamplingFields {
    fn from(s: Sampling) -> Self {
        Self {
            shape: s.shape,
            pitch_x_um: s.pitch.x_um,
            pitch_y_um: s.pitch.y_um,
            origin_x_um: s.origin_x_um,
            origin_y_um: s.origin_y_um,
        }
    }
}

impl TryFrom<SamplingFields> for Sampling {
    type Error = ParamError;
    fn try_from(f: SamplingFields) -> Result<Self, ParamError> {
        Sampling::new(f.shape, f.pitch_x_um, f.pitch_y_um)?
            .with_origin(f.origin_x_um, f.origin_y_um)
    }
}

fn finite(field: &'static str, v: f64, expected: &'static str) -> Result<f64, ParamError> {
    if v.is_finite() {
        Ok(v)
    } else {
        Err(ParamError::new(field, v, expected))
    }
}

impl Sampling {
    /// `shape` at the pitch checked by [`Pitch::new`] (the error names the axis). The origin
    /// is (0, 0).
    pub fn new(shape: Shape, pitch_x_um: f64, pitch_y_um: f64) -> Result<Self, ParamError> {
        Ok(Self::of(shape, Pitch::new(pitch_x_um, pitch_y_um)?))
    }

    /// `shape` at an already checked pitch; the origin is (0, 0).
    pub fn of(shape: Shape, pitch: Pitch) -> Self {
        Self {
            shape,
            pitch,
            origin_x_um: 0.0,
            origin_y_um: 0.0,
        }
    }

    /// The same pitch along x and y.
    pub fn square(shape: Shape, pitch_um: f64) -> Result<Self, ParamError> {
        Self::new(shape, pitch_um, pitch_um)
    }

    /// Moves pixel (0, 0) to (`origin_x_um`, `origin_y_um`), each finite.
    pub fn with_origin(self, origin_x_um: f64, origin_y_um: f64) -> Result<Self, ParamError> {
        const EXPECTED: &str = "a finite scan position in µm";
        Ok(Self {
            origin_x_um: finite("origin_x_um", origin_x_um, EXPECTED)?,
            origin_y_um: finite("origin_y_um", origin_y_um, EXPECTED)?,
            ..self
        })
    }

    /// The same pitch and origin over another shape (a window, a pooled or padded raster).
    pub fn with_shape(self, shape: Shape) -> Self {
        Self { shape, ..self }
    }

    pub fn shape(&self) -> Shape {
        self.shape
    }
    pub fn rows(&self) -> usize {
        self.shape.rows
    }
    pub fn cols(&self) -> usize {
        self.shape.cols
    }
    pub fn pitch(&self) -> Pitch {
        self.pitch
    }
    /// Spacing of columns (along x), µm.
    pub fn pitch_x_um(&self) -> f64 {
        self.pitch.x_um
    }
    /// Spacing of rows (along y), µm.
    pub fn pitch_y_um(&self) -> f64 {
        self.pitch.y_um
    }
    /// `[pitch_x_um, pitch_y_um]`.
    pub fn pitch_um(&self) -> [f64; 2] {
        self.pitch.um()
    }
    pub fn origin_x_um(&self) -> f64 {
        self.origin_x_um
    }
    pub fn origin_y_um(&self) -> f64 {
        self.origin_y_um
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_bad_pitch_is_named() {
        let s = Shape::new(2, 3);
        let e = Sampling::new(s, 0.5, -1.0).unwrap_err();
        assert_eq!(e.field, "pitch_y_um");
        assert_eq!(
            e.to_string(),
            "pitch_y_um = -1: expected a finite positive pitch in µm"
        );
        assert_eq!(
            Sampling::new(s, f64::NAN, 1.0).unwrap_err().field,
            "pitch_x_um"
        );
        assert_eq!(Sampling::square(s, 0.0).unwrap_err().field, "pitch_x_um");
        let e = Sampling::square(s, 1.0)
            .unwrap()
            .with_origin(1.0, f64::INFINITY)
            .unwrap_err();
        assert_eq!(e.field, "origin_y_um");
    }

    #[test]
    fn a_pitch_is_checked_once_and_scaled_with_a_check() {
        let p = Pitch::new(0.5, 0.25).unwrap();
        assert_eq!((p.x_um(), p.y_um(), p.um()), (0.5, 0.25, [0.5, 0.25]));
        assert_eq!((p.min_um(), p.cell_area_um2()), (0.25, 0.125));
        assert_eq!(p.times(4).unwrap().um(), [2.0, 1.0]);
        assert_eq!(Pitch::new(1.0, 0.0).unwrap_err().field, "pitch_y_um");
        assert_eq!(Pitch::square(f64::NAN).unwrap_err().field, "pitch_x_um");
        let huge = Pitch::square(f64::MAX).unwrap();
        assert_eq!(huge.times(2).unwrap_err().field, "pitch_x_um");
        let s = Sampling::of(Shape::new(2, 3), p);
        assert_eq!((s.pitch(), s.pitch_um()), (p, [0.5, 0.25]));
    }

    #[test]
    fn a_frame_header_carries_a_sampling_both_ways() {
        let s = Sampling::new(Shape::new(3, 7), 0.5, 0.75)
            .unwrap()
            .with_origin(-2.0, 4.5)
            .unwrap();
        let h = crate::FrameHeader::at(&s);
        assert_eq!((h.width, h.height), (7, 3));
        assert_eq!((h.pitch_x_um, h.pitch_y_um), (0.5, 0.75));
        assert_eq!((h.origin_x_um, h.origin_y_um), (-2.0, 4.5));
        assert_eq!(h.sampling().unwrap(), s);
        assert_eq!(h.pitch().unwrap(), s.pitch());
        let marker = crate::FrameHeader::end_of_scan(1, 2, 3, 4);
        assert_eq!(marker.pitch().unwrap_err().field, "pitch_x_um");
    }

    #[test]
    fn serde_round_trips_and_checks() {
        let s = Sampling::new(Shape::new(4, 5), 0.8148, 0.9)
            .unwrap()
            .with_origin(-3.0, 2.5)
            .unwrap();
        let json = serde_json::to_string(&s).unwrap();
        // The flat form it always had: the Pitch inside is not a level of its own.
        assert_eq!(
            json,
            r#"{"shape":{"rows":4,"cols":5},"pitch_x_um":0.8148,"pitch_y_um":0.9,"origin_x_um":-3.0,"origin_y_um":2.5}"#
        );
        assert_eq!(serde_json::from_str::<Sampling>(&json).unwrap(), s);
        let no_origin: Sampling = serde_json::from_str(
            r#"{"shape": {"rows": 1, "cols": 2}, "pitch_x_um": 1, "pitch_y_um": 2}"#,
        )
        .unwrap();
        assert_eq!(
            (no_origin.origin_x_um(), no_origin.origin_y_um()),
            (0.0, 0.0)
        );
        let bad = serde_json::from_str::<Sampling>(
            r#"{"shape": {"rows": 1, "cols": 2}, "pitch_x_um": 0, "pitch_y_um": 2}"#,
        )
        .unwrap_err();
        assert!(bad.to_string().contains("pitch_x_um = 0"), "{bad}");
    }
}
