//! Fixtures shared by the integration tests.
#![allow(dead_code)]

use surfstream_mesher::HeightFieldRef;

/// 3 rows x 4 columns, every height distinct, so that any swap of rows, columns or axes shows.
#[rustfmt::skip]
pub const HEIGHTS_3X4_UM: [f32; 12] = [
    1.0, 2.5, 0.3, 4.0, // row 0 (y = origin_y)
    3.2, 0.7, 5.1, 2.2, // row 1
    0.9, 6.3, 1.1, 3.8, // row 2 (largest y)
];
pub const WIDTH: usize = 4;
pub const HEIGHT: usize = 3;
/// Different pitches along x and y, so a transposition shows too.
pub const PITCH_X_UM: f64 = 0.5;
pub const PITCH_Y_UM: f64 = 0.8;

/// The 3 x 4 fixture placed far from the scan origin, as a real tile would be.
pub fn field_3x4(heights_um: &[f32]) -> HeightFieldRef<'_> {
    HeightFieldRef::new(heights_um, WIDTH, HEIGHT, PITCH_X_UM, PITCH_Y_UM)
        .with_origin(12_345.6, -7_890.1)
        .with_z_offset(25_000.0)
}

/// A smooth, asymmetric, deterministic surface of any size (um).
pub fn wavy_heights_um(width: usize, height: usize) -> Vec<f32> {
    (0..height)
        .flat_map(|i| {
            (0..width).map(move |j| {
                let (x, y) = (j as f32 * 0.05, i as f32 * 0.031);
                1.3 * (x).sin() * (1.7 * y).cos() + 0.2 * x + 0.05 * (3.0 * x * y).sin()
            })
        })
        .collect()
}
