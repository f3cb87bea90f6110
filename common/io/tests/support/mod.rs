//! What the io integration tests share: the repository root, the real specimens in
//! ../shared/specimens, and the test environment's Python (scripts/test.sh makes it).

#![allow(dead_code)] // each test file uses its own part

use std::path::{Path, PathBuf};

pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .ancestors()
        .nth(2)
        .expect("common/io lies two levels below the repository root")
        .to_path_buf()
}

pub fn specimen(name: &str) -> PathBuf {
    let dir = std::env::var_os("SURFSTREAM_SPECIMENS")
        .map(PathBuf::from)
        .unwrap_or_else(|| repo_root().join("../shared/specimens"));
    let p = dir.join(name);
    assert!(
        p.exists(),
        "specimen {} missing: the golden tests need ../shared/specimens",
        p.display()
    );
    p
}

/// The test venv's Python (scripts/test.sh makes it); fails loudly when missing.
pub fn python() -> PathBuf {
    if let Some(p) = std::env::var_os("SURFSTREAM_PYTHON") {
        return PathBuf::from(p);
    }
    let venv = repo_root().join(".test-venv/bin/python");
    assert!(
        venv.exists(),
        "no Python test environment: run scripts/test.sh (it creates .test-venv with h5py and surfalize)"
    );
    venv
}
