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
