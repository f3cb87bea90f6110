//! One signal story for `launch`, `run` and `stitch` (issue 27): SIGINT (Ctrl-C), SIGTERM or
//! SIGHUP at any phase asks the run to stop; the verb notices at its next step, stops its
//! nodes, and ends through its normal failure path (the error and the out dir's `FAILED`
//! record name the signal; staging folder and lock are removed). A second stop signal forces:
//! the process exits at once with status 128 + signal.
//!
//! The handler stays installed for the life of the process, so no phase (startup, the scan,
//! the writing of run.json after the nodes finished) ignores a signal.

use std::sync::atomic::{AtomicI32, AtomicU32, Ordering};

use anyhow::{anyhow, Result};

static SIGNAL: AtomicI32 = AtomicI32::new(0);
static COUNT: AtomicU32 = AtomicU32::new(0);

extern "C" fn on_signal(sig: libc::c_int) {
    // Only async-signal-safe calls here: atomics, write(2), _exit(2).
    if COUNT.fetch_add(1, Ordering::SeqCst) == 0 {
        SIGNAL.store(sig, Ordering::SeqCst);
        crate::ipc::STOP_REQUESTED.store(true, Ordering::SeqCst);
        let msg: &[u8] = match sig {
            libc::SIGINT => {
                b"\nsurfstream: SIGINT (Ctrl-C): stopping the run (Ctrl-C again to force)\n"
            }
            libc::SIGTERM => b"\nsurfstream: SIGTERM: stopping the run (again to force)\n",
            _ => b"\nsurfstream: SIGHUP: stopping the run\n",
        };
        // SAFETY: write(2) on fd 2; a failed write (closed or full stderr) is ignored.
        unsafe {
            libc::write(2, msg.as_ptr().cast(), msg.len());
        }
    } else {
        let msg = b"surfstream: second stop signal: exiting now (the staging folder may remain; the next run removes it)\n";
        // SAFETY: write(2) and _exit(2) are async-signal-safe.
        unsafe {
            libc::write(2, msg.as_ptr().cast(), msg.len());
            libc::_exit(128 + sig);
        }
    }
}

/// Installs the handlers of SIGINT, SIGTERM and SIGHUP for the rest of the process.
pub fn install() -> Result<()> {
    for sig in [libc::SIGINT, libc::SIGTERM, libc::SIGHUP] {
        // SAFETY: a plain sigaction with a handler that only touches atomics and calls
        // async-signal-safe functions.
        let rc = unsafe {
            let mut action: libc::sigaction = std::mem::zeroed();
            action.sa_sigaction = on_signal as extern "C" fn(libc::c_int) as usize;
            action.sa_flags = libc::SA_RESTART;
            libc::sigemptyset(&mut action.sa_mask);
            libc::sigaction(sig, &action, std::ptr::null_mut())
        };
        if rc != 0 {
            return Err(anyhow!(
                "cannot install the handler of signal {sig}: {}",
                std::io::Error::last_os_error()
            ));
        }
    }
    Ok(())
}

/// The stop signal received, if any.
pub fn signal() -> Option<i32> {
    match SIGNAL.load(Ordering::SeqCst) {
        0 => None,
        s => Some(s),
    }
}

/// How a stop signal is named in errors and `FAILED` records.
pub fn signal_name(sig: i32) -> &'static str {
    match sig {
        libc::SIGINT => "SIGINT (Ctrl-C)",
        libc::SIGTERM => "SIGTERM",
        libc::SIGHUP => "SIGHUP (the terminal closed)",
        _ => "a stop signal",
    }
}

/// The error of a run stopped by `sig`.
pub fn interrupted(sig: i32) -> anyhow::Error {
    anyhow!(
        "interrupted by {} (signal {sig}): the run was stopped",
        signal_name(sig)
    )
}

/// Fails with [`interrupted`] when a stop signal arrived: called between the phases of a run.
pub fn check() -> Result<()> {
    match signal() {
        Some(sig) => Err(interrupted(sig)),
        None => Ok(()),
    }
}
