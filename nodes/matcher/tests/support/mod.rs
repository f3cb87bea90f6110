//! Synthetic, seeded test data for the matcher: a band-limited random rough surface that can
//! be sampled at exact sub-pixel shifts (Fourier shift theorem), tiles cut from it, and the
//! instrument's defects (piston, tilt, white noise, NaN dropouts).
//!
//! Shared by the integration tests and the examples (`#[path]`-included there).
#![allow(dead_code)]

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use rustfft::num_complex::Complex64;
use rustfft::FftPlanner;

/// A periodic `n x n` random surface given by its spectrum.
pub struct Surface {
    pub n: usize,
    spec: Vec<Complex64>,
}

/// Signed frequency index of bin `k` of an `n`-point DFT.
fn signed(k: usize, n: usize) -> f64 {
    if k <= n / 2 {
        k as f64
    } else {
        k as f64 - n as f64
    }
}

impl Surface {
    /// Self-affine roughness: PSD ~ (1 + (f / f0)^2)^-(1 + hurst) with corner f0 = 1 /
    /// `corr_len_px`, rolled off like an objective above `cutoff` cycles/px, rms 1 um.
    pub fn rough(n: usize, seed: u64, corr_len_px: f64, hurst: f64, cutoff: f64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let normal = Normal::new(0.0, 1.0).expect("unit normal");
        let f0 = 1.0 / corr_len_px;
        let mut spec = vec![Complex64::new(0.0, 0.0); n * n];
        for ky in 0..n {
            let fy = signed(ky, n) / n as f64;
            for kx in 0..n {
                let fx = signed(kx, n) / n as f64;
                let f2 = fx * fx + fy * fy;
                if f2 == 0.0 {
                    continue;
                }
                let psd = (1.0 + f2 / (f0 * f0)).powf(-(1.0 + hurst))
                    * (-f2 / (cutoff * cutoff)).exp();
                let amp = psd.sqrt();
                spec[ky * n + kx] =
                    Complex64::new(normal.sample(&mut rng) * amp, normal.sample(&mut rng) * amp);
            }
        }
        let mut s = Surface { n, spec };
        let field = s.render(0.0, 0.0);
        let rms = (field.iter().map(|v| v * v).sum::<f64>() / field.len() as f64).sqrt();
        for c in &mut s.spec {
            *c /= rms;
        }
        s
    }

    /// A sine grating along x: `amplitude * sin(2 pi x / period)` (period rounded so that the
    /// surface stays periodic on the n-grid).
    pub fn grating_x(n: usize, period_px: f64, amplitude_um: f64) -> Self {
        let k = (n as f64 / period_px).round() as usize;
        let mut spec = vec![Complex64::new(0.0, 0.0); n * n];
        // sin(2 pi k x / n) = (e^{i..} - e^{-i..}) / 2i; inverse FFT is unnormalised here, the
        // render divides by n^2.
        let scale = amplitude_um * (n * n) as f64 / 2.0;
        spec[k] = Complex64::new(0.0, -scale);
        spec[n - k] = Complex64::new(0.0, scale);
        Surface { n, spec }
    }

    /// The field `T(x, y) = S(x + shift_x, y + shift_y)` on the `n x n` grid, row-major.
    pub fn render(&self, shift_x: f64, shift_y: f64) -> Vec<f64> {
        let n = self.n;
        let tau = std::f64::consts::TAU;
        let px: Vec<Complex64> = (0..n)
            .map(|k| Complex64::from_polar(1.0, tau * signed(k, n) * shift_x / n as f64))
            .collect();
        let py: Vec<Complex64> = (0..n)
            .map(|k| Complex64::from_polar(1.0, tau * signed(k, n) * shift_y / n as f64))
            .collect();
        let mut buf: Vec<Complex64> = self
            .spec
            .iter()
            .enumerate()
            .map(|(i, &c)| c * px[i % n] * py[i / n])
            .collect();
        let mut planner = FftPlanner::<f64>::new();
        let fft = planner.plan_fft_inverse(n);
        // Rows, then columns through a transpose.
        fft.process(&mut buf);
        let mut t = vec![Complex64::new(0.0, 0.0); n * n];
        for r in 0..n {
            for c in 0..n {
                t[c * n + r] = buf[r * n + c];
            }
        }
        fft.process(&mut t);
        let norm = 1.0 / (n * n) as f64;
        let mut out = vec![0.0; n * n];
        for c in 0..n {
            for r in 0..n {
                out[r * n + c] = t[c * n + r].re * norm;
            }
        }
        out
    }
}

/// The `w x h` window of an `n x n` field at integer origin (x0, y0), as f32.
pub fn cut(field: &[f64], n: usize, x0: usize, y0: usize, w: usize, h: usize) -> Vec<f32> {
    assert!(x0 + w <= n && y0 + h <= n, "tile outside the surface");
    let mut out = Vec::with_capacity(w * h);
    for r in 0..h {
        out.extend(field[(y0 + r) * n + x0..(y0 + r) * n + x0 + w].iter().map(|&v| v as f32));
    }
    out
}

/// Instrument defects applied to a tile.
#[derive(Debug, Clone, Copy)]
pub struct Defects {
    pub piston_um: f64,
    pub tilt_x_um_per_px: f64,
    pub tilt_y_um_per_px: f64,
    pub noise_um: f64,
    /// Fraction of pixels dropped at random.
    pub nan_fraction: f64,
    /// Number of round dropout blobs (radius 5-30 px).
    pub nan_blobs: usize,
}

impl Defects {
    pub const NONE: Defects = Defects {
        piston_um: 0.0,
        tilt_x_um_per_px: 0.0,
        tilt_y_um_per_px: 0.0,
        noise_um: 0.0,
        nan_fraction: 0.0,
        nan_blobs: 0,
    };

    /// Random piston (+-5 um) and tilt (+-0.005 um/px), with the given noise and dropouts.
    pub fn random(rng: &mut ChaCha8Rng, noise_um: f64, nan_fraction: f64, nan_blobs: usize) -> Self {
        Defects {
            piston_um: rng.gen_range(-5.0..5.0),
            tilt_x_um_per_px: rng.gen_range(-0.005..0.005),
            tilt_y_um_per_px: rng.gen_range(-0.005..0.005),
            noise_um,
            nan_fraction,
            nan_blobs,
        }
    }

    /// Applies the defects in place; the plane is `piston + tilt_x * (col - cx) + tilt_y *
    /// (row - cy)` about the tile centre (the crate's PlaneCorrection convention).
    pub fn apply(&self, tile: &mut [f32], w: usize, h: usize, rng: &mut ChaCha8Rng) {
        let cx = (w as f64 - 1.0) / 2.0;
        let cy = (h as f64 - 1.0) / 2.0;
        let noise = Normal::new(0.0, self.noise_um.max(1e-30)).expect("normal");
        for r in 0..h {
            for c in 0..w {
                let plane = self.piston_um
                    + self.tilt_x_um_per_px * (c as f64 - cx)
                    + self.tilt_y_um_per_px * (r as f64 - cy);
                let nz = if self.noise_um > 0.0 {
                    noise.sample(rng)
                } else {
                    0.0
                };
                let v = &mut tile[r * w + c];
                *v = (*v as f64 + plane + nz) as f32;
                if self.nan_fraction > 0.0 && rng.gen::<f64>() < self.nan_fraction {
                    *v = f32::NAN;
                }
            }
        }
        for _ in 0..self.nan_blobs {
            let bx = rng.gen_range(0.0..w as f64);
            let by = rng.gen_range(0.0..h as f64);
            let rad: f64 = rng.gen_range(5.0..30.0);
            let (c0, c1) = ((bx - rad).max(0.0) as usize, ((bx + rad) as usize + 1).min(w));
            let (r0, r1) = ((by - rad).max(0.0) as usize, ((by + rad) as usize + 1).min(h));
            for r in r0..r1 {
                for c in c0..c1 {
                    let (dx, dy) = (c as f64 - bx, r as f64 - by);
                    if dx * dx + dy * dy <= rad * rad {
                        tile[r * w + c] = f32::NAN;
                    }
                }
            }
        }
    }
}

/// A pair of tiles cut from a surface with a known offset.
pub struct Pair {
    pub a: Vec<f32>,
    pub b: Vec<f32>,
    pub w: usize,
    pub h: usize,
    /// True offset of b relative to a (px).
    pub true_offset_px: [f64; 2],
    /// Nominal offset handed to the matcher (true offset minus a stage error).
    pub nominal_offset_px: [f64; 2],
    pub defects_a: Defects,
    pub defects_b: Defects,
}

/// Scenario of [`make_pair`].
#[derive(Debug, Clone, Copy)]
pub struct PairSpec {
    pub tile_px: usize,
    pub overlap: f64,
    /// true: b is right of a; false: b is below a.
    pub horizontal: bool,
    pub stage_sigma_px: f64,
    pub noise_um: f64,
    pub nan_fraction: f64,
    pub nan_blobs: usize,
    pub seed: u64,
}

impl PairSpec {
    pub fn new(tile_px: usize, overlap: f64, horizontal: bool, seed: u64) -> Self {
        PairSpec {
            tile_px,
            overlap,
            horizontal,
            stage_sigma_px: 3.0,
            noise_um: 0.05,
            nan_fraction: 0.05,
            nan_blobs: 3,
            seed,
        }
    }
}

/// Cuts two overlapping tiles from `surface` (which must be at least ~2 tiles wide): a at
/// integer origin, b at the nominal step plus a random sub-pixel stage error.
pub fn make_pair(surface: &Surface, spec: &PairSpec) -> Pair {
    let mut rng = ChaCha8Rng::seed_from_u64(spec.seed ^ 0x5eed_0f_7e57);
    let t = spec.tile_px;
    let n = surface.n;
    let step = (t as f64 * (1.0 - spec.overlap)).round();
    let err = Normal::new(0.0, spec.stage_sigma_px.max(1e-12)).expect("normal");
    let clamp = 4.0 * spec.stage_sigma_px;
    let mut e = || {
        if spec.stage_sigma_px > 0.0 {
            err.sample(&mut rng).clamp(-clamp, clamp)
        } else {
            0.0
        }
    };
    let (ex, ey) = (e(), e());
    let nominal = if spec.horizontal {
        [step, 0.0]
    } else {
        [0.0, step]
    };
    let truth = [nominal[0] + ex, nominal[1] + ey];
    // a's origin in surface coordinates leaves room for the error on both sides.
    let margin = (clamp.ceil() as usize) + 2;
    let (ax, ay) = (margin, margin);
    let ix = truth[0].floor();
    let iy = truth[1].floor();
    let (fx, fy) = (truth[0] - ix, truth[1] - iy);
    let bx = (ax as f64 + ix) as usize;
    let by = (ay as f64 + iy) as usize;
    let f0 = surface.render(0.0, 0.0);
    let mut a = cut(&f0, n, ax, ay, t, t);
    drop(f0);
    let f1 = surface.render(fx, fy);
    let mut b = cut(&f1, n, bx, by, t, t);
    drop(f1);
    let defects_a = Defects::random(&mut rng, spec.noise_um, spec.nan_fraction, spec.nan_blobs);
    let defects_b = Defects::random(&mut rng, spec.noise_um, spec.nan_fraction, spec.nan_blobs);
    defects_a.apply(&mut a, t, t, &mut rng);
    defects_b.apply(&mut b, t, t, &mut rng);
    Pair {
        a,
        b,
        w: t,
        h: t,
        true_offset_px: truth,
        nominal_offset_px: nominal,
        defects_a,
        defects_b,
    }
}

/// Size of the surface needed for `tile_px` tiles at `overlap` (a power of two).
pub fn surface_size(tile_px: usize, overlap: f64) -> usize {
    let need = tile_px + (tile_px as f64 * (1.0 - overlap)).ceil() as usize + 40;
    need.next_power_of_two()
}
