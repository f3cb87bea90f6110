//! Scans of any size (issue 17): a memory budget that makes the fusion spill its panorama
//! chunks to disk changes no output byte, the run reports its peak memory, and the chunked
//! panorama (Zarr v3) opens in zarr-python with the same heights as the .npy.

use std::path::Path;
use std::process::Command;

use surfstream_e2e::{assert_same_outputs, python, read_json, run, stderr, surfstream};

fn demo(out: &Path, extra: &[&str]) {
    let out_run = run({
        let mut c = surfstream();
        c.args(["run", "launch/graphs/demo.toml", "--out"]).arg(out);
        for s in [
            "stage.rows=3",
            "stage.cols=3",
            "stage.tile_px=512",
            "stage.pacing=fast",
        ]
        .iter()
        .chain(extra)
        {
            c.args(["--set", s]);
        }
        c
    });
    assert!(
        out_run.status.success(),
        "run failed:\n{}",
        stderr(&out_run)
    );
}

#[test]
fn a_memory_budget_changes_no_output_and_zarr_python_reads_the_panorama() {
    let dir = tempfile::tempdir().unwrap();
    let (whole, budget) = (dir.path().join("whole"), dir.path().join("budget"));
    demo(&whole, &[]);
    // 4 MB: the fusion's quarter (1 MB) is less than one 2 MiB chunk: a 512 px tile touches up
    // to 4 of the panorama's 9 chunks, so chunks spill and come back all along the scan.
    demo(
        &budget,
        &["graph.memory_budget_gb=0.004", "fusion.zarr=always"],
    );
    assert_same_outputs(&whole, &budget);

    let w = read_json(&whole.join("run.json"));
    let b = read_json(&budget.join("run.json"));
    let chunks = &b["stages"]["fusion"]["memory"]["chunks"];
    assert!(chunks["spills"].as_u64().unwrap() > 0, "{chunks}");
    assert!(chunks["reloads"].as_u64().unwrap() > 0, "{chunks}");
    assert_eq!(w["stages"]["fusion"]["memory"]["chunks"]["spills"], 0);
    assert_eq!(b["peak_rss"]["memory_budget_gb"], 0.004);
    let peak = b["peak_rss"]["process_bytes"].as_u64().unwrap();
    assert!(peak > 10 << 20, "peak RSS {peak} bytes");
    assert!(b["peak_rss"]["nodes_bytes"]["fusion"].as_u64().unwrap() > 0);
    assert!(
        !whole.join("panorama.zarr").exists(),
        "auto: only large panoramas"
    );
    let files = b["files"].as_array().unwrap();
    assert!(
        files.iter().any(|f| f == "panorama.zarr/zarr.json"),
        "{files:?}"
    );
    // No spill file is left in the out dir.
    let left: Vec<_> = std::fs::read_dir(&budget)
        .unwrap()
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().contains("spill"))
        .collect();
    assert!(left.is_empty(), "{left:?}");

    let script = r#"
import sys, numpy as np, zarr
z = zarr.open_array(sys.argv[1] + "/panorama.zarr", mode="r")
npy = np.load(sys.argv[1] + "/panorama.npy")
assert z.shape == npy.shape, (z.shape, npy.shape)
assert z.dtype == npy.dtype == np.float32, (z.dtype, npy.dtype)  # no z offset: float32 exactly
a = z[:]
assert np.array_equal(a, npy, equal_nan=True), "zarr and npy differ"
assert np.isnan(npy).any() and np.isfinite(npy).sum() > 0.9 * npy.size
# A window read touches only its chunks and gives the same values.
assert np.array_equal(z[100:700, 300:900], npy[100:700, 300:900], equal_nan=True)
attrs = z.attrs["surfstream"]
assert attrs["pitch_x_um"] == 0.8148, attrs
print("zarr ok", z.shape, z.chunks)
"#;
    let out = run({
        let mut c = Command::new(python());
        c.arg("-c").arg(script).arg(&budget);
        c
    });
    assert!(
        out.status.success(),
        "zarr-python check failed:\n{}",
        stderr(&out)
    );
    assert!(String::from_utf8_lossy(&out.stdout).contains("zarr ok"));
}

/// Issue 37: a demo scan under `run` at `memory_budget_gb=0.5` (the default tolerance with its
/// pointwise bound) stays within 1.5 x the budget in every node's record (under `run` each
/// node's figure is the one process's peak when that node finished), run.json sets the peaks
/// against the plan's shares, and the verdict says whether the plan was kept. 4 x 4 tiles
/// (14.3 Mpx); the issue's own 6 x 6 is the next test.
#[test]
fn a_four_by_four_run_stays_within_one_and_a_half_times_its_budget() {
    demo_within_budget("four", 4);
}

/// Issue 37 at its own size: the 6 x 6 demo (31.8 Mpx) at `memory_budget_gb=0.5` stays
/// within 1.5 x the budget in every node's record and in the process's peak: 590 and 591 MB
/// measured, against 743 and 769 MB before a finished node's freed pages went back to the
/// system, the live passes were banded and the mesher's spike search stopped copying the
/// map. Not timed: 2 to 6 min on the shared 2-core machine.
#[test]
fn a_six_by_six_run_stays_within_one_and_a_half_times_its_budget() {
    demo_within_budget("six", 6);
}

/// The demo at `side` x `side` tiles under `run` at `memory_budget_gb=0.5`: every node's peak
/// and the process's within 1.5 x the budget, the shares, the verdict's line, the tolerance
/// met.
fn demo_within_budget(name: &str, side: usize) {
    const BUDGET_BYTES: u64 = 500_000_000;
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join(name);
    let (rows, cols) = (format!("stage.rows={side}"), format!("stage.cols={side}"));
    let out_run = run({
        let mut c = surfstream();
        c.args(["run", "launch/graphs/demo.toml", "--out"])
            .arg(&out);
        for s in [
            rows.as_str(),
            cols.as_str(),
            "stage.pacing=fast",
            "graph.memory_budget_gb=0.5",
        ] {
            c.args(["--set", s]);
        }
        c
    });
    assert!(
        out_run.status.success(),
        "run failed:\n{}",
        stderr(&out_run)
    );
    let r = read_json(&out.join("run.json"));
    let peak = &r["peak_rss"];
    assert_eq!(peak["memory_budget_gb"], 0.5, "{peak}");
    let nodes = peak["nodes_bytes"].as_object().expect("nodes_bytes");
    assert_eq!(nodes.len(), 6, "{peak}");
    let limit = BUDGET_BYTES * 3 / 2;
    for (id, bytes) in nodes {
        let b = bytes
            .as_u64()
            .unwrap_or_else(|| panic!("{id}: no peak in {peak}"));
        assert!(
            b <= limit,
            "node {id}: peak {b} bytes > 1.5 x the budget ({limit})"
        );
        // Every node has its share of the plan beside its peak.
        assert!(
            peak["shares_bytes"][id].as_u64().is_some_and(|s| s > 0),
            "{peak}"
        );
    }
    let process = peak["process_bytes"].as_u64().expect("process_bytes");
    assert!(
        process <= limit,
        "the run's process: {process} bytes > {limit}"
    );
    let shares: u64 = (peak["shares_bytes"].as_object().unwrap().values())
        .filter_map(|v| v.as_u64())
        .sum();
    assert!(
        shares <= BUDGET_BYTES && shares > BUDGET_BYTES - 10,
        "{peak}"
    );
    // The verdict states the peak against the budget (over it or within it, as run.json says).
    let stdout = String::from_utf8_lossy(&out_run.stdout);
    let over = !peak["over_plan"].as_array().is_none_or(|a| a.is_empty());
    let expected = if over {
        "memory      BEYOND THE PLAN: peak"
    } else {
        "memory      peak"
    };
    assert!(stdout.contains(expected), "{stdout}");
    assert!(
        stdout.contains("of one process (every node of `run`)"),
        "{stdout}"
    );
    // The mesh was made to its tolerance.
    assert_eq!(r["stages"]["mesher"]["tolerance"]["met"], true);
}
