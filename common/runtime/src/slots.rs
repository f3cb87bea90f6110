//! Launch slots: which iceoryx2 domain a `surfstream launch` uses, safely on a machine shared
//! by several users (issue 27).
//!
//! - **Per user**: the slot locks and the iceoryx2 records live in a folder only this user can
//!   enter: `$XDG_RUNTIME_DIR/surfstream` when that is the user's own private folder, else
//!   `/tmp/surfstream-<uid>`. The folder is checked (not a symlink, owned by us, no group or
//!   other access) before anything in it is opened, and created 0700 when missing (a folder
//!   another user planted under that name is refused, naming its owner). `$TMPDIR` plays no
//!   part: two launches with different `TMPDIR`s see the same slots.
//! - **Race-free**: a slot is a lock file opened with `O_NOFOLLOW` (a planted symlink is
//!   refused, never followed), checked to be a regular file of ours, and held with `flock`
//!   for the life of the launch.
//! - **Unguessable domain**: each launch names its domain `ss<K>_<nonce>_` (a fresh random
//!   nonce) and records it in the slot's lock file, so the next holder of the slot cleans what
//!   a killed launch left, and no other user can pre-create the domain's shared-memory files.
//! - **Management file 0600 and removed**: iceoryx2 creates a per-domain management segment in
//!   `/dev/shm` world-writable (0666) and never removes it; another user writing into it
//!   blocks every later node of that domain. The launcher creates it itself, 0600, before
//!   iceoryx2 opens it ([`create_management_segment`]), and removes it at the end.

use std::fs::File;
use std::io::{Read, Seek, SeekFrom, Write};
use std::os::fd::AsRawFd;
use std::os::unix::fs::{MetadataExt, OpenOptionsExt, PermissionsExt};
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};

/// Concurrent launches of one user (one iceoryx2 domain each).
pub const SLOTS: usize = 32;

fn euid() -> u32 {
    // SAFETY: geteuid has no preconditions.
    unsafe { libc::geteuid() }
}

/// Whether `dir` is a real folder (not a symlink) owned by this user with no group or other
/// access; `Ok(false)` when it does not exist.
fn private_dir(dir: &Path) -> Result<bool> {
    let meta = match std::fs::symlink_metadata(dir) {
        Ok(m) => m,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(false),
        Err(e) => bail!("{}: cannot inspect: {e}", dir.display()),
    };
    if meta.file_type().is_symlink() {
        bail!(
            "{}: is a symlink; surfstream keeps its launch slots only in a real folder of yours (remove the link)",
            dir.display()
        );
    }
    if !meta.is_dir() {
        bail!("{}: not a folder (remove it)", dir.display());
    }
    if meta.uid() != euid() {
        bail!(
            "{}: owned by uid {}, not by you (uid {}): another user created it, so its launch slots cannot be trusted; have it removed",
            dir.display(),
            meta.uid(),
            euid()
        );
    }
    if meta.mode() & 0o077 != 0 {
        // Ours, but open to others: close it before anything in it is trusted.
        std::fs::set_permissions(dir, std::fs::Permissions::from_mode(0o700))
            .with_context(|| format!("{}: cannot make it private (0700)", dir.display()))?;
    }
    Ok(true)
}

/// Creates `dir` 0700 unless it exists; either way it must pass [`private_dir`].
fn ensure_private_dir(dir: &Path) -> Result<()> {
    if private_dir(dir)? {
        return Ok(());
    }
    let mut b = std::fs::DirBuilder::new();
    std::os::unix::fs::DirBuilderExt::mode(&mut b, 0o700);
    match b.create(dir) {
        Ok(()) => {}
        // Someone made it between the check and now: check what it is.
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
        Err(e) => bail!("{}: cannot create: {e}", dir.display()),
    }
    if !private_dir(dir)? {
        bail!("{}: vanished while being created", dir.display());
    }
    Ok(())
}

/// This user's private surfstream folder (slot locks, iceoryx2 records): checked, created if
/// missing. Does not depend on `$TMPDIR`.
pub fn user_dir() -> Result<PathBuf> {
    if let Some(xdg) = std::env::var_os("XDG_RUNTIME_DIR").map(PathBuf::from) {
        // Only a runtime folder that really is this user's (a `su` keeps the caller's).
        if xdg.is_absolute() && private_dir(&xdg).unwrap_or(false) {
            let dir = xdg.join("surfstream");
            ensure_private_dir(&dir)?;
            return Ok(dir);
        }
    }
    let dir = PathBuf::from(format!("/tmp/surfstream-{}", euid()));
    ensure_private_dir(&dir)?;
    Ok(dir)
}

/// The iceoryx2 root (node and service records) of this user's launches.
pub fn iceoryx2_root() -> Result<PathBuf> {
    Ok(user_dir()?.join("iceoryx2"))
}

/// The lock file of slot `k`.
pub fn lock_path(k: usize) -> Result<PathBuf> {
    Ok(user_dir()?.join(format!("slot-{k}.lock")))
}

/// An iceoryx2 domain prefix (`--domain`, a slot's `ss<K>_<nonce>_`): 1-32 characters of
/// [A-Za-z0-9_].
pub fn validate_prefix(prefix: &str) -> Result<()> {
    if prefix.is_empty()
        || prefix.len() > 32
        || !prefix
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_')
    {
        bail!("--domain {prefix:?}: expected 1-32 characters of [A-Za-z0-9_]");
    }
    Ok(())
}

/// The slot number of a domain `ss<K>_<nonce>_`.
pub fn index_of(domain: &str) -> Option<usize> {
    domain.strip_prefix("ss")?.split('_').next()?.parse().ok()
}

/// Opens a slot's lock file without following a symlink; it must be a regular file of ours.
fn open_lock(path: &Path) -> Result<File> {
    let file = File::options()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .mode(0o600)
        .custom_flags(libc::O_NOFOLLOW | libc::O_CLOEXEC)
        .open(path)
        .map_err(|e| match e.raw_os_error() {
            Some(libc::ELOOP) => anyhow!(
                "{}: is a symlink (planted?): refused, not followed; remove it",
                path.display()
            ),
            _ => anyhow!("{}: cannot open: {e}", path.display()),
        })?;
    let meta = file
        .metadata()
        .with_context(|| format!("{}: cannot inspect", path.display()))?;
    if !meta.is_file() || meta.uid() != euid() {
        bail!(
            "{}: not a regular file of yours (uid {}): refused",
            path.display(),
            meta.uid()
        );
    }
    Ok(file)
}

/// A held launch slot: the lock lives as long as this value.
pub struct Slot {
    lock: File,
    pub index: usize,
    /// This launch's iceoryx2 domain prefix, `ss<K>_<nonce>_`.
    pub prefix: String,
    /// The domain an earlier launch of this slot recorded (to clean), if any.
    pub previous: Option<String>,
}

/// A fresh nonce for a domain name (from the kernel's random source; time and pid otherwise).
fn nonce() -> u32 {
    let mut b = [0u8; 4];
    if File::open("/dev/urandom")
        .and_then(|mut f| f.read_exact(&mut b))
        .is_ok()
    {
        return u32::from_le_bytes(b);
    }
    let t = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.subsec_nanos())
        .unwrap_or(0);
    t ^ std::process::id().rotate_left(16)
}

/// Takes the first free slot of this user and records a fresh domain in it.
pub fn take() -> Result<Slot> {
    let mut refused = Vec::new();
    for k in 0..SLOTS {
        let path = lock_path(k)?;
        let mut file = match open_lock(&path) {
            Ok(f) => f,
            Err(e) => {
                // A bad slot file is named, and the next slot tried.
                refused.push(format!("{e:#}"));
                continue;
            }
        };
        // SAFETY: flock on a descriptor we own.
        if unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) } != 0 {
            continue;
        }
        let mut text = String::new();
        let _ = file.read_to_string(&mut text);
        let previous = text
            .lines()
            .next()
            .map(str::trim)
            .filter(|p| index_of(p) == Some(k) && validate_prefix(p).is_ok())
            .map(str::to_string);
        let prefix = format!("ss{k}_{:08x}_", nonce());
        file.set_len(0)
            .and_then(|_| file.seek(SeekFrom::Start(0)))
            .and_then(|_| file.write_all(format!("{prefix}\n").as_bytes()))
            .with_context(|| format!("{}: cannot record the slot's domain", path.display()))?;
        for r in &refused {
            eprintln!("surfstream: warning: launch slot skipped: {r}");
        }
        return Ok(Slot {
            lock: file,
            index: k,
            prefix,
            previous,
        });
    }
    if refused.is_empty() {
        bail!("all {SLOTS} launch slots are busy: too many graphs running at once")
    }
    bail!(
        "no usable launch slot: {} busy, {} refused:\n  {}",
        SLOTS - refused.len(),
        refused.len(),
        refused.join("\n  ")
    )
}

impl Slot {
    /// Forgets the recorded domain (the launch cleaned up after itself).
    pub fn release_clean(self) {
        let _ = self.lock.set_len(0);
        drop(self);
    }
}

/// Waits for slot `k`'s lock and holds it while the returned file lives (tests, tools: look at
/// a slot's domain without racing a launch).
pub fn hold(k: usize) -> Result<File> {
    let path = lock_path(k)?;
    let file = open_lock(&path)?;
    // SAFETY: flock on a descriptor we own.
    if unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX) } != 0 {
        bail!(
            "{}: cannot lock: {}",
            path.display(),
            std::io::Error::last_os_error()
        );
    }
    Ok(file)
}

/// The hash iceoryx2 0.10 puts in its storage names (of the stored type's name); the unit test
/// checks that iceoryx2 opens the segment named with it (a new iceoryx2 fails the test).
const MANAGEMENT_TYPE_HASH: &str = "9204dd183d1c4d8e1ff592a30766ffa6765aa8b5";

/// The `/dev/shm` name of iceoryx2's management segment of a domain (iceoryx2 0.10:
/// `<prefix><type hash>_node.<version>.global_mgmt`).
pub fn management_segment(prefix: &str) -> PathBuf {
    PathBuf::from(format!(
        "/dev/shm/{prefix}{MANAGEMENT_TYPE_HASH}_node.0_10_0.global_mgmt"
    ))
}

/// Creates a domain's management segment, 0600, before iceoryx2 would create it 0666: the
/// same 16 bytes iceoryx2 writes (its package version, then a zeroed node counter).
pub fn create_management_segment(prefix: &str) -> Result<()> {
    let path = management_segment(prefix);
    let mut f = File::options()
        .write(true)
        .create_new(true)
        .mode(0o600)
        .custom_flags(libc::O_NOFOLLOW | libc::O_CLOEXEC)
        .open(&path)
        .with_context(|| {
            format!(
                "{}: cannot create the domain's management segment",
                path.display()
            )
        })?;
    // iceoryx2 0.10's PackageVersion::to_u64: major << 32 | minor << 16 | patch.
    let version: u64 = 10 << 16;
    let mut bytes = [0u8; 16];
    bytes[..8].copy_from_slice(&version.to_ne_bytes());
    f.write_all(&bytes)
        .with_context(|| format!("{}: cannot write", path.display()))?;
    f.set_permissions(std::fs::Permissions::from_mode(0o600))
        .with_context(|| format!("{}: cannot make it 0600", path.display()))?;
    Ok(())
}

/// Removes a domain's management segment (only when no process of the domain is alive).
pub fn remove_management_segment(prefix: &str) -> bool {
    std::fs::remove_file(management_segment(prefix)).is_ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn slot_numbers_come_back_from_domains() {
        assert_eq!(index_of("ss7_0a0b0c0d_"), Some(7));
        assert_eq!(index_of("ss31_ffffffff_"), Some(31));
        assert_eq!(index_of("xx1_"), None);
    }

    #[test]
    fn a_symlinked_lock_file_is_refused_not_followed() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("victim");
        let link = dir.path().join("slot-0.lock");
        std::os::unix::fs::symlink(&target, &link).unwrap();
        let e = open_lock(&link).unwrap_err().to_string();
        assert!(e.contains("symlink"), "{e}");
        assert!(!target.exists(), "the link's target was created");
    }

    #[test]
    fn a_symlinked_or_open_user_dir_is_refused_or_closed() {
        let dir = tempfile::tempdir().unwrap();
        let real = dir.path().join("real");
        std::fs::create_dir(&real).unwrap();
        std::fs::set_permissions(&real, std::fs::Permissions::from_mode(0o777)).unwrap();
        assert!(private_dir(&real).unwrap());
        let mode = std::fs::metadata(&real).unwrap().mode() & 0o777;
        assert_eq!(mode, 0o700, "an open folder of ours is closed");
        let link = dir.path().join("link");
        std::os::unix::fs::symlink(&real, &link).unwrap();
        assert!(private_dir(&link)
            .unwrap_err()
            .to_string()
            .contains("symlink"));
        assert!(!private_dir(&dir.path().join("none")).unwrap());
    }

    #[test]
    fn the_management_segment_is_ours_0600_and_iceoryx2_uses_it() {
        let prefix = format!("sst{}_{:08x}_", std::process::id() % 1000, nonce());
        create_management_segment(&prefix).unwrap();
        let path = management_segment(&prefix);
        let mode = std::fs::metadata(&path).unwrap().mode() & 0o777;
        assert_eq!(mode, 0o600);
        let cfg = crate::ipc::domain_config(&prefix).unwrap();
        let a = crate::ipc::create_node(&cfg, "t/a").unwrap();
        let b = crate::ipc::create_node(&cfg, "t/b").unwrap();
        assert_ne!(a.id(), b.id());
        // iceoryx2 opened ours (no second management file, still 0600).
        let mgmt: Vec<_> = std::fs::read_dir("/dev/shm")
            .unwrap()
            .flatten()
            .map(|e| e.file_name().to_string_lossy().to_string())
            .filter(|n| n.starts_with(&prefix) && n.ends_with("global_mgmt"))
            .collect();
        assert_eq!(mgmt.len(), 1, "{mgmt:?}");
        assert_eq!(std::fs::metadata(&path).unwrap().mode() & 0o777, 0o600);
        drop((a, b));
        crate::ipc::wipe_domain(&cfg);
        assert!(remove_management_segment(&prefix));
        // A second creation of an existing segment is refused (O_EXCL), never reused blindly.
        create_management_segment(&prefix).unwrap();
        assert!(create_management_segment(&prefix).is_err());
        assert!(remove_management_segment(&prefix));
    }
}
