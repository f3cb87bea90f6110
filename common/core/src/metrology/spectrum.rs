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
    let q = r2c.len();
    let h = r2c.complex_len();
    let mut spec = vec![C::default(); rows * h];
    spec.par_chunks_mut(h).enumerate().for_each_init(
        || (vec![0.0; q], r2c.make_scratch_vec()),
        |(buf, scratch), (r, out)| {
            row(r, &mut buf[..cols]);
            buf[cols..].fill(0.0);
            // Lengths are the planner's own: cannot fail.
            let _ = r2c.process_with_scratch(buf, out, scratch);
        },
    );
    spec
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
