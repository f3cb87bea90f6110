//! The single-file verbs, run as a user runs them: the release `surfstream` binary on the real
//! instrument files in tests/data/specimens and on files the verbs write for each other.

use std::path::{Path, PathBuf};

use serde_json::Value;
use surfstream_e2e::{read_json, run, stderr, surfstream};

/// A real instrument file: tests/data/specimens, or the folder SURFSTREAM_SPECIMENS names.
fn specimen(name: &str) -> PathBuf {
    surfstream_e2e::specimen(name)
}

/// Runs `surfstream ARGS`, asserts success, returns stdout.
fn ok(args: &[&str]) -> String {
    let out = run({
        let mut c = surfstream();
        c.args(args);
        c
    });
    assert!(out.status.success(), "{args:?} failed: {}", stderr(&out));
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// Runs `surfstream ARGS`, asserts a clean failure (exit 1, no panic), returns stderr.
fn fails(args: &[&str]) -> String {
    let out = run({
        let mut c = surfstream();
        c.args(args);
        c
    });
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(1), "{args:?}: {err}");
    assert!(!err.contains("panicked"), "{err}");
    err
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn params(file: &Path) -> Value {
    serde_json::from_str(&ok(&["params", s(file), "--json"])).unwrap()
}

fn rel(a: f64, b: f64) -> f64 {
    (a - b).abs() / b.abs()
}

#[test]
fn inspect_params_and_convert_on_a_metropro_file() {
    let dat = specimen("metropro-1.dat");
    let text = ok(&["inspect", s(&dat)]);
    assert!(text.contains("480 rows x 640 cols"), "{text}");
    assert!(text.contains("metropro"), "{text}");

    // The specimens README's reference (formats.md: height = phase * S * O * lambda / R).
    let p = params(&dat);
    let keys: Vec<&str> = p.as_object().unwrap().keys().map(|k| k.as_str()).collect();
    for k in ["Sa", "Sq", "Sp", "Sv", "Sz", "Ssk", "Sku", "Sdq", "Sdr"] {
        assert!(keys.contains(&k), "{k} missing from {keys:?}");
    }
    // The record also says which file, its shape and pitch, and each parameter's unit; without
    // --all exactly these nine parameters.
    assert_eq!(p["units"].as_object().unwrap().len(), 9, "{keys:?}");
    assert_eq!(p["units"]["Sa"], "um");
    assert_eq!(p["units"]["Sdr"], "%");
    assert_eq!(p["rows"], 480);
    assert_eq!(p["pitch_assumed"], false);
    let sq = p["Sq"].as_f64().unwrap();
    assert!(rel(sq, 0.07528822204734589) < 1e-9, "Sq {sq}");

    // Through .x3p and back: the same parameters; missing output folders are created.
    let d = tempfile::tempdir().unwrap();
    let x3p = d.path().join("new").join("deeper").join("m.x3p");
    ok(&["convert", s(&dat), "-o", s(&x3p)]);
    let q = params(&x3p);
    for k in ["Sa", "Sq", "Sz", "Sdq", "Sdr"] {
        let (a, b) = (p[k].as_f64().unwrap(), q[k].as_f64().unwrap());
        assert!(rel(b, a) < 1e-9, "{k}: {a} vs {b} after .x3p");
    }
    let cmp = ok(&["compare", s(&dat), s(&x3p)]);
    assert!(cmp.contains("SIM   1.000000 "), "{cmp}");
}

#[test]
fn separate_then_mesh_a_real_specimen() {
    let d = tempfile::tempdir().unwrap();
    let sep = d.path().join("sep");
    let dat = specimen("metropro-1.dat");
    ok(&[
        "separate",
        s(&dat),
        "--wavelet",
        "sym5",
        "--level",
        "auto",
        "--pool",
        "4",
        "--out",
        s(&sep),
    ]);
    let summary = read_json(&sep.join("separate.json"));
    let level = summary["level"].as_u64().unwrap();
    let curve = summary["energy_curve"].as_array().unwrap();
    assert!(level >= 1 && curve.len() >= level as usize, "{summary}");
    assert_eq!(summary["wavelet"], "sym5");

    // datum + roughness = the measured heights (f32 round-off of heights ~50 um up, offset kept).
    let py = surfstream_e2e::python();
    let check = r#"
import sys, numpy as np
d = np.load(sys.argv[1] + "/datum.npy"); r = np.load(sys.argv[1] + "/roughness.npy")
p = np.load(sys.argv[1] + "/pooled.npy")
assert d.shape == (480, 640) and r.shape == (480, 640) and p.shape == (120, 160), (d.shape, r.shape, p.shape)
assert 50.0 < np.nanmean(d) < 51.5, np.nanmean(d)      # absolute heights, like the file
assert abs(float(np.nanmean(r))) < 1e-3, np.nanmean(r)  # roughness has no offset
"#;
    let out = run({
        let mut c = std::process::Command::new(py);
        c.args(["-c", check, s(&sep)]);
        c
    });
    assert!(out.status.success(), "{}", stderr(&out));

    // The pooled map as a DEM wall: the error bound holds, the solid is closed.
    let stl = d.path().join("wall.stl");
    ok(&[
        "mesh",
        s(&sep.join("pooled.npy")),
        "--epsilon-um",
        "0.005",
        // No --pitch-um: pooled.npy carries its pitch (pooled.npy.json, 4 x the input's).
        "--solid",
        "--out",
        s(&stl),
    ]);
    let m = read_json(&d.path().join("wall.json"));
    // The pooled map's pitch came with it: 4 x metropro-1's 1.0983 um.
    let pitch = m["pitch_um"][0].as_f64().unwrap();
    assert!((pitch - 4.393).abs() < 1e-3, "{m}");
    assert_eq!(m["watertight"], true, "{m}");
    assert_eq!(m["fidelity"]["bound_met"], true, "{m}");
    assert!(
        m["fidelity"]["error"]["max_um"].as_f64().unwrap() <= 0.005,
        "{m}"
    );
    assert!(std::fs::metadata(&stl).unwrap().len() > 84);

    // The file at its default tolerance, judged on the heights, then also on the roughness
    // the mesh carries against the separated roughness: the second needs more triangles and
    // keeps the roughness within its 5 % in every window.
    let tolerance = |extra: &[&str], name: &str| {
        let stl = d.path().join(name);
        let mut args = vec!["mesh", s(&dat), "--out", s(&stl)];
        args.extend_from_slice(extra);
        ok(&args);
        read_json(&stl.with_extension("json"))["tolerance"].clone()
    };
    let heights_only = tolerance(&[], "heights.stl");
    let rough = sep.join("roughness.npy");
    let with_roughness = tolerance(&["--roughness", s(&rough)], "rough.stl");
    assert!(
        heights_only["tolerance"].get("roughness_pct").is_none(),
        "{heights_only}"
    );
    assert_eq!(with_roughness["tolerance"]["roughness_pct"], 5.0);
    assert_eq!(with_roughness["met"], true, "{with_roughness}");
    for w in with_roughness["region_fits"].as_array().unwrap() {
        for d in w["roughness_deviation_pct"].as_array().unwrap() {
            assert!(d.as_f64().unwrap().abs() <= 5.0, "{w}");
        }
    }
    assert!(
        with_roughness["surface_triangles"].as_u64() > heights_only["surface_triangles"].as_u64(),
        "{heights_only} vs {with_roughness}"
    );
}

#[test]
fn single_file_verbs_refuse_bad_input_by_name() {
    let d = tempfile::tempdir().unwrap();
    let missing = d.path().join("nowhere.npy");
    let err = fails(&["inspect", s(&missing)]);
    assert!(err.contains("nowhere.npy"), "{err}");

    let junk = d.path().join("junk.x3p");
    std::fs::write(&junk, b"PK\x03\x04 not really a zip").unwrap();
    let err = fails(&["params", s(&junk)]);
    assert!(err.contains("junk.x3p"), "{err}");

    let dat = specimen("metropro-1.dat");
    let out = d.path().join("sep");
    let err = fails(&[
        "separate",
        s(&dat),
        "--wavelet",
        "haar9",
        "--level",
        "2",
        "--out",
        s(&out),
    ]);
    assert!(err.contains("haar9"), "{err}");
    assert!(
        !out.join("datum.npy").exists(),
        "nothing written on a refused option"
    );

    let stl = d.path().join("w.stl");
    let err = fails(&["mesh", s(&dat), "--epsilon-um=-1", "--out", s(&stl)]);
    assert!(err.contains("epsilon"), "{err}");
    assert!(!stl.exists());
}
