//! Multilevel 2-D discrete wavelet transform with PyWavelets' semantics (`pywt.wavedec2` /
//! `pywt.waverec2`).
//!
//! # Conventions (those of PyWavelets)
//!
//! * One level filters with `dec_lo` / `dec_hi` and keeps every second sample:
//!   `out[k] = sum_j h[j] * x[2k + s - j]`, with `x` extended past its ends by the [`Mode`]
//!   and `s = 1` ('symmetric') or `s = L/2` ('periodization'). Lengths per level are
//!   [`dwt_coeff_len`]: `floor((N + L - 1) / 2)` or `ceil(N / 2)`.
//! * Reconstruction is PyWavelets' `idwt`: upsample, filter with `rec_lo` / `rec_hi`, keep
//!   the 'valid' part: `2N - L + 2` samples ('symmetric') or `2N` ('periodization').
//! * 2-D: cA = low / low; cH = low along x (rows, axis 1), high along y (columns, axis 0);
//!   cV = high x / low y; cD = high / high. [`Coeffs2::details`] runs from the coarsest
//!   level to the finest, as PyWavelets' list `[cA_n, (cH_n, cV_n, cD_n), ..., (cH_1, cV_1, cD_1)]`.
//! * [`waverec2`] trims the approximation of each level to its detail shape before the next
//!   inverse step (PyWavelets' `_match_coeff_dims`), and, like PyWavelets, does not trim the
//!   final output: an odd input side comes back one sample longer. Crop it to the original size.
//!
//! # Order of the separable passes
//!
//! A level is `A_y X A_x^T`: the pass along x (within rows, axis 1) and the pass along y
//! (down columns, axis 0) commute exactly in exact arithmetic, so their order only moves
//! rounding (~1e-16 relative) and the result is the "rows first, then columns" transform to
//! that precision. (PyWavelets itself filters axis 0 first when decomposing and axis 1 first
//! when reconstructing.) We run the y-pass first and the x-pass second in both directions,
//! because that order lets one task turn a few input rows into finished output rows with no
//! full-size intermediate array (see "Speed").
//!
//! # Speed
//!
//! Each output row of a level is produced by one task, from a few input rows, with no
//! full-size intermediate array. The y-pass is a weighted sum of `L` (decomposition) or `L/2`
//! per parity (reconstruction) whole input rows; the x-pass on that single row runs in
//! polyphase form (even / odd samples split once), so both are contiguous multiply-adds. The
//! kernels work on register blocks of 16 values that keep their sums in registers across all
//! taps, so each input value is loaded once per tap and nothing is re-read from memory
//! accumulators. Tasks (bands of output rows) run on rayon; scratch is allocated per task,
//! never per sample. On x86-64 CPUs with AVX2 and FMA the same code is compiled a second time
//! for those features and chosen at run time, so results can differ in the last bit between
//! machines with and without FMA.

use rayon::prelude::*;

use surfstream_core::raster::{Raster, Shape};

use crate::error::{check_raster, Result, WaveletError};
use crate::wavelet::{dwt_coeff_len, Mode, Wavelet};

/// Highest decomposition level [`wavedec2`] accepts. PyWavelets allows any level (with a
/// warning past [`crate::dwt_max_level`]); 64 levels is far past any map that fits in memory.
pub const MAX_LEVEL: usize = 64;

/// The kernels' input: a whole raster (a coefficient array) as a strided view.
fn view_of(a: &Raster<f64>) -> View<'_> {
    View {
        data: a.values(),
        rows: a.rows(),
        cols: a.cols(),
        stride: a.cols(),
    }
}

/// The three detail sub-bands of one level, each of the level's coefficient shape.
#[derive(Debug, Clone, PartialEq)]
pub struct Details2 {
    /// Horizontal detail: low-pass along x (rows), high-pass along y (PyWavelets' cH).
    pub h: Raster<f64>,
    /// Vertical detail: high-pass along x, low-pass along y (cV).
    pub v: Raster<f64>,
    /// Diagonal detail: high-pass along both axes (cD).
    pub d: Raster<f64>,
}

/// The result of [`wavedec2`]: PyWavelets' list `[cA_n, (cH_n, cV_n, cD_n), ..., (cH_1, cV_1, cD_1)]`.
#[derive(Debug, Clone, PartialEq)]
pub struct Coeffs2 {
    /// Approximation at the deepest level, cA_n.
    pub approx: Raster<f64>,
    /// Details, coarsest level (n) first and finest level (1) last, as in PyWavelets' list.
    pub details: Vec<Details2>,
}

impl Coeffs2 {
    /// Number of decomposition levels (0 when only the approximation is present).
    pub fn level(&self) -> usize {
        self.details.len()
    }
}

/// A possibly trimmed, read-only window on a row-major buffer.
#[derive(Clone, Copy)]
struct View<'a> {
    data: &'a [f64],
    rows: usize,
    cols: usize,
    stride: usize,
}

/// Rows of a coefficient array as the kernels read them: a whole array ([`View`]) or only the
/// rows one band needs (the streamed pass, [`crate::stream`]). Every output row is computed
/// from the rows it reads by the same code either way, so the results are bit-identical.
pub(crate) trait Rows: Sync {
    /// Number of rows of the whole (logical) array: the border extension wraps on it.
    fn n_rows(&self) -> usize;
    fn n_cols(&self) -> usize;
    /// Row `r` (`r < n_rows()`), `n_cols()` values.
    fn row(&self, r: usize) -> &[f64];
}

impl<T: Rows + ?Sized> Rows for &T {
    #[inline(always)]
    fn n_rows(&self) -> usize {
        (**self).n_rows()
    }
    #[inline(always)]
    fn n_cols(&self) -> usize {
        (**self).n_cols()
    }
    #[inline(always)]
    fn row(&self, r: usize) -> &[f64] {
        (**self).row(r)
    }
}

impl Rows for View<'_> {
    #[inline(always)]
    fn n_rows(&self) -> usize {
        self.rows
    }
    #[inline(always)]
    fn n_cols(&self) -> usize {
        self.cols
    }
    #[inline(always)]
    fn row(&self, r: usize) -> &[f64] {
        &self.data[r * self.stride..r * self.stride + self.cols]
    }
}

impl<'a> View<'a> {
    /// The top-left `rows x cols` corner (PyWavelets' trim of a one-larger approximation).
    fn corner(self, rows: usize, cols: usize) -> View<'a> {
        View { rows, cols, ..self }
    }
}

/// Index of the sample that position `i` (possibly outside `0..n`) reads under `mode`.
#[inline(always)]
fn ext_index(i: isize, n: usize, mode: Mode) -> usize {
    match mode {
        Mode::Symmetric => {
            // Half-sample symmetric extension is periodic with period 2n (mirror, then mirror back).
            let m = i.rem_euclid(2 * n as isize) as usize;
            if m < n {
                m
            } else {
                2 * n - 1 - m
            }
        }
        Mode::Periodization => {
            // Odd lengths are padded with one copy of the last sample, then wrapped.
            let p = n + n % 2;
            let m = i.rem_euclid(p as isize) as usize;
            m.min(n - 1)
        }
    }
}

/// `a * b + c`, either as two roundings or as one fused multiply-add. Kernels are generic over
/// this so that the AVX2 build gets FMA while the baseline build never calls libm's slow fma.
trait Madd {
    fn madd(a: f64, b: f64, c: f64) -> f64;
}

struct Plain;

impl Madd for Plain {
    #[inline(always)]
    fn madd(a: f64, b: f64, c: f64) -> f64 {
        a * b + c
    }
}

#[cfg(target_arch = "x86_64")]
struct Fused;

#[cfg(target_arch = "x86_64")]
impl Madd for Fused {
    #[inline(always)]
    fn madd(a: f64, b: f64, c: f64) -> f64 {
        a.mul_add(b, c)
    }
}

// Not surfstream_core::avx2_dispatch!: that macro promises both copies give the same bits,
// and the FMA path here deliberately rounds once per multiply-add (different bits), chosen by
// the caller's `fast` option, and needs the "fma" feature as well as AVX2.
#[cfg(target_arch = "x86_64")]
fn have_avx2_fma() -> bool {
    std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma")
}

#[cfg(not(target_arch = "x86_64"))]
fn have_avx2_fma() -> bool {
    false
}

// ---------------------------------------------------------------------------------------------
// Analysis (decomposition)

/// One wavelet's decomposition filters arranged for one mode.
struct Analysis {
    /// Run the AVX2 + FMA build of the kernels; only ever true when the CPU has both.
    #[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
    fused: bool,
    mode: Mode,
    flen: usize,
    half: usize,
    /// `s` in `out[k] = sum_j h[j] x[2k + s - j]`.
    shift: isize,
    lo: &'static [f64],
    hi: &'static [f64],
    /// Polyphase weights for the x-pass: `g0[i] = h[L-1-2i]` multiplies the even extended
    /// samples, `g1[i] = h[L-2-2i]` the odd ones.
    g0_lo: Vec<f64>,
    g1_lo: Vec<f64>,
    g0_hi: Vec<f64>,
    g1_hi: Vec<f64>,
}

impl Analysis {
    fn new(w: &Wavelet, mode: Mode) -> Self {
        Self::with_kernels(w, mode, true)
    }

    /// `fast: false` forces the portable kernels (tests compare the two builds).
    fn with_kernels(w: &Wavelet, mode: Mode, fast: bool) -> Self {
        let (lo, hi) = (w.dec_lo(), w.dec_hi());
        let flen = lo.len();
        let half = flen / 2;
        let poly = |h: &[f64], off: usize| (0..half).map(|i| h[flen - off - 2 * i]).collect();
        Analysis {
            fused: fast && have_avx2_fma(),
            mode,
            flen,
            half,
            shift: match mode {
                Mode::Symmetric => 1,
                Mode::Periodization => half as isize,
            },
            lo,
            hi,
            g0_lo: poly(lo, 1),
            g1_lo: poly(lo, 2),
            g0_hi: poly(hi, 1),
            g1_hi: poly(hi, 2),
        }
    }

    fn out_len(&self, n: usize) -> usize {
        dwt_coeff_len(n, self.flen, self.mode)
    }

    /// Signal position read by extended sample 0 (output 0, last tap).
    fn first_pos(&self) -> isize {
        self.shift - (self.flen as isize - 1)
    }
}

/// Split the extended signal `e[u] = x[ext(u + first)]` into its even (`e0`) and odd (`e1`)
/// samples; each gets `e0.len()` values.
#[inline(always)]
fn deinterleave_ext(x: &[f64], first: isize, mode: Mode, e0: &mut [f64], e1: &mut [f64]) {
    let n = x.len() as isize;
    let len = e0.len() as isize;
    // Range of m whose two samples 2m + first and 2m + 1 + first both lie inside x.
    let m_start = if first >= 0 { 0 } else { (1 - first) / 2 }.min(len);
    let m_end = if n - 2 - first < 0 {
        m_start
    } else {
        ((n - 2 - first) / 2 + 1).clamp(m_start, len)
    };
    let at = |i: isize| x[ext_index(i, x.len(), mode)];
    for m in (0..m_start).chain(m_end..len) {
        e0[m as usize] = at(2 * m + first);
        e1[m as usize] = at(2 * m + 1 + first);
    }
    let base = (2 * m_start + first) as usize;
    let (ms, me) = (m_start as usize, m_end as usize);
    for ((a, b), pair) in e0[ms..me]
        .iter_mut()
        .zip(e1[ms..me].iter_mut())
        .zip(x[base..].chunks_exact(2))
    {
        *a = pair[0];
        *b = pair[1];
    }
}

/// Values per register block of the kernels: 16 f64 are four AVX2 registers per accumulator
/// set, enough independent multiply-add chains to hide the FMA latency, few enough to stay
/// in registers. Each kernel loads every input value once per block and tap and keeps its
/// sums in registers across all taps (no read-modify-write of memory accumulators).
const LANES: usize = 16;

/// x-pass of one row: low-pass into `lo` and, when `D`, high-pass into `hi`.
#[inline(always)]
fn row_analysis<M: Madd, const D: bool>(
    x: &[f64],
    an: &Analysis,
    e0: &mut [f64],
    e1: &mut [f64],
    lo: &mut [f64],
    hi: &mut [f64],
) {
    let n_out = lo.len();
    deinterleave_ext(x, an.first_pos(), an.mode, e0, e1);
    let taps = || {
        an.g0_lo
            .iter()
            .zip(&an.g1_lo)
            .zip(an.g0_hi.iter().zip(&an.g1_hi))
            .enumerate()
    };
    let full = n_out - n_out % LANES;
    for k in (0..full).step_by(LANES) {
        let mut al = [0.0f64; LANES];
        let mut ah = [0.0f64; LANES];
        for (i, ((&a, &b), (&c, &d))) in taps() {
            let (x0, x1) = (&e0[k + i..k + i + LANES], &e1[k + i..k + i + LANES]);
            if D {
                for (((l, h), &u), &v) in al.iter_mut().zip(ah.iter_mut()).zip(x0).zip(x1) {
                    *l = M::madd(b, v, M::madd(a, u, *l));
                    *h = M::madd(d, v, M::madd(c, u, *h));
                }
            } else {
                for ((l, &u), &v) in al.iter_mut().zip(x0).zip(x1) {
                    *l = M::madd(b, v, M::madd(a, u, *l));
                }
            }
        }
        lo[k..k + LANES].copy_from_slice(&al);
        if D {
            hi[k..k + LANES].copy_from_slice(&ah);
        }
    }
    for k in full..n_out {
        let (mut l, mut h) = (0.0, 0.0);
        for (i, ((&a, &b), (&c, &d))) in taps() {
            let (u, v) = (e0[k + i], e1[k + i]);
            l = M::madd(b, v, M::madd(a, u, l));
            if D {
                h = M::madd(d, v, M::madd(c, u, h));
            }
        }
        lo[k] = l;
        if D {
            hi[k] = h;
        }
    }
}

/// y-pass for one output row: `lo[c] = sum_j dec_lo[j] * taps[j][c]` (and `hi` when `D`).
/// `taps` holds the `L` input rows (already extended), so this is a column-vectorised sum.
#[inline(always)]
fn col_analysis<M: Madd, const D: bool>(
    taps: &[&[f64]],
    an: &Analysis,
    lo: &mut [f64],
    hi: &mut [f64],
) {
    let cols = lo.len();
    let full = cols - cols % LANES;
    for c in (0..full).step_by(LANES) {
        let mut al = [0.0f64; LANES];
        let mut ah = [0.0f64; LANES];
        for ((row, &wl), &wh) in taps.iter().zip(an.lo).zip(an.hi) {
            let r = &row[c..c + LANES];
            if D {
                for ((l, h), &v) in al.iter_mut().zip(ah.iter_mut()).zip(r) {
                    *l = M::madd(wl, v, *l);
                    *h = M::madd(wh, v, *h);
                }
            } else {
                for (l, &v) in al.iter_mut().zip(r) {
                    *l = M::madd(wl, v, *l);
                }
            }
        }
        lo[c..c + LANES].copy_from_slice(&al);
        if D {
            hi[c..c + LANES].copy_from_slice(&ah);
        }
    }
    for c in full..cols {
        let (mut l, mut h) = (0.0, 0.0);
        for ((row, &wl), &wh) in taps.iter().zip(an.lo).zip(an.hi) {
            l = M::madd(wl, row[c], l);
            if D {
                h = M::madd(wh, row[c], h);
            }
        }
        lo[c] = l;
        if D {
            hi[c] = h;
        }
    }
}

/// Output rows of one decomposition task. `D = false`: only `ca` is produced (the others are
/// empty), which is all the datum needs.
struct DecOut<'o> {
    ca: &'o mut [f64],
    ch: &'o mut [f64],
    cv: &'o mut [f64],
    cd: &'o mut [f64],
}

/// Produce output rows `k0 ..` (as many as `out.ca` holds) of one decomposition level.
#[inline(always)]
fn dec_task<M: Madd, const D: bool, S: Rows>(x: &S, an: &Analysis, k0: usize, out: DecOut<'_>) {
    let c2 = an.out_len(x.n_cols());
    let e_len = c2 + an.half - 1;
    let mut e0 = vec![0.0; e_len];
    let mut e1 = vec![0.0; e_len];
    let mut lowy = vec![0.0; x.n_cols()];
    let mut highy = if D { vec![0.0; x.n_cols()] } else { Vec::new() };
    let mut taps: Vec<&[f64]> = Vec::with_capacity(an.flen);
    let n_rows = out.ca.len() / c2;
    for t in 0..n_rows {
        let k = k0 + t;
        taps.clear();
        taps.extend((0..an.flen).map(|j| {
            let pos = 2 * k as isize + an.shift - j as isize;
            x.row(ext_index(pos, x.n_rows(), an.mode))
        }));
        col_analysis::<M, D>(&taps, an, &mut lowy, &mut highy);
        let row = t * c2..(t + 1) * c2;
        if D {
            // low y -> cA (low x), cV (high x); high y -> cH (low x), cD (high x).
            row_analysis::<M, true>(
                &lowy,
                an,
                &mut e0,
                &mut e1,
                &mut out.ca[row.clone()],
                &mut out.cv[row.clone()],
            );
            row_analysis::<M, true>(
                &highy,
                an,
                &mut e0,
                &mut e1,
                &mut out.ch[row.clone()],
                &mut out.cd[row],
            );
        } else {
            row_analysis::<M, false>(&lowy, an, &mut e0, &mut e1, &mut out.ca[row], &mut []);
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn dec_task_avx2<const D: bool, S: Rows>(x: &S, an: &Analysis, k0: usize, out: DecOut<'_>) {
    dec_task::<Fused, D, S>(x, an, k0, out)
}

fn dec_task_dispatch<const D: bool, S: Rows>(x: &S, an: &Analysis, k0: usize, out: DecOut<'_>) {
    #[cfg(target_arch = "x86_64")]
    if an.fused {
        // SAFETY: `fused` is only set when the CPU supports AVX2 and FMA (Analysis::new).
        return unsafe { dec_task_avx2::<D, S>(x, an, k0, out) };
    }
    dec_task::<Plain, D, S>(x, an, k0, out)
}

/// Rows per rayon task: about 8 tasks per thread for load balance, but at least ~4096
/// coefficients each so that small deep levels are not drowned in scheduling overhead.
fn rows_per_task(rows: usize, cols: usize) -> usize {
    let tasks = 8 * rayon::current_num_threads().max(1);
    rows.div_ceil(tasks)
        .max(4096usize.div_ceil(cols.max(1)))
        .max(1)
}

/// One decomposition level of `x`: cA and, when `details`, (cH, cV, cD).
fn dec_level(x: View<'_>, an: &Analysis, details: bool) -> (Raster<f64>, Option<Details2>) {
    let (r2, c2) = (an.out_len(x.rows), an.out_len(x.cols));
    let shape = Shape::new(r2, c2);
    let mut ca = Raster::filled(shape, 0.0);
    let chunk = rows_per_task(r2, c2) * c2;
    if details {
        let mut ch = Raster::filled(shape, 0.0);
        let mut cv = Raster::filled(shape, 0.0);
        let mut cd = Raster::filled(shape, 0.0);
        ca.values_mut()
            .par_chunks_mut(chunk)
            .zip(ch.values_mut().par_chunks_mut(chunk))
            .zip(cv.values_mut().par_chunks_mut(chunk))
            .zip(cd.values_mut().par_chunks_mut(chunk))
            .enumerate()
            .for_each(|(t, (((ca, ch), cv), cd))| {
                let out = DecOut { ca, ch, cv, cd };
                dec_task_dispatch::<true, _>(&x, an, t * chunk / c2, out);
            });
        let det = Details2 {
            h: ch,
            v: cv,
            d: cd,
        };
        (ca, Some(det))
    } else {
        ca.values_mut()
            .par_chunks_mut(chunk)
            .enumerate()
            .for_each(|(t, ca)| {
                let out = DecOut {
                    ca,
                    ch: &mut [],
                    cv: &mut [],
                    cd: &mut [],
                };
                dec_task_dispatch::<false, _>(&x, an, t * chunk / c2, out);
            });
        (ca, None)
    }
}

/// Multilevel 2-D DWT, as `pywt.wavedec2(data, wavelet, mode, level)`.
///
/// `data` is row-major `rows x cols`. `level` may exceed [`crate::dwt_max_level`] (PyWavelets
/// only warns then: every coefficient feels the border extension) but not [`MAX_LEVEL`];
/// level 0 returns the input as the approximation.
pub fn wavedec2(
    data: &[f64],
    rows: usize,
    cols: usize,
    wavelet: &Wavelet,
    mode: Mode,
    level: usize,
) -> Result<Coeffs2> {
    check_raster(data.len(), rows, cols)?;
    check_level(level)?;
    Ok(wavedec2_with(
        data,
        rows,
        cols,
        &Analysis::new(wavelet, mode),
        level,
    ))
}

/// [`wavedec2`] after the argument checks.
fn wavedec2_with(data: &[f64], rows: usize, cols: usize, an: &Analysis, level: usize) -> Coeffs2 {
    let mut details = Vec::with_capacity(level);
    let mut approx: Option<Raster<f64>> = None;
    for _ in 0..level {
        let x = match &approx {
            Some(a) => view_of(a),
            None => View {
                data,
                rows,
                cols,
                stride: cols,
            },
        };
        let (a, d) = dec_level(x, an, true);
        // dec_level(.., true) always returns details.
        details.extend(d);
        approx = Some(a);
    }
    details.reverse();
    let approx = match approx {
        Some(a) => a,
        None => {
            // Level 0: the input itself (the caller checked its size).
            let mut a = Raster::filled(Shape::new(rows, cols), 0.0);
            a.values_mut().copy_from_slice(data);
            a
        }
    };
    Coeffs2 { approx, details }
}

fn check_level(level: usize) -> Result<()> {
    if level > MAX_LEVEL {
        return Err(WaveletError::LevelTooHigh {
            level,
            max: MAX_LEVEL,
        });
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// Synthesis (reconstruction)

/// One wavelet's reconstruction filters arranged for one mode.
///
/// Output sample `2q + p` (parity `p`) is `sum_j rec[2j + r_p] * c[q - j + off_p]`, `j < L/2`,
/// with `r_p = p, off_p = L/2 - 1` ('symmetric', PyWavelets' `upsampling_convolution_valid_sf`)
/// or `r_p = (p + L/2 - 1) % 2, off_p = (p - r_p + L/2 - 1) / 2` with `c` indices taken modulo
/// its length ('periodization'). The latter is the transpose of the periodized analysis.
struct Synthesis {
    /// As [`Analysis::fused`].
    #[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
    fused: bool,
    mode: Mode,
    half: usize,
    off: [isize; 2],
    /// `w_lo[p][j] = rec_lo[2j + r_p]` (y-pass weights); `w_hi` likewise.
    w_lo: [Vec<f64>; 2],
    w_hi: [Vec<f64>; 2],
    /// The same weights reversed, `v[p][i] = w[p][L/2 - 1 - i]`, for the x-pass, which runs
    /// forward over the extended row.
    v_lo: [Vec<f64>; 2],
    v_hi: [Vec<f64>; 2],
}

impl Synthesis {
    fn new(w: &Wavelet, mode: Mode) -> Self {
        Self::with_kernels(w, mode, true)
    }

    /// `fast: false` forces the portable kernels.
    fn with_kernels(w: &Wavelet, mode: Mode, fast: bool) -> Self {
        let (rec_lo, rec_hi) = (w.rec_lo(), w.rec_hi());
        let half = rec_lo.len() / 2;
        let shift = match mode {
            Mode::Symmetric => 2 * half as isize - 2,
            Mode::Periodization => half as isize - 1,
        };
        let r = |p: isize| (p + shift).rem_euclid(2);
        let off = [0, 1].map(|p| (p - r(p) + shift) / 2);
        let w_of =
            |h: &[f64]| [0, 1].map(|p| (0..half).map(|j| h[2 * j + r(p) as usize]).collect());
        let rev = |w: &[Vec<f64>; 2]| {
            [0, 1].map(|p: usize| w[p].iter().rev().copied().collect::<Vec<f64>>())
        };
        let (w_lo, w_hi): ([Vec<f64>; 2], [Vec<f64>; 2]) = (w_of(rec_lo), w_of(rec_hi));
        let (v_lo, v_hi) = (rev(&w_lo), rev(&w_hi));
        Synthesis {
            fused: fast && have_avx2_fma(),
            mode,
            half,
            off,
            w_lo,
            w_hi,
            v_lo,
            v_hi,
        }
    }

    /// Output length of one inverse step from `n` coefficients; `None` if `n` is too short
    /// for the filter ('symmetric' needs `n >= L/2`, as PyWavelets).
    fn out_len(&self, n: usize) -> Option<usize> {
        match self.mode {
            Mode::Symmetric => (n >= self.half && n > 0).then(|| 2 * (n + 1 - self.half)),
            Mode::Periodization => (n > 0).then_some(2 * n),
        }
    }

    /// Index of the coefficient read at position `i` (only periodization wraps: in symmetric
    /// mode the 'valid' output never reads outside).
    #[inline(always)]
    fn coeff_index(&self, i: isize, n: usize) -> usize {
        match self.mode {
            Mode::Symmetric => i as usize,
            Mode::Periodization => i.rem_euclid(n as isize) as usize,
        }
    }

    /// First coefficient position the x-pass reads, relative to which it builds its extended row.
    fn first_pos(&self) -> isize {
        self.off[0].min(self.off[1]) - (self.half as isize - 1)
    }

    /// Extended length the x-pass reads for `n` coefficients.
    fn ext_len(&self, n: usize) -> usize {
        let spread = (self.off[0] - self.off[1]).unsigned_abs();
        match self.mode {
            Mode::Symmetric => n,
            Mode::Periodization => n + self.half - 1 + spread,
        }
    }
}

/// Values per parity in a register block of the x-pass synthesis (two parities: 16 sums).
const HALF_LANES: usize = LANES / 2;

/// x-pass of one row: `out` (length `2 nq`) from `lo` and, when `D`, `hi` (length `n`).
/// `ext_lo` / `ext_hi` are scratch for the wrapped copies periodization reads.
#[inline(always)]
fn row_synthesis<M: Madd, const D: bool>(
    lo: &[f64],
    hi: &[f64],
    sy: &Synthesis,
    ext_lo: &mut [f64],
    ext_hi: &mut [f64],
    out: &mut [f64],
) {
    let n = lo.len();
    let nq = out.len() / 2;
    let first = sy.first_pos();
    // In symmetric mode the row is read as is; periodization reads a wrapped copy.
    let (el, eh): (&[f64], &[f64]) = match sy.mode {
        Mode::Symmetric => (lo, hi),
        Mode::Periodization => {
            for (u, e) in ext_lo.iter_mut().enumerate() {
                *e = lo[sy.coeff_index(u as isize + first, n)];
            }
            if D {
                for (u, e) in ext_hi.iter_mut().enumerate() {
                    *e = hi[sy.coeff_index(u as isize + first, n)];
                }
            }
            (ext_lo, ext_hi)
        }
    };
    // out[2q + p] = sum_i v[p][i] * e[q + i + base_p] over lo (and hi).
    let base = [0, 1].map(|p| (sy.off[p] - (sy.half as isize - 1) - first) as usize);
    let taps = || {
        sy.v_lo[0]
            .iter()
            .zip(&sy.v_hi[0])
            .zip(sy.v_lo[1].iter().zip(&sy.v_hi[1]))
            .enumerate()
    };
    let full = nq - nq % HALF_LANES;
    for q in (0..full).step_by(HALF_LANES) {
        let mut o0 = [0.0f64; HALF_LANES];
        let mut o1 = [0.0f64; HALF_LANES];
        for (i, ((&a0, &b0), (&a1, &b1))) in taps() {
            let (s0, s1) = (q + i + base[0], q + i + base[1]);
            let (x0, x1) = (&el[s0..s0 + HALF_LANES], &el[s1..s1 + HALF_LANES]);
            if D {
                let (y0, y1) = (&eh[s0..s0 + HALF_LANES], &eh[s1..s1 + HALF_LANES]);
                for ((o, &x), &y) in o0.iter_mut().zip(x0).zip(y0) {
                    *o = M::madd(b0, y, M::madd(a0, x, *o));
                }
                for ((o, &x), &y) in o1.iter_mut().zip(x1).zip(y1) {
                    *o = M::madd(b1, y, M::madd(a1, x, *o));
                }
            } else {
                for (o, &x) in o0.iter_mut().zip(x0) {
                    *o = M::madd(a0, x, *o);
                }
                for (o, &x) in o1.iter_mut().zip(x1) {
                    *o = M::madd(a1, x, *o);
                }
            }
        }
        let dst = &mut out[2 * q..2 * (q + HALF_LANES)];
        for ((pair, &u), &v) in dst.chunks_exact_mut(2).zip(&o0).zip(&o1) {
            pair[0] = u;
            pair[1] = v;
        }
    }
    for q in full..nq {
        let (mut u, mut v) = (0.0, 0.0);
        for (i, ((&a0, &b0), (&a1, &b1))) in taps() {
            let (s0, s1) = (q + i + base[0], q + i + base[1]);
            u = M::madd(a0, el[s0], u);
            v = M::madd(a1, el[s1], v);
            if D {
                u = M::madd(b0, eh[s0], u);
                v = M::madd(b1, eh[s1], v);
            }
        }
        out[2 * q] = u;
        out[2 * q + 1] = v;
    }
}

/// Rows one y-pass synthesis step reads: for each tap, the rows of a, cH, cV, cD.
struct SynTaps<'a> {
    a: Vec<&'a [f64]>,
    h: Vec<&'a [f64]>,
    v: Vec<&'a [f64]>,
    d: Vec<&'a [f64]>,
}

/// y-pass for one output row of parity `p`: `lowx = sum_j w_lo a_j + w_hi cH_j` and, when
/// `D`, `highx = sum_j w_lo cV_j + w_hi cD_j`.
#[inline(always)]
fn col_synthesis<M: Madd, const D: bool>(
    t: &SynTaps<'_>,
    wl: &[f64],
    wh: &[f64],
    lowx: &mut [f64],
    highx: &mut [f64],
) {
    let cols = lowx.len();
    let full = cols - cols % LANES;
    for c in (0..full).step_by(LANES) {
        let mut al = [0.0f64; LANES];
        let mut ah = [0.0f64; LANES];
        for (j, (&u, &w)) in wl.iter().zip(wh).enumerate() {
            let ar = &t.a[j][c..c + LANES];
            if D {
                let hr = &t.h[j][c..c + LANES];
                let vr = &t.v[j][c..c + LANES];
                let dr = &t.d[j][c..c + LANES];
                for ((l, &a), &h) in al.iter_mut().zip(ar).zip(hr) {
                    *l = M::madd(w, h, M::madd(u, a, *l));
                }
                for ((l, &v), &d) in ah.iter_mut().zip(vr).zip(dr) {
                    *l = M::madd(w, d, M::madd(u, v, *l));
                }
            } else {
                for (l, &a) in al.iter_mut().zip(ar) {
                    *l = M::madd(u, a, *l);
                }
            }
        }
        lowx[c..c + LANES].copy_from_slice(&al);
        if D {
            highx[c..c + LANES].copy_from_slice(&ah);
        }
    }
    for c in full..cols {
        let (mut l, mut h) = (0.0, 0.0);
        for (j, (&u, &w)) in wl.iter().zip(wh).enumerate() {
            l = M::madd(u, t.a[j][c], l);
            if D {
                l = M::madd(w, t.h[j][c], l);
                h = M::madd(w, t.d[j][c], M::madd(u, t.v[j][c], h));
            }
        }
        lowx[c] = l;
        if D {
            highx[c] = h;
        }
    }
}

/// Inputs of one inverse level: the (trimmed) approximation and, unless approximating only,
/// the three detail bands of the same shape.
#[derive(Clone, Copy)]
struct RecIn<'a, A: Rows = View<'a>> {
    a: A,
    hvd: Option<[View<'a>; 3]>,
}

/// Produce output rows `n0 ..` (as many as `out` holds) of one inverse level.
#[inline(always)]
fn rec_task<M: Madd, const D: bool, A: Rows>(
    inp: RecIn<'_, A>,
    sy: &Synthesis,
    n0: usize,
    out: &mut [f64],
) {
    let (r2, c2) = (inp.a.n_rows(), inp.a.n_cols());
    let Some(c_out) = sy.out_len(c2) else {
        return;
    };
    let hvd = inp.hvd.filter(|_| D);
    let mut lowx = vec![0.0; c2];
    let mut highx = if D { vec![0.0; c2] } else { Vec::new() };
    let mut ext_lo = vec![0.0; sy.ext_len(c2)];
    let mut ext_hi = if D {
        vec![0.0; sy.ext_len(c2)]
    } else {
        Vec::new()
    };
    let mut taps = SynTaps {
        a: Vec::with_capacity(sy.half),
        h: Vec::with_capacity(sy.half),
        v: Vec::with_capacity(sy.half),
        d: Vec::with_capacity(sy.half),
    };
    for (t, out_row) in out.chunks_exact_mut(c_out).enumerate() {
        let nr = n0 + t;
        let (q, p) = ((nr / 2) as isize, nr % 2);
        // y-pass: a weighted sum of L/2 rows of (a, cH) -> low x, of (cV, cD) -> high x.
        let rows = (0..sy.half).map(|j| sy.coeff_index(q - j as isize + sy.off[p], r2));
        taps.a.clear();
        taps.a.extend(rows.clone().map(|r| inp.a.row(r)));
        if let Some([h, v, d]) = &hvd {
            taps.h.clear();
            taps.v.clear();
            taps.d.clear();
            taps.h.extend(rows.clone().map(|r| h.row(r)));
            taps.v.extend(rows.clone().map(|r| v.row(r)));
            taps.d.extend(rows.map(|r| d.row(r)));
        }
        col_synthesis::<M, D>(&taps, &sy.w_lo[p], &sy.w_hi[p], &mut lowx, &mut highx);
        row_synthesis::<M, D>(&lowx, &highx, sy, &mut ext_lo, &mut ext_hi, out_row);
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn rec_task_avx2<const D: bool, A: Rows>(
    inp: RecIn<'_, A>,
    sy: &Synthesis,
    n0: usize,
    out: &mut [f64],
) {
    rec_task::<Fused, D, A>(inp, sy, n0, out)
}

fn rec_task_dispatch<const D: bool, A: Rows>(
    inp: RecIn<'_, A>,
    sy: &Synthesis,
    n0: usize,
    out: &mut [f64],
) {
    #[cfg(target_arch = "x86_64")]
    if sy.fused {
        // SAFETY: `fused` is only set when the CPU supports AVX2 and FMA (Synthesis::new).
        return unsafe { rec_task_avx2::<D, A>(inp, sy, n0, out) };
    }
    rec_task::<Plain, D, A>(inp, sy, n0, out)
}

/// One inverse level. Shapes must already be checked: `a` and the details equal, and long
/// enough for the filter.
fn rec_level(inp: RecIn<'_>, sy: &Synthesis) -> Result<Raster<f64>> {
    let too_short = || {
        WaveletError::CoeffShape(format!(
            "{} x {} coefficients are too few for a filter of length {} in {} mode",
            inp.a.rows,
            inp.a.cols,
            2 * sy.half,
            sy.mode
        ))
    };
    let rows = sy.out_len(inp.a.rows).ok_or_else(too_short)?;
    let cols = sy.out_len(inp.a.cols).ok_or_else(too_short)?;
    let mut out = Raster::filled(Shape::new(rows, cols), 0.0);
    let chunk = rows_per_task(rows, cols) * cols;
    out.values_mut()
        .par_chunks_mut(chunk)
        .enumerate()
        .for_each(|(t, o)| {
            if inp.hvd.is_some() {
                rec_task_dispatch::<true, _>(inp, sy, t * chunk / cols, o);
            } else {
                rec_task_dispatch::<false, _>(inp, sy, t * chunk / cols, o);
            }
        });
    Ok(out)
}

/// The approximation of one level, trimmed as PyWavelets' `_match_coeff_dims`: it may exceed
/// the detail shape by one along each axis (odd sizes); anything else is an error.
fn match_dims<'a>(a: &'a Raster<f64>, rows: usize, cols: usize) -> Result<View<'a>> {
    let fits = |n: usize, m: usize| n == m || n == m + 1;
    if !fits(a.rows(), rows) || !fits(a.cols(), cols) {
        return Err(WaveletError::CoeffShape(format!(
            "approximation {} does not fit details {rows} x {cols}",
            a.shape()
        )));
    }
    Ok(view_of(a).corner(rows, cols))
}

/// Multilevel 2-D inverse DWT, as `pywt.waverec2(coeffs, wavelet, mode)`.
///
/// The output has PyWavelets' shape: for an odd input side it is one sample longer than the
/// data given to [`wavedec2`]; crop it. Errors if the shapes do not chain as `wavedec2` makes
/// them.
pub fn waverec2(coeffs: &Coeffs2, wavelet: &Wavelet, mode: Mode) -> Result<Raster<f64>> {
    waverec2_with(coeffs, &Synthesis::new(wavelet, mode))
}

/// [`waverec2`] with given kernels.
fn waverec2_with(coeffs: &Coeffs2, sy: &Synthesis) -> Result<Raster<f64>> {
    let mut approx: Option<Raster<f64>> = None;
    for (idx, det) in coeffs.details.iter().enumerate() {
        let shape = det.h.shape();
        if det.v.shape() != shape || det.d.shape() != shape {
            return Err(WaveletError::CoeffShape(format!(
                "level {}: cH {}, cV {}, cD {} differ",
                coeffs.details.len() - idx,
                shape,
                det.v.shape(),
                det.d.shape()
            )));
        }
        let a_full = approx.as_ref().unwrap_or(&coeffs.approx);
        let a = if idx == 0 {
            // The deepest level is not trimmed: PyWavelets requires equal shapes there.
            if a_full.shape() != shape {
                return Err(WaveletError::CoeffShape(format!(
                    "cA {} differs from the deepest details {}",
                    a_full.shape(),
                    shape
                )));
            }
            view_of(a_full)
        } else {
            match_dims(a_full, shape.rows, shape.cols)?
        };
        let inp = RecIn {
            a,
            hvd: Some([view_of(&det.h), view_of(&det.v), view_of(&det.d)]),
        };
        approx = Some(rec_level(inp, sy)?);
    }
    Ok(approx.unwrap_or_else(|| coeffs.approx.clone()))
}

/// The last inverse step of a low-pass reconstruction, left for the caller to run band by
/// band ([`LowpassFinal::compute_rows`]), so that [`crate::separate`] can turn output rows
/// straight into its f32 surfaces without a full-size f64 intermediate.
pub(crate) struct LowpassFinal {
    /// Approximation at level 1 (untrimmed: trimmed through `trim` when read).
    a: Raster<f64>,
    trim: (usize, usize),
    sy: Synthesis,
    rows: usize,
    cols: usize,
}

impl LowpassFinal {
    /// Width of the reconstruction (PyWavelets' shape: the input's, plus one if odd).
    pub(crate) fn cols(&self) -> usize {
        self.cols
    }

    /// Height of the reconstruction.
    pub(crate) fn rows(&self) -> usize {
        self.rows
    }

    /// Write reconstruction rows `n0 ..` into `out` (a whole number of rows of
    /// [`Self::cols`] values, not past [`Self::rows`]).
    pub(crate) fn compute_rows(&self, n0: usize, out: &mut [f64]) {
        let a = view_of(&self.a).corner(self.trim.0, self.trim.1);
        rec_task_dispatch::<false, _>(RecIn { a, hvd: None }, &self.sy, n0, out);
    }
}

/// Low-pass part of `data` at `level >= 1`: `waverec2` of `wavedec2(data)` with every detail
/// set to zero, all but its last inverse step. Computes only the low-pass paths (no detail
/// band is ever formed), which is the same arithmetic minus the multiplications by zero.
pub(crate) fn lowpass_final(
    data: &[f64],
    rows: usize,
    cols: usize,
    wavelet: &Wavelet,
    mode: Mode,
    level: usize,
) -> Result<LowpassFinal> {
    check_raster(data.len(), rows, cols)?;
    check_level(level)?;
    if level == 0 {
        // Callers ask for level >= 1 (default_level); level 0 would have no inverse step.
        return Err(WaveletError::CoeffShape(
            "level 0 has no inverse step".into(),
        ));
    }
    let an = Analysis::new(wavelet, mode);
    let sy = Synthesis::new(wavelet, mode);
    // Coefficient shapes per level: shapes[l] is the approximation shape after l levels.
    let mut shapes = vec![(rows, cols)];
    let mut approx = dec_level(
        View {
            data,
            rows,
            cols,
            stride: cols,
        },
        &an,
        false,
    )
    .0;
    shapes.push((approx.rows(), approx.cols()));
    for _ in 1..level {
        approx = dec_level(view_of(&approx), &an, false).0;
        shapes.push((approx.rows(), approx.cols()));
    }
    // As waverec2: before each inverse step, trim to that level's detail shape (equal at the
    // deepest level).
    for l in (2..=level).rev() {
        let (r, c) = shapes[l];
        let a = match_dims(&approx, r, c)?;
        approx = rec_level(RecIn { a, hvd: None }, &sy)?;
    }
    let trim = shapes[1];
    match_dims(&approx, trim.0, trim.1)?;
    let too_short = || WaveletError::CoeffShape(format!("{trim:?} too few for the filter"));
    let out_rows = sy.out_len(trim.0).ok_or_else(too_short)?;
    let out_cols = sy.out_len(trim.1).ok_or_else(too_short)?;
    Ok(LowpassFinal {
        a: approx,
        trim,
        sy,
        rows: out_rows,
        cols: out_cols,
    })
}

/// One wavelet's kernels in one mode for the streamed pass ([`crate::stream`]): which input
/// rows a band of output rows reads, and those output rows computed by the very kernels
/// [`wavedec2`] / [`waverec2`] run (same arithmetic per row, hence the same bits).
pub(crate) struct LevelKernels {
    an: Analysis,
    sy: Synthesis,
}

impl LevelKernels {
    pub(crate) fn new(wavelet: &Wavelet, mode: Mode) -> Self {
        Self {
            an: Analysis::new(wavelet, mode),
            sy: Synthesis::new(wavelet, mode),
        }
    }

    /// Coefficients one decomposition step makes from `n` samples.
    pub(crate) fn dec_out_len(&self, n: usize) -> usize {
        self.an.out_len(n)
    }

    /// Input rows (sorted, distinct) that decomposition output rows `k0..k1` read from an
    /// input of `n_in` rows: `[2 k0 + s - L + 1, 2 (k1 - 1) + s]` and the mode's edge rows.
    pub(crate) fn dec_rows_needed(&self, k0: usize, k1: usize, n_in: usize) -> Vec<usize> {
        let mut v: Vec<usize> = (k0..k1)
            .flat_map(|k| {
                (0..self.an.flen).map(move |j| {
                    let pos = 2 * k as isize + self.an.shift - j as isize;
                    ext_index(pos, n_in, self.an.mode)
                })
            })
            .collect();
        v.sort_unstable();
        v.dedup();
        v
    }

    /// Decomposition output rows `k0 ..` (as many as `ca` holds, `dec_out_len(x.n_cols())`
    /// values each) of input `x`; with `details` also (cH, cV, cD) of the same size.
    pub(crate) fn dec_rows<S: Rows>(
        &self,
        x: &S,
        k0: usize,
        ca: &mut [f64],
        details: Option<[&mut [f64]; 3]>,
    ) {
        match details {
            Some([ch, cv, cd]) => {
                dec_task_dispatch::<true, S>(x, &self.an, k0, DecOut { ca, ch, cv, cd })
            }
            None => dec_task_dispatch::<false, S>(
                x,
                &self.an,
                k0,
                DecOut {
                    ca,
                    ch: &mut [],
                    cv: &mut [],
                    cd: &mut [],
                },
            ),
        }
    }

    /// Samples one inverse step makes from `n` coefficients (`None`: too few for the filter).
    pub(crate) fn rec_out_len(&self, n: usize) -> Option<usize> {
        self.sy.out_len(n)
    }

    /// Approximation rows (sorted, distinct) that inverse output rows `n0..n1` read from
    /// `n_in` rows.
    pub(crate) fn rec_rows_needed(&self, n0: usize, n1: usize, n_in: usize) -> Vec<usize> {
        let sy = &self.sy;
        let mut v: Vec<usize> = (n0..n1)
            .flat_map(|nr| {
                let (q, p) = ((nr / 2) as isize, nr % 2);
                (0..sy.half).map(move |j| sy.coeff_index(q - j as isize + sy.off[p], n_in))
            })
            .collect();
        v.sort_unstable();
        v.dedup();
        v
    }

    /// Approximation-only inverse output rows `n0 ..` (as many as `out` holds, each
    /// `rec_out_len(a.n_cols())` values) from the (trimmed) approximation `a`.
    pub(crate) fn rec_rows<S: Rows>(&self, a: &S, n0: usize, out: &mut [f64]) {
        rec_task_dispatch::<false, &S>(RecIn { a, hvd: None }, &self.sy, n0, out);
    }
}

/// PyWavelets' `_match_coeff_dims` check: an approximation of `have` rows x cols may be read
/// as `want` when each side is equal or one longer.
pub(crate) fn check_trim(have: (usize, usize), want: (usize, usize)) -> Result<()> {
    let fits = |n: usize, m: usize| n == m || n == m + 1;
    if !fits(have.0, want.0) || !fits(have.1, want.1) {
        return Err(WaveletError::CoeffShape(format!(
            "approximation {} x {} does not fit details {} x {}",
            have.0, have.1, want.0, want.1
        )));
    }
    Ok(())
}

/// [`lowpass_final`] run to the end: the whole low-pass reconstruction, in PyWavelets' shape.
#[cfg(test)]
fn approx_only(
    data: &[f64],
    rows: usize,
    cols: usize,
    wavelet: &Wavelet,
    mode: Mode,
    level: usize,
) -> Result<Raster<f64>> {
    let fin = lowpass_final(data, rows, cols, wavelet, mode, level)?;
    let mut out = Raster::filled(Shape::new(fin.rows, fin.cols), 0.0);
    let chunk = rows_per_task(fin.rows, fin.cols) * fin.cols;
    out.values_mut()
        .par_chunks_mut(chunk)
        .enumerate()
        .for_each(|(t, o)| fin.compute_rows(t * chunk / fin.cols, o));
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Deterministic pseudo-random values in [-1, 1) (splitmix64).
    fn noise(n: usize, seed: u64) -> Vec<f64> {
        let mut s = seed;
        (0..n)
            .map(|_| {
                s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
                let mut z = s;
                z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
                z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
                z ^= z >> 31;
                (z >> 11) as f64 / (1u64 << 52) as f64 - 1.0
            })
            .collect()
    }

    #[test]
    fn ext_index_patterns() {
        let sym: Vec<_> = (-4..8).map(|i| ext_index(i, 3, Mode::Symmetric)).collect();
        // ... x2 x2 x1 x0 | x0 x1 x2 | x2 x1 x0 x0 ...
        assert_eq!(sym, [2, 2, 1, 0, 0, 1, 2, 2, 1, 0, 0, 1]);
        let per: Vec<_> = (-4..8)
            .map(|i| ext_index(i, 3, Mode::Periodization))
            .collect();
        assert_eq!(per, [0, 1, 2, 2, 0, 1, 2, 2, 0, 1, 2, 2]);
    }

    #[test]
    fn round_trip_all_wavelets_odd_sizes() {
        let (rows, cols) = (37, 50);
        let x = noise(rows * cols, 7);
        for name in Wavelet::names() {
            let w = Wavelet::by_name(name).expect("listed");
            for mode in [Mode::Symmetric, Mode::Periodization] {
                for level in 0..4 {
                    let c = wavedec2(&x, rows, cols, &w, mode, level).expect("dec");
                    assert_eq!(c.level(), level);
                    let r = waverec2(&c, &w, mode).expect("rec");
                    assert!(r.rows() >= rows && r.cols() >= cols);
                    let mut err: f64 = 0.0;
                    for i in 0..rows {
                        for j in 0..cols {
                            let v = r.get(i, j).copied().unwrap_or(f64::NAN);
                            err = err.max((v - x[i * cols + j]).abs());
                        }
                    }
                    // PyWavelets' sym filters are good to ~5e-12 (sym3): allow for that.
                    assert!(err < 1e-10, "{name} {mode} level {level}: {err}");
                }
            }
        }
    }

    #[test]
    fn portable_and_simd_kernels_agree() {
        let (rows, cols) = (45, 64);
        let x = noise(rows * cols, 11);
        for name in ["db1", "sym5", "coif5"] {
            let w = Wavelet::by_name(name).expect("listed");
            for mode in [Mode::Symmetric, Mode::Periodization] {
                let (an_p, an_f) = (
                    Analysis::with_kernels(&w, mode, false),
                    Analysis::with_kernels(&w, mode, true),
                );
                let (sy_p, sy_f) = (
                    Synthesis::with_kernels(&w, mode, false),
                    Synthesis::with_kernels(&w, mode, true),
                );
                let cp = wavedec2_with(&x, rows, cols, &an_p, 2);
                let cf = wavedec2_with(&x, rows, cols, &an_f, 2);
                let close = |a: &Raster<f64>, b: &Raster<f64>| {
                    a.shape() == b.shape()
                        && a.values()
                            .iter()
                            .zip(b.values())
                            .all(|(u, v)| (u - v).abs() < 1e-13)
                };
                assert!(close(&cp.approx, &cf.approx), "{name} {mode}");
                for (dp, df) in cp.details.iter().zip(&cf.details) {
                    assert!(close(&dp.h, &df.h) && close(&dp.v, &df.v) && close(&dp.d, &df.d));
                }
                let rp = waverec2_with(&cp, &sy_p).expect("rec");
                let rf = waverec2_with(&cp, &sy_f).expect("rec");
                assert!(close(&rp, &rf), "{name} {mode}");
            }
        }
    }

    #[test]
    fn approx_only_equals_zeroed_details() {
        let (rows, cols) = (45, 64);
        let x = noise(rows * cols, 3);
        for name in ["db1", "sym5", "coif2"] {
            let w = Wavelet::by_name(name).expect("listed");
            for mode in [Mode::Symmetric, Mode::Periodization] {
                let mut c = wavedec2(&x, rows, cols, &w, mode, 3).expect("dec");
                for d in &mut c.details {
                    d.h.values_mut().fill(0.0);
                    d.v.values_mut().fill(0.0);
                    d.d.values_mut().fill(0.0);
                }
                let full = waverec2(&c, &w, mode).expect("rec");
                let fast = approx_only(&x, rows, cols, &w, mode, 3).expect("approx");
                assert_eq!(full.shape(), fast.shape());
                for (a, b) in full.values().iter().zip(fast.values()) {
                    assert!((a - b).abs() < 1e-13, "{name} {mode}");
                }
            }
        }
    }

    fn zeros(rows: usize, cols: usize) -> Raster<f64> {
        Raster::filled(Shape::new(rows, cols), 0.0)
    }

    #[test]
    fn bad_shapes_are_errors() {
        let w = Wavelet::by_name("db2").expect("listed");
        assert!(wavedec2(&[0.0; 5], 2, 3, &w, Mode::Symmetric, 1).is_err());
        assert!(wavedec2(&[], 0, 3, &w, Mode::Symmetric, 1).is_err());
        assert!(wavedec2(&[0.0; 6], 2, 3, &w, Mode::Symmetric, MAX_LEVEL + 1).is_err());
        let mut c = wavedec2(&noise(100, 1), 10, 10, &w, Mode::Symmetric, 2).expect("dec");
        c.details[1].v = zeros(3, 3);
        assert!(matches!(
            waverec2(&c, &w, Mode::Symmetric),
            Err(WaveletError::CoeffShape(_))
        ));
        let c = Coeffs2 {
            approx: zeros(1, 1),
            details: vec![Details2 {
                h: zeros(1, 1),
                v: zeros(1, 1),
                d: zeros(1, 1),
            }],
        };
        // One coefficient is too few for a 4-tap filter in symmetric mode.
        assert!(waverec2(&c, &w, Mode::Symmetric).is_err());
        assert!(waverec2(&c, &w, Mode::Periodization).is_ok());
    }
}
