//! What the engineer sees (issue 13): progress per tile, the verdict at the end, `--strict`,
//! parameters checked before anything is written, and one convention across the file verbs
//! (`-o/--out`, folders created, clear errors, fixed-precision numbers, a clean STL header).

use std::path::{Path, PathBuf};
use std::process::Output;

use surfstream_e2e::{read_json, run, stderr, surfstream, write_scan_dir};

fn stdout(out: &Output) -> String {
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// A real instrument file: tests/data/specimens, or the folder SURFSTREAM_SPECIMENS names.
fn specimen(name: &str) -> PathBuf {
    surfstream_e2e::specimen(name)
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// `surfstream <verb> launch/graphs/demo.toml` on 256 px tiles, fast, into `out`, plus `args`.
fn demo(verb: &str, out: &Path, args: &[&str]) -> Output {
    run({
        let mut c = surfstream();
        c.args([
            verb,
            "launch/graphs/demo.toml",
            "--set",
            "stage.tile_px=256",
        ])
        .args(["--set", "stage.pacing=fast", "-o"])
        .arg(out)
        .args(args);
        c
    })
}

/// 27850 -> "27 850", as the verdict prints counts.
fn grouped(n: u64) -> String {
    let d = n.to_string();
    let mut out = String::new();
    for (k, c) in d.chars().enumerate() {
        if k > 0 && (d.len() - k).is_multiple_of(3) {
            out.push(' ');
        }
        out.push(c);
    }
    out
}

/// A number with a unit is never in scientific notation ("1.3630563293e0 um").
fn assert_no_scientific(text: &str) {
    for w in text.split_whitespace() {
        let t = w.trim_matches(|c: char| !c.is_ascii_alphanumeric() && c != '.' && c != '-');
        let sci = t.split_once('e').is_some_and(|(m, e)| {
            !m.is_empty()
                && m.chars()
                    .all(|c| c.is_ascii_digit() || c == '.' || c == '-')
                && !e.is_empty()
                && e.trim_start_matches('-')
                    .chars()
                    .all(|c| c.is_ascii_digit())
        });
        assert!(!sci, "scientific notation {w:?} in:\n{text}");
    }
}

/// The progress lines of a 2 x 2 demo: one per tile, with its grid place, NCC and position.
fn assert_progress_per_tile(err: &str) {
    let lines: Vec<&str> = err.lines().filter(|l| l.starts_with("tile ")).collect();
    assert_eq!(lines.len(), 4, "one progress line per tile:\n{err}");
    // Serpentine: 0 (0,0), 1 (0,1), 2 (1,1), 3 (1,0); tile 0 is the anchor.
    for (k, (r, c)) in [(0, 0), (0, 1), (1, 1), (1, 0)].iter().enumerate() {
        let l = lines
            .iter()
            .find(|l| l.starts_with(&format!("tile {k}/4 ")))
            .unwrap_or_else(|| panic!("no line for tile {k}:\n{err}"));
        assert!(l.contains(&format!("row {r} x col {c}")), "{l}");
        assert!(l.contains(" um "), "{l}");
        if k == 0 {
            assert!(l.contains("anchor"), "{l}");
        } else {
            assert!(l.contains("NCC 0.9") && l.contains("registration"), "{l}");
        }
    }
}

/// `run` prints a line per tile and a verdict with Sa, Sq, Sz in um, the STL path and size
/// and Table 6's outcome; latency only with --verbose; --strict exits 3 on a failed Table 6
/// (a threshold no model meets) after writing every output, and 0 when the checks pass.
#[test]
fn run_prints_progress_and_a_verdict_and_strict_fails_on_a_failed_check() {
    let dir = tempfile::tempdir().unwrap();
    let out_dir = dir.path().join("new").join("run");
    let out = demo(
        "run",
        &out_dir,
        &["--strict", "--set", "deviation.threshold_percent=1000"],
    );
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let (text, err) = (stdout(&out), stderr(&out));
    assert_progress_per_tile(&err);
    let run_json = read_json(&out_dir.join("run.json"));
    let mesher = &run_json["stages"]["mesher"];
    let stl = out_dir.canonicalize().unwrap().join("surface.stl");
    for want in [
        "surface     Sa ".to_string(),
        " um, Sq ".into(),
        " um, Sz ".into(),
        format!("STL {}", stl.display()),
        format!("{} vertices", grouped(mesher["vertices"].as_u64().unwrap())),
        format!(
            "{} triangles",
            grouped(mesher["triangles"].as_u64().unwrap())
        ),
        "2 x 2 tiles (rows x cols): 4 by registration, 0 by stage fallback".into(),
        "deviation   PASS".into(),
        "verdict: PASS".into(),
    ] {
        assert!(
            text.contains(&want),
            "{want:?} missing from the verdict:\n{text}"
        );
    }
    // Sa in the verdict is run.json's, to the printed precision.
    let sa = run_json["deviation"]["stages"]["pooled"]["regions"]["panorama"]["measured"]["Sa"]
        .as_f64()
        .unwrap();
    let sa_text = surfstream_core::units::height(sa);
    assert!(text.contains(&format!("Sa {sa_text},")), "{text}");
    assert!(
        !text.contains("latency"),
        "latency only with --verbose:\n{text}"
    );
    assert_no_scientific(&text);

    // Every model stage fails a 0.001 % threshold: --strict exits 3, outputs still written.
    let strict_dir = dir.path().join("strict");
    let out = demo(
        "run",
        &strict_dir,
        &[
            "--strict",
            "--verbose",
            "--set",
            "deviation.threshold_percent=0.001",
        ],
    );
    assert_eq!(out.status.code(), Some(3), "{}", stderr(&out));
    let text = stdout(&out);
    assert!(text.contains("deviation   FAIL: "), "{text}");
    assert!(text.contains("beyond the limit of +/-0.00 %"), "{text}");
    assert!(
        text.contains("latency (ms)"),
        "--verbose shows latency:\n{text}"
    );
    assert!(
        stderr(&out).contains("--strict: 1 check(s) failed"),
        "{}",
        stderr(&out)
    );
    assert!(strict_dir.join("surface.stl").is_file());
    assert_eq!(
        read_json(&strict_dir.join("run.json"))["deviation"]["pass"],
        false
    );

    // Without --strict the same failure is reported but the exit status is 0.
    let lax_dir = dir.path().join("lax");
    let out = demo(
        "run",
        &lax_dir,
        &["--set", "deviation.threshold_percent=0.001"],
    );
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    assert!(stdout(&out).contains("verdict: FAIL"), "{}", stdout(&out));

    // The graph's STL says its unit and offset once, in a clean 80-byte header.
    let bytes = std::fs::read(&stl).unwrap();
    let header = String::from_utf8_lossy(&bytes[..80])
        .trim_end_matches('\0')
        .to_string();
    assert!(
        header.starts_with("surfstream surface, units=mm, offset_um="),
        "{header:?}"
    );
    assert_eq!(header.matches("units=").count(), 1, "{header:?}");
    assert!(
        bytes[header.len()..80].iter().all(|&b| b == 0),
        "{header:?}"
    );
}

/// `launch` shows the same progress: the launcher's observer subscribes to the matcher's
/// registrations over shared memory.
#[test]
fn launch_prints_progress_from_its_registrations_subscriber_and_a_verdict() {
    let dir = tempfile::tempdir().unwrap();
    let out_dir = dir.path().join("launch");
    let out = demo("launch", &out_dir, &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert_progress_per_tile(&stderr(&out));
    let text = stdout(&out);
    assert!(text.contains("surface.stl: "), "{text}");
    assert!(text.contains("verdict: "), "{text}");
    // The observer is the launcher's, not a node of the graph: run.json does not list it.
    let run_json = read_json(&out_dir.join("run.json"));
    let stages: Vec<&String> = run_json["stages"].as_object().unwrap().keys().collect();
    assert_eq!(
        stages,
        ["fusion", "matcher", "mesher", "recorder", "stage", "wavelet"],
        "{stages:?}"
    );
}

/// A bad node parameter is refused before "launched graph" and before the out dir exists,
/// for `launch`, `run` and `stitch` alike.
#[test]
fn invalid_node_parameters_are_refused_before_the_out_dir_is_touched() {
    let dir = tempfile::tempdir().unwrap();
    for (verb, set, named) in [
        ("launch", "fusion.method=\"bogus\"", "bogus"),
        ("run", "wavelet.pool_op=\"median\"", "median"),
        ("launch", "stage.rows=0", "rows"),
        ("run", "mesher.surface=\"datum\"", "datum"),
        ("launch", "recorder.compression=1", "compression"),
    ] {
        let out_dir = dir.path().join(verb).join("out");
        let out = run({
            let mut c = surfstream();
            c.args([verb, "launch/graphs/demo.toml", "--set", set, "-o"])
                .arg(&out_dir);
            c
        });
        let err = stderr(&out);
        assert_eq!(out.status.code(), Some(1), "{verb} --set {set}: {err}");
        assert!(err.contains(named), "{verb} --set {set}: {err}");
        assert!(
            !err.contains("launched graph") && !err.contains("running graph"),
            "{err}"
        );
        assert!(
            !out_dir.exists(),
            "{verb} --set {set} created {}",
            out_dir.display()
        );
        assert!(!dir.path().join(verb).exists(), "{verb}: parent created");
    }
}

/// convert writes with -o into folders that do not exist yet; the old positional output
/// still works with a deprecation warning; an unwritable extension lists what convert writes;
/// a folder given to inspect is named as a folder.
#[test]
fn convert_inspect_and_mesh_follow_one_convention() {
    let d = tempfile::tempdir().unwrap();
    let dat = specimen("metropro-1.dat");
    let x3p = d.path().join("a").join("b").join("m.x3p");
    let out = run({
        let mut c = surfstream();
        c.args(["convert", s(&dat), "-o", s(&x3p)]);
        c
    });
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(x3p.is_file());
    assert!(!stderr(&out).contains("deprecated"), "{}", stderr(&out));

    let npy = d.path().join("old").join("m.npy");
    let out = run({
        let mut c = surfstream();
        c.args(["convert", s(&dat), s(&npy)]);
        c
    });
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(npy.is_file());
    assert!(
        stderr(&out).contains("deprecated; write `convert IN -o"),
        "{}",
        stderr(&out)
    );

    let png = d.path().join("m.png");
    let out = run({
        let mut c = surfstream();
        c.args(["convert", s(&dat), "-o", s(&png)]);
        c
    });
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains("cannot write .png files; the formats convert writes are .x3p, .npy"),
        "{err}"
    );
    assert!(!png.exists());

    let out = run({
        let mut c = surfstream();
        c.args(["inspect", s(d.path())]);
        c
    });
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains("is a folder; inspect takes one height-map file"),
        "{err}"
    );
    assert!(!err.contains("unsupported format"), "{err}");

    // mesh: -o into a new folder, the bound the tolerance search chose, the default unit named
    // in the summary (no warning: nothing was assumed), fixed-precision numbers, and a header
    // that says units and offset once. (The file is tilted: judged on its roughness, without
    // the plane, its model needs 27 328 surface triangles, so the budget leaves room.)
    let stl = d.path().join("mesh").join("new").join("m.stl");
    let out = run({
        let mut c = surfstream();
        c.args(["mesh", s(&dat), "--max-triangles", "40000", "-o", s(&stl)]);
        c
    });
    let err = stderr(&out);
    assert!(out.status.success(), "{err}");
    assert!(!err.contains("warning"), "{err}");
    assert!(err.contains(" x Sq, the search's)"), "{err}");
    assert!(!err.contains(" = 0.05 x Sq"), "{err}");
    assert!(
        err.contains(" vertices, STL in mm (the default; --units m | mm | um);"),
        "{err}"
    );
    assert_no_scientific(&err);
    let bytes = std::fs::read(&stl).unwrap();
    let header = String::from_utf8_lossy(&bytes[..80])
        .trim_end_matches('\0')
        .to_string();
    assert!(
        header.starts_with("surfstream mesh, units=mm, offset_um="),
        "{header:?}"
    );
    assert_eq!(header.matches("units=").count(), 1, "{header:?}");
    let json = read_json(&stl.with_extension("json"));
    // [cols, rows], as run.json's mesher record.
    assert_eq!(json["grid_px"], serde_json::json!([640, 480]), "{json}");
}

/// `stitch` of a scan directory: progress lines take the grid from scan.toml, the verdict
/// follows, and heights of unitless tiles (.npy) taken as um are said to be.
#[test]
fn stitch_shows_progress_from_the_manifest_and_warns_of_an_assumed_height_unit() {
    let dir = tempfile::tempdir().unwrap();
    let scan = dir.path().join("scan");
    std::fs::create_dir(&scan).unwrap();
    // No height_unit: the .npy tiles' heights are taken as um.
    write_scan_dir(&scan, 1, 2, 256, None);
    let out_dir = dir.path().join("out");
    let out = run({
        let mut c = surfstream();
        c.arg("stitch").arg(&scan).arg("-o").arg(&out_dir);
        c
    });
    let err = stderr(&out);
    assert!(out.status.success(), "{err}");
    assert!(
        err.contains("warning: ")
            && err.contains("no [scan] height_unit")
            && err.contains("heights taken as um"),
        "{err}"
    );
    let lines: Vec<&str> = err.lines().filter(|l| l.starts_with("tile ")).collect();
    assert_eq!(lines.len(), 2, "{err}");
    assert!(
        lines
            .iter()
            .any(|l| l.starts_with("tile 1/2 ") && l.contains("row 0 x col 1")),
        "{err}"
    );
    let text = stdout(&out);
    assert!(text.contains("1 x 2 tiles (rows x cols)"), "{text}");
    assert!(text.contains("verdict: "), "{text}");
    // --height-unit states the unit of a folder of tiles without scan.toml (the Python
    // stitch(arrays, height_unit=) test runs it); a scan with its manifest says it there, and
    // an unknown unit is refused before anything runs.
    for (unit, said) in [
        (
            "nm",
            "has its own manifest: state the unit there ([scan] height_unit)",
        ),
        (
            "inch",
            "--height-unit \"inch\": expected one of um, nm, mm, m",
        ),
    ] {
        let out = run({
            let mut c = surfstream();
            c.arg("stitch")
                .arg(&scan)
                .args(["--height-unit", unit, "-o"])
                .arg(dir.path().join(unit));
            c
        });
        let err = stderr(&out);
        assert_eq!(out.status.code(), Some(1), "{err}");
        assert!(err.contains(said), "{err}");
        assert!(!dir.path().join(unit).exists(), "{err}");
    }
}

/// On a terminal the progress lines come with an indicatif bar (and its ETA) that is cleared
/// at the end; `script` (util-linux, in every Debian) gives the run a pseudo-terminal.
#[test]
fn on_a_terminal_progress_is_a_bar_above_the_lines() {
    let dir = tempfile::tempdir().unwrap();
    let bin = surfstream_e2e::bin_dir().join("surfstream");
    let cmd = format!(
        "{} run launch/graphs/demo.toml --set stage.tile_px=256 --set stage.pacing=fast -o {}",
        bin.display(),
        dir.path().join("out").display()
    );
    let out = run({
        let mut c = std::process::Command::new("script");
        c.current_dir(surfstream_e2e::repo_root())
            .args(["-qec", &cmd, "/dev/null"]);
        c
    });
    assert!(out.status.success(), "{}", stderr(&out));
    let tty = stdout(&out);
    assert!(tty.contains("/4 tiles registered"), "no bar:\n{tty}");
    assert!(tty.contains("ETA "), "no ETA:\n{tty}");
    assert_eq!(
        tty.lines().filter(|l| l.contains("row 1 x col 0")).count(),
        1,
        "each tile's line once:\n{tty}"
    );
    assert!(tty.contains("verdict: "), "{tty}");
}

/// `mesh --level` on a tilted plane plus roughness: without it the verb says the surface is
/// tilted (the tolerance, judged with the mean removed only, would see the tilt); with it the
/// least-squares plane is removed as `params --level` does, the record says so, the tolerance
/// is met on the levelled surface and the model keeps Sdr within 5 %.
#[test]
fn mesh_level_removes_the_tilt_and_the_model_keeps_the_roughness() {
    let d = tempfile::tempdir().unwrap();
    let (rows, cols) = (256usize, 256usize);
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let heights: Vec<f64> = (0..rows * cols)
        .map(|k| {
            let (y, x) = ((k / cols) as f64, (k % cols) as f64);
            // xorshift: deterministic noise of +/-0.05 um.
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            let noise = (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5;
            0.05 * x
                + 0.03 * y
                + 0.3 * (x * 0.7).sin() * (y * 0.9).cos()
                + 0.15 * (x * 0.23 + y * 0.31).sin()
                + 0.1 * noise
        })
        .collect();
    let npy = d.path().join("tilted.npy");
    surfstream_io::npy::write_npy_f64(&npy, &heights, rows, cols).unwrap();

    let raw = d.path().join("raw.stl");
    let out = run({
        let mut c = surfstream();
        c.args(["mesh", s(&npy), "--pitch-um", "1", "-o", s(&raw)]);
        c
    });
    let err = stderr(&out);
    assert!(out.status.success(), "{err}");
    assert!(err.contains("the surface is tilted"), "{err}");
    assert!(err.contains("--level"), "{err}");
    let json = read_json(&raw.with_extension("json"));
    assert!(json.get("form_removed").is_none(), "{json:#}");
    // The STL keeps the tilt, but the tolerance is judged without the plane (form before
    // roughness): met there, the plane stated, and the model keeps the roughness's Sdr.
    assert_eq!(json["tolerance"]["met"], true, "{json:#}");
    let plane = &json["tolerance"]["judged_plane"];
    let slope = |k: &str| plane[k].as_f64().unwrap_or(f64::NAN);
    assert!(
        (slope("slope_x_um_per_um") - 0.05).abs() < 2e-3
            && (slope("slope_y_um_per_um") - 0.03).abs() < 2e-3,
        "{json:#}"
    );
    assert!(
        err.contains("judged about its least-squares plane"),
        "{err}"
    );
    sdr_within_5_pct(&json);

    let levelled = d.path().join("levelled.stl");
    let out = run({
        let mut c = surfstream();
        c.args([
            "mesh",
            s(&npy),
            "--pitch-um",
            "1",
            "--level",
            "-o",
            s(&levelled),
        ]);
        c
    });
    let err = stderr(&out);
    assert!(out.status.success(), "{err}");
    assert!(
        err.contains("levelled: the least-squares plane removed"),
        "{err}"
    );
    assert!(!err.contains("the surface is tilted"), "{err}");
    let json = read_json(&levelled.with_extension("json"));
    assert_eq!(json["form_removed"], "least-squares plane", "{json:#}");
    assert_eq!(json["tolerance"]["met"], true, "{json:#}");
    // The bound is stated, pointwise included, on the levelled surface.
    assert_eq!(
        json["tolerance"]["tolerance"]["max_error_pct"], 50.0,
        "{json:#}"
    );
    sdr_within_5_pct(&json);
}

/// The mesh's Sdr (about the field's plane) within 5 % of the measured one, in a mesh record.
fn sdr_within_5_pct(json: &serde_json::Value) {
    let sdr = |k: &str| {
        json["fidelity"][k]["sdr_percent"]
            .as_f64()
            .unwrap_or(f64::NAN)
    };
    let (field, mesh) = (sdr("field"), sdr("mesh"));
    assert!(field > 0.5, "{json:#}");
    assert!(
        ((mesh - field) / field).abs() <= 0.05,
        "Sdr: mesh {mesh} %, measured {field} %"
    );
}
