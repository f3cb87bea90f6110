//! The error-bounded mesher end to end: the bound at every sample (checked here by an
//! independent point-in-triangle search, not by the mesher's own rasteriser), solids closed and
//! consistently oriented by edge manifoldness, holes never spanned, units and offset round-trip,
//! and STL read back by trimesh (the test Python, SURFSTREAM_PYTHON) with the same geometry.

mod common;

use std::path::PathBuf;
use std::process::Command;

use common::Map;
use surfstream_mesher::{
    check_closed, mesh_height_field, write_stl_ascii, write_stl_binary, AdaptiveMesh, Epsilon,
    LengthUnit, MeshKind, MeshParams, MissingSamples, SolidParams,
};

/// A rough, anisotropic, deterministic surface (um): waviness, a crossed ripple and
/// pseudo-random noise, so that the mesher has to refine unevenly.
fn rough_um(width: usize, height: usize, noise_um: f64) -> Vec<f32> {
    let mut state: u64 = 0x9E37_79B9_7F4A_7C15;
    (0..width * height)
        .map(|k| {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            let r = (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5;
            let (x, y) = ((k % width) as f64 / 40.0, (k / width) as f64 / 40.0);
            (1.5 * (1.3 * x).sin() * (0.9 * y).cos()
                + 0.4 * (5.0 * x + 2.0 * y).sin()
                + 0.2 * x
                + noise_um * r) as f32
        })
        .collect()
}

fn params(epsilon_um: f64, kind: MeshKind, missing: MissingSamples) -> MeshParams {
    MeshParams {
        epsilon: Epsilon::Um(epsilon_um),
        max_triangles: None,
        kind,
        missing,
        solid: SolidParams {
            units: LengthUnit::Mm,
            base_depth_um: None,
            recentre: true,
        },
        // Small blocks, so that every test crosses block seams (the default is one block
        // below 192 samples a side).
        block_samples: Some(40),
    }
}

/// For every measured sample: the heights of the surface triangles that contain it (found by a
/// brute-force barycentric search in scan coordinates). Returns (worst |error| over covered
/// samples, samples covered by no triangle, missing samples covered by a triangle).
fn independent_check(m: &AdaptiveMesh, map: &Map<'_>) -> (f64, usize, usize) {
    let (w, h) = (map.heights.cols(), map.heights.rows());
    let mut worst = 0.0f64;
    let mut covered = vec![false; w * h];
    let mut nan_covered = 0;
    for t in 0..m.mesh.top_triangles {
        let p = m.mesh.triangle_corners(t).map(|v| m.mesh.to_scan_um(v));
        // Back to fractional grid indices.
        let g = p.map(|q| {
            (
                (q[0] - map.at.origin_x_um) / map.at.pitch.x_um(),
                (q[1] - map.at.origin_y_um) / map.at.pitch.y_um(),
                q[2] - map.at.z_offset_um,
            )
        });
        let (x0, x1) = (
            g.iter().map(|c| c.0).fold(f64::INFINITY, f64::min).floor() as i64,
            g.iter()
                .map(|c| c.0)
                .fold(f64::NEG_INFINITY, f64::max)
                .ceil() as i64,
        );
        let (y0, y1) = (
            g.iter().map(|c| c.1).fold(f64::INFINITY, f64::min).floor() as i64,
            g.iter()
                .map(|c| c.1)
                .fold(f64::NEG_INFINITY, f64::max)
                .ceil() as i64,
        );
        let det = (g[1].0 - g[0].0) * (g[2].1 - g[0].1) - (g[2].0 - g[0].0) * (g[1].1 - g[0].1);
        assert!(
            det > 0.0,
            "surface triangle {t} is not counter-clockwise from +z"
        );
        for y in y0.max(0)..=y1.min(h as i64 - 1) {
            for x in x0.max(0)..=x1.min(w as i64 - 1) {
                let (px, py) = (x as f64, y as f64);
                let l1 =
                    ((px - g[0].0) * (g[2].1 - g[0].1) - (g[2].0 - g[0].0) * (py - g[0].1)) / det;
                let l2 =
                    ((g[1].0 - g[0].0) * (py - g[0].1) - (px - g[0].0) * (g[1].1 - g[0].1)) / det;
                let l0 = 1.0 - l1 - l2;
                let tol = -1e-9;
                if l0 < tol || l1 < tol || l2 < tol {
                    continue;
                }
                let s = y as usize * w + x as usize;
                let sample = map.heights.values()[s];
                if sample.is_nan() {
                    // On a vertex of a kept triangle is impossible (missing corners are
                    // dropped); inside or on an edge means the triangle spans a hole.
                    nan_covered += 1;
                    continue;
                }
                let z = l0 * g[0].2 + l1 * g[1].2 + l2 * g[2].2;
                worst = worst.max((z - f64::from(sample)).abs());
                covered[s] = true;
            }
        }
    }
    let uncovered = (0..w * h)
        .filter(|&s| !covered[s] && !map.heights.values()[s].is_nan())
        .count();
    (worst, uncovered, nan_covered)
}

#[test]
fn bound_holds_at_every_sample_of_a_rough_surface_and_the_solid_is_closed() {
    let (w, h) = (157, 119);
    let heights = rough_um(w, h, 0.3);
    let map = Map::new(&heights, h, w, 0.8148, 0.61)
        .with_origin(12_345.6, -789.0)
        .with_z_offset(25_000.0);
    for epsilon_um in [0.5, 0.1, 0.02] {
        let m = mesh_height_field(
            map.heights,
            &map.at,
            &params(epsilon_um, MeshKind::Solid, MissingSamples::Fill),
        )
        .unwrap();
        let (worst, uncovered, _) = independent_check(&m, &map);
        // The mesh's corners are f64 here; 1e-6 um allows for the round trip through mm.
        assert!(
            worst <= epsilon_um + 1e-6,
            "eps {epsilon_um}: worst {worst}"
        );
        assert_eq!(uncovered, 0);
        assert!(m.fidelity.bound_met);
        assert!((m.fidelity.error.max_um - worst).abs() < 1e-6);
        assert!(m.surface_triangles < 2 * (w - 1) * (h - 1));
        let c = check_closed(&m.mesh);
        assert!(c.watertight && c.consistently_oriented, "{c:?}");
        assert_eq!(c.degenerate_triangles, 0);
        assert_eq!(c.duplicate_triangles, 0);
        assert!(c.signed_volume > 0.0, "normals point inwards: {c:?}");
        // Finer bound, more triangles, closer parameters.
        let (f, g) = (m.fidelity.field.unwrap(), m.fidelity.mesh.unwrap());
        assert!((f.sq_um - g.sq_um).abs() <= epsilon_um);
    }
    let coarse = mesh_height_field(
        map.heights,
        &map.at,
        &params(0.5, MeshKind::Solid, MissingSamples::Fill),
    )
    .unwrap();
    let fine = mesh_height_field(
        map.heights,
        &map.at,
        &params(0.02, MeshKind::Solid, MissingSamples::Fill),
    )
    .unwrap();
    assert!(coarse.surface_triangles * 4 < fine.surface_triangles);
}

#[test]
fn budget_stops_refinement_and_says_so() {
    let (w, h) = (80, 60);
    let heights = rough_um(w, h, 0.3);
    let map = Map::new(&heights, h, w, 1.0, 1.0);
    let mut p = params(0.001, MeshKind::Sheet, MissingSamples::Fill);
    p.max_triangles = Some(500);
    let m = mesh_height_field(map.heights, &map.at, &p).unwrap();
    assert!(m.budget_reached && !m.fidelity.bound_met);
    assert!(m.surface_triangles <= 500);
    let c = check_closed(&m.mesh);
    assert!(c.consistently_oriented && c.non_manifold_edges == 0);
    assert!(c.boundary_edges > 0, "a sheet is open");
}

#[test]
fn holes_are_left_out_and_never_spanned() {
    let (w, h) = (120, 90);
    let mut heights = rough_um(w, h, 0.2);
    for i in 20..45 {
        for j in 30..70 {
            heights[i * w + j] = f32::NAN; // a large dropout
        }
    }
    for k in (0..w * h).step_by(211) {
        heights[k] = f32::NAN; // scattered dropouts, including rim samples
    }
    heights[0] = f32::NAN; // a missing corner
    let map = Map::new(&heights, h, w, 0.5, 0.5).with_origin(-40.0, 7.0);
    let m = mesh_height_field(
        map.heights,
        &map.at,
        &params(0.05, MeshKind::Sheet, MissingSamples::Holes),
    )
    .unwrap();
    let (worst, uncovered, nan_covered) = independent_check(&m, &map);
    assert_eq!(nan_covered, 0, "a triangle spans a missing sample");
    assert!(worst <= 0.05 + 1e-6, "worst {worst}");
    // Only measured samples isolated by missing ones may stay outside every triangle.
    assert!(uncovered < 20, "{uncovered} measured samples left out");
    assert_eq!(m.fidelity.error.uncovered, uncovered);
    let c = check_closed(&m.mesh);
    assert!(c.consistently_oriented && c.non_manifold_edges == 0 && c.degenerate_triangles == 0);

    // A solid cannot have holes; filled, it is closed again and meets the bound at the measured
    // samples.
    assert!(mesh_height_field(
        map.heights,
        &map.at,
        &params(0.05, MeshKind::Solid, MissingSamples::Holes)
    )
    .is_err());
    let filled = mesh_height_field(
        map.heights,
        &map.at,
        &params(0.05, MeshKind::Solid, MissingSamples::Fill),
    )
    .unwrap();
    assert!(check_closed(&filled.mesh).watertight);
    let (worst, uncovered, _) = independent_check(&filled, &map);
    assert!(worst <= 0.05 + 1e-6 && uncovered == 0);
}

#[test]
fn units_and_offset_round_trip() {
    let (w, h) = (40, 30);
    let heights = rough_um(w, h, 0.1);
    let map = Map::new(&heights, h, w, 0.8148, 0.8148)
        .with_origin(50_000.0, 20_000.0)
        .with_z_offset(12_000.0);
    let mut reference: Option<Vec<[f64; 3]>> = None;
    for units in [LengthUnit::M, LengthUnit::Mm, LengthUnit::Um] {
        let mut p = params(0.05, MeshKind::Solid, MissingSamples::Fill);
        p.solid.units = units;
        p.solid.base_depth_um = Some(15.0);
        let m = mesh_height_field(map.heights, &map.at, &p).unwrap();
        let scan: Vec<[f64; 3]> = m
            .mesh
            .vertices
            .iter()
            .map(|&v| m.mesh.to_scan_um(v))
            .collect();
        // Re-centred: the solid sits on z = 0 around the x, y origin.
        let min_z = m
            .mesh
            .vertices
            .iter()
            .map(|v| v[2])
            .fold(f64::INFINITY, f64::min);
        assert!(min_z.abs() < 1e-12);
        let half_x = (w - 1) as f64 * 0.8148 / 2.0 / units.um_per_unit();
        assert!(m
            .mesh
            .vertices
            .iter()
            .all(|v| v[0].abs() <= half_x * (1.0 + 1e-12)));
        // Every surface vertex back in scan coordinates is a sample: exact position and height.
        let top: std::collections::BTreeSet<u32> = m.mesh.triangles[..m.mesh.top_triangles]
            .iter()
            .flatten()
            .copied()
            .collect();
        for v in top.iter().map(|&k| scan[k as usize]) {
            let j = (v[0] - 50_000.0) / 0.8148;
            let i = (v[1] - 20_000.0) / 0.8148;
            assert!((j - j.round()).abs() < 1e-6 && (i - i.round()).abs() < 1e-6);
            let s = i.round() as usize * w + j.round() as usize;
            let z = 12_000.0 + f64::from(heights[s]);
            assert!((v[2] - z).abs() < 1e-6, "{v:?} vs {z}");
        }
        match &reference {
            None => reference = Some(scan),
            Some(r) => {
                for (a, b) in r.iter().zip(&scan) {
                    for k in 0..3 {
                        assert!((a[k] - b[k]).abs() < 1e-6, "{units:?}: {a:?} vs {b:?}");
                    }
                }
            }
        }
    }
}

#[test]
fn real_specimen_meets_the_bound() {
    let path =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/specimens/metropro-1.dat");
    let s = surfstream_io::formats::read_surface(&path)
        .unwrap_or_else(|e| panic!("the real specimen must be readable: {e:#}"));
    let mean = s.heights_um.iter().filter(|h| h.is_finite()).sum::<f64>()
        / s.heights_um.iter().filter(|h| h.is_finite()).count() as f64;
    let heights: Vec<f32> = s.heights_um.iter().map(|&h| (h - mean) as f32).collect();
    let map = Map::new(&heights, s.height, s.width, s.pitch_x_um, s.pitch_y_um).with_z_offset(mean);
    let sq = surfstream_mesher::fidelity::field_params(map.heights, map.at.pitch)
        .unwrap()
        .sq_um;
    let epsilon_um = 0.1 * sq;
    for (kind, missing) in [
        (MeshKind::Sheet, MissingSamples::Holes),
        (MeshKind::Solid, MissingSamples::Fill),
    ] {
        let m =
            mesh_height_field(map.heights, &map.at, &params(epsilon_um, kind, missing)).unwrap();
        let (worst, _, nan_covered) = independent_check(&m, &map);
        assert!(
            worst <= epsilon_um + 1e-6,
            "{kind:?}: worst {worst} > {epsilon_um}"
        );
        if kind == MeshKind::Sheet {
            assert_eq!(nan_covered, 0);
        } else {
            let c = check_closed(&m.mesh);
            assert!(c.watertight && c.consistently_oriented && c.degenerate_triangles == 0);
        }
    }
}

fn python() -> PathBuf {
    if let Ok(p) = std::env::var("SURFSTREAM_PYTHON") {
        return PathBuf::from(p);
    }
    let venv = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../.test-venv/bin/python");
    assert!(
        venv.exists(),
        "no Python test environment: run scripts/test.sh (it creates .test-venv with trimesh) \
         or set SURFSTREAM_PYTHON"
    );
    venv
}

#[test]
fn trimesh_reads_binary_and_ascii_with_the_same_geometry() {
    let (w, h) = (60, 45);
    let heights = rough_um(w, h, 0.2);
    let map = Map::new(&heights, h, w, 0.8148, 0.8148).with_origin(1000.0, 2000.0);
    let m = mesh_height_field(
        map.heights,
        &map.at,
        &params(0.05, MeshKind::Solid, MissingSamples::Fill),
    )
    .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let (bin, asc) = (dir.path().join("s.stl"), dir.path().join("s_ascii.stl"));
    let mut b = Vec::new();
    write_stl_binary(&mut b, &m.mesh, "test").unwrap();
    std::fs::write(&bin, b).unwrap();
    let mut a = Vec::new();
    write_stl_ascii(&mut a, &m.mesh, "test").unwrap();
    std::fs::write(&asc, a).unwrap();
    let script = r#"
import sys, json, numpy as np, trimesh
a = trimesh.load(sys.argv[1], file_type="stl")
b = trimesh.load(sys.argv[2], file_type="stl")
fa = np.sort(a.triangles.reshape(len(a.faces), 9), axis=0)
fb = np.sort(b.triangles.reshape(len(b.faces), 9), axis=0)
print(json.dumps({"faces": [len(a.faces), len(b.faces)],
  "watertight": [bool(a.is_watertight), bool(b.is_watertight)],
  "winding": [bool(a.is_winding_consistent), bool(b.is_winding_consistent)],
  "volume": [float(a.volume), float(b.volume)],
  "max_diff": float(np.abs(fa - fb).max()),
  "bounds": a.bounds.tolist()}))
"#;
    let out = Command::new(python())
        .args(["-c", script])
        .arg(&bin)
        .arg(&asc)
        .output()
        .expect("the test Python must start");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let r: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let n = m.mesh.triangles.len() as u64;
    assert_eq!(r["faces"], serde_json::json!([n, n]));
    assert_eq!(r["watertight"], serde_json::json!([true, true]));
    assert_eq!(r["winding"], serde_json::json!([true, true]));
    let vol = check_closed(&m.mesh).signed_volume;
    for v in r["volume"].as_array().unwrap() {
        let v = v.as_f64().unwrap();
        assert!(v > 0.0 && ((v - vol) / vol).abs() < 1e-4, "{v} vs {vol}");
    }
    // ASCII prints enough digits to give back the binary's f32 values.
    assert!(r["max_diff"].as_f64().unwrap() < 1e-9, "{}", r["max_diff"]);
    // Re-centred, in mm: the part sits on z = 0 around the origin.
    let bounds = r["bounds"].as_array().unwrap();
    let lo_z = bounds[0][2].as_f64().unwrap();
    assert!(lo_z.abs() < 1e-9);
    let hi_x = bounds[1][0].as_f64().unwrap();
    assert!((hi_x - (w - 1) as f64 * 0.8148 / 2.0 / 1000.0).abs() < 1e-6);
}

/// The blocks: their shared sides join without a crack (the solid is watertight, every sample
/// on a side is within the bound), the block size changes the triangle count only a little,
/// and the mesh is the same whatever the number of threads.
#[test]
fn blocks_join_exactly_and_do_not_depend_on_threads() {
    let (w, h) = (203, 150);
    let heights = rough_um(w, h, 0.3);
    let map = Map::new(&heights, h, w, 0.5, 0.5);
    let mesh = |block: Option<usize>, threads: usize| {
        let mut p = params(0.03, MeshKind::Solid, MissingSamples::Fill);
        p.block_samples = block;
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| mesh_height_field(map.heights, &map.at, &p).unwrap())
    };
    let one_block = mesh(Some(100_000), 1);
    for block in [7, 16, 64] {
        let m = mesh(Some(block), 1);
        let (worst, uncovered, _) = independent_check(&m, &map);
        assert!(worst <= 0.03 + 1e-6, "block {block}: worst {worst}");
        assert_eq!(uncovered, 0);
        let c = check_closed(&m.mesh);
        assert!(
            c.watertight && c.consistently_oriented,
            "block {block}: {c:?}"
        );
        assert_eq!(c.degenerate_triangles + c.duplicate_triangles, 0);
        // Fixed sides cost vertices along them; on this rough field a few per cent at most.
        let ratio = m.surface_triangles as f64 / one_block.surface_triangles as f64;
        assert!((0.9..1.1).contains(&ratio), "block {block}: {ratio}");
        let m3 = mesh(Some(block), 3);
        assert_eq!(m.mesh.vertices, m3.mesh.vertices, "block {block}");
        assert_eq!(m.mesh.triangles, m3.mesh.triangles, "block {block}");
    }
}
