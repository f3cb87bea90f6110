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

/// Runs a Python check (the test venv: numpy, scipy, surfalize) with `args`; asserts it
/// prints "ok".
fn python_check(script: &str, args: &[&Path]) {
    let out = std::process::Command::new(surfstream_e2e::python())
        .arg("-c")
        .arg(script)
        .args(args)
        .output()
        .expect("python runs");
    assert!(
        out.status.success() && String::from_utf8_lossy(&out.stdout).trim() == "ok",
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn prep_levels_like_surfalize_and_fits_polynomials_like_numpy() {
    let d = tempfile::tempdir().unwrap();
    let x3p = specimen("x3p-2.x3p");
    let plane = d.path().join("plane.npy");
    let text = ok(&["prep", s(&x3p), s(&plane), "--level", "plane"]);
    assert!(
        text.contains("level plane: least-squares polynomial of order 1"),
        "{text}"
    );
    assert!(text.contains("650 rows x 650 cols"), "{text}");
    // surfalize 0.19.2's level() on the same file (its reader agrees with ours on x3p).
    python_check(
        r#"
import sys, numpy as np, surfalize
ours = np.load(sys.argv[2])
ref = surfalize.Surface.load(sys.argv[1]).level().data
assert ours.shape == ref.shape, (ours.shape, ref.shape)
d = np.abs(ours - ref)
assert d.max() < 2e-5, d.max()  # um; heights span 0.55 um, the fit runs in f32 about the mean
print("ok")
"#,
        &[&x3p, &plane],
    );
    // Polynomial order 3 on the MetroPro specimen against numpy's least squares on the full
    // basis x^i y^j, i + j <= 3 (the heights from our own .npy: surfalize reads MetroPro 8x).
    let dat = specimen("metropro-1.dat");
    let (raw, poly) = (d.path().join("raw.npy"), d.path().join("poly.npy"));
    ok(&["convert", s(&dat), "-o", s(&raw)]);
    ok(&["prep", s(&dat), s(&poly), "--level", "poly=3"]);
    python_check(
        r#"
import sys, numpy as np
z = np.load(sys.argv[1]); ours = np.load(sys.argv[2]); p = 1.09825203
r, c = z.shape
y, x = np.mgrid[0:r, 0:c]
x = x * p; y = y * p
m = np.isfinite(z)
xs, ys = x.max(), y.max()
A = np.stack([(x[m]/xs)**i * (y[m]/ys)**j for i in range(4) for j in range(4) if i + j <= 3], 1)
coef, *_ = np.linalg.lstsq(A, z[m], rcond=None)
ref = np.full(z.shape, np.nan); ref[m] = z[m] - A @ coef
assert np.array_equal(np.isnan(ours), np.isnan(ref))
d = np.nanmax(np.abs(ours - ref))
assert d < 2e-5, d
print("ok")
"#,
        &[&raw, &poly],
    );
}

#[test]
fn prep_gaussian_at_a_cutoff_matches_scipy_inside_the_edges() {
    // ISO 16610-61 at lambda_c = 25 um on the anisotropic x3p-2 (0.128 x 0.315 um): the S-L
    // surface against scipy.ndimage.gaussian_filter with sigma = alpha lambda_c / sqrt(2 pi)
    // per axis, compared where the kernel's support lies inside the map (the edges are
    // where the implementations differ by design: ours renormalises, scipy reflects).
    let d = tempfile::tempdir().unwrap();
    let x3p = specimen("x3p-2.x3p");
    let (raw, rough) = (d.path().join("raw.npy"), d.path().join("rough.npy"));
    ok(&["convert", s(&x3p), "-o", s(&raw)]);
    let text = ok(&["prep", s(&x3p), s(&rough), "--filter", "l=25um"]);
    assert!(text.contains("filter gaussian,l=25um"), "{text}");
    python_check(
        r#"
import sys, math, numpy as np
from scipy import ndimage
z = np.load(sys.argv[1]); ours = np.load(sys.argv[2])
px, py, lc = 0.12765651, 0.314582114, 25.0
alpha = math.sqrt(math.log(2) / math.pi)
sx, sy = alpha * lc / math.sqrt(2 * math.pi) / px, alpha * lc / math.sqrt(2 * math.pi) / py
zc = z - z.mean()
mean = ndimage.gaussian_filter(zc, sigma=(sy, sx), mode="reflect", truncate=lc / (alpha * lc / math.sqrt(2 * math.pi)))
ref = zc - mean
mx, my = int(math.ceil(lc / px)), int(math.ceil(lc / py))
a, b = ours[my:-my, mx:-mx], ref[my:-my, mx:-mx]
assert a.size > 50000, a.shape
d = np.abs(a - b).max()
assert d < 1e-4 * (z.max() - z.min()), d
# and it is a high-pass: the long wavelengths are gone
assert abs(np.nanmean(ours)) < 1e-3
print("ok")
"#,
        &[&raw, &rough],
    );
}

#[test]
fn prep_crop_keeps_pitch_and_origin_and_fill_solves_laplace() {
    let d = tempfile::tempdir().unwrap();
    let x3p = specimen("x3p-2.x3p");
    let cut = d.path().join("cut.x3p");
    let text = ok(&["prep", s(&x3p), s(&cut), "--crop", "x=10:110,y=20:70"]);
    assert!(text.contains("50 x 100 (rows x cols) kept"), "{text}");
    let a: Value = serde_json::from_str(&ok(&["inspect", s(&x3p), "--json"])).unwrap();
    let b: Value = serde_json::from_str(&ok(&["inspect", s(&cut), "--json"])).unwrap();
    assert_eq!(
        (b["rows"].as_u64(), b["cols"].as_u64()),
        (Some(50), Some(100))
    );
    assert_eq!(a["pitch_x_um"], b["pitch_x_um"]);
    assert_eq!(a["pitch_y_um"], b["pitch_y_um"]);
    let origin = |v: &Value, k: usize| {
        v["metadata"]["stage_position_um"][k]
            .as_f64()
            .unwrap_or(0.0)
    };
    let px = a["pitch_x_um"].as_f64().unwrap();
    let py = a["pitch_y_um"].as_f64().unwrap();
    assert!(
        (origin(&b, 0) - origin(&a, 0) - 10.0 * px).abs() < 1e-9,
        "{b}"
    );
    assert!(
        (origin(&b, 1) - origin(&a, 1) - 20.0 * py).abs() < 1e-9,
        "{b}"
    );
    // The heights: surfalize's read of the source, sliced.
    python_check(
        r#"
import sys, numpy as np, surfalize
src = surfalize.Surface.load(sys.argv[1]).data[20:70, 10:110]
cut = surfalize.Surface.load(sys.argv[2]).data
assert cut.shape == (50, 100) and np.abs(cut - src).max() < 1e-9
print("ok")
"#,
        &[&x3p, &cut],
    );

    // Fill: a masked region of the real MetroPro map (one hole inside, one on the edge)
    // against scipy's sparse solve of the same discrete Laplace problem (4 neighbours,
    // measured points fixed, only the neighbours inside the map at its edge).
    let dat = specimen("metropro-1.dat");
    let (raw, holed, filled) = (
        d.path().join("raw.npy"),
        d.path().join("holed.npy"),
        d.path().join("filled.npy"),
    );
    ok(&["convert", s(&dat), "-o", s(&raw)]);
    python_check(
        r#"
import sys, numpy as np
z = np.load(sys.argv[1])
z[100:130, 200:260] = np.nan
z[0:12, 500:540] = np.nan
np.save(sys.argv[2], z)
print("ok")
"#,
        &[&raw, &holed],
    );
    let text = ok(&[
        "prep",
        s(&holed),
        s(&filled),
        "--pitch-um",
        "1.09825203",
        "--fill",
        "laplace",
    ]);
    assert!(
        text.contains("2280 not-measured points given the Laplace"),
        "{text}"
    );
    assert!(text.contains("converged"), "{text}");
    python_check(
        r#"
import sys, numpy as np
from scipy.sparse import lil_matrix
from scipy.sparse.linalg import spsolve
z = np.load(sys.argv[1]); ours = np.load(sys.argv[2])
r, c = z.shape
holes = np.argwhere(np.isnan(z))
idx = {(int(i), int(j)): k for k, (i, j) in enumerate(holes)}
A = lil_matrix((len(holes), len(holes))); b = np.zeros(len(holes))
for k, (i, j) in enumerate(holes):
    nb = [(i + di, j + dj) for di, dj in ((0, 1), (0, -1), (1, 0), (-1, 0)) if 0 <= i + di < r and 0 <= j + dj < c]
    A[k, k] = len(nb)
    for q in nb:
        if q in idx: A[k, idx[q]] -= 1
        else: b[k] += z[q]
x = spsolve(A.tocsr(), b)
ref = z.copy(); ref[tuple(holes.T)] = x
assert not np.isnan(ours).any()
m = ~np.isnan(z)
assert np.array_equal(ours[m], z[m])
d = np.abs(ours - ref).max()
assert d < 1e-6, d
print("ok")
"#,
        &[&holed, &filled],
    );
}

#[test]
fn prep_threshold_outliers_rotate_count_and_refuse_clearly() {
    let d = tempfile::tempdir().unwrap();
    let sur = specimen("sur-2.sur");
    let out = d.path().join("t.npy");
    let js = ok(&[
        "prep",
        s(&sur),
        s(&out),
        "--json",
        "--threshold",
        "1,2",
        "--outliers",
        "median,3",
        "--rotate",
        "90",
    ]);
    let v: Value = serde_json::from_str(&js).unwrap();
    // 484 x 563 with 117 not measured: at most 1 % and 2 % of 272375 measured points (by
    // value: heights equal to a threshold's are kept, and these are integer steps).
    let t = v["steps"][0]["points_removed"].as_u64().unwrap();
    assert!(t > 0 && t <= 2723 + 5447, "{js}");
    assert!(v["steps"][1]["points_removed"].as_u64().is_some());
    assert_eq!(
        (v["rows"].as_u64(), v["cols"].as_u64()),
        (Some(563), Some(484))
    );
    let removed: u64 = (0..2)
        .map(|k| v["steps"][k]["points_removed"].as_u64().unwrap())
        .sum();
    assert_eq!(v["invalid_points"].as_u64(), Some(117 + removed), "{js}");
    // Bad input: named, nothing written.
    let never = d.path().join("never.npy");
    for (args, want) in [
        (vec!["--level", "cone"], "expected plane, poly=N"),
        (vec!["--filter", "l=-5um"], "positive length"),
        (vec!["--crop", "x=600:700"], "leave nothing"),
        (vec!["--smooth", "3"], "unknown step"),
        (vec!["plane"], "is not a step"),
    ] {
        let mut a = vec!["prep", s(&sur), s(&never)];
        a.extend(args);
        let err = fails(&a);
        assert!(err.contains(want), "{a:?}: {err}");
        assert!(!never.exists());
    }
    let err = fails(&["prep", s(&sur), "x.png", "--level", "plane"]);
    assert!(err.contains("prep writes .x3p"), "{err}");
}
