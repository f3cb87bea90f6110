//! What the panorama is given: the blend parameters, a tile with its final position and its
//! plane correction, and the checks that turn bad input into a [`FusionError`] naming the field.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use surfstream_core::raster::RasterView;
use surfstream_core::ParamError;
pub use surfstream_core::PlaneCorrection;

use crate::error::{FusionError, Result};
use crate::resample::MAX_RAMP_PX;

/// Parameters of the "gradual in-and-out" blend (paper eq. 5), generalised to 2-D.
///
/// Every resampled tile pixel gets the weight `wx * wy`, where
/// `wx = min((d + 0.5) / ramp_x_px, 1)` and `d` is the distance in pixels from the pixel to the
/// nearer left/right border of its tile (likewise `wy` with top/bottom and `ramp_y_px`). The
/// `+ 0.5` keeps every weight above zero inside the tile, so a pixel measured by any tile is
/// valid in the panorama. With the ramp equal to the overlap width, the two weights across a
/// straight seam add up to 1 and the seam fades linearly from one tile to the other.
///
/// A ramp of at most 0.5 px gives every pixel the weight 1: the plain average (paper eq. 4).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct BlendParams {
    /// Nominal overlap between horizontal neighbours, in pixels (e.g. 0.10 * 1024).
    pub overlap_x_px: f64,
    /// Nominal overlap between vertical neighbours, in pixels.
    pub overlap_y_px: f64,
    /// Length of the horizontal weight ramp in pixels; `None` = `overlap_x_px`.
    #[serde(default)]
    pub ramp_x_px: Option<f64>,
    /// Length of the vertical weight ramp in pixels; `None` = `overlap_y_px`.
    #[serde(default)]
    pub ramp_y_px: Option<f64>,
}

impl BlendParams {
    /// Ramps as long as the nominal overlaps (the paper's choice).
    pub fn from_overlap_px(overlap_x_px: f64, overlap_y_px: f64) -> Self {
        Self {
            overlap_x_px,
            overlap_y_px,
            ramp_x_px: None,
            ramp_y_px: None,
        }
    }

    /// Ramps from a tile size and an overlap fraction (e.g. 1024 x 1024 px at 0.10).
    pub fn from_overlap_fraction(
        tile_width_px: usize,
        tile_height_px: usize,
        overlap: f64,
    ) -> Self {
        Self::from_overlap_px(
            tile_width_px as f64 * overlap,
            tile_height_px as f64 * overlap,
        )
    }

    /// Plain average of all tiles covering a pixel (paper eq. 4): every weight is 1.
    pub fn average() -> Self {
        Self::from_overlap_px(0.0, 0.0)
    }

    /// Override the ramp lengths (pixels) independently of the nominal overlap.
    pub fn with_ramp_px(mut self, ramp_x_px: f64, ramp_y_px: f64) -> Self {
        self.ramp_x_px = Some(ramp_x_px);
        self.ramp_y_px = Some(ramp_y_px);
        self
    }

    /// The horizontal ramp actually used, in pixels.
    pub fn effective_ramp_x_px(&self) -> f64 {
        self.ramp_x_px.unwrap_or(self.overlap_x_px)
    }

    /// The vertical ramp actually used, in pixels.
    pub fn effective_ramp_y_px(&self) -> f64 {
        self.ramp_y_px.unwrap_or(self.overlap_y_px)
    }

    /// Refuse NaN, negative or absurdly long (> 1e6 px) lengths.
    pub fn validate(&self) -> Result<()> {
        const EXPECTED: &str = "a number of pixels in [0, 1e6]";
        let fields = [
            ("overlap_x_px", Some(self.overlap_x_px)),
            ("overlap_y_px", Some(self.overlap_y_px)),
            ("ramp_x_px", self.ramp_x_px),
            ("ramp_y_px", self.ramp_y_px),
        ];
        for (field, value) in fields {
            if let Some(value) = value {
                // Also refuses NaN: every comparison with NaN is false.
                if !(0.0..=MAX_RAMP_PX).contains(&value) {
                    return Err(FusionError::from(ParamError::new(field, value, EXPECTED)));
                }
            }
        }
        Ok(())
    }
}

/// One tile with its final position: the input of [`crate::Panorama::place`].
///
/// The tile's pitch is the panorama's pitch: the instrument does not change objective between
/// fields of one scan.
#[derive(Debug, Clone, Copy)]
pub struct TileInput<'a> {
    /// Acquisition index; [`crate::render`] places tiles in increasing index order.
    pub index: u32,
    /// Heights in um relative to `z_offset_um`, rows along y; NaN = not measured.
    pub heights: RasterView<'a, f32>,
    /// Scan position (um) of the centre of pixel (0, 0) along x (columns). Need not be a
    /// multiple of the pitch.
    pub x_um: f64,
    /// Scan position (um) of the centre of pixel (0, 0) along y (rows).
    pub y_um: f64,
    /// Plane to subtract from the raw heights.
    pub plane: PlaneCorrection,
    /// The heights are relative to this absolute height, um.
    pub z_offset_um: f64,
}

impl TileInput<'_> {
    /// Check the finiteness of every number and of the payload (NaN allowed, +/-inf not); the
    /// size is right by construction of the raster view.
    pub fn validate(&self) -> Result<()> {
        let index = self.index;
        let numbers = [
            ("x_um", self.x_um),
            ("y_um", self.y_um),
            ("z_offset_um", self.z_offset_um),
            ("plane.piston_um", self.plane.piston_um),
            ("plane.tilt_x_um_per_px", self.plane.tilt_x_um_per_px),
            ("plane.tilt_y_um_per_px", self.plane.tilt_y_um_per_px),
        ];
        for (field, value) in numbers {
            if !value.is_finite() {
                return Err(FusionError::NonFinite {
                    index,
                    field,
                    value,
                });
            }
        }
        if let Some(at) = first_infinite(self.heights.values()) {
            let cols = self.heights.cols();
            return Err(FusionError::InfiniteHeight {
                index,
                row: at / cols,
                col: at % cols,
                value: self.heights.values()[at],
            });
        }
        Ok(())
    }
}

/// Index of the first +/-infinite value. This runs on every tile before anything changes, so
/// it scans in parallel blocks with a branch-free (vectorisable) test per block and looks for
/// the exact position only in a block that has one.
fn first_infinite(values: &[f32]) -> Option<usize> {
    const BLOCK: usize = 16 * 1024;
    let block = values.par_chunks(BLOCK).position_first(|chunk| {
        chunk
            .iter()
            .fold(false, |any, v| any | (v.abs() == f32::INFINITY))
    })?;
    let start = block * BLOCK;
    let at = values[start..].iter().position(|v| v.is_infinite())?;
    Some(start + at)
}
