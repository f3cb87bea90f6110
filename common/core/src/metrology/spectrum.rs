//! The 2-D FFTs behind the spatial parameters: the height spectrum (for the PSD and Std) and
//! the linear autocorrelation (for Sal and Str), real-to-complex (realfft) along rows, complex
//! (rustfft) along columns, rows and column blocks in parallel (rayon).
//!
//! Gaps (NaN): the heights enter centred on the mean of the valid points with every gap set
//! to 0, i.e. filled with the mean. The autocorrelation divides each lag by the number of
//! pairs valid at both ends (the autocorrelation of the validity mask, one more FFT pair), so
//! gaps add nothing and remove nothing; the spectrum of a map with gaps is the spectrum of the
//! mean-filled map (see psd.rs for its scaling).

use std::sync::Arc;

use rayon::prelude::*;
use realfft::{ComplexToReal, RealFftPlanner, RealToComplex};
use rustfft::num_complex::Complex;
use rustfft::{Fft, FftPlanner};

use crate::fft::fast_len;
use crate::store::{SpillFile, StoreError};

type C = Complex<f64>;

/// A raw pointer shared by tasks that write disjoint columns of one row-major buffer.
#[derive(Clone, Copy)]
struct Columns(*mut C);
// SAFETY: every task touches only its own columns (see `for_column_blocks`).
unsafe impl Send for Columns {}
unsafe impl Sync for Columns {}

/// Columns per task: enough to read whole cache lines of each row.
const BLOCK: usize = 8;

/// Runs `f(column, buffer)` for every column of the `rows x width` row-major `data`, the
/// column gathered into a zeroed buffer of `len >= rows` and written back (its first `rows`
/// values) after `f`, columns in parallel blocks.
fn for_column_blocks(
    data: &mut [C],
    rows: usize,
    width: usize,
    len: usize,
    f: impl Fn(usize, &mut [C], &mut [C]) + Sync,
    scratch_len: usize,
) {
    let ptr = Columns(data.as_mut_ptr());
    let blocks = width.div_ceil(BLOCK);
    (0..blocks).into_par_iter().for_each_init(
        || (vec![C::default(); len], vec![C::default(); scratch_len]),
        |(buf, scratch), b| {
            let p = ptr;
            for k in b * BLOCK..((b + 1) * BLOCK).min(width) {
                buf.fill(C::default());
                for (r, v) in buf.iter_mut().enumerate().take(rows) {
                    // SAFETY: r < rows, k < width: inside `data`; column k belongs to this task only.
                    *v = unsafe { *p.0.add(r * width + k) };
                }
                f(k, buf, scratch);
                for (r, v) in buf.iter().enumerate().take(rows) {
                    // SAFETY: as above.
                    unsafe { *p.0.add(r * width + k) = *v };
                }
            }
        },
    );
}

/// Real FFT of every row of the `rows x cols` field whose row r `row(r, buf)` writes into
/// `buf` (cols values), zero-padded to `q`: rows x (q/2 + 1). The field itself is never held.
fn rows_forward(
    row: &(impl Fn(usize, &mut [f64]) + Sync),
    rows: usize,
    cols: usize,
    r2c: &Arc<dyn RealToComplex<f64>>,
) -> Vec<C> {
    let mut spec = vec![C::default(); rows * r2c.complex_len()];
    rows_forward_into(row, 0, cols, r2c, &mut spec);
    spec
}

/// [`rows_forward`] of the rows r0.. that `out` holds (whole rows of q/2 + 1).
fn rows_forward_into(
    row: &(impl Fn(usize, &mut [f64]) + Sync),
    r0: usize,
    cols: usize,
    r2c: &Arc<dyn RealToComplex<f64>>,
    out: &mut [C],
) {
    let q = r2c.len();
    out.par_chunks_mut(r2c.complex_len())
        .enumerate()
        .for_each_init(
            || (vec![0.0; q], r2c.make_scratch_vec()),
            |(buf, scratch), (r, out)| {
                row(r0 + r, &mut buf[..cols]);
                buf[cols..].fill(0.0);
                // Lengths are the planner's own: cannot fail.
                let _ = r2c.process_with_scratch(buf, out, scratch);
            },
        );
}

/// A slice as the rows of a `cols` wide field.
fn rows_of(field: &[f64], cols: usize) -> impl Fn(usize, &mut [f64]) + Sync + '_ {
    move |r, buf| buf.copy_from_slice(&field[r * cols..(r + 1) * cols])
}

/// The 2-D DFT of `field` (rows x cols, no padding), the half plane kx = 0..cols/2:
/// rows x (cols/2 + 1), row-major, unnormalised.
pub(crate) fn spectrum2(field: &[f64], rows: usize, cols: usize) -> Vec<C> {
    spectrum2_of(&rows_of(field, cols), rows, cols)
}

/// [`spectrum2`] of the field whose rows `row` writes (see [`rows_forward`]).
pub(crate) fn spectrum2_of(
    row: &(impl Fn(usize, &mut [f64]) + Sync),
    rows: usize,
    cols: usize,
) -> Vec<C> {
    let r2c = RealFftPlanner::<f64>::new().plan_fft_forward(cols);
    let h = r2c.complex_len();
    let mut spec = rows_forward(row, rows, cols, &r2c);
    let fwd: Arc<dyn Fft<f64>> = FftPlanner::new().plan_fft_forward(rows);
    let sl = fwd.get_inplace_scratch_len();
    for_column_blocks(
        &mut spec,
        rows,
        h,
        rows,
        |_, buf, scratch| fwd.process_with_scratch(buf, scratch),
        sl,
    );
    spec
}

/// The linear (not circular) correlation sums S(ty, tx) = sum over x of f(x) f(x + t), for
/// ty = 0..rows and tx = -(cols-1)..=(cols-1): rows x (2 cols - 1), row-major, tx = 0 at
/// column cols - 1 (S(-t) = S(t) gives the other half plane). Zero-padded FFTs of
/// fast_len(2n - 1) in each direction. The field's rows come from `row` (see
/// [`rows_forward`]); the sums are written over the half spectrum's own memory (a row of
/// sums is shorter than a row of the spectrum), so the peak is that spectrum alone.
pub(crate) fn correlation_half_plane(
    row: &(impl Fn(usize, &mut [f64]) + Sync),
    rows: usize,
    cols: usize,
) -> Vec<f64> {
    let plans = CorrelationPlans::new(rows, cols);
    let h = plans.h;
    let mut spec = rows_forward(row, rows, cols, &plans.r2c);
    for_column_blocks(
        &mut spec,
        rows,
        h,
        plans.p,
        plans.column(),
        plans.scratch_len,
    );
    let w = 2 * cols - 1;
    // Row ty of sums (w reals) ends before row ty of the spectrum (2h reals) does: w < 2h
    // since h = q/2 + 1 and q >= w. Rows are taken in blocks, each copied out before its
    // sums are written, in order, so a write never lands on an unread spectrum value.
    debug_assert!(w < 2 * h);
    let mut out = complex_as_reals(spec);
    const ROWS_PER_BLOCK: usize = 64;
    let mut block = vec![C::default(); ROWS_PER_BLOCK.min(rows) * h];
    for ty0 in (0..rows).step_by(ROWS_PER_BLOCK) {
        let nb = ROWS_PER_BLOCK.min(rows - ty0);
        for (k, v) in block[..nb * h].iter_mut().enumerate() {
            let at = 2 * (ty0 * h + k);
            *v = C::new(out[at], out[at + 1]);
        }
        plans.inverse_rows(
            &block[..nb * h],
            &mut out[ty0 * w..(ty0 + nb) * w],
            cols - 1,
        );
    }
    drop(block);
    out.truncate(rows * w);
    out
}

/// [`correlation_half_plane`]'s sums for the lags ty = 0..=`wy`, tx = -`wx`..=`wx` only:
/// (wy + 1) x (2 wx + 1), row-major, tx = 0 at column wx; the same values bit for bit (the
/// same transforms of the same rows and columns), without ever holding the whole half
/// spectrum: its columns are made in `blocks` blocks, every row transformed again for each
/// (see [`for_spectrum_column_blocks`]), and only the first wy + 1 rows of each block's
/// column transforms are kept. The peak is one block (2 x the map / `blocks`) plus the kept
/// rows ((wy + 1) / rows x 2 x the map).
pub(crate) fn correlation_window(
    row: &(impl Fn(usize, &mut [f64]) + Sync),
    rows: usize,
    cols: usize,
    (wy, wx): (usize, usize),
    blocks: usize,
) -> Vec<f64> {
    let (wy, wx) = (wy.min(rows - 1), wx.min(cols - 1));
    let plans = CorrelationPlans::new(rows, cols);
    let h = plans.h;
    let mut kept = vec![C::default(); (wy + 1) * h];
    for_spectrum_column_blocks(
        row,
        rows,
        cols,
        &plans.r2c,
        blocks,
        (plans.p, plans.column(), plans.scratch_len),
        |k0, bw, block| {
            for ty in 0..=wy {
                kept[ty * h + k0..ty * h + k0 + bw].copy_from_slice(&block[ty * bw..(ty + 1) * bw]);
            }
        },
    );
    let w = 2 * wx + 1;
    let mut out = vec![0.0; (wy + 1) * w];
    plans.inverse_rows(&kept, &mut out, wx);
    out
}

/// [`correlation_half_plane`]'s sums without the half spectrum in memory (it is twice the
/// map): the row transforms are written to a spill file in blocks of `block_cols` spectrum
/// columns (each block rows x width, contiguous), each block's column transforms are made in
/// memory and written back over it, and [`SpilledCorrelation::lag_bands`] reads the lag rows back
/// a band at a time, as often as asked. The same transforms of the same rows and columns:
/// the same values bit for bit. Memory: one block and one band.
pub(crate) struct SpilledCorrelation {
    plans: CorrelationPlans,
    rows: usize,
    cols: usize,
    block_cols: usize,
    file: SpillFile,
}

/// Lag rows per band of [`SpilledCorrelation`] (and rows per write of its row transforms).
pub(crate) const SPILL_BAND_ROWS: usize = 64;
/// The size a block of [`SpilledCorrelation`]'s spectrum columns aims at (bytes).
pub(crate) const SPILL_BLOCK_BYTES: usize = 16 << 20;

/// A block of complex values as the bytes a spill file holds (the file is the run's own,
/// read back by this process: native layout).
fn complex_bytes(v: &[C]) -> &[u8] {
    // SAFETY: Complex<f64> is #[repr(C)] { re: f64, im: f64 }, no padding: 16 initialised
    // bytes per value; u8 has alignment 1.
    unsafe { std::slice::from_raw_parts(v.as_ptr().cast::<u8>(), std::mem::size_of_val(v)) }
}

fn complex_bytes_mut(v: &mut [C]) -> &mut [u8] {
    // SAFETY: as in `complex_bytes`; every byte pattern is a valid f64.
    unsafe { std::slice::from_raw_parts_mut(v.as_mut_ptr().cast::<u8>(), std::mem::size_of_val(v)) }
}

impl SpilledCorrelation {
    /// The spilled transforms of the rows x cols field whose rows `row` writes, in blocks of
    /// `block_cols` spectrum columns (rounded up to whole column tasks), in a spill file in
    /// `folder` (`None`: the system's temporary folder).
    pub(crate) fn new(
        row: &(impl Fn(usize, &mut [f64]) + Sync),
        rows: usize,
        cols: usize,
        block_cols: usize,
        folder: Option<std::path::PathBuf>,
    ) -> Result<Self, StoreError> {
        let plans = CorrelationPlans::new(rows, cols);
        let h = plans.h;
        let block_cols = block_cols.max(1).div_ceil(BLOCK) * BLOCK;
        let mut this = Self {
            plans,
            rows,
            cols,
            block_cols,
            file: SpillFile::new(folder),
        };
        // The row transforms, a band of rows at a time, each band's share of every block
        // written where that block keeps those rows.
        let band_rows = SPILL_BAND_ROWS.min(rows);
        let mut band = vec![C::default(); band_rows * h];
        let mut part = vec![C::default(); band_rows * block_cols.min(h)];
        let blocks: Vec<(usize, usize)> = this.blocks().collect();
        for r0 in (0..rows).step_by(band_rows) {
            let nb = band_rows.min(rows - r0);
            rows_forward_into(row, r0, cols, &this.plans.r2c, &mut band[..nb * h]);
            for &(k0, bw) in &blocks {
                for (o, src) in part[..nb * bw].chunks_mut(bw).zip(band[..nb * h].chunks(h)) {
                    o.copy_from_slice(&src[k0..k0 + bw]);
                }
                let at = this.offset(k0, bw, r0);
                this.file.write_at(at, complex_bytes(&part[..nb * bw]))?;
            }
        }
        drop((band, part));
        // Each block's columns: forward, |X|^2, inverse, in place in the file.
        let mut block = vec![C::default(); rows * block_cols.min(h)];
        for &(k0, bw) in &blocks {
            let part = &mut block[..rows * bw];
            let at = this.offset(k0, bw, 0);
            this.file.read_at(at, complex_bytes_mut(part))?;
            let p = &this.plans;
            for_column_blocks(part, rows, bw, p.p, p.column(), p.scratch_len);
            this.file.write_at(at, complex_bytes(part))?;
        }
        Ok(this)
    }

    /// The blocks of spectrum columns: (first column, width).
    fn blocks(&self) -> impl Iterator<Item = (usize, usize)> {
        let (h, bw) = (self.plans.h, self.block_cols);
        (0..h).step_by(bw).map(move |k0| (k0, bw.min(h - k0)))
    }

    /// Where row r of the block of columns k0.. (`bw` wide) is in the file (bytes): blocks
    /// one after the other, each rows x bw.
    fn offset(&self, k0: usize, bw: usize, r: usize) -> u64 {
        ((k0 * self.rows + r * bw) * std::mem::size_of::<C>()) as u64
    }

    /// A reader of the sums of lag rows in bands, tx = -`wx`..=`wx` (see [`LagBands::read`]).
    pub(crate) fn lag_bands(&self, wx: usize) -> LagBands<'_> {
        let h = self.plans.h;
        let wx = wx.min(self.cols - 1);
        let band_rows = SPILL_BAND_ROWS.min(self.rows);
        LagBands {
            of: self,
            wx,
            spec: vec![C::default(); band_rows * h],
            part: vec![C::default(); band_rows * self.block_cols.min(h)],
            out: vec![0.0; band_rows * (2 * wx + 1)],
        }
    }
}

/// Bands of lag rows read back from a [`SpilledCorrelation`], with their buffers.
pub(crate) struct LagBands<'a> {
    of: &'a SpilledCorrelation,
    wx: usize,
    spec: Vec<C>,
    part: Vec<C>,
    out: Vec<f64>,
}

impl LagBands<'_> {
    /// The sums of lag rows ty0..ty0 + nb (nb <= [`SPILL_BAND_ROWS`], ty0 + nb <= rows),
    /// tx = -wx..=wx: nb rows of 2 wx + 1, row-major, tx = 0 at column wx (the values
    /// [`correlation_window`] has there).
    pub(crate) fn read(&mut self, ty0: usize, nb: usize) -> Result<&mut [f64], StoreError> {
        let of = self.of;
        let h = of.plans.h;
        let w = 2 * self.wx + 1;
        for (k0, bw) in of.blocks() {
            let part = &mut self.part[..nb * bw];
            of.file
                .read_at(of.offset(k0, bw, ty0), complex_bytes_mut(part))?;
            for (o, src) in self.spec[..nb * h].chunks_mut(h).zip(part.chunks(bw)) {
                o[k0..k0 + bw].copy_from_slice(src);
            }
        }
        of.plans
            .inverse_rows(&self.spec[..nb * h], &mut self.out[..nb * w], self.wx);
        Ok(&mut self.out[..nb * w])
    }
}

/// The transforms of the linear correlation of a rows x cols field: real FFTs of q =
/// fast_len(2 cols - 1) along rows (h = q/2 + 1 columns of the half spectrum), complex FFTs
/// of p = fast_len(2 rows - 1) along columns.
struct CorrelationPlans {
    p: usize,
    q: usize,
    h: usize,
    r2c: Arc<dyn RealToComplex<f64>>,
    c2r: Arc<dyn ComplexToReal<f64>>,
    fwd: Arc<dyn Fft<f64>>,
    inv: Arc<dyn Fft<f64>>,
    scratch_len: usize,
}

impl CorrelationPlans {
    fn new(rows: usize, cols: usize) -> Self {
        let p = fast_len(2 * rows - 1);
        let q = fast_len(2 * cols - 1);
        let mut rp = RealFftPlanner::<f64>::new();
        let r2c = rp.plan_fft_forward(q);
        let c2r = rp.plan_fft_inverse(q);
        let h = r2c.complex_len();
        let mut cp = FftPlanner::<f64>::new();
        let fwd = cp.plan_fft_forward(p);
        let inv = cp.plan_fft_inverse(p);
        let scratch_len = fwd
            .get_inplace_scratch_len()
            .max(inv.get_inplace_scratch_len());
        Self {
            p,
            q,
            h,
            r2c,
            c2r,
            fwd,
            inv,
            scratch_len,
        }
    }

    /// Along a column: forward, |X|^2, inverse; lags ty = 0..rows are the first rows entries.
    fn column(&self) -> impl Fn(usize, &mut [C], &mut [C]) + Sync + '_ {
        |_, buf, scratch| {
            self.fwd.process_with_scratch(buf, scratch);
            for v in buf.iter_mut() {
                *v = C::new(v.norm_sqr(), 0.0);
            }
            self.inv.process_with_scratch(buf, scratch);
        }
    }

    /// The sums of each lag row ty from its half spectrum along rows (`src`, rows of h), into
    /// `out`'s rows of 2 `wx` + 1 (tx = -wx..=wx), rows in parallel.
    fn inverse_rows(&self, src: &[C], out: &mut [f64], wx: usize) {
        let (h, q) = (self.h, self.q);
        let scale = 1.0 / (self.p as f64 * q as f64);
        out.par_chunks_mut(2 * wx + 1)
            .zip(src.par_chunks(h))
            .for_each_init(
                || {
                    (
                        vec![C::default(); h],
                        vec![0.0; q],
                        self.c2r.make_scratch_vec(),
                    )
                },
                |(sbuf, rbuf, scratch), (o, src)| {
                    sbuf.copy_from_slice(src);
                    // The spectrum of a real sequence: DC (and Nyquist) are real; drop rounding
                    // residue.
                    sbuf[0].im = 0.0;
                    if q.is_multiple_of(2) {
                        sbuf[h - 1].im = 0.0;
                    }
                    let _ = self.c2r.process_with_scratch(sbuf, rbuf, scratch);
                    for (i, v) in o.iter_mut().enumerate() {
                        let tx = i as isize - wx as isize;
                        let j = if tx >= 0 {
                            tx as usize
                        } else {
                            (q as isize + tx) as usize
                        };
                        *v = rbuf[j] * scale;
                    }
                },
            );
    }
}

/// The 2-D transform of the field whose rows `row` writes (real FFTs of `r2c.len()` along
/// rows, then `column` on each column gathered into a zeroed buffer of `col_len`, its first
/// `rows` values kept), handed over in blocks of half-spectrum columns: `take(k0, bw, block)`
/// gets columns k0..k0 + bw as rows x bw, row-major, blocks in ascending k0. The values are
/// [`rows_forward`] + [`for_column_blocks`]'s bit for bit (each row and each column goes
/// through the same transform); the whole rows x h spectrum is never held, at the cost of
/// every row's FFT once per block.
fn for_spectrum_column_blocks(
    row: &(impl Fn(usize, &mut [f64]) + Sync),
    rows: usize,
    cols: usize,
    r2c: &Arc<dyn RealToComplex<f64>>,
    blocks: usize,
    (col_len, column, scratch_len): (usize, impl Fn(usize, &mut [C], &mut [C]) + Sync, usize),
    mut take: impl FnMut(usize, usize, &[C]),
) {
    let (q, h) = (r2c.len(), r2c.complex_len());
    // Whole column tasks per block (see BLOCK).
    let bw_max = h.div_ceil(blocks.max(1)).div_ceil(BLOCK) * BLOCK;
    let mut block = vec![C::default(); rows * bw_max.min(h)];
    let mut k0 = 0;
    while k0 < h {
        let bw = bw_max.min(h - k0);
        let part = &mut block[..rows * bw];
        part.par_chunks_mut(bw).enumerate().for_each_init(
            || (vec![0.0; q], vec![C::default(); h], r2c.make_scratch_vec()),
            |(buf, spec_row, scratch), (r, out)| {
                row(r, &mut buf[..cols]);
                buf[cols..].fill(0.0);
                // Lengths are the planner's own: cannot fail.
                let _ = r2c.process_with_scratch(buf, spec_row, scratch);
                out.copy_from_slice(&spec_row[k0..k0 + bw]);
            },
        );
        for_column_blocks(part, rows, bw, col_len, &column, scratch_len);
        take(k0, bw, part);
        k0 += bw;
    }
}

/// [`spectrum2_of`] in blocks of columns (see [`for_spectrum_column_blocks`]): the same
/// values, `take(k0, bw, block)` per block, peak one block (the map / `blocks`).
pub(crate) fn spectrum2_blocks(
    row: &(impl Fn(usize, &mut [f64]) + Sync),
    rows: usize,
    cols: usize,
    blocks: usize,
    take: impl FnMut(usize, usize, &[C]),
) {
    let r2c = RealFftPlanner::<f64>::new().plan_fft_forward(cols);
    let fwd: Arc<dyn Fft<f64>> = FftPlanner::new().plan_fft_forward(rows);
    let sl = fwd.get_inplace_scratch_len();
    for_spectrum_column_blocks(
        row,
        rows,
        cols,
        &r2c,
        blocks,
        (
            rows,
            |_, buf: &mut [C], scratch: &mut [C]| fwd.process_with_scratch(buf, scratch),
            sl,
        ),
        take,
    );
}

/// The same allocation seen as its real and imaginary parts, interleaved.
fn complex_as_reals(v: Vec<C>) -> Vec<f64> {
    let mut v = std::mem::ManuallyDrop::new(v);
    let (ptr, len, cap) = (v.as_mut_ptr(), v.len(), v.capacity());
    // SAFETY: Complex<f64> is #[repr(C)] { re: f64, im: f64 }: 16 bytes, alignment 8, so the
    // allocation of `cap` complexes is the allocation (same size, same alignment) of 2 cap
    // f64, its first 2 len initialised; ownership moves (ManuallyDrop: no double free).
    unsafe { Vec::from_raw_parts(ptr.cast::<f64>(), 2 * len, 2 * cap) }
}

/// Lines per task of [`axis_sums`].
pub(crate) const AXIS_BLOCK: usize = 8;

/// The linear autocorrelation sums of sequences of `len` values, summed over them: lags
/// 0..len. Task k's sequences (up to `AXIS_BLOCK`, `len` values each, one after the other)
/// are written by `fill(k, lines)`, which returns how many; tasks 0..`tasks`.
pub(crate) fn axis_sums(
    tasks: usize,
    len: usize,
    fill: impl Fn(usize, &mut [f64]) -> usize + Sync,
) -> Vec<f64> {
    let q = fast_len(2 * len - 1);
    let mut planner = RealFftPlanner::<f64>::new();
    let (r2c, c2r) = (planner.plan_fft_forward(q), planner.plan_fft_inverse(q));
    let h = r2c.complex_len();
    let power = (0..tasks)
        .into_par_iter()
        .fold(
            || {
                let lines = vec![0.0; AXIS_BLOCK * len];
                (
                    vec![0.0; h],
                    lines,
                    vec![0.0; q],
                    vec![Complex::default(); h],
                    r2c.make_scratch_vec(),
                )
            },
            |(mut acc, mut lines, mut buf, mut spec, mut scratch), k| {
                let n = fill(k, &mut lines);
                for line in lines.chunks(len).take(n) {
                    buf[..len].copy_from_slice(line);
                    buf[len..].fill(0.0);
                    // Lengths are the planner's own: cannot fail.
                    let _ = r2c.process_with_scratch(&mut buf, &mut spec, &mut scratch);
                    for (a, v) in acc.iter_mut().zip(&spec) {
                        *a += v.norm_sqr();
                    }
                }
                (acc, lines, buf, spec, scratch)
            },
        )
        .map(|(acc, ..)| acc)
        .reduce(
            || vec![0.0; h],
            |mut a, b| {
                a.iter_mut().zip(&b).for_each(|(x, y)| *x += y);
                a
            },
        );
    let mut spec: Vec<Complex<f64>> = power.iter().map(|&p| Complex::new(p, 0.0)).collect();
    let mut out = vec![0.0; q];
    let _ = c2r.process(&mut spec, &mut out);
    out.truncate(len);
    out.iter_mut().for_each(|v| *v /= q as f64);
    out
}
