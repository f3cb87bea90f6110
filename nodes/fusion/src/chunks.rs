//! The panorama's accumulators in fixed-size chunks, so that memory follows what the scan is
//! touching, not the panorama's size (issue 17).
//!
//! The canvas grid is cut into square chunks of [`CHUNK_PX`] x [`CHUNK_PX`] pixels aligned at
//! multiples of `CHUNK_PX` grid indices (chunk `(cx, cy)` holds grid columns `cx * CHUNK_PX ..
//! (cx + 1) * CHUNK_PX`, likewise rows; indices may be negative). A chunk exists once a tile
//! touches it; untouched ones read as "no data". Each chunk holds the two f32 accumulators of
//! [`crate::Panorama`] (running mean and weight sum), 2 MiB per chunk.
//!
//! **Budget and spill.** Without a budget every chunk stays in memory (8 bytes per touched
//! pixel, as before). With one ([`ChunkStore::set_budget_bytes`]) the least recently touched
//! chunks go to a spill file when the resident chunks exceed it; a chunk a later tile touches
//! again is read back. Spilling stores the exact f32 bits, so a run with any budget gives the
//! same panorama, bit for bit, as one without. The chunks one tile touches are always
//! resident while it is placed, so a budget below that (about 9 chunks, 18 MiB, for a
//! 1024 px tile) is exceeded by that much rather than failing.
//!
//! **Spill file layout** (our own, private to the run): an unnamed temporary file (deleted by
//! the OS when the store is dropped or the process dies) in the spill folder
//! ([`ChunkStore::set_spill_dir`], default the system temp folder). A chunk is given a slot
//! the first time it spills and keeps it; slot `k` starts at byte `k * CHUNK_BYTES` and holds
//! the `CHUNK_PX^2` means, row-major, then the `CHUNK_PX^2` weights, each a little-endian f32.

use std::collections::HashMap;
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::PathBuf;

use rayon::prelude::*;
use surfstream_core::canvas::GridRect;

use crate::error::{FusionError, Result};

/// Side of a chunk in pixels. 512 keeps a 1024 px tile on 9 chunks at most (12 when its
/// footprint straddles a boundary in both directions) and one chunk at 2 MiB.
pub const CHUNK_PX: usize = 512;
const CHUNK_LEN: usize = CHUNK_PX * CHUNK_PX;
/// Bytes of one chunk in memory and in the spill file (mean and weight, f32).
pub const CHUNK_BYTES: usize = 2 * 4 * CHUNK_LEN;

/// Chunk coordinates: grid index `div_euclid` [`CHUNK_PX`].
pub type ChunkKey = (i64, i64);

/// The grid rectangle of a chunk.
pub fn chunk_rect((cx, cy): ChunkKey) -> GridRect {
    let c = CHUNK_PX as i64;
    GridRect {
        x0: cx * c,
        y0: cy * c,
        x1: (cx + 1) * c,
        y1: (cy + 1) * c,
    }
}

/// Keys of the chunks a grid rectangle intersects, row by row.
pub fn chunks_of(r: &GridRect) -> Vec<ChunkKey> {
    if r.is_empty() {
        return Vec::new();
    }
    let c = CHUNK_PX as i64;
    let (cx0, cx1) = (r.x0.div_euclid(c), (r.x1 - 1).div_euclid(c));
    let (cy0, cy1) = (r.y0.div_euclid(c), (r.y1 - 1).div_euclid(c));
    (cy0..=cy1)
        .flat_map(|cy| (cx0..=cx1).map(move |cx| (cx, cy)))
        .collect()
}

/// One chunk's accumulators, row-major `CHUNK_PX` x `CHUNK_PX`.
#[derive(Debug, Clone)]
pub(crate) struct Chunk {
    pub mean: Vec<f32>,
    pub weight: Vec<f32>,
}

impl Chunk {
    fn zeroed() -> Self {
        Self {
            mean: vec![0.0; CHUNK_LEN],
            weight: vec![0.0; CHUNK_LEN],
        }
    }
}

#[derive(Debug)]
enum Slot {
    /// In memory, with the clock of its last use.
    Resident(Box<Chunk>, u64),
    /// In the spill file at this slot.
    Spilled(u64),
}

/// What the store did, for reports.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct ChunkStats {
    /// Chunks that exist (touched by a tile).
    pub chunks: usize,
    /// Most chunks in memory at once.
    pub peak_resident_chunks: usize,
    /// Chunk writes to the spill file and reads back from it.
    pub spills: u64,
    pub reloads: u64,
}

/// The chunked accumulators of one panorama.
#[derive(Debug, Default)]
pub struct ChunkStore {
    chunks: HashMap<ChunkKey, Slot>,
    /// Spill slot of every chunk that has spilled once.
    slots: HashMap<ChunkKey, u64>,
    clock: u64,
    resident: usize,
    budget_chunks: Option<usize>,
    spill_dir: Option<PathBuf>,
    spill: Option<File>,
    stats: ChunkStats,
}

impl Clone for ChunkStore {
    /// A clone holds every chunk in memory, without a budget and without sharing the spill
    /// file.
    fn clone(&self) -> Self {
        let mut out = ChunkStore::default();
        for &key in self.chunks.keys() {
            // A clone is for tests and small panoramas; a failing read leaves the chunk empty
            // in the copy rather than panicking.
            if let Ok(c) = self.read(key) {
                out.chunks.insert(key, Slot::Resident(Box::new(c), 0));
            }
        }
        out.resident = out.chunks.len();
        out.stats = ChunkStats {
            chunks: out.chunks.len(),
            peak_resident_chunks: out.chunks.len(),
            ..ChunkStats::default()
        };
        out
    }
}

impl ChunkStore {
    /// Keep at most about `bytes` of chunks in memory (at least the chunks of the tile being
    /// placed); `None`: no limit.
    pub fn set_budget_bytes(&mut self, bytes: Option<usize>) {
        self.budget_chunks = bytes.map(|b| (b / CHUNK_BYTES).max(1));
    }

    /// Folder of the spill file (default: the system temp folder). Takes effect at the first
    /// spill.
    pub fn set_spill_dir(&mut self, dir: Option<PathBuf>) {
        self.spill_dir = dir;
    }

    pub fn stats(&self) -> ChunkStats {
        self.stats
    }

    fn spill_io(e: std::io::Error, what: &str) -> FusionError {
        FusionError::Spill {
            message: format!("{what}: {e}"),
        }
    }

    /// A chunk's content, from memory or from the spill file; a chunk never touched is all
    /// zero (no data).
    fn read(&self, key: ChunkKey) -> Result<Chunk> {
        match self.chunks.get(&key) {
            None => Ok(Chunk::zeroed()),
            Some(Slot::Resident(c, _)) => Ok((**c).clone()),
            Some(Slot::Spilled(slot)) => self.read_slot(*slot),
        }
    }

    fn read_slot(&self, slot: u64) -> Result<Chunk> {
        let file = self.spill.as_ref().ok_or_else(|| FusionError::Spill {
            message: "a spilled chunk without a spill file".into(),
        })?;
        let mut bytes = vec![0u8; CHUNK_BYTES];
        file.read_exact_at(&mut bytes, slot * CHUNK_BYTES as u64)
            .map_err(|e| Self::spill_io(e, "reading a chunk back from the spill file"))?;
        let mut c = Chunk {
            mean: Vec::with_capacity(CHUNK_LEN),
            weight: Vec::with_capacity(CHUNK_LEN),
        };
        let (m, w) = bytes.split_at(CHUNK_BYTES / 2);
        c.mean.extend(
            m.chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
        );
        c.weight.extend(
            w.chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
        );
        Ok(c)
    }

    fn write_slot(&mut self, key: ChunkKey, c: &Chunk) -> Result<u64> {
        if self.spill.is_none() {
            let dir = self.spill_dir.clone().unwrap_or_else(std::env::temp_dir);
            let f = tempfile_in(&dir).map_err(|e| {
                Self::spill_io(e, &format!("creating the spill file in {}", dir.display()))
            })?;
            self.spill = Some(f);
        }
        let next = self.slots.len() as u64;
        let slot = *self.slots.entry(key).or_insert(next);
        let mut bytes = Vec::with_capacity(CHUNK_BYTES);
        for v in c.mean.iter().chain(&c.weight) {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
        if let Some(f) = &self.spill {
            f.write_all_at(&bytes, slot * CHUNK_BYTES as u64)
                .map_err(|e| Self::spill_io(e, "writing a chunk to the spill file"))?;
        }
        self.stats.spills += 1;
        Ok(slot)
    }

    /// Make the chunks `keys` resident (created empty or read back), then spill the least
    /// recently used others while over budget.
    fn make_resident(&mut self, keys: &[ChunkKey]) -> Result<()> {
        self.clock += 1;
        let now = self.clock;
        for &key in keys {
            match self.chunks.get_mut(&key) {
                Some(Slot::Resident(_, t)) => *t = now,
                Some(Slot::Spilled(slot)) => {
                    let slot = *slot;
                    let c = self.read_slot(slot)?;
                    self.chunks.insert(key, Slot::Resident(Box::new(c), now));
                    self.resident += 1;
                    self.stats.reloads += 1;
                }
                None => {
                    self.chunks
                        .insert(key, Slot::Resident(Box::new(Chunk::zeroed()), now));
                    self.resident += 1;
                    self.stats.chunks += 1;
                }
            }
        }
        self.stats.peak_resident_chunks = self.stats.peak_resident_chunks.max(self.resident);
        let Some(budget) = self.budget_chunks else {
            return Ok(());
        };
        if self.resident <= budget {
            return Ok(());
        }
        // Oldest first; the chunks just used (clock == now) stay.
        let mut victims: Vec<(u64, ChunkKey)> = self
            .chunks
            .iter()
            .filter_map(|(k, s)| match s {
                Slot::Resident(_, t) if *t < now => Some((*t, *k)),
                _ => None,
            })
            .collect();
        victims.sort_unstable();
        for (_, key) in victims.into_iter().take(self.resident - budget) {
            if let Some(Slot::Resident(c, _)) = self.chunks.remove(&key) {
                match self.write_slot(key, &c) {
                    Ok(slot) => {
                        self.chunks.insert(key, Slot::Spilled(slot));
                        self.resident -= 1;
                    }
                    Err(e) => {
                        self.chunks.insert(key, Slot::Resident(c, 0));
                        return Err(e);
                    }
                }
            }
        }
        Ok(())
    }

    /// Runs `f(chunk rect, chunk)` on every chunk `rect` intersects, in parallel (each chunk
    /// once, so the result does not depend on the schedule). The chunks are made resident
    /// first.
    pub(crate) fn for_each_mut(
        &mut self,
        rect: &GridRect,
        f: impl Fn(&GridRect, &mut Chunk) + Sync,
    ) -> Result<()> {
        let keys = chunks_of(rect);
        self.make_resident(&keys)?;
        let mut touched: Vec<(ChunkKey, &mut Chunk)> = self
            .chunks
            .iter_mut()
            .filter_map(|(k, s)| match s {
                Slot::Resident(c, t) if *t == self.clock && keys.contains(k) => {
                    Some((*k, &mut **c))
                }
                _ => None,
            })
            .collect();
        touched
            .par_iter_mut()
            .for_each(|(k, c)| f(&chunk_rect(*k), c));
        Ok(())
    }

    /// The means and weights of a grid rectangle, row-major; pixels no tile touched are
    /// (0, 0). Spilled chunks are read from the file without being made resident.
    pub fn read_rect(&self, rect: &GridRect) -> Result<(Vec<f32>, Vec<f32>)> {
        let (w, h) = (rect.cols(), rect.rows());
        let mut mean = vec![0.0f32; w * h];
        let mut weight = vec![0.0f32; w * h];
        for key in chunks_of(rect) {
            let spilled;
            let c: &Chunk = match self.chunks.get(&key) {
                None => continue,
                Some(Slot::Resident(c, _)) => c,
                Some(Slot::Spilled(slot)) => {
                    spilled = self.read_slot(*slot)?;
                    &spilled
                }
            };
            let cr = chunk_rect(key);
            let Some(i) = cr.intersect(rect) else {
                continue;
            };
            let n = i.cols();
            for gy in i.y0..i.y1 {
                let src = (gy - cr.y0) as usize * CHUNK_PX + (i.x0 - cr.x0) as usize;
                let dst = (gy - rect.y0) as usize * w + (i.x0 - rect.x0) as usize;
                mean[dst..dst + n].copy_from_slice(&c.mean[src..src + n]);
                weight[dst..dst + n].copy_from_slice(&c.weight[src..src + n]);
            }
        }
        Ok((mean, weight))
    }
}

/// An unnamed temporary file in `dir`: gone when closed, also after a crash.
fn tempfile_in(dir: &std::path::Path) -> std::io::Result<File> {
    // O_TMPFILE where the file system supports it; otherwise create and unlink at once.
    std::fs::create_dir_all(dir)?;
    for attempt in 0..100u32 {
        let path = dir.join(format!(
            ".surfstream-spill-{}-{}-{attempt}",
            std::process::id(),
            SPILL_SEQ.fetch_add(1, std::sync::atomic::Ordering::Relaxed)
        ));
        match std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create_new(true)
            .open(&path)
        {
            Ok(f) => {
                std::fs::remove_file(&path)?;
                return Ok(f);
            }
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
            Err(e) => return Err(e),
        }
    }
    Err(std::io::Error::other("no free spill file name"))
}

static SPILL_SEQ: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

/// Tiles written once to an unnamed temporary file and read back one at a time: what the
/// final re-render and the overlap quality need, without keeping every tile in memory.
///
/// Layout (our own, private to the run): the tiles' f32 heights, little-endian, row-major,
/// one after another in the order they were written; the offset and length of each are kept
/// in memory with its header.
#[derive(Debug, Default)]
pub struct TileSpill {
    dir: Option<PathBuf>,
    file: Option<File>,
    end: u64,
}

impl TileSpill {
    pub fn new(dir: Option<PathBuf>) -> Self {
        Self {
            dir,
            file: None,
            end: 0,
        }
    }

    /// Appends heights; returns their offset.
    pub fn write(&mut self, heights: &[f32]) -> Result<u64> {
        if self.file.is_none() {
            let dir = self.dir.clone().unwrap_or_else(std::env::temp_dir);
            let f = tempfile_in(&dir).map_err(|e| FusionError::Spill {
                message: format!("creating the tile spill file in {}: {e}", dir.display()),
            })?;
            self.file = Some(f);
        }
        let mut bytes = Vec::with_capacity(heights.len() * 4);
        for v in heights {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
        let at = self.end;
        if let Some(f) = &self.file {
            f.write_all_at(&bytes, at).map_err(|e| FusionError::Spill {
                message: format!("writing a tile to the spill file: {e}"),
            })?;
        }
        self.end += bytes.len() as u64;
        Ok(at)
    }

    /// Reads `len` heights written at `offset`.
    pub fn read(&self, offset: u64, len: usize) -> Result<Vec<f32>> {
        let file = self.file.as_ref().ok_or_else(|| FusionError::Spill {
            message: "reading a tile before any was written".into(),
        })?;
        let mut bytes = vec![0u8; len * 4];
        file.read_exact_at(&mut bytes, offset)
            .map_err(|e| FusionError::Spill {
                message: format!("reading a tile back from the spill file: {e}"),
            })?;
        Ok(bytes
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chunk_keys_cover_negative_and_straddling_rects() {
        let c = CHUNK_PX as i64;
        let r = GridRect {
            x0: -1,
            y0: c - 1,
            x1: 1,
            y1: c + 1,
        };
        assert_eq!(chunks_of(&r), vec![(-1, 0), (0, 0), (-1, 1), (0, 1)]);
        assert!(chunks_of(&GridRect::default()).is_empty());
    }

    #[test]
    fn spilled_chunks_come_back_bit_for_bit() {
        let mut s = ChunkStore::default();
        s.set_budget_bytes(Some(CHUNK_BYTES));
        let c = CHUNK_PX as i64;
        let a = GridRect {
            x0: 3,
            y0: 5,
            x1: 9,
            y1: 7,
        };
        let b = GridRect {
            x0: 3 + c,
            y0: 5,
            x1: 9 + c,
            y1: 7,
        };
        let write = |s: &mut ChunkStore, r: &GridRect, v: f32| {
            let r = *r;
            s.for_each_mut(&r, move |cr, ch| {
                for gy in r.y0..r.y1 {
                    for gx in r.x0..r.x1 {
                        let i = (gy - cr.y0) as usize * CHUNK_PX + (gx - cr.x0) as usize;
                        ch.mean[i] = v + gx as f32 * 1e-3;
                        ch.weight[i] = 0.25;
                    }
                }
            })
            .unwrap()
        };
        write(&mut s, &a, 1.5);
        write(&mut s, &b, -2.5); // spills the first chunk
        assert_eq!(s.stats().spills, 1);
        let (m, w) = s.read_rect(&a).unwrap();
        assert_eq!(m[0].to_bits(), (1.5f32 + 3.0 * 1e-3).to_bits());
        assert!(w.iter().all(|&w| w == 0.25));
        write(&mut s, &a, 7.0); // reads it back, spills the second
        assert_eq!((s.stats().reloads, s.stats().spills), (1, 2));
        let (m, _) = s.read_rect(&b).unwrap();
        assert_eq!(m[1], -2.5 + (4 + c) as f32 * 1e-3);
        let wide = GridRect {
            x0: 0,
            y0: 0,
            x1: 2 * c,
            y1: 8,
        };
        let (_, w) = s.read_rect(&wide).unwrap();
        assert_eq!(w.iter().filter(|&&w| w > 0.0).count(), 2 * 6 * 2);
        // The chunk being touched comes in before the old one goes out.
        assert_eq!(s.stats().peak_resident_chunks, 2);
    }

    #[test]
    fn tiles_round_trip_through_the_spill_file() {
        let dir = tempfile::tempdir().unwrap();
        let mut t = TileSpill::new(Some(dir.path().into()));
        let a = [1.0f32, f32::NAN, -0.0];
        let b = [3.25f32; 5];
        let (oa, ob) = (t.write(&a).unwrap(), t.write(&b).unwrap());
        assert_eq!(t.read(ob, 5).unwrap(), b);
        let back = t.read(oa, 3).unwrap();
        assert!(back.iter().zip(&a).all(|(x, y)| x.to_bits() == y.to_bits()));
        // Unnamed: nothing is left in the folder.
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }
}
