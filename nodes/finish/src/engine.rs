//! Starting LIGGGHTS as a real process (alone, or under `mpirun` for several ranks), following
//! its thermo output for progress, and stopping it on request.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};

/// The command that installs the engine, for the error that says it is missing.
pub const INSTALL_HINT: &str =
    "LIGGGHTS is not installed: install it with `apt-get install liggghts` (and `apt-get install openmpi-bin` for --ranks > 1)";

/// `name` on PATH.
pub fn which(name: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .map(|d| d.join(name))
        .find(|p| p.is_file())
}

/// The engine binary: `$SURFSTREAM_LIGGGHTS` or `liggghts` on PATH.
pub fn find_liggghts() -> Result<PathBuf> {
    if let Some(p) = std::env::var_os("SURFSTREAM_LIGGGHTS") {
        let p = PathBuf::from(p);
        if p.is_file() {
            return Ok(p);
        }
        bail!(
            "SURFSTREAM_LIGGGHTS={}: no such file. {INSTALL_HINT}",
            p.display()
        );
    }
    which("liggghts").ok_or_else(|| anyhow!("{INSTALL_HINT}"))
}

/// How the engine is started.
#[derive(Debug, Clone)]
pub struct EngineCommand {
    pub liggghts: PathBuf,
    /// MPI ranks; 1 starts the binary directly.
    pub ranks: usize,
    /// `mpirun --hostfile FILE` for a cluster.
    pub hostfile: Option<PathBuf>,
}

impl EngineCommand {
    pub fn locate(ranks: usize, hostfile: Option<PathBuf>) -> Result<Self> {
        if ranks == 0 {
            bail!("--ranks 0: expected at least one MPI rank");
        }
        let liggghts = find_liggghts()?;
        if ranks > 1 && which("mpirun").is_none() {
            bail!("--ranks {ranks} needs mpirun: install it with `apt-get install openmpi-bin`");
        }
        Ok(EngineCommand {
            liggghts,
            ranks,
            hostfile,
        })
    }

    /// The command line, as a user would type it in the segment's folder.
    pub fn argv(&self, input: &str, log: &str) -> Vec<String> {
        let mut v = Vec::new();
        if self.ranks > 1 {
            v.push("mpirun".to_string());
            // The CI and containers run as root; Open MPI refuses that without the flag.
            v.push("--allow-run-as-root".to_string());
            if let Some(h) = &self.hostfile {
                v.push("--hostfile".to_string());
                v.push(h.display().to_string());
            }
            v.push("-np".to_string());
            v.push(self.ranks.to_string());
        }
        v.push(self.liggghts.display().to_string());
        v.extend(["-in", input, "-log", log].map(String::from));
        v
    }
}

/// Progress of a running segment, from the script's `print` lines and LIGGGHTS' thermo.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EngineProgress {
    pub pass: usize,
    pub passes: usize,
    /// Steps done of the whole segment.
    pub steps_done: usize,
    pub steps_total: usize,
    pub elapsed_s: f64,
    /// Remaining wall time, extrapolated from the steps done so far.
    pub eta_s: Option<f64>,
}

/// How a segment's engine run ended.
#[derive(Debug, Clone, PartialEq)]
pub struct EngineRun {
    pub wall_s: f64,
    /// CPU time of the engine's processes (user + system, from getrusage of the children).
    pub cpu_s: f64,
    /// Stopped by the caller (Ctrl-C) before the end.
    pub stopped: bool,
    pub command: String,
}

/// How a run is watched: its name in messages and the stall time.
#[derive(Debug, Clone, PartialEq)]
pub struct EngineWatch {
    /// Named in every message about the run ("cycle 3", "the machine run in OUT/macro").
    pub name: String,
    /// No line on the engine's stdout or stderr for this long: the engine is stalled (stopped,
    /// hung, swapping), killed and named, s.
    pub stall_s: f64,
}

/// The default stall time, s: LIGGGHTS prints a thermo line every few hundred steps (a few
/// seconds on a loaded machine), so two minutes of silence is not slowness.
/// `SURFSTREAM_ENGINE_STALL_S` overrides it.
pub const DEFAULT_STALL_S: f64 = 120.0;

impl Default for EngineWatch {
    fn default() -> Self {
        let stall_s = std::env::var("SURFSTREAM_ENGINE_STALL_S")
            .ok()
            .and_then(|v| v.parse::<f64>().ok())
            .filter(|v| v.is_finite() && *v > 0.0)
            .unwrap_or(DEFAULT_STALL_S);
        EngineWatch {
            name: "the engine run".into(),
            stall_s,
        }
    }
}

/// Runs the engine in `dir` on `input`, writing `log`; `steps_per_pass` and `passes` turn the
/// thermo steps into progress, reported through `progress` about every `report_every`. A set
/// `stop` ends the engine (SIGTERM, then SIGKILL) and returns with `stopped`. Watched as
/// [`run_engine_watched`] with the default [`EngineWatch`] named after `dir`.
#[allow(clippy::too_many_arguments)]
pub fn run_engine(
    engine: &EngineCommand,
    dir: &Path,
    input: &str,
    log: &str,
    steps_per_pass: usize,
    passes: usize,
    stop: &AtomicBool,
    progress: &mut dyn FnMut(EngineProgress),
) -> Result<EngineRun> {
    let watch = EngineWatch {
        name: format!("the engine run in {}", dir.display()),
        ..EngineWatch::default()
    };
    run_engine_watched(
        engine,
        dir,
        input,
        log,
        steps_per_pass,
        passes,
        stop,
        &mut |p| progress(p),
        &watch,
    )
}

/// [`run_engine`] under the nodes' discipline: the engine (and mpirun's ranks) in its own
/// process group, killed with this process (PR_SET_PDEATHSIG), the whole group stopped on
/// `stop` ([`stop_group`]), a stall watch (`watch.stall_s` with neither a line of output nor
/// CPU time spent by the group: killed, and the error names `watch.name`), and a failure's
/// error with the exit status and the log's last ERROR line.
#[allow(clippy::too_many_arguments)]
pub fn run_engine_watched(
    engine: &EngineCommand,
    dir: &Path,
    input: &str,
    log: &str,
    steps_per_pass: usize,
    passes: usize,
    stop: &AtomicBool,
    progress: &mut dyn FnMut(EngineProgress),
    watch: &EngineWatch,
) -> Result<EngineRun> {
    let argv = engine.argv(input, log);
    let cpu0 = children_cpu_s();
    let t0 = Instant::now();
    let mut child = spawn_in_own_group(&argv, dir, engine.ranks > 1)?;
    let group = child.id() as i32;
    let stdout = child.stdout.take().ok_or_else(|| anyhow!("no stdout"))?;
    let stderr = child.stderr.take().ok_or_else(|| anyhow!("no stderr"))?;
    // Lines come through a channel so that the stop flag is polled even while the engine is
    // silent.
    let (tx, rx) = std::sync::mpsc::channel::<String>();
    let tx2 = tx.clone();
    std::thread::spawn(move || {
        for l in BufReader::new(stdout).lines().map_while(Result::ok) {
            if tx.send(l).is_err() {
                break;
            }
        }
    });
    let err_lines = std::thread::spawn(move || {
        let mut kept = Vec::new();
        for l in BufReader::new(stderr).lines().map_while(Result::ok) {
            kept.push(l.clone());
            let _ = tx2.send(l);
        }
        kept
    });
    let mut pass = 0usize;
    let mut last_error = None;
    let mut tail: Vec<String> = Vec::new();
    let mut stopped = false;
    let mut stalled = None;
    let mut last_line = Instant::now();
    let mut last_cpu_check = Instant::now();
    let mut group_cpu = 0u64;
    let steps_total = steps_per_pass * passes;
    let status = loop {
        // A launched node's stall watch: the engine is working.
        surfstream_core::liveness::beat();
        if stop.load(Ordering::SeqCst) && !stopped {
            stopped = true;
            stop_group(group, &mut child, engine.ranks > 1)?;
        }
        // Alive: a new line, or CPU time spent by the group (LIGGGHTS' stdout is a pipe, so
        // its lines come in blocks; a stopped or sleeping engine spends none).
        if last_cpu_check.elapsed() >= Duration::from_secs(1) {
            last_cpu_check = Instant::now();
            let cpu = group_cpu_ticks(group);
            if cpu > group_cpu {
                group_cpu = cpu;
                last_line = Instant::now();
            }
        }
        let silent_s = last_line.elapsed().as_secs_f64();
        if stalled.is_none() && !stopped && silent_s > watch.stall_s {
            stalled = Some(silent_s);
            stop_group(group, &mut child, engine.ranks > 1)?;
        }
        match rx.recv_timeout(Duration::from_millis(200)) {
            Ok(line) => {
                last_line = Instant::now();
                if let Some(rest) = line.strip_prefix("surfstream pass ") {
                    if let Some(k) = rest.split_whitespace().next().and_then(|w| w.parse().ok()) {
                        pass = k;
                    }
                } else if line.starts_with("ERROR") {
                    last_error = Some(line.clone());
                } else if let Some(step) = thermo_step(&line) {
                    // Thermo steps count across runs (LIGGGHTS keeps the step counter).
                    let elapsed_s = t0.elapsed().as_secs_f64();
                    let done = step.min(steps_total);
                    let eta_s =
                        (done > 0).then(|| elapsed_s * (steps_total - done) as f64 / done as f64);
                    progress(EngineProgress {
                        pass,
                        passes,
                        steps_done: done,
                        steps_total,
                        elapsed_s,
                        eta_s,
                    });
                }
                tail.push(line);
                if tail.len() > 20 {
                    tail.remove(0);
                }
            }
            Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {
                if let Some(s) = child.try_wait()? {
                    // Drain what is left.
                    while let Ok(l) = rx.try_recv() {
                        if l.starts_with("ERROR") {
                            last_error = Some(l.clone());
                        }
                        tail.push(l);
                    }
                    break s;
                }
            }
            Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => break child.wait()?,
        }
    };
    // Whatever is left of the group (mpirun's ranks) goes with the engine.
    kill_group(group, libc::SIGKILL);
    let _ = err_lines.join();
    let wall_s = t0.elapsed().as_secs_f64();
    let cpu_s = children_cpu_s() - cpu0;
    let command = argv.join(" ");
    let log_path = dir.join(log);
    if let Some(silent_s) = stalled {
        bail!(
            "LIGGGHTS stalled in {}: no output for {silent_s:.0} s (stall time {} s; SURFSTREAM_ENGINE_STALL_S sets it), killed after {wall_s:.0} s{}\n(command: {command})",
            watch.name,
            watch.stall_s,
            log_note(&log_path),
        );
    }
    if stopped || stop.load(Ordering::SeqCst) {
        return Ok(EngineRun {
            wall_s,
            cpu_s,
            stopped: true,
            command,
        });
    }
    let log_error = last_log_error(&log_path);
    if !status.success() || last_error.is_some() {
        let why = log_error.or(last_error).unwrap_or_else(|| {
            let t = tail.len().saturating_sub(6);
            format!("last output:\n{}", tail[t..].join("\n"))
        });
        bail!(
            "LIGGGHTS failed in {} ({status}): {why}{}\n(command: {command}; folder {})",
            watch.name,
            log_note(&log_path),
            dir.display()
        );
    }
    Ok(EngineRun {
        wall_s,
        cpu_s,
        stopped: false,
        command,
    })
}

/// Starts `argv` in `dir` as the leader of a new process group, to die with this process:
/// PR_SET_PDEATHSIG (SIGKILL for the engine itself; SIGTERM for mpirun, which passes it to
/// its ranks before it exits). The death signal follows the thread that started the child,
/// which is this one, and it waits for the child before it returns.
fn spawn_in_own_group(argv: &[String], dir: &Path, mpirun: bool) -> Result<std::process::Child> {
    use std::os::unix::process::CommandExt;
    let death = if mpirun { libc::SIGTERM } else { libc::SIGKILL };
    // SAFETY: the pre_exec closure only makes async-signal-safe system calls.
    let parent = unsafe { libc::getpid() };
    let mut cmd = Command::new(&argv[0]);
    cmd.args(&argv[1..])
        .current_dir(dir)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    unsafe {
        cmd.pre_exec(move || {
            if libc::setpgid(0, 0) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            if libc::prctl(libc::PR_SET_PDEATHSIG, death as libc::c_ulong, 0, 0, 0) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            // The parent died before prctl: nobody would send the signal.
            if libc::getppid() != parent {
                libc::_exit(1);
            }
            Ok(())
        });
    }
    cmd.spawn()
        .with_context(|| format!("cannot start {} in {}", argv.join(" "), dir.display()))
}

/// Signals the process group `group` (ignoring a group already gone).
fn kill_group(group: i32, signal: i32) {
    // SAFETY: signalling the group of the child this module started (its pid is the group id).
    unsafe {
        libc::kill(-group, signal);
    }
}

/// Stops the group: SIGKILL for the engine alone (LIGGGHTS answers SIGTERM by writing a
/// restart file into the folder); for mpirun, SIGTERM (and SIGCONT, for a stopped engine) so
/// that it passes the signal to its ranks, then SIGKILL after 3 s.
fn stop_group(group: i32, child: &mut std::process::Child, mpirun: bool) -> Result<()> {
    if mpirun {
        kill_group(group, libc::SIGTERM);
        kill_group(group, libc::SIGCONT);
        let t = Instant::now();
        while t.elapsed() < Duration::from_secs(3) {
            if child.try_wait()?.is_some() {
                break;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }
    kill_group(group, libc::SIGKILL);
    Ok(())
}

/// User + system CPU ticks of the live processes of group `group` (from /proc).
fn group_cpu_ticks(group: i32) -> u64 {
    let Ok(dir) = std::fs::read_dir("/proc") else {
        return 0;
    };
    let group = group.to_string();
    dir.flatten()
        .filter(|d| {
            d.file_name()
                .to_string_lossy()
                .bytes()
                .all(|b| b.is_ascii_digit())
        })
        .filter_map(|d| std::fs::read_to_string(d.path().join("stat")).ok())
        .filter_map(|stat| {
            // pid (comm) state ppid pgrp session tty tpgid flags minflt cminflt majflt
            // cmajflt utime stime ...
            let rest = stat.rsplit_once(") ")?.1;
            let w: Vec<&str> = rest.split_whitespace().collect();
            if w.get(2) != Some(&group.as_str()) {
                return None;
            }
            Some(w.get(11)?.parse::<u64>().ok()? + w.get(12)?.parse::<u64>().ok()?)
        })
        .sum()
}

/// The last line of the log that starts with ERROR.
fn last_log_error(path: &Path) -> Option<String> {
    let text = std::fs::read(path).ok()?;
    String::from_utf8_lossy(&text)
        .lines()
        .rev()
        .find(|l| l.starts_with("ERROR"))
        .map(str::to_string)
}

/// "; see LOG" when the log exists, "; no log was written (LOG)" when it does not.
fn log_note(path: &Path) -> String {
    if path.is_file() {
        format!("; see {}", path.display())
    } else {
        format!("; no log was written ({} does not exist)", path.display())
    }
}

/// User + system CPU time of the waited-for children of this process, s.
fn children_cpu_s() -> f64 {
    // SAFETY: getrusage fills the struct it is given.
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    if unsafe { libc::getrusage(libc::RUSAGE_CHILDREN, &mut u) } != 0 {
        return 0.0;
    }
    let t = |v: libc::timeval| v.tv_sec as f64 + v.tv_usec as f64 * 1e-6;
    t(u.ru_utime) + t(u.ru_stime)
}

/// The step of a thermo line of `thermo_style custom step atoms ke cpu` (four numbers, the
/// first an integer).
fn thermo_step(line: &str) -> Option<usize> {
    let w: Vec<&str> = line.split_whitespace().collect();
    if w.len() != 4 || w[1..].iter().any(|x| x.parse::<f64>().is_err()) {
        return None;
    }
    w[0].parse().ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn thermo_lines_give_steps_and_mpirun_wraps_the_engine() {
        assert_eq!(
            thermo_step("    1200        1  1.37e-05  0.81 "),
            Some(1200)
        );
        assert_eq!(thermo_step("Step Atoms KinEng CPU"), None);
        assert_eq!(thermo_step("Loop time of 0.8 on 1 procs"), None);
        let e = EngineCommand {
            liggghts: PathBuf::from("/usr/bin/liggghts"),
            ranks: 2,
            hostfile: Some(PathBuf::from("hosts")),
        };
        assert_eq!(
            e.argv("in.x", "log.x").join(" "),
            "mpirun --allow-run-as-root --hostfile hosts -np 2 /usr/bin/liggghts -in in.x -log log.x"
        );
        let one = EngineCommand { ranks: 1, ..e };
        assert_eq!(one.argv("a", "b")[0], "/usr/bin/liggghts");
    }
}
