//! Block pooling (downsampling) of height maps, NaN-aware.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::error::{check_raster, Result, WaveletError};

/// What a block reduces to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PoolOp {
    /// Highest valid height of the block (keeps peaks: the surface a contact touches).
    Max,
    /// Mean of the valid heights of the block.
    Mean,
}

impl PoolOp {
    /// "max" or "mean".
    pub fn name(self) -> &'static str {
        match self {
            PoolOp::Max => "max",
            PoolOp::Mean => "mean",
        }
    }

    /// Parse "max" / "mean" (ASCII case ignored).
    pub fn by_name(name: &str) -> Option<PoolOp> {
        [PoolOp::Max, PoolOp::Mean]
            .into_iter()
            .find(|p| p.name().eq_ignore_ascii_case(name.trim()))
    }
}

/// A pooled map, row-major `rows x cols`.
///
/// Output pixel `(i, j)` summarises input rows `i*block .. min((i+1)*block, in_rows)` and
/// columns `j*block .. min((j+1)*block, in_cols)`; so the pooled pitch is `block` times the
/// input pitch and a full block's centre sits `(block - 1) / 2` input pixels past its first
/// pixel.
#[derive(Debug, Clone, PartialEq)]
pub struct Pooled {
    /// Pooled heights, NaN where a block had no valid pixel.
    pub heights: Vec<f32>,
    /// `ceil(in_rows / block)`.
    pub rows: usize,
    /// `ceil(in_cols / block)`.
    pub cols: usize,
}

/// Pool `heights` (row-major `rows x cols`) over `block x block` blocks with `op`.
///
/// * NaN-aware: max / mean over the block's non-NaN pixels; a block of only NaN gives NaN.
///   (Infinities are ordinary values here: the frame marks missing data with NaN only.)
/// * Partial blocks at the right and bottom edges are kept and reduced over the pixels they
///   have, so the output is `ceil(rows / block) x ceil(cols / block)` and no data is dropped.
/// * `block == 1` returns a copy.
///
/// Errors if `heights.len() != rows * cols`, a side is zero, or `block == 0`.
pub fn pool(heights: &[f32], rows: usize, cols: usize, block: usize, op: PoolOp) -> Result<Pooled> {
    check_raster(heights.len(), rows, cols)?;
    if block == 0 {
        return Err(WaveletError::ZeroBlock);
    }
    let (out_rows, out_cols) = (rows.div_ceil(block), cols.div_ceil(block));
    let mut out = vec![0.0f32; out_rows * out_cols];
    // Each task owns a band of output rows and streams its input rows once, in order.
    let band = (16384 / out_cols).clamp(1, 64);
    out.par_chunks_mut(band * out_cols)
        .enumerate()
        .for_each(|(t, out_band)| {
            let r0 = t * band * block;
            let input = &heights[r0 * cols..((t + 1) * band * block).min(rows) * cols];
            pool_band_dispatched(input, cols, block, op, out_band);
        });
    Ok(Pooled {
        heights: out,
        rows: out_rows,
        cols: out_cols,
    })
}

surfstream_core::avx2_dispatch! {
    /// [`pool_band`], compiled with AVX2 when the CPU has it. Max and a NaN-skipping f64 sum
    /// in a fixed order: both copies give the same bits (no FMA involved).
    fn pool_band_dispatched(input: &[f32], cols: usize, block: usize, op: PoolOp, out: &mut [f32]) -> () {
        pool_band(input, cols, block, op, out)
    }
}

/// Pool the input rows of a band of output rows. Each output row first reduces its `block`
/// input rows column-wise into a row of scratch (contiguous, vectorised, input read once),
/// then reduces that row in groups of `block`.
#[inline(always)]
fn pool_band(input: &[f32], cols: usize, block: usize, op: PoolOp, out: &mut [f32]) {
    let out_cols = cols.div_ceil(block);
    let rows = input
        .chunks(block * cols)
        .zip(out.chunks_exact_mut(out_cols));
    match op {
        PoolOp::Max => {
            let mut acc = vec![0.0f32; cols];
            for (block_rows, out_row) in rows {
                let mut it = block_rows.chunks_exact(cols);
                let Some(first) = it.next() else { continue };
                acc.copy_from_slice(first);
                for row in it {
                    // f32::max ignores a NaN operand: all-NaN columns stay NaN.
                    for (a, &v) in acc.iter_mut().zip(row) {
                        *a = a.max(v);
                    }
                }
                max_groups(&acc, block, out_row);
            }
        }
        PoolOp::Mean => {
            let mut sum = vec![0.0f64; cols];
            let mut count = vec![0u32; cols];
            for (block_rows, out_row) in rows {
                sum.fill(0.0);
                count.fill(0);
                for row in block_rows.chunks_exact(cols) {
                    for ((s, n), &v) in sum.iter_mut().zip(count.iter_mut()).zip(row) {
                        let ok = !v.is_nan();
                        *s += if ok { f64::from(v) } else { 0.0 };
                        *n += u32::from(ok);
                    }
                }
                for ((o, s), n) in out_row
                    .iter_mut()
                    .zip(sum.chunks(block))
                    .zip(count.chunks(block))
                {
                    let n: u32 = n.iter().sum();
                    let s: f64 = s.iter().sum();
                    *o = if n > 0 {
                        (s / f64::from(n)) as f32
                    } else {
                        f32::NAN
                    };
                }
            }
        }
    }
}

/// `out[j] = max(row[j*block .. (j+1)*block])` (NaN-ignoring), the last group possibly
/// shorter; the pipeline's block of 4 gets a fixed-size fast path.
#[inline(always)]
fn max_groups(row: &[f32], block: usize, out: &mut [f32]) {
    let group_max = |c: &[f32]| c.iter().fold(f32::NAN, |m, &v| m.max(v));
    if block == 4 {
        let full = row.len() / 4;
        for (o, c) in out.iter_mut().zip(row.chunks_exact(4)) {
            *o = c[0].max(c[1]).max(c[2].max(c[3]));
        }
        if let Some(o) = out.get_mut(full) {
            *o = group_max(&row[full * 4..]);
        }
    } else {
        for (o, c) in out.iter_mut().zip(row.chunks(block)) {
            *o = group_max(c);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Straightforward reference: loop over every block.
    fn naive(h: &[f32], rows: usize, cols: usize, b: usize, op: PoolOp) -> Vec<f32> {
        let (orows, ocols) = (rows.div_ceil(b), cols.div_ceil(b));
        let mut out = Vec::new();
        for i in 0..orows {
            for j in 0..ocols {
                let vals: Vec<f32> = (i * b..((i + 1) * b).min(rows))
                    .flat_map(|r| (j * b..((j + 1) * b).min(cols)).map(move |c| (r, c)))
                    .map(|(r, c)| h[r * cols + c])
                    .filter(|v| !v.is_nan())
                    .collect();
                out.push(match (vals.is_empty(), op) {
                    (true, _) => f32::NAN,
                    (false, PoolOp::Max) => vals.iter().copied().fold(f32::MIN, f32::max),
                    (false, PoolOp::Mean) => {
                        (vals.iter().map(|&v| f64::from(v)).sum::<f64>() / vals.len() as f64) as f32
                    }
                });
            }
        }
        out
    }

    #[test]
    fn matches_naive_with_nan_and_partial_blocks() {
        for (rows, cols) in [(1, 1), (7, 9), (16, 16), (33, 70), (100, 3)] {
            let h: Vec<f32> = (0..rows * cols)
                .map(|i| {
                    if i % 7 == 3 || (i / cols) % 5 == 4 {
                        f32::NAN
                    } else {
                        ((i * 37 % 101) as f32 - 50.0) * 0.1
                    }
                })
                .collect();
            for block in [1, 2, 3, 4, 5, 8] {
                for op in [PoolOp::Max, PoolOp::Mean] {
                    let p = pool(&h, rows, cols, block, op).expect("pools");
                    assert_eq!(
                        (p.rows, p.cols),
                        (rows.div_ceil(block), cols.div_ceil(block))
                    );
                    let want = naive(&h, rows, cols, block, op);
                    for (k, (a, b)) in p.heights.iter().zip(&want).enumerate() {
                        assert!(
                            (a.is_nan() && b.is_nan()) || a == b,
                            "{rows}x{cols} block {block} {op:?} at {k}: {a} vs {b}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn avx2_and_baseline_copies_give_the_same_bits() {
        let (rows, cols) = (67, 131);
        let h: Vec<f32> = (0..rows * cols)
            .map(|i| {
                if i % 11 == 5 {
                    f32::NAN
                } else {
                    ((i * 7919 % 1009) as f32 - 500.0) * 1.37e-3 + 25_000.0
                }
            })
            .collect();
        for block in [1, 2, 3, 4, 7] {
            for op in [PoolOp::Max, PoolOp::Mean] {
                let fast = pool(&h, rows, cols, block, op).expect("pools");
                let base = surfstream_core::simd::with_baseline(|| pool(&h, rows, cols, block, op))
                    .expect("pools");
                let bits = |p: &Pooled| p.heights.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&fast), bits(&base), "block {block} {op:?}");
            }
        }
    }

    #[test]
    fn all_nan_block_and_errors() {
        let n = f32::NAN;
        let h = [n, n, 1.0, n, n, n, n, 5.0];
        let p = pool(&h, 2, 4, 2, PoolOp::Max).expect("pools");
        assert!(p.heights[0].is_nan());
        assert_eq!(p.heights[1], 5.0);
        let p = pool(&h, 2, 4, 2, PoolOp::Mean).expect("pools");
        assert!(p.heights[0].is_nan());
        assert_eq!(p.heights[1], 3.0);
        assert_eq!(pool(&h, 2, 4, 0, PoolOp::Max), Err(WaveletError::ZeroBlock));
        assert!(pool(&h, 3, 4, 2, PoolOp::Max).is_err());
        assert!(pool(&[], 0, 4, 2, PoolOp::Max).is_err());
    }
}
