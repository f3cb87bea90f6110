//! What the io integration tests share: the repository root, the real specimens in
//! tests/data/specimens (SURFSTREAM_SPECIMENS looked in first), and the test environment's
//! Python (scripts/test.sh makes it).

#![allow(dead_code)] // each test file uses its own part

use std::path::{Path, PathBuf};

pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .ancestors()
        .nth(2)
        .expect("common/io lies two levels below the repository root")
        .to_path_buf()
}

/// A real instrument file: the folder SURFSTREAM_SPECIMENS names when it holds `name`, else the
/// repository's own copy in tests/data/specimens (its README gives each file's source and
/// licence).
pub fn specimen(name: &str) -> PathBuf {
    optional_specimen(name).unwrap_or_else(|| {
        panic!(
            "specimen {name} missing: neither in tests/data/specimens nor in $SURFSTREAM_SPECIMENS"
        )
    })
}

/// A specimen that is not in the repository (its licence does not fit: see
/// tests/data/specimens/README.md): Some only when SURFSTREAM_SPECIMENS holds it; a test that
/// needs it says "skipped" when it is None.
pub fn optional_specimen(name: &str) -> Option<PathBuf> {
    std::env::var_os("SURFSTREAM_SPECIMENS")
        .map(|d| PathBuf::from(d).join(name))
        .into_iter()
        .chain([repo_root().join("tests/data/specimens").join(name)])
        .find(|p| p.is_file())
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
