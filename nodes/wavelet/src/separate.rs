//! Datum / roughness separation of a height map by a 2-D wavelet low-pass.
//!
//! datum = `waverec2` of the level-`l` approximation with every detail band set to zero,
//! cropped to the map; roughness = heights - datum, i.e. the sum of the detail
//! reconstructions (paper eq. 11). Computed in f64, returned as f32 like the frame payload.
//!
//! # Non-measured pixels
//!
//! The transform needs a complete grid, so non-finite pixels (NaN = not measured; infinities
//! are treated the same) are filled first, and set back to NaN in both outputs afterwards:
//!
//! 1. each row: linear interpolation between the nearest valid pixels left and right; before
//!    the first / after the last valid pixel, that pixel's value (constant extension);
//! 2. rows without any valid pixel: the same, down each column, between the nearest rows that
//!    had valid pixels (already filled by step 1).
//!
//! The fill is cheap, local and continuous, so a hole does not ring across the map; but the
//! datum next to a large hole is a smooth bridge over made-up data, and callers that care
//! should mask a margin of about `filter_len * 2^level` pixels around big holes. A map with no
//! finite value is an error.

use rayon::prelude::*;
use surfstream_core::raster::{Shape, ShapeError};

use crate::dwt::lowpass_final;
use crate::error::{check_raster, Result, WaveletError};
use crate::wavelet::{dwt_max_level, Mode, Wavelet};

/// Level used when the caller asks for none: the reference study's level 8.
pub const DEFAULT_LEVEL: usize = 8;

/// The two surfaces of a separation, row-major like the input, and the level used.
#[derive(Debug, Clone, PartialEq)]
pub struct Separation {
    /// Low-pass (form / waviness) surface, NaN where the input was not finite.
    pub datum: Vec<f32>,
    /// heights - datum, NaN where the input was not finite.
    pub roughness: Vec<f32>,
    /// Decomposition level actually used (see [`default_level`]).
    pub level: usize,
}

/// The decomposition level to use for a `rows x cols` map: `requested` (default
/// [`DEFAULT_LEVEL`] = 8) clamped to `1 ..= dwt_max_level(min(rows, cols), filter_len)`, so
/// that every approximation coefficient still sees real data.
///
/// Errors if a side is zero, or if the smaller side is below `2 * (filter_len - 1)` (18 for
/// sym5), where not even level 1 is meaningful.
pub fn default_level(
    rows: usize,
    cols: usize,
    wavelet: &Wavelet,
    requested: Option<usize>,
) -> Result<usize> {
    if rows == 0 || cols == 0 {
        return Err(ShapeError::Empty(Shape::new(rows, cols)).into());
    }
    let flen = wavelet.filter_len();
    let max = dwt_max_level(rows.min(cols), flen);
    if max == 0 {
        return Err(WaveletError::TooSmall {
            rows,
            cols,
            wavelet: wavelet.name(),
            min_side: 2 * (flen - 1),
        });
    }
    Ok(requested.unwrap_or(DEFAULT_LEVEL).clamp(1, max))
}

/// Split `heights` (row-major `rows x cols`, µm, NaN = not measured) into datum and roughness
/// with a `level` (see [`default_level`]) decomposition by `wavelet` in `mode`.
///
/// Matches PyWavelets: `datum = waverec2([cA_l, zeros...], wavelet, mode)[:rows, :cols]` of
/// `wavedec2(filled, wavelet, mode, level)`. Non-finite pixels are handled as the module doc
/// says.
///
/// The whole map in memory (its coefficients too): the product path is the streamed
/// [`crate::separate_streamed`] (through [`crate::separate_map`], the node's final pass and
/// the `separate` verb), which gives the same bits band by band. This one stays as the test
/// oracle of that pass, for the level chosen by minimum energy and the base by RMSE
/// ([`crate::analyse`]) and for the Python binding.
pub fn separate(
    heights: &[f32],
    rows: usize,
    cols: usize,
    wavelet: &Wavelet,
    mode: Mode,
    level: Option<usize>,
) -> Result<Separation> {
    check_raster(heights.len(), rows, cols)?;
    let level = default_level(rows, cols, wavelet, level)?;
    let filled = fill_invalid(heights, rows, cols)?;
    let fin = lowpass_final(&filled, rows, cols, wavelet, mode, level)?;
    drop(filled);
    // The last inverse step runs here, a few rows at a time into scratch, and each row goes
    // straight to datum / roughness: no full-size f64 reconstruction is ever allocated, and
    // PyWavelets' extra row / column on odd sizes is never computed.
    const SUB: usize = 8;
    let fcols = fin.cols();
    if fin.rows() < rows || fcols < cols {
        // Cannot happen (each inverse step gives back N or N + 1 samples); keeps slicing safe.
        return Err(WaveletError::CoeffShape(format!(
            "low-pass {} x {fcols} smaller than the map {rows} x {cols}",
            fin.rows()
        )));
    }
    let band = rows
        .div_ceil(8 * rayon::current_num_threads().max(1))
        .max(SUB);
    let mut datum = vec![0.0f32; rows * cols];
    let mut roughness = vec![0.0f32; rows * cols];
    datum
        .par_chunks_mut(band * cols)
        .zip(roughness.par_chunks_mut(band * cols))
        .zip(heights.par_chunks(band * cols))
        .enumerate()
        .for_each(|(t, ((d_band, r_band), h_band))| {
            let mut low = vec![0.0f64; SUB * fcols];
            let n_rows = d_band.len() / cols;
            for s in (0..n_rows).step_by(SUB) {
                let k = SUB.min(n_rows - s);
                fin.compute_rows(t * band + s, &mut low[..k * fcols]);
                for i in 0..k {
                    let r = (s + i) * cols..(s + i + 1) * cols;
                    let l_row = &low[i * fcols..i * fcols + cols];
                    finish_row(
                        &h_band[r.clone()],
                        l_row,
                        &mut d_band[r.clone()],
                        &mut r_band[r],
                    );
                }
            }
        });
    Ok(Separation {
        datum,
        roughness,
        level,
    })
}

/// datum = low-pass, roughness = heights - datum, both NaN where the height is not finite.
#[inline]
pub(crate) fn finish_row(h: &[f32], low: &[f64], datum: &mut [f32], roughness: &mut [f32]) {
    for (((d, r), &h), &l) in datum.iter_mut().zip(roughness).zip(h).zip(low) {
        // Compute both, then select: branch-free, so the loop vectorises.
        let ok = h.is_finite();
        let (dv, rv) = (l as f32, (f64::from(h) - l) as f32);
        *d = if ok { dv } else { f32::NAN };
        *r = if ok { rv } else { f32::NAN };
    }
}

/// The heights as f64 with every non-finite pixel filled (module doc, "Non-measured pixels").
/// Errors with [`WaveletError::AllNan`] if no pixel is finite.
pub fn fill_invalid(heights: &[f32], rows: usize, cols: usize) -> Result<Vec<f64>> {
    check_raster(heights.len(), rows, cols)?;
    let mut out = vec![0.0f64; rows * cols];
    // Step 1, rows in parallel; remember which rows had any valid pixel.
    let row_ok: Vec<bool> = out
        .par_chunks_mut(cols)
        .zip(heights.par_chunks(cols))
        .map(|(o, h)| fill_row(h, o))
        .collect();
    let valid_rows: Vec<usize> = (0..rows).filter(|&r| row_ok[r]).collect();
    let (Some(&first), Some(&last)) = (valid_rows.first(), valid_rows.last()) else {
        return Err(WaveletError::AllNan);
    };
    if valid_rows.len() == rows {
        return Ok(out);
    }
    // Step 2: each empty row from the nearest valid rows above and below.
    for pair in valid_rows.windows(2) {
        let (p, q) = (pair[0], pair[1]);
        for r in p + 1..q {
            let t = (r - p) as f64 / (q - p) as f64;
            let (head, tail) = out.split_at_mut(r * cols);
            let (target, below) = tail.split_at_mut(cols);
            let above = &head[p * cols..(p + 1) * cols];
            let below = &below[(q - r - 1) * cols..(q - r) * cols];
            for ((o, &a), &b) in target.iter_mut().zip(above).zip(below) {
                *o = a + t * (b - a);
            }
        }
    }
    // Constant extension above the first and below the last valid row.
    for r in (0..first).chain(last + 1..rows) {
        let src = if r < first { first } else { last };
        out.copy_within(src * cols..(src + 1) * cols, r * cols);
    }
    Ok(out)
}

/// Fill one row (step 1). Returns false, leaving `out` untouched, if it has no valid pixel.
pub(crate) fn fill_row(h: &[f32], out: &mut [f64]) -> bool {
    // Most rows are complete: a vectorisable count, then a plain conversion.
    if h.iter().filter(|v| !v.is_finite()).count() == 0 {
        for (o, &v) in out.iter_mut().zip(h) {
            *o = f64::from(v);
        }
        return true;
    }
    let mut prev: Option<usize> = None;
    for (i, &v) in h.iter().enumerate() {
        if !v.is_finite() {
            continue;
        }
        let v = f64::from(v);
        out[i] = v;
        match prev {
            // Leading gap: constant extension of the first valid value.
            None => out[..i].fill(v),
            Some(p) if p + 1 < i => {
                let a = out[p];
                let span = (i - p) as f64;
                for (k, o) in out[p + 1..i].iter_mut().enumerate() {
                    *o = a + (k + 1) as f64 / span * (v - a);
                }
            }
            Some(_) => {}
        }
        prev = Some(i);
    }
    match prev {
        Some(p) => {
            // Trailing gap: constant extension of the last valid value.
            let v = out[p];
            out[p + 1..].fill(v);
            true
        }
        None => false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_level_clamps() {
        let w = Wavelet::by_name("sym5").expect("listed");
        assert_eq!(default_level(1024, 1024, &w, None), Ok(6));
        assert_eq!(default_level(1024, 4096, &w, Some(3)), Ok(3));
        assert_eq!(default_level(1024, 1024, &w, Some(0)), Ok(1));
        assert_eq!(default_level(18, 500, &w, None), Ok(1));
        assert!(matches!(
            default_level(17, 500, &w, None),
            Err(WaveletError::TooSmall { min_side: 18, .. })
        ));
        assert!(default_level(0, 5, &w, None).is_err());
        let haar = Wavelet::by_name("db1").expect("listed");
        assert_eq!(default_level(4096, 4096, &haar, None), Ok(8));
        assert_eq!(default_level(4096, 4096, &haar, Some(20)), Ok(12));
    }

    #[test]
    fn fill_rows_then_columns() {
        let n = f32::NAN;
        #[rustfmt::skip]
        let h = [
            n,   1.0, n,   3.0, n,
            n,   n,   n,   n,   n,
            n,   n,   n,   n,   n,
            2.0, n,   n,   n,   6.0,
            n,   n,   n,   n,   n,
        ];
        let f = fill_invalid(&h, 5, 5).expect("has data");
        let row0 = [1.0, 1.0, 2.0, 3.0, 3.0];
        let row3 = [2.0, 3.0, 4.0, 5.0, 6.0];
        assert_eq!(&f[0..5], &row0);
        assert_eq!(&f[15..20], &row3);
        for c in 0..5 {
            let third = (row3[c] - row0[c]) / 3.0;
            assert!((f[5 + c] - (row0[c] + third)).abs() < 1e-12);
            assert!((f[10 + c] - (row0[c] + 2.0 * third)).abs() < 1e-12);
            assert_eq!(f[20 + c], row3[c]);
        }
        assert_eq!(fill_invalid(&[n; 6], 2, 3), Err(WaveletError::AllNan));
        assert_eq!(
            fill_invalid(&[f32::INFINITY, 2.0], 1, 2).expect("one valid"),
            [2.0, 2.0]
        );
    }

    #[test]
    fn separation_restores_nan_and_sums_back() {
        let (rows, cols) = (40, 57);
        let mut h: Vec<f32> = (0..rows * cols)
            .map(|i| {
                let (r, c) = ((i / cols) as f32, (i % cols) as f32);
                0.01 * r * c + (0.7 * c).sin() + (1.3 * r).cos()
            })
            .collect();
        h[3] = f32::NAN;
        h[cols * 10..cols * 11].fill(f32::NAN);
        let w = Wavelet::by_name("sym5").expect("listed");
        for mode in [Mode::Symmetric, Mode::Periodization] {
            let s = separate(&h, rows, cols, &w, mode, None).expect("separates");
            // dwt_max_level(40, 10) = floor(log2(40 / 9)) = 2.
            assert_eq!(s.level, 2);
            for ((&v, &d), &r) in h.iter().zip(&s.datum).zip(&s.roughness) {
                if v.is_nan() {
                    assert!(d.is_nan() && r.is_nan());
                } else {
                    assert!((d + r - v).abs() < 1e-5);
                }
            }
        }
        assert!(separate(&h, rows, cols + 1, &w, Mode::Symmetric, None).is_err());
        assert!(separate(&[f32::NAN; 400], 20, 20, &w, Mode::Symmetric, None).is_err());
    }
}
