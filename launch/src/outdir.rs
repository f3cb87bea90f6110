//! An out dir holds exactly one run (issue 15): a run writes into a fresh staging folder beside
//! the out dir (`OUT.staging-<pid>`) and moves it into place only when it is complete, so old
//! and new outputs never mix and a killed run never leaves a complete-looking folder.
//!
//! - **Lock**: `OUT.lock` beside the out dir (flock, holding the owner's pid) is held for the
//!   whole run; a second run into the same out dir is refused, naming the pid that holds it.
//! - **Stale staging**: whoever holds the lock removes `OUT.staging-*` folders of earlier runs
//!   (a launcher killed with SIGKILL cannot clean up after itself).
//! - **Commit**: the staging folder is exchanged with the out dir in one `renameat2(EXCHANGE)`
//!   (two renames where the file system cannot exchange), then the old run is removed.
//! - **Failure** after the scan started: the out dir is replaced by the failed run: a `FAILED`
//!   record naming the cause, the logs and the resolved graph; its outputs are removed.
//!   A failure before the scan started (bad parameters, a bad input file, no free slot) leaves
//!   the out dir as it was and removes the staging folder: nothing was produced.
//! - **Ownership** (issue 27): a run only ever replaces a folder that a surfstream run made.
//!   Every run folder (and every staging folder, which becomes the run folder) holds the marker
//!   [`MARKER`]. An existing out dir that is neither empty nor marked is refused unless the user
//!   says `--force`; a symlinked out dir, `/`, the home folder, the current folder or any of its
//!   parents, and a folder that holds (or is) an input of the run are refused always. Stale
//!   staging folders are removed only when they carry the marker.

use std::fs::File;
use std::io::{Read, Seek, Write};
use std::os::fd::AsRawFd;
use std::os::unix::fs::MetadataExt;
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use surfstream_core::record::{NodeRecord, ReplayReport};

/// Name of the failure record in a failed run's folder.
pub const FAILED: &str = "FAILED";

/// The file that makes a folder a surfstream run folder (written when the run's staging folder
/// is created, so every committed or failed run carries it).
pub const MARKER: &str = ".surfstream-run";

/// Names in an out dir that belong to the run itself or to a node's fixed outputs: no output
/// parameter of a graph may take one (a trailing `*` makes a prefix; checked when the graph is
/// read, [`surfstream_runtime::graph::NodeRegistry::with_reserved_outputs`]).
pub const RESERVED_NAMES: &[&str] = &[
    "run.json",
    FAILED,
    MARKER,
    surfstream_runtime::shell::RESOLVED_GRAPH,
    "logs",
    "nodes",
    "report*",
    "panorama.*",
    "datum.*",
    "roughness.*",
    "pooled.*",
    "mesh_resampled.*",
    "truth.json",
    "scan.toml",
    "finish.json",
    "finish.html",
    ".failure-reserve",
];

/// Written into the staging folder of a run that completed but could not be moved into place:
/// the user was pointed to it, so a later run into the same out dir keeps it (issue 36).
pub const COMPLETE_NOT_MOVED: &str = "COMPLETE-NOT-MOVED";

/// What a run folder made by an earlier surfstream (before the marker) always holds.
const LEGACY_MARKER: &str = surfstream_runtime::shell::RESOLVED_GRAPH;

/// What the run reads and whether the user allowed replacing a folder that is not a run.
#[derive(Debug, Default, Clone)]
pub struct Claim {
    /// Files and folders the run reads: the out dir may not be one of them or hold one
    /// (files inside an out dir that is already a run are carried into the new run instead).
    pub inputs: Vec<PathBuf>,
    /// `--force`: replace an existing out dir that is not a surfstream run.
    pub force: bool,
}

/// What a failed run keeps besides [`FAILED`]: the diagnostics, never an output.
const KEPT_ON_FAILURE: &[&str] = &[
    "logs",
    "nodes",
    surfstream_runtime::shell::RESOLVED_GRAPH,
    MARKER,
];

/// The out dir of a run in progress: locked, with its staging folder.
pub struct StagedOut {
    /// Where the outputs end up.
    pub final_dir: PathBuf,
    /// Where this run writes while it runs.
    pub staging: PathBuf,
    _lock: OutDirLock,
}

fn sibling(out: &Path, suffix: &str) -> Result<PathBuf> {
    let name = out
        .file_name()
        .ok_or_else(|| anyhow!("{}: an out dir needs a folder name", out.display()))?;
    let mut n = name.to_os_string();
    n.push(suffix);
    Ok(out.with_file_name(n))
}

/// `out` made absolute without resolving symlinks of the last component (it may not exist).
fn absolute(out: &Path) -> Result<PathBuf> {
    let abs = if out.is_absolute() {
        out.to_path_buf()
    } else {
        std::env::current_dir()
            .context("cannot read the current folder")?
            .join(out)
    };
    let parent = abs
        .parent()
        .ok_or_else(|| anyhow!("{}: an out dir needs a parent folder", out.display()))?;
    std::fs::create_dir_all(parent)
        .with_context(|| format!("{}: cannot create the out dir's parent", parent.display()))?;
    let parent = parent
        .canonicalize()
        .with_context(|| format!("{}: cannot resolve", parent.display()))?;
    let name = abs
        .file_name()
        .filter(|n| *n != "..")
        .ok_or_else(|| anyhow!("{}: an out dir needs a folder name", out.display()))?;
    Ok(parent.join(name))
}

/// Whether `dir` is a folder a surfstream run made (or an earlier surfstream's run folder).
pub fn is_run_folder(dir: &Path) -> bool {
    dir.join(MARKER).is_file() || dir.join(LEGACY_MARKER).is_file()
}

/// Checks that `out` may become this run's out dir (see the module doc, "Ownership"); touches
/// nothing. Returns `out` made absolute.
pub fn check_ours(out: &Path, claim: &Claim) -> Result<PathBuf> {
    let shown = out.display();
    if out.canonicalize().is_ok_and(|p| p.parent().is_none()) {
        bail!(
            "{shown}: refusing to use this folder as an out dir (the file system root): name a \
             new folder with -o, e.g. -o out/run1"
        );
    }
    if std::fs::symlink_metadata(out).is_ok_and(|m| m.file_type().is_symlink()) {
        bail!(
            "{shown}: the out dir is a symbolic link; surfstream does not replace a link or write through it: name the real folder with -o"
        );
    }
    let final_dir = absolute(out)?;
    if final_dir.exists() && !final_dir.is_dir() {
        bail!(
            "{}: the out dir exists and is not a folder",
            final_dir.display()
        );
    }
    let home = std::env::var_os("HOME").map(PathBuf::from);
    let cwd = std::env::current_dir().ok();
    let canon = |p: &Path| p.canonicalize().unwrap_or_else(|_| p.to_path_buf());
    if final_dir.parent().is_none()
        || home.as_deref().is_some_and(|h| canon(h) == final_dir)
        || cwd
            .as_deref()
            .is_some_and(|c| canon(c).starts_with(&final_dir))
    {
        bail!(
            "{}: refusing to use this folder as an out dir (the file system root, the home folder, or the current folder or one of its parents): a run replaces its out dir whole; name a new folder with -o, e.g. -o out/run1",
            final_dir.display()
        );
    }
    let ours = final_dir.is_dir() && is_run_folder(&final_dir);
    for input in &claim.inputs {
        let Ok(input) = input.canonicalize() else {
            continue;
        };
        if !input.starts_with(&final_dir) {
            continue;
        }
        // A file read from inside an earlier run (an inferred scan.toml, a recording) is
        // carried into the new run; anything else would be lost when the run replaces it.
        if ours && input != final_dir && input.is_file() {
            continue;
        }
        bail!(
            "{}: the out dir {} the input {}; a run replaces its out dir whole, so the input would be lost: choose another -o",
            final_dir.display(),
            if input == final_dir { "is" } else { "holds" },
            input.display()
        );
    }
    if final_dir.is_dir() && !ours && !claim.force {
        let empty = std::fs::read_dir(&final_dir)
            .with_context(|| format!("{}: cannot read the out dir", final_dir.display()))?
            .next()
            .is_none();
        if !empty {
            bail!(
                "{}: the out dir exists and is not a surfstream run (it has no {MARKER}); a run replaces its out dir whole, so its files would be deleted. Choose another -o, or pass --force to replace it",
                final_dir.display()
            );
        }
    }
    Ok(final_dir)
}

/// The files and folders a graph reads: every node parameter that names an existing path,
/// and for a scan manifest the folder of its tiles (unless the manifest lies in `out` itself:
/// then it was inferred there, and the caller names the tiles' folder).
pub fn inputs_of(graph: &surfstream_runtime::graph::GraphFile, out: &Path) -> Vec<PathBuf> {
    let out = absolute(out).ok().and_then(|o| o.canonicalize().ok());
    let mut inputs = Vec::new();
    for n in &graph.nodes {
        // A scan source's tiles lie beside its manifest (the replay's own reading of it).
        let scan_source = n.node == <ReplayReport as NodeRecord>::NODE_KIND
            && matches!(
                surfstream_replay::Config::from_table(&n.params),
                Ok(surfstream_replay::Config::Scan(_))
            );
        for v in n.params.values() {
            let Some(path) = v
                .as_str()
                .map(Path::new)
                .and_then(|p| p.canonicalize().ok())
            else {
                continue;
            };
            let inside_out = out.as_deref().is_some_and(|o| path.starts_with(o));
            if path.is_file() && !inside_out && scan_source {
                if let Some(dir) = path.parent() {
                    inputs.push(dir.to_path_buf());
                }
            }
            inputs.push(path);
        }
    }
    inputs
}

/// Creates `out` (and its parents) for files written before the run is staged (an inferred
/// scan.toml), marked as a run folder; `out` must pass [`check_ours`] first.
pub fn create_marked(out: &Path) -> Result<()> {
    if !out.exists() {
        std::fs::create_dir_all(out)
            .with_context(|| format!("{}: cannot create", out.display()))?;
    }
    if !is_run_folder(out) {
        write_marker(out)?;
    }
    Ok(())
}

fn write_marker(dir: &Path) -> Result<()> {
    let path = dir.join(MARKER);
    let mut file = create_new_file(&path, "the run marker")?;
    writeln!(
        file,
        "This folder was made by surfstream {}: a later run into it replaces it whole.",
        env!("CARGO_PKG_VERSION")
    )
    .with_context(|| format!("{}: cannot write the run marker", path.display()))
}

/// Creates `path`, which must not exist: never through a symbolic link (O_NOFOLLOW), never an
/// existing file (O_EXCL). For files a run creates in a folder the user named (issue 36).
pub fn create_new_file(path: &Path, what: &str) -> Result<File> {
    use std::os::unix::fs::OpenOptionsExt;
    File::options()
        .write(true)
        .create_new(true)
        .custom_flags(libc::O_NOFOLLOW | libc::O_CLOEXEC)
        .open(path)
        .map_err(|e| match e.kind() {
            std::io::ErrorKind::AlreadyExists => anyhow!(
                "{}: cannot create {what}: something of that name is already there (a file or a symbolic link that surfstream did not make); remove it or choose another folder",
                path.display()
            ),
            _ => anyhow!("{}: cannot create {what}: {e}", path.display()),
        })
}

/// Opens (or creates, mode 0600) a file of this user's that may exist already, such as the
/// out dir's lock: never through a symbolic link (O_NOFOLLOW), and refused unless it is a
/// regular file owned by this user (issue 36: a lock planted as a link to a user's file made
/// the run truncate that file).
fn open_own_file(path: &Path, what: &str) -> Result<File> {
    use std::os::unix::fs::OpenOptionsExt;
    let file = File::options()
        .create(true)
        .truncate(false)
        .read(true)
        .write(true)
        .mode(0o600)
        .custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK | libc::O_CLOEXEC)
        .open(path)
        .map_err(|e| {
            if e.raw_os_error() == Some(libc::ELOOP) {
                anyhow!(
                    "{}: {what} is a symbolic link; surfstream does not follow it (it would write into the file it points to): remove it, or choose another --out",
                    path.display()
                )
            } else {
                anyhow!("{}: cannot open {what}: {e}", path.display())
            }
        })?;
    let meta = file
        .metadata()
        .with_context(|| format!("{}: cannot read {what}", path.display()))?;
    if !meta.file_type().is_file() {
        bail!(
            "{}: {what} is not a regular file (a folder, FIFO or device is there): remove it, or choose another --out",
            path.display()
        );
    }
    // SAFETY: geteuid has no preconditions.
    let me = unsafe { libc::geteuid() };
    if meta.uid() != me {
        bail!(
            "{}: {what} is owned by uid {}, not by you (uid {me}): another user's file is never used; remove it, or choose another --out",
            path.display(),
            meta.uid()
        );
    }
    Ok(file)
}

/// Locks `out`, removes stale staging folders of killed runs, and creates this run's staging
/// folder (marked as a run folder). Nothing in `out` itself is touched.
pub fn stage(out: &Path, claim: &Claim) -> Result<StagedOut> {
    let final_dir = check_ours(out, claim)?;
    let lock = OutDirLock::take(&sibling(&final_dir, ".lock")?, &final_dir)?;
    // Checked again under the lock: another run may have committed meanwhile.
    check_ours(&final_dir, claim)?;
    check_replaceable(&final_dir)?;
    let stale = remove_stale_staging(&final_dir);
    if stale > 0 {
        eprintln!(
            "surfstream: removed {stale} staging folder(s) of an earlier run into {} that was killed",
            final_dir.display()
        );
    }
    let staging = sibling(&final_dir, &format!(".staging-{}", std::process::id()))?;
    std::fs::create_dir(&staging)
        .with_context(|| format!("{}: cannot create the staging folder", staging.display()))?;
    if let Err(e) = write_marker(&staging) {
        let _ = std::fs::remove_dir_all(&staging);
        return Err(e);
    }
    Ok(StagedOut {
        final_dir,
        staging,
        _lock: lock,
    })
}

/// Checks, before any work, that a finished run could be moved into `out` (issue 36: a
/// read-only or unmovable out dir was found only after the whole pipeline): its parent is
/// writable, and an existing `out` is neither a mount point nor, in a sticky folder, another
/// user's (neither can be renamed).
fn check_replaceable(out: &Path) -> Result<()> {
    use std::ffi::CString;
    use std::os::unix::ffi::OsStrExt;
    let parent = out
        .parent()
        .ok_or_else(|| anyhow!("{}: an out dir needs a parent folder", out.display()))?;
    let c = CString::new(parent.as_os_str().as_bytes())
        .map_err(|_| anyhow!("{}: a path with a NUL byte", parent.display()))?;
    // SAFETY: a valid NUL-terminated path; access only reads it.
    if unsafe { libc::access(c.as_ptr(), libc::W_OK | libc::X_OK) } != 0 {
        bail!(
            "{}: the out dir's folder is not writable ({}): a run writes beside its out dir and moves its result into place; choose another -o",
            parent.display(),
            std::io::Error::last_os_error()
        );
    }
    let Ok(meta) = std::fs::symlink_metadata(out) else {
        return Ok(()); // no out dir yet
    };
    let pmeta =
        std::fs::metadata(parent).with_context(|| format!("{}: cannot read", parent.display()))?;
    if meta.dev() != pmeta.dev() {
        bail!(
            "{}: the out dir is a mount point; a run replaces its out dir by renaming, which a mount point cannot be: name a folder inside it with -o",
            out.display()
        );
    }
    // SAFETY: geteuid has no preconditions.
    let me = unsafe { libc::geteuid() };
    let sticky = pmeta.mode() & libc::S_ISVTX != 0;
    if sticky && me != 0 && meta.uid() != me && pmeta.uid() != me {
        bail!(
            "{}: the out dir belongs to uid {} in a sticky folder, so it cannot be replaced by you: choose another -o",
            out.display(),
            meta.uid()
        );
    }
    Ok(())
}

/// Removes `OUT.staging-*` beside `out` that carry the run marker (a user's folder of that
/// name is left alone), except those of completed runs that could not be moved
/// ([`COMPLETE_NOT_MOVED`]), which are named. Only for the holder of `out`'s lock: no live run
/// writes there.
fn remove_stale_staging(out: &Path) -> usize {
    let (Some(parent), Some(name)) = (out.parent(), out.file_name()) else {
        return 0;
    };
    let prefix = format!("{}.staging-", name.to_string_lossy());
    let Ok(entries) = std::fs::read_dir(parent) else {
        return 0;
    };
    entries
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().starts_with(&prefix))
        .filter(|e| e.file_type().is_ok_and(|t| t.is_dir()) && e.path().join(MARKER).is_file())
        .filter(|e| {
            let complete = e.path().join(COMPLETE_NOT_MOVED).is_file();
            if complete {
                eprintln!(
                    "surfstream: kept {}: a completed run that could not be moved into {} (move or remove it yourself)",
                    e.path().display(),
                    out.display()
                );
            }
            !complete
        })
        .filter(|e| std::fs::remove_dir_all(e.path()).is_ok())
        .count()
}

impl StagedOut {
    /// Copies files that the graph reads from inside the out dir (an inferred `scan.toml`, a
    /// recording replayed into its own folder) into the staging folder, so the committed run
    /// still holds them. Node parameters name such files as strings. Returns their paths
    /// relative to the out dir: files the run did not make (the model output set keeps them).
    pub fn carry_inputs(
        &self,
        graph: &surfstream_runtime::graph::GraphFile,
    ) -> Result<Vec<String>> {
        let mut carried = Vec::new();
        let Ok(out) = self.final_dir.canonicalize() else {
            return Ok(carried); // no out dir yet: nothing to carry
        };
        for n in &graph.nodes {
            for v in n.params.values() {
                let Some(s) = v.as_str() else { continue };
                let Ok(path) = Path::new(s).canonicalize() else {
                    continue;
                };
                let Ok(rel) = path.strip_prefix(&out) else {
                    continue;
                };
                if !path.is_file() {
                    continue;
                }
                let to = self.staging.join(rel);
                if let Some(dir) = to.parent() {
                    std::fs::create_dir_all(dir)
                        .with_context(|| format!("{}: cannot create", dir.display()))?;
                }
                std::fs::copy(&path, &to).with_context(|| {
                    format!(
                        "{}: cannot copy the input into the staging folder {}",
                        path.display(),
                        to.display()
                    )
                })?;
                carried.push(rel.to_string_lossy().to_string());
            }
        }
        Ok(carried)
    }

    /// The run is complete: it replaces the out dir (and whatever run was there). When it
    /// cannot be moved, the staging folder is marked complete ([`COMPLETE_NOT_MOVED`]) so no
    /// later run removes it.
    pub fn commit(self) -> Result<PathBuf> {
        if let Err(e) = replace_dir(&self.staging, &self.final_dir) {
            let mark = self.staging.join(COMPLETE_NOT_MOVED);
            if let Ok(mut f) = create_new_file(&mark, "the completed-run mark") {
                let _ = writeln!(
                    f,
                    "This run completed but could not be moved into {}: {e:#}\nsurfstream keeps this folder.",
                    self.final_dir.display()
                );
            }
            return Err(e);
        }
        Ok(self.final_dir.clone())
    }

    /// The run failed before anything was produced: the out dir stays as it was.
    pub fn discard(self) {
        let _ = std::fs::remove_dir_all(&self.staging);
    }

    /// The run failed after it started producing: the out dir becomes the failed run (a
    /// [`FAILED`] record naming the cause, the logs), without any of its outputs. Returns the
    /// folder that holds the record.
    pub fn fail(self, cause: &anyhow::Error) -> Result<PathBuf> {
        // Outputs first: on a full disk this frees the room the record needs.
        if let Ok(entries) = std::fs::read_dir(&self.staging) {
            for e in entries.flatten() {
                let name = e.file_name().to_string_lossy().to_string();
                if KEPT_ON_FAILURE.contains(&name.as_str()) {
                    continue;
                }
                let p = e.path();
                let _ = if p.is_dir() {
                    std::fs::remove_dir_all(&p)
                } else {
                    std::fs::remove_file(&p)
                };
            }
        }
        let record = self.staging.join(FAILED);
        let text = failure_record(cause);
        std::fs::write(&record, text)
            .with_context(|| format!("{}: cannot write the failure record", record.display()))?;
        replace_dir(&self.staging, &self.final_dir)?;
        Ok(self.final_dir.clone())
    }
}

fn failure_record(cause: &anyhow::Error) -> String {
    let when = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0);
    format!(
        "surfstream: this run FAILED; the folder holds no outputs, only its logs.\n\
         cause: {cause:#}\n\
         unix_time: {when}\n\
         pid: {}\n",
        std::process::id()
    )
}

/// Puts `from` at `to`, replacing a folder at `to`; removes the replaced folder.
fn replace_dir(from: &Path, to: &Path) -> Result<()> {
    if !to.exists() {
        return std::fs::rename(from, to).with_context(|| {
            format!(
                "{}: cannot move the staging folder {} into place",
                to.display(),
                from.display()
            )
        });
    }
    if exchange(from, to).is_ok() {
        // `from` now holds the replaced run.
        let _ = std::fs::remove_dir_all(from);
        return Ok(());
    }
    // No atomic exchange on this file system: move the old run aside first.
    let old = sibling(to, &format!(".replaced-{}", std::process::id()))?;
    std::fs::rename(to, &old)
        .with_context(|| format!("{}: cannot move the previous run aside", to.display()))?;
    std::fs::rename(from, to).with_context(|| {
        format!(
            "{}: cannot move the staging folder {} into place",
            to.display(),
            from.display()
        )
    })?;
    let _ = std::fs::remove_dir_all(&old);
    Ok(())
}

fn exchange(a: &Path, b: &Path) -> std::io::Result<()> {
    use std::ffi::CString;
    use std::os::unix::ffi::OsStrExt;
    let ca = CString::new(a.as_os_str().as_bytes())?;
    let cb = CString::new(b.as_os_str().as_bytes())?;
    // SAFETY: two valid NUL-terminated paths; renameat2 only reads them.
    let rc = unsafe {
        libc::renameat2(
            libc::AT_FDCWD,
            ca.as_ptr(),
            libc::AT_FDCWD,
            cb.as_ptr(),
            libc::RENAME_EXCHANGE,
        )
    };
    if rc == 0 {
        Ok(())
    } else {
        Err(std::io::Error::last_os_error())
    }
}

/// `OUT.lock`: an exclusive flock for the life of the run, with the owner's pid inside (for the
/// error another run gets). The file is removed when the run ends.
struct OutDirLock {
    file: File,
    path: PathBuf,
}

impl OutDirLock {
    fn take(path: &Path, out: &Path) -> Result<Self> {
        loop {
            let mut file = open_own_file(path, "the out dir's lock")?;
            // SAFETY: flock on a file descriptor we own.
            if unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) } != 0 {
                let mut owner = String::new();
                let _ = file.read_to_string(&mut owner);
                let owner = owner.trim();
                bail!(
                    "{}: the out dir is in use by another run ({}; lock {}); wait for it or choose another --out",
                    out.display(),
                    if owner.is_empty() {
                        "pid unknown".to_string()
                    } else {
                        format!("pid {owner}")
                    },
                    path.display()
                );
            }
            // The previous holder may have removed the file between our open and our lock:
            // then we locked an orphan inode, and must lock the file that is there now.
            let same = std::fs::metadata(path)
                .ok()
                .zip(file.metadata().ok())
                .is_some_and(|(on_disk, ours)| {
                    on_disk.ino() == ours.ino() && on_disk.dev() == ours.dev()
                });
            if !same {
                continue;
            }
            file.set_len(0)
                .and_then(|_| file.rewind())
                .and_then(|_| write!(file, "{}", std::process::id()))
                .with_context(|| format!("{}: cannot write the lock", path.display()))?;
            return Ok(Self {
                file,
                path: path.to_path_buf(),
            });
        }
    }
}

impl Drop for OutDirLock {
    fn drop(&mut self) {
        // Remove while still holding the lock; a waiter that opened the old inode notices the
        // change of inode and retries.
        let _ = std::fs::remove_file(&self.path);
        let _ = &self.file;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_committed_run_replaces_the_old_one_whole() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        std::fs::create_dir(&out).unwrap();
        std::fs::write(out.join(MARKER), "").unwrap();
        std::fs::write(out.join("report.html"), "old").unwrap();
        std::fs::write(out.join("surface.stl"), "old").unwrap();
        let staged = stage(&out, &Claim::default()).unwrap();
        assert!(staged
            .staging
            .starts_with(dir.path().canonicalize().unwrap()));
        std::fs::write(staged.staging.join("surface.stl"), "new").unwrap();
        // Untouched while the run runs.
        assert_eq!(
            std::fs::read_to_string(out.join("surface.stl")).unwrap(),
            "old"
        );
        staged.commit().unwrap();
        assert_eq!(
            std::fs::read_to_string(out.join("surface.stl")).unwrap(),
            "new"
        );
        assert!(!out.join("report.html").exists(), "an old output survived");
        let names: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .flatten()
            .map(|e| e.file_name().to_string_lossy().to_string())
            .collect();
        assert_eq!(names, ["out"], "staging, replaced run or lock left behind");
    }

    #[test]
    fn a_lock_that_is_a_link_or_not_a_regular_file_is_refused_and_its_target_untouched() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        let precious = dir.path().join("precious.txt");
        std::fs::write(&precious, "years of work").unwrap();
        let lock = dir.path().join("out.lock");
        std::os::unix::fs::symlink(&precious, &lock).unwrap();
        let e = format!(
            "{:#}",
            stage(&out, &Claim::default()).err().expect("refused")
        );
        assert!(e.contains("out.lock") && e.contains("symbolic link"), "{e}");
        assert_eq!(std::fs::read_to_string(&precious).unwrap(), "years of work");
        // A dangling link: its target is never created.
        std::fs::remove_file(&lock).unwrap();
        let target = dir.path().join("created-through-the-link");
        std::os::unix::fs::symlink(&target, &lock).unwrap();
        assert!(stage(&out, &Claim::default()).is_err());
        assert!(!target.exists(), "the lock was created through a link");
        // A folder in its place.
        std::fs::remove_file(&lock).unwrap();
        std::fs::create_dir(&lock).unwrap();
        let e = format!(
            "{:#}",
            stage(&out, &Claim::default()).err().expect("refused")
        );
        assert!(e.contains("out.lock"), "{e}");
        assert!(!out.exists(), "a refused run created the out dir");
    }

    #[test]
    fn a_run_marker_planted_as_a_link_is_refused_not_followed() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        std::fs::create_dir(&out).unwrap();
        let precious = dir.path().join("precious.txt");
        std::fs::write(&precious, "years of work").unwrap();
        // An empty folder becomes a run folder by its marker: a dangling link there is refused.
        let target = dir.path().join("through-the-marker");
        std::os::unix::fs::symlink(&target, out.join(MARKER)).unwrap();
        assert!(create_marked(&out).is_err());
        assert!(!target.exists());
        assert_eq!(std::fs::read_to_string(&precious).unwrap(), "years of work");
    }

    /// Mounts a 1 MiB tmpfs at `at` (root only); unmounted when dropped.
    struct Mounted(PathBuf);
    impl Mounted {
        fn at(at: &Path) -> Option<Self> {
            let ok = std::process::Command::new("mount")
                .args(["-t", "tmpfs", "-o", "size=1m", "tmpfs"])
                .arg(at)
                .stderr(std::process::Stdio::null())
                .status()
                .is_ok_and(|s| s.success());
            if !ok {
                eprintln!(
                    "SKIPPED: cannot mount a tmpfs (needs root) to make an unmovable out dir"
                );
            }
            ok.then(|| Self(at.to_path_buf()))
        }
    }
    impl Drop for Mounted {
        fn drop(&mut self) {
            let _ = std::process::Command::new("umount").arg(&self.0).status();
        }
    }

    #[test]
    fn an_unmovable_out_dir_is_refused_before_work_and_a_completed_unmoved_run_is_kept() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        std::fs::create_dir(&out).unwrap();
        let staged = stage(&out, &Claim::default()).unwrap();
        std::fs::write(staged.staging.join("panorama.npy"), "result").unwrap();
        let staging = staged.staging.clone();
        // The out dir becomes unmovable while the run runs.
        let Some(_mount) = Mounted::at(&out) else {
            staged.discard();
            return;
        };
        assert!(staged.commit().is_err(), "moved onto a mount point");
        assert!(staging.join(COMPLETE_NOT_MOVED).is_file());
        // Known before any work now, and the completed run is kept, not removed as stale.
        std::fs::write(out.join(MARKER), "").unwrap();
        let e = format!(
            "{:#}",
            stage(&out, &Claim::default()).err().expect("refused")
        );
        assert!(e.contains("mount point"), "{e}");
        assert_eq!(
            std::fs::read_to_string(staging.join("panorama.npy")).unwrap(),
            "result"
        );
        let other = dir.path().join("other");
        assert_eq!(remove_stale_staging(&out), 0);
        assert!(staging.is_dir(), "a completed run was removed");
        stage(&other, &Claim::default()).unwrap().discard();
    }

    #[test]
    fn a_second_run_into_the_same_out_dir_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        let first = stage(&out, &Claim::default()).unwrap();
        let e = stage(&out, &Claim::default())
            .err()
            .expect("second run refused")
            .to_string();
        assert!(
            e.contains("in use by another run") && e.contains(&std::process::id().to_string()),
            "{e}"
        );
        first.discard();
        // Released: the next run gets it.
        stage(&out, &Claim::default()).unwrap().discard();
        assert!(!out.exists(), "a discarded run created the out dir");
    }

    #[test]
    fn a_failed_run_leaves_a_failed_record_and_no_outputs() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        std::fs::create_dir(&out).unwrap();
        std::fs::write(out.join(MARKER), "").unwrap();
        std::fs::write(out.join("panorama.npy"), "old").unwrap();
        let staged = stage(&out, &Claim::default()).unwrap();
        std::fs::create_dir(staged.staging.join("logs")).unwrap();
        std::fs::write(staged.staging.join("logs/fusion.stderr"), "boom").unwrap();
        std::fs::write(staged.staging.join("datum.npy"), "half").unwrap();
        staged
            .fail(&anyhow!("No space left on device (os error 28)"))
            .unwrap();
        let record = std::fs::read_to_string(out.join(FAILED)).unwrap();
        assert!(record.contains("No space left on device"), "{record}");
        assert!(out.join("logs/fusion.stderr").exists());
        assert!(!out.join("datum.npy").exists() && !out.join("panorama.npy").exists());
    }

    #[test]
    fn staging_folders_of_killed_runs_are_removed_by_the_next_run() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        let killed = dir.path().join("out.staging-999999");
        std::fs::create_dir_all(killed.join("nodes")).unwrap();
        std::fs::write(killed.join("recording.mcap.partial"), "x").unwrap();
        std::fs::write(killed.join(MARKER), "").unwrap();
        // A user's folder that merely has the name is not ours.
        let users = dir.path().join("out.staging-notes");
        std::fs::create_dir(&users).unwrap();
        std::fs::write(users.join("thesis.txt"), "x").unwrap();
        let staged = stage(&out, &Claim::default()).unwrap();
        assert!(!killed.exists());
        assert!(
            users.join("thesis.txt").exists(),
            "a user's folder was removed"
        );
        staged.discard();
    }

    #[test]
    fn inputs_read_from_inside_the_out_dir_are_carried_into_the_new_run() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        std::fs::create_dir(&out).unwrap();
        std::fs::write(out.join(MARKER), "").unwrap();
        std::fs::write(out.join("scan.toml"), "[scan]").unwrap();
        let text = format!(
            "[graph]\nname = \"g\"\n[[node]]\nid = \"stage\"\nnode = \"replay\"\nparams = {{ path = {:?} }}\n",
            out.join("scan.toml").to_str().unwrap()
        );
        let graph =
            surfstream_runtime::graph::GraphFile::parse(&text, "g.toml", &crate::nodes::registry())
                .unwrap();
        let staged = stage(&out, &Claim::default()).unwrap();
        staged.carry_inputs(&graph).unwrap();
        staged.commit().unwrap();
        assert_eq!(
            std::fs::read_to_string(out.join("scan.toml")).unwrap(),
            "[scan]"
        );
    }

    fn listing(dir: &Path) -> Vec<String> {
        let mut v: Vec<_> = std::fs::read_dir(dir)
            .unwrap()
            .flatten()
            .map(|e| e.file_name().to_string_lossy().to_string())
            .collect();
        v.sort();
        v
    }

    #[test]
    fn a_folder_that_is_not_a_run_is_refused_and_left_intact() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("V");
        std::fs::create_dir_all(out.join("sub")).unwrap();
        std::fs::write(out.join("thesis.txt"), "x").unwrap();
        let e = format!(
            "{:#}",
            stage(&out, &Claim::default()).err().expect("refused")
        );
        assert!(
            e.contains("is not a surfstream run") && e.contains("--force"),
            "{e}"
        );
        assert_eq!(listing(&out), ["sub", "thesis.txt"]);
        assert_eq!(listing(dir.path()), ["V"], "lock or staging left behind");
        // --force is the explicit override.
        let forced = Claim {
            force: true,
            ..Claim::default()
        };
        stage(&out, &forced).unwrap().commit().unwrap();
        assert_eq!(listing(&out), [MARKER]);
    }

    #[test]
    fn an_empty_folder_may_become_the_out_dir() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("empty");
        std::fs::create_dir(&out).unwrap();
        stage(&out, &Claim::default()).unwrap().commit().unwrap();
        assert!(is_run_folder(&out));
    }

    #[test]
    fn a_symlinked_out_dir_is_refused_even_with_force() {
        let dir = tempfile::tempdir().unwrap();
        let real = dir.path().join("real");
        std::fs::create_dir(&real).unwrap();
        std::fs::write(real.join(MARKER), "").unwrap();
        let link = dir.path().join("link");
        std::os::unix::fs::symlink(&real, &link).unwrap();
        let forced = Claim {
            force: true,
            ..Claim::default()
        };
        let e = format!("{:#}", stage(&link, &forced).err().expect("refused"));
        assert!(e.contains("symbolic link"), "{e}");
        assert!(std::fs::symlink_metadata(&link)
            .unwrap()
            .file_type()
            .is_symlink());
    }

    #[test]
    fn the_input_folder_or_a_parent_of_an_input_is_refused_even_with_force() {
        let dir = tempfile::tempdir().unwrap();
        let scan = dir.path().join("D");
        std::fs::create_dir(&scan).unwrap();
        std::fs::write(scan.join("scan.toml"), "[scan]").unwrap();
        std::fs::write(scan.join("tile_000.npy"), "x").unwrap();
        let claim = Claim {
            inputs: vec![scan.clone()],
            force: true,
        };
        for out in [scan.clone(), dir.path().to_path_buf()] {
            let e = format!("{:#}", stage(&out, &claim).err().expect("refused"));
            assert!(e.contains("the input"), "{e}");
        }
        assert_eq!(listing(&scan), ["scan.toml", "tile_000.npy"]);
        // Beside the input is fine.
        stage(&dir.path().join("out"), &claim).unwrap().discard();
    }

    #[test]
    fn the_current_folder_root_and_home_are_refused() {
        let forced = Claim {
            force: true,
            ..Claim::default()
        };
        for out in [Path::new("."), Path::new("/")] {
            let e = format!("{:#}", check_ours(out, &forced).expect_err("refused"));
            assert!(e.contains("refusing to use this folder"), "{out:?}: {e}");
        }
        if let Some(home) = std::env::var_os("HOME") {
            assert!(check_ours(Path::new(&home), &forced).is_err());
        }
    }
}
