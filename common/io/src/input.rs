//! Input paths checked before they are opened: a folder, a FIFO or a device given where a file
//! is read would fail with a misleading message ("no such file"), block the reader forever (a
//! FIFO) or never end (`/dev/zero`). Each is named for what it is.

use std::os::unix::fs::FileTypeExt;
use std::path::Path;

use anyhow::{bail, Result};

/// What the file system entry at `path` is, in words, when it is not a regular file
/// (symbolic links followed); `None` for a regular file.
fn not_regular(md: &std::fs::Metadata) -> Option<&'static str> {
    let t = md.file_type();
    if t.is_file() {
        None
    } else if t.is_dir() {
        Some("a folder")
    } else if t.is_fifo() {
        Some("a FIFO (named pipe)")
    } else if t.is_char_device() {
        Some("a character device")
    } else if t.is_block_device() {
        Some("a block device")
    } else if t.is_socket() {
        Some("a socket")
    } else {
        Some("not a file")
    }
}

/// Checks that `path` names an existing regular file (after symbolic links) before it is read.
/// `expected` says what should be there ("a .mcap recording"); the error names the path and what
/// it is instead: `no such file`, or `a folder, not a regular file`.
pub fn check_regular_file(path: &Path, expected: &str) -> Result<()> {
    // The OS error stays in the chain (under the message), so that callers can tell a missing
    // path from a bad file by its kind (Python's PathError).
    match std::fs::metadata(path) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Err(anyhow::Error::new(e).context(
            format!("{}: no such file (expected {expected})", path.display()),
        )),
        Err(e) => bail!("{}: cannot read: {e} (expected {expected})", path.display()),
        Ok(md) => match not_regular(&md) {
            None => Ok(()),
            Some(what) => {
                let msg = format!(
                    "{}: {what}, not a regular file (expected {expected})",
                    path.display()
                );
                if md.is_dir() {
                    Err(
                        anyhow::Error::new(std::io::Error::from(std::io::ErrorKind::IsADirectory))
                            .context(msg),
                    )
                } else {
                    Err(anyhow::anyhow!(msg))
                }
            }
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn folders_fifos_devices_and_missing_files_are_each_named() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("a.mcap");
        std::fs::write(&file, b"x").unwrap();
        assert!(check_regular_file(&file, "a recording").is_ok());
        let fifo = dir.path().join("f.mcap");
        let made = std::process::Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .unwrap();
        assert!(made.success(), "mkfifo {}", fifo.display());
        let link = dir.path().join("link.mcap");
        std::os::unix::fs::symlink(&file, &link).unwrap();
        assert!(
            check_regular_file(&link, "a recording").is_ok(),
            "a link to a file is read"
        );
        for (path, said) in [
            (dir.path().to_path_buf(), "a folder, not a regular file"),
            (fifo, "a FIFO (named pipe), not a regular file"),
            ("/dev/zero".into(), "a character device, not a regular file"),
            (dir.path().join("none.mcap"), "no such file"),
        ] {
            let e = check_regular_file(&path, "a recording")
                .unwrap_err()
                .to_string();
            assert!(
                e.contains(said) && e.contains("expected a recording"),
                "{e}"
            );
            assert!(e.starts_with(&path.display().to_string()), "{e}");
        }
    }
}
