//! `surfstream finish` and the `finish` graph node, end to end with the real engine
//! (LIGGGHTS, Debian package `liggghts`; scripts/test.sh installs it): a height-map file is
//! finished into wear maps, a worn surface, finish.json and finish.html; a graph runs the node
//! after the stitching with the ideal model beside it; a missing engine names its install
//! command. Few passes: each test takes seconds.

use surfstream_e2e::{read_json, repo_root, run, stderr, surfstream};

/// A rough .npy height map (um), 3 um pitch given on the command line.
fn rough_npy(path: &std::path::Path) {
    let (rows, cols) = (50, 60);
    let z: Vec<f64> = (0..rows * cols)
        .map(|k| {
            let (x, y) = ((k % cols) as f64 * 3.0, (k / cols) as f64 * 3.0);
            1.2 * (x / 17.0).sin() * (y / 23.0).cos() + 0.5 * (x / 5.0 + y / 9.0).sin()
        })
        .collect();
    surfstream_io::npy::write_npy_f64(path, &z, rows, cols).unwrap();
}

#[test]
fn finish_a_height_map_writes_wear_worn_surface_script_log_and_summary() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("rough.npy");
    rough_npy(&input);
    let out = dir.path().join("fin");
    let mut c = surfstream();
    c.args(["finish"])
        .arg(&input)
        .args([
            "--pitch-um",
            "3",
            "--patch-um",
            "90,75",
            "--cycles",
            "2",
            "--passes",
            "4",
        ])
        .args(["--calibrate", "1.272,0.565", "-o"])
        .arg(&out);
    let o = run(c);
    assert!(o.status.success(), "{}", stderr(&o));
    let err = stderr(&o);
    assert!(err.contains("finish: cycle 2/2"), "{err}");
    assert!(err.contains("ETA"), "no progress lines: {err}");
    let s = read_json(&out.join("finish.json"));
    assert_eq!(s["partial"], false);
    assert_eq!(s["cycles_completed"], 2);
    assert_eq!(
        s["setting"]["patch"]["rows_cols"],
        serde_json::json!([25, 30])
    );
    assert_eq!(s["setting"]["media"]["diameter_mm"], 3.0);
    assert!(s["setting"]["action"]["source"]
        .as_str()
        .unwrap()
        .contains("centrifugal barrel"));
    for k in ["Sa", "Sq", "Sz", "Spk", "Svk", "Sk"] {
        assert!(s["before"][k].as_f64().unwrap() > 0.0, "before.{k}");
        assert!(s["after"][k].as_f64().unwrap() > 0.0, "after.{k}");
    }
    assert!(s["after"]["Sa"].as_f64() < s["before"]["Sa"].as_f64());
    assert!(s["volume_check"]["relative_error"].as_f64().unwrap() < 0.005);
    assert!(s["calibration"]["k_finnie_fitted_per_pa"].as_f64().unwrap() > 0.0);
    assert!(s["timings"]["engine_s"].as_f64().unwrap() > 0.0);
    // The prediction (issue 38): at least 5 times up to the process time, what was fitted
    // named, both no-DEM baselines with the parameters of `after`, labels on stdout.
    let series = s["series"].as_array().unwrap();
    assert!(series.len() >= 5, "{series:?}");
    assert_eq!(series.last().unwrap()["time_s"], 300.0);
    for k in ["time_s", "Sa", "Sq", "Sz", "Spk", "Svk", "Sk"] {
        assert!(series[0][k].as_f64().unwrap() > 0.0, "series[0].{k}");
    }
    assert_eq!(series.last().unwrap()["Sa"], s["after"]["Sa"]);
    let fitted: Vec<&str> = s["fitted"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f.as_str().unwrap())
        .collect();
    assert!(fitted.contains(&"calibration.fit.scale"), "{fitted:?}");
    for b in ["constant_wear", "plateau"] {
        for k in ["Sa", "Sq", "Sz", "Spk", "Svk"] {
            assert!(
                s["baselines"][b]["after"][k].as_f64().unwrap() > 0.0,
                "{b}.{k}"
            );
        }
        assert_eq!(
            s["baselines"][b]["series"].as_array().unwrap().len(),
            series.len()
        );
    }
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        stdout.contains("(fitted)") && stdout.contains("(prediction)"),
        "{stdout}"
    );
    for f in [
        "wear.npy",
        "wear_finnie.npy",
        "wear_archard.npy",
        "worn.npy",
        "worn.x3p",
        "original.npy",
        "finish.html",
        "cycle_01/in.liggghts",
        "cycle_01/log.liggghts",
        "cycle_02/patch.stl",
    ] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    // The worn surface reads back (x3p with its pitch) and the wear map is on its grid.
    let worn = surfstream_io::formats::read_surface(&out.join("worn.x3p")).unwrap();
    assert_eq!((worn.height, worn.width), (25, 30));
    assert!((worn.pitch_x_um - 3.0).abs() < 1e-9);
    let wear = surfstream_io::npy::read_npy_f64(out.join("wear.npy")).unwrap();
    assert_eq!((wear.rows, wear.cols), (25, 30));
    assert!(wear.data.iter().all(|w| *w >= 0.0) && wear.data.iter().any(|w| *w > 0.0));
    // The script in the output reruns as it is.
    let script = std::fs::read_to_string(out.join("cycle_01/in.liggghts")).unwrap();
    assert!(script.contains("fix wall all mesh/surface/stress file patch.stl type 2 wear finnie"));
}

#[test]
fn a_missing_engine_names_its_install_command() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("rough.npy");
    rough_npy(&input);
    let mut c = surfstream();
    c.env("PATH", dir.path())
        .env_remove("SURFSTREAM_LIGGGHTS")
        .arg("finish")
        .arg(&input)
        .args(["--pitch-um", "3", "-o"])
        .arg(dir.path().join("fin"));
    let o = run(c);
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("apt-get install liggghts"),
        "{}",
        stderr(&o)
    );
}

#[test]
fn the_finish_node_runs_after_stitching_beside_the_ideal_model() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("g");
    let mut c = surfstream();
    c.args(["run", "launch/graphs/finish.toml"])
        .args(["--set", "stage.tile_px=256", "--set", "finish.passes=3"])
        .args(["--set", "finish.patch_um=[60]", "-o"])
        .arg(&out);
    let o = run(c);
    assert!(o.status.success(), "{}", stderr(&o));
    let s = read_json(&out.join("finish/finish.json"));
    assert_eq!(s["cycles_completed"], 2);
    let sim = s["ideal_model"]["sim_wear_maps"].as_f64().unwrap();
    assert!((-1.0..=1.0).contains(&sim), "{sim}");
    assert!(out.join("finish/ideal/in.liggghts").is_file());
    let r = read_json(&out.join("run.json"));
    assert!(
        r.to_string().contains("finish"),
        "run.json does not mention the node"
    );
    assert!(repo_root().join("launch/graphs/finish.toml").is_file());
    // The run's report.html has the finish section: wear map, profile, Abbott curves,
    // parameters beside the paper's and the calibration table, from finish/finish.json.
    let report = std::fs::read_to_string(out.join("report.html")).unwrap();
    let at = report
        .find("<section id=\"finish\">")
        .expect("no finish section in report.html");
    let section = &report[at..];
    for want in [
        "Wear depth along z",
        "Abbott-Firestone",
        "paper after 5 min",
        "<h3>Calibration</h3>",
        "Wear per contact measured by the DEM",
    ] {
        assert!(section.contains(want), "finish section lacks {want:?}");
    }
    assert!(!section.contains("Not shown"), "the finish section failed");
}

#[test]
fn ctrl_c_stops_the_engine_and_keeps_completed_cycles_marked_partial() {
    use std::io::{BufRead, BufReader};
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("rough.npy");
    rough_npy(&input);
    let out = dir.path().join("fin");
    let mut c = surfstream();
    c.args(["finish"])
        .arg(&input)
        .args(["--pitch-um", "3", "--patch-um", "90", "--cycles", "3"])
        .args(["--passes", "150", "--calibrate", "1.272,0.565", "-o"])
        .arg(&out)
        .stderr(std::process::Stdio::piped());
    let mut child = c.spawn().unwrap();
    let err = child.stderr.take().unwrap();
    let mut seen = Vec::new();
    // Wait until the first cycle is done and the second one is running, then Ctrl-C.
    // Keep reading to the end: a closed pipe would end surfstream by SIGPIPE instead.
    let mut sent = false;
    for line in BufReader::new(err).lines().map_while(Result::ok) {
        seen.push(line.clone());
        if !sent && line.starts_with("finish: cycle 2/3: pass") {
            // SAFETY: signalling the child this test started.
            unsafe {
                libc::kill(child.id() as i32, libc::SIGINT);
            }
            sent = true;
        }
    }
    let status = child.wait().unwrap();
    assert_eq!(status.code(), Some(130), "{}", seen.join("\n"));
    let s = read_json(&out.join("finish.json"));
    assert_eq!(s["partial"], true);
    assert_eq!(s["cycles_completed"], 1);
    assert!(out.join("worn.npy").is_file() && out.join("wear.npy").is_file());
    // The engine of cycle 2 was stopped: its wear was never written.
    assert!(!out.join("cycle_02/wear.vtk").exists());
}
