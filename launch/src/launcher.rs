//! Starting graphs: as supervised processes over iceoryx2 (`launch`) or as threads (`run`).
//!
//! `launch` takes a free domain slot (a fixed set of iceoryx2 prefixes guarded by file locks, so
//! concurrent runs never see each other's services and no prefix files pile up), removes what
//! dead processes of an earlier run of that slot left behind, starts every node with its stderr
//! captured, waits until all report ready, says "go" to the sources, and supervises: a node that
//! exits non-zero or dies stops the graph, is named with the tail of its stderr, and makes the
//! launcher exit non-zero. SIGINT (Ctrl-C), SIGTERM or SIGHUP stops every node, and the error
//! names the signal. Children die with the launcher (PR_SET_PDEATHSIG, and a parent check at
//! every tick), and the slot is cleaned again at the end. A node that makes no progress for
//! `[graph] stall_timeout_s` is named and stops the graph ([`watchdog`]). Both `launch` and
//! `run` write into a staging folder that replaces the out dir only when complete
//! ([`outdir`]: one run per out dir, a `FAILED` record otherwise).

use std::collections::BTreeMap;
use std::fs::File;
use std::os::unix::process::{CommandExt, ExitStatusExt};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};
use crossbeam_channel::{unbounded, Receiver, RecvTimeoutError};
use surfstream_core::fsutil;
use surfstream_runtime::graph::{GraphFile, NodeContext};
use surfstream_runtime::inproc::{self, InProcessNode};
use surfstream_runtime::node::NodeReport;
use surfstream_runtime::watchdog::{self, StallWatch};
use surfstream_runtime::{ipc, shell, slots, stop};

use crate::deviation;
use crate::outputs::RunOutputs;
use crate::{nodes, outdir, runjson};

/// How long stopped nodes get to exit after SIGTERM before SIGKILL.
const STOP_GRACE: Duration = Duration::from_secs(3);
/// A node silent this long when another fails is a suspect (named if stopped, or silent for
/// half the stall deadline).
const STALL_HINT: Duration = Duration::from_secs(2);

mod iceoryx2_free {
    //! Small process helpers that need no iceoryx2.
    pub fn signal(pid: u32, sig: i32) {
        // SAFETY: kill(2) on a pid we started; a stale pid at worst gets ESRCH.
        unsafe {
            libc::kill(pid as libc::pid_t, sig);
        }
    }
}

/// Resolves the graph into the run's staging folder and writes the resolved form there; the
/// out dir itself is not touched until the run is complete (see [`outdir`]).
fn prepare(
    graph: &mut GraphFile,
    staged: &outdir::StagedOut,
) -> Result<(Vec<NodeContext>, RunOutputs)> {
    reserve_failure_room(&staged.staging);
    let outputs = RunOutputs {
        choice: graph.output_choice(),
        carried: staged.carry_inputs(graph)?,
    };
    graph.graph.out_dir = staged.staging.clone();
    let scan_id = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos() as u64)
        .unwrap_or(0);
    let mut contexts = graph.resolve(scan_id, &crate::nodes::registry())?;
    // This process runs every node under `run`, and the Table 6 pass under both.
    let budget = contexts.first().and_then(|c| c.memory.budget_bytes);
    surfstream_runtime::memory::return_freed_buffers(budget);
    crate::progress::attach_observer(&mut contexts);
    crate::live::attach(&mut contexts);
    write_resolved(&staged.staging, &contexts)?;
    Ok((contexts, outputs))
}

fn write_resolved(dir: &Path, contexts: &[NodeContext]) -> Result<()> {
    let resolved = dir.join(shell::RESOLVED_GRAPH);
    fsutil::write_atomic(&resolved, |w| {
        serde_json::to_writer_pretty(w, contexts)
            .map_err(|e| anyhow!("{}: {e}", resolved.display()))
    })
}

/// A file of reserved disk blocks in the staging folder, removed before the `FAILED` record
/// is written (the record's writer removes every output first) or before a complete run is
/// moved into place: on a disk that filled up during the run, the record naming ENOSPC still
/// fits.
const FAILURE_RESERVE: &str = ".failure-reserve";
const FAILURE_RESERVE_BYTES: i64 = 256 * 1024;

fn reserve_failure_room(staging: &Path) {
    if let Ok(f) = File::create(staging.join(FAILURE_RESERVE)) {
        use std::os::fd::AsRawFd;
        // SAFETY: fallocate on a descriptor we own; failure (no room, no support) is ignored.
        unsafe {
            libc::fallocate(f.as_raw_fd(), 0, 0, FAILURE_RESERVE_BYTES);
        }
    }
}

/// How far a run got when it ended: decides what happens to its out dir.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Reached {
    /// Nothing was produced (bad parameters or inputs, a node that could not start).
    Startup,
    /// The scan started: outputs may exist.
    Scan,
}

/// Ends a run's out dir: a complete run replaces the out dir; a run that failed during the scan
/// replaces it by a folder with a `FAILED` record and the logs; a run that failed at startup
/// leaves it as it was.
fn settle(
    staged: outdir::StagedOut,
    contexts: &[NodeContext],
    outcome: Result<()>,
    reached: Reached,
) -> Result<()> {
    match outcome {
        Ok(()) => {
            // The resolved graph names where the nodes wrote; after the move that is the out dir.
            let mut moved = contexts.to_vec();
            for c in &mut moved {
                c.out_dir = staged.final_dir.clone();
            }
            let (staging, final_dir) = (staged.staging.clone(), staged.final_dir.clone());
            let _ = std::fs::remove_file(staging.join(FAILURE_RESERVE));
            let written = write_resolved(&staging, &moved).and_then(|_| staged.commit());
            if let Err(e) = written {
                return Err(e.context(format!(
                    "the run completed but could not be moved into {}; its outputs are in {}",
                    final_dir.display(),
                    staging.display()
                )));
            }
            Ok(())
        }
        Err(e) if reached == Reached::Startup => {
            let out = staged.final_dir.clone();
            // The logs a message names go with the staging folder: say so instead of naming a
            // path that no longer exists (the message carries their last lines).
            let e = anyhow!(
                "{}",
                format!("{e:#}").replace(
                    &staged.staging.display().to_string(),
                    "<the staging folder, removed>"
                )
            );
            staged.discard();
            Err(e.context(format!(
                "the run did not start; {} was left as it was",
                out.display()
            )))
        }
        Err(e) => {
            let staging = staged.staging.clone();
            // The logs a message points at are in the out dir once the failed run is moved.
            let e = anyhow!(
                "{}",
                format!("{e:#}").replace(
                    &staging.display().to_string(),
                    &staged.final_dir.display().to_string()
                )
            );
            match staged.fail(&e) {
                Ok(dir) => Err(e.context(format!(
                    "the run failed; {} holds only its logs and the record {}",
                    dir.display(),
                    dir.join(outdir::FAILED).display()
                ))),
                Err(f) => Err(e.context(format!(
                    "the run failed, and marking it failed failed too ({f:#}); what it left is in {}",
                    staging.display()
                ))),
            }
        }
    }
}

/// `surfstream run`: the graph in this process.
pub fn run_in_process(
    mut graph: GraphFile,
    origin: &Path,
    deviation: deviation::Settings,
    claim: &outdir::Claim,
) -> Result<()> {
    let staged = outdir::stage(&graph.graph.out_dir, claim)?;
    let final_dir = staged.final_dir.clone();
    // Free space before work (issue 36): an estimate of the outputs against what is free.
    let (contexts, outputs) = match crate::outdir_space::check(&graph, &staged.staging)
        .and_then(|()| prepare(&mut graph, &staged))
    {
        Ok(c) => c,
        Err(e) => return settle(staged, &[], Err(e), Reached::Startup),
    };
    let started = Instant::now();
    let progress = crate::progress::Progress::start(&contexts);
    let mut threads = Vec::new();
    for c in &contexts {
        let built = if crate::live::is_observer(&c.node_kind) {
            crate::live::observer(c)
        } else if crate::progress::is_observer(&c.node_kind) {
            Ok(progress.observer())
        } else {
            nodes::build(c)
        };
        match built {
            Ok(logic) => threads.push(InProcessNode {
                context: c.clone(),
                logic,
            }),
            Err(e) => return settle(staged, &contexts, Err(e), Reached::Startup),
        }
    }
    eprintln!(
        "surfstream: running graph '{}' in one process ({} nodes) -> {}",
        graph.graph.name,
        graph.nodes.len(),
        final_dir.display()
    );
    // A signal during startup leaves the out dir as it was; from here on it is a failed run.
    if let Err(e) = stop::check() {
        return settle(staged, &contexts, Err(e), Reached::Startup);
    }
    let supervision = inproc::Supervision {
        stall_timeout: Duration::from_secs_f64(graph.graph.stall_timeout_s),
        grace: STOP_GRACE,
    };
    let outcome = inproc::run_graph_supervised(threads, Some(supervision));
    progress.finish();
    let outcome = outcome.and_then(|mut reports| {
        stop::check()?;
        crate::progress::drop_observer_reports(&mut reports);
        for r in &reports {
            shell::write_report(&graph.graph.out_dir, r)?;
        }
        finish(
            &graph, origin, &reports, "run", started, deviation, &outputs,
        )?;
        stop::check()
    });
    settle(staged, &contexts, outcome, Reached::Scan)
}

/// Writes run.json (and report.html, panorama.x3p), then leaves the output set's files; the
/// verdict (main.rs) reads run.json.
fn finish(
    graph: &GraphFile,
    origin: &Path,
    reports: &[NodeReport],
    mode: &str,
    started: Instant,
    deviation: deviation::Settings,
    outputs: &RunOutputs,
) -> Result<()> {
    let how = runjson::RunEnd {
        mode,
        elapsed: started.elapsed(),
        deviation,
        outputs,
    };
    runjson::write(graph, origin, reports, &how)
}

enum Event {
    Exited {
        id: String,
        status: std::process::ExitStatus,
    },
}

struct Running {
    id: String,
    kind: String,
    pid: u32,
    log: PathBuf,
    exited: bool,
}

fn node_binary(kind: &str) -> Result<PathBuf> {
    let exe = std::env::current_exe().context("cannot locate the surfstream binary")?;
    let dir = exe
        .parent()
        .ok_or_else(|| anyhow!("surfstream binary has no directory"))?;
    let bin = dir.join(format!("surfstream-{kind}"));
    if !bin.exists() {
        bail!(
            "{}: node binary not found (build all binaries: cargo build --release)",
            bin.display()
        );
    }
    Ok(bin)
}

fn stderr_tail(path: &Path, lines: usize) -> String {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    let all: Vec<&str> = text.lines().collect();
    let tail = all[all.len().saturating_sub(lines)..].join("\n    ");
    if tail.is_empty() {
        "(no output on stderr)".into()
    } else {
        format!("\n    {tail}")
    }
}

fn describe_exit(status: &std::process::ExitStatus) -> String {
    match (status.code(), status.signal()) {
        (Some(surfstream_runtime::stdio::EXIT_NO_SPACE), _) => format!(
            "exited with status {}: the disk is full (no space left on device, ENOSPC)",
            surfstream_runtime::stdio::EXIT_NO_SPACE
        ),
        (Some(c), _) => format!("exited with status {c}"),
        (None, Some(s)) => format!("was killed by signal {s}"),
        _ => "ended".into(),
    }
}

/// `surfstream launch`: every node its own process.
pub fn launch(
    mut graph: GraphFile,
    origin: &Path,
    deviation: deviation::Settings,
    claim: &outdir::Claim,
) -> Result<()> {
    // Everything that can be checked without running is checked before anything is written:
    // the graph (validated when loaded), the node binaries, a free slot, the out dir's lock.
    for n in &graph.nodes {
        node_binary(&n.node)?;
    }
    let slot = slots::take()?;
    let staged = outdir::stage(&graph.graph.out_dir, claim)?;
    let final_dir = staged.final_dir.clone();
    // Free space before work (issue 36): an estimate of the outputs against what is free.
    let (contexts, outputs) = match crate::outdir_space::check(&graph, &staged.staging)
        .and_then(|()| prepare(&mut graph, &staged))
    {
        Ok(c) => c,
        Err(e) => return settle(staged, &[], Err(e), Reached::Startup),
    };
    let started = Instant::now();
    let out = graph.graph.out_dir.clone();
    // The progress observer is a launcher thread, not a process (see progress.rs).
    let binaries: Vec<PathBuf> = contexts
        .iter()
        .map(|c| match crate::progress::is_observer(&c.node_kind) {
            true => Ok(PathBuf::new()),
            false => node_binary(&c.node_kind),
        })
        .collect::<Result<_>>()?;
    let cfg = match ipc::domain_config(&slot.prefix).and_then(|cfg| {
        clean_slot(&slot)?;
        // Ours alone, 0600, before iceoryx2 would make it world-writable.
        slots::create_management_segment(&slot.prefix)?;
        Ok(cfg)
    }) {
        Ok(c) => c,
        Err(e) => return settle(staged, &contexts, Err(e), Reached::Startup),
    };
    let mut reached = Reached::Startup;
    let result = (|| {
        stop::check()?;
        let logs = out.join("logs");
        std::fs::create_dir_all(&logs)
            .with_context(|| format!("{}: cannot create", logs.display()))?;
        let launcher = ipc::create_node(&cfg, &format!("{}/launcher", graph.graph.name))?;
        let link = ipc::launcher_link(&graph.graph.name);
        let ready_events = ipc::open_event_service(&launcher, &link.ready_service)?;
        let ready = ready_events
            .listener_builder()
            .create()
            .map_err(|e| anyhow!("cannot create the launcher's ready listener: {e:?}"))?;
        let go_events = ipc::open_event_service(&launcher, &link.go_service)?;
        let go = go_events
            .notifier_builder()
            .create()
            .map_err(|e| anyhow!("cannot create the launcher's go notifier: {e:?}"))?;

        let (tx, rx) = unbounded();
        let resolved = out.join(shell::RESOLVED_GRAPH);
        let mut running = Vec::new();
        let mut spawn_error = None;
        let progress = crate::progress::Progress::start(&contexts);
        let mut observer = None;
        let mut live_observer = None;
        for (c, bin) in contexts.iter().zip(&binaries) {
            if crate::live::is_observer(&c.node_kind) {
                live_observer = Some(crate::live::spawn_ipc_observer(c.clone(), cfg.clone())?);
                continue;
            }
            if crate::progress::is_observer(&c.node_kind) {
                // A launcher thread, not a process (see progress.rs).
                observer = Some(crate::progress::spawn_ipc_observer(
                    c.clone(),
                    &progress,
                    cfg.clone(),
                )?);
                continue;
            }
            let log = logs.join(format!("{}.stderr", c.node_id));
            match spawn(bin, &resolved, c, &slot.prefix, &log) {
                Ok(mut child) => {
                    let pid = child.id();
                    let id = c.node_id.clone();
                    let tx = tx.clone();
                    std::thread::spawn(move || {
                        if let Ok(status) = child.wait() {
                            let _ = tx.send(Event::Exited { id, status });
                        }
                    });
                    running.push(Running {
                        id: c.node_id.clone(),
                        kind: c.node_kind.clone(),
                        pid,
                        log,
                        exited: false,
                    });
                }
                Err(e) => {
                    spawn_error = Some(e.context(format!("cannot start node '{}'", c.node_id)));
                    break;
                }
            }
        }
        eprintln!(
            "surfstream: launched graph '{}' ({} processes, domain {}) -> {}",
            graph.graph.name,
            running.len(),
            slot.prefix,
            final_dir.display()
        );
        let outcome = match spawn_error {
            Some(e) => Err(e),
            None => supervise(
                &graph,
                &contexts,
                &mut running,
                &rx,
                &ready,
                &go,
                &mut reached,
            ),
        };
        if outcome.is_err() {
            stop_all(&mut running, &rx);
            // The observer's upstream is gone: end its event loop too.
            ipc::STOP_REQUESTED.store(true, std::sync::atomic::Ordering::Relaxed);
        }
        if let Some(o) = observer {
            let _ = o.join();
        }
        if let Some(o) = live_observer {
            let _ = o.join();
        }
        progress.finish();
        drop(go);
        drop(ready);
        drop(launcher);
        outcome
    })();
    // Whatever happened, leave the slot clean, and no half-written file behind.
    let cleaned = ipc::cleanup_dead_nodes(&cfg).unwrap_or(0) + ipc::wipe_domain(&cfg);
    if cleaned > 0 {
        eprintln!("surfstream: removed {cleaned} stale resource(s) of stopped nodes");
    }
    slots::remove_management_segment(&slot.prefix);
    slot.release_clean();
    let outcome = result.and_then(|()| {
        stop::check()?;
        let reports = read_reports(&out, &contexts)?;
        finish(
            &graph, origin, &reports, "launch", started, deviation, &outputs,
        )?;
        stop::check()
    });
    settle(staged, &contexts, outcome, reached)
}

/// The slot is ours alone and the processes of its earlier launch died with their launcher:
/// remove what that launch left (node records, services, shared memory, node folders, the
/// management segment), found by the domain it recorded in the slot.
fn clean_slot(slot: &slots::Slot) -> Result<()> {
    let Some(previous) = &slot.previous else {
        return Ok(());
    };
    let cfg = ipc::domain_config(previous)?;
    let stale = ipc::cleanup_dead_nodes(&cfg).unwrap_or(0)
        + ipc::wipe_domain(&cfg)
        + usize::from(slots::remove_management_segment(previous));
    if stale > 0 {
        eprintln!(
            "surfstream: removed {stale} stale resource(s) left in slot {} by an earlier run ({previous})",
            slot.index
        );
    }
    Ok(())
}

/// Disk blocks reserved for each node's stderr log: its last words (the error that ended it)
/// still reach the log when the disk filled up during the run.
const LOG_RESERVE: i64 = 64 * 1024;

/// Reserves `bytes` of blocks for `file` without changing its size (ignored where the file
/// system cannot).
fn reserve(file: &File, bytes: i64) {
    use std::os::fd::AsRawFd;
    // SAFETY: fallocate on a descriptor we own; KEEP_SIZE leaves the visible size alone.
    unsafe {
        libc::fallocate(file.as_raw_fd(), libc::FALLOC_FL_KEEP_SIZE, 0, bytes);
    }
}

fn spawn(
    bin: &Path,
    resolved: &Path,
    c: &NodeContext,
    prefix: &str,
    log: &Path,
) -> Result<std::process::Child> {
    let stderr = File::create(log).with_context(|| format!("{}: cannot create", log.display()))?;
    reserve(&stderr, LOG_RESERVE);
    let mut cmd = Command::new(bin);
    cmd.arg("--graph")
        .arg(resolved)
        .arg("--node")
        .arg(&c.node_id)
        .arg("--domain")
        .arg(prefix)
        .arg("--launched")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(stderr);
    let launcher = std::process::id() as libc::pid_t;
    // SAFETY: only async-signal-safe calls between fork and exec.
    unsafe {
        cmd.pre_exec(move || {
            // Own process group: a terminal's Ctrl-C reaches the launcher, which stops nodes in order.
            libc::setpgid(0, 0);
            // A node never outlives its launcher.
            libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL);
            // The launcher may have died between fork and prctl: then no signal will come.
            if libc::getppid() != launcher {
                libc::_exit(1);
            }
            Ok(())
        });
    }
    cmd.spawn()
        .with_context(|| format!("{}: cannot start", bin.display()))
}

fn supervise(
    graph: &GraphFile,
    contexts: &[NodeContext],
    running: &mut [Running],
    rx: &Receiver<Event>,
    ready: &iceoryx2::port::listener::Listener<iceoryx2::prelude::ipc::Service>,
    go: &iceoryx2::port::notifier::Notifier<iceoryx2::prelude::ipc::Service>,
    reached: &mut Reached,
) -> Result<()> {
    let mut watch = StallWatch::new(Duration::from_secs_f64(graph.graph.stall_timeout_s));
    for (r, c) in running.iter().zip(contexts) {
        watch.watch(
            &r.id,
            r.pid,
            watchdog::heartbeat_path(&c.out_dir, &c.node_id),
        );
    }
    // Readiness: every node attached all its channels. Judged by progress (issue 36): a node
    // becoming ready, or any node beating, is progress; a slow start on a loaded machine is
    // waited for, a stopped node is named by the stall watch.
    let limit = Duration::from_secs_f64(graph.graph.startup_timeout_s + 5.0);
    let mut ready_count = 0u64;
    let mut last_ready = Instant::now();
    while ready_count < contexts.len() as u64 {
        let alive = |id: &str| running.iter().any(|r| r.id == id && !r.exited);
        if watch.all_silent_for(alive).min(last_ready.elapsed()) > limit {
            bail!(
                "only {ready_count} of {} nodes became ready, and no node made progress for {:.0} s ([graph] startup_timeout_s + 5 s)",
                contexts.len(),
                limit.as_secs_f64()
            );
        }
        let before = ready_count;
        ready
            .timed_wait(|e| ready_count += e.count, Duration::from_millis(50))
            .map(|_| ())
            .or_else(ipc::retry_if_interrupted)
            .map_err(|e| anyhow!("ready wait failed: {e:?}"))?;
        if ready_count > before {
            last_ready = Instant::now();
        }
        while let Ok(ev) = rx.try_recv() {
            handle(ev, contexts, running, rx, &watch)?;
        }
        stopping()?;
        check_stalls(&watch, running)?;
    }
    *reached = Reached::Scan;
    go.notify()
        .map_err(|e| anyhow!("cannot tell the sources to start: {e:?}"))?;
    watch.restart();
    eprintln!(
        "surfstream: all {} nodes ready; scan started",
        graph.nodes.len()
    );
    while running.iter().any(|r| !r.exited) {
        match rx.recv_timeout(STOP_POLL) {
            Ok(ev) => handle(ev, contexts, running, rx, &watch)?,
            Err(RecvTimeoutError::Timeout) => {
                stopping()?;
                check_stalls(&watch, running)?
            }
            Err(RecvTimeoutError::Disconnected) => bail!("lost track of the node processes"),
        }
    }
    stopping()
}

/// How often the supervisor looks for a stop signal while waiting for its nodes.
const STOP_POLL: Duration = Duration::from_millis(100);

/// Fails when a stop signal arrived: the graph is stopped and the error names the signal.
fn stopping() -> Result<()> {
    stop::check()
}

/// Fails, naming the node, when a running node made no progress within the stall deadline.
fn check_stalls(watch: &StallWatch, running: &[Running]) -> Result<()> {
    let alive = |id: &str| running.iter().any(|r| r.id == id && !r.exited);
    if let Some(stall) = watch.stalled(alive) {
        bail!(
            "stalled: {stall}; the graph is stopped ([graph] stall_timeout_s = {:.0})",
            watch.timeout().as_secs_f64()
        );
    }
    Ok(())
}

/// A node exit seen by the supervisor: a failure is named through [`blame`].
fn handle(
    ev: Event,
    contexts: &[NodeContext],
    running: &mut [Running],
    rx: &Receiver<Event>,
    watch: &StallWatch,
) -> Result<()> {
    match ev {
        Event::Exited { id, status } => {
            let r = running
                .iter_mut()
                .find(|r| r.id == id)
                .ok_or_else(|| anyhow!("unknown node '{id}' exited"))?;
            r.exited = true;
            if status.success() {
                return Ok(());
            }
            // A sender that gave up on a full queue is not the culprit: the receiver that
            // stopped draining is (it beats no more, or its process is stopped).
            let alive = |n: &str| n != id && running.iter().any(|r| r.id == n && !r.exited);
            let stalled = watch
                .silent_longer_than(STALL_HINT, alive)
                .filter(|s| s.stopped || s.silent_for >= watch.timeout() / 2);
            if let Some(stall) = stalled {
                let r = failure_of(running, &id, status)?;
                bail!(
                    "stalled: {stall}, so node '{}' (surfstream-{}) {} waiting for it; last lines of its stderr ({}):{}",
                    r.id,
                    r.kind,
                    describe_exit(&r.status),
                    r.log.display(),
                    r.tail
                );
            }
            Err(blame(
                failure_of(running, &id, status)?,
                contexts,
                running,
                rx,
            ))
        }
    }
}

/// A node that ended with an error, as the supervisor saw it.
struct Failure {
    id: String,
    kind: String,
    status: std::process::ExitStatus,
    log: PathBuf,
    /// The last lines of its stderr.
    tail: String,
    /// It ended after the supervisor had told every node to stop.
    after_stop: bool,
}

fn failure_of(running: &[Running], id: &str, status: std::process::ExitStatus) -> Result<Failure> {
    let r = running
        .iter()
        .find(|r| r.id == id)
        .ok_or_else(|| anyhow!("unknown node '{id}' exited"))?;
    Ok(Failure {
        id: r.id.clone(),
        kind: r.kind.clone(),
        status,
        log: r.log.clone(),
        tail: stderr_tail(&r.log, 12),
        after_stop: false,
    })
}

/// What a node says when it fails because another node failed first: its upstream is gone,
/// a downstream node left or stopped draining, the graph is being stopped.
const CONSEQUENCES: &[&str] = &[
    "is gone before end of scan",
    "a lossless channel must not drop",
    "send failed (a subscriber",
    "still attached after this node finished",
    "stopped by a termination request",
    "did not appear, and node",
    "subscribers attached, and they made no progress",
    "the launcher did not say 'go'",
];

/// How near a failure is to the cause (issue 36: the record names the first cause, ordered by
/// causality, not by who reported first): 0 an error of the operating system (a full disk,
/// a permission: exit status 74 or an `os error` in the node's last words), 1 a node's own
/// error or a signal the supervisor did not send, 2 a consequence of another node's failure
/// ([`CONSEQUENCES`]), 3 a node that ended after the supervisor stopped the graph.
fn cause_rank(f: &Failure) -> u8 {
    let no_space = f.status.code() == Some(surfstream_runtime::stdio::EXIT_NO_SPACE);
    if no_space || f.tail.contains("(os error ") || f.tail.contains("No space left on device") {
        0
    } else if f.after_stop {
        3
    } else if CONSEQUENCES.iter().any(|c| f.tail.contains(c)) {
        2
    } else {
        1
    }
}

/// How long the supervisor waits, after a failure that is a consequence, for the failure it
/// is a consequence of (a node whose publisher is gone is on its way out).
const CAUSE_WAIT: Duration = Duration::from_secs(10);

/// Names the cause of a failed graph: gathers the exits of the other nodes (waiting, after a
/// consequence, up to [`CAUSE_WAIT`] for a node's own failure), stops the rest, and returns
/// the failure nearest the cause ([`cause_rank`]); among equals the upstream one (the order
/// of the graph, whose wiring has no cycle), then the first seen.
fn blame(
    first: Failure,
    contexts: &[NodeContext],
    running: &mut [Running],
    rx: &Receiver<Event>,
) -> anyhow::Error {
    let mut failures = vec![first];
    let waited = Instant::now();
    while failures.iter().map(cause_rank).min() == Some(2)
        && running.iter().any(|r| !r.exited)
        && waited.elapsed() < CAUSE_WAIT
    {
        if let Ok(Event::Exited { id, status }) = rx.recv_timeout(STOP_POLL) {
            if let Some(r) = running.iter_mut().find(|r| r.id == id) {
                r.exited = true;
            }
            if !status.success() {
                if let Ok(f) = failure_of(running, &id, status) {
                    failures.push(f);
                }
            }
        }
        if stop::signal().is_some() {
            break;
        }
    }
    for (id, status) in stop_all(running, rx) {
        if let Ok(mut f) = failure_of(running, &id, status) {
            f.after_stop = true;
            failures.push(f);
        }
    }
    let depth = upstream_order(contexts);
    let position = |id: &str| depth.get(id).copied().unwrap_or(usize::MAX);
    let (k, _) = failures
        .iter()
        .enumerate()
        .min_by_key(|(k, f)| (cause_rank(f), position(&f.id), *k))
        .unwrap_or((0, &failures[0]));
    let cause = failures.swap_remove(k);
    let mut also: Vec<String> = failures
        .iter()
        .filter(|f| !f.after_stop)
        .map(|f| format!("'{}'", f.id))
        .collect();
    also.dedup();
    anyhow!(
        "node '{}' (surfstream-{}) {}; last lines of its stderr ({}):{}{}",
        cause.id,
        cause.kind,
        describe_exit(&cause.status),
        cause.log.display(),
        cause.tail,
        if also.is_empty() {
            String::new()
        } else {
            format!(
                "\n  (failed after it, as a consequence: {})",
                also.join(", ")
            )
        }
    )
}

/// Each node's distance from the sources (0 for a source, 1 + the deepest producer
/// otherwise): upstream first.
fn upstream_order(contexts: &[NodeContext]) -> BTreeMap<String, usize> {
    let mut depth: BTreeMap<String, usize> = BTreeMap::new();
    // The wiring is acyclic (checked when read), so as many passes as nodes settle it.
    for _ in 0..contexts.len() {
        for c in contexts {
            let d = c
                .inputs
                .iter()
                .map(|i| depth.get(&i.from_node).map_or(0, |d| d + 1))
                .max()
                .unwrap_or(0);
            depth.insert(c.node_id.clone(), d);
        }
    }
    depth
}

/// SIGTERM to every node still running, SIGKILL after a grace period. Returns the nodes that
/// ended with an error meanwhile (those that had already failed on their own among them).
fn stop_all(
    running: &mut [Running],
    rx: &Receiver<Event>,
) -> Vec<(String, std::process::ExitStatus)> {
    let mut failed = Vec::new();
    let mut seen = |running: &mut [Running], ev: Event| {
        let Event::Exited { id, status } = ev;
        if let Some(r) = running.iter_mut().find(|r| r.id == id) {
            r.exited = true;
        }
        if !status.success() {
            failed.push((id, status));
        }
    };
    for r in running.iter().filter(|r| !r.exited) {
        iceoryx2_free::signal(r.pid, libc::SIGTERM);
    }
    let deadline = Instant::now() + STOP_GRACE;
    while running.iter().any(|r| !r.exited) {
        let left = deadline.saturating_duration_since(Instant::now());
        if left.is_zero() {
            break;
        }
        if let Ok(ev) = rx.recv_timeout(left) {
            seen(running, ev);
        }
    }
    for r in running.iter().filter(|r| !r.exited) {
        iceoryx2_free::signal(r.pid, libc::SIGKILL);
    }
    // Reap them: cleanup must not race a process that still holds its node's lock.
    let deadline = Instant::now() + STOP_GRACE;
    while running.iter().any(|r| !r.exited) {
        let left = deadline.saturating_duration_since(Instant::now());
        match rx.recv_timeout(left) {
            Ok(ev) => seen(running, ev),
            Err(_) => break,
        }
    }
    failed
}

fn read_reports(out: &Path, contexts: &[NodeContext]) -> Result<Vec<NodeReport>> {
    let mut reports = BTreeMap::new();
    for c in contexts
        .iter()
        .filter(|c| !crate::progress::is_observer(&c.node_kind))
    {
        let path = shell::report_path(out, &c.node_id);
        let text = std::fs::read_to_string(&path)
            .with_context(|| format!("{}: node '{}' left no report", path.display(), c.node_id))?;
        let r: NodeReport = serde_json::from_str(&text)
            .map_err(|e| anyhow!("{}: malformed node report: {e}", path.display()))?;
        reports.insert(c.node_id.clone(), r);
    }
    Ok(contexts
        .iter()
        .filter_map(|c| reports.remove(&c.node_id))
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn failure(id: &str, code: i32, tail: &str, after_stop: bool) -> Failure {
        Failure {
            id: id.into(),
            kind: id.into(),
            // A wait status: the exit code in the second byte.
            status: std::process::ExitStatus::from_raw(code << 8),
            log: PathBuf::new(),
            tail: tail.into(),
            after_stop,
        }
    }

    /// An OS error beats a node's own error, which beats a consequence, which beats a node the
    /// supervisor stopped (issue 36: a full disk was blamed on "producer ... is gone").
    #[test]
    fn causes_rank_before_their_consequences() {
        let gone = failure(
            "recorder",
            1,
            "input 'registrations': producer matcher/registrations is gone before end of scan",
            false,
        );
        let dropped = failure(
            "stage",
            1,
            "output 'tiles': message 3 reached 2 of 3 subscribers: a lossless channel must not drop",
            false,
        );
        let own = failure("wavelet", 1, "bad level", false);
        let full = failure("fusion", 74, "(no output on stderr)", false);
        let enospc = failure("matcher", 1, "No space left on device (os error 28)", false);
        let stopped = failure("mesher", 1, "bad level", true);
        assert_eq!(cause_rank(&full), 0);
        assert_eq!(cause_rank(&enospc), 0);
        assert_eq!(cause_rank(&own), 1);
        assert_eq!(cause_rank(&gone), 2);
        assert_eq!(cause_rank(&dropped), 2);
        assert_eq!(cause_rank(&stopped), 3);
    }
}
