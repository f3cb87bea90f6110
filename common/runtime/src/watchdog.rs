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

use std::collections::BTreeMap;
use std::fs::File;
use std::os::fd::AsRawFd;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicI32, AtomicU64, Ordering};
use std::sync::{Mutex, OnceLock};
use std::time::{Duration, Instant, SystemTime};

use anyhow::{bail, Result};

/// How often a node touches its heartbeat at most.
pub const BEAT_PERIOD: Duration = Duration::from_millis(250);

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
    let mut file = File::create(&path)
        .map_err(|e| anyhow::anyhow!("{}: cannot create the heartbeat: {e}", path.display()))?;
    // Its pid, for the peers that judge their waits by this node's CPU time too (a beat only
    // touches the time stamp, so this is written once, before the first beat).
    let _ = std::io::Write::write_all(&mut file, std::process::id().to_string().as_bytes());
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

/// The last beat of a heartbeat file (its modification time), if it exists.
fn last_beat(heartbeat: &Path) -> Option<SystemTime> {
    std::fs::metadata(heartbeat).and_then(|m| m.modified()).ok()
}

/// The pid a launched node wrote into its heartbeat file ([`install`]).
fn pid_in(heartbeat: &Path) -> Option<u32> {
    std::fs::read_to_string(heartbeat).ok()?.trim().parse().ok()
}

/// The CPU time (user + system, every thread) `pid` has used, from `/proc/<pid>/stat`.
pub fn cpu_time(pid: u32) -> Option<Duration> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // "pid (comm) S ppid ...": utime and stime are fields 14 and 15, the 12th and 13th after
    // the last ')'.
    let rest = &stat[stat.rfind(')')? + 1..];
    let mut fields = rest.split_whitespace().skip(11);
    let ticks: u64 = fields.next()?.parse::<u64>().ok()? + fields.next()?.parse::<u64>().ok()?;
    // SAFETY: sysconf has no preconditions.
    let per_s = unsafe { libc::sysconf(libc::_SC_CLK_TCK) };
    let per_s = u64::try_from(per_s).ok().filter(|&t| t > 0)?;
    Some(Duration::from_nanos(
        ticks.saturating_mul(1_000_000_000) / per_s,
    ))
}

/// One node as a watcher sees it (issue 36: liveness, not wall-clock limits). Progress is a
/// heartbeat or CPU time used: a node computing on a loaded machine gets little CPU per second
/// and beats rarely, but it uses CPU; a stopped node (SIGSTOP) or one blocked in a read uses
/// none. Its silence is the longer of the wall time with neither a beat nor CPU time used, and
/// the CPU time it used since its last beat (a loop that never beats is still found, after
/// that much CPU time).
#[derive(Debug)]
struct Liveness {
    heartbeat: PathBuf,
    /// Its process, when known (the launcher's child, or read from the heartbeat file).
    pid: Option<u32>,
    /// The last beat seen.
    beat: Option<SystemTime>,
    /// The CPU time at the last beat seen (or when first seen).
    cpu_at_beat: Option<Duration>,
    /// The last CPU time seen, and when it last grew.
    cpu: Option<(Duration, SystemTime)>,
}

impl Liveness {
    fn new(heartbeat: PathBuf, pid: Option<u32>) -> Self {
        Self {
            heartbeat,
            pid,
            beat: None,
            cpu_at_beat: None,
            cpu: None,
        }
    }

    /// How long the node has made no progress at `now`, counted from `began` at the most.
    fn silence(&mut self, began: SystemTime, now: SystemTime) -> Silence {
        if self.pid.is_none() {
            self.pid = pid_in(&self.heartbeat);
        }
        let cpu = self.pid.and_then(cpu_time);
        if let Some(b) = last_beat(&self.heartbeat) {
            if self.beat.is_none_or(|seen| b > seen) {
                self.beat = Some(b);
                self.cpu_at_beat = cpu;
            }
        }
        if let Some(c) = cpu {
            match self.cpu {
                // First seen: when it last grew is not known; the wait's start is assumed.
                None => self.cpu = Some((c, began)),
                Some((seen, _)) if c > seen => self.cpu = Some((c, now)),
                Some(_) => {}
            }
            self.cpu_at_beat.get_or_insert(c);
        }
        let last = [self.beat, self.cpu.map(|(_, t)| t)]
            .into_iter()
            .flatten()
            .fold(began, SystemTime::max);
        let idle = now.duration_since(last).unwrap_or_default();
        let busy = cpu
            .zip(self.cpu_at_beat)
            .map(|(c, at)| c.saturating_sub(at))
            .unwrap_or_default();
        Silence { idle, busy }
    }
}

/// A node's silence: wall time without any progress, CPU time used without a beat.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct Silence {
    idle: Duration,
    busy: Duration,
}

impl Silence {
    fn length(&self) -> Duration {
        self.idle.max(self.busy)
    }
}

/// The other nodes of a launched graph, by whose progress a node judges its waits (issue 36):
/// a wait on a peer that keeps beating or computing is a slow peer, never a stuck one. Without
/// a launcher (no heartbeats) a wait is judged by its own length, as before.
#[derive(Debug, Clone, Default)]
pub struct Peers {
    /// Heartbeat file of every other node of the graph, by node id.
    heartbeats: BTreeMap<String, PathBuf>,
    /// Output port of this node -> the nodes wired to it.
    consumers: BTreeMap<String, Vec<String>>,
}

impl Peers {
    /// The peers of `me` in the resolved `graph` (their heartbeats in `me`'s out dir).
    pub fn of(graph: &[crate::graph::NodeContext], me: &crate::graph::NodeContext) -> Self {
        let mut peers = Self::default();
        for c in graph.iter().filter(|c| c.node_id != me.node_id) {
            peers
                .heartbeats
                .insert(c.node_id.clone(), heartbeat_path(&me.out_dir, &c.node_id));
            for i in c.inputs.iter().filter(|i| i.from_node == me.node_id) {
                peers
                    .consumers
                    .entry(i.from_port.clone())
                    .or_default()
                    .push(c.node_id.clone());
            }
        }
        peers
    }

    fn progress_of<'a>(&self, ids: impl IntoIterator<Item = &'a String>) -> Progress {
        Progress::of(
            ids.into_iter()
                .filter_map(|id| self.heartbeats.get(id).cloned())
                .collect(),
        )
    }

    /// The progress of the nodes wired to this node's output `port`.
    pub fn consumers(&self, port: &str) -> Progress {
        self.progress_of(self.consumers.get(port).into_iter().flatten())
    }

    /// The progress of one node (a producer this node waits for).
    pub fn node(&self, id: &str) -> Progress {
        self.progress_of(self.heartbeats.keys().filter(|k| k.as_str() == id))
    }

    /// The progress of every other node of the graph (what the launcher waits for).
    pub fn all(&self) -> Progress {
        self.progress_of(self.heartbeats.keys())
    }
}

/// How long the nodes one wait depends on have made no progress (a beat or CPU time used,
/// [`Liveness`]): the least silent of them, counted from the start of the wait at the most. A
/// node without a heartbeat, or no node at all, counts from the start of the wait. Reads the
/// files at most every [`BEAT_PERIOD`].
#[derive(Debug)]
pub struct Progress {
    nodes: Mutex<Vec<Liveness>>,
    began: SystemTime,
    /// (when last read, the silence then).
    seen: Mutex<Option<(Instant, Duration)>>,
}

impl Progress {
    /// A wait beginning now on the nodes of `heartbeats`.
    pub fn of(heartbeats: Vec<PathBuf>) -> Self {
        Self {
            nodes: Mutex::new(
                heartbeats
                    .into_iter()
                    .map(|h| Liveness::new(h, None))
                    .collect(),
            ),
            began: SystemTime::now(),
            seen: Mutex::new(None),
        }
    }

    /// No peers: the wait is judged by its own length.
    pub fn none() -> Self {
        Self::of(Vec::new())
    }

    /// How long none of the nodes waited on made progress (at most the length of the wait).
    pub fn silent_for(&self) -> Duration {
        let mut seen = self.seen.lock().unwrap_or_else(|p| p.into_inner());
        if let Some((at, silence)) = *seen {
            if at.elapsed() < BEAT_PERIOD {
                return silence + at.elapsed();
            }
        }
        let now = SystemTime::now();
        let mut nodes = self.nodes.lock().unwrap_or_else(|p| p.into_inner());
        let silence = nodes
            .iter_mut()
            .map(|n| n.silence(self.began, now).length())
            .min()
            .unwrap_or_else(|| now.duration_since(self.began).unwrap_or_default());
        *seen = Some((Instant::now(), silence));
        silence
    }

    /// Whether the nodes waited on made no progress for longer than `limit`.
    pub fn silent_longer_than(&self, limit: Duration) -> bool {
        self.silent_for() > limit
    }
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
    /// It used CPU time all along without a beat (a loop, or one long computation).
    pub busy: bool,
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
            } else if self.busy {
                " of CPU time without a heartbeat (a loop that never ends, or one computation longer than [graph] stall_timeout_s)"
            } else {
                " (hung: no heartbeat and no CPU time used, e.g. blocked in a read)"
            }
        )
    }
}

struct Watched {
    node_id: String,
    pid: u32,
    live: Mutex<Liveness>,
}

/// The launcher's side: which node stopped making progress (no heartbeat, no CPU time:
/// [`Liveness`]).
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
            live: Mutex::new(Liveness::new(heartbeat, Some(pid))),
        });
    }

    /// Counting starts now (e.g. when the scan starts).
    pub fn restart(&mut self) {
        self.since = SystemTime::now();
    }

    fn silence_of(&self, n: &Watched, now: SystemTime) -> Silence {
        n.live
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .silence(self.since, now)
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
                let silence = self.silence_of(n, now);
                let stopped = is_stopped(n.pid);
                (silence.length() > threshold).then(|| Stall {
                    node_id: n.node_id.clone(),
                    silent_for: silence.length(),
                    stopped,
                    busy: !stopped && silence.busy > silence.idle,
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

    /// How long no watched node (among those `alive` says still run) made progress: the
    /// progress of the graph as a whole (counted from [`StallWatch::restart`] at most).
    pub fn all_silent_for(&self, alive: impl Fn(&str) -> bool) -> Duration {
        let now = SystemTime::now();
        self.nodes
            .iter()
            .filter(|n| alive(&n.node_id))
            .map(|n| self.silence_of(n, now).length())
            .min()
            .unwrap_or_else(|| now.duration_since(self.since).unwrap_or_default())
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
        // Processes that use no CPU time (this test's own process does).
        let mut sleeping: Vec<_> = (0..2)
            .map(|_| {
                std::process::Command::new("sleep")
                    .arg("30")
                    .spawn()
                    .unwrap()
            })
            .collect();
        w.watch("busy", sleeping[0].id(), busy);
        w.watch("quiet", sleeping[1].id(), quiet);
        let s = w.stalled(|_| true).expect("quiet is stalled");
        assert_eq!(s.node_id, "quiet");
        assert!(s.silent_for >= Duration::from_secs(29), "{s:?}");
        assert!(!s.stopped && !s.busy, "{s:?}");
        assert!(w.stalled(|id| id != "quiet").is_none());
        for c in &mut sleeping {
            let _ = c.kill();
            let _ = c.wait();
        }
    }

    /// A wait on peers is judged by their heartbeats (issue 36): it stays young while a peer
    /// beats, however long it lasts, and ages from the freshest beat once they stop; without
    /// a heartbeat (or peers) it ages from its own start.
    #[test]
    fn a_wait_ages_from_the_last_beat_of_the_nodes_it_waits_on() {
        let dir = tempfile::tempdir().unwrap();
        let (slow, gone) = (
            heartbeat_path(dir.path(), "slow"),
            heartbeat_path(dir.path(), "gone"),
        );
        std::fs::create_dir_all(slow.parent().unwrap()).unwrap();
        let old = SystemTime::now() - Duration::from_secs(100);
        for p in [&slow, &gone] {
            File::create(p).unwrap().set_modified(old).unwrap();
        }
        let mut progress = Progress::of(vec![slow.clone(), gone.clone()]);
        // Began 50 s ago: both peers silent since before, so silent for the wait's length.
        progress.began = SystemTime::now() - Duration::from_secs(50);
        assert!(progress.silent_for() >= Duration::from_secs(49));
        assert!(progress.silent_longer_than(Duration::from_secs(30)));
        // One peer beats: the wait is young again (after the cache period).
        File::options()
            .write(true)
            .open(&slow)
            .unwrap()
            .set_modified(SystemTime::now())
            .unwrap();
        std::thread::sleep(BEAT_PERIOD);
        assert!(
            progress.silent_for() < Duration::from_secs(5),
            "{:?}",
            progress.silent_for()
        );
        // No heartbeat at all: the wait's own length.
        let alone = Progress::of(vec![dir.path().join("logs/missing.alive")]);
        assert!(alone.silent_for() < Duration::from_secs(5));
        assert!(!Progress::none().silent_longer_than(Duration::from_secs(5)));
    }

    /// A peer that computes without beating (a slow node on a loaded machine) uses CPU time:
    /// it makes progress; one that sleeps (or is stopped) does not.
    #[test]
    fn cpu_time_is_progress_and_a_sleeping_process_makes_none() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(dir.path().join("logs")).unwrap();
        let mut spin = std::process::Command::new("sh")
            .args(["-c", "while :; do :; done"])
            .spawn()
            .unwrap();
        let mut sleep = std::process::Command::new("sleep")
            .arg("30")
            .spawn()
            .unwrap();
        let old = SystemTime::now() - Duration::from_secs(100);
        let wait_on = |name: &str, pid: u32| {
            let path = heartbeat_path(dir.path(), name);
            std::fs::write(&path, pid.to_string()).unwrap();
            File::options()
                .write(true)
                .open(&path)
                .unwrap()
                .set_modified(old)
                .unwrap();
            let mut p = Progress::of(vec![path]);
            p.began = SystemTime::now() - Duration::from_secs(50);
            p
        };
        let (busy, idle) = (wait_on("spin", spin.id()), wait_on("sleep", sleep.id()));
        assert!(cpu_time(spin.id()).is_some());
        // CPU time grows in ticks (10 ms): sample until the spinning one has used some.
        let t0 = Instant::now();
        let _ = (busy.silent_for(), idle.silent_for());
        while busy.silent_for() > Duration::from_secs(5) && t0.elapsed() < Duration::from_secs(20) {
            std::thread::sleep(BEAT_PERIOD);
        }
        assert!(
            busy.silent_for() < Duration::from_secs(5),
            "{:?}",
            busy.silent_for()
        );
        assert!(
            idle.silent_for() >= Duration::from_secs(49),
            "{:?}",
            idle.silent_for()
        );
        for c in [&mut spin, &mut sleep] {
            let _ = c.kill();
            let _ = c.wait();
        }
    }

    #[test]
    fn peers_are_the_consumers_of_a_port_and_the_producers_of_the_graph() {
        use crate::graph::{Delivery, InputSpec, NodeContext, PortKind};
        let text = r#"{"graph_name":"g","node_id":"ID","node_kind":"k","params":{},"out_dir":"/o",
            "inputs":[],"outputs":[],"backpressure_timeout_s":1,"startup_timeout_s":1,"scan_id":0,
            "memory":{"budget_bytes":null,"available_bytes":null,"spill_dir":"/o"}}"#;
        let ctx = |id: &str, from: &[(&str, &str)]| -> NodeContext {
            let mut c: NodeContext = serde_json::from_str(&text.replace("ID", id)).unwrap();
            c.inputs = from
                .iter()
                .map(|(n, p)| InputSpec {
                    port: "in".into(),
                    from_node: n.to_string(),
                    from_port: p.to_string(),
                    kind: PortKind::Frames,
                    delivery: Delivery::Lossless,
                    producer_subscribers: 1,
                })
                .collect();
            c
        };
        let graph = vec![
            ctx("stage", &[]),
            ctx("fusion", &[("stage", "tiles")]),
            ctx("mesher", &[("fusion", "panorama")]),
            ctx("wavelet", &[("fusion", "panorama")]),
        ];
        let peers = Peers::of(&graph, &graph[1]);
        let watched = |p: Progress| -> Vec<PathBuf> {
            let nodes = p.nodes.lock().unwrap();
            nodes.iter().map(|n| n.heartbeat.clone()).collect()
        };
        assert_eq!(peers.consumers["panorama"], ["mesher", "wavelet"]);
        assert_eq!(watched(peers.consumers("panorama")).len(), 2);
        assert_eq!(
            watched(peers.node("stage")),
            [heartbeat_path(Path::new("/o"), "stage")]
        );
        assert_eq!(watched(peers.all()).len(), 3, "every node but fusion");
        assert!(watched(peers.consumers("preview")).is_empty());
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
