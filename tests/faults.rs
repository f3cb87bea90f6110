//! Fault injection (issue 15): kill (SIGKILL), stop (SIGSTOP) and starve every node and the
//! launcher at random moments, and after each fault check what must always hold:
//!
//! - the out dir holds exactly one run: the new complete run, a `FAILED` record without any
//!   output, or the previous run untouched; never old and new outputs side by side;
//! - no process of the run is alive one housekeeping tick (+ margin) after its launcher ended;
//! - a stopped node is detected within `[graph] stall_timeout_s`, named, and the graph stops;
//! - the next launch into the same out dir succeeds and leaves its slot's /dev/shm files,
//!   iceoryx2 node records and node folders, staging folders and `.partial` files at zero.
//!
//! "Starving" a node is stopping its producer: the consumer then waits with nothing to read,
//! keeps beating, and the stopped producer is the one named.
//!
//! In the suite: a few runs (`SURFSTREAM_FAULT_RUNS`, default 4, one of each kind). The larger
//! campaign is `scripts/fault_inject.sh [N] [SEED]` (README "Failures and recovery").

use std::path::{Path, PathBuf};
use std::process::{Child, Stdio};
use std::time::{Duration, Instant};

use surfstream_e2e::*;

/// `[graph] stall_timeout_s` of the test graph: short, so a stop is detected quickly.
const STALL_TIMEOUT_S: f64 = 4.0;
/// A node may outlive its launcher by one housekeeping tick (250 ms); the margin is for load.
const ORPHAN_GRACE: Duration = Duration::from_secs(3);
/// No launch of the small test graph may take longer, faults included.
const RUN_LIMIT: Duration = Duration::from_secs(120);

/// (node id, binary) of the demo graph.
const NODES: &[(&str, &str)] = &[
    ("stage", "surfstream-replay"),
    ("matcher", "surfstream-matcher"),
    ("fusion", "surfstream-fusion"),
    ("wavelet", "surfstream-wavelet"),
    ("mesher", "surfstream-mesher"),
    ("recorder", "surfstream-recorder"),
];

#[derive(Clone, Copy, Debug)]
enum Fault {
    KillNode(usize),
    KillLauncher,
    StopNode(usize),
    StopLauncher,
}

impl Fault {
    fn name(&self) -> String {
        match self {
            Fault::KillNode(i) => format!("SIGKILL {}", NODES[*i].0),
            Fault::KillLauncher => "SIGKILL launcher".into(),
            Fault::StopNode(i) => format!("SIGSTOP {}", NODES[*i].0),
            Fault::StopLauncher => "SIGSTOP launcher 2 s".into(),
        }
    }
}

/// xorshift64*: reproducible from the printed seed, no dependency.
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
}

/// The demo graph, small and paced (2 x 2 fields of 256 px, 1 s each), with a short stall
/// deadline.
fn test_graph(dir: &Path) -> PathBuf {
    let demo = std::fs::read_to_string(repo_root().join("launch/graphs/demo.toml")).unwrap();
    let text = demo.replace(
        "[graph]\nname = \"demo\"\n",
        &format!(
            "[graph]\nname = \"demo\"\nstall_timeout_s = {STALL_TIMEOUT_S}\nstartup_timeout_s = 20\nbackpressure_timeout_s = 30\n"
        ),
    );
    assert_ne!(text, demo, "demo.toml's [graph] header changed");
    let path = dir.join("faults.toml");
    std::fs::write(&path, text).unwrap();
    path
}

fn start(graph: &Path, out: &Path, log: &Path, pacing: &str) -> Child {
    surfstream()
        .arg("launch")
        .arg(graph)
        .args([
            "--set",
            "stage.tile_px=256",
            "--set",
            "stage.field_time_s=1.0",
            "--set",
        ])
        .arg(format!("stage.pacing=\"{pacing}\""))
        .arg("--out")
        .arg(out)
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(log).unwrap())
        .spawn()
        .unwrap()
}

/// Live processes whose command line contains `marker` (the out dir's path: node binaries get
/// `--graph OUT.staging-<pid>/graph.resolved.json`).
fn pids_with(marker: &str) -> Vec<(i32, String)> {
    let me = std::process::id() as i32;
    let mut found = Vec::new();
    for e in std::fs::read_dir("/proc").into_iter().flatten().flatten() {
        let Ok(pid) = e.file_name().to_string_lossy().parse::<i32>() else {
            continue;
        };
        if pid == me {
            continue;
        }
        let Ok(cmd) = std::fs::read(e.path().join("cmdline")) else {
            continue;
        };
        let cmd = String::from_utf8_lossy(&cmd).replace('\0', " ");
        if cmd.contains(marker) {
            found.push((pid, cmd));
        }
    }
    found
}

fn signal(pid: i32, sig: i32) -> bool {
    // SAFETY: kill(2) on a process this test started or found by its command line.
    unsafe { libc::kill(pid, sig) == 0 }
}

/// Waits for `child` at most `limit`; kills it (and fails) past that.
fn wait_bounded(child: &mut Child, limit: Duration) -> std::process::ExitStatus {
    let t0 = Instant::now();
    loop {
        if let Some(s) = child.try_wait().unwrap() {
            return s;
        }
        if t0.elapsed() > limit {
            let _ = child.kill();
            panic!("launch did not end within {limit:?}: an unbounded wait");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

const OLD: &str = "output of an earlier run";

/// A complete-looking earlier run in `out`: every output and run.json.
fn plant_old_run(out: &Path) {
    std::fs::create_dir_all(out).unwrap();
    // The marker every run folder carries (an unmarked folder is refused as not ours).
    std::fs::write(out.join(".surfstream-run"), "").unwrap();
    for f in OUTPUTS.iter().chain(&["run.json", "report.html"]) {
        std::fs::write(out.join(f), OLD).unwrap();
    }
}

#[derive(Debug, PartialEq, Eq, Clone, Copy)]
enum OutState {
    New,
    Failed,
    Untouched,
}

/// What the out dir holds; panics on any mix of runs or a half-written folder.
fn out_state(out: &Path) -> OutState {
    let has = |f: &str| out.join(f).exists();
    let old = |f: &str| std::fs::read_to_string(out.join(f)).is_ok_and(|t| t == OLD);
    let outputs: Vec<&str> = OUTPUTS.iter().copied().filter(|f| has(f)).collect();
    let partial = walk(out)
        .iter()
        .any(|p| p.to_string_lossy().ends_with(".partial"));
    assert!(!partial, "{}: a .partial file", out.display());
    if has("FAILED") {
        assert!(
            outputs.is_empty() && !has("run.json"),
            "{}: FAILED beside outputs {outputs:?}",
            out.display()
        );
        return OutState::Failed;
    }
    if OUTPUTS.iter().chain(&["run.json"]).all(|f| old(f)) {
        return OutState::Untouched;
    }
    assert!(
        has("run.json") && outputs.len() == OUTPUTS.len(),
        "{}: neither complete nor FAILED: outputs {outputs:?}, run.json {}",
        out.display(),
        has("run.json")
    );
    for f in OUTPUTS.iter().chain(&["run.json", "report.html"]) {
        assert!(
            !old(f),
            "{}: {f} of the earlier run beside a new run",
            out.display()
        );
    }
    OutState::New
}

fn walk(dir: &Path) -> Vec<PathBuf> {
    let mut all = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).into_iter().flatten().flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p.clone());
            }
            all.push(p);
        }
    }
    all
}

/// Siblings of `out` that a run leaves only while it runs (staging folder, lock).
fn run_leftovers(out: &Path) -> Vec<String> {
    let name = out.file_name().unwrap().to_string_lossy().to_string();
    std::fs::read_dir(out.parent().unwrap())
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().to_string())
        .filter(|n| n.starts_with(&format!("{name}.")))
        .collect()
}

/// Takes the launcher's lock of slot `domain` ("ss{k}_") while looking at it.
fn hold_slot(domain: &str) -> std::fs::File {
    let k = surfstream_runtime::slots::index_of(domain).expect("slot domain ss{k}_{nonce}_");
    surfstream_runtime::slots::hold(k).unwrap()
}

/// The slot of `domain` holds nothing: no shared memory, no node record, no node folder.
fn assert_domain_clean(domain: &str) {
    let _slot = hold_slot(domain);
    assert!(
        shm_leftovers(domain).is_empty(),
        "/dev/shm: {:?}",
        shm_leftovers(domain)
    );
    let cfg = surfstream_runtime::ipc::domain_config(domain).unwrap();
    assert_eq!(surfstream_runtime::ipc::count_nodes(&cfg).unwrap(), 0);
    let dirs = surfstream_runtime::ipc::node_dirs_of_domain(&cfg);
    assert!(dirs.is_empty(), "iceoryx2 node folders left: {dirs:?}");
}

#[derive(Default, Debug)]
struct Tally {
    runs: usize,
    applied: usize,
    missed: usize,
    new: usize,
    failed: usize,
    untouched: usize,
    stalls_named: usize,
    orphan_checks: usize,
    recoveries: usize,
    same_slot_recoveries: usize,
}

fn one_fault(k: usize, fault: Fault, delay: Duration, base: &Path, graph: &Path, t: &mut Tally) {
    let dir = base.join(format!("run{k}"));
    std::fs::create_dir_all(&dir).unwrap();
    let out = dir.join("out");
    plant_old_run(&out);
    let log = dir.join("launcher.stderr");
    let marker = out.to_str().unwrap().to_string();
    let mut child = start(graph, &out, &log, "realtime");
    let launcher = child.id() as i32;
    std::thread::sleep(delay);
    let node_pid = |i: usize| {
        pids_with(&marker)
            .into_iter()
            .find(|(_, c)| c.contains(NODES[i].1))
            .map(|(p, _)| p)
    };
    let applied = match fault {
        Fault::KillNode(i) => node_pid(i).is_some_and(|p| signal(p, libc::SIGKILL)),
        Fault::StopNode(i) => node_pid(i).is_some_and(|p| signal(p, libc::SIGSTOP)),
        Fault::KillLauncher => signal(launcher, libc::SIGKILL),
        Fault::StopLauncher => {
            let ok = signal(launcher, libc::SIGSTOP);
            std::thread::sleep(Duration::from_secs(2));
            signal(launcher, libc::SIGCONT);
            ok
        }
    };
    let status = wait_bounded(&mut child, RUN_LIMIT);
    let err = std::fs::read_to_string(&log).unwrap_or_default();
    assert!(!err.contains("panicked"), "run {k}: {err}");
    // A node that exited just before the signal (a zombie takes it without effect) left its
    // report in a complete run: the fault missed.
    let applied = applied
        && !match fault {
            Fault::KillNode(i) | Fault::StopNode(i) => {
                status.success()
                    && out
                        .join("nodes")
                        .join(format!("{}.json", NODES[i].0))
                        .exists()
            }
            _ => false,
        };
    if applied {
        t.applied += 1;
    } else {
        t.missed += 1;
    }
    // No orphan: every process of the run is gone one tick after the launcher.
    let t0 = Instant::now();
    while !pids_with(&marker).is_empty() {
        assert!(
            t0.elapsed() < ORPHAN_GRACE,
            "run {k} ({}): processes outlived the launcher: {:?}",
            fault.name(),
            pids_with(&marker)
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    t.orphan_checks += 1;
    let state = out_state(&out);
    match state {
        OutState::New => t.new += 1,
        OutState::Failed => t.failed += 1,
        OutState::Untouched => t.untouched += 1,
    }
    eprintln!(
        "run {k}: {} at {:.2} s ({}) -> exit {:?}, out dir {state:?}",
        fault.name(),
        delay.as_secs_f64(),
        if applied {
            "applied"
        } else {
            "missed: process gone or not yet started"
        },
        status.code()
    );
    if applied {
        match fault {
            Fault::KillNode(i) => {
                assert!(
                    !status.success(),
                    "run {k}: a killed node must fail the launch"
                );
                assert!(
                    err.contains(&format!("node '{}'", NODES[i].0)),
                    "run {k}: the killed node is not named: {err}"
                );
            }
            Fault::StopNode(i) => {
                assert!(
                    !status.success(),
                    "run {k}: a stopped node must fail the launch"
                );
                let named = format!("stalled: node '{}' made no progress", NODES[i].0);
                assert!(
                    err.contains(&named),
                    "run {k}: expected {named:?} in: {err}"
                );
                t.stalls_named += 1;
            }
            // Killed mid-run the old run stays; killed while committing, the new one is
            // whole (out_state checked there is no mix either way).
            Fault::KillLauncher | Fault::StopLauncher => {}
        }
        if !status.success() && !matches!(fault, Fault::KillLauncher) {
            // Failed before the scan started: nothing produced, the out dir left as it was.
            let expected = if err.contains("the run did not start") {
                OutState::Untouched
            } else {
                OutState::Failed
            };
            assert_eq!(state, expected, "run {k}: {err}");
        }
    }
    if status.success() {
        assert_eq!(
            state,
            OutState::New,
            "run {k}: exit 0 without a complete run"
        );
    }
    let faulted_domain = domain_of(&err);
    // The next launch into the same out dir cleans up after the fault and completes.
    let log2 = dir.join("recovery.stderr");
    let mut again = start(graph, &out, &log2, "fast");
    let status2 = wait_bounded(&mut again, RUN_LIMIT);
    let err2 = std::fs::read_to_string(&log2).unwrap_or_default();
    assert!(
        status2.success(),
        "run {k}: the launch after the fault failed: {err2}"
    );
    assert_eq!(out_state(&out), OutState::New, "run {k}: recovery");
    assert!(
        run_leftovers(&out).is_empty(),
        "run {k}: left beside the out dir: {:?}",
        run_leftovers(&out)
    );
    let domain = domain_of(&err2).expect("launch names its domain");
    assert_domain_clean(&domain);
    t.recoveries += 1;
    if faulted_domain.as_deref() == Some(domain.as_str()) {
        t.same_slot_recoveries += 1;
    }
    t.runs += 1;
}

/// Runs `n` faults, the kinds in rotation, the node and the moment drawn from `seed`.
fn campaign(n: usize, seed: u64) -> Tally {
    let base = tempfile::tempdir().unwrap();
    let graph = test_graph(base.path());
    let mut rng = Rng(seed.max(1));
    let mut t = Tally::default();
    eprintln!("fault campaign: {n} runs, seed {seed}");
    for k in 0..n {
        let node = rng.below(NODES.len() as u64) as usize;
        let fault = match k % 4 {
            0 => Fault::KillNode(node),
            1 => Fault::StopNode(node),
            2 => Fault::KillLauncher,
            _ => Fault::StopLauncher,
        };
        // From the first process start to about the end of the scan (~3.5 s).
        let delay = Duration::from_millis(200 + rng.below(3000));
        one_fault(k, fault, delay, base.path(), &graph, &mut t);
    }
    eprintln!("fault campaign result: {t:?}");
    t
}

#[test]
fn faults_leave_one_run_no_orphans_and_a_clean_slot() {
    let n = std::env::var("SURFSTREAM_FAULT_RUNS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(4);
    let seed = std::env::var("SURFSTREAM_FAULT_SEED")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| {
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .unwrap()
                .as_nanos() as u64
        });
    let t = campaign(n, seed);
    assert_eq!(t.runs, n);
    assert_eq!(t.recoveries, n);
}

/// A stopped node is named as the stalled one (not the node that sends to it), the launch
/// fails within the deadline, and the out dir says FAILED.
#[test]
fn a_stopped_receiver_is_named_as_stalled() {
    let base = tempfile::tempdir().unwrap();
    let graph = test_graph(base.path());
    let out = base.path().join("out");
    let log = base.path().join("launcher.stderr");
    let marker = out.to_str().unwrap().to_string();
    let mut child = start(&graph, &out, &log, "realtime");
    let t0 = Instant::now();
    while !std::fs::read_to_string(&log)
        .unwrap_or_default()
        .contains("scan started")
    {
        assert!(t0.elapsed() < Duration::from_secs(60), "scan never started");
        std::thread::sleep(Duration::from_millis(20));
    }
    // The matcher receives every tile; the stage keeps sending to it.
    let matcher = pids_with(&marker)
        .into_iter()
        .find(|(_, c)| c.contains("surfstream-matcher"))
        .expect("matcher runs")
        .0;
    assert!(signal(matcher, libc::SIGSTOP));
    let stopped_at = Instant::now();
    let status = wait_bounded(&mut child, RUN_LIMIT);
    let waited = stopped_at.elapsed();
    let err = std::fs::read_to_string(&log).unwrap();
    assert!(!status.success());
    assert!(
        err.contains("stalled: node 'matcher' made no progress")
            && err.contains("its process is stopped"),
        "{err}"
    );
    // Bounded by the deadline (plus the stop grace), not by the 30 s backpressure timeout.
    assert!(
        waited < Duration::from_secs_f64(STALL_TIMEOUT_S + 20.0),
        "detected after {waited:?}"
    );
    let record = std::fs::read_to_string(out.join("FAILED")).unwrap();
    assert!(record.contains("matcher"), "{record}");
    assert!(pids_with(&marker).is_empty(), "{:?}", pids_with(&marker));
}

/// A full disk: the run fails, the FAILED record and the error keep the OS's reason, and no
/// output is left. Needs root to mount a 2 MiB tmpfs; skipped (with the reason) otherwise.
#[test]
fn a_full_disk_fails_the_run_and_keeps_the_os_reason() {
    let base = tempfile::tempdir().unwrap();
    let disk = base.path().join("disk");
    std::fs::create_dir(&disk).unwrap();
    let mounted = std::process::Command::new("mount")
        .args(["-t", "tmpfs", "-o", "size=2m", "tmpfs"])
        .arg(&disk)
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if !mounted {
        eprintln!("SKIPPED: cannot mount a 2 MiB tmpfs (needs root) to fill a disk");
        return;
    }
    struct Unmount(PathBuf);
    impl Drop for Unmount {
        fn drop(&mut self) {
            let _ = std::process::Command::new("umount").arg(&self.0).status();
        }
    }
    let _unmount = Unmount(disk.clone());
    let graph = test_graph(base.path());
    let out = disk.join("out");
    let log = base.path().join("launcher.stderr");
    let mut child = start(&graph, &out, &log, "fast");
    let status = wait_bounded(&mut child, RUN_LIMIT);
    let err = std::fs::read_to_string(&log).unwrap();
    assert!(
        !status.success(),
        "a run on a full disk reported success: {err}"
    );
    assert!(err.contains("No space left on device"), "{err}");
    // Said before the scan (issue 36): the estimate of the outputs against the free space.
    let warned = err
        .find("not enough free space: this run will write about 13.1 MB (262144 measured points x 50 bytes)")
        .unwrap_or_else(|| panic!("no free-space warning: {err}"));
    assert!(
        err.find("tile 0")
            .is_none_or(|first_tile| warned < first_tile),
        "the free-space warning came after the scan started: {err}"
    );
    assert_eq!(out_state(&out), OutState::Failed, "{err}");
    let record = std::fs::read_to_string(out.join("FAILED")).unwrap();
    assert!(record.contains("No space left on device"), "{record}");
    assert!(run_leftovers(&out).is_empty(), "{:?}", run_leftovers(&out));
}

/// Starts `surfstream ARGS` with stderr to `log`, waits until the log shows `when`, sends
/// `signals` (each after `gap`), and returns the exit status and the log.
fn interrupt(
    args: &[&str],
    log: &Path,
    when: &str,
    signals: &[i32],
    gap: Duration,
) -> (std::process::ExitStatus, String) {
    let mut child = surfstream()
        .args(args)
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(log).unwrap())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    while !std::fs::read_to_string(log)
        .unwrap_or_default()
        .contains(when)
    {
        if let Some(s) = child.try_wait().unwrap() {
            panic!(
                "ended ({s:?}) before {when:?}: {}",
                std::fs::read_to_string(log).unwrap_or_default()
            );
        }
        assert!(t0.elapsed() < RUN_LIMIT, "never reached {when:?}");
        std::thread::sleep(Duration::from_millis(20));
    }
    for (k, &sig) in signals.iter().enumerate() {
        assert!(signal(child.id() as i32, sig));
        std::thread::sleep(gap);
        if k + 1 < signals.len() {
            // Two signals sent before the first is handled merge into one (a pending signal
            // is a bit, not a queue): the next goes only once the first is seen handled.
            let t1 = Instant::now();
            while !std::fs::read_to_string(log)
                .unwrap_or_default()
                .contains("stopping the run")
                && t1.elapsed() < Duration::from_secs(10)
            {
                std::thread::sleep(Duration::from_millis(2));
            }
        }
    }
    let status = wait_bounded(&mut child, RUN_LIMIT);
    (status, std::fs::read_to_string(log).unwrap_or_default())
}

/// What every interrupted run must leave: exit 1, the signal named in the error and in the
/// FAILED record, no staging folder, no lock, no process of the run.
fn assert_interrupted(out: &Path, status: std::process::ExitStatus, err: &str, name: &str) {
    assert_eq!(status.code(), Some(1), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    assert!(err.contains(&format!("interrupted by {name}")), "{err}");
    assert_eq!(out_state(out), OutState::Failed, "{err}");
    let record = std::fs::read_to_string(out.join("FAILED")).unwrap();
    assert!(
        record.contains(name),
        "the FAILED record names no signal: {record}"
    );
    assert!(run_leftovers(out).is_empty(), "{:?}", run_leftovers(out));
    let marker = out.to_str().unwrap();
    let t0 = Instant::now();
    while !pids_with(marker).is_empty() {
        assert!(t0.elapsed() < ORPHAN_GRACE, "{:?}", pids_with(marker));
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Ctrl-C to `run` mid-scan (issue 27): the nodes stop, FAILED names SIGINT, staging and lock
/// are gone. Before, the process died at once and left OUT.staging-PID and OUT.lock.
#[test]
fn sigint_to_run_mid_scan_leaves_failed_and_no_staging() {
    let base = tempfile::tempdir().unwrap();
    let graph = test_graph(base.path());
    let out = base.path().join("out");
    let (status, err) = interrupt(
        &[
            "run",
            graph.to_str().unwrap(),
            "--set",
            "stage.tile_px=256",
            "--set",
            "stage.field_time_s=1.0",
            "--set",
            "stage.pacing=\"realtime\"",
            "-o",
            out.to_str().unwrap(),
        ],
        &base.path().join("run.stderr"),
        "(1 done)",
        &[libc::SIGINT],
        Duration::ZERO,
    );
    assert_interrupted(&out, status, &err, "SIGINT");
}

/// SIGTERM to `stitch` mid-scan: the same story as `run`.
#[test]
fn sigterm_to_stitch_mid_scan_leaves_failed_and_no_staging() {
    let base = tempfile::tempdir().unwrap();
    let scan = base.path().join("scan");
    std::fs::create_dir(&scan).unwrap();
    write_scan_dir(&scan, 2, 2, 256, Some("um"));
    let out = base.path().join("out");
    let (status, err) = interrupt(
        &[
            "stitch",
            scan.to_str().unwrap(),
            "--set",
            "stage.pacing=\"realtime\"",
            "--set",
            "stage.field_time_s=1.0",
            "-o",
            out.to_str().unwrap(),
        ],
        &base.path().join("stitch.stderr"),
        "(1 done)",
        &[libc::SIGTERM],
        Duration::ZERO,
    );
    assert_interrupted(&out, status, &err, "SIGTERM");
    // The input was not touched.
    assert!(scan.join("scan.toml").is_file() && scan.join("tile_000.npy").is_file());
}

/// SIGHUP (the terminal closed) to `launch` mid-scan: every node stopped, FAILED names it.
#[test]
fn sighup_to_launch_mid_scan_leaves_failed_and_no_staging() {
    let base = tempfile::tempdir().unwrap();
    let graph = test_graph(base.path());
    let out = base.path().join("out");
    let (status, err) = interrupt(
        &[
            "launch",
            graph.to_str().unwrap(),
            "--set",
            "stage.tile_px=256",
            "--set",
            "stage.field_time_s=1.0",
            "--set",
            "stage.pacing=\"realtime\"",
            "-o",
            out.to_str().unwrap(),
        ],
        &base.path().join("launch.stderr"),
        "(1 done)",
        &[libc::SIGHUP],
        Duration::ZERO,
    );
    assert_interrupted(&out, status, &err, "SIGHUP");
    if let Some(domain) = domain_of(&err) {
        assert_domain_clean(&domain);
    }
}

/// A second Ctrl-C forces: the process exits at once with 128 + SIGINT, saying so.
#[test]
fn a_second_ctrl_c_forces_an_exit() {
    let base = tempfile::tempdir().unwrap();
    let graph = test_graph(base.path());
    let out = base.path().join("out");
    let (status, err) = interrupt(
        &[
            "run",
            graph.to_str().unwrap(),
            "--set",
            "stage.tile_px=256",
            "--set",
            "stage.field_time_s=1.0",
            "--set",
            "stage.pacing=\"realtime\"",
            "-o",
            out.to_str().unwrap(),
        ],
        &base.path().join("run.stderr"),
        "(1 done)",
        &[libc::SIGINT, libc::SIGINT],
        Duration::from_millis(1),
    );
    // The first signal's stop takes at least one watch tick (250 ms); the second comes 1 ms on.
    assert_eq!(status.code(), Some(130), "{err}");
    assert!(err.contains("second stop signal"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
}

/// Hostile neighbours (issue 27): in a private runtime folder, slot 0's lock file is a planted
/// symlink and slot 1's belongs to another user. The launch refuses both (naming them), never
/// creates the link's target, takes slot 2, and leaves no management segment behind. A slot
/// folder owned by another user is refused outright, naming its owner.
#[test]
fn planted_and_foreign_slot_files_are_refused_not_followed() {
    use std::os::unix::fs::PermissionsExt;
    let base = tempfile::tempdir().unwrap();
    let runtime = base.path().join("runtime");
    std::fs::create_dir(&runtime).unwrap();
    std::fs::set_permissions(&runtime, std::fs::Permissions::from_mode(0o700)).unwrap();
    let slots = runtime.join("surfstream");
    std::fs::create_dir(&slots).unwrap();
    std::fs::set_permissions(&slots, std::fs::Permissions::from_mode(0o700)).unwrap();
    let victim = base.path().join("victim");
    std::os::unix::fs::symlink(&victim, slots.join("slot-0.lock")).unwrap();
    // SAFETY: geteuid has no preconditions.
    let root = unsafe { libc::geteuid() } == 0;
    if root {
        let foreign = slots.join("slot-1.lock");
        std::fs::write(&foreign, "").unwrap();
        std::os::unix::fs::chown(&foreign, Some(65534), Some(65534)).unwrap();
    }
    let graph = test_graph(base.path());
    let out = base.path().join("out");
    let launch = |out: &Path| {
        surfstream()
            .env("XDG_RUNTIME_DIR", &runtime)
            .args(["launch", graph.to_str().unwrap()])
            .args([
                "--set",
                "stage.tile_px=256",
                "--set",
                "stage.pacing=\"fast\"",
                "-o",
            ])
            .arg(out)
            .output()
            .unwrap()
    };
    let o = launch(&out);
    let err = stderr(&o);
    assert!(o.status.success(), "{err}");
    assert!(
        err.contains("slot-0.lock") && err.contains("symlink"),
        "{err}"
    );
    assert!(!victim.exists(), "the planted link was followed");
    let domain = domain_of(&err).unwrap();
    if root {
        assert!(
            err.contains("slot-1.lock") && err.contains("not a regular file of yours"),
            "{err}"
        );
        assert!(domain.starts_with("ss2_"), "{domain}");
    } else {
        assert!(domain.starts_with("ss1_"), "{domain}");
    }
    assert!(
        shm_leftovers(&domain).is_empty(),
        "{:?}",
        shm_leftovers(&domain)
    );
    assert!(
        slots.join("iceoryx2").is_dir(),
        "the iceoryx2 records are in the user's folder"
    );
    if root {
        // The whole slot folder planted by another user: refused, nothing started.
        std::os::unix::fs::chown(&slots, Some(65534), Some(65534)).unwrap();
        let o = launch(&base.path().join("out2"));
        let err = stderr(&o);
        assert_eq!(o.status.code(), Some(1), "{err}");
        assert!(err.contains("owned by uid 65534, not by you"), "{err}");
    }
}
