//! The piston-and-tilt correction of a tile, shared by the matcher (which estimates it) and
//! the fusion (which applies it), so both read the one convention.

use serde::{Deserialize, Serialize};

use crate::raster::{Raster, RasterView, Shape};

/// The height correction of one tile: a piston plus a tilt about the tile centre.
///
/// `corrected(row, col) = raw(row, col) - plane(row, col)` with `plane(row, col) = piston_um +
/// tilt_x_um_per_px * (col - (cols-1)/2) + tilt_y_um_per_px * (row - (rows-1)/2)`, the same
/// convention as [`crate::TileRegistration`]. The plane is centred on the tile, so the piston is the plane's
/// height at the tile centre and does not change when the tilt does.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct PlaneCorrection {
    /// Height of the plane at the tile centre, um.
    pub piston_um: f64,
    /// Slope along columns (x), um per pixel.
    pub tilt_x_um_per_px: f64,
    /// Slope along rows (y), um per pixel.
    pub tilt_y_um_per_px: f64,
}

impl PlaneCorrection {
    /// No correction.
    pub const ZERO: PlaneCorrection = PlaneCorrection {
        piston_um: 0.0,
        tilt_x_um_per_px: 0.0,
        tilt_y_um_per_px: 0.0,
    };

    /// The correction (um) at a possibly fractional pixel position of a tile of `shape`.
    #[inline]
    pub fn at(&self, row: f64, col: f64, shape: Shape) -> f64 {
        let (cx, cy) = shape.centre_px();
        self.piston_um + self.tilt_x_um_per_px * (col - cx) + self.tilt_y_um_per_px * (row - cy)
    }

    /// Subtracts the correction in place (NaN stays NaN).
    pub fn apply(&self, raster: &mut Raster<f32>) {
        let (cx, cy) = raster.shape().centre_px();
        for (row, line) in raster.rows_iter_mut().enumerate() {
            let base = self.piston_um + self.tilt_y_um_per_px * (row as f64 - cy)
                - self.tilt_x_um_per_px * cx;
            for (col, z) in line.iter_mut().enumerate() {
                *z = (*z as f64 - (base + self.tilt_x_um_per_px * col as f64)) as f32;
            }
        }
    }

    /// A corrected copy.
    pub fn corrected(&self, raster: RasterView<'_, f32>) -> Raster<f32> {
        let mut out = raster.to_owned();
        self.apply(&mut out);
        out
    }

    /// The sum of two corrections (apply `self`, then `other`).
    pub fn then(&self, other: &PlaneCorrection) -> PlaneCorrection {
        PlaneCorrection {
            piston_um: self.piston_um + other.piston_um,
            tilt_x_um_per_px: self.tilt_x_um_per_px + other.tilt_x_um_per_px,
            tilt_y_um_per_px: self.tilt_y_um_per_px + other.tilt_y_um_per_px,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn correction_is_centred_and_levels_a_tilted_tile() {
        let shape = Shape::new(3, 5);
        let p = PlaneCorrection {
            piston_um: 2.0,
            tilt_x_um_per_px: 0.5,
            tilt_y_um_per_px: -1.0,
        };
        assert_eq!(p.at(1.0, 2.0, shape), 2.0);
        let tilted = Raster::new(
            (0..15)
                .map(|i| p.at((i / 5) as f64, (i % 5) as f64, shape) as f32)
                .collect(),
            shape,
        )
        .unwrap();
        let level = p.corrected(tilted.view());
        assert!(level.values().iter().all(|v| v.abs() < 1e-6));
    }
}
