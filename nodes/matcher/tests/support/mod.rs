//! Synthetic, seeded test data for the matcher: a band-limited random rough surface sampled at
//! exact sub-pixel shifts (Fourier shift theorem), tiles cut from it, and the instrument's
//! defects (piston, tilt, white noise, NaN dropouts).
//!
//! Shared by the integration tests and the examples (`#[path]`-included there).
#![allow(dead_code)]

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use rustfft::num_complex::Complex64;
use rustfft::FftPlanner;
use surfstream_core::fft::fast_len;

/// Signed frequency index of bin `k` of an `n`-point DFT.
fn signed(k: usize, n: usize) -> f64 {
    if k <= n / 2 {
        k as f64
    } else {
        k as f64 - n as f64
    }
}

/// A periodic `nx x ny` real random surface given by its (Hermitian) spectrum, rms 1 um.
pub struct Surface {
    pub nx: usize,
    pub ny: usize,
    spec: Vec<Complex64>,
}

impl Surface {
    /// Self-affine roughness: PSD ~ (1 + (f / f0)^2)^-(1 + hurst) with corner f0 = 1 /
    /// `corr_len_px`, rolled off like an objective's transfer function above `cutoff`
    /// cycles/px (Gaussian), normalised to rms 1 um.
    pub fn rough(
        nx: usize,
        ny: usize,
        seed: u64,
        corr_len_px: f64,
        hurst: f64,
        cutoff: f64,
    ) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let f0 = 1.0 / corr_len_px;
        let mut spec = vec![Complex64::new(0.0, 0.0); nx * ny];
        for ky in 0..ny {
            let fy = signed(ky, ny) / ny as f64;
            for kx in 0..nx {
                let fx = signed(kx, nx) / nx as f64;
                let f2 = fx * fx + fy * fy;
                // Random phase, Rayleigh amplitude (Box-Muller on two uniforms).
                let u1: f64 = rng.gen::<f64>().max(1e-300);
                let u2: f64 = rng.gen();
                // Skip DC and the Nyquist lines (where the shift ramp breaks the symmetry).
                if f2 == 0.0 || 2 * kx == nx || 2 * ky == ny {
                    continue;
                }
                let psd =
                    (1.0 + f2 / (f0 * f0)).powf(-(1.0 + hurst)) * (-f2 / (cutoff * cutoff)).exp();
                let amp = psd.sqrt() * (-2.0 * u1.ln()).sqrt();
                spec[ky * nx + kx] = Complex64::from_polar(amp, std::f64::consts::TAU * u2);
            }
        }
        // Hermitian symmetry: S(-k) = conj(S(k)), so the field is real.
        let mut herm = vec![Complex64::new(0.0, 0.0); nx * ny];
        for ky in 0..ny {
            for kx in 0..nx {
                let m = ((ny - ky) % ny) * nx + (nx - kx) % nx;
                herm[ky * nx + kx] = (spec[ky * nx + kx] + spec[m].conj()) * 0.5;
            }
        }
        // Parseval: rms of the field = sqrt(sum |S|^2) / (nx ny) for an unnormalised inverse.
        let sum2: f64 = herm.iter().map(|c| c.norm_sqr()).sum();
        let scale = (nx * ny) as f64 / sum2.sqrt().max(1e-300);
        for c in &mut herm {
            *c *= scale;
        }
        Surface { nx, ny, spec: herm }
    }

    /// The field at shift (0, 0) and the field `T(x, y) = S(x + shift_x, y + shift_y)`, both
    /// row-major `nx x ny`, from one complex inverse FFT (the first in the real part, the
    /// second in the imaginary part).
    pub fn render_pair(&self, shift_x: f64, shift_y: f64) -> (Vec<f64>, Vec<f64>) {
        let (nx, ny) = (self.nx, self.ny);
        let tau = std::f64::consts::TAU;
        let px: Vec<Complex64> = (0..nx)
            .map(|k| Complex64::from_polar(1.0, tau * signed(k, nx) * shift_x / nx as f64))
            .collect();
        let py: Vec<Complex64> = (0..ny)
            .map(|k| Complex64::from_polar(1.0, tau * signed(k, ny) * shift_y / ny as f64))
            .collect();
        let i = Complex64::new(0.0, 1.0);
        let mut buf: Vec<Complex64> = self
            .spec
            .iter()
            .enumerate()
            .map(|(k, &c)| c + i * c * px[k % nx] * py[k / nx])
            .collect();
        let mut planner = FftPlanner::<f64>::new();
        planner.plan_fft_inverse(nx).process(&mut buf);
        let mut t = vec![Complex64::new(0.0, 0.0); nx * ny];
        for r in 0..ny {
            for c in 0..nx {
                t[c * ny + r] = buf[r * nx + c];
            }
        }
        planner.plan_fft_inverse(ny).process(&mut t);
        let norm = 1.0 / (nx * ny) as f64;
        let mut f0 = vec![0.0; nx * ny];
        let mut f1 = vec![0.0; nx * ny];
        for c in 0..nx {
            for r in 0..ny {
                let v = t[c * ny + r];
                f0[r * nx + c] = v.re * norm;
                f1[r * nx + c] = v.im * norm;
            }
        }
        (f0, f1)
    }
}

/// The `w x h` window of a row-major field of width `nx` at integer origin (x0, y0), as f32.
pub fn cut(field: &[f64], nx: usize, x0: usize, y0: usize, w: usize, h: usize) -> Vec<f32> {
    let ny = field.len() / nx;
    assert!(x0 + w <= nx && y0 + h <= ny, "tile outside the surface");
    let mut out = Vec::with_capacity(w * h);
    for r in 0..h {
        let row = &field[(y0 + r) * nx + x0..(y0 + r) * nx + x0 + w];
        out.extend(row.iter().map(|&v| v as f32));
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
    pub fn random(
        rng: &mut ChaCha8Rng,
        noise_um: f64,
        nan_fraction: f64,
        nan_blobs: usize,
    ) -> Self {
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
            let (c0, c1) = (
                (bx - rad).max(0.0) as usize,
                ((bx + rad) as usize + 1).min(w),
            );
            let (r0, r1) = (
                (by - rad).max(0.0) as usize,
                ((by + rad) as usize + 1).min(h),
            );
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
    /// Nominal offset handed to the matcher (the true offset minus a stage error).
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
    /// Stage positioning error (sigma, px, clamped at 4 sigma) per axis.
    pub stage_sigma_px: f64,
    pub noise_um: f64,
    pub nan_fraction: f64,
    pub nan_blobs: usize,
    /// Random piston and tilt per tile.
    pub planes: bool,
    /// When set, this stage error (px) instead of a random one.
    pub fixed_error_px: Option<[f64; 2]>,
    pub seed: u64,
}

impl PairSpec {
    /// 3 px stage error, 0.05 um noise (surface rms 1 um), 5 % dropouts plus 3 blobs,
    /// random piston and tilt.
    pub fn new(tile_px: usize, overlap: f64, horizontal: bool, seed: u64) -> Self {
        PairSpec {
            tile_px,
            overlap,
            horizontal,
            stage_sigma_px: 3.0,
            noise_um: 0.05,
            nan_fraction: 0.05,
            nan_blobs: 3,
            planes: true,
            fixed_error_px: None,
            seed,
        }
    }

    /// Nominal step between the tiles' origins along the scan axis, px.
    pub fn step_px(&self) -> f64 {
        (self.tile_px as f64 * (1.0 - self.overlap)).round()
    }

    /// Surface size (nx, ny) that holds both tiles with room for the stage error.
    pub fn surface_dims(&self) -> (usize, usize) {
        let margin = 2 * (self.max_error_px().ceil() as usize + 2);
        let long = fast_len(self.tile_px + self.step_px() as usize + margin);
        let short = fast_len(self.tile_px + margin);
        if self.horizontal {
            (long, short)
        } else {
            (short, long)
        }
    }

    /// Largest stage error this spec can produce, px.
    pub fn max_error_px(&self) -> f64 {
        match self.fixed_error_px {
            Some([x, y]) => x.abs().max(y.abs()),
            None => 4.0 * self.stage_sigma_px,
        }
    }

    /// A rough surface of the right size for this pair.
    pub fn surface(&self, corr_len_px: f64, hurst: f64, cutoff: f64) -> Surface {
        let (nx, ny) = self.surface_dims();
        Surface::rough(nx, ny, self.seed ^ 0x57f, corr_len_px, hurst, cutoff)
    }
}

/// Cuts two overlapping tiles from `surface` (see [`PairSpec::surface_dims`]): a at an
/// integer origin, b at the nominal step plus a random sub-pixel stage error.
pub fn make_pair(surface: &Surface, spec: &PairSpec) -> Pair {
    let mut rng = ChaCha8Rng::seed_from_u64(spec.seed ^ 0x005e_ed0f_7e57);
    let t = spec.tile_px;
    let step = spec.step_px();
    let err = Normal::new(0.0, spec.stage_sigma_px.max(1e-12)).expect("normal");
    let clamp = 4.0 * spec.stage_sigma_px;
    let room = spec.max_error_px();
    let mut e = || {
        if spec.stage_sigma_px > 0.0 {
            err.sample(&mut rng).clamp(-clamp, clamp)
        } else {
            0.0
        }
    };
    let (ex, ey) = match spec.fixed_error_px {
        Some([x, y]) => (x, y),
        None => (e(), e()),
    };
    let nominal = if spec.horizontal {
        [step, 0.0]
    } else {
        [0.0, step]
    };
    let truth = [nominal[0] + ex, nominal[1] + ey];
    // a's origin leaves room for the error on both sides.
    let margin = (room.ceil() as usize) + 2;
    let (ax, ay) = (margin, margin);
    let (ix, iy) = (truth[0].floor(), truth[1].floor());
    let (fx, fy) = (truth[0] - ix, truth[1] - iy);
    let bx = (ax as f64 + ix) as usize;
    let by = (ay as f64 + iy) as usize;
    let (f0, f1) = surface.render_pair(fx, fy);
    let mut a = cut(&f0, surface.nx, ax, ay, t, t);
    let mut b = cut(&f1, surface.nx, bx, by, t, t);
    let (da, db) = if spec.planes {
        (
            Defects::random(&mut rng, spec.noise_um, spec.nan_fraction, spec.nan_blobs),
            Defects::random(&mut rng, spec.noise_um, spec.nan_fraction, spec.nan_blobs),
        )
    } else {
        let d = Defects {
            noise_um: spec.noise_um,
            nan_fraction: spec.nan_fraction,
            nan_blobs: spec.nan_blobs,
            ..Defects::NONE
        };
        (d, d)
    };
    da.apply(&mut a, t, t, &mut rng);
    db.apply(&mut b, t, t, &mut rng);
    Pair {
        a,
        b,
        w: t,
        h: t,
        true_offset_px: truth,
        nominal_offset_px: nominal,
        defects_a: da,
        defects_b: db,
    }
}

/// A pair described by `spec` on its own rough surface (correlation length 40 px, Hurst 0.8,
/// optical cut-off 0.25 cycles/px: a smooth-at-the-pixel-scale surface, the harder case for
/// sub-pixel registration).
pub fn rough_pair(spec: &PairSpec) -> Pair {
    make_pair(&spec.surface(40.0, 0.8, 0.25), spec)
}
