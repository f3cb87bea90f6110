//! Standard streams that cannot be written (issue 27): `surfstream ... 2> /dev/full`, a
//! stdout on a full disk, a node's stderr log when the disk filled up. Rust's `eprintln!`
//! panics when a write fails (exit 101, and the cause lost); these helpers make such runs end
//! cleanly and keep the cause where it can still be told.

use std::os::fd::AsRawFd;

/// Exit status of a node (or the CLI) that failed because the disk is full (ENOSPC): the
/// launcher names the cause from the status even when nothing could be written to the log
/// (EX_CANTCREAT of sysexits.h is 73; this one is not used by anything else here).
pub const EXIT_NO_SPACE: i32 = 74;

/// Whether `fd` is `/dev/full`, or a file on a file system with no free block: a write to it
/// fails.
fn unwritable(fd: i32) -> bool {
    // SAFETY: fstat/fstatvfs on a descriptor number, into zeroed structs we own.
    unsafe {
        let mut st: libc::stat = std::mem::zeroed();
        if libc::fstat(fd, &mut st) != 0 {
            return false;
        }
        match st.st_mode & libc::S_IFMT {
            libc::S_IFCHR => st.st_rdev == libc::makedev(1, 7),
            libc::S_IFREG => {
                let mut vfs: libc::statvfs = std::mem::zeroed();
                libc::fstatvfs(fd, &mut vfs) == 0 && vfs.f_bavail == 0 && vfs.f_blocks > 0
            }
            _ => false,
        }
    }
}

/// Points stderr at `/dev/null` when it cannot be written (`/dev/full`, a full disk):
/// messages are lost either way, and a lost message must not become a panic.
pub fn discard_unwritable_stderr() {
    if !unwritable(2) {
        return;
    }
    if let Ok(null) = std::fs::OpenOptions::new().write(true).open("/dev/null") {
        // SAFETY: dup2 onto fd 2 from a descriptor we own.
        unsafe {
            libc::dup2(null.as_raw_fd(), 2);
        }
    }
}

/// Whether an error's chain holds "no space left on device".
pub fn is_no_space(e: &anyhow::Error) -> bool {
    e.chain().any(|c| {
        c.downcast_ref::<std::io::Error>()
            .is_some_and(|io| io.raw_os_error() == Some(libc::ENOSPC))
            || c.to_string().contains("os error 28")
    })
}

/// A panic whose message says the disk is full (a failed `eprintln!` to a log on a full disk)
/// or that a standard stream could not be written ends the process with a status that names
/// the cause ([`EXIT_NO_SPACE`], or 1), instead of 101 and no message.
pub fn exit_cleanly_on_stream_panics() {
    let default = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        let msg = info
            .payload()
            .downcast_ref::<String>()
            .map(String::as_str)
            .or_else(|| info.payload().downcast_ref::<&str>().copied())
            .unwrap_or("");
        if msg.starts_with("failed printing to stdout") {
            use std::io::Write;
            let _ = writeln!(
                std::io::stderr(),
                "surfstream: error: cannot write to stdout: {}",
                msg.trim_start_matches("failed printing to stdout: ")
            );
            std::process::exit(1);
        }
        if msg.starts_with("failed printing to stderr") {
            std::process::exit(1);
        }
        // Any other write that failed for a full disk, in a thread that panicked on it.
        if msg.contains("os error 28") {
            std::process::exit(EXIT_NO_SPACE);
        }
        default(info);
    }));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dev_full_is_unwritable_and_a_normal_file_is_not() {
        let full = std::fs::OpenOptions::new()
            .write(true)
            .open("/dev/full")
            .unwrap();
        assert!(unwritable(full.as_raw_fd()));
        let tmp = tempfile::tempfile().unwrap();
        assert!(!unwritable(tmp.as_raw_fd()));
        let null = std::fs::OpenOptions::new()
            .write(true)
            .open("/dev/null")
            .unwrap();
        assert!(!unwritable(null.as_raw_fd()));
    }

    #[test]
    fn no_space_is_found_in_a_chain() {
        let io = std::io::Error::from_raw_os_error(libc::ENOSPC);
        let e = anyhow::Error::new(io).context("x.npy: write failed");
        assert!(is_no_space(&e));
        assert!(!is_no_space(&anyhow::anyhow!("other")));
    }
}
