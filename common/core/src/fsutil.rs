//! Writing output files so that a failure never leaves a half-written file behind.
//!
//! * [`write_atomic`]: one file, written under a temporary name, synced, renamed into place.
//! * [`OutputSet`]: the files of one result (a verb's outputs) committed together: every file
//!   is written under its temporary name first, then the set is synced at one point (the
//!   files' data, whose write-back each writer starts as it goes, then the renames, then the
//!   folder once), or not synced at all for scratch outputs ([`Durability::NoSync`]).

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
    let (tmp, file) = write_partial(path, fill)?;
    file.sync_all().ok();
    drop(file);
    std::fs::rename(&tmp, path).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        anyhow::anyhow!("{}: cannot rename into place: {e}", path.display())
    })
}

/// Creates `path`'s parent folders and writes `fill` into `path`'s temporary name; on an
/// error the temporary file is removed.
fn write_partial<F>(path: &Path, fill: F) -> anyhow::Result<(PathBuf, File)>
where
    F: FnOnce(&mut BufWriter<File>) -> anyhow::Result<()>,
{
    create_parent(path)?;
    let tmp = partial_path(path);
    let result = (|| {
        let file = File::create(&tmp)
            .map_err(|e| anyhow::anyhow!("{}: cannot create: {e}", tmp.display()))?;
        let mut w = BufWriter::new(file);
        fill(&mut w)?;
        w.flush()
            .map_err(|e| anyhow::anyhow!("{}: write failed: {e}", tmp.display()))?;
        w.into_inner()
            .map_err(|e| anyhow::anyhow!("{}: {e}", tmp.display()))
    })();
    match result {
        Ok(file) => Ok((tmp, file)),
        Err(e) => {
            let _ = std::fs::remove_file(&tmp);
            Err(e)
        }
    }
}

/// Creates the folders above `path` (none for a bare file name).
pub fn create_parent(path: &Path) -> anyhow::Result<()> {
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)
            .map_err(|e| anyhow::anyhow!("{}: cannot create the folder: {e}", parent.display()))?;
    }
    Ok(())
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

/// Whether committed outputs are pushed to the disk before the commit returns.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Durability {
    /// The files' data and the folder entries are on the disk when the commit returns (a
    /// power cut afterwards loses nothing).
    #[default]
    Synced,
    /// Renamed into place atomically but not synced (scratch outputs: a power cut may lose
    /// them, a crash of the process never leaves a half-written file).
    NoSync,
}

/// Bytes a streaming writer appends between two write-back starts ([`start_writeback`]).
pub const WRITEBACK_CHUNK_BYTES: u64 = 8 << 20;

/// Asks the kernel to start writing `len` bytes of `file` from `offset` to the disk, without
/// waiting: a large output is then mostly on the disk when it is synced. A no-op off Linux
/// (and where the call is refused: the sync still makes the data durable).
pub fn start_writeback(file: &File, offset: u64, len: u64) {
    #[cfg(target_os = "linux")]
    {
        use std::os::fd::AsRawFd;
        let (Ok(off), Ok(n)) = (i64::try_from(offset), i64::try_from(len)) else {
            return;
        };
        // SAFETY: sync_file_range reads no memory of ours; the fd is open for the call.
        unsafe {
            libc::sync_file_range(file.as_raw_fd(), off, n, libc::SYNC_FILE_RANGE_WRITE);
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = (file, offset, len);
}

/// A file written under its temporary name, waiting for [`OutputSet::commit`].
#[derive(Debug)]
struct Staged {
    tmp: PathBuf,
    path: PathBuf,
    file: File,
}

/// The files of one result, moved into place together by [`OutputSet::commit`]: until then
/// each sits under its temporary name ([`partial_path`]), and a set dropped uncommitted (an
/// error on the way) removes them, so a failure leaves no output half-written.
///
/// With [`Durability::Synced`] the commit is one sync point for the whole set: every file's
/// data is synced (its write-back queued for all files first, so the disk works on them
/// together), the files are renamed, and the folder is synced once for all the renames.
#[derive(Debug)]
pub struct OutputSet {
    durability: Durability,
    staged: Vec<Staged>,
}

impl OutputSet {
    /// An empty set committed with `durability`.
    pub fn new(durability: Durability) -> Self {
        Self {
            durability,
            staged: Vec::new(),
        }
    }

    /// The set's durability (streaming writers start write-back only when synced).
    pub fn durability(&self) -> Durability {
        self.durability
    }

    /// Writes `path` through `fill` under its temporary name; it appears at `path` on commit.
    pub fn write<F>(&mut self, path: &Path, fill: F) -> anyhow::Result<()>
    where
        F: FnOnce(&mut BufWriter<File>) -> anyhow::Result<()>,
    {
        let (tmp, file) = write_partial(path, fill)?;
        self.stage(tmp, path.to_path_buf(), file);
        Ok(())
    }

    /// Adds a file a streaming writer wrote completely to `tmp` (flushed), to appear at `path`.
    pub fn stage(&mut self, tmp: PathBuf, path: PathBuf, file: File) {
        if self.durability == Durability::Synced {
            start_writeback(&file, 0, 0);
        }
        self.staged.push(Staged { tmp, path, file });
    }

    /// The files staged so far, as their final paths.
    pub fn paths(&self) -> impl Iterator<Item = &Path> {
        self.staged.iter().map(|s| s.path.as_path())
    }

    /// Syncs (when [`Durability::Synced`]) and renames every staged file into place, then
    /// syncs each folder they are in once. On an error the files not yet renamed are removed.
    pub fn commit(mut self) -> anyhow::Result<()> {
        let staged = std::mem::take(&mut self.staged);
        let synced = self.durability == Durability::Synced;
        if synced {
            for s in &staged {
                if let Err(e) = s.file.sync_data() {
                    remove_all(&staged);
                    anyhow::bail!("{}: cannot sync to the disk: {e}", s.tmp.display());
                }
            }
        }
        let mut folders: Vec<PathBuf> = Vec::new();
        for (i, s) in staged.iter().enumerate() {
            if let Err(e) = std::fs::rename(&s.tmp, &s.path) {
                remove_all(&staged[i..]);
                anyhow::bail!("{}: cannot rename into place: {e}", s.path.display());
            }
            let folder = match s.path.parent() {
                Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
                _ => PathBuf::from("."),
            };
            if !folders.contains(&folder) {
                folders.push(folder);
            }
        }
        if synced {
            for folder in &folders {
                // A folder that cannot be opened or synced (some file systems refuse fsync
                // on a directory) leaves the renames to the file system's own schedule.
                if let Ok(d) = File::open(folder) {
                    d.sync_all().ok();
                }
            }
        }
        Ok(())
    }
}

fn remove_all(staged: &[Staged]) {
    for s in staged {
        let _ = std::fs::remove_file(&s.tmp);
    }
}

impl Drop for OutputSet {
    fn drop(&mut self) {
        // Uncommitted (an error on the way): no temporary file stays behind.
        remove_all(&self.staged);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    }

    #[test]
    fn a_set_appears_only_on_commit_and_whole() {
        for durability in [Durability::Synced, Durability::NoSync] {
            let d = tempfile::tempdir().unwrap();
            let mut set = OutputSet::new(durability);
            set.write(&d.path().join("a.txt"), |w| Ok(w.write_all(b"alpha")?))
                .unwrap();
            set.write(&d.path().join("sub/b.txt"), |w| Ok(w.write_all(b"beta")?))
                .unwrap();
            assert_eq!(names(d.path()), ["a.txt.partial", "sub"], "{durability:?}");
            assert_eq!(set.paths().count(), 2);
            set.commit().unwrap();
            assert_eq!(names(d.path()), ["a.txt", "sub"], "{durability:?}");
            assert_eq!(std::fs::read(d.path().join("a.txt")).unwrap(), b"alpha");
            assert_eq!(std::fs::read(d.path().join("sub/b.txt")).unwrap(), b"beta");
        }
    }

    #[test]
    fn a_set_dropped_or_failing_leaves_nothing_behind() {
        let d = tempfile::tempdir().unwrap();
        {
            let mut set = OutputSet::new(Durability::Synced);
            set.write(&d.path().join("a.txt"), |w| Ok(w.write_all(b"alpha")?))
                .unwrap();
            let err = set
                .write(&d.path().join("b.txt"), |_| {
                    anyhow::bail!("the data ran out")
                })
                .unwrap_err();
            assert!(err.to_string().contains("the data ran out"), "{err}");
        }
        assert!(names(d.path()).is_empty(), "{:?}", names(d.path()));
    }

    #[test]
    fn write_atomic_replaces_whole_and_cleans_up_on_error() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("new/x.bin");
        write_atomic(&p, |w| Ok(w.write_all(b"one")?)).unwrap();
        assert!(write_atomic(&p, |_| anyhow::bail!("no")).is_err());
        assert_eq!(std::fs::read(&p).unwrap(), b"one");
        assert_eq!(names(&d.path().join("new")), ["x.bin"]);
    }
}
