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
