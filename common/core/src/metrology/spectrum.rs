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
    let p = fast_len(2 * rows - 1);
    let q = fast_len(2 * cols - 1);
    let mut rp = RealFftPlanner::<f64>::new();
    let r2c = rp.plan_fft_forward(q);
    let c2r: Arc<dyn ComplexToReal<f64>> = rp.plan_fft_inverse(q);
    let h = r2c.complex_len();
    let mut spec = rows_forward(row, rows, cols, &r2c);
    let mut cp = FftPlanner::<f64>::new();
    let fwd = cp.plan_fft_forward(p);
    let inv = cp.plan_fft_inverse(p);
    let sl = fwd
        .get_inplace_scratch_len()
        .max(inv.get_inplace_scratch_len());
    // Along columns: forward, |X|^2, inverse; lags ty = 0..rows are the first rows entries.
    for_column_blocks(
        &mut spec,
        rows,
        h,
        p,
        |_, buf, scratch| {
            fwd.process_with_scratch(buf, scratch);
            for v in buf.iter_mut() {
                *v = C::new(v.norm_sqr(), 0.0);
            }
            inv.process_with_scratch(buf, scratch);
        },
        sl,
    );
    let w = 2 * cols - 1;
    // Row ty of sums (w reals) ends before row ty of the spectrum (2h reals) does: w < 2h
    // since h = q/2 + 1 and q >= w. Rows are taken in blocks, each copied out before its
    // sums are written, in order, so a write never lands on an unread spectrum value.
    debug_assert!(w < 2 * h);
    let mut out = complex_as_reals(spec);
    let scale = 1.0 / (p as f64 * q as f64);
    const ROWS_PER_BLOCK: usize = 64;
    let mut block = vec![C::default(); ROWS_PER_BLOCK.min(rows) * h];
    for ty0 in (0..rows).step_by(ROWS_PER_BLOCK) {
        let nb = ROWS_PER_BLOCK.min(rows - ty0);
        for (k, v) in block[..nb * h].iter_mut().enumerate() {
            let at = 2 * (ty0 * h + k);
            *v = C::new(out[at], out[at + 1]);
        }
        out[ty0 * w..(ty0 + nb) * w]
            .par_chunks_mut(w)
            .zip(block[..nb * h].par_chunks(h))
            .for_each_init(
                || (vec![C::default(); h], vec![0.0; q], c2r.make_scratch_vec()),
                |(sbuf, rbuf, scratch), (o, src)| {
                    sbuf.copy_from_slice(src);
                    // The spectrum of a real sequence: DC (and Nyquist) are real; drop rounding
                    // residue.
                    sbuf[0].im = 0.0;
                    if q.is_multiple_of(2) {
                        sbuf[h - 1].im = 0.0;
                    }
                    let _ = c2r.process_with_scratch(sbuf, rbuf, scratch);
                    for (i, v) in o.iter_mut().enumerate() {
                        let tx = i as isize - (cols as isize - 1);
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
    out.truncate(rows * w);
    out
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
