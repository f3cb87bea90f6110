//! NumPy `.npy` files: 2-D height maps in and out.
//!
//! Reading accepts format versions 1.0, 2.0 and 3.0 (the header is a Python dict literal with
//! `descr`, `fortran_order` and `shape`), 2-D arrays only, of dtype float32 or float64 in either
//! byte order, and the integer types int8/16/32/64 and uint8/16/32/64 (converted to floating
//! point). Fortran-order (column-major) arrays are transposed on the way in, so the result is
//! always row-major: `data[row * cols + col]`, row index = first axis of the NumPy array.
//!
//! Writing produces exactly what `numpy.save` writes for a C-order little-endian array: format
//! 1.0 (2.0 only if the header would not fit a 1.0 header), the header padded with spaces to a
//! multiple of 64 bytes and ended by `\n`. Files are written atomically
//! ([`surfstream_core::fsutil::write_atomic`]): a reader never sees a half-written file.
//!
//! Every error names the file and what was wrong with it.

use std::io::Write;
use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};
use surfstream_core::fsutil::OutputSet;

/// The magic string every `.npy` file starts with.
const MAGIC: &[u8; 6] = b"\x93NUMPY";
/// Header blocks (magic + version + length + dict) are padded to a multiple of this.
const HEADER_ALIGN: usize = 64;

/// A 2-D array read from a `.npy` file, row-major: element (row, col) is
/// `data[row * cols + col]`.
#[derive(Debug, Clone, PartialEq)]
pub struct NpyArray<T = f32> {
    pub data: Vec<T>,
    pub rows: usize,
    pub cols: usize,
}

impl<T: Copy> NpyArray<T> {
    /// Element (row, col). Panics when out of bounds, like slice indexing.
    pub fn get(&self, row: usize, col: usize) -> T {
        assert!(
            row < self.rows && col < self.cols,
            "index ({row}, {col}) out of bounds"
        );
        self.data[row * self.cols + col]
    }
}

/// Reads a 2-D `.npy` array as f32 (float64 and integer data are converted).
pub fn read_npy(path: impl AsRef<Path>) -> Result<NpyArray<f32>> {
    read_as(path.as_ref())
}

/// Reads a 2-D `.npy` array as f64: float64 data stay exact, float32 and integers are widened.
pub fn read_npy_f64(path: impl AsRef<Path>) -> Result<NpyArray<f64>> {
    read_as(path.as_ref())
}

/// Writes `data` (row-major, `rows * cols` values) as a little-endian float32 `.npy` file.
pub fn write_npy_f32(path: impl AsRef<Path>, data: &[f32], rows: usize, cols: usize) -> Result<()> {
    write_values(None, path.as_ref(), data, rows, cols, |v| v)
}

/// Writes `data` (row-major, `rows * cols` values) as a little-endian float64 `.npy` file.
pub fn write_npy_f64(path: impl AsRef<Path>, data: &[f64], rows: usize, cols: usize) -> Result<()> {
    write_values(None, path.as_ref(), data, rows, cols, |v| v)
}

/// Whether absolute heights `f64::from(z) + z_offset_um` of f32 frame heights `z` are exactly
/// f32 values: with no offset they are the frame's own f32 heights, so a float32 file holds
/// them without loss (half the bytes of float64). With an offset the sum has more digits than
/// an f32 keeps: float64.
pub fn absolute_fits_f32(z_offset_um: f64) -> bool {
    z_offset_um == 0.0
}

/// Writes f32 frame heights as absolute heights: float32 (`<f4`) when they are exactly f32
/// ([`absolute_fits_f32`]: no offset), else float64 `f64::from(z) + z_offset_um` (the values
/// [`surfstream_core::frame::from_frame_heights`] gives), converted as they are written: no
/// f64 copy of the whole raster is made. Either way every reader of ours, and numpy, reads the
/// same absolute heights.
pub fn write_npy_abs(
    path: impl AsRef<Path>,
    data: &[f32],
    rows: usize,
    cols: usize,
    z_offset_um: f64,
) -> Result<()> {
    if absolute_fits_f32(z_offset_um) {
        write_npy_f32(path, data, rows, cols)
    } else {
        write_values(None, path.as_ref(), data, rows, cols, |v| {
            f64::from(v) + z_offset_um
        })
    }
}

// ---------------------------------------------------------------------------------------------
// Writing

/// [`write_npy_f64`] as one file of `set`: it appears with the set's other files on
/// [`OutputSet::commit`].
pub fn write_npy_f64_into(
    set: &mut OutputSet,
    path: impl AsRef<Path>,
    data: &[f64],
    rows: usize,
    cols: usize,
) -> Result<()> {
    write_values(Some(set), path.as_ref(), data, rows, cols, |v| v)
}

/// The float types a file is written in: the dtype its header names and its bytes.
trait NpyFloat: Copy {
    const DESCR: &'static str;
    const IS_F64: bool;
    fn put_le(self, out: &mut Vec<u8>);
}

impl NpyFloat for f32 {
    const DESCR: &'static str = "<f4";
    const IS_F64: bool = false;
    fn put_le(self, out: &mut Vec<u8>) {
        out.extend_from_slice(&self.to_le_bytes())
    }
}

impl NpyFloat for f64 {
    const DESCR: &'static str = "<f8";
    const IS_F64: bool = true;
    fn put_le(self, out: &mut Vec<u8>) {
        out.extend_from_slice(&self.to_le_bytes())
    }
}

/// The `numpy.save` header dict of a C-order `rows x cols` array of `descr`.
fn header_dict(descr: &str, rows: usize, cols: usize) -> String {
    format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': ({rows}, {cols}), }}")
}

/// Writes `value(v)` of every value of `data` as an `E` array, atomically on its own or into
/// `set`: the one body of every whole-array writer, so the header's dtype and the bytes written
/// cannot disagree.
fn write_values<T: Copy, E: NpyFloat>(
    set: Option<&mut OutputSet>,
    path: &Path,
    data: &[T],
    rows: usize,
    cols: usize,
    value: impl Fn(T) -> E,
) -> Result<()> {
    let expected = rows.checked_mul(cols);
    if expected != Some(data.len()) {
        bail!(
            "{}: cannot write {rows} x {cols} array: got {} values, expected {}",
            path.display(),
            data.len(),
            rows as u128 * cols as u128
        );
    }
    let header = header_block(&header_dict(E::DESCR, rows, cols));
    let fill = |w: &mut std::io::BufWriter<std::fs::File>| {
        w.write_all(&header)
            .with_context(|| format!("{}: write failed", path.display()))?;
        let mut buf = Vec::with_capacity(8192 * 8);
        for (k, chunk) in data.chunks(8192).enumerate() {
            if k % 4096 == 0 {
                surfstream_core::liveness::beat();
            }
            buf.clear();
            for &v in chunk {
                value(v).put_le(&mut buf);
            }
            w.write_all(&buf)
                .with_context(|| format!("{}: write failed", path.display()))?;
        }
        Ok(())
    };
    match set {
        Some(set) => set.write(path, fill),
        None => surfstream_core::fsutil::write_atomic(path, fill),
    }
}

/// Magic, version, header length and the padded dict: version 1.0 when the header fits its
/// 16-bit length field, 2.0 otherwise (as numpy does).
fn header_block(dict: &str) -> Vec<u8> {
    let padded_len = |prefix: usize| {
        let unpadded = prefix + dict.len() + 1; // + '\n'
        unpadded.div_ceil(HEADER_ALIGN) * HEADER_ALIGN - prefix
    };
    let v1_len = padded_len(MAGIC.len() + 2 + 2);
    let (version, header_len) = if v1_len <= u16::MAX as usize {
        (1u8, v1_len)
    } else {
        (2u8, padded_len(MAGIC.len() + 4 + 2))
    };
    let mut out = Vec::with_capacity(header_len + 12);
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&[version, 0]);
    if version == 1 {
        out.extend_from_slice(&(header_len as u16).to_le_bytes());
    } else {
        out.extend_from_slice(&(header_len as u32).to_le_bytes());
    }
    out.extend_from_slice(dict.as_bytes());
    out.resize(out.len() + header_len - dict.len() - 1, b' ');
    out.push(b'\n');
    out
}

/// Writes a 2-D `.npy` file row by row, for maps that are never whole in memory: the same
/// bytes as [`write_npy_f32`] / [`write_npy_f64`] / [`write_npy_abs`] give. The data go to
/// `<path>.partial`, renamed into place by [`NpyRowWriter::finish`] once every row arrived;
/// dropped unfinished (an error on the way), the partial file is removed: a reader never sees
/// a half-written file.
#[derive(Debug)]
pub struct NpyRowWriter {
    path: std::path::PathBuf,
    tmp: std::path::PathBuf,
    out: Option<std::io::BufWriter<std::fs::File>>,
    rows: usize,
    cols: usize,
    rows_written: usize,
    /// float64 (else float32).
    f64: bool,
    buf: Vec<u8>,
    /// Bytes handed to the file so far, and up to where its write-back was started
    /// ([`surfstream_core::fsutil::start_writeback`]); `None`: write-back left to the kernel.
    bytes_written: u64,
    writeback_from: Option<u64>,
}

impl NpyRowWriter {
    /// A float32 file of `rows x cols` (rows go in with [`NpyRowWriter::push_f32`]).
    pub fn create_f32(path: impl AsRef<Path>, rows: usize, cols: usize) -> Result<Self> {
        Self::create(path.as_ref(), rows, cols, false)
    }

    /// A float64 file of `rows x cols` ([`NpyRowWriter::push_abs_f64`] or
    /// [`NpyRowWriter::push_f64`]).
    pub fn create_f64(path: impl AsRef<Path>, rows: usize, cols: usize) -> Result<Self> {
        Self::create(path.as_ref(), rows, cols, true)
    }

    /// A file of absolute heights from f32 frame heights relative to `z_offset_um`
    /// (rows go in with [`NpyRowWriter::push_abs`]): float32 when no offset is added
    /// ([`absolute_fits_f32`]), else float64; the bytes of [`write_npy_abs`].
    pub fn create_abs(
        path: impl AsRef<Path>,
        rows: usize,
        cols: usize,
        z_offset_um: f64,
    ) -> Result<Self> {
        Self::create(path.as_ref(), rows, cols, !absolute_fits_f32(z_offset_um))
    }

    fn create(path: &Path, rows: usize, cols: usize, f64: bool) -> Result<Self> {
        if rows == 0 || cols == 0 || rows.checked_mul(cols).is_none() {
            bail!("{}: cannot write a {rows} x {cols} array", path.display());
        }
        if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
            std::fs::create_dir_all(parent)
                .with_context(|| format!("{}: cannot create the folder", parent.display()))?;
        }
        let tmp = surfstream_core::fsutil::partial_path(path);
        let file = std::fs::File::create(&tmp)
            .with_context(|| format!("{}: cannot create", tmp.display()))?;
        let mut w = Self {
            path: path.to_path_buf(),
            tmp,
            out: Some(std::io::BufWriter::with_capacity(1 << 20, file)),
            rows,
            cols,
            rows_written: 0,
            f64,
            buf: Vec::new(),
            bytes_written: 0,
            writeback_from: Some(0),
        };
        let descr = if f64 { f64::DESCR } else { f32::DESCR };
        let header = header_block(&header_dict(descr, rows, cols));
        w.write(&header)?;
        Ok(w)
    }

    /// Whole rows of f32 values (float32 files).
    pub fn push_f32(&mut self, values: &[f32]) -> Result<()> {
        self.push_values(values, |v| v)
    }

    /// Whole rows of f32 frame heights written as absolute float64 heights,
    /// `f64::from(z) + z_offset_um` (float64 files; as [`write_npy_abs`] with an offset).
    pub fn push_abs_f64(&mut self, values: &[f32], z_offset_um: f64) -> Result<()> {
        self.push_values(values, |v| f64::from(v) + z_offset_um)
    }

    /// Whole rows of f32 frame heights as absolute heights into a file made by
    /// [`NpyRowWriter::create_abs`] with the same `z_offset_um`.
    pub fn push_abs(&mut self, values: &[f32], z_offset_um: f64) -> Result<()> {
        if self.f64 {
            self.push_abs_f64(values, z_offset_um)
        } else if absolute_fits_f32(z_offset_um) {
            self.push_f32(values)
        } else {
            bail!(
                "{}: heights with an offset of {z_offset_um} um pushed into a float32 file made for no offset",
                self.path.display()
            )
        }
    }

    /// Whole rows of f64 values (float64 files).
    pub fn push_f64(&mut self, values: &[f64]) -> Result<()> {
        self.push_values(values, |v| v)
    }

    /// Whole rows of `value(v)`, into a file of `E`'s dtype: the one body of every push.
    fn push_values<T: Copy, E: NpyFloat>(
        &mut self,
        values: &[T],
        value: impl Fn(T) -> E,
    ) -> Result<()> {
        self.check(values.len(), E::IS_F64)?;
        self.buf.clear();
        for &v in values {
            value(v).put_le(&mut self.buf);
        }
        self.flush_buf(values.len())
    }

    fn check(&self, n: usize, f64: bool) -> Result<()> {
        if f64 != self.f64 {
            bail!(
                "{}: {} values pushed into a {} file",
                self.path.display(),
                if f64 { "float64" } else { "float32" },
                if self.f64 { "float64" } else { "float32" }
            );
        }
        if !n.is_multiple_of(self.cols) || self.rows_written + n / self.cols > self.rows {
            bail!(
                "{}: {n} values are not whole rows of {} within the {} x {} array ({} rows written)",
                self.path.display(),
                self.cols,
                self.rows,
                self.cols,
                self.rows_written
            );
        }
        Ok(())
    }

    fn flush_buf(&mut self, n: usize) -> Result<()> {
        let buf = std::mem::take(&mut self.buf);
        let r = self.write(&buf);
        self.buf = buf;
        r?;
        self.rows_written += n / self.cols;
        Ok(())
    }

    fn write(&mut self, bytes: &[u8]) -> Result<()> {
        let out = self
            .out
            .as_mut()
            .ok_or_else(|| anyhow!("{}: already finished", self.path.display()))?;
        out.write_all(bytes)
            .with_context(|| format!("{}: write failed", self.tmp.display()))?;
        self.bytes_written += bytes.len() as u64;
        // The data reach the disk while the rows are still being computed: the sync at the
        // end then waits for the last few MiB only.
        if let Some(from) = self.writeback_from {
            let in_file = self.bytes_written - out.buffer().len() as u64;
            if in_file >= from + surfstream_core::fsutil::WRITEBACK_CHUNK_BYTES {
                surfstream_core::fsutil::start_writeback(out.get_ref(), from, in_file - from);
                self.writeback_from = Some(in_file);
            }
        }
        Ok(())
    }

    /// Leaves the write-back to the kernel's own schedule (outputs that are never synced:
    /// [`surfstream_core::fsutil::Durability::NoSync`]); by default it is started every
    /// [`surfstream_core::fsutil::WRITEBACK_CHUNK_BYTES`] written.
    pub fn without_writeback(mut self) -> Self {
        self.writeback_from = None;
        self
    }

    /// Rows written so far.
    pub fn rows_written(&self) -> usize {
        self.rows_written
    }

    /// Checks that every row arrived, then moves the file into place.
    pub fn finish(mut self) -> Result<()> {
        let out = self.complete()?;
        let result = (|| {
            let file = out
                .into_inner()
                .map_err(|e| anyhow!("{}: write failed: {e}", self.tmp.display()))?;
            file.sync_all().ok();
            drop(file);
            std::fs::rename(&self.tmp, &self.path)
                .with_context(|| format!("{}: cannot rename into place", self.path.display()))
        })();
        if result.is_err() {
            let _ = std::fs::remove_file(&self.tmp);
        }
        result
    }
}

impl NpyRowWriter {
    /// The buffered file, once every row arrived.
    fn complete(&mut self) -> Result<std::io::BufWriter<std::fs::File>> {
        if self.rows_written != self.rows {
            bail!(
                "{}: {} of {} rows written",
                self.path.display(),
                self.rows_written,
                self.rows
            );
        }
        self.out
            .take()
            .ok_or_else(|| anyhow!("{}: already finished", self.path.display()))
    }

    /// Checks that every row arrived and hands the file to `set`, which moves it into place
    /// with the set's other files ([`OutputSet::commit`]).
    pub fn finish_into(mut self, set: &mut OutputSet) -> Result<()> {
        let out = self.complete()?;
        match out.into_inner() {
            Ok(file) => {
                set.stage(self.tmp.clone(), self.path.clone(), file);
                Ok(())
            }
            Err(e) => {
                let _ = std::fs::remove_file(&self.tmp);
                bail!("{}: write failed: {e}", self.tmp.display())
            }
        }
    }
}

impl Drop for NpyRowWriter {
    fn drop(&mut self) {
        // Unfinished: no half-written file stays behind.
        if self.out.take().is_some() {
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Reading

/// Element types a file can be read into.
trait Element: Copy {
    fn from_f32(v: f32) -> Self;
    fn from_f64(v: f64) -> Self;
    fn from_i64(v: i64) -> Self;
    fn from_u64(v: u64) -> Self;
}

impl Element for f32 {
    fn from_f32(v: f32) -> Self {
        v
    }
    fn from_f64(v: f64) -> Self {
        v as f32
    }
    fn from_i64(v: i64) -> Self {
        v as f32
    }
    fn from_u64(v: u64) -> Self {
        v as f32
    }
}

impl Element for f64 {
    fn from_f32(v: f32) -> Self {
        v as f64
    }
    fn from_f64(v: f64) -> Self {
        v
    }
    fn from_i64(v: i64) -> Self {
        v as f64
    }
    fn from_u64(v: u64) -> Self {
        v as f64
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    Float,
    Int,
    Uint,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Dtype {
    kind: Kind,
    size: usize,
    big_endian: bool,
}

/// What the header says.
#[derive(Debug)]
struct Header {
    dtype: Dtype,
    fortran_order: bool,
    rows: usize,
    cols: usize,
    /// Offset of the first data byte.
    data_offset: usize,
}

/// The start of a header for an error message: a corrupt file's "header" can be 150 KB of
/// binary, which nobody wants echoed to the terminal.
fn excerpt(text: &str) -> String {
    const MAX_CHARS: usize = 80;
    let trimmed = text.trim();
    let total = trimmed.chars().count();
    if total <= MAX_CHARS {
        format!("{trimmed:?}")
    } else {
        let head: String = trimmed.chars().take(MAX_CHARS).collect();
        format!("{head:?}... ({total} characters in all)")
    }
}

/// Opens `path` and reads and parses its header only: the file positioned at the data, its
/// length, the header.
fn open_header(path: &Path) -> Result<(std::fs::File, u64, Header)> {
    use std::io::Read;
    let mut file =
        std::fs::File::open(path).with_context(|| format!("{}: cannot read", path.display()))?;
    let len = file
        .metadata()
        .with_context(|| format!("{}: cannot read", path.display()))?
        .len();
    // Magic, version and the header length, then the whole header.
    let mut head = vec![0u8; 12.min(len as usize)];
    file.read_exact(&mut head)
        .with_context(|| format!("{}: cannot read", path.display()))?;
    let header_len = match head.get(6) {
        Some(1) => head
            .get(8..10)
            .map(|b| u16::from_le_bytes([b[0], b[1]]) as usize + 10),
        Some(2 | 3) => head
            .get(8..12)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize + 12),
        _ => None,
    };
    let mut bytes = head;
    if let Some(total) = header_len.filter(|&t| t as u64 <= len && t > bytes.len()) {
        let mut rest = vec![0u8; total - bytes.len()];
        file.read_exact(&mut rest)
            .with_context(|| format!("{}: cannot read", path.display()))?;
        bytes.extend_from_slice(&rest);
    }
    let header = parse_header(&bytes).map_err(|e| anyhow!("{}: {e}", path.display()))?;
    Ok((file, len, header))
}

/// The common case read without a copy: a C-order little-endian array of exactly `T`'s
/// float type, of the right length, read straight into its values. `None` for any other file
/// (the general path then reads it, or names what is wrong with it).
fn read_native<T: Element>(path: &Path) -> Result<Option<NpyArray<T>>> {
    use std::io::Read;
    if cfg!(target_endian = "big") {
        return Ok(None);
    }
    let Ok((mut file, len, header)) = open_header(path) else {
        return Ok(None);
    };
    let (rows, cols) = (header.rows, header.cols);
    let n = rows * cols; // checked in parse_header
    let native = header.dtype.kind == Kind::Float
        && header.dtype.size == std::mem::size_of::<T>()
        && !header.dtype.big_endian
        && !(header.fortran_order && rows > 1 && cols > 1)
        && len.checked_sub(header.data_offset as u64) == Some((n * header.dtype.size) as u64);
    if !native {
        return Ok(None);
    }
    let mut data = vec![T::from_f32(0.0); n];
    // SAFETY: T is f32 or f64 (the only Element types whose size matches a float dtype), plain
    // values for which every bit pattern is valid; the byte view covers exactly `data`.
    let bytes = unsafe {
        std::slice::from_raw_parts_mut(
            data.as_mut_ptr().cast::<u8>(),
            std::mem::size_of_val(&data[..]),
        )
    };
    file.read_exact(bytes)
        .with_context(|| format!("{}: cannot read", path.display()))?;
    Ok(Some(NpyArray { data, rows, cols }))
}

fn read_as<T: Element>(path: &Path) -> Result<NpyArray<T>> {
    if let Some(a) = read_native(path)? {
        return Ok(a);
    }
    let bytes = std::fs::read(path).with_context(|| format!("{}: cannot read", path.display()))?;
    let header = parse_header(&bytes).map_err(|e| anyhow!("{}: {e}", path.display()))?;
    let Header {
        dtype,
        fortran_order,
        rows,
        cols,
        data_offset,
    } = header;
    let n = rows * cols; // checked in parse_header
    let expected_bytes = n * dtype.size;
    let found = bytes.len() - data_offset;
    if found < expected_bytes {
        bail!(
            "{}: truncated: expected {expected_bytes} bytes of data for a {rows} x {cols} array, \
             found {found}",
            path.display()
        );
    }
    if found > expected_bytes {
        bail!(
            "{}: {} unexpected bytes after the data of a {rows} x {cols} array \
             (expected {expected_bytes} bytes of data, found {found})",
            path.display(),
            found - expected_bytes
        );
    }
    let raw = &bytes[data_offset..];
    let values: Vec<T> = decode(raw, dtype)
        .ok_or_else(|| anyhow!("{}: unsupported dtype {dtype:?}", path.display()))?;
    let data = if fortran_order && rows > 1 && cols > 1 {
        // Column-major storage: element (r, c) sits at c * rows + r.
        let mut out = Vec::with_capacity(n);
        for r in 0..rows {
            out.extend((0..cols).map(|c| values[c * rows + r]));
        }
        out
    } else {
        values
    };
    Ok(NpyArray { data, rows, cols })
}

fn decode<T: Element>(raw: &[u8], dtype: Dtype) -> Option<Vec<T>> {
    fn conv<T, const N: usize>(raw: &[u8], big: bool, f: impl Fn([u8; N], bool) -> T) -> Vec<T> {
        raw.chunks_exact(N)
            .map(|c| {
                let mut a = [0u8; N];
                a.copy_from_slice(c);
                f(a, big)
            })
            .collect()
    }
    macro_rules! num {
        ($t:ty, $into:ident, $via:ty) => {
            conv(raw, dtype.big_endian, |a, big| {
                let v = if big {
                    <$t>::from_be_bytes(a)
                } else {
                    <$t>::from_le_bytes(a)
                };
                T::$into(v as $via)
            })
        };
    }
    Some(match (dtype.kind, dtype.size) {
        (Kind::Float, 4) => num!(f32, from_f32, f32),
        (Kind::Float, 8) => num!(f64, from_f64, f64),
        (Kind::Int, 1) => num!(i8, from_i64, i64),
        (Kind::Int, 2) => num!(i16, from_i64, i64),
        (Kind::Int, 4) => num!(i32, from_i64, i64),
        (Kind::Int, 8) => num!(i64, from_i64, i64),
        (Kind::Uint, 1) => num!(u8, from_u64, u64),
        (Kind::Uint, 2) => num!(u16, from_u64, u64),
        (Kind::Uint, 4) => num!(u32, from_u64, u64),
        (Kind::Uint, 8) => num!(u64, from_u64, u64),
        // parse_dtype only lets the combinations above through.
        _ => return None,
    })
}

/// Parses magic, version and the header dict; the error text is prefixed with the path by the
/// caller.
fn parse_header(bytes: &[u8]) -> std::result::Result<Header, String> {
    if bytes.len() < MAGIC.len() || &bytes[..MAGIC.len()] != MAGIC {
        return Err("not a .npy file (bad magic: expected \\x93NUMPY at the start)".into());
    }
    let (major, minor) = match bytes.get(6..8) {
        Some(&[major, minor]) => (major, minor),
        _ => return Err("truncated: the file ends inside the .npy preamble".into()),
    };
    let (len_size, utf8) = match major {
        1 => (2, false),
        2 => (4, false),
        3 => (4, true),
        _ => {
            return Err(format!(
                "unsupported .npy format version {major}.{minor} (expected 1.0, 2.0 or 3.0)"
            ))
        }
    };
    let len_bytes = bytes
        .get(8..8 + len_size)
        .ok_or_else(|| "truncated: the file ends inside the .npy preamble".to_string())?;
    let header_len = if len_size == 2 {
        u16::from_le_bytes([len_bytes[0], len_bytes[1]]) as usize
    } else {
        u32::from_le_bytes([len_bytes[0], len_bytes[1], len_bytes[2], len_bytes[3]]) as usize
    };
    let start = 8 + len_size;
    let data_offset = start + header_len;
    let raw = bytes.get(start..data_offset).ok_or_else(|| {
        format!(
            "truncated: the header says it is {header_len} bytes long but the file ends after {}",
            bytes.len().saturating_sub(start)
        )
    })?;
    let text: String = if utf8 {
        String::from_utf8(raw.to_vec())
            .map_err(|_| "the version 3.0 header is not valid UTF-8".to_string())?
    } else {
        raw.iter().map(|&b| b as char).collect() // latin-1
    };
    let dict = match PyParser::new(&text).parse_top() {
        Ok(PyValue::Dict(d)) => d,
        Ok(_) => return Err(format!("the header is not a dict: {}", excerpt(&text))),
        Err(e) => return Err(format!("cannot parse the header {}: {e}", excerpt(&text))),
    };
    let get = |key: &str| {
        dict.iter()
            .find(|(k, _)| matches!(k, PyValue::Str(s) if s == key))
            .map(|(_, v)| v)
    };
    let descr = get("descr").ok_or("the header has no 'descr' key")?;
    let dtype = match descr {
        PyValue::Str(s) => parse_dtype(s)?,
        other => {
            return Err(format!(
                "unsupported dtype {} (expected float32 or float64)",
                other.to_python()
            ))
        }
    };
    let fortran_order = match get("fortran_order").ok_or("the header has no 'fortran_order' key")? {
        PyValue::Bool(b) => *b,
        other => {
            return Err(format!(
                "'fortran_order' is {} (expected True or False)",
                other.to_python()
            ))
        }
    };
    let shape_value = get("shape").ok_or("the header has no 'shape' key")?;
    let shape: Vec<u64> = match shape_value {
        PyValue::Tuple(items) => items
            .iter()
            .map(|v| match v {
                PyValue::Int(n) => Ok(*n),
                _ => Err(format!(
                    "'shape' is {} (expected a tuple of integers)",
                    shape_value.to_python()
                )),
            })
            .collect::<std::result::Result<_, _>>()?,
        _ => {
            return Err(format!(
                "'shape' is {} (expected a tuple)",
                shape_value.to_python()
            ))
        }
    };
    if shape.len() != 2 {
        return Err(format!(
            "not 2-D (shape {}): a height map needs a 2-D array (rows, cols)",
            shape_value.to_python()
        ));
    }
    let too_big = || format!("shape {} is too large", shape_value.to_python());
    let rows = usize::try_from(shape[0]).map_err(|_| too_big())?;
    let cols = usize::try_from(shape[1]).map_err(|_| too_big())?;
    rows.checked_mul(cols)
        .and_then(|n| n.checked_mul(dtype.size))
        .ok_or_else(too_big)?;
    Ok(Header {
        dtype,
        fortran_order,
        rows,
        cols,
        data_offset,
    })
}

fn parse_dtype(descr: &str) -> std::result::Result<Dtype, String> {
    let unsupported = || {
        format!(
            "unsupported dtype \"{descr}\" (expected float32 or float64; \
             8- to 64-bit integer types are converted too)"
        )
    };
    let (order, rest) = match descr.chars().next() {
        Some(c @ ('<' | '>' | '|' | '=')) => (c, &descr[1..]),
        _ => ('=', descr),
    };
    let mut chars = rest.chars();
    let kind = match chars.next() {
        Some('f') => Kind::Float,
        Some('i') => Kind::Int,
        Some('u') => Kind::Uint,
        _ => return Err(unsupported()),
    };
    let size: usize = chars.as_str().parse().map_err(|_| unsupported())?;
    let ok = match kind {
        Kind::Float => matches!(size, 4 | 8),
        Kind::Int | Kind::Uint => matches!(size, 1 | 2 | 4 | 8),
    };
    if !ok || (order == '|' && size != 1) {
        return Err(unsupported());
    }
    let big_endian = match order {
        '>' => true,
        '<' | '|' => false,
        _ => cfg!(target_endian = "big"),
    };
    Ok(Dtype {
        kind,
        size,
        big_endian,
    })
}

// ---------------------------------------------------------------------------------------------
// The header dict: a small parser for the Python literals numpy writes.

#[derive(Debug, Clone, PartialEq)]
enum PyValue {
    Str(String),
    Int(u64),
    Bool(bool),
    None,
    Tuple(Vec<PyValue>),
    List(Vec<PyValue>),
    Dict(Vec<(PyValue, PyValue)>),
}

impl PyValue {
    /// Python-like text, for error messages.
    fn to_python(&self) -> String {
        let join = |items: &[PyValue]| items.iter().map(|v| v.to_python()).collect::<Vec<_>>();
        match self {
            PyValue::Str(s) => format!("'{s}'"),
            PyValue::Int(n) => n.to_string(),
            PyValue::Bool(true) => "True".into(),
            PyValue::Bool(false) => "False".into(),
            PyValue::None => "None".into(),
            PyValue::Tuple(items) if items.len() == 1 => format!("({},)", items[0].to_python()),
            PyValue::Tuple(items) => format!("({})", join(items).join(", ")),
            PyValue::List(items) => format!("[{}]", join(items).join(", ")),
            PyValue::Dict(items) => format!(
                "{{{}}}",
                items
                    .iter()
                    .map(|(k, v)| format!("{}: {}", k.to_python(), v.to_python()))
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        }
    }
}

struct PyParser<'a> {
    s: &'a [u8],
    pos: usize,
    depth: usize,
}

impl<'a> PyParser<'a> {
    fn new(text: &'a str) -> Self {
        Self {
            s: text.as_bytes(),
            pos: 0,
            depth: 0,
        }
    }

    fn parse_top(&mut self) -> std::result::Result<PyValue, String> {
        let v = self.value()?;
        self.skip_ws();
        if self.pos != self.s.len() {
            return Err(format!("unexpected text at byte {}", self.pos));
        }
        Ok(v)
    }

    fn skip_ws(&mut self) {
        while self.pos < self.s.len() && self.s[self.pos].is_ascii_whitespace() {
            self.pos += 1;
        }
    }

    fn peek(&mut self) -> Option<u8> {
        self.skip_ws();
        self.s.get(self.pos).copied()
    }

    fn expect(&mut self, c: u8) -> std::result::Result<(), String> {
        if self.peek() == Some(c) {
            self.pos += 1;
            Ok(())
        } else {
            Err(format!("expected '{}' at byte {}", c as char, self.pos))
        }
    }

    fn value(&mut self) -> std::result::Result<PyValue, String> {
        self.depth += 1;
        if self.depth > 32 {
            return Err("nested too deeply".into());
        }
        let v = match self.peek() {
            Some(b'{') => self.dict(),
            Some(b'(') => self.sequence(b'(', b')').map(PyValue::Tuple),
            Some(b'[') => self.sequence(b'[', b']').map(PyValue::List),
            Some(q @ (b'\'' | b'"')) => self.string(q),
            Some(c) if c.is_ascii_digit() => self.int(),
            Some(c) if c.is_ascii_alphabetic() => self.word(),
            Some(c) => Err(format!("unexpected '{}' at byte {}", c as char, self.pos)),
            None => Err("unexpected end of header".into()),
        };
        self.depth -= 1;
        v
    }

    fn dict(&mut self) -> std::result::Result<PyValue, String> {
        self.expect(b'{')?;
        let mut items = Vec::new();
        loop {
            if self.peek() == Some(b'}') {
                self.pos += 1;
                return Ok(PyValue::Dict(items));
            }
            let k = self.value()?;
            self.expect(b':')?;
            let v = self.value()?;
            items.push((k, v));
            match self.peek() {
                Some(b',') => self.pos += 1,
                Some(b'}') => {}
                _ => return Err(format!("expected ',' or '}}' at byte {}", self.pos)),
            }
        }
    }

    fn sequence(&mut self, open: u8, close: u8) -> std::result::Result<Vec<PyValue>, String> {
        self.expect(open)?;
        let mut items = Vec::new();
        loop {
            if self.peek() == Some(close) {
                self.pos += 1;
                return Ok(items);
            }
            items.push(self.value()?);
            match self.peek() {
                Some(b',') => self.pos += 1,
                Some(c) if c == close => {}
                _ => {
                    return Err(format!(
                        "expected ',' or '{}' at byte {}",
                        close as char, self.pos
                    ))
                }
            }
        }
    }

    fn string(&mut self, quote: u8) -> std::result::Result<PyValue, String> {
        self.pos += 1;
        let mut out = Vec::new();
        while let Some(&c) = self.s.get(self.pos) {
            self.pos += 1;
            if c == quote {
                return Ok(PyValue::Str(String::from_utf8_lossy(&out).into_owned()));
            }
            if c == b'\\' {
                match self.s.get(self.pos) {
                    Some(&e) => {
                        out.push(e);
                        self.pos += 1;
                    }
                    None => break,
                }
            } else {
                out.push(c);
            }
        }
        Err("unterminated string".into())
    }

    fn int(&mut self) -> std::result::Result<PyValue, String> {
        let start = self.pos;
        while self.pos < self.s.len() && self.s[self.pos].is_ascii_digit() {
            self.pos += 1;
        }
        let digits = std::str::from_utf8(&self.s[start..self.pos]).map_err(|e| e.to_string())?;
        let n: u64 = digits
            .parse()
            .map_err(|_| format!("integer {digits} is too large"))?;
        // Python 2 era files write longs as `3L`.
        if matches!(self.s.get(self.pos), Some(b'L' | b'l')) {
            self.pos += 1;
        }
        Ok(PyValue::Int(n))
    }

    fn word(&mut self) -> std::result::Result<PyValue, String> {
        let start = self.pos;
        while self.pos < self.s.len()
            && (self.s[self.pos].is_ascii_alphanumeric() || self.s[self.pos] == b'_')
        {
            self.pos += 1;
        }
        match &self.s[start..self.pos] {
            b"True" => Ok(PyValue::Bool(true)),
            b"False" => Ok(PyValue::Bool(false)),
            b"None" => Ok(PyValue::None),
            w => Err(format!(
                "unexpected word '{}' at byte {start}",
                String::from_utf8_lossy(w)
            )),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn row_writer_writes_the_same_bytes_and_nothing_half_written() {
        let dir = tempfile::tempdir().unwrap();
        let (rows, cols) = (5, 3);
        let v: Vec<f32> = (0..15).map(|i| i as f32 * 0.37 - 2.0).collect();
        let mut v2 = v.clone();
        v2[4] = f32::NAN;
        write_npy_f32(dir.path().join("a.npy"), &v2, rows, cols).unwrap();
        write_npy_abs(dir.path().join("b.npy"), &v2, rows, cols, 123.25).unwrap();
        let f64s: Vec<f64> = v.iter().map(|&x| f64::from(x) / 3.0).collect();
        write_npy_f64(dir.path().join("c.npy"), &f64s, rows, cols).unwrap();
        let mut a = NpyRowWriter::create_f32(dir.path().join("a2.npy"), rows, cols).unwrap();
        let mut b = NpyRowWriter::create_f64(dir.path().join("b2.npy"), rows, cols).unwrap();
        let mut c = NpyRowWriter::create_f64(dir.path().join("c2.npy"), rows, cols).unwrap();
        // Uneven pieces of whole rows.
        for (r0, r1) in [(0, 2), (2, 3), (3, 5)] {
            a.push_f32(&v2[r0 * cols..r1 * cols]).unwrap();
            b.push_abs_f64(&v2[r0 * cols..r1 * cols], 123.25).unwrap();
            c.push_f64(&f64s[r0 * cols..r1 * cols]).unwrap();
        }
        assert!(!dir.path().join("a2.npy").exists());
        a.finish().unwrap();
        b.finish().unwrap();
        c.finish().unwrap();
        for (x, y) in [
            ("a.npy", "a2.npy"),
            ("b.npy", "b2.npy"),
            ("c.npy", "c2.npy"),
        ] {
            let read = |n: &str| std::fs::read(dir.path().join(n)).unwrap();
            assert_eq!(read(x), read(y), "{y}");
        }
        // Part rows, too many rows, the wrong type: errors.
        let mut d = NpyRowWriter::create_f32(dir.path().join("d.npy"), rows, cols).unwrap();
        assert!(d.push_f32(&v[..2]).is_err());
        assert!(d.push_f64(&f64s[..3]).is_err());
        assert!(d.push_f32(&[0.0; 18]).is_err());
        d.push_f32(&v[..3]).unwrap();
        // Unfinished: finish refuses, and nothing stays behind.
        let e = d.finish().unwrap_err();
        assert!(format!("{e:#}").contains("1 of 5 rows"), "{e:#}");
        let mut e = NpyRowWriter::create_f32(dir.path().join("e.npy"), rows, cols).unwrap();
        e.push_f32(&v[..3]).unwrap();
        drop(e);
        let names: Vec<String> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.starts_with('d') || n.starts_with('e'))
            .collect();
        assert!(names.is_empty(), "{names:?}");
    }

    fn tmp() -> tempfile::TempDir {
        tempfile::tempdir().expect("tempdir")
    }

    /// A .npy file built by hand (version, dict, raw data bytes), padded like numpy does.
    fn raw_npy(version: u8, dict: &str, data: &[u8]) -> Vec<u8> {
        let prefix = if version == 1 { 10 } else { 12 };
        let total = (prefix + dict.len() + 1).div_ceil(64) * 64;
        let hlen = total - prefix;
        let mut out = MAGIC.to_vec();
        out.extend_from_slice(&[version, 0]);
        if version == 1 {
            out.extend_from_slice(&(hlen as u16).to_le_bytes());
        } else {
            out.extend_from_slice(&(hlen as u32).to_le_bytes());
        }
        out.extend_from_slice(dict.as_bytes());
        out.resize(out.len() + hlen - dict.len() - 1, b' ');
        out.push(b'\n');
        out.extend_from_slice(data);
        out
    }

    fn write(dir: &tempfile::TempDir, name: &str, bytes: &[u8]) -> std::path::PathBuf {
        let p = dir.path().join(name);
        std::fs::write(&p, bytes).expect("write fixture");
        p
    }

    fn err_text(r: Result<impl std::fmt::Debug>) -> String {
        format!("{:#}", r.expect_err("expected an error"))
    }

    #[test]
    fn a_huge_binary_header_is_not_echoed_and_the_path_is_named_once() {
        let dir = tmp();
        let junk: String = (0..160_000)
            .map(|i| char::from(b'!' + (i % 90) as u8))
            .collect();
        let p = write(&dir, "junk.npy", &raw_npy(2, &junk, &[]));
        let e = err_text(crate::formats::read_surface(&p));
        assert!(e.len() < 400, "{} characters: {}", e.len(), &e[..400]);
        assert!(e.contains("characters in all"), "{e}");
        assert_eq!(e.matches("junk.npy").count(), 1, "{e}");
    }

    #[test]
    fn f32_round_trip_is_bit_exact_and_matches_numpy_layout() {
        let dir = tmp();
        let p = dir.path().join("a.npy");
        let data: Vec<f32> = vec![
            0.0,
            -1.5,
            f32::NAN,
            f32::INFINITY,
            1e-38,
            3.25,
            f32::MIN_POSITIVE,
            -0.0,
            7.0,
        ];
        write_npy_f32(&p, &data, 3, 3).expect("write");
        let bytes = std::fs::read(&p).expect("read back");
        // What numpy.save writes for np.zeros((3, 3), '<f4'): a 128-byte header block.
        let dict = b"{'descr': '<f4', 'fortran_order': False, 'shape': (3, 3), }";
        assert_eq!(&bytes[..8], b"\x93NUMPY\x01\x00");
        assert_eq!(u16::from_le_bytes([bytes[8], bytes[9]]), 118);
        assert_eq!(&bytes[10..10 + dict.len()], dict);
        assert_eq!(bytes[127], b'\n');
        assert_eq!(bytes.len(), 128 + 9 * 4);
        let a = read_npy(&p).expect("read");
        assert_eq!((a.rows, a.cols), (3, 3));
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&a.data), bits(&data));
        assert!(!dir.path().join("a.npy.partial").exists());
    }

    #[test]
    fn f64_round_trip_is_exact() {
        let dir = tmp();
        let p = dir.path().join("b.npy");
        let data: Vec<f64> = (0..12).map(|i| 1.0e4 + i as f64 * 0.1 + 1e-9).collect();
        write_npy_f64(&p, &data, 4, 3).expect("write");
        let a = read_npy_f64(&p).expect("read");
        assert_eq!((a.rows, a.cols), (4, 3));
        assert_eq!(a.data, data);
        assert_eq!(a.get(3, 2), data[11]);
        // The f32 reader converts.
        let b = read_npy(&p).expect("read f32");
        assert_eq!(b.data, data.iter().map(|&v| v as f32).collect::<Vec<_>>());
    }

    #[test]
    fn write_rejects_wrong_length() {
        let dir = tmp();
        let p = dir.path().join("c.npy");
        let e = err_text(write_npy_f32(&p, &[1.0; 5], 2, 3));
        assert!(
            e.contains("c.npy") && e.contains("got 5 values, expected 6"),
            "{e}"
        );
        assert!(!p.exists());
    }

    #[test]
    fn fortran_order_is_transposed_to_row_major() {
        let dir = tmp();
        // The 2 x 3 array [[1, 2, 3], [4, 5, 6]] stored column by column.
        let cols_major: Vec<u8> = [1.0f32, 4.0, 2.0, 5.0, 3.0, 6.0]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let p = write(
            &dir,
            "f.npy",
            &raw_npy(
                1,
                "{'descr': '<f4', 'fortran_order': True, 'shape': (2, 3), }",
                &cols_major,
            ),
        );
        let a = read_npy(&p).expect("read");
        assert_eq!((a.rows, a.cols), (2, 3));
        assert_eq!(a.data, vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
    }

    #[test]
    fn big_endian_floats() {
        let dir = tmp();
        let v = [1.5f32, -2.25, 1e10, f32::NAN];
        let be: Vec<u8> = v.iter().flat_map(|x| x.to_be_bytes()).collect();
        let p = write(
            &dir,
            "be4.npy",
            &raw_npy(
                1,
                "{'descr': '>f4', 'fortran_order': False, 'shape': (2, 2), }",
                &be,
            ),
        );
        let a = read_npy(&p).expect("read >f4");
        assert_eq!(
            a.data.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
            v.iter().map(|x| x.to_bits()).collect::<Vec<_>>()
        );

        let v8 = [1.0e-300f64, 12345.678901234, -3.0];
        let be8: Vec<u8> = v8.iter().flat_map(|x| x.to_be_bytes()).collect();
        let p = write(
            &dir,
            "be8.npy",
            &raw_npy(
                1,
                "{'descr': '>f8', 'fortran_order': False, 'shape': (1, 3), }",
                &be8,
            ),
        );
        assert_eq!(read_npy_f64(&p).expect("read >f8").data, v8.to_vec());
    }

    #[test]
    fn integer_dtypes_are_converted() {
        let dir = tmp();
        let i2: Vec<u8> = [-3i16, 300].iter().flat_map(|x| x.to_le_bytes()).collect();
        let p = write(
            &dir,
            "i2.npy",
            &raw_npy(
                1,
                "{'descr': '<i2', 'fortran_order': False, 'shape': (1, 2), }",
                &i2,
            ),
        );
        assert_eq!(read_npy(&p).expect("<i2").data, vec![-3.0, 300.0]);
        let i4: Vec<u8> = [-70000i32, 5]
            .iter()
            .flat_map(|x| x.to_le_bytes())
            .collect();
        let p = write(
            &dir,
            "i4.npy",
            &raw_npy(
                1,
                "{'descr': '<i4', 'fortran_order': False, 'shape': (2, 1), }",
                &i4,
            ),
        );
        let a = read_npy(&p).expect("<i4");
        assert_eq!((a.rows, a.cols, a.data), (2, 1, vec![-70000.0, 5.0]));
        let u2: Vec<u8> = [65535u16, 1].iter().flat_map(|x| x.to_le_bytes()).collect();
        let p = write(
            &dir,
            "u2.npy",
            &raw_npy(
                1,
                "{'descr': '<u2', 'fortran_order': False, 'shape': (1, 2), }",
                &u2,
            ),
        );
        assert_eq!(read_npy_f64(&p).expect("<u2").data, vec![65535.0, 1.0]);
        let p = write(
            &dir,
            "u1.npy",
            &raw_npy(
                1,
                "{'descr': '|u1', 'fortran_order': False, 'shape': (1, 2), }",
                &[7, 255],
            ),
        );
        assert_eq!(read_npy(&p).expect("|u1").data, vec![7.0, 255.0]);
    }

    #[test]
    fn versions_2_and_3_and_python2_longs() {
        let dir = tmp();
        let d: Vec<u8> = [1.0f32, 2.0].iter().flat_map(|x| x.to_le_bytes()).collect();
        let p = write(
            &dir,
            "v2.npy",
            &raw_npy(
                2,
                "{'descr': '<f4', 'fortran_order': False, 'shape': (1, 2), }",
                &d,
            ),
        );
        assert_eq!(read_npy(&p).expect("v2").data, vec![1.0, 2.0]);
        let p = write(
            &dir,
            "v3.npy",
            &raw_npy(
                3,
                "{\"descr\": \"<f4\", \"fortran_order\": False, \"shape\": (2, 1)}",
                &d,
            ),
        );
        let a = read_npy(&p).expect("v3");
        assert_eq!((a.rows, a.cols), (2, 1));
        let p = write(
            &dir,
            "py2.npy",
            &raw_npy(
                1,
                "{'descr': '<f4', 'fortran_order': False, 'shape': (1L, 2L), }",
                &d,
            ),
        );
        assert_eq!(read_npy(&p).expect("py2 longs").cols, 2);
    }

    #[test]
    fn long_headers_use_version_2() {
        let dict = format!(
            "{{'descr': '<f4', 'fortran_order': False, 'shape': (1, 1), 'x': '{}', }}",
            "y".repeat(70000)
        );
        let block = header_block(&dict);
        assert_eq!(&block[6..8], &[2, 0]);
        assert_eq!(block.len() % 64, 0);
        let mut file = block.clone();
        file.extend_from_slice(&4.0f32.to_le_bytes());
        let h = parse_header(&file).expect("parse v2 header");
        assert_eq!((h.rows, h.cols, h.data_offset), (1, 1, block.len()));
    }

    #[test]
    fn truncated_data_is_reported_with_sizes() {
        let dir = tmp();
        let p = dir.path().join("t.npy");
        write_npy_f32(&p, &[1.0; 6], 2, 3).expect("write");
        let bytes = std::fs::read(&p).expect("read");
        let q = write(&dir, "trunc.npy", &bytes[..bytes.len() - 5]);
        let e = err_text(read_npy(&q));
        assert!(
            e.contains("trunc.npy")
                && e.contains("truncated: expected 24 bytes of data")
                && e.contains("found 19"),
            "{e}"
        );
        // Cut inside the header and inside the preamble.
        let q = write(&dir, "trunc_header.npy", &bytes[..40]);
        let e = err_text(read_npy(&q));
        assert!(
            e.contains("trunc_header.npy") && e.contains("truncated"),
            "{e}"
        );
        let q = write(&dir, "trunc_pre.npy", &bytes[..7]);
        assert!(err_text(read_npy(&q)).contains("truncated"));
        // Trailing garbage.
        let mut longer = bytes.clone();
        longer.extend_from_slice(&[0; 3]);
        let q = write(&dir, "long.npy", &longer);
        assert!(err_text(read_npy(&q)).contains("3 unexpected bytes after the data"));
    }

    #[test]
    fn bad_magic_and_missing_file() {
        let dir = tmp();
        let p = write(
            &dir,
            "x.npy",
            b"PK\x03\x04 this is a zip file, not an array",
        );
        let e = err_text(read_npy(&p));
        assert!(
            e.contains("x.npy") && e.contains("not a .npy file (bad magic"),
            "{e}"
        );
        let p = write(&dir, "empty.npy", b"");
        assert!(err_text(read_npy(&p)).contains("bad magic"));
        let e = err_text(read_npy(dir.path().join("missing.npy")));
        assert!(
            e.contains("missing.npy") && e.contains("cannot read"),
            "{e}"
        );
        let p = write(&dir, "v9.npy", b"\x93NUMPY\x09\x00\x00\x00");
        assert!(err_text(read_npy(&p)).contains("unsupported .npy format version 9.0"));
    }

    #[test]
    fn non_2d_arrays_are_rejected() {
        let dir = tmp();
        let d: Vec<u8> = [1.0f32; 8].iter().flat_map(|x| x.to_le_bytes()).collect();
        let p = write(
            &dir,
            "one.npy",
            &raw_npy(
                1,
                "{'descr': '<f4', 'fortran_order': False, 'shape': (8,), }",
                &d,
            ),
        );
        let e = err_text(read_npy(&p));
        assert!(
            e.contains("one.npy") && e.contains("not 2-D (shape (8,))"),
            "{e}"
        );
        let p = write(
            &dir,
            "three.npy",
            &raw_npy(
                1,
                "{'descr': '<f4', 'fortran_order': False, 'shape': (2, 2, 2), }",
                &d,
            ),
        );
        assert!(err_text(read_npy(&p)).contains("not 2-D (shape (2, 2, 2))"));
        let p = write(
            &dir,
            "zero.npy",
            &raw_npy(
                1,
                "{'descr': '<f4', 'fortran_order': False, 'shape': (), }",
                &d[..4],
            ),
        );
        assert!(err_text(read_npy(&p)).contains("not 2-D (shape ())"));
    }

    #[test]
    fn unsupported_dtypes_and_bad_headers() {
        let dir = tmp();
        for descr in ["<c8", "<f2", "|b1", "<U10", "|i2"] {
            let dict = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': (1, 1), }}");
            let p = write(&dir, "d.npy", &raw_npy(1, &dict, &[0; 16]));
            let e = err_text(read_npy(&p));
            assert!(
                e.contains(&format!(
                    "unsupported dtype \"{descr}\" (expected float32 or float64"
                )),
                "{e}"
            );
        }
        let p = write(
            &dir,
            "s.npy",
            &raw_npy(
                1,
                "{'descr': [('a', '<f4')], 'fortran_order': False, 'shape': (1, 1), }",
                &[0; 4],
            ),
        );
        assert!(err_text(read_npy(&p)).contains("unsupported dtype [('a', '<f4')]"));
        let p = write(
            &dir,
            "k.npy",
            &raw_npy(1, "{'descr': '<f4', 'shape': (1, 1), }", &[0; 4]),
        );
        assert!(err_text(read_npy(&p)).contains("no 'fortran_order' key"));
        let p = write(
            &dir,
            "g.npy",
            &raw_npy(
                1,
                "{'descr': '<f4', 'fortran_order': Nope, 'shape': (1, 1), }",
                &[0; 4],
            ),
        );
        assert!(err_text(read_npy(&p)).contains("cannot parse the header"));
        let p = write(
            &dir,
            "h.npy",
            &raw_npy(
                1,
                "{'descr': '<f4', 'fortran_order': False, 'shape': (99999999999, 99999999999), }",
                &[0; 4],
            ),
        );
        assert!(err_text(read_npy(&p)).contains("too large"));
    }
}

// ---------------------------------------------------------------------------------------------
// Reading by rows: a window of a file without the whole array in memory (issue 17).

/// A 2-D C-order `.npy` file opened for reading rows or windows on demand: the header is
/// parsed and the size checked once; every read seeks to the rows it needs.
#[derive(Debug)]
pub struct NpyRows {
    path: std::path::PathBuf,
    file: std::fs::File,
    dtype: Dtype,
    rows: usize,
    cols: usize,
    data_offset: u64,
    raw: Vec<u8>,
}

impl NpyRows {
    /// Opens `path`; the same header checks as [`read_npy`], and the file's length must be
    /// exactly the header plus the data. Fortran-order arrays are refused (a row of them is
    /// scattered over the whole file).
    pub fn open(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        let (file, len, header) = open_header(path)?;
        let (rows, cols) = (header.rows, header.cols);
        if header.fortran_order && rows > 1 && cols > 1 {
            bail!(
                "{}: a Fortran-order (column-major) array cannot be read by rows; \
                 expected fortran_order False",
                path.display()
            );
        }
        let expected = (rows * cols * header.dtype.size) as u64;
        let found = len.saturating_sub(header.data_offset as u64);
        if found != expected {
            bail!(
                "{}: expected {expected} bytes of data for a {rows} x {cols} array, found {found}",
                path.display()
            );
        }
        Ok(Self {
            path: path.to_path_buf(),
            file,
            dtype: header.dtype,
            rows,
            cols,
            data_offset: header.data_offset as u64,
            raw: Vec::new(),
        })
    }

    pub fn rows(&self) -> usize {
        self.rows
    }

    pub fn cols(&self) -> usize {
        self.cols
    }

    /// True when the file stores float32 (f32 reads then lose nothing).
    pub fn is_f32(&self) -> bool {
        self.dtype.kind == Kind::Float && self.dtype.size == 4
    }

    /// Rows `row0 .. row0 + rows`, whole, as f64 into `out` (cleared first).
    pub fn read_rows_f64(&mut self, row0: usize, rows: usize, out: &mut Vec<f64>) -> Result<()> {
        self.read_window(row0, 0, rows, self.cols, out)
    }

    /// The window of `rows` x `cols` values from (`row0`, `col0`), row-major, into `out`
    /// (cleared first), converted as [`read_npy_f64`] / [`read_npy`] convert.
    pub fn read_window<T: WindowElement>(
        &mut self,
        row0: usize,
        col0: usize,
        rows: usize,
        cols: usize,
        out: &mut Vec<T>,
    ) -> Result<()> {
        use std::io::{Read, Seek, SeekFrom};
        if row0 + rows > self.rows || col0 + cols > self.cols {
            bail!(
                "{}: window {rows} x {cols} at row {row0}, col {col0} leaves the {} x {} array",
                self.path.display(),
                self.rows,
                self.cols
            );
        }
        out.clear();
        out.reserve(rows * cols);
        let size = self.dtype.size;
        // Whole rows are one read; a narrower window one read per row.
        let (per_read, reads) = if cols == self.cols {
            (rows * cols, usize::from(rows > 0))
        } else {
            (cols, rows)
        };
        for k in 0..reads {
            let (r, c) = if cols == self.cols {
                (row0, 0)
            } else {
                (row0 + k, col0)
            };
            let at = self.data_offset + ((r * self.cols + c) * size) as u64;
            self.raw.resize(per_read * size, 0);
            self.file
                .seek(SeekFrom::Start(at))
                .and_then(|_| self.file.read_exact(&mut self.raw))
                .with_context(|| format!("{}: cannot read rows from {r}", self.path.display()))?;
            let values = decode::<T>(&self.raw, self.dtype).ok_or_else(|| {
                anyhow!(
                    "{}: unsupported dtype {:?}",
                    self.path.display(),
                    self.dtype
                )
            })?;
            out.extend_from_slice(&values);
        }
        Ok(())
    }

    /// Every `step`-th row and column from (0, 0), as f64: a `rows.div_ceil(step)` x
    /// `cols.div_ceil(step)` map read one row at a time.
    pub fn read_strided_f64(&mut self, step: usize) -> Result<(Vec<f64>, usize, usize)> {
        let step = step.max(1);
        let (rows, cols) = (self.rows.div_ceil(step), self.cols.div_ceil(step));
        let mut out = Vec::with_capacity(rows * cols);
        let mut row = Vec::new();
        for r in 0..rows {
            self.read_rows_f64(r * step, 1, &mut row)?;
            out.extend(row.iter().step_by(step));
        }
        Ok((out, rows, cols))
    }

    /// NaN-aware means of `block` x `block` cells (ragged at the right and bottom edges), as
    /// f64: a `rows.div_ceil(block)` x `cols.div_ceil(block)` map read `block` rows at a time.
    pub fn read_block_means_f64(&mut self, block: usize) -> Result<(Vec<f64>, usize, usize)> {
        let block = block.max(1);
        let (rows, cols) = (self.rows.div_ceil(block), self.cols.div_ceil(block));
        let mut out = Vec::with_capacity(rows * cols);
        let mut band = Vec::new();
        let (mut sum, mut count) = (vec![0.0f64; cols], vec![0u32; cols]);
        for br in 0..rows {
            let r0 = br * block;
            let n = block.min(self.rows - r0);
            self.read_rows_f64(r0, n, &mut band)?;
            sum.iter_mut().for_each(|s| *s = 0.0);
            count.iter_mut().for_each(|c| *c = 0);
            for row in band.chunks_exact(self.cols) {
                for (c, &v) in row.iter().enumerate() {
                    if v.is_finite() {
                        sum[c / block] += v;
                        count[c / block] += 1;
                    }
                }
            }
            out.extend(sum.iter().zip(&count).map(
                |(&s, &n)| {
                    if n > 0 {
                        s / n as f64
                    } else {
                        f64::NAN
                    }
                },
            ));
        }
        Ok((out, rows, cols))
    }
}

/// What [`NpyRows::read_window`] reads into: f32 or f64.
#[allow(private_bounds)]
pub trait WindowElement: Element {}
impl WindowElement for f32 {}
impl WindowElement for f64 {}

#[cfg(test)]
mod rows_tests {
    use super::*;

    #[test]
    fn windows_rows_and_decimations_equal_the_whole_read() {
        let dir = std::env::temp_dir().join(format!("npy-rows-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (rows, cols) = (7, 5);
        let data: Vec<f32> = (0..rows * cols)
            .map(|i| {
                if i == 12 {
                    f32::NAN
                } else {
                    i as f32 * 0.5 - 3.0
                }
            })
            .collect();
        let p = dir.join("a.npy");
        write_npy_f32(&p, &data, rows, cols).unwrap();
        let whole = read_npy_f64(&p).unwrap();
        let mut f = NpyRows::open(&p).unwrap();
        assert_eq!((f.rows(), f.cols(), f.is_f32()), (rows, cols, true));
        let mut out: Vec<f64> = Vec::new();
        f.read_rows_f64(2, 3, &mut out).unwrap();
        assert_eq!(
            out.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
            whole.data[10..25]
                .iter()
                .map(|v| v.to_bits())
                .collect::<Vec<_>>()
        );
        let mut w: Vec<f32> = Vec::new();
        f.read_window(1, 2, 3, 2, &mut w).unwrap();
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        let expected: Vec<f32> = [7, 8, 12, 13, 17, 18].map(|i| data[i]).to_vec();
        assert_eq!(bits(&w), bits(&expected));
        let (s, sr, sc) = f.read_strided_f64(3).unwrap();
        assert_eq!((sr, sc), (3, 2));
        assert_eq!(s[..2], [whole.data[0], whole.data[3]]);
        assert_eq!(s[4..], [whole.data[30], whole.data[33]]);
        let (m, mr, mc) = f.read_block_means_f64(2).unwrap();
        assert_eq!((mr, mc), (4, 3));
        // Cell (1, 1): rows 2-3, cols 2-3, value 12 is NaN.
        let cell = [13, 17, 18].map(|i| whole.data[i]);
        assert_eq!(m[4], cell.iter().sum::<f64>() / 3.0);
        assert_eq!(m[11], whole.data[34]);
        assert!(f.read_window::<f64>(5, 0, 3, 5, &mut out).is_err());
        // A truncated file is refused at open, naming the file.
        let bytes = std::fs::read(&p).unwrap();
        let t = dir.join("t.npy");
        std::fs::write(&t, &bytes[..bytes.len() - 4]).unwrap();
        let e = NpyRows::open(&t).unwrap_err().to_string();
        assert!(
            e.contains("t.npy") && e.contains("expected 140 bytes"),
            "{e}"
        );
        std::fs::remove_dir_all(&dir).ok();
    }
}
