//! The entry points the fuzz targets drive, one function per input kind. Shared, by `#[path]`,
//! by the cargo-fuzz targets (`fuzz_targets/*.rs`, nightly or `RUSTC_BOOTSTRAP=1`) and by the
//! stable corpus test (`tests/bad_input.rs` `mutated_inputs_of_every_parser_are_refused_cleanly`),
//! so CI drives exactly what the fuzzer does. Each takes arbitrary bytes and must return
//! (`true` when the input was read, `false` when it was refused with an error); a panic or an
//! abort is the bug.
//!
//! Needs: surfstream-io, surfstream-runtime, surfstream-replay.

#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use surfstream_io::formats::{parse_surface, read_surface, Format};

/// A private scratch folder for this process (in /dev/shm when there is one), made once.
fn scratch() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let base = if Path::new("/dev/shm").is_dir() {
            PathBuf::from("/dev/shm")
        } else {
            std::env::temp_dir()
        };
        let dir = base.join(format!("surfstream-fuzz-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("scratch folder");
        // Two small tiles for scan manifests to name.
        let z: Vec<f32> = (0..16 * 24).map(|i| (i % 7) as f32 * 0.1).collect();
        for name in ["tile_000.npy", "tile_001.npy"] {
            surfstream_io::npy::write_npy_f32(dir.join(name), &z, 16, 24).expect("tile");
        }
        dir
    })
}

/// Removes the scratch folder (the stable test calls it at the end).
pub fn clean_scratch() {
    let _ = std::fs::remove_dir_all(scratch());
}

fn write_scratch(name: &str, data: &[u8]) -> PathBuf {
    let path = scratch().join(name);
    std::fs::write(&path, data).expect("scratch file writable");
    path
}

/// One of the height-map readers, from bytes (`.npy` through a file: its reader reads paths).
pub fn reader(data: &[u8], format: Format) -> bool {
    let s = if format == Format::Npy {
        read_surface(&write_scratch("input.npy", data))
    } else {
        parse_surface(data, format)
    };
    s.map(|s| assert_eq!(s.heights_um.len(), s.width * s.height))
        .is_ok()
}

/// An MCAP recording, read whole and checked as `stitch` and the replay node read it.
pub fn mcap(data: &[u8]) -> bool {
    let path = write_scratch("input.mcap", data);
    let Ok(r) = surfstream_io::recording::read_recording(&path) else {
        return false;
    };
    for m in &r.messages {
        if let surfstream_io::recording::Recorded::Frame(f) = &m.message {
            assert_eq!(
                f.heights.len(),
                f.header.width as usize * f.header.height as usize
            );
        }
    }
    true
}

/// A scan manifest (`scan.toml`) beside two 16 x 24 tiles `tile_000.npy`, `tile_001.npy`,
/// loaded as `stitch` loads it (the tiles read too).
pub fn scan_toml(data: &[u8]) -> bool {
    let path = write_scratch("scan.toml", data);
    let Ok(s) = surfstream_replay::scan_dir::load_scan(&path) else {
        return false;
    };
    for t in &s.tiles {
        assert_eq!(t.heights_um.len(), s.tile_width_px * s.tile_height_px);
    }
    true
}

/// The node kinds a fuzzed graph may name: the replay source and a recorder-like sink that
/// takes any input and writes a file (`path`), as the CLI's registry declares them.
fn registry() -> surfstream_runtime::graph::NodeRegistry {
    use surfstream_runtime::graph::{InputDef, NodePorts, NodeRegistry};
    const SINK: NodePorts = NodePorts {
        kind: "recorder",
        inputs: &[InputDef::ANY],
        outputs: &[],
    };
    NodeRegistry::new([surfstream_replay::ports::PORTS, SINK])
        .with_output_files("recorder", &["path"])
        .with_output_default("recorder", "path", "recording.mcap")
        .with_reserved_outputs(&["run.json", "FAILED", "logs", "report*"])
}

/// A graph file: parsed, validated, `--set` overrides applied and resolved into node contexts,
/// as `run` and `launch` read it.
pub fn graph_toml(data: &[u8]) -> bool {
    let Ok(text) = std::str::from_utf8(data) else {
        return false;
    };
    let registry = registry();
    let Ok(mut g) = surfstream_runtime::graph::GraphFile::parse(text, "fuzz.toml", &registry)
    else {
        return false;
    };
    let resolved = g.resolve(1, &registry).is_ok();
    let _ = g.apply_override("stage.rows=3");
    let _ = g.resolve(1, &registry);
    resolved
}

/// A `.npy` file's pitch sidecar (`x.npy.json`), read alone and with its array.
pub fn sidecar(data: &[u8]) -> bool {
    let npy = scratch().join("sidecar.npy");
    if !npy.exists() {
        let z = [0.5f32; 12];
        surfstream_io::npy::write_npy_f32(&npy, &z, 3, 4).expect("array");
    }
    std::fs::write(surfstream_io::sidecar::sidecar_path(&npy), data).expect("sidecar");
    let read = surfstream_io::sidecar::read_sidecar(&npy).is_ok_and(|g| g.is_some());
    match read_surface(&npy) {
        Ok(s) => {
            assert_eq!(s.heights_um.len(), 12);
            read
        }
        Err(_) => false,
    }
}
