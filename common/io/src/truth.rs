//! The true tile positions of a scan, read from a `ground_truth.json`: the file
//! `bench/make_tiles.py` writes beside a scan's `scan.toml`, and the layout the simulated stage
//! writes as `truth.json` beside a graph's outputs (`surfstream-replay`'s `GroundTruth`, whose
//! output this reader is tested on). The one reader of that file: the matcher scores feature
//! matches with it, the benchmarks and tests score registrations.
//!
//! The file is read as `surfstream_core::record::TruthRecord` (the writer's tile record);
//! only `tiles[].index` and `tiles[].true_origin_px` (`[x, y]`, px) are used; a pair's true
//! offset is `true_origin_px[b] - true_origin_px[a]`, the same definition as the file's
//! `pairs[].true_offset_px`, for any two tiles.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Why a truth file was refused; every variant names the file.
#[derive(Debug)]
pub enum TruthError {
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    Json {
        path: PathBuf,
        source: serde_path_to_error::Error<serde_json::Error>,
    },
    Field {
        path: PathBuf,
        field: String,
        expected: &'static str,
    },
    Duplicate {
        path: PathBuf,
        at: usize,
        index: u64,
    },
}

impl std::fmt::Display for TruthError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            TruthError::Read { path, source } => {
                write!(f, "{}: cannot read: {source}", path.display())
            }
            TruthError::Json { path, source } if source.inner().is_syntax() || source.inner().is_eof() => {
                write!(f, "{}: not JSON: {}", path.display(), source.inner())
            }
            TruthError::Json { path, source } => write!(
                f,
                "{}: not a truth file (tiles[] with index, row, col, true_origin_px, ...): at {}: {}",
                path.display(),
                source.path(),
                source.inner()
            ),
            TruthError::Field {
                path,
                field,
                expected,
            } => write!(f, "{}: {field}: expected {expected}", path.display()),
            TruthError::Duplicate { path, at, index } => write!(
                f,
                "{}: tiles[{at}].index = {index} appears twice",
                path.display()
            ),
        }
    }
}

impl std::error::Error for TruthError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            TruthError::Read { source, .. } => Some(source),
            TruthError::Json { source, .. } => Some(source),
            _ => None,
        }
    }
}

/// True origins by acquisition index.
#[derive(Debug, Clone, PartialEq)]
pub struct ScanTruth {
    pub path: PathBuf,
    origins_px: BTreeMap<u64, [f64; 2]>,
}

impl ScanTruth {
    /// Reads and checks a truth file.
    pub fn read(path: &Path) -> Result<ScanTruth, TruthError> {
        let text = std::fs::read_to_string(path).map_err(|source| TruthError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        Self::parse(&text, path)
    }

    /// Parses the text of a truth file (`path` only names it in errors).
    pub fn parse(text: &str, path: &Path) -> Result<ScanTruth, TruthError> {
        // Through serde_path_to_error so that a refused field is named by its place in the
        // file (`tiles[0]: missing field ...`), not only by line and column.
        let record: surfstream_core::record::TruthRecord =
            serde_path_to_error::deserialize(&mut serde_json::Deserializer::from_str(text))
                .map_err(|source| TruthError::Json {
                    path: path.to_path_buf(),
                    source,
                })?;
        let mut origins_px = BTreeMap::new();
        for (k, t) in record.tiles.iter().enumerate() {
            let (index, o) = (t.index as u64, t.true_origin_px);
            if !o.iter().all(|c| c.is_finite()) {
                return Err(TruthError::Field {
                    path: path.to_path_buf(),
                    field: format!("tiles[{k}].true_origin_px"),
                    expected: "two finite numbers [x, y] in px",
                });
            }
            if origins_px.insert(index, o).is_some() {
                return Err(TruthError::Duplicate {
                    path: path.to_path_buf(),
                    at: k,
                    index,
                });
            }
        }
        Ok(ScanTruth {
            path: path.to_path_buf(),
            origins_px,
        })
    }

    /// True offset of tile `b` relative to tile `a` (acquisition indices), px; `None` when
    /// either is not in the file.
    pub fn true_offset_px(&self, a: u64, b: u64) -> Option<[f64; 2]> {
        let (oa, ob) = (self.origins_px.get(&a)?, self.origins_px.get(&b)?);
        Some([ob[0] - oa[0], ob[1] - oa[1]])
    }

    /// Number of tiles with a true origin.
    pub fn tiles(&self) -> usize {
        self.origins_px.len()
    }
}
