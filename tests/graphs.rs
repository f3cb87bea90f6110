//! Real graphs, really started: the demo as processes and as threads, record -> replay,
//! a scan directory, a node killed mid-run, two launches at once.

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value;
use surfstream_e2e::*;

/// Tile positions relative to tile 0 against the truth: max error in px.
fn max_position_error_px(run: &Value, truth: &Value) -> f64 {
    let pitch = truth["pixel_pitch_um"]["x"].as_f64().unwrap();
    let tiles = run["tiles"].as_array().unwrap();
    let t_tiles = truth["tiles"].as_array().unwrap();
    assert_eq!(tiles.len(), t_tiles.len());
    let pos = |t: &Value| [t["x_um"].as_f64().unwrap(), t["y_um"].as_f64().unwrap()];
    let tru = |i: usize| {
        let t = &t_tiles[i]["true_origin_px"];
        [t[0].as_f64().unwrap(), t[1].as_f64().unwrap()]
    };
    let (p0, t0) = (pos(&tiles[0]), tru(0));
    let mut worst: f64 = 0.0;
    for (i, t) in tiles.iter().enumerate() {
        assert_eq!(t["index"].as_u64(), Some(i as u64));
        let p = pos(t);
        let tr = tru(i);
        for k in 0..2 {
            let err = ((p[k] - p0[k]) / pitch - (tr[k] - t0[k])).abs();
            worst = worst.max(err);
        }
    }
    worst
}

/// Bilinear sample of a row-major map at fractional (x, y) px.
fn bilinear(map: &[f32], w: usize, h: usize, x: f64, y: f64) -> Option<f64> {
    let (x0, y0) = (x.floor(), y.floor());
    if x0 < 0.0 || y0 < 0.0 || x0 as usize + 1 >= w || y0 as usize + 1 >= h {
        return None;
    }
    let (fx, fy) = (x - x0, y - y0);
    let (i, j) = (y0 as usize, x0 as usize);
    let v = |r: usize, c: usize| map[r * w + c] as f64;
    Some(
        v(i, j) * (1.0 - fx) * (1.0 - fy)
            + v(i, j + 1) * fx * (1.0 - fy)
            + v(i + 1, j) * (1.0 - fx) * fy
            + v(i + 1, j + 1) * fx * fy,
    )
}

/// RMS of panorama - specimen after removing the best-fit plane of the difference (tile 0's
/// own piston and tilt are the panorama's reference).
fn height_rms_vs_specimen(out: &Path, run: &Value, truth: &Value) -> (f64, usize) {
    let pano = surfstream_io::npy::read_npy(out.join("panorama.npy")).unwrap();
    let spec = surfstream_io::npy::read_npy(out.join("specimen.npy")).unwrap();
    let pitch = truth["pixel_pitch_um"]["x"].as_f64().unwrap();
    // The specimen's pitch travels with it (specimen.npy.json), equal to the truth's.
    let g = surfstream_io::sidecar::read_sidecar(&out.join("specimen.npy"))
        .unwrap()
        .expect("specimen.npy.json");
    assert_eq!((g.pitch_x_um, g.pitch_y_um), (pitch, pitch));
    let p = &run["stages"]["fusion"]["panorama"];
    let (ox, oy) = (
        p["origin_x_um"].as_f64().unwrap(),
        p["origin_y_um"].as_f64().unwrap(),
    );
    // The panorama's frame is tile 0's stage position; the specimen's is the truth.
    let t0 = &truth["tiles"][0];
    let dx = t0["true_origin_px"][0].as_f64().unwrap()
        - t0["stage_position_um"][0].as_f64().unwrap() / pitch;
    let dy = t0["true_origin_px"][1].as_f64().unwrap()
        - t0["stage_position_um"][1].as_f64().unwrap() / pitch;
    let mut rows = Vec::new();
    // Skip a 4 px border (bilinear sampling and resampling at canvas edges).
    for i in (4..pano.rows.saturating_sub(4)).step_by(3) {
        for j in (4..pano.cols.saturating_sub(4)).step_by(3) {
            let z = pano.data[i * pano.cols + j];
            if z.is_nan() {
                continue;
            }
            let sx = ox / pitch + j as f64 + dx;
            let sy = oy / pitch + i as f64 + dy;
            if let Some(s) = bilinear(&spec.data, spec.cols, spec.rows, sx, sy) {
                rows.push((j as f64, i as f64, z as f64 - s));
            }
        }
    }
    // Least-squares plane of the difference: normal equations, 3x3.
    let mut a = [[0.0f64; 3]; 3];
    let mut b = [0.0f64; 3];
    for (x, y, d) in &rows {
        let v = [1.0, *x, *y];
        for r in 0..3 {
            for c in 0..3 {
                a[r][c] += v[r] * v[c];
            }
            b[r] += v[r] * d;
        }
    }
    let coef = solve3(a, b);
    let n = rows.len();
    let ss: f64 = rows
        .iter()
        .map(|(x, y, d)| (d - coef[0] - coef[1] * x - coef[2] * y).powi(2))
        .sum();
    ((ss / n as f64).sqrt(), n)
}

#[allow(clippy::needless_range_loop)] // Gaussian elimination reads best with indices.
fn solve3(mut a: [[f64; 3]; 3], mut b: [f64; 3]) -> [f64; 3] {
    for k in 0..3 {
        let p = (k..3)
            .max_by(|&i, &j| a[i][k].abs().total_cmp(&a[j][k].abs()))
            .unwrap();
        a.swap(k, p);
        b.swap(k, p);
        for i in k + 1..3 {
            let f = a[i][k] / a[k][k];
            for j in k..3 {
                a[i][j] -= f * a[k][j];
            }
            b[i] -= f * b[k];
        }
    }
    let mut x = [0.0; 3];
    for k in (0..3).rev() {
        x[k] = (b[k] - (k + 1..3).map(|j| a[k][j] * x[j]).sum::<f64>()) / a[k][k];
    }
    x
}

fn check_python_reads(recording: &Path, stl: &Path) {
    let script = r#"
import sys, json, base64
from mcap.reader import make_reader
counts, schemas = {}, set()
with open(sys.argv[1], "rb") as f:
    reader = make_reader(f)
    for schema, channel, message in reader.iter_messages():
        counts[channel.topic] = counts.get(channel.topic, 0) + 1
        schemas.add(schema.name)
        if channel.topic == "stage/tiles" and counts[channel.topic] == 1:
            # Self-describing: JSON Schema in the file, JSON messages, cells in base64.
            assert schema.encoding == "jsonschema", schema.encoding
            assert json.loads(schema.data)["properties"]["data"]["contentEncoding"] == "base64"
            grid = json.loads(message.data)
            payload = len(base64.b64decode(grid["data"]))
            assert payload == 1024 * 1024 * 4 == grid["row_stride"] * 1024, payload
assert counts.get("stage/tiles") == 5, counts
# 4 streamed + 4 FINAL (global solve) + end of scan
assert counts.get("matcher/registrations") == 9, counts
assert "foxglove.Grid" in schemas and "surfstream.TileRegistration" in schemas, schemas
import trimesh
m = trimesh.load(sys.argv[2])
assert m.is_watertight, "not watertight"
assert m.is_winding_consistent, "winding"
assert m.volume > 0, m.volume
print("python ok", counts, len(m.faces))
"#;
    let out = run({
        let mut c = Command::new(python());
        c.arg("-c").arg(script).arg(recording).arg(stl);
        c
    });
    assert!(
        out.status.success(),
        "python check failed:\n{}",
        stderr(&out)
    );
}

#[test]
fn demo_launch_run_and_replay_agree_and_match_the_truth() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b, c) = (
        dir.path().join("launch"),
        dir.path().join("run"),
        dir.path().join("replay"),
    );

    // 1. The demo graph as processes, exactly as the README runs it (plus the specimen).
    let out = run({
        let mut cmd = surfstream();
        cmd.args([
            "launch",
            "launch/graphs/demo.toml",
            "--set",
            "stage.save_specimen=true",
            "--out",
        ])
        .arg(&a);
        cmd
    });
    assert!(
        out.status.success(),
        "demo launch failed:\n{}",
        stderr(&out)
    );
    let run_json = read_json(&a.join("run.json"));
    let truth = read_json(&a.join("truth.json"));
    typed_records_round_trip(&a);

    // Every tile reached every subscriber: 4 tiles + end of scan, to matcher, fusion, recorder.
    let msgs = &run_json["messages"];
    assert_eq!(msgs["stage"]["sent"]["tiles"], 5);
    assert_eq!(msgs["stage"]["deliveries"]["tiles"], 15);
    for node in ["matcher", "fusion", "recorder"] {
        assert_eq!(msgs[node]["received"]["tiles"], 5, "{node}");
    }
    // Registrations: 4 streamed, 4 FINAL from the global solve, end of scan.
    assert_eq!(msgs["fusion"]["received"]["registrations"], 9);
    assert_eq!(msgs["recorder"]["received"]["registrations"], 9);
    assert_eq!(
        msgs["wavelet"]["received"]["panorama"],
        msgs["fusion"]["sent"]["panorama"]
    );
    // The mesher meshes the full-resolution panorama (the pooled map is an option).
    assert_eq!(
        msgs["mesher"]["received"]["surface"],
        msgs["fusion"]["sent"]["panorama"]
    );

    // Tile positions within 0.5 px of the truth, all registered.
    let err = max_position_error_px(&run_json, &truth);
    eprintln!("max tile position error: {err:.3} px");
    assert!(err < 0.5, "tile position error {err} px");
    for t in run_json["tiles"].as_array().unwrap() {
        assert_eq!(t["placed_by"], "registration", "{t}");
    }
    // Heights within the noise (0.02 um) plus sub-pixel resampling of a rough surface.
    let (rms, n) = height_rms_vs_specimen(&a, &run_json, &truth);
    eprintln!("panorama vs specimen: rms {rms:.4} um over {n} samples");
    assert!(n > 100_000 && rms < 0.1, "height rms {rms} um");

    // Table 6 judges every model stage against the measurement, the mesh included.
    let stages = &run_json["deviation"]["stages"];
    for stage in ["roughness (mesh - datum)", "pooled", "mesh"] {
        let sa = &stages[stage]["regions"]["panorama"]["model"]["Sa"];
        assert!(
            sa.as_f64().is_some(),
            "deviation stage {stage}: {}",
            stages[stage]
        );
    }
    // The model from the default tolerance: met at the measured points in every tile's
    // footprint, on the panorama grid, at well under 0.5 surface triangles per measured pixel;
    // the pooled map is reported but not judged (the STL is not made from it).
    let mesh = &stages["mesh"];
    assert_eq!(mesh["grid"]["cell_px"], 1, "{mesh}");
    assert_eq!(mesh["pass"], true, "{mesh}");
    assert!(mesh["regions"]["S1"]["residual_rms_pct_of_sq"]
        .as_f64()
        .is_some());
    assert_eq!(stages["pooled"]["judged"], false);
    assert_eq!(run_json["deviation"]["pass"], true);
    let tolerance = &run_json["stages"]["mesher"]["tolerance"];
    assert_eq!(tolerance["met"], true, "{tolerance}");
    assert!(tolerance["triangles_per_measured_px"].as_f64().unwrap() <= 0.5);
    let curve = tolerance["curve"].as_array().unwrap();
    assert!(curve.len() >= 6 && curve.iter().filter(|c| c["chosen"] == true).count() == 1);

    // Latency of every stage is known.
    let lat = &run_json["latency_ms"];
    assert_eq!(lat["tile_to_registration"]["n"], 4);
    assert_eq!(lat["tile_to_panorama"]["n"], 4);
    assert!(
        lat["final_frames"]["last_tile_to_mesh"]["max"]
            .as_f64()
            .unwrap()
            > 0.0
    );
    assert_eq!(lat["final_frames"]["last_tile_to_final_panorama"]["n"], 1);
    assert!(lat["hops"]["registration_to_panorama"]["p50"]
        .as_f64()
        .is_some());

    // 2. The same graph in one process: bit-identical outputs.
    let out = run({
        let mut cmd = surfstream();
        cmd.args([
            "run",
            "launch/graphs/demo.toml",
            "--set",
            "stage.pacing=fast",
            "--out",
        ])
        .arg(&b);
        cmd
    });
    assert!(out.status.success(), "demo run failed:\n{}", stderr(&out));
    assert_same_outputs(&a, &b);

    // 3. The recording opens in Python's mcap reader; the STL in trimesh.
    check_python_reads(&a.join("recording.mcap"), &a.join("surface.stl"));

    // 4. Record -> replay reproduces identical outputs.
    let rec = a.join("recording.mcap");
    let out = run({
        let mut cmd = surfstream();
        cmd.args(["launch", "launch/graphs/replay.toml", "--set"])
            .arg(format!("stage.path={:?}", rec.to_str().unwrap()))
            .args(["--set", "stage.pacing=fast", "--out"])
            .arg(&c);
        cmd
    });
    assert!(
        out.status.success(),
        "replay launch failed:\n{}",
        stderr(&out)
    );
    assert_same_outputs(&a, &c);

    // Nothing left in shared memory by either launch.
    let domain = domain_of(&stderr(&out)).expect("launch names its domain");
    assert!(
        shm_leftovers(&domain).is_empty(),
        "{:?}",
        shm_leftovers(&domain)
    );
}

/// Issue 33: the demo's tolerance search judges Table 6's tile regions (from the fusion's
/// panorama.tiles.json) beside its windows, under Table 6's names and on the same rectangles:
/// the mesher's Sa, Sq, Sz and residual per tile region are Table 6's. The model line still
/// says met, Table 6 PASS.
#[test]
fn the_demo_models_search_judges_table_6s_tile_regions() {
    let dir = tempfile::tempdir().unwrap();
    let out_dir = dir.path().join("out");
    let out = run({
        let mut cmd = surfstream();
        cmd.args([
            "run",
            "launch/graphs/demo.toml",
            "--set",
            "stage.pacing=fast",
            "--out",
        ])
        .arg(&out_dir);
        cmd
    });
    assert!(out.status.success(), "demo run failed:\n{}", stderr(&out));
    let stdout = String::from_utf8_lossy(&out.stdout);
    let line = |name: &str| {
        (stdout.lines())
            .find(|l| l.trim_start().starts_with(name))
            .unwrap_or_else(|| panic!("no {name} line:\n{stdout}"))
            .to_string()
    };
    assert!(line("model").contains("per region: met at"), "{stdout}");
    assert!(line("deviation").contains("PASS"), "{stdout}");
    assert!(stdout.contains("verdict: PASS"), "{stdout}");

    let run_json = read_json(&out_dir.join("run.json"));
    let t = &run_json["stages"]["mesher"]["tolerance"];
    assert_eq!(t["footprints"], 4, "{t}");
    let fits: Vec<&Value> = t["region_fits"].as_array().unwrap().iter().collect();
    assert_eq!(t["regions"].as_u64(), Some(fits.len() as u64));
    let table6 = &run_json["deviation"]["stages"]["mesh"]["regions"];
    let tiles: Vec<&String> = (table6.as_object().unwrap().keys())
        .filter(|k| k.starts_with('S'))
        .collect();
    assert_eq!(tiles.len(), 4, "{table6}");
    for name in tiles {
        let fit = (fits.iter())
            .find(|f| f["region"] == name.as_str())
            .unwrap_or_else(|| panic!("{name} not judged by the search: {t}"));
        let r = &table6[name.as_str()];
        for (k, p) in ["Sa", "Sq", "Sz"].iter().enumerate() {
            let (a, b) = (
                fit["deviation_pct"][k].as_f64().unwrap(),
                r["deviation_pct"][p].as_f64().unwrap(),
            );
            assert!(
                (a - b).abs() < 0.01,
                "{name} {p}: search {a} %, Table 6 {b} %"
            );
        }
        let (a, b) = (
            fit["residual_pct_of_sq"].as_f64().unwrap(),
            r["residual_rms_pct_of_sq"].as_f64().unwrap(),
        );
        assert!(
            (a - b).abs() < 0.01,
            "{name} residual: search {a} %, Table 6 {b} %"
        );
    }
}

/// A simulated scan directory (`rows` x `cols` tiles of `tile_px`) in a fresh temp dir, whose
/// tiles `prepare` may rewrite, stitched by `surfstream stitch ARGS`; returns the temp dir
/// (holding `scan/` and `out/`) and run.json.
fn stitch_simulated_scan(
    rows: usize,
    cols: usize,
    tile_px: usize,
    args: &[&str],
    prepare: impl FnOnce(&Path),
) -> (tempfile::TempDir, Value) {
    let dir = tempfile::tempdir().unwrap();
    let scan = dir.path().join("scan");
    std::fs::create_dir(&scan).unwrap();
    write_scan_dir(&scan, rows, cols, tile_px, Some("um"));
    prepare(&scan);
    let out_dir = dir.path().join("out");
    let out = run({
        let mut cmd = surfstream();
        cmd.arg("stitch")
            .arg(&scan)
            .arg("--out")
            .arg(&out_dir)
            .args(args);
        cmd
    });
    assert!(
        out.status.success(),
        "stitch {args:?} failed:\n{}",
        stderr(&out)
    );
    let run_json = read_json(&out_dir.join("run.json"));
    (dir, run_json)
}

#[test]
fn stitch_scans_a_scan_directory() {
    let (dir, run_json) = stitch_simulated_scan(2, 3, 256, &[], |_| {});
    let (scan, out_dir) = (dir.path().join("scan"), dir.path().join("out"));
    let truth = read_json(&scan.join("ground_truth.json"));
    let err = max_position_error_px(&run_json, &truth);
    eprintln!("max tile position error: {err:.3} px");
    assert!(err < 0.5, "tile position error {err} px");
    for f in OUTPUTS {
        assert!(out_dir.join(f).exists(), "{f} missing");
    }
    assert_eq!(
        run_json["tiles"][4]["stage_x_um"],
        read_json(&scan.join("ground_truth.json"))["tiles"][4]["stage_position_um"][0]
    );
}

/// A folder of tiles without scan.toml: `stitch DIR --grid 2x3 --overlap 20% --serpentine`
/// infers the manifest (written to OUT), places every tile within half a pixel of the truth,
/// and a grid that disagrees with the folder is a clear error.
#[test]
fn stitch_infers_the_scan_from_a_folder_and_the_grid() {
    let dir = tempfile::tempdir().unwrap();
    let scan = dir.path().join("scan");
    std::fs::create_dir(&scan).unwrap();
    write_scan_dir(&scan, 2, 3, 256, Some("um"));
    std::fs::remove_file(scan.join("scan.toml")).unwrap();
    let truth = read_json(&scan.join("ground_truth.json"));
    let pitch = truth["pixel_pitch_um"]["x"].as_f64().unwrap().to_string();
    let out_dir = dir.path().join("out");
    let stitch = |grid: &str| {
        let mut cmd = surfstream();
        cmd.arg("stitch")
            .arg(&scan)
            .args(["--grid", grid, "--overlap", "20%", "--serpentine"])
            .args(["--pitch-um", &pitch, "--out"])
            .arg(&out_dir);
        run(cmd)
    };
    let out = stitch("2x3");
    assert!(out.status.success(), "{}", stderr(&out));
    let run_json = read_json(&out_dir.join("run.json"));
    let err = max_position_error_px(&run_json, &truth);
    assert!(err < 0.5, "tile position error {err} px");
    let manifest = std::fs::read_to_string(out_dir.join("scan.toml")).unwrap();
    assert!(
        manifest.contains("rows = 2") && manifest.contains("cols = 3"),
        "{manifest}"
    );
    // The serpentine: the 4th tile acquired (index 3) is the last column of row 1.
    assert_eq!(run_json["tiles"][3]["row"], 1);
    assert_eq!(run_json["tiles"][3]["col"], 2);

    let out = stitch("3x3");
    assert!(!out.status.success());
    let e = stderr(&out);
    assert!(
        e.contains("6 tile files, but --grid 3x3 (rows x cols) needs 9"),
        "{e}"
    );
}

/// The paper's Harris + NCC path through a real graph: `stitch --method harris` on a scan whose
/// `ground_truth.json` lies beside `scan.toml` scores every pair's matches (r, eq. 2; MAP, eq. 3)
/// in run.json, and the tiles still land within half a pixel of the truth.
#[test]
fn stitch_with_harris_scores_matches_against_the_truth() {
    let (dir, run_json) = stitch_simulated_scan(2, 2, 256, &["--method", "harris"], |_| {});
    let truth = read_json(&dir.path().join("scan/ground_truth.json"));
    let err = max_position_error_px(&run_json, &truth);
    assert!(err < 0.5, "tile position error {err} px");
    let pairs = run_json["pairs"].as_array().expect("run.json pairs");
    assert_eq!(pairs.len(), 4, "a 2 x 2 serpentine has 4 neighbour pairs");
    for p in pairs {
        let f = &p["features"];
        assert_eq!(f["method"], "harris", "{p}");
        let q = &f["truth"];
        let (matches, correct) = (q["matches"].as_u64(), q["correct"].as_u64());
        assert!(matches.is_some_and(|m| m > 0), "no scored matches: {p}");
        let r = q["r"].as_f64().expect("r");
        assert!((r - correct.unwrap() as f64 / matches.unwrap() as f64).abs() < 1e-12);
        assert!(r > 0.3, "matching efficiency {r}: {p}");
    }
    let summary = &run_json["stages"]["matcher"]["global"]["features"];
    let map = summary["map"]
        .as_f64()
        .expect("MAP in stages.matcher.global.features");
    assert!((0.0..=1.0).contains(&map) && map > 0.3, "MAP {map}");
}

/// A part far up the z axis: the tiles' f64 heights survive the f32 frames (scan-wide offset)
/// and the written panorama, datum and pooled map are absolute.
#[test]
fn stitch_keeps_absolute_heights_of_a_part_far_up_the_z_axis() {
    const Z_UM: f64 = 25_000.0;
    let mut tiles_mean = 0.0;
    let (dir, _) = stitch_simulated_scan(1, 2, 256, &[], |scan| {
        let mut valid = Vec::new();
        for k in 0..2 {
            let path = scan.join(format!("tile_{k:03}.npy"));
            let a = surfstream_io::npy::read_npy_f64(&path).unwrap();
            let lifted: Vec<f64> = a.data.iter().map(|z| z + Z_UM).collect();
            valid.extend(a.data.iter().filter(|z| z.is_finite()).copied());
            surfstream_io::npy::write_npy_f64(&path, &lifted, a.rows, a.cols).unwrap();
        }
        tiles_mean = valid.iter().sum::<f64>() / valid.len() as f64;
    });
    for f in ["panorama.npy", "datum.npy", "pooled.npy"] {
        // The tiles carry a z offset: float32 would lose its digits, the files stay float64.
        let bytes = std::fs::read(dir.path().join("out").join(f)).unwrap();
        assert!(
            String::from_utf8_lossy(&bytes[..128]).contains("'descr': '<f8'"),
            "{f}: expected float64"
        );
        let a = surfstream_io::npy::read_npy_f64(dir.path().join("out").join(f)).unwrap();
        let valid: Vec<f64> = a.data.iter().copied().filter(|z| z.is_finite()).collect();
        let mean = valid.iter().sum::<f64>() / valid.len() as f64;
        // The tiles are levelled against each other (piston, tilt), so the mean moves by the
        // tiles' own relief, never by the 25 mm offset.
        assert!(
            (mean - (Z_UM + tiles_mean)).abs() < 5.0,
            "{f}: mean {mean} um, tiles {} um",
            Z_UM + tiles_mean
        );
    }
}

fn find_pid(binary: &str, marker: &str) -> Option<i32> {
    for e in std::fs::read_dir("/proc").ok()?.flatten() {
        let Ok(pid) = e.file_name().to_string_lossy().parse::<i32>() else {
            continue;
        };
        let Ok(cmd) = std::fs::read(e.path().join("cmdline")) else {
            continue;
        };
        let cmd = String::from_utf8_lossy(&cmd);
        if cmd.contains(binary) && cmd.contains(marker) {
            return Some(pid);
        }
    }
    None
}

/// Starts the demo graph (3 x 2 fields, one per second) in the background and returns once the
/// scan has started and ~1 s of it ran; stderr goes to `log`.
fn launch_mid_scan(out_dir: &Path, log: &Path) -> std::process::Child {
    let child = surfstream()
        .args([
            "launch",
            "launch/graphs/demo.toml",
            "--set",
            "stage.rows=3",
            "--set",
            "stage.field_time_s=1.0",
            "--out",
        ])
        .arg(out_dir)
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(log).unwrap())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    while !std::fs::read_to_string(log)
        .unwrap_or_default()
        .contains("scan started")
    {
        assert!(t0.elapsed() < Duration::from_secs(60), "scan never started");
        std::thread::sleep(Duration::from_millis(20));
    }
    std::thread::sleep(Duration::from_millis(1200));
    child
}

/// After a failed launch: no node alive, no shared memory, no node records, no outputs.
fn assert_nothing_left_behind(err: &str, out_dir: &Path) {
    assert!(!err.contains("panicked"), "{err}");
    let marker = out_dir.to_str().unwrap();
    for node in [
        "replay", "matcher", "fusion", "wavelet", "mesher", "recorder",
    ] {
        assert!(
            find_pid(&format!("surfstream-{node}"), marker).is_none(),
            "{node} still running"
        );
    }
    let domain = domain_of(err).expect("launch names its domain");
    // The launcher released its slot on exit; another test's launch may already be using the
    // domain. Hold the slot while looking, so what is counted is what this launch left.
    let _slot = hold_slot(&domain);
    assert!(
        shm_leftovers(&domain).is_empty(),
        "{:?}",
        shm_leftovers(&domain)
    );
    let cfg = surfstream_runtime::ipc::domain_config(&domain).unwrap();
    assert_eq!(
        surfstream_runtime::ipc::count_nodes(&cfg).unwrap(),
        0,
        "nodes left registered"
    );
    for f in ["panorama.npy", "recording.mcap", "run.json"] {
        assert!(!out_dir.join(f).exists(), "{f} written by a failed launch");
    }
    let partial = std::fs::read_dir(out_dir)
        .unwrap()
        .flatten()
        .any(|e| e.file_name().to_string_lossy().ends_with(".partial"));
    assert!(!partial, "a .partial file was left behind");
}

#[test]
fn a_killed_node_fails_the_launch_and_leaves_no_shared_memory() {
    let dir = tempfile::tempdir().unwrap();
    let (out_dir, log) = (
        dir.path().join("killed"),
        dir.path().join("launcher.stderr"),
    );
    let mut child = launch_mid_scan(&out_dir, &log);
    let pid = find_pid("surfstream-matcher", out_dir.to_str().unwrap()).expect("matcher runs");
    // SAFETY: signalling a process this test found by its command line.
    unsafe { libc_signal(pid, 9) };
    let status = child.wait().unwrap();
    let err = std::fs::read_to_string(&log).unwrap();
    assert!(!status.success(), "launch must fail when a node dies");
    assert!(
        err.contains("node 'matcher'") && err.contains("signal 9"),
        "{err}"
    );
    assert_nothing_left_behind(&err, &out_dir);
}

#[test]
fn two_launches_at_once_are_isolated() {
    let dir = tempfile::tempdir().unwrap();
    let spawn = |name: &str| {
        surfstream()
            .args([
                "launch",
                "launch/graphs/demo.toml",
                "--set",
                "stage.pacing=fast",
                "--set",
                "stage.tile_px=256",
                "--out",
            ])
            .arg(dir.path().join(name))
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap()
    };
    let (x, y) = (spawn("x"), spawn("y"));
    for (name, child) in [("x", x), ("y", y)] {
        let out = child.wait_with_output().unwrap();
        assert!(
            out.status.success(),
            "{name}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let run_json = read_json(&dir.path().join(name).join("run.json"));
        assert_eq!(
            run_json["messages"]["fusion"]["received"]["tiles"], 5,
            "{name}"
        );
    }
    // Same graph, same seed: the same surface, although they ran side by side.
    assert_same_outputs(&dir.path().join("x"), &dir.path().join("y"));
}

#[test]
fn a_stop_signal_stops_every_node_names_itself_and_leaves_nothing_behind() {
    for (sig, name) in [(2, "SIGINT (Ctrl-C)"), (15, "SIGTERM")] {
        let dir = tempfile::tempdir().unwrap();
        let (out_dir, log) = (
            dir.path().join("interrupted"),
            dir.path().join("launcher.stderr"),
        );
        let mut child = launch_mid_scan(&out_dir, &log);
        // SAFETY: signalling the launcher this test started.
        unsafe { libc_signal(child.id() as i32, sig) };
        let status = child.wait().unwrap();
        let err = std::fs::read_to_string(&log).unwrap();
        assert!(
            !status.success(),
            "an interrupted launch must not report success"
        );
        assert!(err.contains(&format!("interrupted by {name}")), "{err}");
        if sig != 2 {
            assert!(!err.contains("Ctrl-C"), "{name} reported as Ctrl-C: {err}");
        }
        assert_nothing_left_behind(&err, &out_dir);
    }
}

/// Takes the launcher's lock on the slot of `domain` ("ss{k}_"), waiting while a launch holds
/// it; released when the returned file is dropped.
fn hold_slot(domain: &str) -> std::fs::File {
    let k = surfstream_runtime::slots::index_of(domain).expect("slot domain ss{k}_{nonce}_");
    surfstream_runtime::slots::hold(k).unwrap()
}

unsafe fn libc_signal(pid: i32, sig: i32) {
    extern "C" {
        fn kill(pid: i32, sig: i32) -> i32;
    }
    kill(pid, sig);
}

/// Table 6's threshold e reaches run.json from `--set deviation.threshold_percent` on `stitch`,
/// and from a graph file's `[deviation]` table on `run` (each run judged by its own setting).
#[test]
fn deviation_threshold_comes_from_the_command_line_or_the_graph_file() {
    let (_dir, run_json) = stitch_simulated_scan(
        1,
        2,
        256,
        &["--set", "deviation.threshold_percent=0.5"],
        |_| {},
    );
    assert_eq!(run_json["deviation"]["threshold_pct"], 0.5);

    let dir = tempfile::tempdir().unwrap();
    let demo = std::fs::read_to_string(repo_root().join("launch/graphs/demo.toml")).unwrap();
    let graph = dir.path().join("strict.toml");
    std::fs::write(
        &graph,
        format!("{demo}\n[deviation]\nthreshold_percent = 7.5\n"),
    )
    .unwrap();
    let out_dir = dir.path().join("out");
    let out = run({
        let mut cmd = surfstream();
        cmd.arg("run").arg(&graph).arg("--out").arg(&out_dir);
        cmd
    });
    assert!(out.status.success(), "run failed:\n{}", stderr(&out));
    let run_json = read_json(&out_dir.join("run.json"));
    assert_eq!(run_json["deviation"]["threshold_pct"], 7.5);
}

/// run.json and the node reports are typed records (surfstream_core::record): each reads as
/// its record, and the record written back is the same bytes (run.json) or the same value.
fn typed_records_round_trip(out: &std::path::Path) {
    use surfstream_core::record::{
        self, FusionReport, MatcherReport, MeshReport, RecorderReport, ReplayReport, RunRecord,
        WaveletReport,
    };
    let text = std::fs::read_to_string(out.join("run.json")).expect("run.json");
    let run: RunRecord = serde_json::from_str(&text).expect("run.json reads as a RunRecord");
    let again = serde_json::to_string_pretty(&record::to_value(&run).unwrap()).expect("serialize");
    assert!(
        again == text,
        "run.json written back from its record differs"
    );
    macro_rules! same {
        ($t:ty, $v:expr) => {{
            let r: $t = record::from_value($v, stringify!($t)).expect("reads as its record");
            assert_eq!(&record::to_value(&r).unwrap(), $v, "{}", stringify!($t));
        }};
    }
    same!(ReplayReport, &run.stages["stage"]);
    same!(MatcherReport, &run.stages["matcher"]);
    same!(FusionReport, &run.stages["fusion"]);
    same!(WaveletReport, &run.stages["wavelet"]);
    same!(RecorderReport, &run.stages["recorder"]);
    // The mesher writes its report as a JSON value; this ties it to the record its readers use.
    same!(MeshReport, &run.stages["mesher"]);
}

/// Issue 36: a wrong layout is not a registration. A 3 x 3 serpentine folder of tiles (no
/// positions in the files) stitched without `--serpentine`: row 1 runs right to left, so the
/// planned overlaps of tiles 3 and 5 with their neighbours do not exist. Before, pair 3-4 was
/// accepted as a weak distinct peak (NCC 0.20, 8.3 px off the plan), tile 3 was "placed by
/// registration" about 400 px from its true place, the verdict named tile 5 only, with Table 6
/// PASS, and report.html showed a green PASS box above a red FAIL box. Now the link is refused
/// as inconsistent with the layout (pair record, pair log), the verdict fails with the layout
/// as its first failure and the serpentine hint, and the report shows no PASS. With
/// `--serpentine` the same folder passes.
#[test]
fn a_serpentine_stitched_without_serpentine_fails_with_the_layout_as_its_cause() {
    let dir = tempfile::tempdir().unwrap();
    let scan = dir.path().join("scan");
    std::fs::create_dir(&scan).unwrap();
    write_scan_dir(&scan, 3, 3, 256, Some("um"));
    std::fs::remove_file(scan.join("scan.toml")).unwrap();
    let truth = read_json(&scan.join("ground_truth.json"));
    let pitch = truth["pixel_pitch_um"]["x"].as_f64().unwrap().to_string();
    let stitch = |out_dir: &Path, serpentine: bool| {
        let mut cmd = surfstream();
        cmd.arg("stitch")
            .arg(&scan)
            .args(["--grid", "3x3", "--overlap", "20%"])
            .args(["--pitch-um", &pitch, "--out"])
            .arg(out_dir);
        if serpentine {
            cmd.arg("--serpentine");
        }
        run(cmd)
    };
    let wrong = dir.path().join("wrong");
    let out = stitch(&wrong, false);
    // Outputs written, a failed check: exit 0 without --strict (the CLI's convention).
    assert!(out.status.success(), "{}", stderr(&out));
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), stderr(&out));
    let verdict = text
        .lines()
        .find(|l| l.starts_with("verdict:"))
        .unwrap_or("");
    assert!(verdict.starts_with("verdict: FAIL"), "{text}");
    let layout = text
        .lines()
        .find(|l| l.trim_start().starts_with("layout "))
        .unwrap_or_else(|| panic!("no layout line:\n{text}"));
    assert!(
        layout.contains("without --serpentine") && layout.contains("tiles 3-4"),
        "{layout}"
    );
    assert!(!text.contains("  deviation   PASS"), "{text}");
    let run_json = read_json(&wrong.join("run.json"));
    let pair = run_json["pairs"]
        .as_array()
        .unwrap()
        .iter()
        .find(|p| p["a"] == 3 && p["b"] == 4)
        .expect("pair 3-4");
    assert_eq!(pair["accepted"], false, "{pair}");
    assert_eq!(pair["layout_inconsistent"]["refused"], true, "{pair}");
    assert!(
        pair["reason"].as_str().unwrap().contains("layout"),
        "{pair}"
    );
    // No tile off the layout is "placed by registration": tiles 3 and 5 are the stage's.
    for k in [3, 5] {
        assert_eq!(run_json["tiles"][k]["placed_by"], "stage", "tile {k}");
    }
    // The live pair log says it too, as the matcher decided it.
    let log = std::fs::read_to_string(wrong.join("nodes/matcher.pairs.jsonl")).unwrap();
    let line = log
        .lines()
        .find(|l| l.contains("\"a\":3,") && l.contains("\"b\":4,"))
        .expect("pair 3-4 in the pair log");
    assert!(line.contains("layout_inconsistent"), "{line}");
    // report.html: the failures first, and no PASS box at all.
    let html = std::fs::read_to_string(wrong.join("report.html")).unwrap();
    let fail = html.find("class=\"verdict fail\"").expect("a FAIL box");
    assert!(!html.contains("class=\"verdict pass\""), "a PASS box");
    assert!(html[fail..].contains("wrong layout"));

    // The right layout: every tile registered within half a pixel, PASS.
    let right = dir.path().join("right");
    let out = stitch(&right, true);
    assert!(out.status.success(), "{}", stderr(&out));
    let run_json = read_json(&right.join("run.json"));
    let err = max_position_error_px(&run_json, &truth);
    assert!(err < 0.5, "tile position error {err} px");
    assert!(run_json["pairs"]
        .as_array()
        .unwrap()
        .iter()
        .all(|p| p.get("layout_inconsistent").is_none()));
    let html = std::fs::read_to_string(right.join("report.html")).unwrap();
    assert!(html.contains("class=\"verdict pass\"") && !html.contains("class=\"verdict fail\""));
}
