//! Writing output files so that a failure never leaves a half-written file behind.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

/// Writes `path` through `fill` into a temporary sibling, then renames it into place: readers
/// see either the old file, no file, or the whole new file. Missing parent folders are created
/// (`convert x.dat out/new/x.x3p` works, as users expect of an output path).
pub fn write_atomic<F>(path: &Path, fill: F) -> anyhow::Result<()>
where
    F: FnOnce(&mut BufWriter<File>) -> anyhow::Result<()>,
{
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)
            .map_err(|e| anyhow::anyhow!("{}: cannot create the folder: {e}", parent.display()))?;
    }
    let tmp = partial_path(path);
    let result = (|| {
        let file = File::create(&tmp)
            .map_err(|e| anyhow::anyhow!("{}: cannot create: {e}", tmp.display()))?;
        let mut w = BufWriter::new(file);
        fill(&mut w)?;
        w.flush()
            .map_err(|e| anyhow::anyhow!("{}: write failed: {e}", tmp.display()))?;
        let file = w
            .into_inner()
            .map_err(|e| anyhow::anyhow!("{}: {e}", tmp.display()))?;
        file.sync_all().ok();
        Ok(())
    })();
    match result {
        Ok(()) => std::fs::rename(&tmp, path)
            .map_err(|e| anyhow::anyhow!("{}: cannot rename into place: {e}", path.display())),
        Err(e) => {
            let _ = std::fs::remove_file(&tmp);
            Err(e)
        }
    }
}

/// The temporary name used while `path` is being written.
pub fn partial_path(path: &Path) -> PathBuf {
    let mut name = path
        .file_name()
        .map(|n| n.to_os_string())
        .unwrap_or_default();
    name.push(".partial");
    path.with_file_name(name)
}

/// Removes `*.partial` files directly in `dir` (left by a process that was killed while
/// writing): after a failed run, no half-written output may remain.
pub fn remove_partials(dir: &Path) -> usize {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    entries
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().ends_with(".partial"))
        .filter(|e| std::fs::remove_file(e.path()).is_ok())
        .count()
}
