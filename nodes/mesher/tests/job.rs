//! The mesher's job without a node: settings from graph parameters, wiring checked against the
//! surface choice, live frames skipped, meshing only when every input has ended, datum +
//! roughness summed, and the mesh + fidelity report it produces.

use surfstream_core::frame::{flags, FrameHeader, FrameKind, HeightMap};
use surfstream_core::record;
use surfstream_mesher::{MeshJob, MesherConfig, StlFormat, SurfaceChoice};

const ROWS: usize = 24;
const COLS: usize = 40;

fn config(text: &str) -> MesherConfig {
    toml::from_str(text).expect("test config")
}

fn frame(kind: FrameKind, flag: u32, heights: Vec<f32>) -> HeightMap {
    HeightMap {
        header: FrameHeader {
            kind: kind as u32,
            flags: flag,
            width: COLS as u32,
            height: ROWS as u32,
            pitch_x_um: 2.0,
            pitch_y_um: 3.0,
            origin_x_um: 10.0,
            origin_y_um: 20.0,
            z_offset_um: 500.0,
            ..Default::default()
        },
        heights,
    }
}

fn wavy(scale: f32) -> Vec<f32> {
    (0..ROWS * COLS)
        .map(|k| {
            let (i, j) = ((k / COLS) as f32, (k % COLS) as f32);
            scale * ((0.4 * j).sin() + 0.3 * (0.5 * i).cos())
        })
        .collect()
}

fn eos() -> HeightMap {
    HeightMap {
        header: FrameHeader::end_of_scan(1, 9, 0, 0),
        heights: Vec::new(),
    }
}

#[test]
fn settings_and_wiring_are_checked() {
    // The default: the full-resolution panorama, meshed to the default tolerance.
    let s = config("").settings().unwrap();
    assert_eq!(s.surface, SurfaceChoice::Panorama);
    assert_eq!(s.format, StlFormat::Binary);
    assert!(s.adaptive.is_some());
    let t = s.tolerance.unwrap();
    assert_eq!(t.tolerance, surfstream_mesher::tolerance::DEFAULT_TOLERANCE);
    // A fixed bound replaces the tolerance; the pooled map stays a choice.
    let fixed = config(
        "epsilon_sq_fraction = 0.05
surface = \"pooled\"",
    )
    .settings()
    .unwrap();
    assert!(fixed.tolerance.is_none());
    assert_eq!(fixed.surface, SurfaceChoice::Pooled);
    let t = config("tolerance = \"sa=2,sz=4\"\nregion_px = 64")
        .settings()
        .unwrap()
        .tolerance
        .unwrap();
    assert_eq!(
        (t.tolerance.sa_pct, t.tolerance.sz_pct, t.region_px),
        (2.0, 4.0, Some(64))
    );
    assert!(config("method = \"grid\"")
        .settings()
        .unwrap()
        .adaptive
        .is_none());
    // LIGGGHTS: the model from the tolerance with its angles bounded, or its regular grid.
    let lig = config("target = \"liggghts\"\ntolerance = \"sa=2\"")
        .settings()
        .unwrap();
    let t = lig.tolerance.unwrap();
    assert_eq!((t.tolerance.sa_pct, t.min_angle_deg), (2.0, Some(1.0)));
    assert_eq!(
        lig.adaptive.unwrap().kind,
        surfstream_mesher::MeshKind::Sheet
    );
    let grid = config("target = \"liggghts\"\nmethod = \"grid\"")
        .settings()
        .unwrap();
    assert!(grid.tolerance.is_none() && grid.adaptive.is_none());
    assert_eq!(
        grid.target.unwrap().method,
        surfstream_mesher::TargetMethod::Grid
    );
    // A bad choice is refused as the graph file is read, with the allowed values named.
    for (bad, says) in [
        ("format = \"obj\"", "expected `binary` or `ascii`"),
        ("method = \"poisson\"", "expected `adaptive` or `grid`"),
        ("units = \"furlong\"", "`m`, `mm`, `um`"),
        ("model_method = \"fast\"", "expected `balanced` or `greedy`"),
    ] {
        let table: toml::Table = toml::from_str(bad).unwrap();
        let e = surfstream_runtime::graph::params_from_table::<MesherConfig>(&table)
            .err()
            .unwrap();
        let key = bad.split(' ').next().unwrap();
        assert!(e.starts_with(key) && e.contains(says), "{bad}: {e}");
    }
    for (bad, says) in [
        ("epsilon_um = 0.1\nepsilon_sq_fraction = 0.1", "not both"),
        ("epsilon_um = 0.1\ntolerance = \"sa=1\"", "not both"),
        ("method = \"grid\"\ntolerance = \"sa=1\"", "needs method"),
        ("region_px = 4", "region_px = 4"),
        (
            "target = \"liggghts\"\nepsilon_um = 0.1",
            "needs the model from a tolerance",
        ),
        ("target = \"yade\"\ntolerance = \"sa=1\"", "regular grid"),
    ] {
        let e = config(bad).settings().unwrap_err();
        assert!(e.contains(says), "{bad}: {e}");
    }
    let both = SurfaceChoice::DatumPlusRoughness;
    assert!(both.check_wiring(&["datum", "roughness"]).is_ok());
    assert!(both
        .check_wiring(&["datum"])
        .unwrap_err()
        .contains("needs the input 'roughness'"));
    assert!(SurfaceChoice::Datum
        .check_wiring(&["datum", "surface"])
        .unwrap_err()
        .contains("input 'surface' is wired but"));
    // The panorama may take its measured roughness (the roughness judgement's reference);
    // no other surface may.
    assert!(SurfaceChoice::Panorama
        .check_wiring(&["surface", "roughness"])
        .is_ok());
    assert!(SurfaceChoice::Pooled
        .check_wiring(&["surface", "roughness"])
        .unwrap_err()
        .contains("input 'roughness' is wired but"));
}

#[test]
fn meshes_the_sum_once_both_inputs_have_ended() {
    let settings = config(
        "surface = \"datum+roughness\"\nepsilon_um = 0.02\nunits = \"um\"\nformat = \"ascii\"",
    )
    .settings()
    .unwrap();
    let mut job = MeshJob::new(settings);
    let (datum, roughness) = (wavy(1.0), wavy(0.1));
    // A live frame is counted and skipped.
    assert!(!job.accept("datum", frame(FrameKind::Datum, 0, datum.clone()).view()));
    assert!(!job.accept(
        "datum",
        frame(FrameKind::Datum, flags::FINAL, datum.clone()).view()
    ));
    assert!(!job.accept(
        "roughness",
        frame(FrameKind::Roughness, flags::FINAL, roughness.clone()).view()
    ));
    assert!(!job.accept("datum", eos().view()));
    assert!(job.accept("roughness", eos().view()));
    assert_eq!(job.live_frames_skipped(), 1);

    let m = job.mesh().unwrap();
    assert!(m.check.watertight);
    assert_eq!((m.resampled_um.rows(), m.resampled_um.cols()), (ROWS, COLS));
    // The resampled mesh is absolute and within the bound of datum + roughness.
    for ((&r, &d), &q) in m.resampled_um.values().iter().zip(&datum).zip(&roughness) {
        let sum = 500.0 + f64::from(d + q);
        assert!((r - sum).abs() <= 0.02 + 1e-4, "{r} vs {sum}");
    }
    // The report as it is written (a JSON object).
    let summary = record::to_value(&m.summary(job.settings()).unwrap()).unwrap();
    assert_eq!(summary["method"], "adaptive");
    assert_eq!(summary["surface"], "datum+roughness");
    assert_eq!(summary["grid_px"], serde_json::json!([COLS, ROWS]));
    assert_eq!(summary["format"], "ascii");
    assert_eq!(summary["fidelity"]["bound_met"], true);
    let mut stl = Vec::new();
    m.write_stl(&mut stl, StlFormat::Ascii).unwrap();
    assert!(stl.starts_with(b"solid"));
    // The frames were taken: a second mesh has nothing to mesh.
    assert!(job.mesh().is_err());
}

/// With its measured roughness wired, the panorama's mesh waits for both ends of scan and
/// every judged region reports the roughness the mesh carries.
#[test]
fn a_wired_roughness_is_awaited_and_judged() {
    let mut job = MeshJob::new(config("").settings().unwrap()).with_roughness_reference();
    let (surface, roughness) = (wavy(1.0), wavy(0.1));
    job.accept(
        "surface",
        frame(FrameKind::Panorama, flags::FINAL, surface).view(),
    );
    assert!(
        !job.accept("surface", eos().view()),
        "the roughness has not ended"
    );
    job.accept(
        "roughness",
        frame(FrameKind::Roughness, flags::FINAL, roughness).view(),
    );
    assert!(job.accept("roughness", eos().view()));
    let m = job.mesh().unwrap();
    let summary = record::to_value(&m.summary(job.settings()).unwrap()).unwrap();
    let report = &summary["tolerance"];
    let fits = report["region_fits"].as_array().unwrap();
    assert!(!fits.is_empty());
    assert!(
        fits.iter().all(|f| f["roughness_deviation_pct"].is_array()),
        "{report}"
    );
    assert_eq!(report["tolerance"]["roughness_pct"], 5.0);
}

#[test]
fn grid_method_resamples_to_the_samples_themselves() {
    let mut job = MeshJob::new(config("method = \"grid\"").settings().unwrap());
    let h = wavy(1.0);
    job.accept(
        "surface",
        frame(FrameKind::Pooled, flags::FINAL, h.clone()).view(),
    );
    assert!(job.accept("surface", eos().view()));
    let m = job.mesh().unwrap();
    assert!(m.adaptive.is_none());
    assert_eq!(m.summary(job.settings()).unwrap().method, "grid");
    for (&r, &z) in m.resampled_um.values().iter().zip(&h) {
        assert_eq!(r, f64::from(z) + 500.0);
    }
}

#[test]
fn end_of_scan_without_a_final_frame_is_an_error() {
    let mut job = MeshJob::new(config("").settings().unwrap());
    assert!(job.accept("surface", eos().view()));
    let e = job.mesh().err().unwrap().to_string();
    assert!(e.contains("without a final 'surface' frame"), "{e}");
}

/// `level = true`: the node removes the least-squares plane before meshing, as
/// `params --level` and `mesh --level`; the record says so and the mesh is of the levelled
/// surface (a tilted wave meshes with far fewer triangles than its tilt needs).
#[test]
fn level_removes_the_plane_and_the_record_says_so() {
    let tilted: Vec<f32> = wavy(0.05)
        .iter()
        .enumerate()
        .map(|(k, &z)| z + 0.4 * (k % COLS) as f32 - 0.3 * (k / COLS) as f32)
        .collect();
    let run = |text: &str, name: &str| {
        let mut job = MeshJob::new(config(text).settings().unwrap());
        job.accept(
            "surface",
            frame(FrameKind::Panorama, flags::FINAL, tilted.clone()).view(),
        );
        assert!(job.accept("surface", eos().view()));
        let dir = tempfile::tempdir().unwrap();
        let stl = dir.path().join(format!("{name}.stl"));
        let npy = dir.path().join("r.npy");
        let files = job.mesh_to_files(&stl, &npy).unwrap();
        let resampled = surfstream_io::npy::read_npy_f64(&npy).unwrap().data;
        let (lo, hi) = resampled
            .iter()
            .fold((f64::MAX, f64::MIN), |(a, b), &z| (a.min(z), b.max(z)));
        (record::to_value(&files.summary).unwrap(), hi - lo)
    };
    let (flat, flat_range_um) = run("level = true\nepsilon_um = 0.01", "flat");
    let (raw, raw_range_um) = run("epsilon_um = 0.01", "raw");
    assert_eq!(flat["form_removed"], "least-squares plane", "{flat:#}");
    assert!(raw.get("form_removed").is_none(), "{raw:#}");
    // The plane removed: the meshed heights span the wave (0.05 x 1.3 um peak to peak at
    // most), not the tilt's 22.5 um.
    assert!(raw_range_um > 20.0, "{raw_range_um}");
    assert!(flat_range_um < 0.2, "{flat_range_um}");
    assert_eq!(flat["fidelity"]["bound_met"], true);
}

/// The fusion's tile placements (panorama.tiles.json) for the test frame's grid: two tiles of
/// 24 x 24 px, the second 20 px to the right (its footprint clipped to the map's 40 columns).
fn panorama_tiles(origin_x_um: f64) -> record::PanoramaTiles {
    let tile = |index: u32, x_um: f64| record::PlacedTile {
        index,
        x_um,
        y_um: 20.0,
        width_px: 24,
        height_px: 24,
    };
    record::PanoramaTiles {
        panorama: record::PanoramaSummary {
            width_px: COLS,
            height_px: ROWS,
            origin_x_um,
            origin_y_um: 20.0,
            pitch_x_um: 2.0,
            pitch_y_um: 3.0,
            z_offset_um: 500.0,
            invalid_px: 0,
        },
        tiles: vec![tile(0, 10.0), tile(1, 10.0 + 20.0 * 2.0)],
    }
}

/// Meshes the test panorama with the tile placements `tiles` (as text) in the out dir.
fn mesh_with_tiles(tiles: Option<&str>) -> anyhow::Result<serde_json::Value> {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join(record::PANORAMA_TILES);
    if let Some(text) = tiles {
        std::fs::write(&path, text).unwrap();
    }
    let mut job =
        MeshJob::new(config("region_px = 16").settings().unwrap()).with_tile_footprints(path);
    job.accept(
        "surface",
        frame(FrameKind::Panorama, flags::FINAL, wavy(1.0)).view(),
    );
    assert!(job.accept("surface", eos().view()));
    let files = job.mesh_to_files(
        &dir.path().join("surface.stl"),
        &dir.path().join("mesh_resampled.npy"),
    )?;
    Ok(record::to_value(&files.summary.tolerance).unwrap())
}

/// Table 6's tile regions from the fusion's tile placements are judged as regions, named as
/// Table 6 names them; on another grid, or without the file, the windows alone.
#[test]
fn the_tile_footprints_from_the_fusion_are_judged_as_regions() {
    let text = serde_json::to_string(&panorama_tiles(10.0)).unwrap();
    let t = mesh_with_tiles(Some(&text)).unwrap();
    assert_eq!(t["met"], true, "{t}");
    assert_eq!(t["footprints"], 2, "{t}");
    let names: Vec<&str> = (t["region_fits"].as_array().unwrap().iter())
        .map(|r| r["region"].as_str().unwrap())
        .collect();
    assert!(names.contains(&"S1") && names.contains(&"S2"), "{names:?}");
    // The second footprint, clipped to the map: 24 x 20 px (rows x cols) at col 20.
    let s2 = (t["region_fits"].as_array().unwrap().iter())
        .find(|r| r["region"] == "S2")
        .unwrap();
    assert_eq!(s2["samples"], 24 * 20);
    let windows_only = t["regions"].as_u64().unwrap() - 2;

    // Another grid (the panorama placed elsewhere) or no file: the windows alone.
    let other = serde_json::to_string(&panorama_tiles(12.0)).unwrap();
    for t in [
        mesh_with_tiles(Some(&other)).unwrap(),
        mesh_with_tiles(None).unwrap(),
    ] {
        // (0 is not written: the record of a search that judged windows only.)
        assert!(t.get("footprints").is_none(), "{t}");
        assert_eq!(t["regions"].as_u64(), Some(windows_only), "{t}");
    }
    // A file that is not the fusion's placements is an error naming it.
    let e = mesh_with_tiles(Some("{\"tiles\": 3}")).unwrap_err();
    let e = format!("{e:#}");
    assert!(
        e.contains(record::PANORAMA_TILES) && e.contains("tile placements"),
        "{e}"
    );
}
