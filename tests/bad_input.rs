//! Bad input: a clear error naming the file and the field, a non-zero exit, no panic, and
//! nothing half-written.

use std::path::Path;

use surfstream_e2e::*;

/// Runs `surfstream ARGS` expecting failure; returns stderr.
fn fails(args: &[&str], out_dir: &Path) -> String {
    let out = run({
        let mut c = surfstream();
        c.args(args);
        c
    });
    let err = stderr(&out);
    assert!(!out.status.success(), "expected failure for {args:?}");
    assert_eq!(
        out.status.code(),
        Some(1),
        "a clean error exit, not a crash: {err}"
    );
    assert!(!err.contains("panicked"), "{err}");
    if out_dir.exists() {
        for f in OUTPUTS.iter().chain(&["run.json"]) {
            assert!(!out_dir.join(f).exists(), "{f} written by a failed run");
        }
        let partial = std::fs::read_dir(out_dir)
            .unwrap()
            .flatten()
            .any(|e| e.file_name().to_string_lossy().ends_with(".partial"));
        assert!(!partial, "a .partial file was left behind");
    }
    err
}

fn write(path: &Path, text: &str) {
    std::fs::write(path, text).unwrap();
}

const GOOD_SCAN: &str = r#"
[scan]
name = "bad"
pitch_x_um = 0.8148
pitch_y_um = 0.8148
height_unit = "um"
rows = 1
cols = 2

[[tile]]
file = "tile_000.npy"
row = 0
col = 0
stage_x_um = 0.0
stage_y_um = 0.0

[[tile]]
file = "tile_001.npy"
row = 0
col = 1
stage_x_um = 80.0
stage_y_um = 0.0
"#;

fn tile(dir: &Path, name: &str, rows: usize, cols: usize) {
    let data: Vec<f32> = (0..rows * cols)
        .map(|i| ((i * 7919) % 101) as f32 * 0.01)
        .collect();
    surfstream_io::npy::write_npy_f32(dir.join(name), &data, rows, cols).unwrap();
}

#[test]
fn malformed_graph_files_are_named() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("out");
    let g = d.path().join("broken.toml");
    write(&g, "[graph]\nname = \"x\"\n[[node]\nid = \"a\"\n");
    let err = fails(
        &[
            "launch",
            g.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ],
        &out,
    );
    assert!(
        err.contains("broken.toml") && err.contains("not a valid graph file"),
        "{err}"
    );

    let g = d.path().join("wiring.toml");
    let demo = std::fs::read_to_string(repo_root().join("launch/graphs/demo.toml")).unwrap();
    write(
        &g,
        &demo.replace(
            "tiles = \"stage/tiles\" }\n\n[[node]]\nid = \"fusion\"",
            "tiles = \"stage/tile\" }\n\n[[node]]\nid = \"fusion\"",
        ),
    );
    let err = fails(
        &["run", g.to_str().unwrap(), "--out", out.to_str().unwrap()],
        &out,
    );
    assert!(
        err.contains("wiring.toml")
            && err.contains("inputs.tiles")
            && err.contains("no output \"tile\""),
        "{err}"
    );

    let err = fails(
        &[
            "run",
            "launch/graphs/demo.toml",
            "--set",
            "stage.rows=\"two\"",
            "--out",
            out.to_str().unwrap(),
        ],
        &out,
    );
    assert!(
        err.contains("node 'stage'") && err.contains("rows"),
        "{err}"
    );

    let err = fails(
        &[
            "launch",
            "launch/graphs/demo.toml",
            "--set",
            "stage.colz=3",
            "--out",
            out.to_str().unwrap(),
        ],
        &out,
    );
    assert!(
        err.contains("node 'stage'") && err.contains("colz"),
        "{err}"
    );

    let err = fails(
        &[
            "run",
            "launch/graphs/demo.toml",
            "--set",
            "wavelet.wavelet=\"haar9\"",
            "--out",
            out.to_str().unwrap(),
        ],
        &out,
    );
    assert!(
        err.contains("node 'wavelet'") && err.contains("haar9"),
        "{err}"
    );
}

#[test]
fn bad_scan_directories_are_named() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("out");
    let scan = d.path().join("scan");
    std::fs::create_dir(&scan).unwrap();
    let s = scan.join("scan.toml");
    let stitch = |err_hint: &str| {
        let err = fails(
            &[
                "stitch",
                s.to_str().unwrap(),
                "--out",
                out.to_str().unwrap(),
            ],
            &out,
        );
        assert!(err.contains(err_hint), "expected {err_hint:?} in: {err}");
        err
    };

    // A missing field (the .npy tiles carry no pitch, so the manifest must).
    tile(&scan, "tile_000.npy", 64, 100);
    tile(&scan, "tile_001.npy", 64, 100);
    write(&s, &GOOD_SCAN.replace("pitch_y_um = 0.8148\n", ""));
    let err = stitch("pitch_y_um");
    assert!(err.contains("scan.toml"), "{err}");

    // Inconsistent manifests: the same file at two grid positions, more tiles than the grid
    // holds, a pitch no profiler has.
    write(&s, &GOOD_SCAN.replace("tile_001.npy", "tile_000.npy"));
    let err = stitch("both name file \"tile_000.npy\"");
    assert!(err.contains("#1 and #2"), "{err}");
    write(&s, &GOOD_SCAN.replace("cols = 2", "cols = 1"));
    stitch("2 [[tile]] entries for a 1 x 1 (rows x cols) scan");
    write(
        &s,
        &GOOD_SCAN.replace("pitch_x_um = 0.8148", "pitch_x_um = 1e30"),
    );
    stitch("pitch_x_um = 1000000000000000000000000000000: expected a pitch between");

    // The issue's case: `rows = 3` (one column) with four tiles listed.
    let four = format!(
        "{}\n[[tile]]\nfile = \"tile_002.npy\"\nrow = 2\ncol = 0\nstage_x_um = 0.0\nstage_y_um = 100.0\n\n[[tile]]\nfile = \"tile_003.npy\"\nrow = 2\ncol = 1\nstage_x_um = 80.0\nstage_y_um = 100.0\n",
        GOOD_SCAN.replace("rows = 1\ncols = 2", "rows = 3\ncols = 1")
    );
    write(&s, &four);
    stitch("4 [[tile]] entries for a 3 x 1 (rows x cols) scan: expected at most 3");

    // A physically absurd height: one 1e30 um point would make an STL 1e25 mm tall.
    let mut absurd: Vec<f32> = (0..64 * 100).map(|i| (i % 13) as f32 * 0.01).collect();
    absurd[3 * 100 + 7] = 1e30;
    surfstream_io::npy::write_npy_f32(scan.join("tile_001.npy"), &absurd, 64, 100).unwrap();
    write(&s, GOOD_SCAN);
    let err = stitch("1 height(s) beyond +-1e6 um, the first 1.000e30 um at row 3, col 7");
    assert!(err.contains("tile_001.npy"), "{err}");
    tile(&scan, "tile_001.npy", 64, 100);

    // A missing tile file.
    write(&s, GOOD_SCAN);
    std::fs::remove_file(scan.join("tile_001.npy")).unwrap();
    let err = stitch("tile_001.npy");
    assert!(err.contains("no such tile file"), "{err}");

    // A tile with the wrong shape.
    tile(&scan, "tile_001.npy", 64, 99);
    let err = stitch("tile_001.npy");
    assert!(err.contains("expected 64 x 100"), "{err}");

    // A tile that is not a .npy at all.
    write(&scan.join("tile_001.npy"), "this is not numpy");
    stitch("tile_001.npy");

    // A missing scan.
    let err = fails(
        &[
            "stitch",
            d.path().join("nowhere").to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ],
        &out,
    );
    assert!(err.contains("nowhere"), "{err}");
}

#[test]
fn corrupt_and_truncated_recordings_are_named() {
    use surfstream_core::{FrameHeader, FrameKind};
    use surfstream_io::recording::Recorder;
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("out");
    let good = d.path().join("good.mcap");
    let mut rec = Recorder::create(&good).unwrap();
    let ch = rec
        .add_frame_channel("stage/tiles", Default::default())
        .unwrap();
    for i in 0..3u32 {
        let h = FrameHeader {
            kind: FrameKind::Tile as u32,
            tile_index: i,
            width: 64,
            height: 64,
            pitch_x_um: 1.0,
            pitch_y_um: 1.0,
            origin_x_um: 50.0 * i as f64,
            ..Default::default()
        };
        let z: Vec<f32> = (0..64 * 64).map(|k| (k % 13) as f32).collect();
        rec.write_frame(ch, &h, &z, 1_000 + i as u64).unwrap();
    }
    rec.finish().unwrap();
    let bytes = std::fs::read(&good).unwrap();

    let truncated = d.path().join("truncated.mcap");
    std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
    let err = fails(
        &[
            "stitch",
            truncated.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ],
        &out,
    );
    assert!(err.contains("truncated.mcap"), "{err}");

    let garbage = d.path().join("garbage.mcap");
    std::fs::write(
        &garbage,
        b"\x89MCAP0\r\n not really a recording at all, just text",
    )
    .unwrap();
    let err = fails(
        &[
            "stitch",
            garbage.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ],
        &out,
    );
    assert!(err.contains("garbage.mcap"), "{err}");

    let mut flipped = bytes.clone();
    let mid = flipped.len() / 2;
    for b in &mut flipped[mid..mid + 64] {
        *b ^= 0x5a;
    }
    let corrupt = d.path().join("corrupt.mcap");
    std::fs::write(&corrupt, &flipped).unwrap();
    let err = fails(
        &[
            "stitch",
            corrupt.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ],
        &out,
    );
    assert!(err.contains("corrupt.mcap"), "{err}");
}

/// A single file with a physically absurd height is flagged by every verb that reads it.
#[test]
fn absurd_heights_in_a_single_file_are_flagged() {
    let d = tempfile::tempdir().unwrap();
    let mut z: Vec<f32> = (0..32 * 40).map(|i| (i % 11) as f32 * 0.1).collect();
    z[5] = -1e30;
    let f = d.path().join("spike.npy");
    surfstream_io::npy::write_npy_f32(&f, &z, 32, 40).unwrap();
    let out = run({
        let mut c = surfstream();
        c.args(["params", f.to_str().unwrap(), "--pitch-um", "1"]);
        c
    });
    let err = stderr(&out);
    assert!(
        err.contains("warning")
            && err.contains("1 height(s) beyond +-1e6 um (1 m), the largest -1.000e30 um"),
        "{err}"
    );
}

/// `surfstream ARGS` (with `graph` and `-o out`) must fail naming every `want`.
fn graph_fails(verb: &str, graph: &Path, out: &Path, sets: &[&str], want: &[&str]) -> String {
    let mut args = vec![verb, graph.to_str().unwrap(), "-o", out.to_str().unwrap()];
    for s in sets {
        args.push("--set");
        args.push(s);
    }
    let err = fails(&args, out);
    for w in want {
        assert!(err.contains(w), "expected {w:?} for {sets:?} in: {err}");
    }
    err
}

/// Every file a graph writes lives under OUT (issue 27): a recorder or mesher file given as
/// an absolute path or with `..` is refused when the graph is read, naming file, node and
/// field, and nothing is written there.
#[test]
fn graph_files_writing_outside_the_out_dir_are_refused() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("sub").join("out");
    let demo = repo_root().join("launch/graphs/demo.toml");
    let outside = d.path().join("outside.mcap");
    let abs = format!("recorder.path=\"{}\"", outside.display());
    for (set, node, field) in [
        (abs.as_str(), "node 'recorder'", "params.path"),
        (
            "recorder.path=\"../../x.mcap\"",
            "node 'recorder'",
            "params.path",
        ),
        ("mesher.file=\"../x.stl\"", "node 'mesher'", "params.file"),
        (
            "mesher.file=\"/tmp/surfstream-x.stl\"",
            "node 'mesher'",
            "params.file",
        ),
    ] {
        for verb in ["run", "launch"] {
            graph_fails(verb, &demo, &out, &[set], &["demo.toml", node, field]);
        }
    }
    assert!(!outside.exists());
    assert!(!d.path().join("sub").join("x.stl").exists());
    assert!(!d.path().join("x.mcap").exists());
    // The same in the graph file itself.
    let g = d.path().join("escape.toml");
    let text = std::fs::read_to_string(&demo)
        .unwrap()
        .replace("path = \"recording.mcap\"", "path = \"../escape.mcap\"");
    write(&g, &text);
    graph_fails(
        "run",
        &g,
        &out,
        &[],
        &["escape.toml", "node 'recorder'", "leaves the out dir"],
    );
}

/// A cycle is refused when the graph is read, not found by a stall watch minutes later.
#[test]
fn a_graph_with_a_cycle_is_refused_when_read() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("out");
    let g = d.path().join("cycle.toml");
    let demo = std::fs::read_to_string(repo_root().join("launch/graphs/demo.toml")).unwrap();
    let text = demo.replace(
        "params = { method = \"auto\" }\ninputs = { tiles = \"stage/tiles\" }",
        "params = { method = \"auto\" }\ninputs = { tiles = \"fusion/panorama\" }",
    );
    assert_ne!(text, demo, "demo.toml's matcher changed");
    write(&g, &text);
    for verb in ["run", "launch"] {
        let t0 = std::time::Instant::now();
        graph_fails(
            verb,
            &g,
            &out,
            &[],
            &["cycle.toml", "cycle", "matcher", "fusion"],
        );
        // Refused on reading (well within a stall deadline of 60 s), not by the stall watch.
        assert!(t0.elapsed() < std::time::Duration::from_secs(30));
    }
}

/// No parameter value panics (issue 27): durations, sizes and heights out of range are
/// clear errors naming the field.
#[test]
fn absurd_durations_sizes_and_heights_are_clear_errors() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("out");
    let demo = repo_root().join("launch/graphs/demo.toml");
    graph_fails(
        "run",
        &demo,
        &out,
        &["stage.field_time_s=1e20"],
        &["field_time_s = 100000000000000000000", "at most"],
    );
    graph_fails(
        "run",
        &demo,
        &out,
        &["stage.noise_um=1e30"],
        &["noise_um", "at most"],
    );
    graph_fails(
        "launch",
        &demo,
        &out,
        &["stage.sa_um=1e12"],
        &["sa_um", "at most"],
    );
    graph_fails(
        "run",
        &demo,
        &out,
        &["stage.rows=4294967296", "stage.cols=4294967296"],
        &["rows"],
    );
    for field in [
        "backpressure_timeout_s",
        "startup_timeout_s",
        "stall_timeout_s",
    ] {
        let g = d.path().join(format!("{field}.toml"));
        let text = std::fs::read_to_string(&demo).unwrap().replace(
            "name = \"demo\"\n",
            &format!("name = \"demo\"\n{field} = 1e300\n"),
        );
        write(&g, &text);
        graph_fails("run", &g, &out, &[], &[field, "at most"]);
    }
    // A scan manifest whose grid overflows rows * cols.
    let scan = d.path().join("scan");
    std::fs::create_dir(&scan).unwrap();
    tile(&scan, "tile_000.npy", 64, 100);
    tile(&scan, "tile_001.npy", 64, 100);
    write(
        &scan.join("scan.toml"),
        &GOOD_SCAN.replace("rows = 1\ncols = 2", "rows = 4294967296\ncols = 4294967296"),
    );
    let err = fails(
        &[
            "stitch",
            scan.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
        ],
        &out,
    );
    assert!(err.contains("rows * cols <="), "{err}");
}

/// The +-1 m guard of scan directories holds for recordings too: a recording with an absurd
/// z offset or absurd heights is refused, naming the file, the tile and the field.
#[test]
fn recordings_with_absurd_heights_are_refused() {
    use surfstream_core::{FrameHeader, FrameKind};
    use surfstream_io::recording::Recorder;
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("out");
    let write_rec = |name: &str, z_offset_um: f64, spike: f32| {
        let path = d.path().join(name);
        let mut rec = Recorder::create(&path).unwrap();
        let ch = rec
            .add_frame_channel("stage/tiles", Default::default())
            .unwrap();
        for i in 0..2u32 {
            let h = FrameHeader {
                kind: FrameKind::Tile as u32,
                tile_index: i,
                tile_col: i,
                width: 64,
                height: 64,
                pitch_x_um: 1.0,
                pitch_y_um: 1.0,
                origin_x_um: 50.0 * i as f64,
                z_offset_um,
                ..Default::default()
            };
            let mut z: Vec<f32> = (0..64 * 64).map(|k| (k % 13) as f32).collect();
            z[64 * 3 + 5] = spike;
            rec.write_frame(ch, &h, &z, 1_000 + i as u64).unwrap();
        }
        rec.finish().unwrap();
        path
    };
    let offset = write_rec("offset.mcap", 1e30, 1.0);
    let err = fails(
        &[
            "stitch",
            offset.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
        ],
        &out,
    );
    assert!(
        err.contains("offset.mcap") && err.contains("tile #1") && err.contains("z_offset_um"),
        "{err}"
    );
    let spike = write_rec("spike.mcap", 0.0, 1e20);
    let err = fails(
        &[
            "stitch",
            spike.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
        ],
        &out,
    );
    assert!(
        err.contains("spike.mcap")
            && err.contains("beyond +-1e6 um")
            && err.contains("row 3, col 5"),
        "{err}"
    );
}

/// Manifests that lie: tile files outside the scan directory, a FIFO as a tile, a pitch the
/// tiles were not made with; a grid the tiles do not fill is named.
#[test]
fn manifests_that_lie_are_refused_or_named() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("out");
    let scan = d.path().join("scan");
    std::fs::create_dir(&scan).unwrap();
    tile(&scan, "tile_000.npy", 64, 100);
    tile(&scan, "tile_001.npy", 64, 100);
    tile(d.path(), "secret.npy", 64, 100);
    let s = scan.join("scan.toml");
    let stitch = || {
        fails(
            &["stitch", s.to_str().unwrap(), "-o", out.to_str().unwrap()],
            &out,
        )
    };
    write(
        &s,
        &GOOD_SCAN.replace("\"tile_001.npy\"", "\"../secret.npy\""),
    );
    let err = stitch();
    assert!(
        err.contains("outside the scan directory") && err.contains("secret.npy"),
        "{err}"
    );
    let abs = d.path().join("secret.npy");
    write(
        &s,
        &GOOD_SCAN.replace(
            "\"tile_001.npy\"",
            &format!("{:?}", abs.display().to_string()),
        ),
    );
    let err = stitch();
    assert!(err.contains("outside the scan directory"), "{err}");
    // A FIFO: refused at once, not a silent hang.
    let fifo = scan.join("fifo.npy");
    let made = std::process::Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .unwrap();
    assert!(made.success());
    write(&s, &GOOD_SCAN.replace("\"tile_001.npy\"", "\"fifo.npy\""));
    // (No wall-clock bound: the refusal comes before any read, so a hang would be the failure.)
    let err = stitch();
    assert!(
        err.contains("fifo.npy") && err.contains("a FIFO (named pipe), not a regular file"),
        "{err}"
    );
    // A pitch that disagrees with the ground truth the tiles were made with.
    let sim = d.path().join("sim");
    std::fs::create_dir(&sim).unwrap();
    write_scan_dir(&sim, 2, 2, 128, Some("um"));
    let m = std::fs::read_to_string(sim.join("scan.toml")).unwrap();
    let wrong = m
        .replace("pitch_x_um = 0.8148", "pitch_x_um = 2.0")
        .replace("pitch_y_um = 0.8148", "pitch_y_um = 2.0");
    assert_ne!(wrong, m);
    write(&sim.join("scan.toml"), &wrong);
    let err = fails(
        &["stitch", sim.to_str().unwrap(), "-o", out.to_str().unwrap()],
        &out,
    );
    assert!(
        err.contains("ground_truth.json") && err.contains("disagree"),
        "{err}"
    );
    // Stage steps larger than a tile at the manifest's pitch: the tiles cannot overlap.
    write(
        &s,
        &GOOD_SCAN.replace("stage_x_um = 80.0", "stage_x_um = 800.0"),
    );
    // Flagged, not refused: a sparse survey may leave gaps on purpose.
    let o = run({
        let mut c = surfstream();
        c.args(["stitch", s.to_str().unwrap(), "-o", out.to_str().unwrap()]);
        c
    });
    let err = stderr(&o);
    assert!(
        err.contains("cannot overlap") && !err.contains("panicked"),
        "{err}"
    );
}

/// A 3-tile manifest for a 2 x 2 grid runs, and says which field has no tile.
#[test]
fn a_grid_the_tiles_do_not_fill_is_named() {
    let d = tempfile::tempdir().unwrap();
    let sim = d.path().join("sim");
    std::fs::create_dir(&sim).unwrap();
    write_scan_dir(&sim, 2, 2, 128, Some("um"));
    let m = std::fs::read_to_string(sim.join("scan.toml")).unwrap();
    // Drop the last [[tile]] (acquisition index 3).
    let cut = m.rfind("\n[[tile]]").unwrap();
    write(&sim.join("scan.toml"), &m[..cut]);
    let out = d.path().join("out");
    let o = run({
        let mut c = surfstream();
        c.args(["stitch", sim.to_str().unwrap(), "-o", out.to_str().unwrap()]);
        c
    });
    let err = stderr(&o);
    assert!(!err.contains("panicked"), "{err}");
    assert!(
        err.contains("3 [[tile]] entries for a 2 x 2 (rows x cols) grid")
            && err.contains("1 field(s) have no tile"),
        "{err}"
    );
}

/// A full or closed stdout/stderr ends cleanly (issue 27): no exit 101, no panic.
#[test]
fn a_full_stdout_or_stderr_is_a_clean_exit() {
    let d = tempfile::tempdir().unwrap();
    tile(d.path(), "t.npy", 16, 16);
    let f = d.path().join("t.npy");
    let full = || {
        std::fs::OpenOptions::new()
            .write(true)
            .open("/dev/full")
            .unwrap()
    };
    // stdout on /dev/full: a clean error on stderr.
    let o = surfstream()
        .args(["params", f.to_str().unwrap()])
        .stdout(full())
        .output()
        .unwrap();
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("cannot write to stdout"), "{err}");
    // stderr on /dev/full: the error is lost, but the exit is the error's, not a panic's.
    let o = surfstream()
        .args(["stitch", d.path().join("nowhere").to_str().unwrap(), "-o"])
        .arg(d.path().join("out"))
        .stderr(full())
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1));
    // Both on /dev/full, a verb that prints a table.
    let o = surfstream()
        .args(["inspect", f.to_str().unwrap()])
        .stdout(full())
        .stderr(full())
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1));
}

/// Single-file verbs touch nothing of the user's (issue 36): `convert a.x3p -o a.x3p` rewrote
/// its input, `convert p.npy -o p.npy` its sidecar, `mesh ... -o notes.stl` replaced a file,
/// `separate p.npy -o sf` wrote into a user's folder. Now an input is never overwritten, an
/// existing file or a non-empty folder only with `--force`, each refused before any work.
#[test]
fn single_file_verbs_overwrite_nothing_without_force_and_never_an_input() {
    let d = tempfile::tempdir().unwrap();
    let p = |name: &str| d.path().join(name);
    let s = |path: &Path| path.to_str().unwrap().to_string();
    let heights: Vec<f64> = (0..64 * 64)
        .map(|i| ((i % 64) as f64 * 0.3).sin())
        .collect();
    surfstream_io::npy::write_npy_f64(p("p.npy"), &heights, 64, 64).unwrap();
    let convert = |args: &[&str]| {
        let mut c = surfstream();
        c.args(["convert", &s(&p("p.npy")), "--pitch-um", "1"])
            .args(args);
        run(c)
    };
    // The input itself, or its sidecar through a .npy output of the same name: refused, even
    // with --force.
    for force in [&[][..], &["--force"][..]] {
        let mut args = vec!["-o".to_string(), s(&p("p.npy"))];
        args.extend(force.iter().map(|f| f.to_string()));
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let o = convert(&args);
        assert!(!o.status.success(), "convert onto its input succeeded");
        assert!(
            stderr(&o).contains("an input is never overwritten"),
            "{}",
            stderr(&o)
        );
    }
    // An existing file: refused, then replaced with --force.
    write(&p("notes.x3p"), "my notes");
    let o = convert(&["-o", &s(&p("notes.x3p"))]);
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("notes.x3p exists") && stderr(&o).contains("--force"),
        "{}",
        stderr(&o)
    );
    assert_eq!(std::fs::read_to_string(p("notes.x3p")).unwrap(), "my notes");
    let o = convert(&["-o", &s(&p("notes.x3p")), "--force"]);
    assert!(o.status.success(), "{}", stderr(&o));
    // mesh: the STL and its OUT.json.
    write(&p("m.json"), "my notes");
    let mut c = surfstream();
    c.args(["mesh", &s(&p("notes.x3p")), "-o", &s(&p("m.stl"))]);
    let o = run(c);
    assert!(
        !o.status.success() && stderr(&o).contains("m.json exists"),
        "{}",
        stderr(&o)
    );
    assert!(!p("m.stl").exists());
    // separate: a folder that exists and holds files is not the verb's to write into.
    std::fs::create_dir(p("sf")).unwrap();
    write(&p("sf/thesis.txt"), "years of work");
    let mut c = surfstream();
    c.args(["separate", &s(&p("notes.x3p")), "-o", &s(&p("sf"))]);
    let o = run(c);
    assert!(
        !o.status.success() && stderr(&o).contains("not empty") && stderr(&o).contains("--force"),
        "{}",
        stderr(&o)
    );
    assert_eq!(
        std::fs::read_dir(p("sf")).unwrap().count(),
        1,
        "separate wrote into the user's folder"
    );
}

/// Issue 36: a tile listed twice through a link or another path, a tile with no measured
/// point, and a folder, FIFO or device given as a recording or manifest are each named for
/// what they are (before: the duplicate passed, the all-NaN tile ran with exit 0, and a folder,
/// FIFO or /dev/zero said "no such file").
#[test]
fn duplicate_unmeasured_and_non_regular_inputs_are_named() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("out");
    let scan = d.path().join("scan");
    std::fs::create_dir(&scan).unwrap();
    tile(&scan, "tile_000.npy", 64, 100);
    tile(&scan, "tile_001.npy", 64, 100);
    let s = scan.join("scan.toml");
    let stitch = |what: &Path| {
        fails(
            &[
                "stitch",
                what.to_str().unwrap(),
                "-o",
                out.to_str().unwrap(),
            ],
            &out,
        )
    };
    // The same file at two grid positions, through a symbolic link and through "./".
    std::os::unix::fs::symlink("tile_000.npy", scan.join("link.npy")).unwrap();
    for other in ["link.npy", "./tile_000.npy", "sub/../tile_000.npy"] {
        std::fs::create_dir_all(scan.join("sub")).unwrap();
        write(
            &s,
            &GOOD_SCAN.replace("\"tile_001.npy\"", &format!("{other:?}")),
        );
        let err = stitch(&s);
        assert!(
            err.contains("the same file listed twice")
                && err.contains("[[tile]] #1")
                && err.contains(other),
            "{other}: {err}"
        );
    }
    // A tile whose every height is NaN.
    let nan = vec![f32::NAN; 64 * 100];
    surfstream_io::npy::write_npy_f32(scan.join("tile_001.npy"), &nan, 64, 100).unwrap();
    write(&s, GOOD_SCAN);
    let err = stitch(&s);
    assert!(
        err.contains("[[tile]] #2")
            && err.contains("tile_001.npy")
            && err.contains("every one of its 6400 heights is NaN"),
        "{err}"
    );
    // The first tile all NaN: named too (it sets the scan's height offset).
    write(
        &s,
        &GOOD_SCAN
            .replace("\"tile_000.npy\"", "\"tmp.npy\"")
            .replace("\"tile_001.npy\"", "\"tile_000.npy\"")
            .replace("\"tmp.npy\"", "\"tile_001.npy\""),
    );
    let err = stitch(&s);
    assert!(
        err.contains("[[tile]] #1") && err.contains("is NaN"),
        "{err}"
    );
    // A folder, a FIFO and a device as the recording or manifest.
    let folder = d.path().join("folder.mcap");
    std::fs::create_dir(&folder).unwrap();
    let fifo = d.path().join("fifo.mcap");
    let made = std::process::Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .unwrap();
    assert!(made.success());
    let fifo_toml = scan.join("fifo.toml");
    let made = std::process::Command::new("mkfifo")
        .arg(&fifo_toml)
        .status()
        .unwrap();
    assert!(made.success());
    // (A folder given to `stitch` is a folder of tiles; a graph's recording path below.)
    for (path, what) in [
        (fifo.as_path(), "a FIFO (named pipe), not a regular file"),
        (
            fifo_toml.as_path(),
            "a FIFO (named pipe), not a regular file",
        ),
        (
            Path::new("/dev/zero"),
            "a character device, not a regular file",
        ),
    ] {
        let err = stitch(path);
        assert!(
            err.contains(&path.display().to_string()) && err.contains(what),
            "{}: {err}",
            path.display()
        );
        assert!(!err.contains("no such file"), "{err}");
    }
    // Under `run`, where a graph names the recording: a folder and a FIFO.
    for (path, what) in [
        (&folder, "a folder, not a regular file"),
        (&fifo, "a FIFO (named pipe), not a regular file"),
    ] {
        let graph = d.path().join("g.toml");
        write(
            &graph,
            &format!(
                r#"
[graph]
name = "g"
[[node]]
id = "stage"
node = "replay"
[node.params]
source = "mcap"
path = {:?}
"#,
                path.display().to_string()
            ),
        );
        let err = fails(
            &["run", graph.to_str().unwrap(), "-o", out.to_str().unwrap()],
            &out,
        );
        assert!(
            err.contains("params.path") && err.contains(what) && !err.contains("no such file"),
            "{}: {err}",
            path.display()
        );
    }
}

#[path = "../fuzz/entry.rs"]
mod entry;

/// A deterministic xorshift generator: the corpus is the same on every run.
struct Mutator(u64);

impl Mutator {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
    /// One mutation of `seed`: a byte flipped or set to an edge value, a truncation, a slice
    /// repeated or removed, random bytes inserted, or (in text) a number replaced by an
    /// extreme one. `focus` bytes at the start take half of the byte edits (headers).
    fn mutate(&mut self, seed: &[u8], focus: usize) -> Vec<u8> {
        let mut v = seed.to_vec();
        let edits = 1 + self.below(3);
        for _ in 0..edits {
            if v.is_empty() {
                v.push(0);
            }
            let at = if self.below(2) == 0 {
                self.below(focus.min(v.len()))
            } else {
                self.below(v.len())
            };
            match self.below(7) {
                0 => v[at] ^= 1 << self.below(8),
                1 => v[at] = [0x00, 0xff, 0x7f, 0x80, b'9', b'-'][self.below(6)],
                2 => v.truncate(at),
                3 => {
                    let end = (at + 1 + self.below(64)).min(v.len());
                    let slice = v[at..end].to_vec();
                    v.splice(at..at, slice);
                }
                4 => {
                    let end = (at + 1 + self.below(64)).min(v.len());
                    v.drain(at..end);
                }
                5 => {
                    let n = 1 + self.below(16);
                    let bytes: Vec<u8> = (0..n).map(|_| self.next() as u8).collect();
                    v.splice(at..at, bytes);
                }
                _ => {
                    // A number in text (the first digit at or after `at`) made extreme.
                    if let Some(start) = v[at..].iter().position(u8::is_ascii_digit) {
                        let start = at + start;
                        let len = v[start..]
                            .iter()
                            .take_while(|b| b.is_ascii_digit() || **b == b'.')
                            .count();
                        let extreme = [
                            "0",
                            "-1",
                            "1e300",
                            "-1e300",
                            "1e-300",
                            "nan",
                            "inf",
                            "18446744073709551615",
                            "4294967296",
                            "\"x\"",
                            "[]",
                        ][self.below(11)];
                        v.splice(start..start + len, extreme.bytes());
                    }
                }
            }
        }
        v
    }
}

/// Issue 36: the fuzz targets' entry points (`fuzz/entry.rs`, shared with cargo-fuzz) driven by
/// a deterministic corpus of mutated inputs on the stable toolchain, so every test run checks
/// them: MCAP recordings, scan manifests, graph files, `.npy` pitch sidecars and the readers
/// (X3P, NumPy, MetroPro, SUR, DATX). Every input must come back Ok or Err: a panic names the
/// seed and the mutation, and the input is kept under target/ for the fuzzer's corpus.
#[test]
fn mutated_inputs_of_every_parser_are_refused_cleanly() {
    use surfstream_io::formats::{self, Format};
    let d = tempfile::tempdir().unwrap();
    // Seeds: valid inputs of each kind.
    let rec_path = d.path().join("seed.mcap");
    {
        use surfstream_core::{FrameHeader, FrameKind};
        let mut rec = surfstream_io::recording::Recorder::create(&rec_path).unwrap();
        let ch = rec
            .add_frame_channel("stage/tiles", Default::default())
            .unwrap();
        for i in 0..2u32 {
            let h = FrameHeader {
                kind: FrameKind::Tile as u32,
                tile_index: i,
                tile_col: i,
                width: 8,
                height: 6,
                pitch_x_um: 1.0,
                pitch_y_um: 1.0,
                origin_x_um: 6.0 * i as f64,
                ..Default::default()
            };
            let z: Vec<f32> = (0..48).map(|k| (k % 5) as f32).collect();
            rec.write_frame(ch, &h, &z, 1_000 + i as u64).unwrap();
        }
        rec.finish().unwrap();
    }
    let scan = GOOD_SCAN
        .replace("stage_x_um = 80.0", "stage_x_um = 16.0")
        .replace("0.8148", "1.0");
    let graph = r#"
[graph]
name = "fuzz"
out_dir = "out"
stall_timeout_s = 60
[[node]]
id = "stage"
node = "replay"
params = { source = "simulated", rows = 2, cols = 2, overlap = 0.1, tile_px = 64, pitch_um = 0.8148, seed = 1, pacing = "fast" }
[[node]]
id = "recorder"
node = "recorder"
params = { path = "tiles.mcap" }
inputs = { tiles = "stage/tiles" }
"#;
    let npy = d.path().join("s.npy");
    surfstream_io::npy::write_npy_f32(&npy, &[0.5f32; 12], 3, 4).unwrap();
    surfstream_io::sidecar::write_sidecar(
        &npy,
        &surfstream_io::sidecar::NpyGeometry {
            pitch_x_um: 0.8148,
            pitch_y_um: 0.8148,
            origin_um: Some([10.0, 20.0]),
        },
    )
    .unwrap();
    let sidecar = std::fs::read(surfstream_io::sidecar::sidecar_path(&npy)).unwrap();
    let surface = formats::read_surface(&npy).unwrap();
    let x3p = d.path().join("s.x3p");
    formats::write_surface(&x3p, &surface).unwrap();
    let specimens = repo_root().join("tests/data/specimens");
    let fixtures = repo_root().join("common/io/tests/fixtures");
    type Entry = Box<dyn Fn(&[u8]) -> bool>;
    let reader = |f: Format| -> Entry { Box::new(move |b: &[u8]| entry::reader(b, f)) };
    // (name, seed bytes, entry point, mutations, header bytes to focus on)
    let seeds: Vec<(&str, Vec<u8>, Entry, usize, usize)> = vec![
        (
            "mcap",
            std::fs::read(&rec_path).unwrap(),
            Box::new(entry::mcap),
            600,
            256,
        ),
        (
            "scan.toml",
            scan.into_bytes(),
            Box::new(entry::scan_toml),
            600,
            4096,
        ),
        (
            "graph.toml",
            graph.as_bytes().to_vec(),
            Box::new(entry::graph_toml),
            600,
            4096,
        ),
        ("sidecar", sidecar, Box::new(entry::sidecar), 600, 4096),
        (
            "npy",
            std::fs::read(&npy).unwrap(),
            reader(Format::Npy),
            300,
            128,
        ),
        (
            "x3p",
            std::fs::read(&x3p).unwrap(),
            reader(Format::X3p),
            300,
            4096,
        ),
        (
            "metropro-1.dat",
            std::fs::read(specimens.join("metropro-1.dat")).unwrap(),
            reader(Format::MetroPro),
            60,
            1024,
        ),
        (
            "sur-2.sur",
            std::fs::read(specimens.join("sur-2.sur")).unwrap(),
            reader(Format::Sur),
            60,
            512,
        ),
        (
            "fuzz-datx-3tb-dataspace.datx",
            std::fs::read(fixtures.join("fuzz-datx-3tb-dataspace.datx")).unwrap(),
            reader(Format::Datx),
            100,
            4096,
        ),
    ];
    let kept = repo_root().join("target/fuzz-corpus-failures");
    let mut failures = Vec::new();
    for (name, seed, run, count, focus) in &seeds {
        // The seed itself is read (else the corpus tests nothing past the first check), but
        // for the fuzzer's own regression fixtures, which must be refused.
        let regression = name.starts_with("fuzz-");
        assert_eq!(run(seed), !regression, "the seed {name}");
        let mut m = Mutator(0x9e37_79b9_7f4a_7c15 ^ name.len() as u64);
        for k in 0..*count {
            let input = m.mutate(seed, *focus);
            let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| run(&input)));
            if outcome.is_err() {
                std::fs::create_dir_all(&kept).unwrap();
                let file = kept.join(format!("{name}-{k}"));
                std::fs::write(&file, &input).unwrap();
                failures.push(format!(
                    "{name} mutation #{k} panicked (kept as {})",
                    file.display()
                ));
            }
        }
    }
    entry::clean_scratch();
    assert!(failures.is_empty(), "{failures:#?}");
}
