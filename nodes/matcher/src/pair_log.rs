//! The matcher's pair log, `nodes/<id>.pairs.jsonl` in the run's out dir: every neighbour
//! pair's streaming record (a [`MatcherPair`], the type of the report's `pairs`) appended as
//! one JSON line the moment the matcher decides the pair, so that an observer (the live view,
//! `launch/src/live/`) sees each pair's NCC, offset, outcome and weak link while the scan runs.
//! The report's `pairs` are the same records, completed by the global solve (its residual,
//! kept or not); the log holds what streaming decided, before that solve.
//!
//! [`PairLog`] writes (the node, after each tile), [`PairLogTail`] reads the lines a log has
//! gained since the last read (complete lines only: a line being written is left for later).

use std::fs::File;
use std::io::{BufWriter, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use anyhow::{anyhow, Context, Result};
use surfstream_core::record::MatcherPair;

/// Where the matcher `node_id` of a run writes its pair log.
pub fn path(out_dir: &Path, node_id: &str) -> PathBuf {
    out_dir.join("nodes").join(format!("{node_id}.pairs.jsonl"))
}

/// The writing side: one line per pair, flushed after each batch. The file is created (or
/// emptied) by the first [`PairLog::append`], not before: building a node writes nothing.
pub struct PairLog {
    path: PathBuf,
    file: Option<BufWriter<File>>,
}

impl PairLog {
    /// The log of `node_id` in `out_dir`.
    pub fn new(out_dir: &Path, node_id: &str) -> PairLog {
        PairLog {
            path: path(out_dir, node_id),
            file: None,
        }
    }

    fn open(&mut self) -> Result<&mut BufWriter<File>> {
        if self.file.is_none() {
            if let Some(dir) = self.path.parent() {
                std::fs::create_dir_all(dir)
                    .with_context(|| format!("{}: cannot create", dir.display()))?;
            }
            let file = File::create(&self.path)
                .with_context(|| format!("{}: cannot create the pair log", self.path.display()))?;
            self.file = Some(BufWriter::new(file));
        }
        self.file
            .as_mut()
            .ok_or_else(|| anyhow!("{}: not open", self.path.display()))
    }

    /// Appends `pairs`, one JSON line each, and flushes them to the file.
    pub fn append<'a>(&mut self, pairs: impl IntoIterator<Item = &'a MatcherPair>) -> Result<()> {
        let at = self.path.display().to_string();
        let err = |e: &dyn std::fmt::Display| anyhow!("{at}: cannot write: {e}");
        let file = self.open()?;
        for p in pairs {
            serde_json::to_writer(&mut *file, p).map_err(|e| err(&e))?;
            file.write_all(b"\n").map_err(|e| err(&e))?;
        }
        file.flush().map_err(|e| err(&e))
    }
}

/// The reading side: the records a log gained since the last [`PairLogTail::read_new`].
#[derive(Debug)]
pub struct PairLogTail {
    path: PathBuf,
    /// Bytes consumed (complete lines).
    offset: u64,
    lines: u64,
}

impl PairLogTail {
    pub fn new(path: PathBuf) -> PairLogTail {
        PairLogTail {
            path,
            offset: 0,
            lines: 0,
        }
    }

    /// The complete lines written since the last call, parsed (none while the log does not
    /// exist yet). A line that does not read as a pair record is an error naming the file and
    /// the line; the lines after it are still read by the next call.
    pub fn read_new(&mut self) -> Result<Vec<MatcherPair>> {
        let mut file = match File::open(&self.path) {
            Ok(f) => f,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(e) => return Err(anyhow!("{}: cannot open: {e}", self.path.display())),
        };
        file.seek(SeekFrom::Start(self.offset))
            .and_then(|_| {
                let mut buf = Vec::new();
                file.read_to_end(&mut buf).map(|_| buf)
            })
            .map_err(|e| anyhow!("{}: cannot read: {e}", self.path.display()))
            .and_then(|buf| self.parse(&buf))
    }

    fn parse(&mut self, buf: &[u8]) -> Result<Vec<MatcherPair>> {
        let complete = buf.iter().rposition(|&b| b == b'\n').map_or(0, |k| k + 1);
        let mut pairs = Vec::new();
        let mut bad = None;
        for line in buf[..complete].split(|&b| b == b'\n') {
            if line.is_empty() {
                continue;
            }
            self.lines += 1;
            match serde_json::from_slice::<MatcherPair>(line) {
                Ok(p) => pairs.push(p),
                Err(e) => {
                    bad.get_or_insert((self.lines, e));
                }
            }
        }
        self.offset += complete as u64;
        match bad {
            None => Ok(pairs),
            Some((n, e)) => Err(anyhow!(
                "{}: line {n}: expected a pair record (MatcherPair): {e}",
                self.path.display()
            )),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pair(a: u32, b: u32, ncc: f64, weak: bool) -> MatcherPair {
        MatcherPair {
            a,
            b,
            direction: "horizontal".into(),
            nominal_offset_px: [90.0, 0.0],
            offset_px: Some([91.5, -0.25]),
            ncc,
            peak_ratio: f64::NAN,
            accepted: true,
            reason: None,
            accepted_below_min_ncc: weak,
            layout_inconsistent: None,
            features: None,
            final_offset_px: None,
            z_samples: None,
            alternatives_px: None,
            chosen_alternative: None,
            directional: None,
            kept_by_global_solve: None,
            residual_px: None,
            offset_covariance_px2: None,
            offset_sd_px: None,
        }
    }

    #[test]
    fn a_tail_reads_each_pair_once_as_the_log_grows() {
        let dir = tempfile::tempdir().unwrap();
        let mut tail = PairLogTail::new(path(dir.path(), "matcher"));
        assert!(tail.read_new().unwrap().is_empty(), "no log yet: nothing");
        let mut log = PairLog::new(dir.path(), "matcher");
        assert!(!path(dir.path(), "matcher").exists(), "nothing written yet");
        log.append(&[pair(0, 1, 0.97, false)]).unwrap();
        let got = tail.read_new().unwrap();
        assert_eq!(got.len(), 1);
        assert_eq!((got[0].a, got[0].b, got[0].ncc), (0, 1, 0.97));
        assert!(got[0].peak_ratio.is_nan(), "NaN goes through null and back");
        assert!(tail.read_new().unwrap().is_empty(), "read once");
        log.append(&[pair(1, 2, 0.31, true), pair(0, 3, 0.9, false)])
            .unwrap();
        let got = tail.read_new().unwrap();
        assert_eq!(got.len(), 2);
        assert!(got[0].accepted_below_min_ncc && !got[1].accepted_below_min_ncc);
    }

    #[test]
    fn a_line_being_written_waits_and_a_bad_line_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let p = path(dir.path(), "m");
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
        let line = serde_json::to_string(&pair(0, 1, 0.9, false)).unwrap();
        std::fs::write(&p, format!("{line}\n{}", &line[..10])).unwrap();
        let mut tail = PairLogTail::new(p.clone());
        assert_eq!(tail.read_new().unwrap().len(), 1, "the partial line waits");
        std::fs::write(&p, format!("{line}\n{line}\n{{\"a\": 1}}\n{line}\n")).unwrap();
        let e = tail.read_new().unwrap_err().to_string();
        assert!(
            e.contains("m.pairs.jsonl: line 3: expected a pair record"),
            "{e}"
        );
        assert!(tail.read_new().unwrap().is_empty(), "past the bad line");
    }
}
