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
//! **Spill file**: [`surfstream_core::store::ChunkedGrid`], an unnamed temporary file in the
//! spill folder ([`ChunkStore::set_spill_dir`], default the system temp folder); a chunk's slot
//! holds the `CHUNK_PX^2` means, row-major, then the `CHUNK_PX^2` weights, little-endian f32.

use std::path::PathBuf;

use rayon::prelude::*;
use surfstream_core::canvas::GridRect;
use surfstream_core::store::{self, AppendLog, ChunkedGrid, GridChunk};

use crate::error::Result;

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

impl GridChunk for Chunk {
    const BYTES: usize = CHUNK_BYTES;
    fn encode(&self, out: &mut Vec<u8>) {
        out.extend(store::encode(&self.mean));
        out.extend(store::encode(&self.weight));
    }
    fn decode(bytes: &[u8]) -> Self {
        let (m, w) = bytes.split_at(CHUNK_BYTES / 2);
        let mut c = Chunk {
            mean: Vec::with_capacity(CHUNK_LEN),
            weight: Vec::with_capacity(CHUNK_LEN),
        };
        store::decode_into(m, &mut c.mean);
        store::decode_into(w, &mut c.weight);
        c
    }
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
    grid: ChunkedGrid<Chunk>,
    budget_chunks: Option<usize>,
    spill_dir: Option<PathBuf>,
}

impl Clone for ChunkStore {
    /// A clone holds every chunk in memory, without a budget and without sharing the spill
    /// file.
    fn clone(&self) -> Self {
        let mut out = ChunkStore::default();
        out.grid.tick();
        for key in self.grid.keys() {
            // A clone is for tests and small panoramas; a failing read leaves the chunk empty
            // in the copy rather than panicking.
            if let Ok(Some(c)) = self.grid.peek(key, Chunk::clone) {
                out.grid.insert(key, c);
            }
        }
        out
    }
}

impl ChunkStore {
    /// Keep at most about `bytes` of chunks in memory (at least the chunks of the tile being
    /// placed); `None`: no limit.
    pub fn set_budget_bytes(&mut self, bytes: Option<usize>) {
        self.budget_chunks = bytes.map(|b| (b / CHUNK_BYTES).max(1));
        self.grid
            .set_limit(self.budget_chunks, self.spill_dir.clone());
    }

    /// Folder of the spill file (default: the system temp folder). Takes effect at the first
    /// spill.
    pub fn set_spill_dir(&mut self, dir: Option<PathBuf>) {
        self.spill_dir = dir;
        self.grid
            .set_limit(self.budget_chunks, self.spill_dir.clone());
    }

    pub fn stats(&self) -> ChunkStats {
        let s = self.grid.stats();
        ChunkStats {
            chunks: s.chunks,
            peak_resident_chunks: s.peak_resident,
            spills: s.spills,
            reloads: s.reloads,
        }
    }

    /// Make the chunks `keys` resident (created empty or read back), then spill the least
    /// recently used others while over budget.
    fn make_resident(&mut self, keys: &[ChunkKey]) -> Result<()> {
        self.grid.tick();
        for &key in keys {
            if !self.grid.load(key)? {
                self.grid.insert(key, Chunk::zeroed());
            }
        }
        self.grid.evict(|k| keys.contains(&k))?;
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
        let mut touched = self.grid.resident_mut(&keys);
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
            let cr = chunk_rect(key);
            let Some(i) = cr.intersect(rect) else {
                continue;
            };
            let n = i.cols();
            self.grid.peek(key, |c| {
                for gy in i.y0..i.y1 {
                    let src = (gy - cr.y0) as usize * CHUNK_PX + (i.x0 - cr.x0) as usize;
                    let dst = (gy - rect.y0) as usize * w + (i.x0 - rect.x0) as usize;
                    mean[dst..dst + n].copy_from_slice(&c.mean[src..src + n]);
                    weight[dst..dst + n].copy_from_slice(&c.weight[src..src + n]);
                }
            })?;
        }
        Ok((mean, weight))
    }
}

/// Tiles written once to an unnamed temporary file and read back one at a time: what the
/// final re-render and the overlap quality need, without keeping every tile in memory
/// ([`surfstream_core::store::AppendLog`]: the tiles' f32 heights, little-endian, row-major,
/// one after another; the offset and length of each are kept in memory with its header).
#[derive(Debug)]
pub struct TileSpill {
    log: AppendLog<f32>,
}

impl Default for TileSpill {
    fn default() -> Self {
        Self::new(None)
    }
}

impl TileSpill {
    pub fn new(dir: Option<PathBuf>) -> Self {
        Self {
            log: AppendLog::new(dir),
        }
    }

    /// Appends heights; returns their offset.
    pub fn write(&mut self, heights: &[f32]) -> Result<u64> {
        Ok(self.log.append(heights)?)
    }

    /// Reads `len` heights written at `offset`.
    pub fn read(&self, offset: u64, len: usize) -> Result<Vec<f32>> {
        Ok(self.log.read(offset, len)?)
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
