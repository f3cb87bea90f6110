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

/// The readable extensions as every message lists them: ".npy, .datx, ...".
pub fn readable_list() -> String {
    crate::formats::EXTENSIONS
        .iter()
        .map(|e| format!(".{e}"))
        .collect::<Vec<_>>()
        .join(", ")
}

/// Refuses a folder given where `taker` (a verb, Python's `read`) reads one height-map file:
/// "DIR: is a folder; inspect takes one height-map file (.npy, ...)", with `stitch` named when
/// it holds a scan.toml, instead of the extension's "unsupported format '.'". The CLI's verbs,
/// [`crate::formats::read_surface`] and Python say it with this one message. The error is an
/// `IsADirectory` I/O error (Python's PathError).
pub fn not_a_folder(path: &Path, taker: &str) -> Result<()> {
    if !path.is_dir() {
        return Ok(());
    }
    let hint = if path.join("scan.toml").is_file() {
        format!(
            " (it holds a scan: stitch it with `surfstream stitch {} -o OUT`)",
            path.display()
        )
    } else {
        String::new()
    };
    // An I/O error of kind IsADirectory that is the message itself (no ": is a directory"
    // appended by `{:#}`).
    let msg = format!(
        "{}: is a folder; {taker} takes one height-map file ({}){hint}",
        path.display(),
        readable_list()
    );
    Err(std::io::Error::new(std::io::ErrorKind::IsADirectory, msg).into())
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

    #[test]
    fn a_folder_is_named_with_what_reads_one_file() {
        let dir = tempfile::tempdir().unwrap();
        let e = not_a_folder(dir.path(), "read").unwrap_err();
        let text = format!("{e:#}");
        assert!(
            text.starts_with(&format!(
                "{}: is a folder; read takes one height-map file (.npy, .datx",
                dir.path().display()
            )) && text.ends_with(".tiff)"),
            "{text}"
        );
        let io = e.chain().find_map(|c| c.downcast_ref::<std::io::Error>());
        assert_eq!(
            io.map(std::io::Error::kind),
            Some(std::io::ErrorKind::IsADirectory)
        );
        std::fs::write(dir.path().join("scan.toml"), "").unwrap();
        let text = not_a_folder(dir.path(), "read").unwrap_err().to_string();
        assert!(text.contains("stitch it with `surfstream stitch"), "{text}");
        let file = dir.path().join("scan.toml");
        assert!(not_a_folder(&file, "read").is_ok());
        assert!(not_a_folder(&dir.path().join("none.x3p"), "read").is_ok());
    }
}
