//! 2-D complex FFTs over row-major buffers, built from rustfft's 1-D plans and a blocked
//! transpose. Plans are cached by the planner, so repeated sizes cost no planning.

use std::sync::Arc;

use rayon::prelude::*;
use rustfft::num_complex::Complex32;
use rustfft::{Fft, FftPlanner};

/// Rows handed to one rayon task in a batch of 1-D FFTs / transposes.
const ROWS_PER_TASK: usize = 32;
/// Edge of the square blocks of the transpose.
const BLOCK: usize = 32;

/// Cached forward/inverse plans and scratch space for 2-D transforms.
pub(crate) struct Fft2 {
    planner: FftPlanner<f32>,
}

impl Default for Fft2 {
    fn default() -> Self {
        Self::new()
    }
}

impl Fft2 {
    pub(crate) fn new() -> Self {
        Fft2 {
            planner: FftPlanner::new(),
        }
    }

    fn plan(&mut self, len: usize, inverse: bool) -> Arc<dyn Fft<f32>> {
        if inverse {
            self.planner.plan_fft_inverse(len)
        } else {
            self.planner.plan_fft_forward(len)
        }
    }

    /// Forward 2-D FFT of `data` (`rows x cols`, row-major). The spectrum is left TRANSPOSED in
    /// `out` (`cols x rows`: index `[kx][ky]`); `data` is clobbered.
    pub(crate) fn forward_transposed(
        &mut self,
        data: &mut [Complex32],
        out: &mut [Complex32],
        rows: usize,
        cols: usize,
    ) {
        let row_fft = self.plan(cols, false);
        let col_fft = self.plan(rows, false);
        batch(&*row_fft, data, cols);
        transpose(data, out, rows, cols);
        batch(&*col_fft, out, rows);
    }

    /// Inverse of [`Self::forward_transposed`] (unnormalised): `spec` is `cols x rows`
    /// (`[kx][ky]`), the result in `out` is `rows x cols` row-major; `spec` is clobbered.
    pub(crate) fn inverse_from_transposed(
        &mut self,
        spec: &mut [Complex32],
        out: &mut [Complex32],
        rows: usize,
        cols: usize,
    ) {
        let row_fft = self.plan(cols, true);
        let col_fft = self.plan(rows, true);
        batch(&*col_fft, spec, rows);
        transpose(spec, out, cols, rows);
        batch(&*row_fft, out, cols);
    }
}

/// In-place 1-D FFTs of every consecutive `len`-long row of `data`.
fn batch(fft: &dyn Fft<f32>, data: &mut [Complex32], len: usize) {
    let scratch_len = fft.get_inplace_scratch_len();
    data.par_chunks_mut(len * ROWS_PER_TASK).for_each_init(
        || vec![Complex32::new(0.0, 0.0); scratch_len],
        |scratch, chunk| fft.process_with_scratch(chunk, scratch),
    );
}

/// `dst[c][r] = src[r][c]` for a `rows x cols` source; blocked for cache locality.
fn transpose(src: &[Complex32], dst: &mut [Complex32], rows: usize, cols: usize) {
    // Each task fills a band of BLOCK destination rows (= BLOCK source columns).
    dst.par_chunks_mut(rows * BLOCK)
        .enumerate()
        .for_each(|(band, out)| {
            let c0 = band * BLOCK;
            let nc = out.len() / rows;
            for r0 in (0..rows).step_by(BLOCK) {
                let r1 = (r0 + BLOCK).min(rows);
                for dc in 0..nc {
                    let c = c0 + dc;
                    let orow = &mut out[dc * rows..(dc + 1) * rows];
                    for r in r0..r1 {
                        orow[r] = src[r * cols + c];
                    }
                }
            }
        });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn transpose_roundtrip() {
        let (rows, cols) = (37, 70);
        let src: Vec<Complex32> = (0..rows * cols)
            .map(|i| Complex32::new(i as f32, -(i as f32)))
            .collect();
        let mut t = vec![Complex32::new(0.0, 0.0); rows * cols];
        transpose(&src, &mut t, rows, cols);
        for r in 0..rows {
            for c in 0..cols {
                assert_eq!(t[c * rows + r], src[r * cols + c]);
            }
        }
    }

    #[test]
    fn forward_inverse_roundtrip() {
        let (rows, cols) = (12, 20);
        let orig: Vec<Complex32> = (0..rows * cols)
            .map(|i| Complex32::new(((i * 7) % 11) as f32, ((i * 3) % 5) as f32))
            .collect();
        let mut fft = Fft2::new();
        let mut data = orig.clone();
        let mut spec = vec![Complex32::new(0.0, 0.0); rows * cols];
        fft.forward_transposed(&mut data, &mut spec, rows, cols);
        // DC term is the sum.
        let sum: Complex32 = orig.iter().sum();
        assert!((spec[0] - sum).norm() < 1e-3);
        fft.inverse_from_transposed(&mut spec, &mut data, rows, cols);
        let n = (rows * cols) as f32;
        for (a, b) in data.iter().zip(&orig) {
            assert!((a / n - b).norm() < 1e-4);
        }
    }
}
