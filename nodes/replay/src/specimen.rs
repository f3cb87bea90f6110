//! The virtual specimen: self-affine roughness plus waviness plus form.
//!
//! The roughness is synthesised in the Fourier domain: every coefficient of a padded 2-D
//! spectrum gets the amplitude `sqrt(C(q))` of the isotropic power spectrum
//!
//! ```text
//! C(q) ~ (1 + (q / q0)^2)^-(1 + H),   q0 = 1 / correlation_length_um  (cycles per um)
//! ```
//!
//! (flat for wavelengths longer than the correlation length, self-affine with Hurst exponent
//! `H` below it) and a seeded uniform random phase; the real part of the inverse FFT, cropped
//! to the specimen, is the roughness. It is then shifted to zero mean and scaled so that its Sa
//! (mean absolute deviation) is exactly `sa_um`. Waviness (a few plane waves of random
//! direction) and form (a paraboloid dome) are added on top; they do not count in the Sa.
//!
//! The inverse 2-D FFT is done row-column in f32 with rayon: first along y for the spectrum
//! columns `kx = 0 ..= nx / 2` (the field is real, the rest is their Hermitian mirror; in
//! place, each column contiguous), then along x for blocks of output rows gathered from that
//! buffer, two real rows per complex transform. Peak memory is half a complex f32 buffer of
//! the padded size plus the output (about 0.35 GB for a 9353 x 4745 px specimen). Every random number comes from a stream keyed
//! by (seed, spectrum column), so the result is bit-identical for a seed whatever the number of
//! threads.

use std::f64::consts::TAU;

use rand::Rng;
use rayon::prelude::*;
use rustfft::num_complex::Complex32;
use rustfft::FftPlanner;
use serde::{Deserialize, Serialize};

use surfstream_core::fft::fast_len;
use surfstream_core::raster::Shape;

use crate::error::{invalid, ReplayError, Result};
use crate::rng::{domain, stream};

/// Largest padded synthesis grid, in points (2^28: a 2 GiB complex f32 buffer).
pub const MAX_SYNTHESIS_POINTS: usize = 1 << 28;

/// Largest side of a specimen, in pixels.
pub const MAX_SIDE_PX: usize = 1 << 17;

/// Output rows transformed together in the second FFT pass.
const ROW_BLOCK: usize = 16;

/// Parameters of a generated specimen. Every field has a default (a barrel-finished aluminium
/// sheet as seen by a ZeGage at 0.8148 um pitch); unknown fields are rejected.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SpecimenParams {
    /// Width in pixels (x, columns).
    pub width_px: usize,
    /// Height in pixels (y, rows).
    pub height_px: usize,
    /// Pixel pitch in micrometres (same in x and y).
    pub pitch_um: f64,
    /// Sa of the roughness component in micrometres (mean absolute deviation from the mean).
    /// 0 gives no roughness.
    pub sa_um: f64,
    /// Hurst exponent of the self-affine roughness, in (0, 1].
    pub hurst: f64,
    /// Roll-off (correlation) length in micrometres: the spectrum is flat for longer
    /// wavelengths.
    pub correlation_length_um: f64,
    /// Waviness: the amplitudes of all components add up to this, in micrometres.
    pub waviness_amplitude_um: f64,
    /// Waviness: nominal wavelength in micrometres; each component's is drawn within
    /// 0.75 .. 1.25 times this.
    pub waviness_wavelength_um: f64,
    /// Waviness: number of plane-wave components of random direction and phase (0 = none).
    pub waviness_components: usize,
    /// Form: height of the centre above the corners in micrometres (a paraboloid dome; a
    /// negative value gives a bowl).
    pub form_sag_um: f64,
    /// Seed of every random quantity of the specimen.
    pub seed: u64,
}

impl Default for SpecimenParams {
    fn default() -> Self {
        Self {
            width_px: 1024,
            height_px: 1024,
            pitch_um: 0.8148,
            sa_um: 1.3,
            hurst: 0.8,
            correlation_length_um: 40.0,
            waviness_amplitude_um: 2.0,
            waviness_wavelength_um: 400.0,
            waviness_components: 2,
            form_sag_um: 3.0,
            seed: 0,
        }
    }
}

const SECTION: &str = "specimen";

fn check_positive(field: &'static str, v: f64) -> Result<()> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(invalid(SECTION, field, v, "a finite number > 0"))
    }
}

fn check_non_negative(field: &'static str, v: f64) -> Result<()> {
    if v.is_finite() && v >= 0.0 {
        Ok(())
    } else {
        Err(invalid(SECTION, field, v, "a finite number >= 0"))
    }
}

impl SpecimenParams {
    /// Checks every field; the error names the first field out of range.
    pub fn validate(&self) -> Result<()> {
        for (field, v) in [("width_px", self.width_px), ("height_px", self.height_px)] {
            if !(2..=MAX_SIDE_PX).contains(&v) {
                return Err(invalid(
                    SECTION,
                    field,
                    v,
                    format!("an integer in 2 ..= {MAX_SIDE_PX}"),
                ));
            }
        }
        check_positive("pitch_um", self.pitch_um)?;
        check_non_negative("sa_um", self.sa_um)?;
        if !(self.hurst.is_finite() && self.hurst > 0.0 && self.hurst <= 1.0) {
            return Err(invalid(SECTION, "hurst", self.hurst, "a number in (0, 1]"));
        }
        check_positive("correlation_length_um", self.correlation_length_um)?;
        check_non_negative("waviness_amplitude_um", self.waviness_amplitude_um)?;
        check_positive("waviness_wavelength_um", self.waviness_wavelength_um)?;
        if self.waviness_components > 64 {
            return Err(invalid(
                SECTION,
                "waviness_components",
                self.waviness_components,
                "an integer in 0 ..= 64",
            ));
        }
        if !self.form_sag_um.is_finite() {
            return Err(invalid(
                SECTION,
                "form_sag_um",
                self.form_sag_um,
                "a finite number",
            ));
        }
        let (nx, ny) = synthesis_shape(self.width_px, self.height_px);
        if nx.saturating_mul(ny) > MAX_SYNTHESIS_POINTS {
            return Err(ReplayError::TooLarge {
                what: "specimen".to_string(),
                width_px: self.width_px,
                height_px: self.height_px,
                limit: format!(
                    "a synthesis grid of at most {MAX_SYNTHESIS_POINTS} points (this one is {nx} x {ny})"
                ),
            });
        }
        Ok(())
    }
}

/// A height map in micrometres, row-major (`heights[y * cols + x]`, x = column, y = row), NaN
/// = not measured. Pixel (0, 0) sits at scan position (0, 0) um.
#[derive(Debug, Clone, PartialEq)]
pub struct Specimen {
    /// `shape.rows * shape.cols` heights in micrometres.
    pub heights: Vec<f32>,
    /// Rows (y) x columns (x), in pixels.
    pub shape: Shape,
    /// Pixel pitch in micrometres (x and y).
    pub pitch_um: f64,
}

impl Specimen {
    /// Wraps an existing height map (e.g. one loaded from a file), checking its shape and pitch.
    pub fn from_heights(heights: Vec<f32>, shape: Shape, pitch_um: f64) -> Result<Self> {
        let expected = shape.checked_len();
        if expected != Some(heights.len()) || shape.is_empty() {
            return Err(ReplayError::ShapeMismatch {
                len: heights.len(),
                rows: shape.rows,
                cols: shape.cols,
                expected: expected.unwrap_or(usize::MAX),
            });
        }
        check_positive("pitch_um", pitch_um)?;
        Ok(Self {
            heights,
            shape,
            pitch_um,
        })
    }

    /// The height at integer pixel (x, y), or `None` outside the specimen.
    pub fn get(&self, x: usize, y: usize) -> Option<f32> {
        if x < self.shape.cols && y < self.shape.rows {
            self.heights.get(self.shape.index(y, x)).copied()
        } else {
            None
        }
    }

    /// One row of heights (`None` outside).
    pub fn row(&self, y: usize) -> Option<&[f32]> {
        if y < self.shape.rows {
            let cols = self.shape.cols;
            self.heights.get(y * cols..(y + 1) * cols)
        } else {
            None
        }
    }
}

/// The padded synthesis grid (nx, ny) for a specimen of `width x height` px.
fn synthesis_shape(width: usize, height: usize) -> (usize, usize) {
    (fast_len(width), fast_len(height))
}

/// Signed frequency index of FFT bin `k` of an `n`-point transform.
fn signed_bin(k: usize, n: usize) -> f64 {
    if k <= n / 2 {
        k as f64
    } else {
        k as f64 - n as f64
    }
}

/// Generates the specimen described by `params`: roughness (Sa = `sa_um` exactly, up to f32
/// rounding) plus waviness plus form. Deterministic for a seed, whatever the thread count.
pub fn generate_specimen(params: &SpecimenParams) -> Result<Specimen> {
    params.validate()?;
    let (w, h) = (params.width_px, params.height_px);
    let mut heights = vec![0f32; w * h];
    let (mean, scale) = if params.sa_um > 0.0 {
        synthesize_roughness(params, &mut heights);
        let (mean, sa) = mean_and_sa(&heights, w);
        (mean, if sa > 0.0 { params.sa_um / sa } else { 0.0 })
    } else {
        (0.0, 0.0)
    };
    let waves = waviness_components(params);
    let pitch = params.pitch_um;
    // Form: a paraboloid through +sag/2 at the centre and -sag/2 at the corners.
    let cx = (w as f64 - 1.0) / 2.0;
    let cy = (h as f64 - 1.0) / 2.0;
    let r2_max = ((cx * pitch).powi(2) + (cy * pitch).powi(2)).max(f64::MIN_POSITIVE);
    let sag = params.form_sag_um;
    let form_x: Vec<f64> = (0..w)
        .map(|x| sag * ((x as f64 - cx) * pitch).powi(2) / r2_max)
        .collect();
    // Waviness: a * sin(kx x + ky y + phi) = a (sin(kx x + phi) cos(ky y) + cos(kx x + phi) sin(ky y)).
    let wave_x: Vec<(Vec<f64>, Vec<f64>)> = waves
        .iter()
        .map(|wv| {
            (0..w)
                .map(|x| (wv.kx_per_um * x as f64 * pitch + wv.phase_rad).sin_cos())
                .unzip()
        })
        .collect();
    heights.par_chunks_mut(w).enumerate().for_each_init(
        || vec![0f64; w],
        |z, (y, row)| {
            let y_um = y as f64 * pitch;
            let fy = sag * (0.5 - ((y as f64 - cy) * pitch).powi(2) / r2_max);
            for ((zx, &v), fx) in z.iter_mut().zip(row.iter()).zip(&form_x) {
                *zx = (f64::from(v) - mean) * scale + fy - fx;
            }
            for (wv, (sx, cx_)) in waves.iter().zip(&wave_x) {
                let (sy, cy_) = (wv.ky_per_um * y_um).sin_cos();
                let (a_cy, a_sy) = (wv.amplitude_um * cy_, wv.amplitude_um * sy);
                for ((zx, s), c) in z.iter_mut().zip(sx).zip(cx_) {
                    *zx += a_cy * s + a_sy * c;
                }
            }
            for (v, zx) in row.iter_mut().zip(z.iter()) {
                *v = *zx as f32;
            }
        },
    );
    Ok(Specimen {
        heights,
        shape: Shape::new(h, w),
        pitch_um: pitch,
    })
}

/// Fills `out` (width x height, row-major) with unscaled roughness.
///
/// The field is real, so only the spectrum columns `kx = 0 ..= nx / 2` are drawn (the others
/// are their Hermitian mirrors). Pass 1 transforms those columns along y; pass 2 recovers two
/// output rows with one complex transform along x (`Z = G(y1) + i G(y2)`, extended
/// Hermitian-wise, gives `f(y1)` in the real and `f(y2)` in the imaginary part). The
/// self-mirrored columns (`kx = 0` and, for even `nx`, `nx / 2`) are made Hermitian by keeping
/// the real part after pass 1, with their amplitude raised by sqrt(2) so that they carry the
/// same power as the rest of the spectrum.
fn synthesize_roughness(params: &SpecimenParams, out: &mut [f32]) {
    let (w, h) = (params.width_px, params.height_px);
    let (nx, ny) = synthesis_shape(w, h);
    let half = nx / 2 + 1; // columns kx = 0 ..= nx / 2
    let mut planner = FftPlanner::<f32>::new();
    let fft_y = planner.plan_fft_inverse(ny);
    let fft_x = planner.plan_fft_inverse(nx);
    let q0 = 1.0 / params.correlation_length_um;
    let exponent = (-(1.0 + params.hurst) / 2.0) as f32; // amplitude = sqrt(PSD)
    let dqx = 1.0 / (nx as f64 * params.pitch_um * q0);
    let dqy = 1.0 / (ny as f64 * params.pitch_um * q0);
    let qy2: Vec<f32> = (0..ny)
        .map(|k| (signed_bin(k, ny) * dqy).powi(2) as f32)
        .collect();
    let seed = params.seed;
    let self_mirrored = |kx: usize| kx == 0 || 2 * kx == nx;

    // Pass 1: spectrum column kx (contiguous, length ny), then inverse FFT along y.
    let mut buf = vec![Complex32::default(); half * ny];
    let scratch_y = fft_y.get_inplace_scratch_len();
    buf.par_chunks_mut(ny).enumerate().for_each_init(
        || {
            (
                vec![Complex32::default(); scratch_y],
                vec![0f32; ny / 2 + 1],
            )
        },
        |(scratch, amps), (kx, col)| {
            let mut rng = stream(seed, domain::ROUGHNESS, kx as u64);
            let qx2 = (signed_bin(kx, nx) * dqx).powi(2) as f32;
            let gain = if self_mirrored(kx) {
                std::f32::consts::SQRT_2
            } else {
                1.0
            };
            // The amplitude depends on |ky| only: one powf per pair of bins.
            for (a, &qy2k) in amps.iter_mut().zip(&qy2) {
                *a = gain * (1.0 + qx2 + qy2k).powf(exponent);
            }
            for (ky, c) in col.iter_mut().enumerate() {
                let phase = rng.gen::<f32>() * std::f32::consts::TAU;
                let amp = amps[ky.min(ny - ky)];
                let (s, co) = phase.sin_cos();
                *c = Complex32::new(amp * co, amp * s);
            }
            if kx == 0 {
                col[0] = Complex32::default(); // no DC
            }
            fft_y.process_with_scratch(col, scratch);
            if self_mirrored(kx) {
                for c in col.iter_mut() {
                    c.im = 0.0;
                }
            }
        },
    );

    // Pass 2: blocks of output rows, two rows per complex transform along x.
    let scratch_x = fft_x.get_inplace_scratch_len();
    let buf = &buf;
    out.par_chunks_mut(ROW_BLOCK * w).enumerate().for_each_init(
        || {
            (
                vec![Complex32::default(); ROW_BLOCK * half],
                vec![Complex32::default(); nx],
                vec![Complex32::default(); scratch_x],
            )
        },
        |(cols, line, scratch), (block, rows_out)| {
            let y0 = block * ROW_BLOCK;
            let rows = rows_out.len() / w;
            // cols[b * half + kx] = G(kx, y0 + b)
            for kx in 0..half {
                let src = &buf[kx * ny + y0..kx * ny + y0 + rows];
                for (b, v) in src.iter().enumerate() {
                    cols[b * half + kx] = *v;
                }
            }
            for (pair, rows_pair) in rows_out.chunks_mut(2 * w).enumerate() {
                let g1 = &cols[2 * pair * half..(2 * pair + 1) * half];
                let zero: [Complex32; 0] = [];
                let g2: &[Complex32] = if rows_pair.len() == 2 * w {
                    &cols[(2 * pair + 1) * half..(2 * pair + 2) * half]
                } else {
                    &zero
                };
                for (kx, z) in line.iter_mut().enumerate() {
                    let (m, mirrored) = if kx < half {
                        (kx, false)
                    } else {
                        (nx - kx, true)
                    };
                    let a = g1[m];
                    let b = g2.get(m).copied().unwrap_or_default();
                    *z = if mirrored {
                        Complex32::new(a.re + b.im, b.re - a.im)
                    } else {
                        Complex32::new(a.re - b.im, a.im + b.re)
                    };
                }
                fft_x.process_with_scratch(line, scratch);
                let (r1, r2) = rows_pair.split_at_mut(w.min(rows_pair.len()));
                for (o, c) in r1.iter_mut().zip(line.iter()) {
                    *o = c.re;
                }
                for (o, c) in r2.iter_mut().zip(line.iter()) {
                    *o = c.im;
                }
            }
        },
    );
}

/// Mean and Sa (mean absolute deviation) of a row-major raster, deterministic (row sums in
/// parallel, added in order).
fn mean_and_sa(values: &[f32], width: usize) -> (f64, f64) {
    let n = values.len() as f64;
    let sums: Vec<f64> = values
        .par_chunks(width)
        .map(|r| r.iter().map(|&v| f64::from(v)).sum())
        .collect();
    let mean = sums.iter().sum::<f64>() / n;
    let abs: Vec<f64> = values
        .par_chunks(width)
        .map(|r| r.iter().map(|&v| (f64::from(v) - mean).abs()).sum())
        .collect();
    (mean, abs.iter().sum::<f64>() / n)
}

/// One waviness component.
struct Wave {
    amplitude_um: f64,
    kx_per_um: f64,
    ky_per_um: f64,
    phase_rad: f64,
}

fn waviness_components(params: &SpecimenParams) -> Vec<Wave> {
    let n = params.waviness_components;
    if n == 0 || params.waviness_amplitude_um == 0.0 {
        return Vec::new();
    }
    let mut rng = stream(params.seed, domain::WAVINESS, 0);
    (0..n)
        .map(|_| {
            let wavelength = params.waviness_wavelength_um * rng.gen_range(0.75..1.25);
            let direction = rng.gen_range(0.0..std::f64::consts::PI);
            let phase_rad = rng.gen_range(0.0..TAU);
            let k = TAU / wavelength;
            Wave {
                amplitude_um: params.waviness_amplitude_um / n as f64,
                kx_per_um: k * direction.cos(),
                ky_per_um: k * direction.sin(),
                phase_rad,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn signed_bins() {
        assert_eq!(signed_bin(0, 8), 0.0);
        assert_eq!(signed_bin(4, 8), 4.0);
        assert_eq!(signed_bin(5, 8), -3.0);
    }
}
