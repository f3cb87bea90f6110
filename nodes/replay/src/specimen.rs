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
//! the padded size plus the output (8 B per point: about 0.13 GB at the 2^24-point limit
//! below). Every random number comes from a stream keyed by (seed, spectrum column), so the
//! result is bit-identical for a seed whatever the number of threads.
//!
//! ## Large specimens: a periodic roughness texture
//!
//! Synthesising the roughness whole costs memory in proportion to the specimen's area (8 B per
//! pixel at peak): a 20 x 20 scan of 1024 px fields needs a 17.4k x 17.4k specimen. So the
//! whole synthesis is kept only while the padded grid has at most
//! [`WHOLE_SYNTHESIS_MAX_POINTS`] (2^24) points, which holds every scan up to 4 x 4 fields of
//! 1024 px (the demo, the tests, the goldens: bit for bit as before). Beyond, or when
//! `roughness_period_px` is given, the roughness is one `P x P` texture (P =
//! [`ROUGHNESS_PERIOD_PX`] = 4096 px, 3.3 mm at 0.8148 um) synthesised by the same
//! spectrum with an unpadded P-point inverse FFT per axis, which is exactly periodic by
//! construction, so the texture tiles the plane without seams. It is scaled so that one period
//! has Sa = `sa_um`; the waviness and the form stay those of the whole specimen and are
//! evaluated analytically where a tile reads them ([`PeriodicSpecimen`]). Memory is then the
//! texture (64 MiB, about 130 MB while it is synthesised), whatever the scan's area.
//!
//! What it means for a user: the specimen is synthetic either way; a large one repeats its
//! roughness every P pixels in x and y (the true heights at (x, y) and (x + P, y) differ only by
//! waviness and form), its roughness statistics (Sa, the spectrum below the period, the
//! height distribution) are those of one period, and wavelengths longer than P carry no
//! roughness. P is four fields: two neighbouring tiles never see the same texture at two
//! offsets within the stage's uncertainty (tens of pixels), so registration, which searches
//! around the stage's prior, is never ambiguous. The truth (`truth.json`) says
//! `specimen.roughness_period_px` when the roughness is periodic.

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

/// Largest specimen held as a raster in memory, in pixels (2^28: 1 GiB of f32).
pub const MAX_RASTER_POINTS: usize = 1 << 28;

/// Largest padded grid synthesised whole (2^24 points: about 0.2 GB at peak). Beyond, the
/// roughness is a periodic texture.
pub const WHOLE_SYNTHESIS_MAX_POINTS: usize = 1 << 24;

/// The roughness period of a large specimen, in pixels (x and y): 4096 px = 3.34 mm at
/// 0.8148 um, four 1024 px fields.
pub const ROUGHNESS_PERIOD_PX: usize = 4096;

/// Smallest and largest `roughness_period_px` (a 8192^2 texture is 256 MiB).
pub const MIN_PERIOD_PX: usize = 8;
/// See [`MIN_PERIOD_PX`].
pub const MAX_PERIOD_PX: usize = 8192;

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
    /// Period of the roughness texture in pixels (x and y). Absent: the roughness is
    /// synthesised whole when its padded grid has at most [`WHOLE_SYNTHESIS_MAX_POINTS`]
    /// points, and as a periodic texture of [`ROUGHNESS_PERIOD_PX`] beyond (see the module
    /// doc). Given: always periodic with this period.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub roughness_period_px: Option<usize>,
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
            roughness_period_px: None,
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

/// The largest height parameter (um) of a simulated specimen or stage: 1 m, the guard every
/// input path applies to heights (`surfstream_io::formats::MAX_PLAUSIBLE_HEIGHT_UM`).
pub const MAX_HEIGHT_PARAM_UM: f64 = surfstream_io::formats::MAX_PLAUSIBLE_HEIGHT_UM;

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
        // Heights beyond +-1 m are refused from a scan directory and a recording alike; a
        // simulated specimen may not make them either.
        for (field, v) in [
            ("sa_um", self.sa_um),
            ("waviness_amplitude_um", self.waviness_amplitude_um),
            ("form_sag_um", self.form_sag_um.abs()),
        ] {
            if v > MAX_HEIGHT_PARAM_UM {
                return Err(invalid(
                    SECTION,
                    field,
                    v,
                    format!(
                        "at most {MAX_HEIGHT_PARAM_UM:e} um (heights beyond +-1 m are refused)"
                    ),
                ));
            }
        }
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
        if let Some(p) = self.roughness_period_px {
            if !(MIN_PERIOD_PX..=MAX_PERIOD_PX).contains(&p) {
                return Err(invalid(
                    SECTION,
                    "roughness_period_px",
                    p,
                    format!("an integer in {MIN_PERIOD_PX} ..= {MAX_PERIOD_PX}"),
                ));
            }
        }
        Ok(())
    }

    /// The period of the roughness texture in pixels, or `None` when the roughness is
    /// synthesised whole (see the module doc).
    pub fn roughness_period(&self) -> Option<usize> {
        if self.roughness_period_px.is_some() {
            return self.roughness_period_px;
        }
        let (nx, ny) = synthesis_shape(self.width_px, self.height_px);
        (nx.saturating_mul(ny) > WHOLE_SYNTHESIS_MAX_POINTS).then_some(ROUGHNESS_PERIOD_PX)
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
        shape.check(heights.len())?;
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

/// A height field the stage can measure: a raster in memory ([`Specimen`]) or a specimen
/// evaluated where it is looked at ([`PeriodicSpecimen`]).
pub trait SpecimenSurface: Sync {
    /// Rows (y) x columns (x), in pixels.
    fn shape(&self) -> Shape;
    /// Pixel pitch in micrometres (x and y).
    fn pitch_um(&self) -> f64;
    /// Writes the heights of the block whose pixel (0, 0) is specimen pixel (`x0`, `y0`),
    /// `width` columns by `out.len() / width` rows, row-major into `out`. Pixels outside the
    /// specimen are NaN.
    fn read_block(&self, x0: usize, y0: usize, width: usize, out: &mut [f32]);
}

impl SpecimenSurface for Specimen {
    fn shape(&self) -> Shape {
        self.shape
    }

    fn pitch_um(&self) -> f64 {
        self.pitch_um
    }

    fn read_block(&self, x0: usize, y0: usize, width: usize, out: &mut [f32]) {
        if width == 0 {
            return;
        }
        for (r, orow) in out.chunks_exact_mut(width).enumerate() {
            let src = self
                .row(y0 + r)
                .and_then(|row| row.get(x0..x0.checked_add(width)?));
            match src {
                Some(src) => orow.copy_from_slice(src),
                None => orow.fill(f32::NAN),
            }
        }
    }
}

/// Generates the specimen described by `params` as a raster in memory: roughness (Sa =
/// `sa_um` exactly, up to f32 rounding) plus waviness plus form. Deterministic for a seed,
/// whatever the thread count. A specimen whose roughness is periodic
/// ([`SpecimenParams::roughness_period`]) is the [`PeriodicSpecimen`] rendered whole; use
/// [`generate_virtual_specimen`] to measure a large one without holding its area.
pub fn generate_specimen(params: &SpecimenParams) -> Result<Specimen> {
    params.validate()?;
    let (w, h) = (params.width_px, params.height_px);
    check_raster_size(w, h)?;
    if params.roughness_period().is_some() {
        return PeriodicSpecimen::generate(params)?.to_specimen();
    }
    let mut heights = vec![0f32; w * h];
    let (mean, scale) = if params.sa_um > 0.0 {
        synthesize_roughness(params, (w, h), synthesis_shape(w, h), &mut heights);
        let (mean, sa) = mean_and_sa(&heights, w);
        (mean, if sa > 0.0 { params.sa_um / sa } else { 0.0 })
    } else {
        (0.0, 0.0)
    };
    let relief = Relief::new(params, mean, scale);
    let columns = relief.columns(0, w);
    heights.par_chunks_mut(w).enumerate().for_each_init(
        || vec![0f64; w],
        |z, (y, row)| relief.apply_row(y, &columns, row, z),
    );
    Ok(Specimen {
        heights,
        shape: Shape::new(h, w),
        pitch_um: params.pitch_um,
    })
}

fn check_raster_size(w: usize, h: usize) -> Result<()> {
    if w.saturating_mul(h) > MAX_RASTER_POINTS {
        return Err(ReplayError::TooLarge {
            what: "specimen raster".to_string(),
            width_px: w,
            height_px: h,
            limit: format!(
                "at most {MAX_RASTER_POINTS} pixels in memory (a larger specimen is measured \
                 without a raster: generate_virtual_specimen)"
            ),
        });
    }
    Ok(())
}

/// How the unscaled roughness, the waviness and the form add up to the height at a point.
/// One definition for the whole raster and for a periodic specimen's blocks.
struct Relief {
    mean: f64,
    scale: f64,
    waves: Vec<Wave>,
    pitch: f64,
    cx: f64,
    cy: f64,
    r2_max: f64,
    sag: f64,
}

/// Per-column terms of a block of columns: the form along x and every wave's (sin, cos).
struct Columns {
    form_x: Vec<f64>,
    wave_x: Vec<(Vec<f64>, Vec<f64>)>,
}

impl Relief {
    fn new(params: &SpecimenParams, mean: f64, scale: f64) -> Self {
        let (w, h) = (params.width_px, params.height_px);
        let pitch = params.pitch_um;
        // Form: a paraboloid through +sag/2 at the centre and -sag/2 at the corners.
        let cx = (w as f64 - 1.0) / 2.0;
        let cy = (h as f64 - 1.0) / 2.0;
        let r2_max = ((cx * pitch).powi(2) + (cy * pitch).powi(2)).max(f64::MIN_POSITIVE);
        Self {
            mean,
            scale,
            waves: waviness_components(params),
            pitch,
            cx,
            cy,
            r2_max,
            sag: params.form_sag_um,
        }
    }

    fn columns(&self, x0: usize, width: usize) -> Columns {
        let (pitch, cx) = (self.pitch, self.cx);
        let form_x = (x0..x0 + width)
            .map(|x| self.sag * ((x as f64 - cx) * pitch).powi(2) / self.r2_max)
            .collect();
        // Waviness: a sin(kx x + ky y + phi) = a (sin(kx x + phi) cos(ky y) + cos(kx x + phi) sin(ky y)).
        let wave_x = self
            .waves
            .iter()
            .map(|wv| {
                (x0..x0 + width)
                    .map(|x| (wv.kx_per_um * x as f64 * pitch + wv.phase_rad).sin_cos())
                    .unzip()
            })
            .collect();
        Columns { form_x, wave_x }
    }

    /// Turns one row (specimen row `y`, the columns of `columns`) of unscaled roughness into
    /// heights, in place; `z` is scratch of at least the row's length.
    fn apply_row(&self, y: usize, columns: &Columns, row: &mut [f32], z: &mut [f64]) {
        let pitch = self.pitch;
        let (mean, scale) = (self.mean, self.scale);
        let z = &mut z[..row.len()];
        let y_um = y as f64 * pitch;
        let fy = self.sag * (0.5 - ((y as f64 - self.cy) * pitch).powi(2) / self.r2_max);
        for ((zx, &v), fx) in z.iter_mut().zip(row.iter()).zip(&columns.form_x) {
            *zx = (f64::from(v) - mean) * scale + fy - fx;
        }
        for (wv, (sx, cx_)) in self.waves.iter().zip(&columns.wave_x) {
            let (sy, cy_) = (wv.ky_per_um * y_um).sin_cos();
            let (a_cy, a_sy) = (wv.amplitude_um * cy_, wv.amplitude_um * sy);
            for ((zx, s), c) in z.iter_mut().zip(sx).zip(cx_) {
                *zx += a_cy * s + a_sy * c;
            }
        }
        for (v, zx) in row.iter_mut().zip(z.iter()) {
            *v = *zx as f32;
        }
    }
}

/// A specimen of any size whose roughness is one periodic texture (see the module doc):
/// memory is the `period x period` texture, whatever the specimen's area. Heights are
/// evaluated where they are read ([`SpecimenSurface::read_block`]): the texture at
/// (x mod period, y mod period), scaled, plus the waviness and the form of the whole specimen.
pub struct PeriodicSpecimen {
    /// `period * period` unscaled roughness, row-major (empty when `sa_um` = 0).
    texture: Vec<f32>,
    period_px: usize,
    relief: Relief,
    shape: Shape,
    pitch_um: f64,
}

impl PeriodicSpecimen {
    /// Synthesises the texture for `params` (period [`SpecimenParams::roughness_period`], or
    /// [`ROUGHNESS_PERIOD_PX`] if the specimen is small enough to be made whole) and scales it
    /// so that the Sa of one period is exactly `sa_um` (up to f32 rounding).
    pub fn generate(params: &SpecimenParams) -> Result<Self> {
        params.validate()?;
        let p = params.roughness_period().unwrap_or(ROUGHNESS_PERIOD_PX);
        let mut texture = Vec::new();
        let (mean, scale) = if params.sa_um > 0.0 {
            texture = vec![0f32; p * p];
            // An unpadded p-point transform per axis: the inverse FFT is exactly periodic.
            synthesize_roughness(params, (p, p), (p, p), &mut texture);
            let (mean, sa) = mean_and_sa(&texture, p);
            (mean, if sa > 0.0 { params.sa_um / sa } else { 0.0 })
        } else {
            (0.0, 0.0)
        };
        Ok(Self {
            texture,
            period_px: p,
            relief: Relief::new(params, mean, scale),
            shape: Shape::new(params.height_px, params.width_px),
            pitch_um: params.pitch_um,
        })
    }

    /// The roughness period in pixels (x and y).
    pub fn period_px(&self) -> usize {
        self.period_px
    }

    /// Values held in memory (the texture): `period^2`, or 0 without roughness. Independent
    /// of the specimen's area.
    pub fn allocated_points(&self) -> usize {
        self.texture.len()
    }

    /// The whole specimen as a raster (refused past [`MAX_RASTER_POINTS`]).
    pub fn to_specimen(&self) -> Result<Specimen> {
        let Shape { rows, cols } = self.shape;
        check_raster_size(cols, rows)?;
        let mut heights = vec![0f32; rows * cols];
        heights
            .par_chunks_mut(cols * ROW_BLOCK)
            .enumerate()
            .for_each(|(b, block)| self.read_block(0, b * ROW_BLOCK, cols, block));
        Specimen::from_heights(heights, self.shape, self.pitch_um)
    }
}

impl SpecimenSurface for PeriodicSpecimen {
    fn shape(&self) -> Shape {
        self.shape
    }

    fn pitch_um(&self) -> f64 {
        self.pitch_um
    }

    fn read_block(&self, x0: usize, y0: usize, width: usize, out: &mut [f32]) {
        if width == 0 {
            return;
        }
        let Shape { rows, cols } = self.shape;
        let inside = cols.saturating_sub(x0).min(width);
        let columns = self.relief.columns(x0, inside);
        let mut z = vec![0f64; inside];
        let p = self.period_px;
        for (r, orow) in out.chunks_exact_mut(width).enumerate() {
            let y = y0 + r;
            orow.fill(f32::NAN);
            if y >= rows {
                continue;
            }
            let row = &mut orow[..inside];
            if self.texture.is_empty() {
                row.fill(0.0);
            } else {
                let trow = &self.texture[(y % p) * p..(y % p + 1) * p];
                // Copy the texture row in runs that wrap at the period.
                let mut done = 0;
                while done < inside {
                    let tx = (x0 + done) % p;
                    let n = (p - tx).min(inside - done);
                    row[done..done + n].copy_from_slice(&trow[tx..tx + n]);
                    done += n;
                }
            }
            self.relief.apply_row(y, &columns, row, &mut z);
        }
    }
}

/// The specimen a simulated stage measures: a raster when it is small enough to be
/// synthesised whole (every existing scan, bit for bit), a periodic specimen beyond.
pub enum VirtualSpecimen {
    /// Synthesised whole, held in memory.
    Raster(Specimen),
    /// Roughness from one periodic texture, evaluated where it is read.
    Periodic(PeriodicSpecimen),
}

impl VirtualSpecimen {
    /// The roughness period in pixels, if periodic.
    pub fn period_px(&self) -> Option<usize> {
        match self {
            VirtualSpecimen::Raster(_) => None,
            VirtualSpecimen::Periodic(s) => Some(s.period_px()),
        }
    }

    /// Values held in memory: the raster's pixels or the periodic texture's.
    pub fn allocated_points(&self) -> usize {
        match self {
            VirtualSpecimen::Raster(s) => s.heights.len(),
            VirtualSpecimen::Periodic(s) => s.allocated_points(),
        }
    }

    /// The whole specimen as a raster (a copy for a periodic one, refused past
    /// [`MAX_RASTER_POINTS`]).
    pub fn to_specimen(&self) -> Result<std::borrow::Cow<'_, Specimen>> {
        Ok(match self {
            VirtualSpecimen::Raster(s) => std::borrow::Cow::Borrowed(s),
            VirtualSpecimen::Periodic(s) => std::borrow::Cow::Owned(s.to_specimen()?),
        })
    }
}

impl SpecimenSurface for VirtualSpecimen {
    fn shape(&self) -> Shape {
        match self {
            VirtualSpecimen::Raster(s) => s.shape,
            VirtualSpecimen::Periodic(s) => s.shape,
        }
    }

    fn pitch_um(&self) -> f64 {
        match self {
            VirtualSpecimen::Raster(s) => s.pitch_um,
            VirtualSpecimen::Periodic(s) => s.pitch_um,
        }
    }

    fn read_block(&self, x0: usize, y0: usize, width: usize, out: &mut [f32]) {
        match self {
            VirtualSpecimen::Raster(s) => s.read_block(x0, y0, width, out),
            VirtualSpecimen::Periodic(s) => s.read_block(x0, y0, width, out),
        }
    }
}

/// The specimen for `params`, whole ([`generate_specimen`]) when its padded synthesis grid
/// has at most [`WHOLE_SYNTHESIS_MAX_POINTS`] points and no period is asked for, periodic
/// ([`PeriodicSpecimen`]) otherwise. Memory is bounded either way.
pub fn generate_virtual_specimen(params: &SpecimenParams) -> Result<VirtualSpecimen> {
    params.validate()?;
    Ok(if params.roughness_period().is_some() {
        VirtualSpecimen::Periodic(PeriodicSpecimen::generate(params)?)
    } else {
        VirtualSpecimen::Raster(generate_specimen(params)?)
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
fn synthesize_roughness(
    params: &SpecimenParams,
    (w, _h): (usize, usize),
    (nx, ny): (usize, usize),
    out: &mut [f32],
) {
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
