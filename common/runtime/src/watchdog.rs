//! Liveness of a launched graph (issue 15): stalls are detected, and no node outlives its
//! launcher.
//!
//! - **Heartbeat**: a launched node touches `<out>/logs/<node>.alive` (its modification time,
//!   no data: it costs no disk space, so a full disk cannot fake a stall) at most every
//!   [`BEAT_PERIOD`] from every loop it can wait in: its event loop, its startup waits, its
//!   end-of-run wait, and the backpressure handler of a send blocked by a full downstream
//!   queue. A node whose file stays untouched for `[graph] stall_timeout_s` is stalled:
//!   stopped (SIGSTOP), hung, or in one computation longer than the deadline.
//! - **Stall watch**: the launcher reads the files (and `/proc/<pid>/stat` to say whether the
//!   process is stopped) and names the stalled node, which is the receiver that does not drain,
//!   never the sender waiting for it: a sender blocked in `send()` keeps beating.
//! - **Launcher gone**: a node started by the launcher dies with it (PR_SET_PDEATHSIG), and
//!   checks at every housekeeping tick that its parent is still the launcher, which also
//!   covers a launcher that died before the death signal was armed.

use std::fs::File;
use std::os::fd::AsRawFd;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicI32, AtomicU64, Ordering};
use std::sync::OnceLock;
use std::time::{Duration, Instant, SystemTime};

use anyhow::{bail, Result};

/// How often a node touches its heartbeat at most.
pub const BEAT_PERIOD: Duration = Duration::from_millis(250);

/// Default of `[graph] stall_timeout_s`.
pub const DEFAULT_STALL_TIMEOUT_S: f64 = 60.0;

/// The heartbeat file of `node_id` in a run's out dir.
pub fn heartbeat_path(out_dir: &Path, node_id: &str) -> PathBuf {
    out_dir.join("logs").join(format!("{node_id}.alive"))
}

struct Heartbeat {
    file: File,
    epoch: Instant,
    /// Nanoseconds since `epoch` of the last touch.
    last_ns: AtomicU64,
}

static HEARTBEAT: OnceLock<Heartbeat> = OnceLock::new();
/// The launcher's pid as this process saw it at start; 0 when not launched.
static LAUNCHER_PID: AtomicI32 = AtomicI32::new(0);

/// Under the launcher: starts this process's heartbeat and remembers its parent (the
/// launcher). Called once, first thing in a node binary.
pub fn install(out_dir: &Path, node_id: &str) -> Result<()> {
    // SAFETY: getppid has no preconditions.
    let parent = unsafe { libc::getppid() };
    if parent == 1 {
        bail!("the launcher is gone (this node's parent is init): not starting");
    }
    LAUNCHER_PID.store(parent, Ordering::Relaxed);
    let path = heartbeat_path(out_dir, node_id);
    if let Some(dir) = path.parent() {
        let _ = std::fs::create_dir_all(dir);
    }
    let file = File::create(&path)
        .map_err(|e| anyhow::anyhow!("{}: cannot create the heartbeat: {e}", path.display()))?;
    let _ = HEARTBEAT.set(Heartbeat {
        file,
        epoch: Instant::now(),
        last_ns: AtomicU64::new(0),
    });
    // Long computations in the algorithm crates beat through the core's hook.
    surfstream_core::liveness::set_hook(beat);
    Ok(())
}

/// Tells the launcher this process is making progress (cheap; rate-limited).
pub fn beat() {
    let Some(h) = HEARTBEAT.get() else {
        return;
    };
    let now = h.epoch.elapsed().as_nanos() as u64;
    let last = h.last_ns.load(Ordering::Relaxed);
    if now.saturating_sub(last) < BEAT_PERIOD.as_nanos() as u64 && last != 0 {
        return;
    }
    h.last_ns.store(now, Ordering::Relaxed);
    // SAFETY: futimens on a descriptor we own; a null times pointer means "now".
    unsafe {
        libc::futimens(h.file.as_raw_fd(), std::ptr::null());
    }
}

/// Fails when the launcher that started this node is gone (this process was re-parented).
pub fn check_launcher() -> Result<()> {
    let launcher = LAUNCHER_PID.load(Ordering::Relaxed);
    // SAFETY: getppid has no preconditions.
    if launcher != 0 && unsafe { libc::getppid() } != launcher {
        bail!("the launcher (pid {launcher}) is gone: stopping");
    }
    Ok(())
}

/// Whether `pid` is stopped (SIGSTOP / SIGTSTP, or a tracer), from `/proc/<pid>/stat`.
pub fn is_stopped(pid: u32) -> bool {
    let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else {
        return false;
    };
    // "pid (comm) S ...": the state follows the last ')'.
    stat.rfind(')')
        .and_then(|i| stat[i + 1..].split_whitespace().next())
        .is_some_and(|s| s == "T" || s == "t")
}

/// A node that made no progress.
#[derive(Debug, Clone, PartialEq)]
pub struct Stall {
    pub node_id: String,
    pub silent_for: Duration,
    /// Its process is stopped (SIGSTOP), not merely busy or hung.
    pub stopped: bool,
}

impl std::fmt::Display for Stall {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "node '{}' made no progress for {:.0} s{}",
            self.node_id,
            self.silent_for.as_secs_f64(),
            if self.stopped {
                " (its process is stopped: SIGSTOP?)"
            } else {
                " (hung, or one computation longer than [graph] stall_timeout_s)"
            }
        )
    }
}

struct Watched {
    node_id: String,
    pid: u32,
    heartbeat: PathBuf,
}

/// The launcher's side: which node stopped beating.
pub struct StallWatch {
    timeout: Duration,
    since: SystemTime,
    nodes: Vec<Watched>,
}

impl StallWatch {
    pub fn new(timeout: Duration) -> Self {
        Self {
            timeout,
            since: SystemTime::now(),
            nodes: Vec::new(),
        }
    }

    pub fn watch(&mut self, node_id: &str, pid: u32, heartbeat: PathBuf) {
        self.nodes.push(Watched {
            node_id: node_id.to_string(),
            pid,
            heartbeat,
        });
    }

    /// Counting starts now (e.g. when the scan starts).
    pub fn restart(&mut self) {
        self.since = SystemTime::now();
    }

    /// The node (among those `alive` says still run) silent the longest, if longer than
    /// `threshold`.
    pub fn silent_longer_than(
        &self,
        threshold: Duration,
        alive: impl Fn(&str) -> bool,
    ) -> Option<Stall> {
        let now = SystemTime::now();
        self.nodes
            .iter()
            .filter(|n| alive(&n.node_id))
            .filter_map(|n| {
                let last = std::fs::metadata(&n.heartbeat)
                    .and_then(|m| m.modified())
                    .unwrap_or(self.since)
                    .max(self.since);
                let silent = now.duration_since(last).unwrap_or_default();
                let stopped = is_stopped(n.pid);
                (silent > threshold).then(|| Stall {
                    node_id: n.node_id.clone(),
                    silent_for: silent,
                    stopped,
                })
            })
            .max_by(|a, b| {
                // A stopped process is the culprit before a merely silent one.
                (a.stopped, a.silent_for).cmp(&(b.stopped, b.silent_for))
            })
    }

    /// A node silent for longer than the stall deadline.
    pub fn stalled(&self, alive: impl Fn(&str) -> bool) -> Option<Stall> {
        self.silent_longer_than(self.timeout, alive)
    }

    pub fn timeout(&self) -> Duration {
        self.timeout
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_silent_node_is_named_and_a_beating_one_is_not() {
        let dir = tempfile::tempdir().unwrap();
        let quiet = heartbeat_path(dir.path(), "quiet");
        let busy = heartbeat_path(dir.path(), "busy");
        std::fs::create_dir_all(quiet.parent().unwrap()).unwrap();
        let old = SystemTime::now() - Duration::from_secs(30);
        for p in [&quiet, &busy] {
            let f = File::create(p).unwrap();
            f.set_modified(old).unwrap();
        }
        File::options()
            .write(true)
            .open(&busy)
            .unwrap()
            .set_modified(SystemTime::now())
            .unwrap();
        let mut w = StallWatch::new(Duration::from_secs(10));
        w.since = old - Duration::from_secs(1);
        w.watch("busy", std::process::id(), busy);
        w.watch("quiet", std::process::id(), quiet);
        let s = w.stalled(|_| true).expect("quiet is stalled");
        assert_eq!(s.node_id, "quiet");
        assert!(s.silent_for >= Duration::from_secs(29), "{s:?}");
        assert!(!s.stopped, "this test process is running");
        assert!(w.stalled(|id| id != "quiet").is_none());
    }

    #[test]
    fn a_stopped_process_is_seen_as_stopped() {
        let mut child = std::process::Command::new("sleep")
            .arg("30")
            .spawn()
            .unwrap();
        let pid = child.id();
        assert!(!is_stopped(pid));
        // SAFETY: signalling the child this test started.
        unsafe { libc::kill(pid as i32, libc::SIGSTOP) };
        let t0 = Instant::now();
        while !is_stopped(pid) && t0.elapsed() < Duration::from_secs(10) {
            std::thread::sleep(Duration::from_millis(10));
        }
        assert!(is_stopped(pid));
        let _ = child.kill();
        let _ = child.wait();
    }
}
