//! Free space before work (issue 36): a run states an estimate of what it will write and
//! compares it with what the out dir's file system has free, before the scan starts. A run
//! that will not fit, or would leave less than its own size again free, is warned about,
//! naming both numbers; it is not refused (the estimate is rough, and space can be freed
//! while the scan runs: a disk that does fill fails the run with the OS's reason).
//!
//! The estimate is per measured point: the demo at 4 tiles of 256 x 256 px wrote 13 065 742
//! bytes (`du -sb`), 49.8 bytes per tile point (the panorama as .npy and .x3p, datum,
//! roughness, the resampled mesh surface, previews, the STL, the recording, report.html).
//! [`BYTES_PER_TILE_POINT`] rounds it to 50. Spill files of the nodes are not counted (they
//! go to the spill folder and are gone at the end of the run).

use std::path::Path;

use anyhow::{bail, Result};
use surfstream_core::record::{NodeRecord, ReplayReport};
use surfstream_replay::Config;
use surfstream_runtime::graph::GraphFile;

/// Bytes a run writes per measured point of its tiles (measured, see the module text).
pub const BYTES_PER_TILE_POINT: u64 = 50;

/// The measured points the graph's sources will read: a simulated stage's tiles as planned;
/// a scan manifest's or a recording's from the bytes of its files, 4 bytes (an f32) a point.
/// `None` when no source can be estimated (the check is then skipped and said so).
pub fn tile_points(graph: &GraphFile) -> Option<u64> {
    let mut total = None::<u64>;
    for n in graph
        .nodes
        .iter()
        .filter(|n| n.node == <ReplayReport as NodeRecord>::NODE_KIND)
    {
        let points = match Config::from_table(&n.params).ok()? {
            Config::Simulated(p) => {
                let plan = p.check().ok()?;
                (plan.tiles.len() as u64)
                    .saturating_mul(plan.tile_width_px as u64)
                    .saturating_mul(plan.tile_height_px as u64)
            }
            Config::Scan(s) => scan_bytes(&s.manifest())? / 4,
            Config::Mcap(m) => std::fs::metadata(&m.path).ok()?.len() / 4,
        };
        total = Some(total.unwrap_or(0).saturating_add(points));
    }
    total
}

/// The bytes of the tile files a scan manifest lists (read by the replay's own loader).
fn scan_bytes(manifest: &Path) -> Option<u64> {
    let listing = surfstream_replay::scan_dir::ManifestListing::read(manifest).ok()?;
    let mut bytes = 0u64;
    for file in &listing.tile_files {
        bytes = bytes.saturating_add(std::fs::metadata(file).ok()?.len());
    }
    Some(bytes)
}

/// Bytes free to this user on the file system of `dir` (statvfs: blocks available to an
/// unprivileged user times the fragment size).
pub fn free_bytes(dir: &Path) -> Result<u64> {
    use std::os::unix::ffi::OsStrExt;
    let c = std::ffi::CString::new(dir.as_os_str().as_bytes())
        .map_err(|_| anyhow::anyhow!("{}: a path with a NUL byte", dir.display()))?;
    // SAFETY: statvfs is plain data; zeroed is a valid value.
    let mut s: libc::statvfs = unsafe { std::mem::zeroed() };
    // SAFETY: a valid NUL-terminated path and a valid out pointer.
    if unsafe { libc::statvfs(c.as_ptr(), &mut s) } != 0 {
        bail!(
            "{}: cannot read the free space: {}",
            dir.display(),
            std::io::Error::last_os_error()
        );
    }
    Ok((s.f_bavail as u64).saturating_mul(s.f_frsize as u64))
}

/// What to do with an estimate `need` against `free` bytes.
#[derive(Debug, PartialEq, Eq)]
pub enum Room {
    /// Fits with room to spare.
    Fits,
    /// Fits, but leaves less than `need` free again: warn.
    Tight,
    /// Does not fit: warn that the run will likely fail.
    Short,
}

pub fn judge(need: u64, free: u64) -> Room {
    if need > free {
        Room::Short
    } else if need > free / 2 {
        Room::Tight
    } else {
        Room::Fits
    }
}

fn mb(bytes: u64) -> String {
    format!("{:.1} MB", bytes as f64 / 1e6)
}

/// Checks the run's estimated output size against the free space where `staging` (beside the
/// out dir, on its file system) lives, and warns when it does not fit or is tight.
pub fn check(graph: &GraphFile, staging: &Path) -> Result<()> {
    let Some(points) = tile_points(graph) else {
        eprintln!(
            "surfstream: note: no estimate of the outputs' size for this graph's source: the free space in {} is not checked",
            staging.display()
        );
        return Ok(());
    };
    let need = points.saturating_mul(BYTES_PER_TILE_POINT);
    let free = free_bytes(staging)?;
    let at = staging.parent().unwrap_or(staging);
    match judge(need, free) {
        Room::Fits => Ok(()),
        Room::Tight => {
            eprintln!(
                "surfstream: warning: this run will write about {} ({points} measured points x {BYTES_PER_TILE_POINT} bytes) and {} has {} free: little room is left",
                mb(need),
                at.display(),
                mb(free)
            );
            Ok(())
        }
        Room::Short => {
            eprintln!(
                "surfstream: warning: {}: not enough free space: this run will write about {} ({points} measured points x {BYTES_PER_TILE_POINT} bytes), and {} are free there: it will likely fail with a full disk; free some space or choose another -o",
                at.display(),
                mb(need),
                mb(free)
            );
            Ok(())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_estimate_is_judged_against_the_free_space() {
        assert_eq!(judge(10, 100), Room::Fits);
        assert_eq!(judge(60, 100), Room::Tight);
        assert_eq!(judge(101, 100), Room::Short);
        let free = free_bytes(Path::new("/")).unwrap();
        assert!(free > 0);
    }

    #[test]
    fn a_simulated_scan_is_estimated_from_its_plan() {
        let g: GraphFile = toml::from_str(
            r#"
[graph]
name = "g"
[[node]]
id = "stage"
node = "replay"
params = { source = "simulated", rows = 2, cols = 3, overlap = 0.2, tile_px = 256, pitch_um = 1.0 }
"#,
        )
        .unwrap();
        assert_eq!(tile_points(&g), Some(6 * 256 * 256));
    }
}
