//! The datum / roughness separation of [`crate::separate`], streamed: the same numbers (bit
//! for bit) with memory bounded by a band of rows instead of the whole map.
//!
//! The transform is multi-resolution: each output row of a level is computed from a few input
//! rows (decomposition: `L` rows, `ext_index(2k + s - j)`; reconstruction: `L/2` rows), and the
//! kernels do the same arithmetic per row however the rows are banded. So each level is
//! produced band by band: the input rows a band of output rows reads (its range plus the
//! mode's edge rows, reflected or wrapped) are gathered by index into a small buffer, the
//! crate's own kernels ([`crate::dwt::LevelKernels`]) compute the band, and the band goes to
//! a [`LevelStore`] (an unnamed temporary file, or memory when the level is small). Only the
//! deepest approximation is needed to reconstruct, so at most two levels are stored at once.
//!
//! * Level 1's input rows are the heights filled as [`crate::fill_invalid`] fills them, one row
//!   at a time: per-row interpolation, and rows without a valid pixel interpolated between
//!   the nearest valid rows (computed from those two rows when asked for).
//! * The last inverse step runs band by band straight into datum / roughness rows, which go
//!   to the caller's row sink in order: no whole datum or roughness array is ever formed.
//!
//! Memory: `O((L + band) * cols)` f64 plus the stores' memory part (at most
//! [`StreamOptions::memory_store_max_bytes`] per level); the heights themselves are the
//! caller's. [`energy_curve_streamed`] does the same for [`crate::energy_curve`] (details
//! included; its sums are added in another order, so it agrees to round-off, not bits).

use std::path::PathBuf;

use rayon::prelude::*;
use surfstream_core::store::{RowStore, StoreError};

use crate::dwt::{check_trim, LevelKernels, Rows};
use crate::error::{check_raster, WaveletError};
use crate::select::{plane_coef, EnergyPoint};
use crate::separate::{default_level, fill_row, finish_row};
use crate::wavelet::{dwt_max_level, Mode, Wavelet};

/// Bytes of input rows one band gathers (about): large enough that the per-band overhead
/// (gathering the `L - 2` rows shared with the previous band) stays a few per cent, small
/// enough to be a constant next to the map.
const BAND_INPUT_BYTES: usize = 8 << 20;

/// How the streamed pass keeps its intermediate levels.
#[derive(Debug, Clone)]
pub struct StreamOptions {
    /// Output rows per band; `None` = about [`BAND_INPUT_BYTES`] of input per band.
    pub band_rows: Option<usize>,
    /// A level up to this size (bytes of f64) stays in memory; larger ones go to a file.
    pub memory_store_max_bytes: usize,
    /// Folder of the unnamed temporary files (default: the system's temp folder).
    pub spill_dir: Option<PathBuf>,
}

impl Default for StreamOptions {
    fn default() -> Self {
        Self {
            band_rows: None,
            memory_store_max_bytes: 8 << 20,
            spill_dir: None,
        }
    }
}

/// Errors of the streamed pass: the transform's own, the store's I/O, or the row sink's.
#[derive(Debug, thiserror::Error)]
pub enum StreamError {
    #[error(transparent)]
    Wavelet(#[from] WaveletError),
    #[error("wavelet level store: {0}")]
    Store(#[from] std::io::Error),
    #[error("{0:#}")]
    Sink(anyhow::Error),
}

impl From<StoreError> for StreamError {
    /// The message names the spill folder.
    fn from(e: StoreError) -> Self {
        StreamError::Store(e.into())
    }
}

/// Where input rows come from: the filled heights (level 0) or a stored level.
trait RowFetch: Sync {
    fn rows(&self) -> usize;
    fn cols(&self) -> usize;
    /// Row `r` into `out` (`cols()` values).
    fn fetch(&self, r: usize, out: &mut [f64]) -> std::io::Result<()>;
}

/// The heights as [`crate::fill_invalid`] fills them, one row at a time; optionally minus
/// the least-squares plane (the energy curve's levelling).
struct FilledRows<'a> {
    heights: &'a [f32],
    rows: usize,
    cols: usize,
    /// Rows holding at least one finite pixel, ascending.
    valid_rows: Vec<usize>,
    row_ok: Vec<bool>,
    /// (coefficients, cx, cy) of the plane to subtract.
    plane: Option<([f64; 3], f64, f64)>,
}

impl<'a> FilledRows<'a> {
    fn new(heights: &'a [f32], rows: usize, cols: usize) -> Result<Self, WaveletError> {
        check_raster(heights.len(), rows, cols)?;
        let row_ok: Vec<bool> = heights
            .par_chunks(cols)
            .map(|h| h.iter().any(|v| v.is_finite()))
            .collect();
        let valid_rows: Vec<usize> = (0..rows).filter(|&r| row_ok[r]).collect();
        if valid_rows.is_empty() {
            return Err(WaveletError::AllNan);
        }
        Ok(Self {
            heights,
            rows,
            cols,
            valid_rows,
            row_ok,
            plane: None,
        })
    }

    fn height_row(&self, r: usize) -> &[f32] {
        &self.heights[r * self.cols..(r + 1) * self.cols]
    }

    /// Row `r` of `fill_invalid`'s result, with its arithmetic.
    fn fill(&self, r: usize, out: &mut [f64]) {
        if self.row_ok[r] {
            fill_row(self.height_row(r), out);
        } else {
            let i = self.valid_rows.partition_point(|&v| v < r);
            let n = self.valid_rows.len();
            if i == 0 || i == n {
                // Constant extension above the first / below the last valid row.
                let src = self.valid_rows[if i == 0 { 0 } else { n - 1 }];
                fill_row(self.height_row(src), out);
            } else {
                let (p, q) = (self.valid_rows[i - 1], self.valid_rows[i]);
                let mut below = vec![0.0f64; self.cols];
                fill_row(self.height_row(p), out);
                fill_row(self.height_row(q), &mut below);
                let t = (r - p) as f64 / (q - p) as f64;
                for (o, &b) in out.iter_mut().zip(&below) {
                    let a = *o;
                    *o = a + t * (b - a);
                }
            }
        }
        if let Some((coef, cx, cy)) = self.plane {
            for (c, z) in out.iter_mut().enumerate() {
                *z -= coef[0] + coef[1] * (c as f64 - cx) + coef[2] * (r as f64 - cy);
            }
        }
    }
}

impl RowFetch for FilledRows<'_> {
    fn rows(&self) -> usize {
        self.rows
    }
    fn cols(&self) -> usize {
        self.cols
    }
    fn fetch(&self, r: usize, out: &mut [f64]) -> std::io::Result<()> {
        self.fill(r, out);
        Ok(())
    }
}

/// One level's coefficients, `rows x cols` f64: in memory when small, else in an unnamed
/// temporary file (gone when dropped, also after a crash) read and written by row.
type LevelStore = RowStore<f64>;

fn new_level(rows: usize, cols: usize, opts: &StreamOptions) -> Result<LevelStore, StoreError> {
    RowStore::new(
        rows,
        cols,
        opts.memory_store_max_bytes,
        opts.spill_dir.clone(),
    )
}

impl RowFetch for LevelStore {
    fn rows(&self) -> usize {
        RowStore::rows(self)
    }
    fn cols(&self) -> usize {
        RowStore::cols(self)
    }
    fn fetch(&self, r: usize, out: &mut [f64]) -> std::io::Result<()> {
        Ok(self.read_row(r, out)?)
    }
}

/// The input rows one band reads, by their index in the whole level.
struct BandRows {
    n_rows: usize,
    n_cols: usize,
    index: Vec<usize>,
    data: Vec<f64>,
}

impl BandRows {
    fn gather(src: &dyn RowFetch, index: Vec<usize>) -> std::io::Result<Self> {
        let n_cols = src.cols();
        let mut data = vec![0.0f64; index.len() * n_cols];
        data.par_chunks_mut(n_cols)
            .zip(index.par_iter())
            .try_for_each(|(o, &r)| src.fetch(r, o))?;
        Ok(Self {
            n_rows: src.rows(),
            n_cols,
            index,
            data,
        })
    }
}

impl Rows for BandRows {
    fn n_rows(&self) -> usize {
        self.n_rows
    }
    fn n_cols(&self) -> usize {
        self.n_cols
    }
    fn row(&self, r: usize) -> &[f64] {
        // The band holds every row its outputs read (dec_rows_needed / rec_rows_needed).
        let i = self
            .index
            .binary_search(&r)
            .expect("the band gathered every row its outputs read");
        &self.data[i * self.n_cols..(i + 1) * self.n_cols]
    }
}

/// Output rows per band: as asked, or about [`BAND_INPUT_BYTES`] of input.
fn band_rows(opts: &StreamOptions, in_cols: usize, in_rows_per_out: usize) -> usize {
    opts.band_rows
        .unwrap_or_else(|| BAND_INPUT_BYTES / (8 * in_cols.max(1) * in_rows_per_out).max(1))
        .max(1)
}

/// Rows per parallel task inside a band.
fn task_rows(band: usize) -> usize {
    band.div_ceil(2 * rayon::current_num_threads().max(1))
        .max(1)
}

/// Energies of one decomposition step (sum of squares).
#[derive(Default)]
struct StepEnergy {
    approx: f64,
    details: f64,
}

/// One decomposition step of `src` into a new store; with `details`, the detail bands'
/// energy is summed (the bands themselves are not kept).
fn dec_step(
    src: &dyn RowFetch,
    k: &LevelKernels,
    details: bool,
    opts: &StreamOptions,
) -> Result<(LevelStore, StepEnergy), StreamError> {
    let (r2, c2) = (k.dec_out_len(src.rows()), k.dec_out_len(src.cols()));
    let mut store = new_level(r2, c2, opts)?;
    let band = band_rows(opts, src.cols(), 2);
    let sub = task_rows(band);
    let mut energy = StepEnergy::default();
    let sq = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>();
    for k0 in (0..r2).step_by(band) {
        surfstream_core::liveness::beat();
        let k1 = (k0 + band).min(r2);
        let rows = BandRows::gather(src, k.dec_rows_needed(k0, k1, src.rows()))?;
        let n = (k1 - k0) * c2;
        let mut ca = vec![0.0f64; n];
        if details {
            let (mut ch, mut cv, mut cd) = (vec![0.0f64; n], vec![0.0f64; n], vec![0.0f64; n]);
            let (ea, ed) = ca
                .par_chunks_mut(sub * c2)
                .zip(ch.par_chunks_mut(sub * c2))
                .zip(cv.par_chunks_mut(sub * c2))
                .zip(cd.par_chunks_mut(sub * c2))
                .enumerate()
                .map(|(t, (((a, h), v), d))| {
                    k.dec_rows(&rows, k0 + t * sub, a, Some([&mut *h, &mut *v, &mut *d]));
                    // Row by row: a task's rows depend on the thread count.
                    let rows_of = |x: &[f64]| x.chunks(c2).map(sq).collect::<Vec<f64>>();
                    let (hr, vr, dr) = (rows_of(h), rows_of(v), rows_of(d));
                    let details = (hr.iter().zip(&vr).zip(&dr)).map(|((h, v), d)| h + v + d);
                    rows_of(a)
                        .into_iter()
                        .zip(details)
                        .collect::<Vec<(f64, f64)>>()
                })
                // Each row's energy added in row order: rayon's reduce would pair partial sums
                // as the threads split the work (and a task's rows follow the thread count),
                // so the energy's last bits would vary from run to run and machine to machine.
                .collect::<Vec<Vec<(f64, f64)>>>()
                .into_iter()
                .flatten()
                .fold((0.0, 0.0), |x, y| (x.0 + y.0, x.1 + y.1));
            energy.approx += ea;
            energy.details += ed;
        } else {
            ca.par_chunks_mut(sub * c2)
                .enumerate()
                .for_each(|(t, a)| k.dec_rows(&rows, k0 + t * sub, a, None));
        }
        store.write_rows(k0, &ca)?;
    }
    Ok((store, energy))
}

/// One approximation-only inverse step of `src`, keeping the top-left `want` (PyWavelets'
/// trim before the next step).
fn rec_step(
    src: &LevelStore,
    k: &LevelKernels,
    want: (usize, usize),
    opts: &StreamOptions,
) -> Result<LevelStore, StreamError> {
    let out_rows = k.rec_out_len(src.rows()).ok_or_else(|| too_short(src))?;
    let out_cols = k.rec_out_len(src.cols()).ok_or_else(|| too_short(src))?;
    check_trim((out_rows, out_cols), want)?;
    let mut store = new_level(want.0, want.1, opts)?;
    let band = band_rows(opts, out_cols, 1);
    let sub = task_rows(band);
    let mut out = Vec::new();
    let mut kept = Vec::new();
    for n0 in (0..want.0).step_by(band) {
        surfstream_core::liveness::beat();
        let n1 = (n0 + band).min(want.0);
        let rows = BandRows::gather(src, k.rec_rows_needed(n0, n1, src.rows()))?;
        out.clear();
        out.resize((n1 - n0) * out_cols, 0.0);
        out.par_chunks_mut(sub * out_cols)
            .enumerate()
            .for_each(|(t, o)| k.rec_rows(&rows, n0 + t * sub, o));
        kept.clear();
        for row in out.chunks_exact(out_cols) {
            kept.extend_from_slice(&row[..want.1]);
        }
        store.write_rows(n0, &kept)?;
    }
    Ok(store)
}

fn too_short(a: &LevelStore) -> WaveletError {
    WaveletError::CoeffShape(format!(
        "{} x {} coefficients are too few for the filter",
        a.rows(),
        a.cols()
    ))
}

/// [`crate::separate`], streamed: the datum and roughness rows go to `sink(first_row, datum,
/// roughness)` band by band, top to bottom (whole rows of `cols` values each), bit-identical
/// to [`crate::separate`]'s. Returns the level used.
// separate()'s arguments plus the stream options and the sink.
#[allow(clippy::too_many_arguments)]
pub fn separate_streamed(
    heights: &[f32],
    rows: usize,
    cols: usize,
    wavelet: &Wavelet,
    mode: Mode,
    level: Option<usize>,
    opts: &StreamOptions,
    mut sink: impl FnMut(usize, &[f32], &[f32]) -> anyhow::Result<()>,
) -> Result<usize, StreamError> {
    check_raster(heights.len(), rows, cols)?;
    let level = default_level(rows, cols, wavelet, level)?;
    let filled = FilledRows::new(heights, rows, cols)?;
    let k = LevelKernels::new(wavelet, mode);
    // Decompose, keeping only the newest approximation; remember every level's shape.
    let mut shapes = vec![(rows, cols)];
    let (mut approx, _) = dec_step(&filled, &k, false, opts)?;
    shapes.push((approx.rows(), approx.cols()));
    for _ in 1..level {
        approx = dec_step(&approx, &k, false, opts)?.0;
        shapes.push((approx.rows(), approx.cols()));
    }
    // Reconstruct approximation-only, trimming as waverec2 does, down to level 1.
    for l in (2..=level).rev() {
        approx = rec_step(&approx, &k, shapes[l - 1], opts)?;
    }
    // The last inverse step, band by band into datum / roughness rows.
    let out_rows = k
        .rec_out_len(approx.rows())
        .ok_or_else(|| too_short(&approx))?;
    let out_cols = k
        .rec_out_len(approx.cols())
        .ok_or_else(|| too_short(&approx))?;
    if out_rows < rows || out_cols < cols {
        return Err(WaveletError::CoeffShape(format!(
            "low-pass {out_rows} x {out_cols} smaller than the map {rows} x {cols}"
        ))
        .into());
    }
    let band = band_rows(opts, out_cols, 1);
    let sub = task_rows(band);
    let mut low = Vec::new();
    let mut datum = Vec::new();
    let mut roughness = Vec::new();
    for n0 in (0..rows).step_by(band) {
        let n1 = (n0 + band).min(rows);
        let src = BandRows::gather(&approx, k.rec_rows_needed(n0, n1, approx.rows()))?;
        low.clear();
        low.resize((n1 - n0) * out_cols, 0.0);
        datum.clear();
        datum.resize((n1 - n0) * cols, 0.0f32);
        roughness.clear();
        roughness.resize((n1 - n0) * cols, 0.0f32);
        let h_band = &heights[n0 * cols..n1 * cols];
        low.par_chunks_mut(sub * out_cols)
            .zip(datum.par_chunks_mut(sub * cols))
            .zip(roughness.par_chunks_mut(sub * cols))
            .zip(h_band.par_chunks(sub * cols))
            .enumerate()
            .for_each(|(t, (((l, d), r), h))| {
                k.rec_rows(&src, n0 + t * sub, l);
                for (((l_row, d_row), r_row), h_row) in l
                    .chunks_exact(out_cols)
                    .zip(d.chunks_exact_mut(cols))
                    .zip(r.chunks_exact_mut(cols))
                    .zip(h.chunks_exact(cols))
                {
                    finish_row(h_row, &l_row[..cols], d_row, r_row);
                }
            });
        sink(n0, &datum, &roughness).map_err(StreamError::Sink)?;
    }
    Ok(level)
}

/// [`crate::energy_curve`], streamed (each level's detail bands are summed band by band and
/// never kept). Agrees with it to round-off: the sums run in another order.
pub fn energy_curve_streamed(
    heights: &[f32],
    rows: usize,
    cols: usize,
    wavelet: &Wavelet,
    mode: Mode,
    opts: &StreamOptions,
) -> Result<Vec<EnergyPoint>, StreamError> {
    default_level(rows, cols, wavelet, Some(1))?;
    let max = dwt_max_level(rows.min(cols), wavelet.filter_len());
    let mut filled = FilledRows::new(heights, rows, cols)?;
    filled.plane = Some(plane_coef(heights, rows, cols));
    let k = LevelKernels::new(wavelet, mode);
    let mut detail_energy = 0.0f64;
    let mut curve = Vec::with_capacity(max);
    let mut approx: Option<LevelStore> = None;
    for level in 1..=max {
        let src: &dyn RowFetch = match &approx {
            Some(a) => a,
            None => &filled,
        };
        let (next, e) = dec_step(src, &k, true, opts)?;
        detail_energy += e.details;
        let total = e.approx + detail_energy;
        curve.push(EnergyPoint {
            level,
            approx_energy_fraction: if total > 0.0 { e.approx / total } else { 0.0 },
        });
        approx = Some(next);
    }
    Ok(curve)
}
