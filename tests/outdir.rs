//! A run never deletes what it did not create (issue 27): the real binary, the commands of the
//! issue. An out dir that is not a surfstream run, the scan's own folder, the current folder
//! are refused with nothing touched; `--force` replaces a foreign folder only when asked; a run
//! folder is replaced as before.

use std::path::Path;

use surfstream_e2e::{repo_root, run, stderr, surfstream, write_scan_dir};

fn names(dir: &Path) -> Vec<String> {
    let mut v: Vec<_> = std::fs::read_dir(dir)
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().to_string())
        .collect();
    v.sort();
    v
}

fn small_demo(out: &Path, extra: &[&str]) -> std::process::Output {
    let mut cmd = surfstream();
    cmd.arg("run")
        .arg(repo_root().join("launch/graphs/demo.toml"))
        .args(["--set", "stage.pacing=fast", "--set", "stage.tile_px=256"])
        .arg("-o")
        .arg(out)
        .args(extra);
    run(cmd)
}

#[test]
fn a_folder_that_is_not_a_run_is_refused_then_replaced_only_with_force() {
    let dir = tempfile::tempdir().unwrap();
    let v = dir.path().join("V");
    std::fs::create_dir_all(v.join("sub")).unwrap();
    std::fs::write(v.join("thesis.txt"), "years of work").unwrap();
    let out = small_demo(&v, &[]);
    assert!(!out.status.success());
    let err = stderr(&out);
    assert!(
        err.contains("is not a surfstream run") && err.contains("--force"),
        "{err}"
    );
    assert_eq!(names(&v), ["sub", "thesis.txt"]);
    assert_eq!(
        std::fs::read_to_string(v.join("thesis.txt")).unwrap(),
        "years of work"
    );
    assert_eq!(names(dir.path()), ["V"], "staging or lock left beside V");

    // A run folder is ours: a second run replaces it without --force.
    let r = dir.path().join("R");
    assert!(small_demo(&r, &[]).status.success());
    assert!(r.join(".surfstream-run").is_file());
    assert!(small_demo(&r, &[]).status.success());

    // --force is the explicit override.
    let forced = small_demo(&v, &["--force"]);
    assert!(forced.status.success(), "{}", stderr(&forced));
    assert!(!v.join("thesis.txt").exists() && v.join("run.json").is_file());
}

#[test]
fn stitch_into_its_own_scan_folder_or_the_current_folder_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let scan = dir.path().join("D");
    std::fs::create_dir(&scan).unwrap();
    write_scan_dir(&scan, 1, 2, 256, Some("um"));
    let before = names(&scan);
    for (out, cwd) in [
        (scan.as_path(), dir.path()),
        (Path::new("."), scan.as_path()),
    ] {
        let mut cmd = surfstream();
        cmd.current_dir(cwd)
            .arg("stitch")
            .arg(scan.join("scan.toml"))
            .arg("-o")
            .arg(out)
            .arg("--force");
        let o = run(cmd);
        assert!(!o.status.success(), "stitch -o {} accepted", out.display());
        let err = stderr(&o);
        assert!(
            err.contains("the input") || err.contains("refusing to use this folder"),
            "{err}"
        );
        assert_eq!(names(&scan), before, "the scan folder was touched");
    }
    assert_eq!(names(dir.path()), ["D"]);
}

#[test]
fn a_symlinked_out_dir_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let real = dir.path().join("real");
    std::fs::create_dir(&real).unwrap();
    let link = dir.path().join("link");
    std::os::unix::fs::symlink(&real, &link).unwrap();
    let out = small_demo(&link, &[]);
    assert!(!out.status.success());
    assert!(stderr(&out).contains("symbolic link"), "{}", stderr(&out));
    assert!(std::fs::symlink_metadata(&link)
        .unwrap()
        .file_type()
        .is_symlink());
    assert!(names(&real).is_empty());
}

/// A throwaway second user for the hostile-neighbour checks (made with `useradd`, removed
/// again when the test made it); `None` (with the reason printed) unless the test runs as
/// root on a machine with useradd and runuser.
struct Neighbour {
    name: &'static str,
    made: bool,
}

impl Neighbour {
    fn get() -> Option<Self> {
        // SAFETY: geteuid has no preconditions.
        if unsafe { libc::geteuid() } != 0 {
            eprintln!(
                "SKIPPED second-user part: the test does not run as root (cannot create a user)"
            );
            return None;
        }
        let name = "ssneighbour36";
        let exists = std::process::Command::new("id")
            .arg("-u")
            .arg(name)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .status()
            .is_ok_and(|s| s.success());
        let made = !exists
            && std::process::Command::new("useradd")
                .args(["--no-create-home", "--shell", "/usr/sbin/nologin", name])
                .status()
                .is_ok_and(|s| s.success());
        if !exists && !made {
            eprintln!("SKIPPED second-user part: useradd is not available or failed");
            return None;
        }
        Some(Self { name, made })
    }

    /// Runs `sh -c script` as the neighbour.
    fn sh(&self, script: &str) {
        let ok = std::process::Command::new("runuser")
            .args(["-u", self.name, "--", "sh", "-c", script])
            .status()
            .is_ok_and(|s| s.success());
        assert!(ok, "as {}: {script}", self.name);
    }
}

impl Drop for Neighbour {
    fn drop(&mut self) {
        if self.made {
            let _ = std::process::Command::new("userdel")
                .arg(self.name)
                .status();
        }
    }
}

/// The out dir's lock is never followed nor another user's (issue 36): `ln -s precious.txt
/// out.lock; surfstream run G -o out` wrote the pid into precious.txt. Now a link planted as
/// the lock is refused and its target untouched; as root, the same for a link and a lock file
/// a second user planted in a shared sticky folder (the victim's `run` wrote through them).
#[test]
fn a_lock_planted_as_a_link_or_by_another_user_is_refused_and_its_target_untouched() {
    let dir = tempfile::tempdir().unwrap();
    let precious = dir.path().join("precious.txt");
    std::fs::write(&precious, "years of work").unwrap();
    std::os::unix::fs::symlink(&precious, dir.path().join("out.lock")).unwrap();
    let o = small_demo(&dir.path().join("out"), &[]);
    assert!(
        !o.status.success(),
        "a run through a planted lock link succeeded"
    );
    let err = stderr(&o);
    assert!(
        err.contains("out.lock") && err.contains("symbolic link"),
        "{err}"
    );
    assert_eq!(std::fs::read_to_string(&precious).unwrap(), "years of work");
    assert_eq!(names(dir.path()), ["out.lock", "precious.txt"], "{err}");

    let Some(neighbour) = Neighbour::get() else {
        return;
    };
    use std::os::unix::fs::PermissionsExt;
    // A folder every user may write into, like /tmp: the neighbour plants, root runs.
    std::fs::set_permissions(dir.path(), std::fs::Permissions::from_mode(0o755)).unwrap();
    let shared = dir.path().join("shared");
    std::fs::create_dir(&shared).unwrap();
    std::fs::set_permissions(&shared, std::fs::Permissions::from_mode(0o1777)).unwrap();
    let thesis = dir.path().join("thesis.txt");
    std::fs::write(&thesis, "the victim's thesis").unwrap();
    neighbour.sh(&format!(
        "ln -s {} {}/a.lock && echo 4242 > {}/b.lock",
        thesis.display(),
        shared.display(),
        shared.display()
    ));
    for (out, what) in [("a", "symbolic link"), ("b", "not by you")] {
        let o = small_demo(&shared.join(out), &[]);
        assert!(!o.status.success(), "run -o shared/{out} succeeded");
        let err = stderr(&o);
        assert!(
            err.contains(&format!("{out}.lock"))
                && (err.contains(what) || err.contains("Permission denied")),
            "{err}"
        );
    }
    assert_eq!(
        std::fs::read_to_string(&thesis).unwrap(),
        "the victim's thesis"
    );
    assert_eq!(
        std::fs::read_to_string(shared.join("b.lock")).unwrap(),
        "4242\n"
    );
    assert_eq!(names(&shared), ["a.lock", "b.lock"]);
}
