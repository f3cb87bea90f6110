//! The output sets of a graph run (issue 35): `--outputs model|full` on `launch`, `run` and
//! `stitch`, or a graph's `[outputs] set`.
//!
//! - **full** (the default): every file the run writes.
//! - **model**: what a user keeps of a large scan: the STL, run.json, report.html with
//!   report_maps/, the small JSON records (truth.json, panorama.tiles.json, the node reports,
//!   the resolved graph), the logs. Not kept: the height-map arrays (top-level `.npy` with
//!   their `.npy.json` sidecars, `.zarr` stores, `.x3p`), the node previews (top-level
//!   `.png`; the report draws its own maps) and recordings (`.mcap`, anywhere).
//!
//! Table 6 and report.html read the arrays, so the model set is made at the very end: the
//! launcher does not write `panorama.x3p` at all, and removes the other arrays after the
//! report is written. Only files the run itself wrote are removed: the run writes into its
//! own fresh staging folder (`outdir`), and the inputs carried into it from an earlier run
//! (a recording replayed into its own out dir) are never removed.

use std::path::Path;

use anyhow::{Context, Result};
use surfstream_core::record::{OutputChoice, OutputsRecord};

/// The output set of one run and the files in its out dir it did not make.
#[derive(Debug, Clone, Default)]
pub struct RunOutputs {
    pub choice: OutputChoice,
    /// Inputs carried into the staging folder from the out dir (relative paths): never removed.
    pub carried: Vec<String>,
}

/// One entry of the out dir the model set removes.
#[derive(Debug, Clone, PartialEq)]
pub struct Removal {
    /// Path relative to the out dir.
    pub name: String,
    pub bytes: u64,
    pub is_dir: bool,
}

/// Whether the model set keeps `name` (a path relative to the out dir, `/`-separated).
pub fn model_keeps(name: &str) -> bool {
    if name.ends_with(".mcap") {
        return false;
    }
    if name.contains('/') {
        return true; // report_maps/, nodes/, logs/, a finish folder
    }
    let array = [".npy", ".npy.json", ".zarr", ".x3p", ".png"];
    !array.iter().any(|ext| name.ends_with(ext))
}

/// What `choice` removes of the run's own files in `out`: every entry [`model_keeps`] does
/// not keep (a `.zarr` store as one folder), except `not_ours` (relative paths of inputs
/// carried into the run). Nothing for the full set.
pub fn plan(out: &Path, choice: OutputChoice, not_ours: &[String]) -> Result<Vec<Removal>> {
    if choice == OutputChoice::Full {
        return Ok(Vec::new());
    }
    let mut removals = Vec::new();
    walk(out, out, not_ours, &mut removals)?;
    removals.sort_by(|a, b| a.name.cmp(&b.name));
    Ok(removals)
}

fn walk(out: &Path, dir: &Path, not_ours: &[String], removals: &mut Vec<Removal>) -> Result<()> {
    let entries =
        std::fs::read_dir(dir).with_context(|| format!("{}: cannot list", dir.display()))?;
    for e in entries {
        let e = e.with_context(|| format!("{}: cannot list", dir.display()))?;
        let path = e.path();
        let Ok(rel) = path.strip_prefix(out) else {
            continue;
        };
        let name = rel.to_string_lossy().to_string();
        let kind = e
            .file_type()
            .with_context(|| format!("{}: cannot read", path.display()))?;
        let carried = not_ours
            .iter()
            .any(|n| n == &name || n.starts_with(&format!("{name}/")));
        if kind.is_dir() {
            if !carried && !name.contains('/') && name.ends_with(".zarr") {
                let bytes = tree_bytes(&path)?;
                removals.push(Removal {
                    name,
                    bytes,
                    is_dir: true,
                });
            } else {
                walk(out, &path, not_ours, removals)?;
            }
        } else if kind.is_file() && !carried && !model_keeps(&name) {
            let bytes = e
                .metadata()
                .with_context(|| format!("{}: cannot read", path.display()))?
                .len();
            removals.push(Removal {
                name,
                bytes,
                is_dir: false,
            });
        }
    }
    Ok(())
}

fn tree_bytes(dir: &Path) -> Result<u64> {
    let mut sum = 0;
    let entries =
        std::fs::read_dir(dir).with_context(|| format!("{}: cannot list", dir.display()))?;
    for e in entries.flatten() {
        let meta = e
            .metadata()
            .with_context(|| format!("{}: cannot read", e.path().display()))?;
        sum += if meta.is_dir() {
            tree_bytes(&e.path())?
        } else {
            meta.len()
        };
    }
    Ok(sum)
}

/// run.json's `outputs` for `choice` and its removals.
pub fn record(choice: OutputChoice, removals: &[Removal]) -> OutputsRecord {
    OutputsRecord {
        set: choice,
        removed: removals.iter().map(|r| r.name.clone()).collect(),
        removed_bytes: removals.iter().map(|r| r.bytes).sum(),
    }
}

/// Whether run.json's file `name` is one of the removals (or inside a removed folder).
pub fn is_removed(name: &str, removals: &[Removal]) -> bool {
    removals
        .iter()
        .any(|r| name == r.name || (r.is_dir && name.starts_with(&format!("{}/", r.name))))
}

/// Removes what [`plan`] listed (after Table 6 and the report read it).
pub fn remove(out: &Path, removals: &[Removal]) -> Result<()> {
    for r in removals {
        let path = out.join(&r.name);
        let done = if r.is_dir {
            std::fs::remove_dir_all(&path)
        } else {
            std::fs::remove_file(&path)
        };
        done.with_context(|| format!("{}: cannot remove (the model output set)", path.display()))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn touch(dir: &Path, name: &str, bytes: usize) {
        let p = dir.join(name);
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
        std::fs::write(p, vec![0u8; bytes]).unwrap();
    }

    #[test]
    fn the_model_set_removes_the_arrays_previews_and_recordings_of_the_run_only() {
        let d = tempfile::tempdir().unwrap();
        let out = d.path();
        for (name, bytes) in [
            ("panorama.npy", 800),
            ("panorama.npy.json", 10),
            ("panorama.png", 50),
            ("panorama.tiles.json", 20),
            ("datum.npy", 800),
            ("mesh_resampled.npy", 800),
            ("surface.stl", 300),
            ("run.json", 40),
            ("truth.json", 30),
            ("recording.mcap", 600),
            ("rec/other.mcap", 5),
            ("replayed.mcap", 7),
            ("report.html", 90),
            ("report_maps/panorama.png", 60),
            ("nodes/mesher.json", 10),
            ("logs/mesher.stderr", 3),
            ("panorama.zarr/zarr.json", 4),
            ("panorama.zarr/c/0/0", 100),
            ("finish/wear.npy", 8),
        ] {
            touch(out, name, bytes);
        }
        assert!(plan(out, OutputChoice::Full, &[]).unwrap().is_empty());
        let carried = vec!["replayed.mcap".to_string()];
        let removals = plan(out, OutputChoice::Model, &carried).unwrap();
        let names: Vec<&str> = removals.iter().map(|r| r.name.as_str()).collect();
        assert_eq!(
            names,
            [
                "datum.npy",
                "mesh_resampled.npy",
                "panorama.npy",
                "panorama.npy.json",
                "panorama.png",
                "panorama.zarr",
                "rec/other.mcap",
                "recording.mcap"
            ]
        );
        let rec = record(OutputChoice::Model, &removals);
        assert_eq!(rec.removed_bytes, 800 * 3 + 10 + 50 + 104 + 5 + 600);
        assert!(is_removed("panorama.zarr/c/0/0", &removals));
        assert!(!is_removed("panorama.tiles.json", &removals));
        remove(out, &removals).unwrap();
        for kept in [
            "surface.stl",
            "run.json",
            "report.html",
            "report_maps/panorama.png",
            "panorama.tiles.json",
            "replayed.mcap",
            "finish/wear.npy",
            "nodes/mesher.json",
        ] {
            assert!(out.join(kept).is_file(), "{kept} removed");
        }
        for gone in [
            "panorama.npy",
            "recording.mcap",
            "panorama.zarr",
            "rec/other.mcap",
        ] {
            assert!(!out.join(gone).exists(), "{gone} kept");
        }
    }
}
