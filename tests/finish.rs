//! `surfstream finish` and the `finish` graph node, end to end with the real engine
//! (LIGGGHTS, Debian package `liggghts`; scripts/test.sh installs it): a height-map file is
//! finished into wear maps, a worn surface, finish.json and finish.html; a graph runs the node
//! after the stitching with the ideal model beside it; a missing engine names its install
//! command; the default path, the machine run (a scaled drum) and then the micro passes on
//! the tolerance mesh, with the ideal model and a shifted after-finish scan registered to the
//! model. Few passes and short simulated times: each test takes seconds to a minute or two.

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
        // The one-medium segment on the kinematics' rates (the macro run: its own test).
        .arg("--no-macro")
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
    // No macro run: the barrel's assumed action sets the passes, and says so.
    assert_eq!(s["setting"]["action_used"], true);
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
        .args([
            "--set",
            "finish.patch_um=[60]",
            "--set",
            "finish.macro=false",
            "-o",
        ])
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
        .args([
            "--no-macro",
            "--pitch-um",
            "3",
            "--patch-um",
            "90",
            "--cycles",
            "3",
        ])
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

/// The default `finish`: the macro run first (here a scaled drum: 504 media, 0.3 s recorded),
/// its contact samples driving micro passes on the tolerance-meshed patch, for the model and
/// the ideal model alike; a measured after-finish scan, shifted as a re-mounted part is, is
/// registered to the model. finish.json carries the names the issue fixes.
#[test]
fn the_default_finish_runs_the_machine_then_micro_passes_and_registers_the_after_scan() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("rough.npy");
    rough_npy(&input);
    // The ideal model: the same grid, form only (flat).
    let ideal = dir.path().join("ideal.npy");
    surfstream_io::npy::write_npy_f64(&ideal, &vec![0.0; 50 * 60], 50, 60).unwrap();
    // The after-finish scan: the surface with its peaks cut, measured 4 px right and 3 px
    // down of the model's origin (its pixel (0, 0) is the model's (3, 4)), 44 x 52 px.
    let after = dir.path().join("after.npy");
    let (rows, cols) = (44, 52);
    let z: Vec<f64> = (0..rows * cols)
        .map(|k| {
            let (x, y) = (((k % cols) + 4) as f64 * 3.0, ((k / cols) + 3) as f64 * 3.0);
            (1.2 * (x / 17.0).sin() * (y / 23.0).cos() + 0.5 * (x / 5.0 + y / 9.0).sin()).min(1.0)
        })
        .collect();
    surfstream_io::npy::write_npy_f64(&after, &z, rows, cols).unwrap();
    let machine = dir.path().join("small.toml");
    std::fs::write(
        &machine,
        "drum_radius_mm = 15.0\ndrum_height_mm = 24.0\nsettle_s = 0.1\nrecord_s = 0.3\n\
         [part]\nshape = \"plate\"\nwidth_mm = 12.0\nlength_mm = 12.0\n",
    )
    .unwrap();
    let out = dir.path().join("fin");
    let mut c = surfstream();
    c.args(["finish"])
        .arg(&input)
        .args(["--pitch-um", "3", "--patch-um", "60", "--cycles", "2"])
        .args(["--passes", "4", "--calibrate", "1.272,0.565", "--machine"])
        .arg(&machine)
        .arg("--ideal")
        .arg(&ideal)
        .arg("--after")
        .arg(&after)
        .arg("-o")
        .arg(&out);
    let o = run(c);
    let err = stderr(&o);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("registered to the model"), "{err}");
    let s = read_json(&out.join("finish.json"));
    let m = &s["macro"];
    assert_eq!(m["engine"], "liggghts");
    assert_eq!(m["media_count"], 504);
    assert!((m["simulated_s"].as_f64().unwrap() - 0.3).abs() < 1e-3);
    let c = &m["contacts"];
    assert!(c["rate_per_mm2_s"].as_f64().unwrap() > 0.0, "{c}");
    for k in ["normal_speed_m_s", "tangential_speed_m_s", "normal_force_n"] {
        for p in ["p10", "p50", "p90"] {
            assert!(c[k][p].as_f64().is_some(), "macro.contacts.{k}.{p}");
        }
    }
    assert!(c["sliding_work_j_per_mm2_s"].as_f64().unwrap() > 0.0);
    assert!(s["cycle_path"]
        .as_str()
        .unwrap()
        .starts_with("micro passes"));
    let pm = &s["patch"]["model"];
    assert!(pm["surface_triangles"].as_u64().unwrap() > 0);
    assert!(pm["max_error_over_sq"].as_f64().unwrap().is_finite());
    assert!(s["wear_laws"]["rates_from"]
        .as_str()
        .unwrap()
        .starts_with("the macro run"));
    // p(gap) comes from the same contacts the passes draw: its reach is theirs.
    let cf = &s["contact_field"];
    let sampled = &cf["approach"];
    assert_eq!(sampled["source"], "macro-samples", "{cf}");
    assert!(sampled["contacts"].as_u64().unwrap() > 0, "{cf}");
    assert!(
        cf["reach_um"].as_f64().unwrap() >= sampled["max_um"].as_f64().unwrap(),
        "{cf}"
    );
    assert!(cf["approach_model"]
        .as_str()
        .unwrap()
        .starts_with("p(gap) = the share of the macro run's contact samples"));
    assert!(cf["impact_rate_model"]
        .as_str()
        .unwrap()
        .starts_with("the macro run"));
    assert!(cf["envelope"]["sa_um"].as_f64().unwrap() > 0.0, "{cf}");
    // Each cycle's sliding passes: the DEM's Archard volume beside K/H F s on a flat.
    for c in s["cycles"].as_array().unwrap() {
        let m = &c["micro"];
        if m["sliding"].as_u64().unwrap() > 0 {
            assert!(m["archard_over_flat"].as_f64().unwrap() > 0.0, "{m}");
            assert!(m["archard_flat_um3"].as_f64().unwrap() > 0.0, "{m}");
        }
    }
    // The passes drew the macro run's contacts: the barrel's assumed speed and pressure are
    // labelled as not used, and the time step is the passes' own.
    let st = &s["setting"];
    assert_eq!(st["action_used"], false, "{st}");
    assert!(st["contacts_from"]
        .as_str()
        .unwrap()
        .starts_with("the macro run's"));
    assert_eq!(st["timestep_s"], s["cycles"][0]["timestep_s"], "{st}");
    assert!(
        err.contains("contacts drawn from the macro run's") && !err.contains("m/s, 3997 Pa"),
        "{err}"
    );
    // The table used and the one measured, with the bins the monotone pooling joined.
    let table = &cf["table"];
    assert!(table["pooled_bins"].as_u64().is_some(), "{table}");
    for b in table["bins"].as_array().unwrap() {
        assert!(
            b["measured_wear_per_contact_um"].as_f64().unwrap() >= 0.0,
            "{b}"
        );
        assert!(b["pooled"].is_boolean(), "{b}");
    }
    // The micro passes' volume check says how much wear went to the nearest sample.
    for c in s["cycles"].as_array().unwrap() {
        let v = &c["volume_check"];
        assert!(v["to_nearest_sample_um3"].as_f64().unwrap() >= 0.0, "{v}");
    }
    // The fit is judged where it holds (the calibration time).
    let cal = &s["calibration"];
    assert_eq!(
        cal["sa_after_um"].as_f64(),
        cal["fit"]["sa_after_um"].as_f64(),
        "{cal}"
    );
    // The macro run is engine time of this job; the overhead is what is left.
    let t = &s["timings"];
    let macro_s = t["macro_engine_s"].as_f64().unwrap();
    assert!(
        macro_s > 0.0 && macro_s < t["engine_s"].as_f64().unwrap(),
        "{t}"
    );
    // The ideal model ran the same micro passes.
    assert!(out.join("ideal/group_01/in.liggghts").is_file());
    assert!(
        !out.join("ideal/in.liggghts").exists(),
        "the ideal model ran the one-medium segment"
    );
    assert!(
        s["ideal_model"]["sim_wear_maps"].as_f64().is_some(),
        "{}",
        s["ideal_model"]
    );
    // The after scan: found at its offset, and compared with the prediction.
    let r = &s["after_registrations"][0];
    assert_eq!(r["role"], "after");
    assert!(
        (r["offset_px"][0].as_f64().unwrap() - 4.0).abs() < 0.2,
        "{r}"
    );
    assert!(
        (r["offset_px"][1].as_f64().unwrap() - 3.0).abs() < 0.2,
        "{r}"
    );
    assert!(
        s["sim"]["worn_vs_measured_after"].as_f64().is_some(),
        "{}",
        s["sim"]
    );
    let html = std::fs::read_to_string(out.join("finish.html")).unwrap();
    for want in [
        "The machine (macro run)",
        "Patch model (first cycle)",
        "media velocity (assumed, not used)",
        "registered to the model",
    ] {
        assert!(html.contains(want), "finish.html lacks {want:?}");
    }
}

/// An engine that fails (here a stand-in that writes LIGGGHTS' kind of ERROR line and exits
/// 1): the command fails naming the error, OUT holds the FAILED record and the engine's script
/// and log, and none of the outputs (no finish.json beside half a run).
#[test]
fn a_failing_engine_leaves_a_failed_record_and_its_logs_not_half_an_output() {
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("rough.npy");
    rough_npy(&input);
    let engine = dir.path().join("liggghts");
    std::fs::write(
        &engine,
        "#!/bin/sh\n# a stand-in engine: arguments -in SCRIPT -log LOG\n\
         echo 'ERROR: Lost atoms: original 1 current 0 (../thermo.cpp:441)' > \"$4\"\n\
         cat \"$4\"\nexit 1\n",
    )
    .unwrap();
    std::fs::set_permissions(&engine, std::fs::Permissions::from_mode(0o755)).unwrap();
    let out = dir.path().join("fin");
    let mut c = surfstream();
    c.env("SURFSTREAM_LIGGGHTS", &engine)
        .args(["finish"])
        .arg(&input)
        .args(["--no-macro", "--pitch-um", "3", "--patch-um", "60"])
        .args(["--cycles", "2", "--passes", "2", "-o"])
        .arg(&out);
    let o = run(c);
    let err = stderr(&o);
    assert!(!o.status.success(), "{err}");
    assert!(
        err.contains("Lost atoms") && err.contains("FAILED"),
        "{err}"
    );
    let record = std::fs::read_to_string(out.join("FAILED")).unwrap();
    assert!(record.contains("Lost atoms"), "{record}");
    let logs: Vec<String> = std::fs::read_dir(out.join("logs"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
        .collect();
    assert!(
        logs.iter().any(|n| n.ends_with("log.liggghts"))
            && logs.iter().any(|n| n.ends_with("in.liggghts")),
        "{logs:?}"
    );
    for f in ["finish.json", "finish.html", "wear.npy", "worn.x3p"] {
        assert!(!out.join(f).exists(), "{f} was left in a failed run");
    }
    // No staging folder or lock left beside OUT.
    let beside: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
        .filter(|n| n.starts_with("fin.staging") || n == "fin.lock")
        .collect();
    assert!(beside.is_empty(), "{beside:?}");
}
