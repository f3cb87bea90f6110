//! The streaming mesher (issue 17) against the in-memory one: the same STL bytes, the same
//! statistics, the same mesh on the grid and the same closed-solid check, on surfaces with
//! and without missing samples, solids and sheets, binary and ASCII, many blocks or one (a
//! triangle budget); and the streamed STL, read back and welded by position, is watertight
//! across the block seams. MeshJob::mesh_to_files writes the same files as mesh() + write_stl.

use surfstream_core::frame::{flags, FrameHeader, FrameKind, HeightMap};
use surfstream_core::raster::{RasterView, Shape};
use surfstream_core::record;
use surfstream_core::Pitch;
use surfstream_mesher::{
    check_closed, grid_solid, grid_streaming, mesh_height_field, mesh_streaming, write_stl_ascii,
    write_stl_binary, Epsilon, LengthUnit, MeshCheck, MeshCounts, MeshJob, MeshKind, MeshParams,
    MesherConfig, MissingSamples, ScanPlacement, SolidMesh, SolidParams, StlFormat,
};

const LABEL: &str = "surfstream surface";

/// Rough, deterministic heights (um) with optional square holes of NaN.
fn surface(rows: usize, cols: usize, holes: bool) -> Vec<f32> {
    let mut state: u64 = 0x2545_F491_4F6C_DD1D;
    (0..rows * cols)
        .map(|k| {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            let r = (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5;
            let (i, j) = (k / cols, k % cols);
            let (x, y) = (j as f64 / 17.0, i as f64 / 23.0);
            let hole = holes
                && ((i % 37 > 29 && j % 41 > 30)
                    || (i > 5 && i < 9 && j < 12)
                    || (i > 78 && i < 86 && j > 50 && j < 62));
            if hole {
                f32::NAN
            } else {
                (2.0 * x.sin() * y.cos() + 0.3 * (3.0 * x + y).sin() + 0.25 * r + 40.0) as f32
            }
        })
        .collect()
}

fn params(kind: MeshKind, missing: MissingSamples, block: Option<usize>) -> MeshParams {
    MeshParams {
        epsilon: Epsilon::SqFraction(0.05),
        max_triangles: None,
        kind,
        missing,
        solid: SolidParams::default(),
        block_samples: block,
    }
}

fn in_memory(
    heights: RasterView<'_, f32>,
    at: &ScanPlacement,
    p: &MeshParams,
    ascii: bool,
) -> (Vec<u8>, serde_json::Value, Vec<f32>, MeshCheck, SolidMesh) {
    let m = mesh_height_field(heights, at, p).unwrap();
    let mut stl = Vec::new();
    if ascii {
        write_stl_ascii(&mut stl, &m.mesh, LABEL).unwrap();
    } else {
        write_stl_binary(&mut stl, &m.mesh, LABEL).unwrap();
    }
    let check = check_closed(&m.mesh);
    (stl, m.summary().unwrap(), m.resampled_um, check, m.mesh)
}

fn streamed(
    heights: RasterView<'_, f32>,
    at: &ScanPlacement,
    p: &MeshParams,
    ascii: bool,
) -> (Vec<u8>, serde_json::Value, Vec<f32>, MeshCheck) {
    let dir = tempfile::tempdir().unwrap();
    let mut m = mesh_streaming(heights, at, p, dir.path()).unwrap();
    let mut stl = Vec::new();
    let check = m.write_stl(&mut stl, ascii, LABEL, heights).unwrap();
    (
        stl,
        m.summary.to_value().unwrap(),
        m.resampled_um.clone(),
        check,
    )
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

/// Reads a binary STL back and welds its corners by exact f32 position: the solid as a reader
/// sees it.
fn read_binary_stl(bytes: &[u8]) -> SolidMesh {
    let n = u32::from_le_bytes(bytes[80..84].try_into().unwrap()) as usize;
    assert_eq!(bytes.len(), 84 + 50 * n);
    let mut index = std::collections::HashMap::new();
    let (mut vertices, mut triangles) = (Vec::new(), Vec::new());
    for t in 0..n {
        let r = &bytes[84 + 50 * t..84 + 50 * (t + 1)];
        let f = |k: usize| f32::from_le_bytes(r[4 * k..4 * k + 4].try_into().unwrap());
        let tri = [1, 2, 3].map(|c| {
            let p = [f(3 * c), f(3 * c + 1), f(3 * c + 2)];
            *index.entry(p.map(f32::to_bits)).or_insert_with(|| {
                vertices.push(p.map(f64::from));
                (vertices.len() - 1) as u32
            })
        });
        triangles.push(tri);
    }
    SolidMesh {
        vertices,
        triangles,
        offset_um: [0.0; 3],
        units: LengthUnit::Mm,
        filled_samples: 0,
        top_triangles: n,
        base_depth_um: 0.0,
    }
}

fn same_check(a: &MeshCheck, b: &MeshCheck) {
    let strip = |c: &MeshCheck| MeshCheck {
        signed_volume: 0.0,
        ..c.clone()
    };
    assert_eq!(strip(a), strip(b));
    let scale = a.signed_volume.abs().max(1e-30);
    assert!(
        (a.signed_volume - b.signed_volume).abs() <= 1e-9 * scale,
        "{} vs {}",
        a.signed_volume,
        b.signed_volume
    );
}

#[test]
fn streamed_equals_in_memory_on_solids_sheets_holes_and_formats() {
    let (rows, cols) = (157, 213);
    let at = ScanPlacement::new(Pitch::new(0.8148, 0.91).expect("a positive pitch"))
        .with_origin(1234.5, -87.25)
        .with_z_offset(-310.0);
    let full = surface(rows, cols, false);
    let holed = surface(rows, cols, true);
    assert!(holed.iter().any(|h| h.is_nan()));
    let cases = [
        (
            &full,
            MeshKind::Solid,
            MissingSamples::Fill,
            Some(40),
            false,
        ),
        (&full, MeshKind::Solid, MissingSamples::Fill, Some(40), true),
        (
            &holed,
            MeshKind::Solid,
            MissingSamples::Fill,
            Some(33),
            false,
        ),
        (
            &holed,
            MeshKind::Sheet,
            MissingSamples::Holes,
            Some(40),
            false,
        ),
        (
            &holed,
            MeshKind::Sheet,
            MissingSamples::Holes,
            Some(25),
            true,
        ),
        (&full, MeshKind::Sheet, MissingSamples::Fill, None, true),
        // The default block size: one row of blocks here.
        (&holed, MeshKind::Solid, MissingSamples::Fill, None, false),
    ];
    for (k, (z, kind, missing, block, ascii)) in cases.into_iter().enumerate() {
        let heights = RasterView::new(z, Shape::new(rows, cols)).unwrap();
        let p = params(kind, missing, block);
        let (stl_a, sum_a, res_a, check_a, mesh) = in_memory(heights, &at, &p, ascii);
        let (stl_b, sum_b, res_b, check_b) = streamed(heights, &at, &p, ascii);
        assert_eq!(stl_a.len(), stl_b.len(), "case {k}");
        assert!(stl_a == stl_b, "case {k}: STL bytes differ");
        assert_eq!(sum_a, sum_b, "case {k}");
        assert_eq!(bits(&res_a), bits(&res_b), "case {k}");
        same_check(&check_a, &check_b);
        assert_eq!(check_b.watertight, kind == MeshKind::Solid, "case {k}");
        assert!(check_b.consistently_oriented, "case {k}");
        assert!(
            mesh.triangles.len() > 1000,
            "case {k}: a mesh worth testing"
        );
        if !ascii && kind == MeshKind::Solid {
            // Read back and welded by position: closed across every block seam.
            let back = check_closed(&read_binary_stl(&stl_b));
            assert!(
                back.watertight && back.consistently_oriented,
                "case {k}: {back:?}"
            );
            assert!(back.signed_volume > 0.0);
        }
    }
}

#[test]
fn streamed_equals_in_memory_with_a_budget_and_without_recentring() {
    let (rows, cols) = (90, 120);
    let z = surface(rows, cols, true);
    let heights = RasterView::new(&z, Shape::new(rows, cols)).unwrap();
    let at = ScanPlacement::new(Pitch::new(2.5, 2.5).expect("a positive pitch"))
        .with_origin(5.0e4, 3.0e4);
    let mut p = params(MeshKind::Solid, MissingSamples::Fill, Some(30));
    p.max_triangles = Some(900);
    p.epsilon = Epsilon::Um(0.01);
    let (stl_a, sum_a, res_a, check_a, _) = in_memory(heights, &at, &p, false);
    let (stl_b, sum_b, res_b, check_b) = streamed(heights, &at, &p, false);
    assert!(stl_a == stl_b);
    assert_eq!(sum_a, sum_b);
    assert_eq!(sum_b["budget_reached"], true);
    assert_eq!(bits(&res_a), bits(&res_b));
    same_check(&check_a, &check_b);

    // Absolute coordinates in um: the f32 vertices far from the origin.
    let mut p = params(MeshKind::Sheet, MissingSamples::Holes, Some(30));
    p.solid.recentre = false;
    p.solid.units = LengthUnit::Um;
    let (stl_a, sum_a, _, check_a, _) = in_memory(heights, &at, &p, true);
    let (stl_b, sum_b, _, check_b) = streamed(heights, &at, &p, true);
    assert!(stl_a == stl_b);
    assert_eq!(sum_a, sum_b);
    same_check(&check_a, &check_b);

    // 10 m from the origin in mm without recentring: f32 welds vertices; counted alike.
    let at = ScanPlacement::new(Pitch::new(0.5, 0.5).expect("a positive pitch"))
        .with_origin(1.0e7, 1.0e7)
        .with_z_offset(1.0e7);
    p.solid.units = LengthUnit::Mm;
    p.epsilon = Epsilon::Um(0.02);
    let (_, _, _, check_a, _) = in_memory(heights, &at, &p, false);
    let (_, _, _, check_b) = streamed(heights, &at, &p, false);
    assert!(check_a.coincident_vertices_f32 > 0);
    same_check(&check_a, &check_b);
}

#[test]
fn streamed_refuses_what_the_in_memory_mesher_refuses() {
    let z = vec![f32::NAN; 12];
    let heights = RasterView::new(&z, Shape::new(3, 4)).unwrap();
    let at = ScanPlacement::new(Pitch::new(1.0, 1.0).expect("a positive pitch"));
    let dir = tempfile::tempdir().unwrap();
    for p in [
        params(MeshKind::Solid, MissingSamples::Holes, None),
        params(MeshKind::Sheet, MissingSamples::Fill, None),
    ] {
        let a = mesh_height_field(heights, &at, &p)
            .err()
            .unwrap()
            .to_string();
        let b = mesh_streaming(heights, &at, &p, dir.path())
            .err()
            .unwrap()
            .to_string();
        assert_eq!(a, b);
    }
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
}

/// The full-grid solid streamed: the same bytes and check as grid_solid + the writers, with and
/// without missing samples, recentred or not.
#[test]
fn streamed_grid_equals_grid_solid() {
    let (rows, cols) = (61, 83);
    // The last case sits 10 m from the origin without recentring: f32 welds neighbouring
    // samples, and both checks must count the same coincident vertices.
    for (holes, recentre, ascii, origin_um) in [
        (false, true, false, 3.0e4),
        (true, true, true, 3.0e4),
        (true, false, false, 3.0e4),
        (false, false, false, 1.0e7),
    ] {
        let z = surface(rows, cols, holes);
        let heights = RasterView::new(&z, Shape::new(rows, cols)).unwrap();
        let at = ScanPlacement::new(Pitch::new(1.5, 0.75).expect("a positive pitch"))
            .with_origin(origin_um, origin_um)
            .with_z_offset(origin_um);
        let p = SolidParams {
            recentre,
            ..SolidParams::default()
        };
        let mesh = grid_solid(heights, &at, &p).unwrap();
        let mut want = Vec::new();
        if ascii {
            write_stl_ascii(&mut want, &mesh, LABEL).unwrap();
        } else {
            write_stl_binary(&mut want, &mesh, LABEL).unwrap();
        }
        let g = grid_streaming(heights, &at, &p).unwrap();
        let mut got = Vec::new();
        let check = g.write_stl(&mut got, ascii, LABEL, heights).unwrap();
        assert!(got == want, "holes {holes}, recentre {recentre}");
        let want_check = check_closed(&mesh);
        same_check(&want_check, &check);
        assert!(check.watertight);
        assert_eq!(want_check.coincident_vertices_f32 > 0, origin_um > 1e6);
        assert_eq!(g.counts, MeshCounts::of(&mesh));
    }
}

fn frame(rows: usize, cols: usize, flag: u32, heights: Vec<f32>) -> HeightMap {
    HeightMap {
        header: FrameHeader {
            kind: FrameKind::Pooled as u32,
            flags: flag,
            width: cols as u32,
            height: rows as u32,
            pitch_x_um: 3.2592,
            pitch_y_um: 3.2592,
            origin_x_um: 10.0,
            origin_y_um: 20.0,
            z_offset_um: 500.0,
            ..Default::default()
        },
        heights,
    }
}

/// The node's path (mesh_to_files) writes the same STL and .npy and reports the same
/// statistics as the in-memory path, for the adaptive mesh (streamed) and the grid one.
#[test]
fn mesh_to_files_matches_the_in_memory_job() {
    let (rows, cols) = (140, 150);
    let z = surface(rows, cols, true);
    for text in [
        "",
        "format = \"ascii\"\nunits = \"m\"",
        "kind = \"sheet\"\nmissing = \"holes\"",
        "method = \"grid\"",
        "target = \"liggghts\"\nmax_triangles = 4000",
        "target = \"liggghts\"\nmethod = \"grid\"\nmax_triangles = 4000",
    ] {
        let config: MesherConfig = toml::from_str(text).unwrap();
        let settings = config.settings().unwrap();
        let run = |job: &mut MeshJob| {
            job.accept("surface", frame(rows, cols, flags::FINAL, z.clone()).view());
            let eos = HeightMap {
                header: FrameHeader::end_of_scan(1, 9, 0, 0),
                heights: Vec::new(),
            };
            assert!(job.accept("surface", eos.view()));
        };
        let mut a = MeshJob::new(settings.clone());
        run(&mut a);
        let m = a.mesh().unwrap();
        let mut stl_a = Vec::new();
        m.write_stl(&mut stl_a, settings.format).unwrap();

        let dir = tempfile::tempdir().unwrap();
        let (stl, npy) = (dir.path().join("s.stl"), dir.path().join("r.npy"));
        let mut b = MeshJob::new(settings.clone());
        run(&mut b);
        let files = b.mesh_to_files(&stl, &npy).unwrap();
        // The engines' regular grids are made in memory; LIGGGHTS' tolerance mesh streams.
        let grid_target = text.contains("target") && text.contains("grid");
        assert_eq!(files.streamed, !grid_target, "{text}");
        assert!(std::fs::read(&stl).unwrap() == stl_a, "{text}: STL differs");
        // Compared as written (NaN as null).
        // The time meshing took and the file's name are the streamed record's alone.
        assert!(files.summary.mesh_s.is_some_and(|s| s >= 0.0), "{text}");
        assert_eq!(files.summary.file, "s.stl");
        let streamed = surfstream_core::record::MeshReport {
            mesh_s: None,
            file: String::new(),
            ..files.summary.clone()
        };
        assert_eq!(
            record::to_value(&streamed).unwrap(),
            record::to_value(&m.summary(&settings).unwrap()).unwrap(),
            "{text}"
        );
        assert_eq!(files.check.watertight, m.check.watertight, "{text}");
        let back = surfstream_io::npy::read_npy_f64(&npy).unwrap();
        assert_eq!((back.rows, back.cols), (rows, cols));
        let want: Vec<u64> = m
            .resampled_um
            .values()
            .iter()
            .map(|v| v.to_bits())
            .collect();
        let got: Vec<u64> = back.data.iter().map(|v| v.to_bits()).collect();
        assert_eq!(got, want, "{text}");
        // Only the outputs (the STL, the re-sampled mesh and its pitch sidecar): the spill
        // file was unnamed.
        let mut names: Vec<String> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        assert_eq!(names, ["r.npy", "r.npy.json", "s.stl"], "{text}");
        if text.is_empty() {
            assert_eq!(StlFormat::Binary, settings.format);
        }
    }
}
