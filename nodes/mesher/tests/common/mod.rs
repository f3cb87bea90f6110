//! Fixtures shared by the integration tests.
#![allow(dead_code)]

use surfstream_core::raster::{RasterView, Shape};
use surfstream_core::Pitch;
use surfstream_mesher::{grid_solid, MeshError, ScanPlacement, SolidMesh, SolidParams};

/// A height field for the tests: the raster and where it sits in scan coordinates.
#[derive(Clone, Copy)]
pub struct Map<'a> {
    pub heights: RasterView<'a, f32>,
    pub at: ScanPlacement,
}

impl<'a> Map<'a> {
    /// `rows x cols` heights (panics on a wrong length: a test fixture).
    pub fn new(
        heights_um: &'a [f32],
        rows: usize,
        cols: usize,
        pitch_x_um: f64,
        pitch_y_um: f64,
    ) -> Self {
        Self {
            heights: RasterView::new(heights_um, Shape::new(rows, cols)).expect("fixture shape"),
            at: ScanPlacement::new(Pitch::new(pitch_x_um, pitch_y_um).expect("a positive pitch")),
        }
    }
    pub fn with_origin(mut self, x_um: f64, y_um: f64) -> Self {
        self.at = self.at.with_origin(x_um, y_um);
        self
    }
    pub fn with_z_offset(mut self, z_um: f64) -> Self {
        self.at = self.at.with_z_offset(z_um);
        self
    }
}

/// 3 rows x 4 columns, every height distinct, so that any swap of rows, columns or axes shows.
#[rustfmt::skip]
pub const HEIGHTS_3X4_UM: [f32; 12] = [
    1.0, 2.5, 0.3, 4.0, // row 0 (y = origin_y)
    3.2, 0.7, 5.1, 2.2, // row 1
    0.9, 6.3, 1.1, 3.8, // row 2 (largest y)
];
pub const ROWS: usize = 3;
pub const COLS: usize = 4;
/// Different pitches along x and y, so a transposition shows too.
pub const PITCH_X_UM: f64 = 0.5;
pub const PITCH_Y_UM: f64 = 0.8;

/// The 3 x 4 fixture placed far from the scan origin, as a real tile would be.
pub fn field_3x4(heights_um: &[f32]) -> Map<'_> {
    Map::new(heights_um, ROWS, COLS, PITCH_X_UM, PITCH_Y_UM)
        .with_origin(12_345.6, -7_890.1)
        .with_z_offset(25_000.0)
}

/// A smooth, asymmetric, deterministic surface of any size (um).
pub fn wavy_heights_um(rows: usize, cols: usize) -> Vec<f32> {
    (0..rows)
        .flat_map(|i| {
            (0..cols).map(move |j| {
                let (x, y) = (j as f32 * 0.05, i as f32 * 0.031);
                1.3 * (x).sin() * (1.7 * y).cos() + 0.2 * x + 0.05 * (3.0 * x * y).sin()
            })
        })
        .collect()
}

/// The grid solid of a test map.
pub fn solid(map: Map<'_>, params: &SolidParams) -> Result<SolidMesh, MeshError> {
    grid_solid(map.heights, &map.at, params)
}
