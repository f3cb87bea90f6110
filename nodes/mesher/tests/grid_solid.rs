//! The regular-grid solid: counts, topology, orientation, placement, units, NaN filling, errors.

mod common;

use common::*;
use surfstream_core::raster::{RasterView, Shape, ShapeError};
use surfstream_core::Pitch;
use surfstream_mesher::{
    check_closed, grid_solid, LengthUnit, MeshError, ScanPlacement, SolidMesh, SolidParams,
};

fn params(units: LengthUnit, recentre: bool) -> SolidParams {
    SolidParams {
        units,
        base_depth_um: None,
        recentre,
    }
}

fn assert_close(a: f64, b: f64, tol: f64, what: &str) {
    assert!((a - b).abs() <= tol, "{what}: {a} vs {b} (tol {tol})");
}

/// Volume between the triangulated top surface and the base, computed independently of the
/// mesh: each top triangle's x-y area times the mean height of its corners above the base.
fn prism_volume(mesh: &SolidMesh, base_z: f64) -> f64 {
    (0..mesh.top_triangles)
        .map(|t| {
            let [a, b, c] = mesh.triangle_corners(t);
            let area_xy = 0.5 * ((b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1]));
            area_xy * ((a[2] + b[2] + c[2]) / 3.0 - base_z)
        })
        .sum()
}

#[test]
fn small_asymmetric_map_is_a_closed_outward_solid() {
    let mesh = solid(field_3x4(&HEIGHTS_3X4_UM), &SolidParams::default()).unwrap();
    // Top 2 (4-1)(3-1) = 12, rim B = 2*3 + 2*2 = 10 samples: walls 2B = 20, base B = 10.
    assert_eq!(mesh.top_triangles, 12);
    assert_eq!(mesh.triangles.len(), 42);
    assert_eq!(mesh.vertices.len(), 12 + 10 + 1);
    assert_eq!(mesh.filled_samples, 0);
    assert_eq!(mesh.units, LengthUnit::Mm);

    let check = check_closed(&mesh);
    assert!(check.watertight, "{check:?}");
    assert!(check.consistently_oriented, "{check:?}");
    assert_eq!(check.degenerate_triangles, 0);
    assert_eq!(check.duplicate_triangles, 0);
    assert_eq!(check.coincident_vertices_f32, 0);
    assert!(
        check.signed_volume > 0.0,
        "normals point inwards: {check:?}"
    );
    // Recentred: the base is at z = 0.
    let expected = prism_volume(&mesh, 0.0);
    assert_close(check.signed_volume, expected, 1e-12 * expected, "volume");
    // Default base depth: range 6.0 um -> max(10 um, 0.6 um) = 10 um.
    assert_eq!(mesh.base_depth_um, 10.0);
}

#[test]
fn every_face_points_outwards() {
    let mesh = solid(field_3x4(&HEIGHTS_3X4_UM), &params(LengthUnit::Um, true)).unwrap();
    let centre = [0.0, 0.0]; // recentred: the x-y centre of the grid
    for t in 0..mesh.triangles.len() {
        let n = mesh.face_normal(t);
        let [a, b, c] = mesh.triangle_corners(t);
        let mid = [(a[0] + b[0] + c[0]) / 3.0, (a[1] + b[1] + c[1]) / 3.0];
        let all_base = [a, b, c].iter().all(|v| v[2] == 0.0);
        if t < mesh.top_triangles {
            assert!(n[2] > 0.0, "top triangle {t} normal {n:?}");
        } else if all_base {
            assert_eq!(n, [0.0, 0.0, -1.0], "base triangle {t}");
        } else {
            // A wall: horizontal normal pointing away from the centre.
            assert!(n[2].abs() < 1e-12, "wall triangle {t} normal {n:?}");
            let away = (mid[0] - centre[0]) * n[0] + (mid[1] - centre[1]) * n[1];
            assert!(away > 0.0, "wall triangle {t} normal {n:?} points inwards");
        }
    }
}

#[test]
fn vertices_sit_on_the_samples_without_flips() {
    // No recentring, origin 0, z offset 0, um: vertex (i, j) is exactly (j px, i py, h).
    let map = Map::new(&HEIGHTS_3X4_UM, ROWS, COLS, PITCH_X_UM, PITCH_Y_UM);
    let mesh = solid(map, &params(LengthUnit::Um, false)).unwrap();
    assert_eq!(mesh.offset_um, [0.0; 3]);
    for i in 0..ROWS {
        for j in 0..COLS {
            let v = mesh.vertices[i * COLS + j];
            let expected = [
                j as f64 * PITCH_X_UM,
                i as f64 * PITCH_Y_UM,
                f64::from(HEIGHTS_3X4_UM[i * COLS + j]),
            ];
            assert_eq!(v, expected, "vertex (row {i}, col {j})");
        }
    }
    // Base 10 um below the lowest sample (0.3 um).
    let base_z = mesh.vertices[COLS * ROWS][2];
    assert_close(base_z, 0.3f32 as f64 - 10.0, 1e-12, "base z");

    // With recentring and an origin: the same positions once the offset is added back.
    let mesh = solid(field_3x4(&HEIGHTS_3X4_UM), &params(LengthUnit::Um, true)).unwrap();
    for i in 0..ROWS {
        for j in 0..COLS {
            let scan = mesh.to_scan_um(mesh.vertices[i * COLS + j]);
            let expected = [
                12_345.6 + j as f64 * PITCH_X_UM,
                -7_890.1 + i as f64 * PITCH_Y_UM,
                25_000.0 + f64::from(HEIGHTS_3X4_UM[i * COLS + j]),
            ];
            for k in 0..3 {
                assert_close(scan[k], expected[k], 1e-9, "scan coordinate");
            }
        }
    }
    // Recentred: x-y centre of the grid at 0, base at z = 0, everything else above it.
    let top = &mesh.vertices[..COLS * ROWS];
    let (sx, sy) = top
        .iter()
        .fold((0.0, 0.0), |(sx, sy), v| (sx + v[0], sy + v[1]));
    assert_close(sx, 0.0, 1e-12, "mean x");
    assert_close(sy, 0.0, 1e-12, "mean y");
    assert!(mesh.vertices[COLS * ROWS..].iter().all(|v| v[2] == 0.0));
    assert!(top.iter().all(|v| v[2] >= 10.0));
    assert_eq!(
        mesh.offset_um,
        [
            12_345.6 + 1.5 * PITCH_X_UM,
            -7_890.1 + PITCH_Y_UM,
            25_000.0 + 0.3f32 as f64 - 10.0
        ]
    );
}

#[test]
fn units_scale_and_round_trip() {
    let um = solid(field_3x4(&HEIGHTS_3X4_UM), &params(LengthUnit::Um, true)).unwrap();
    for (units, per_um) in [(LengthUnit::Mm, 1e-3), (LengthUnit::M, 1e-6)] {
        let mesh = solid(field_3x4(&HEIGHTS_3X4_UM), &params(units, true)).unwrap();
        assert_eq!(mesh.triangles, um.triangles);
        assert_eq!(mesh.offset_um, um.offset_um, "the offset is always in um");
        for (v, v_um) in mesh.vertices.iter().zip(&um.vertices) {
            for k in 0..3 {
                assert_close(v[k], v_um[k] * per_um, 1e-12 * per_um, "scaled");
            }
            let back = mesh.to_scan_um(*v);
            let back_um = um.to_scan_um(*v_um);
            for k in 0..3 {
                assert_close(back[k], back_um[k], 1e-9, "round trip");
            }
        }
        let volume = check_closed(&mesh).signed_volume;
        let volume_um = check_closed(&um).signed_volume;
        assert_close(
            volume,
            volume_um * per_um.powi(3),
            1e-9 * volume,
            "volume scales",
        );
    }
    // Without recentring the units apply to absolute coordinates.
    let m = solid(field_3x4(&HEIGHTS_3X4_UM), &params(LengthUnit::M, false)).unwrap();
    assert_close(
        m.vertices[1][0],
        (12_345.6 + PITCH_X_UM) * 1e-6,
        1e-18,
        "x in m",
    );
}

#[test]
fn nan_samples_are_filled_and_counted() {
    let mut h = HEIGHTS_3X4_UM;
    h[5] = f32::NAN; // (1, 1): all 8 neighbours measured
    h[11] = f32::NAN; // corner (2, 3): neighbours (1, 2), (1, 3), (2, 2)
    let mesh = solid(field_3x4(&h), &params(LengthUnit::Um, false)).unwrap();
    assert_eq!(mesh.filled_samples, 2);
    let z = |k: usize| mesh.vertices[k][2] - 25_000.0;
    let ring = [1.0, 2.5, 0.3, 3.2, 5.1, 0.9, 6.3, 1.1];
    assert_close(z(5), ring.iter().sum::<f64>() / 8.0, 1e-5, "filled (1, 1)");
    assert_close(z(11), (5.1 + 2.2 + 1.1) / 3.0, 1e-5, "filled (2, 3)");
    let check = check_closed(&mesh);
    assert!(check.watertight && check.signed_volume > 0.0, "{check:?}");

    // A whole missing row and column still fill, from the one remaining block.
    let mut h = HEIGHTS_3X4_UM;
    for k in [0, 1, 2, 3, 4, 8] {
        h[k] = f32::NAN;
    }
    let mesh = solid(field_3x4(&h), &SolidParams::default()).unwrap();
    assert_eq!(mesh.filled_samples, 6);
    assert!(mesh
        .vertices
        .iter()
        .all(|v| v.iter().all(|c| c.is_finite())));
    assert!(check_closed(&mesh).watertight);
}

#[test]
fn bad_inputs_give_clear_errors() {
    let params = SolidParams::default();
    let one = [1.0f32];
    let err = solid(Map::new(&one, 1, 1, 1.0, 1.0), &params).unwrap_err();
    assert!(matches!(err, MeshError::TooSmall { rows: 1, cols: 1 }));
    assert!(err.to_string().contains("at least 2 x 2"), "{err}");

    let row = [1.0f32; 5];
    let err = solid(Map::new(&row, 1, 5, 1.0, 1.0), &params).unwrap_err();
    assert!(
        matches!(err, MeshError::TooSmall { rows: 1, cols: 5 }),
        "{err}"
    );
    assert!(
        err.to_string().contains("1 x 5 samples (rows x cols)"),
        "{err}"
    );

    // A payload that does not fill its shape, an empty or an overflowing shape never becomes
    // a raster, so it never reaches the mesher; the error converts into the mesher's.
    let at = ScanPlacement::new(Pitch::new(1.0, 1.0).expect("a positive pitch"));
    for (values, shape) in [
        (&row[..], Shape::new(2, 2)),
        (&[][..], Shape::new(0, 0)),
        (&row[..], Shape::new(2, usize::MAX)),
    ] {
        let e = RasterView::new(values, shape).unwrap_err();
        assert!(matches!(
            e,
            ShapeError::Length { .. } | ShapeError::Empty(_)
        ));
        let err = MeshError::from(e);
        assert!(err.to_string().starts_with("height field: "), "{err}");
    }
    let short = RasterView::new(&row[..4], Shape::new(2, 2)).unwrap();
    assert!(grid_solid(short, &at, &params).is_ok());

    // A bad pitch never becomes a Pitch, so it never reaches the mesher; the error of the one
    // check converts into the mesher's, naming the axis.
    for bad in [f64::NAN, f64::INFINITY, 0.0, -0.8] {
        let err = MeshError::from(Pitch::new(bad, 1.0).unwrap_err());
        assert!(
            matches!(
                err,
                MeshError::Param(surfstream_core::ParamError {
                    field: "pitch_x_um",
                    ..
                })
            ),
            "{err}"
        );
        let err = MeshError::from(Pitch::new(1.0, bad).unwrap_err());
        assert!(err.to_string().starts_with("pitch_y_um"), "{err}");
    }
    let map = field_3x4(&HEIGHTS_3X4_UM).with_origin(f64::NAN, 0.0);
    assert!(solid(map, &params).is_err());
    let map = field_3x4(&HEIGHTS_3X4_UM).with_z_offset(f64::INFINITY);
    assert!(solid(map, &params).is_err());

    let nan = [f32::NAN; 12];
    let err = solid(field_3x4(&nan), &params).unwrap_err();
    assert!(
        matches!(err, MeshError::NoValidSample { samples: 12 }),
        "{err}"
    );

    let mut inf = HEIGHTS_3X4_UM;
    inf[6] = f32::NEG_INFINITY;
    let err = solid(field_3x4(&inf), &params).unwrap_err();
    assert!(
        matches!(err, MeshError::InfiniteSample { row: 1, col: 2, .. }),
        "{err}"
    );

    for depth in [0.0, -1.0, f64::NAN] {
        let p = SolidParams {
            base_depth_um: Some(depth),
            ..SolidParams::default()
        };
        let err = solid(field_3x4(&HEIGHTS_3X4_UM), &p).unwrap_err();
        assert!(err.to_string().starts_with("base_depth_um"), "{err}");
    }
}

#[test]
fn explicit_base_depth_is_used() {
    let p = SolidParams {
        units: LengthUnit::Um,
        base_depth_um: Some(2.5),
        recentre: true,
    };
    let mesh = solid(field_3x4(&HEIGHTS_3X4_UM), &p).unwrap();
    assert_eq!(mesh.base_depth_um, 2.5);
    let lowest_top = mesh.vertices[..12]
        .iter()
        .map(|v| v[2])
        .fold(f64::INFINITY, f64::min);
    assert_close(lowest_top, 2.5, 1e-12, "lowest sample above the base");
}

#[test]
fn larger_field_is_watertight_with_the_prism_volume() {
    let (w, h) = (97, 64);
    let heights = wavy_heights_um(h, w);
    let map = Map::new(&heights, h, w, 0.8148, 0.8148).with_origin(5.0e4, 3.0e4);
    let mesh = solid(map, &SolidParams::default()).unwrap();
    let b = 2 * (w - 1) + 2 * (h - 1);
    assert_eq!(mesh.triangles.len(), 2 * (w - 1) * (h - 1) + 3 * b);
    let check = check_closed(&mesh);
    assert!(check.watertight && check.consistently_oriented, "{check:?}");
    assert_eq!(check.degenerate_triangles + check.duplicate_triangles, 0);
    assert_eq!(check.coincident_vertices_f32, 0);
    let expected = prism_volume(&mesh, 0.0);
    assert_close(check.signed_volume, expected, 1e-9 * expected, "volume");
}

#[test]
fn recentring_keeps_f32_resolution_far_from_the_origin() {
    // 1 nm pitch 50 mm from the scan origin: f32 metres resolve only ~4 nm there.
    let heights = wavy_heights_um(8, 8);
    let map = Map::new(&heights, 8, 8, 1e-3, 1e-3).with_origin(5.0e4, 5.0e4);
    let absolute = solid(map, &params(LengthUnit::M, false)).unwrap();
    assert!(check_closed(&absolute).coincident_vertices_f32 > 0);
    let recentred = solid(map, &params(LengthUnit::M, true)).unwrap();
    assert_eq!(check_closed(&recentred).coincident_vertices_f32, 0);
}

#[test]
fn params_deserialise_with_defaults_and_lowercase_units() {
    // Graph files carry node parameters as maps; missing keys take the defaults.
    use serde::de::value::{Error, MapDeserializer, StrDeserializer};
    use serde::Deserialize;
    let empty: Vec<(String, String)> = Vec::new();
    let p = SolidParams::deserialize(MapDeserializer::<_, Error>::new(empty.into_iter())).unwrap();
    assert_eq!(p, SolidParams::default());
    for (text, unit) in [
        ("m", LengthUnit::M),
        ("mm", LengthUnit::Mm),
        ("um", LengthUnit::Um),
    ] {
        let parsed = LengthUnit::deserialize(StrDeserializer::<Error>::new(text)).unwrap();
        assert_eq!(parsed, unit);
        assert_eq!(unit.symbol(), text);
    }
}
