//! Helpers for the end-to-end tests: find the built binaries, run commands, read outputs.
//!
//! The tests start the release binaries (`cargo build --release` first; `scripts/test.sh`
//! does both), as a user would.
//!
//! Not for: unit tests, which live beside the code in each crate; these tests check what a
//! user sees (processes, files, exit status, messages), so they need the built binaries.

pub mod dem;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The directory holding `surfstream` and the `surfstream-<node>` binaries.
pub fn bin_dir() -> PathBuf {
    // target/<profile>/deps/<test> -> target/<profile>; prefer release binaries.
    let exe = std::env::current_exe().expect("test executable path");
    let target = exe
        .parent()
        .and_then(Path::parent)
        .and_then(Path::parent)
        .expect("target dir");
    for profile in ["release", "debug"] {
        let dir = target.join(profile);
        if dir.join("surfstream").exists() && dir.join("surfstream-replay").exists() {
            return dir;
        }
    }
    panic!(
        "surfstream binaries not found under {}: build them first with `cargo build --release` \
         (scripts/test.sh builds and tests)",
        target.display()
    );
}

/// The repository root (graphs live in launch/graphs).
pub fn repo_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("repo root")
        .to_path_buf()
}

/// A real instrument file: the folder SURFSTREAM_SPECIMENS names when it holds `name`, else the
/// repository's own copy in tests/data/specimens (its README gives each file's source and
/// licence). Panics, naming both places, when neither has it.
pub fn specimen(name: &str) -> PathBuf {
    optional_specimen(name).unwrap_or_else(|| {
        panic!(
            "specimen {name} missing: neither in tests/data/specimens nor in \
             $SURFSTREAM_SPECIMENS"
        )
    })
}

/// A specimen found in SURFSTREAM_SPECIMENS or tests/data/specimens, or None: for the files
/// whose licence keeps them out of the repository (tests/data/specimens/README.md), which a
/// test reads only where they are at hand.
pub fn optional_specimen(name: &str) -> Option<PathBuf> {
    std::env::var_os("SURFSTREAM_SPECIMENS")
        .map(|d| PathBuf::from(d).join(name))
        .into_iter()
        .chain([repo_root().join("tests/data/specimens").join(name)])
        .find(|p| p.is_file())
}

pub fn surfstream() -> Command {
    let mut c = Command::new(bin_dir().join("surfstream"));
    c.current_dir(repo_root());
    c
}

/// Runs and returns the output; prints stderr for the test log.
pub fn run(mut cmd: Command) -> Output {
    let out = cmd.output().expect("start surfstream");
    eprintln!(
        "--- {:?} -> {:?}\n{}",
        cmd,
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// The demo graph in one process (`run`), 2 x 2 fields of 256 px, as fast as possible, into
/// `out`, with `extra` arguments; asserts it succeeded.
pub fn small_demo(out: &Path, extra: &[&str]) {
    let mut cmd = surfstream();
    cmd.args(["run", "launch/graphs/demo.toml", "--out"])
        .arg(out)
        .args([
            "--set",
            "stage.pacing=\"fast\"",
            "--set",
            "stage.tile_px=256",
        ])
        .args(extra);
    let o = run(cmd);
    assert!(o.status.success(), "{}", stderr(&o));
}

pub fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).to_string()
}

pub fn read_json(path: &Path) -> serde_json::Value {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The Python with `mcap`, `numpy` and `trimesh` that scripts/test.sh prepares.
pub fn python() -> PathBuf {
    if let Ok(p) = std::env::var("SURFSTREAM_PYTHON") {
        return PathBuf::from(p);
    }
    let venv = repo_root().join(".test-venv/bin/python");
    assert!(
        venv.exists(),
        "no Python test environment: run scripts/test.sh (it creates .test-venv with mcap, numpy, trimesh)"
    );
    venv
}

/// The files that every pipeline run must produce identically in `launch` and `run`.
pub const OUTPUTS: &[&str] = &[
    "panorama.npy",
    "datum.npy",
    "roughness.npy",
    "pooled.npy",
    "surface.stl",
    "mesh_resampled.npy",
    "mesh_resampled.npy.json",
    "panorama.png",
    "datum.png",
    "roughness.png",
    "pooled.png",
];

/// Asserts two out dirs hold byte-identical outputs.
pub fn assert_same_outputs(a: &Path, b: &Path) {
    for f in OUTPUTS {
        let x = std::fs::read(a.join(f)).unwrap_or_else(|e| panic!("{}: {e}", a.join(f).display()));
        let y = std::fs::read(b.join(f)).unwrap_or_else(|e| panic!("{}: {e}", b.join(f).display()));
        assert!(
            x == y,
            "{f} differs between {} and {}",
            a.display(),
            b.display()
        );
    }
}

/// The iceoryx2 domain a launch used, from its stderr ("domain ssN_").
pub fn domain_of(stderr: &str) -> Option<String> {
    let at = stderr.find("domain ")? + "domain ".len();
    let rest = &stderr[at..];
    let end = rest.find(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))?;
    Some(rest[..end].to_string())
}

/// Shared-memory files of a domain, the management segment included (the launcher creates it
/// 0600 and removes it at the end; each launch's domain is its own).
pub fn shm_leftovers(domain: &str) -> Vec<String> {
    std::fs::read_dir("/dev/shm")
        .map(|d| {
            d.flatten()
                .map(|e| e.file_name().to_string_lossy().to_string())
                .filter(|n| n.starts_with(domain))
                .collect()
        })
        .unwrap_or_default()
}

/// Writes a scan directory (scan.toml + .npy tiles + ground_truth.json) from the simulated
/// stage; `height_unit: None` leaves `[scan] height_unit` out.
pub fn write_scan_dir(
    dir: &Path,
    rows: usize,
    cols: usize,
    tile_px: usize,
    height_unit: Option<&str>,
) -> surfstream_replay::ScanPlan {
    use surfstream_replay::*;
    let stage = StageParams {
        rows,
        cols,
        tile_px,
        overlap: 0.2,
        seed: 7,
        ..Default::default()
    };
    let plan = plan_scan(&stage).unwrap();
    let spec = generate_specimen(&plan.specimen_params(&SpecimenParams {
        seed: 7,
        ..Default::default()
    }))
    .unwrap();
    let unit = height_unit.map_or(String::new(), |u| format!("height_unit = \"{u}\"\n"));
    let mut toml = format!(
        "[scan]\nname = \"fixture\"\npitch_x_um = {p}\npitch_y_um = {p}\n{unit}rows = {rows}\ncols = {cols}\n",
        p = stage.pitch_um
    );
    for t in &plan.tiles {
        let heights = acquire_tile(&spec, t, &stage);
        let name = format!("tile_{:03}.npy", t.index);
        surfstream_io::npy::write_npy_f32(dir.join(&name), &heights, tile_px, tile_px).unwrap();
        toml += &format!(
            "\n[[tile]]\nfile = \"{name}\"\nrow = {}\ncol = {}\nstage_x_um = {}\nstage_y_um = {}\n",
            t.row, t.col, t.stage_position_um[0], t.stage_position_um[1]
        );
    }
    std::fs::write(dir.join("scan.toml"), toml).unwrap();
    let truth = truth_for(&plan);
    std::fs::write(
        dir.join("ground_truth.json"),
        serde_json::to_string(&truth).unwrap(),
    )
    .unwrap();
    plan
}
