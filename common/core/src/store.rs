//! Spill stores: where a node puts data that need not stay in memory, and gets it back bit for
//! bit. One mechanism for every node, with one error that names the spill folder.
//!
//! - [`SpillFile`]: an unnamed temporary file in a spill folder (the `tempfile` crate:
//!   O_TMPFILE where the file system has it), created at the first write and gone when
//!   dropped or when the process dies, however it dies. Positioned reads and writes.
//! - [`AppendLog`]: values appended one block after another, each block read back by the
//!   offset its append returned (the matcher's and the fusion's placed tiles).
//! - [`ChunkedGrid`]: the chunks of an unbounded grid under `(cx, cy)` keys, the least
//!   recently used written to a spill file beyond a limit and read back when used again (the
//!   fusion's panorama accumulators, the wavelet's live mirror).
//! - [`RowStore`]: a `rows x cols` matrix in memory when small, else in a spill file, written
//!   and read by rows (the wavelet's level coefficients).
//!
//! Every layout is private to the run: values little-endian, a block or a chunk at the offset
//! the store chose. Nothing here knows what the values mean.

use std::collections::HashMap;
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

/// A spill file could not be created, written or read (disk full, folder not writable...).
#[derive(Debug, thiserror::Error)]
#[error("spill file in {}: {action}: {source}", folder.display())]
pub struct StoreError {
    /// The spill folder.
    pub folder: PathBuf,
    /// What was being done: "creating", "writing 2097152 bytes at 0", ...
    pub action: String,
    #[source]
    pub source: std::io::Error,
}

impl From<StoreError> for std::io::Error {
    /// For code paths that speak `std::io` (row readers): the kind is kept, the message names
    /// the folder and the action.
    fn from(e: StoreError) -> Self {
        std::io::Error::new(e.source.kind(), e.to_string())
    }
}

pub type Result<T> = std::result::Result<T, StoreError>;

/// A value kept in a spill file: fixed size, little-endian.
pub trait Element: Copy + Send + Sync + 'static {
    const BYTES: usize;
    fn put(self, out: &mut Vec<u8>);
    /// `b.len() == Self::BYTES`.
    fn get(b: &[u8]) -> Self;
}

impl Element for f32 {
    const BYTES: usize = 4;
    fn put(self, out: &mut Vec<u8>) {
        out.extend_from_slice(&self.to_le_bytes());
    }
    fn get(b: &[u8]) -> Self {
        f32::from_le_bytes([b[0], b[1], b[2], b[3]])
    }
}

impl Element for u32 {
    const BYTES: usize = 4;
    fn put(self, out: &mut Vec<u8>) {
        out.extend_from_slice(&self.to_le_bytes());
    }
    fn get(b: &[u8]) -> Self {
        u32::from_le_bytes([b[0], b[1], b[2], b[3]])
    }
}

impl Element for f64 {
    const BYTES: usize = 8;
    fn put(self, out: &mut Vec<u8>) {
        out.extend_from_slice(&self.to_le_bytes());
    }
    fn get(b: &[u8]) -> Self {
        let mut a = [0u8; 8];
        a.copy_from_slice(&b[..8]);
        f64::from_le_bytes(a)
    }
}

/// `values` as bytes, little-endian.
pub fn encode<T: Element>(values: &[T]) -> Vec<u8> {
    let mut out = Vec::with_capacity(values.len() * T::BYTES);
    for &v in values {
        v.put(&mut out);
    }
    out
}

/// Appends the values `bytes` holds to `out`.
pub fn decode_into<T: Element>(bytes: &[u8], out: &mut Vec<T>) {
    out.extend(bytes.chunks_exact(T::BYTES).map(T::get));
}

/// An unnamed temporary file in a spill folder, created at the first write.
#[derive(Debug)]
pub struct SpillFile {
    folder: PathBuf,
    file: Option<File>,
}

impl SpillFile {
    /// A spill file in `folder` (created with its parents when needed); `None`: the system's
    /// temporary folder. Nothing is created before the first write.
    pub fn new(folder: Option<PathBuf>) -> Self {
        Self {
            folder: folder.unwrap_or_else(std::env::temp_dir),
            file: None,
        }
    }

    pub fn folder(&self) -> &Path {
        &self.folder
    }

    /// Whether anything was written yet (the file exists).
    pub fn is_created(&self) -> bool {
        self.file.is_some()
    }

    fn error(&self, action: String, source: std::io::Error) -> StoreError {
        StoreError {
            folder: self.folder.clone(),
            action,
            source,
        }
    }

    fn file(&mut self) -> Result<&File> {
        if self.file.is_none() {
            let f = std::fs::create_dir_all(&self.folder)
                .and_then(|()| tempfile::tempfile_in(&self.folder))
                .map_err(|e| self.error("creating".into(), e))?;
            self.file = Some(f);
        }
        match &self.file {
            Some(f) => Ok(f),
            None => Err(self.error("creating".into(), std::io::Error::other("no file"))),
        }
    }

    /// Makes the file `len` bytes long (creating it).
    pub fn set_len(&mut self, len: u64) -> Result<()> {
        let r = self.file()?.set_len(len);
        r.map_err(|e| self.error(format!("sizing to {len} bytes"), e))
    }

    pub fn write_at(&mut self, offset: u64, bytes: &[u8]) -> Result<()> {
        let r = self.file()?.write_all_at(bytes, offset);
        r.map_err(|e| self.error(format!("writing {} bytes at {offset}", bytes.len()), e))
    }

    /// Fills `buf` from `offset`; reading what was never written is an error.
    pub fn read_at(&self, offset: u64, buf: &mut [u8]) -> Result<()> {
        let len = buf.len();
        let action = || format!("reading {len} bytes at {offset}");
        let Some(f) = &self.file else {
            return Err(self.error(action(), std::io::Error::other("nothing was written")));
        };
        f.read_exact_at(buf, offset)
            .map_err(|e| self.error(action(), e))
    }

    /// The `len` values at `offset`.
    pub fn read_values<T: Element>(&self, offset: u64, len: usize) -> Result<Vec<T>> {
        let mut bytes = vec![0u8; len * T::BYTES];
        self.read_at(offset, &mut bytes)?;
        let mut out = Vec::with_capacity(len);
        decode_into(&bytes, &mut out);
        Ok(out)
    }
}

/// Blocks of values appended to a spill file, each read back by the offset its append
/// returned.
#[derive(Debug)]
pub struct AppendLog<T: Element> {
    file: SpillFile,
    end: u64,
    _values: std::marker::PhantomData<T>,
}

impl<T: Element> AppendLog<T> {
    /// A log in `folder` (`None`: the system's temporary folder); the file is created at the
    /// first append.
    pub fn new(folder: Option<PathBuf>) -> Self {
        Self {
            file: SpillFile::new(folder),
            end: 0,
            _values: std::marker::PhantomData,
        }
    }

    /// Appends `values`; returns their offset (bytes).
    pub fn append(&mut self, values: &[T]) -> Result<u64> {
        let at = self.end;
        let bytes = encode(values);
        self.file.write_at(at, &bytes)?;
        self.end += bytes.len() as u64;
        Ok(at)
    }

    /// The `len` values appended at `offset`.
    pub fn read(&self, offset: u64, len: usize) -> Result<Vec<T>> {
        self.file.read_values(offset, len)
    }

    pub fn folder(&self) -> &Path {
        self.file.folder()
    }
}

/// A chunk a [`ChunkedGrid`] can spill: a fixed number of bytes.
pub trait GridChunk: Send + Sized {
    /// Bytes of one chunk in the spill file.
    const BYTES: usize;
    fn encode(&self, out: &mut Vec<u8>);
    /// `bytes.len() == Self::BYTES`.
    fn decode(bytes: &[u8]) -> Self;
}

/// Chunk coordinates on an unbounded grid.
pub type ChunkKey = (i64, i64);

/// What a [`ChunkedGrid`] did, for reports.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct GridStats {
    /// Chunks that exist.
    pub chunks: usize,
    /// Most chunks in memory at once.
    pub peak_resident: usize,
    /// Chunk writes to the spill file.
    pub spills: u64,
    /// Chunk reads back from it.
    pub reloads: u64,
}

#[derive(Debug)]
enum Slot<C> {
    /// In memory, with the clock of its last use.
    Resident(Box<C>, u64),
    /// In the spill file only.
    Spilled,
}

/// The chunks of a grid, at most `limit` in memory: beyond it the least recently used go to a
/// spill file (a chunk gets a slot, `slot * C::BYTES`, the first time it spills and keeps it)
/// and come back when used again. Spilling stores the exact bytes, so a limit changes no
/// result.
///
/// Use: [`ChunkedGrid::tick`] starts a use (a clock step), [`ChunkedGrid::load`] /
/// [`ChunkedGrid::insert`] make chunks resident under the current tick, then
/// [`ChunkedGrid::evict`] spills while over the limit, never a chunk the caller keeps.
#[derive(Debug)]
pub struct ChunkedGrid<C: GridChunk> {
    chunks: HashMap<ChunkKey, Slot<C>>,
    slots: HashMap<ChunkKey, u64>,
    clock: u64,
    resident: usize,
    limit: Option<usize>,
    file: SpillFile,
    stats: GridStats,
}

impl<C: GridChunk> Default for ChunkedGrid<C> {
    fn default() -> Self {
        Self {
            chunks: HashMap::new(),
            slots: HashMap::new(),
            clock: 0,
            resident: 0,
            limit: None,
            file: SpillFile::new(None),
            stats: GridStats::default(),
        }
    }
}

impl<C: GridChunk> ChunkedGrid<C> {
    /// At most `limit` chunks in memory (`None`: all), the rest spilled into `folder`
    /// (`None`: the system's temporary folder). Takes effect at the next eviction.
    pub fn set_limit(&mut self, limit: Option<usize>, folder: Option<PathBuf>) {
        self.limit = limit.map(|l| l.max(1));
        if !self.file.is_created() {
            self.file = SpillFile::new(folder);
        }
    }

    pub fn stats(&self) -> GridStats {
        self.stats
    }

    /// Chunks in memory now.
    pub fn resident_len(&self) -> usize {
        self.resident
    }

    /// Whether any chunk went to the spill file.
    pub fn has_spilled(&self) -> bool {
        self.file.is_created()
    }

    /// Every chunk that exists, in memory or spilled.
    pub fn keys(&self) -> impl Iterator<Item = ChunkKey> + '_ {
        self.chunks.keys().copied()
    }

    /// Starts a use: chunks loaded or inserted until the next tick count as used now.
    pub fn tick(&mut self) -> u64 {
        self.clock += 1;
        self.clock
    }

    /// Makes chunk `key` resident under the current tick (read back if spilled); false when
    /// it does not exist.
    pub fn load(&mut self, key: ChunkKey) -> Result<bool> {
        let now = self.clock;
        match self.chunks.get_mut(&key) {
            None => return Ok(false),
            Some(Slot::Resident(_, t)) => {
                *t = now;
                return Ok(true);
            }
            Some(Slot::Spilled) => {}
        }
        let c = self.read_spilled(key)?;
        self.chunks.insert(key, Slot::Resident(Box::new(c), now));
        self.resident += 1;
        self.stats.reloads += 1;
        self.stats.peak_resident = self.stats.peak_resident.max(self.resident);
        Ok(true)
    }

    /// Adds a new chunk, resident under the current tick (replacing one that exists).
    pub fn insert(&mut self, key: ChunkKey, chunk: C) {
        let now = self.clock;
        match self
            .chunks
            .insert(key, Slot::Resident(Box::new(chunk), now))
        {
            Some(Slot::Resident(..)) => {}
            Some(Slot::Spilled) => self.resident += 1,
            None => {
                self.resident += 1;
                self.stats.chunks += 1;
            }
        }
        self.stats.peak_resident = self.stats.peak_resident.max(self.resident);
    }

    /// A resident chunk.
    pub fn get(&self, key: ChunkKey) -> Option<&C> {
        match self.chunks.get(&key) {
            Some(Slot::Resident(c, _)) => Some(c),
            _ => None,
        }
    }

    pub fn get_mut(&mut self, key: ChunkKey) -> Option<&mut C> {
        match self.chunks.get_mut(&key) {
            Some(Slot::Resident(c, _)) => Some(c),
            _ => None,
        }
    }

    /// The resident chunks among `keys`, mutable at once (for parallel work).
    pub fn resident_mut(&mut self, keys: &[ChunkKey]) -> Vec<(ChunkKey, &mut C)> {
        self.chunks
            .iter_mut()
            .filter_map(|(k, s)| match s {
                Slot::Resident(c, _) if keys.contains(k) => Some((*k, &mut **c)),
                _ => None,
            })
            .collect()
    }

    /// Calls `f` with chunk `key`, resident or read from the spill file without making it
    /// resident; `None` when it does not exist.
    pub fn peek<R>(&self, key: ChunkKey, f: impl FnOnce(&C) -> R) -> Result<Option<R>> {
        match self.chunks.get(&key) {
            None => Ok(None),
            Some(Slot::Resident(c, _)) => Ok(Some(f(c))),
            Some(Slot::Spilled) => Ok(Some(f(&self.read_spilled(key)?))),
        }
    }

    fn read_spilled(&self, key: ChunkKey) -> Result<C> {
        let slot = self.slots.get(&key).copied().ok_or_else(|| StoreError {
            folder: self.file.folder().to_path_buf(),
            action: format!("reading chunk {key:?}"),
            source: std::io::Error::other("the chunk has no slot"),
        })?;
        let mut bytes = vec![0u8; C::BYTES];
        self.file.read_at(slot * C::BYTES as u64, &mut bytes)?;
        Ok(C::decode(&bytes))
    }

    /// While more than the limit are resident, spills the least recently used chunk (the
    /// oldest tick, then the smallest key) that `keep` does not keep.
    pub fn evict(&mut self, keep: impl Fn(ChunkKey) -> bool) -> Result<()> {
        let Some(limit) = self.limit else {
            return Ok(());
        };
        if self.resident <= limit {
            return Ok(());
        }
        let mut victims: Vec<(u64, ChunkKey)> = self
            .chunks
            .iter()
            .filter_map(|(k, s)| match s {
                Slot::Resident(_, t) if !keep(*k) => Some((*t, *k)),
                _ => None,
            })
            .collect();
        victims.sort_unstable();
        let excess = self.resident - limit;
        let mut bytes = Vec::with_capacity(C::BYTES);
        for (_, key) in victims.into_iter().take(excess) {
            let Some(Slot::Resident(c, t)) = self.chunks.remove(&key) else {
                continue;
            };
            let next = self.slots.len() as u64;
            let slot = *self.slots.entry(key).or_insert(next);
            bytes.clear();
            c.encode(&mut bytes);
            if let Err(e) = self.file.write_at(slot * C::BYTES as u64, &bytes) {
                // Kept in memory: nothing is lost, the caller reports the error.
                self.chunks.insert(key, Slot::Resident(c, t));
                return Err(e);
            }
            self.chunks.insert(key, Slot::Spilled);
            self.resident -= 1;
            self.stats.spills += 1;
        }
        Ok(())
    }
}

/// A `rows x cols` matrix written and read by rows: in memory up to `memory_max_bytes`, else in
/// a spill file.
#[derive(Debug)]
pub struct RowStore<T: Element> {
    rows: usize,
    cols: usize,
    mem: Vec<T>,
    file: Option<SpillFile>,
}

impl<T: Element + Default> RowStore<T> {
    /// A zeroed matrix; in a spill file in `folder` (`None`: the system's temporary folder)
    /// when larger than `memory_max_bytes`.
    pub fn new(
        rows: usize,
        cols: usize,
        memory_max_bytes: usize,
        folder: Option<PathBuf>,
    ) -> Result<Self> {
        let bytes = rows.saturating_mul(cols).saturating_mul(T::BYTES);
        if bytes <= memory_max_bytes {
            return Ok(Self {
                rows,
                cols,
                mem: vec![T::default(); rows * cols],
                file: None,
            });
        }
        let mut file = SpillFile::new(folder);
        file.set_len(bytes as u64)?;
        Ok(Self {
            rows,
            cols,
            mem: Vec::new(),
            file: Some(file),
        })
    }
}

impl<T: Element> RowStore<T> {
    pub fn rows(&self) -> usize {
        self.rows
    }

    pub fn cols(&self) -> usize {
        self.cols
    }

    /// Whole rows `r0 ..` from `data`.
    pub fn write_rows(&mut self, r0: usize, data: &[T]) -> Result<()> {
        let at = r0 * self.cols;
        match &mut self.file {
            None => {
                self.mem[at..at + data.len()].copy_from_slice(data);
                Ok(())
            }
            Some(f) => f.write_at((at * T::BYTES) as u64, &encode(data)),
        }
    }

    /// Row `r` into `out` (`cols` long).
    pub fn read_row(&self, r: usize, out: &mut [T]) -> Result<()> {
        let at = r * self.cols;
        match &self.file {
            None => {
                out.copy_from_slice(&self.mem[at..at + self.cols]);
                Ok(())
            }
            Some(f) => {
                let mut bytes = vec![0u8; self.cols * T::BYTES];
                f.read_at((at * T::BYTES) as u64, &mut bytes)?;
                for (o, b) in out.iter_mut().zip(bytes.chunks_exact(T::BYTES)) {
                    *o = T::get(b);
                }
                Ok(())
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, Clone, PartialEq)]
    struct Pair([f32; 2]);

    impl GridChunk for Pair {
        const BYTES: usize = 8;
        fn encode(&self, out: &mut Vec<u8>) {
            out.extend(encode(&self.0));
        }
        fn decode(bytes: &[u8]) -> Self {
            let mut v = Vec::new();
            decode_into::<f32>(bytes, &mut v);
            Pair([v[0], v[1]])
        }
    }

    #[test]
    fn an_append_log_returns_every_block_bit_for_bit() {
        let dir = tempfile::tempdir().expect("temp dir");
        let mut log = AppendLog::<f32>::new(Some(dir.path().join("new/sub")));
        let a = [1.5f32, f32::NAN, -0.0, f32::MIN_POSITIVE];
        let b = [7.25f32; 3];
        let (oa, ob) = (log.append(&a).unwrap(), log.append(&b).unwrap());
        assert_eq!((oa, ob), (0, 16));
        let back = log.read(oa, a.len()).unwrap();
        assert!(back.iter().zip(&a).all(|(x, y)| x.to_bits() == y.to_bits()));
        assert_eq!(log.read(ob, 3).unwrap(), b);
        // Unnamed: the folder holds no file.
        assert_eq!(
            std::fs::read_dir(dir.path().join("new/sub"))
                .unwrap()
                .count(),
            0
        );
    }

    #[test]
    fn errors_name_the_folder_and_the_action() {
        let log = AppendLog::<f64>::new(Some("/nonexistent-spill".into()));
        let e = log.read(0, 1).unwrap_err().to_string();
        assert!(
            e.contains("/nonexistent-spill") && e.contains("reading 8 bytes"),
            "{e}"
        );
        let dir = tempfile::tempdir().expect("temp dir");
        let blocker = dir.path().join("file");
        std::fs::write(&blocker, b"x").unwrap();
        let mut log = AppendLog::<f32>::new(Some(blocker.join("below")));
        let e = log.append(&[1.0]).unwrap_err();
        assert!(
            e.to_string().contains("below") && e.action == "creating",
            "{e}"
        );
        let io: std::io::Error = e.into();
        assert!(io.to_string().contains("spill file in"), "{io}");
    }

    #[test]
    fn a_grid_spills_the_least_recently_used_and_reads_them_back() {
        let dir = tempfile::tempdir().expect("temp dir");
        let mut g = ChunkedGrid::<Pair>::default();
        g.set_limit(Some(2), Some(dir.path().into()));
        for (i, key) in [(0, 0), (1, 0), (-1, 5)].into_iter().enumerate() {
            g.tick();
            g.insert(key, Pair([i as f32, -(i as f32)]));
            g.evict(|k| k == key).unwrap();
        }
        // (0, 0) was the oldest: it went to the file.
        assert_eq!(g.resident_len(), 2);
        assert!(g.get((0, 0)).is_none() && g.has_spilled());
        assert_eq!(
            g.peek((0, 0), |c| c.clone()).unwrap(),
            Some(Pair([0.0, -0.0]))
        );
        g.tick();
        assert!(g.load((0, 0)).unwrap());
        assert!(!g.load((9, 9)).unwrap());
        g.evict(|k| k == (0, 0)).unwrap();
        assert_eq!(g.get((0, 0)), Some(&Pair([0.0, -0.0])));
        assert!(g.get((1, 0)).is_none(), "the least recently used went");
        let s = g.stats();
        assert_eq!(
            (s.chunks, s.peak_resident, s.spills, s.reloads),
            (3, 3, 2, 1)
        );
        let mut keys: Vec<_> = g.keys().collect();
        keys.sort();
        assert_eq!(keys, vec![(-1, 5), (0, 0), (1, 0)]);
    }

    #[test]
    fn a_row_store_in_a_file_equals_one_in_memory() {
        let dir = tempfile::tempdir().expect("temp dir");
        let mut mem = RowStore::<f64>::new(3, 4, 1 << 20, None).unwrap();
        let mut file = RowStore::<f64>::new(3, 4, 0, Some(dir.path().into())).unwrap();
        let data: Vec<f64> = (0..8).map(|i| i as f64 * 0.1 - 0.3).collect();
        mem.write_rows(1, &data).unwrap();
        file.write_rows(1, &data).unwrap();
        for r in 0..3 {
            let (mut a, mut b) = (vec![9.0; 4], vec![9.0; 4]);
            mem.read_row(r, &mut a).unwrap();
            file.read_row(r, &mut b).unwrap();
            assert_eq!(a, b);
        }
    }
}
