//! Issue 35, outputs a 20 x 20 user can keep: float32 `.npy` where the heights are float32,
//! the `model` output set (`--outputs`, a graph's `[outputs]`) against the full one, and a
//! model run never removing a file the run did not make (a recording replayed into its own
//! out dir).

use std::path::Path;

use serde_json::Value;
use surfstream_e2e::*;

/// The dtype a `.npy` header names ("<f4", "<f8").
fn descr(path: &Path) -> String {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let head = String::from_utf8_lossy(&bytes[..128.min(bytes.len())]).into_owned();
    let at = head.find("'descr': '").expect("a .npy header") + "'descr': '".len();
    head[at..at + 3].to_string()
}

fn files_of(run: &Value) -> Vec<String> {
    run["files"]
        .as_array()
        .expect("run.json files")
        .iter()
        .map(|f| f.as_str().unwrap().to_string())
        .collect()
}

#[test]
fn the_model_set_keeps_the_stl_report_and_records_and_the_full_set_everything() {
    let dir = tempfile::tempdir().unwrap();
    let (full, model) = (dir.path().join("full"), dir.path().join("model"));
    small_demo(&full, &[]);
    small_demo(&model, &["--outputs", "model"]);

    // Full: the arrays as float32 (the simulated stage's frames carry no z offset), numpy
    // reads them as the absolute heights our reader gives.
    for f in [
        "panorama.npy",
        "datum.npy",
        "pooled.npy",
        "mesh_resampled.npy",
        "roughness.npy",
    ] {
        assert_eq!(descr(&full.join(f)), "<f4", "{f}");
    }
    let script = r#"
import sys, numpy as np
for f in ["panorama", "datum", "pooled", "mesh_resampled"]:
    a = np.load(sys.argv[1] + "/" + f + ".npy")
    assert a.dtype == np.float32 and a.ndim == 2, (f, a.dtype, a.shape)
    assert np.isfinite(a).sum() > 0.5 * a.size, f
print("numpy ok")
"#;
    let o = run({
        let mut c = std::process::Command::new(python());
        c.arg("-c").arg(script).arg(&full);
        c
    });
    assert!(o.status.success(), "numpy check failed:\n{}", stderr(&o));

    let (rf, rm) = (
        read_json(&full.join("run.json")),
        read_json(&model.join("run.json")),
    );
    assert_eq!(rf["outputs"]["set"], "full");
    assert_eq!(rf["outputs"]["removed"], serde_json::json!([]));
    assert_eq!(rm["outputs"]["set"], "model");
    // run.json lists only files that exist, in both sets.
    for (out, run) in [(&full, &rf), (&model, &rm)] {
        for f in files_of(run) {
            assert!(
                out.join(&f).is_file(),
                "{}: {f} listed, not there",
                out.display()
            );
        }
    }
    let kept = files_of(&rm);
    for f in [
        "surface.stl",
        "run.json",
        "truth.json",
        "panorama.tiles.json",
        "graph.resolved.json",
        "nodes/mesher.json",
    ] {
        assert!(kept.iter().any(|k| k == f), "model set lost {f}: {kept:?}");
    }
    assert!(model.join("report.html").is_file());
    assert!(model.join("report_maps/panorama.png").is_file() || !full.join("report_maps").exists());
    let removed: Vec<&str> = rm["outputs"]["removed"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap())
        .collect();
    for f in [
        "panorama.npy",
        "panorama.npy.json",
        "datum.npy",
        "roughness.npy",
        "pooled.npy",
        "mesh_resampled.npy",
        "panorama.png",
        "recording.mcap",
    ] {
        assert!(removed.contains(&f), "{f} not removed: {removed:?}");
        assert!(!model.join(f).exists(), "{f} still there");
    }
    assert!(
        !model.join("panorama.x3p").exists(),
        "the model set writes no x3p"
    );
    assert!(full.join("panorama.x3p").is_file());
    let bytes: u64 = removed
        .iter()
        .map(|f| {
            std::fs::metadata(full.join(f))
                .map(|m| m.len())
                .unwrap_or(0)
        })
        .sum();
    // The same files of the full run: equal but for the recording, whose JSON carries the
    // run's own times (its compressed size moves by some bytes).
    let said = rm["outputs"]["removed_bytes"].as_u64().unwrap();
    assert!(
        said.abs_diff(bytes) < 10_000 && said > 1_000_000,
        "removed_bytes {said}, the full run's same files {bytes}"
    );

    // The same model: the STL and Table 6 do not depend on the set.
    assert!(
        std::fs::read(full.join("surface.stl")).unwrap()
            == std::fs::read(model.join("surface.stl")).unwrap(),
        "surface.stl differs between the sets"
    );
    assert_eq!(rf["deviation"], rm["deviation"]);
    // The report of the model run names no removed file.
    let html = std::fs::read_to_string(model.join("report.html")).unwrap();
    for f in &removed {
        assert!(!html.contains(&format!("href=\"{f}\"")), "report links {f}");
    }
}

#[test]
fn a_graphs_outputs_table_chooses_the_set_and_a_model_run_keeps_what_it_did_not_make() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("rec");
    small_demo(&out, &[]);
    let rec = out.join("recording.mcap");
    let before = std::fs::read(&rec).unwrap();
    // The replay graph with `[outputs] set = "model"`, replaying the recording into its own
    // out dir: the recording is the run's input, carried into the new run, and stays.
    let text = std::fs::read_to_string(repo_root().join("launch/graphs/replay.toml")).unwrap();
    let graph = dir.path().join("replay_model.toml");
    std::fs::write(&graph, format!("{text}\n[outputs]\nset = \"model\"\n")).unwrap();
    let o = run({
        let mut cmd = surfstream();
        cmd.arg("run")
            .arg(&graph)
            .args(["--set"])
            .arg(format!("stage.path={:?}", rec.to_str().unwrap()))
            .args(["--set", "stage.pacing=\"fast\"", "--out"])
            .arg(&out);
        cmd
    });
    assert!(o.status.success(), "{}", stderr(&o));
    let r = read_json(&out.join("run.json"));
    assert_eq!(r["outputs"]["set"], "model");
    assert_eq!(
        std::fs::read(&rec).unwrap(),
        before,
        "the replayed recording changed"
    );
    assert!(files_of(&r).iter().any(|f| f == "recording.mcap"));
    assert!(!out.join("panorama.npy").exists());
    assert!(out.join("surface.stl").is_file());
    // --outputs full over the graph's table.
    let full = dir.path().join("full");
    let o = run({
        let mut cmd = surfstream();
        cmd.arg("run")
            .arg(&graph)
            .args(["--set"])
            .arg(format!("stage.path={:?}", rec.to_str().unwrap()))
            .args([
                "--set",
                "stage.pacing=\"fast\"",
                "--outputs",
                "full",
                "--out",
            ])
            .arg(&full);
        cmd
    });
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(full.join("panorama.npy").is_file());
    assert_eq!(read_json(&full.join("run.json"))["outputs"]["set"], "full");
    // A bad set is refused, naming what is expected.
    let o = run({
        let mut cmd = surfstream();
        cmd.args([
            "run",
            "launch/graphs/demo.toml",
            "--outputs",
            "small",
            "--out",
        ])
        .arg(dir.path().join("bad"));
        cmd
    });
    assert!(!o.status.success());
    assert!(stderr(&o).contains("model"), "{}", stderr(&o));
    assert!(!dir.path().join("bad").exists());
}

#[test]
fn compare_fusion_keeps_the_chosen_output_set_for_every_method() {
    // `stitch --compare-fusion` stitches once per fusion method: each run keeps the set
    // `--outputs` chose, as a plain stitch does (it used to ignore the flag).
    let dir = tempfile::tempdir().unwrap();
    let (scan, out) = (dir.path().join("scan"), dir.path().join("out"));
    std::fs::create_dir(&scan).unwrap();
    write_scan_dir(&scan, 1, 2, 256, Some("um"));
    let o = run({
        let mut c = surfstream();
        c.arg("stitch").arg(&scan).arg("-o").arg(&out);
        c.args(["--compare-fusion", "--outputs", "model"]);
        c
    });
    assert!(o.status.success(), "compare-fusion failed:\n{}", stderr(&o));
    for m in ["average", "gradual", "wavelet"] {
        let r = read_json(&out.join(m).join("run.json"));
        assert_eq!(r["outputs"]["set"], "model", "{m}");
        assert!(out.join(m).join("surface.stl").is_file(), "{m}");
        assert!(!out.join(m).join("panorama.npy").exists(), "{m}");
    }

    // With the specimen beside the scan, the height error needs each panorama.npy: the model
    // set is refused before anything runs, naming the files and the way out.
    std::fs::write(scan.join("specimen.npy"), b"not read").unwrap();
    let out2 = dir.path().join("out2");
    let o = run({
        let mut c = surfstream();
        c.arg("stitch").arg(&scan).arg("-o").arg(&out2);
        c.args(["--compare-fusion", "--outputs", "model"]);
        c
    });
    let e = stderr(&o);
    assert!(!o.status.success());
    assert!(
        e.contains("specimen.npy") && e.contains("--outputs full"),
        "{e}"
    );
    assert!(!out2.join("average").exists(), "nothing run: {e}");
}
