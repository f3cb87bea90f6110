//! A non-square map with different pitches: the STL's x spans the columns times pitch x and
//! its y the rows times pitch y, for the grid solid and the adaptive mesh alike, so rows and
//! columns cannot be swapped anywhere between the raster and the file.

use surfstream_core::raster::{RasterView, Shape};
use surfstream_core::Pitch;
use surfstream_mesher::{
    grid_solid, mesh_height_field, write_stl_binary, Epsilon, LengthUnit, MeshKind, MeshParams,
    MissingSamples, ScanPlacement, SolidMesh, SolidParams,
};

const ROWS: usize = 7;
const COLS: usize = 19;
const PITCH_X_UM: f64 = 0.5;
const PITCH_Y_UM: f64 = 1.25;

/// Rough enough that the adaptive mesh keeps interior vertices; distinct along rows and
/// columns.
fn heights_um() -> Vec<f32> {
    (0..ROWS * COLS)
        .map(|k| {
            let (i, j) = ((k / COLS) as f32, (k % COLS) as f32);
            0.7 * (1.3 * j).sin() + 0.4 * (2.1 * i).cos() + 0.01 * i * j
        })
        .collect()
}

/// (min, max) of x and y over the vertices of a binary STL.
fn stl_extent(stl: &[u8]) -> [(f32, f32); 2] {
    let n = u32::from_le_bytes(stl[80..84].try_into().unwrap()) as usize;
    let mut ext = [(f32::INFINITY, f32::NEG_INFINITY); 2];
    for t in 0..n {
        let facet = &stl[84 + 50 * t..84 + 50 * (t + 1)];
        for v in 0..3 {
            for (axis, e) in ext.iter_mut().enumerate() {
                let at = 12 + 12 * v + 4 * axis;
                let c = f32::from_le_bytes(facet[at..at + 4].try_into().unwrap());
                *e = (e.0.min(c), e.1.max(c));
            }
        }
    }
    ext
}

fn check_extent(mesh: &SolidMesh, origin_um: [f64; 2]) {
    let mut stl = Vec::new();
    write_stl_binary(&mut stl, mesh, "non-square").unwrap();
    let [x, y] = stl_extent(&stl);
    let span_x = (COLS - 1) as f64 * PITCH_X_UM;
    let span_y = (ROWS - 1) as f64 * PITCH_Y_UM;
    // Not recentred, in um: the file holds scan coordinates.
    for (got, want) in [
        (x.0, origin_um[0]),
        (x.1, origin_um[0] + span_x),
        (y.0, origin_um[1]),
        (y.1, origin_um[1] + span_y),
    ] {
        assert!(
            (f64::from(got) - want).abs() < 1e-3,
            "{got} vs {want}: {x:?} {y:?}"
        );
    }
}

#[test]
fn stl_x_spans_the_columns_and_y_the_rows() {
    let h = heights_um();
    let heights = RasterView::new(&h, Shape::new(ROWS, COLS)).unwrap();
    let origin = [100.0, -20.0];
    let at = ScanPlacement::new(Pitch::new(PITCH_X_UM, PITCH_Y_UM).expect("a positive pitch"))
        .with_origin(origin[0], origin[1]);
    let solid = SolidParams {
        units: LengthUnit::Um,
        base_depth_um: None,
        recentre: false,
    };
    check_extent(&grid_solid(heights, &at, &solid).unwrap(), origin);
    let params = MeshParams {
        epsilon: Epsilon::Um(0.05),
        max_triangles: None,
        kind: MeshKind::Solid,
        missing: MissingSamples::Fill,
        solid,
        block_samples: Some(5),
    };
    let m = mesh_height_field(heights, &at, &params).unwrap();
    check_extent(&m.mesh, origin);
    assert_eq!(m.resampled_um.len(), ROWS * COLS);
    // The transposed raster is a different surface: its x spans the rows.
    let transposed = RasterView::new(&h, Shape::new(COLS, ROWS)).unwrap();
    let t = grid_solid(transposed, &at, &params.solid).unwrap();
    let mut stl = Vec::new();
    write_stl_binary(&mut stl, &t, "transposed").unwrap();
    let [x, _] = stl_extent(&stl);
    assert!((f64::from(x.1 - x.0) - (ROWS - 1) as f64 * PITCH_X_UM).abs() < 1e-3);
}
