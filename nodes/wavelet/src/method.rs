//! The separation methods beside the paper's wavelet: the ISO 16610 filters of
//! `surfstream_core::filter`, and the wavelet level's equivalent cutoff wavelength.
//!
//! * `gaussian` / `robust-gaussian`: datum = the L-filter's mean surface (ISO 16610-61
//!   Gaussian or ISO 16610-71 robust Gaussian regression, cutoff `lambda_c`), computed on the
//!   map minus its least-squares plane and the plane added back, so a tilted map keeps its
//!   tilt in the datum up to the edges (the filter's zeroth-order end correction alone would
//!   bend it there); roughness = heights - datum. With an S-filter `lambda_s`, heights are the
//!   primary surface (the map S-filtered) and roughness is the S-L surface; datum + roughness
//!   is then the primary surface, not the raw map.
//! * [`equivalent_cutoff_um`]: the wavelength at which the level-`l` approximation passes 50 %
//!   amplitude. The approximation-only reconstruction is analysis low-pass, downsampling,
//!   upsampling and synthesis low-pass per level; ignoring aliasing it transmits
//!   `T(w) = prod_{k<l} |H(2^k w)|^2 / 2` of a sinusoid of angular frequency `w` (rad per
//!   sample), `H` the decomposition low-pass (`|H(0)|^2 = 2`). The cutoff is `2 pi pitch / w50`
//!   with `w50` the smallest `w` where `T` falls to 0.5, found numerically. For every
//!   orthogonal base `T = 0.5` at `w = pi/2` for level 1, i.e. 4 pitches; each level about
//!   doubles it.

use std::f64::consts::PI;

use surfstream_core::filter::{
    fit_polynomial, gaussian_filter, robust_gaussian_filter, FilterError, RobustSettings,
};
use surfstream_core::{ParamError, Sampling};

use crate::Wavelet;

/// How the datum is separated from the roughness.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum SeparationMethod {
    /// The paper's wavelet low-pass (base and level from the settings).
    Wavelet,
    /// ISO 16610-61 Gaussian L-filter with `lambda_c = cutoff_um`.
    Gaussian { cutoff_um: f64 },
    /// ISO 16610-71 robust Gaussian regression filter (zeroth order), `lambda_c = cutoff_um`.
    RobustGaussian { cutoff_um: f64 },
}

/// A separation method by name, before its cutoff is known (a graph's `method`, the
/// `separate` verb's `--method`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum SeparationKind {
    /// The paper's wavelet low-pass (default).
    #[default]
    Wavelet,
    /// ISO 16610-61 Gaussian L-filter.
    Gaussian,
    /// ISO 16610-71 robust Gaussian regression filter.
    RobustGaussian,
}

impl SeparationKind {
    /// "wavelet", "gaussian" or "robust-gaussian".
    pub fn name(self) -> &'static str {
        match self {
            SeparationKind::Wavelet => "wavelet",
            SeparationKind::Gaussian => "gaussian",
            SeparationKind::RobustGaussian => "robust-gaussian",
        }
    }
}

impl std::str::FromStr for SeparationKind {
    type Err = String;
    /// A name, ASCII case and surrounding blanks ignored.
    fn from_str(s: &str) -> Result<Self, String> {
        [
            SeparationKind::Wavelet,
            SeparationKind::Gaussian,
            SeparationKind::RobustGaussian,
        ]
        .into_iter()
        .find(|k| k.name().eq_ignore_ascii_case(s.trim()))
        .ok_or_else(|| format!("{s:?}: expected \"wavelet\", \"gaussian\" or \"robust-gaussian\""))
    }
}

impl SeparationMethod {
    /// "wavelet", "gaussian" or "robust-gaussian".
    pub fn name(&self) -> &'static str {
        match self {
            SeparationMethod::Wavelet => "wavelet",
            SeparationMethod::Gaussian { .. } => "gaussian",
            SeparationMethod::RobustGaussian { .. } => "robust-gaussian",
        }
    }

    /// The method by name; `cutoff_um` is required by the filters and refused by the wavelet.
    /// The error says what was expected (the caller names the field).
    pub fn parse(name: &str, cutoff_um: Option<f64>) -> Result<Self, String> {
        let kind = name.parse().map_err(|e| format!("method = {e}"))?;
        Self::with_cutoff(kind, cutoff_um)
    }

    /// The method of this kind; `cutoff_um` is required by the filters and refused by the
    /// wavelet.
    pub fn with_cutoff(kind: SeparationKind, cutoff_um: Option<f64>) -> Result<Self, String> {
        let cutoff = |c: Option<f64>| match c {
            Some(c) if c.is_finite() && c > 0.0 => Ok(c),
            Some(c) => Err(format!(
                "cutoff_um = {c}: expected a positive wavelength in µm"
            )),
            None => Err(format!(
                "cutoff_um missing: method \"{}\" needs the L-filter's cutoff wavelength in µm",
                kind.name()
            )),
        };
        match kind {
            SeparationKind::Wavelet => match cutoff_um {
                None => Ok(SeparationMethod::Wavelet),
                Some(_) => Err("cutoff_um: applies to method \"gaussian\" or \"robust-gaussian\"; the wavelet's cutoff follows from its level".into()),
            },
            SeparationKind::Gaussian => Ok(SeparationMethod::Gaussian {
                cutoff_um: cutoff(cutoff_um)?,
            }),
            SeparationKind::RobustGaussian => Ok(SeparationMethod::RobustGaussian {
                cutoff_um: cutoff(cutoff_um)?,
            }),
        }
    }

    /// The L-filter's cutoff, for the filter methods.
    pub fn cutoff_um(&self) -> Option<f64> {
        match *self {
            SeparationMethod::Wavelet => None,
            SeparationMethod::Gaussian { cutoff_um }
            | SeparationMethod::RobustGaussian { cutoff_um } => Some(cutoff_um),
        }
    }
}

/// Datum and roughness by an ISO 16610 filter (module doc).
#[derive(Debug, Clone, PartialEq)]
pub struct FilterSeparation {
    pub datum: Vec<f32>,
    pub roughness: Vec<f32>,
    /// The plane removed before filtering and added back: [a, b, c] of `a + b u + c v`
    /// (`u, v` in [-1, 1] across the map), µm.
    pub plane_um: [f64; 3],
    /// Robust filter only: iterations and whether it converged.
    pub robust_iterations: Option<(usize, bool)>,
}

/// Separates `heights` (row-major, µm, NaN = not measured) on `grid` with a filter `method`
/// (not [`SeparationMethod::Wavelet`]) and optional S-filter `lambda_s_um`.
pub fn filter_separation(
    heights: &[f32],
    grid: Sampling,
    method: SeparationMethod,
    lambda_s_um: Option<f64>,
) -> Result<FilterSeparation, FilterError> {
    let cutoff = method.cutoff_um().ok_or(FilterError::from(ParamError::new(
        "method",
        f64::NAN,
        "a filter method (gaussian or robust-gaussian)",
    )))?;
    if let Some(ls) = lambda_s_um {
        if !(ls.is_finite() && ls > 0.0 && ls < cutoff) {
            return Err(FilterError::from(ParamError::new(
                "lambda_s_um",
                ls,
                "a positive S-filter cutoff shorter than cutoff_um",
            )));
        }
    }
    let primary = match lambda_s_um {
        Some(ls) => gaussian_filter(heights, grid, ls)?,
        None => heights.to_vec(),
    };
    let plane = fit_polynomial(&primary, grid, 1)?;
    let levelled = plane.remove(&primary, grid);
    let (mean, robust_iterations) = match method {
        SeparationMethod::RobustGaussian { .. } => {
            let fit = robust_gaussian_filter(&levelled, grid, &RobustSettings::new(cutoff))?;
            (fit.mean, Some((fit.iterations, fit.converged)))
        }
        _ => (gaussian_filter(&levelled, grid, cutoff)?, None),
    };
    drop(levelled);
    let form = plane.evaluate(grid);
    let mut datum = vec![0.0f32; heights.len()];
    let mut roughness = vec![0.0f32; heights.len()];
    for i in 0..heights.len() {
        let d = f64::from(mean[i]) + form[i];
        let ok = heights[i].is_finite() && mean[i].is_finite();
        datum[i] = if ok { d as f32 } else { f32::NAN };
        roughness[i] = if ok {
            (f64::from(primary[i]) - d) as f32
        } else {
            f32::NAN
        };
    }
    let c = &plane.coefficients;
    Ok(FilterSeparation {
        datum,
        roughness,
        plane_um: [c[0], c[1], c[2]],
        robust_iterations,
    })
}

/// The amplitude transmission `T(w)` of the level-`level` approximation of `wavelet` for a
/// sinusoid of `w` radians per sample (module doc).
pub fn approximation_transmission(wavelet: &Wavelet, level: usize, w: f64) -> f64 {
    let h = wavelet.dec_lo();
    (0..level)
        .map(|k| {
            let wk = w * f64::from(1u32 << k.min(30));
            let (re, im) = h.iter().enumerate().fold((0.0, 0.0), |(re, im), (n, &c)| {
                (
                    re + c * (n as f64 * wk).cos(),
                    im - c * (n as f64 * wk).sin(),
                )
            });
            (re * re + im * im) / 2.0
        })
        .product()
}

/// The equivalent cutoff wavelength (µm) of the level-`level` wavelet datum at `pitch_um`:
/// where its approximation passes 50 % amplitude (module doc).
pub fn equivalent_cutoff_um(wavelet: &Wavelet, level: usize, pitch_um: f64) -> f64 {
    let level = level.max(1);
    // T falls from 1 at w = 0; the first crossing of 0.5 lies below pi / 2^(level-1). Scan on
    // a fine grid for the bracket, then bisect.
    let top = PI / f64::from(1u32 << (level - 1).min(30));
    let steps = 4096;
    let mut lo = 0.0;
    let mut hi = top;
    for s in 1..=steps {
        let w = top * s as f64 / steps as f64;
        if approximation_transmission(wavelet, level, w) <= 0.5 {
            hi = w;
            break;
        }
        lo = w;
    }
    for _ in 0..60 {
        let mid = 0.5 * (lo + hi);
        if approximation_transmission(wavelet, level, mid) > 0.5 {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    2.0 * PI * pitch_um / (0.5 * (lo + hi))
}

/// The warning to print when the level used is below the level asked for (the map is too
/// small for it), with both cutoffs; `None` when the level was kept.
pub fn level_lowered_warning(
    wavelet: &Wavelet,
    requested: usize,
    used: usize,
    pitch_um: f64,
) -> Option<String> {
    (used < requested).then(|| {
        format!(
            "warning: wavelet level {requested} lowered to {used}: the map is too small for {}; \
             the datum's equivalent cutoff is {:.1} µm instead of {:.1} µm",
            wavelet.name(),
            equivalent_cutoff_um(wavelet, used, pitch_um),
            equivalent_cutoff_um(wavelet, requested, pitch_um),
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn level_one_cuts_at_four_pitches_and_each_level_about_doubles() {
        for name in ["db1", "sym5", "coif3"] {
            let w = Wavelet::by_name(name).unwrap();
            let l1 = equivalent_cutoff_um(&w, 1, 0.5);
            assert!((l1 - 2.0).abs() < 1e-9, "{name}: {l1}");
            for level in 2..=8 {
                let r =
                    equivalent_cutoff_um(&w, level, 0.5) / equivalent_cutoff_um(&w, level - 1, 0.5);
                assert!((1.7..2.3).contains(&r), "{name} level {level}: ratio {r}");
            }
        }
        // Haar level 1: T = cos^2(w / 2).
        let haar = Wavelet::by_name("db1").unwrap();
        let w = 1.1;
        assert!((approximation_transmission(&haar, 1, w) - (w / 2.0).cos().powi(2)).abs() < 1e-12);
    }

    /// Amplitude of the sinusoid of `period` samples in `v`, by least squares on sin and cos.
    fn amplitude(v: &[f32], period: f64) -> f64 {
        let (mut ss, mut cc, mut sc, mut zs, mut zc) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for (n, &z) in v.iter().enumerate() {
            let (s, c) = (2.0 * PI * n as f64 / period).sin_cos();
            let z = f64::from(z);
            (ss, cc, sc, zs, zc) = (ss + s * s, cc + c * c, sc + s * c, zs + z * s, zc + z * c);
        }
        let det = ss * cc - sc * sc;
        let (a, b) = ((zs * cc - zc * sc) / det, (zc * ss - zs * sc) / det);
        (a * a + b * b).sqrt()
    }

    #[test]
    fn the_datum_transmits_sinusoids_as_the_filter_bank_response_says() {
        // The separation itself (sym5 level 4, periodization) on sinusoids along x: the amplitude
        // at the input's frequency follows T(w) on both sides of the cutoff. At the cutoff
        // itself (2^(l+1) samples, the coarse grid's Nyquist) the alias falls on the same
        // frequency and the transmission depends on phase: the definition ignores aliasing.
        let sym5 = Wavelet::by_name("sym5").unwrap();
        let (rows, cols, level) = (256, 2048, 4);
        let lc = equivalent_cutoff_um(&sym5, level, 1.0);
        assert!((lc - 32.0).abs() < 0.5, "{lc}");
        for period in [20.0, 24.0, 40.0, 48.0, 64.0] {
            let h: Vec<f32> = (0..rows * cols)
                .map(|i| (2.0 * PI * (i % cols) as f64 / period).sin() as f32)
                .collect();
            let s = crate::separate(
                &h,
                rows,
                cols,
                &sym5,
                crate::Mode::Periodization,
                Some(level),
            )
            .unwrap();
            assert_eq!(s.level, level);
            let row = &s.datum[128 * cols..129 * cols];
            let got = amplitude(row, period);
            let want = approximation_transmission(&sym5, level, 2.0 * PI / period);
            assert!(
                (got - want).abs() < 0.03,
                "period {period}: {got} vs T = {want}"
            );
        }
    }

    #[test]
    fn methods_parse_and_name_the_field() {
        assert_eq!(
            SeparationMethod::parse("wavelet", None),
            Ok(SeparationMethod::Wavelet)
        );
        assert_eq!(
            SeparationMethod::parse(" Robust-Gaussian", Some(80.0)),
            Ok(SeparationMethod::RobustGaussian { cutoff_um: 80.0 })
        );
        assert!(SeparationMethod::parse("gaussian", None)
            .unwrap_err()
            .starts_with("cutoff_um"));
        assert!(SeparationMethod::parse("gaussian", Some(-1.0))
            .unwrap_err()
            .starts_with("cutoff_um"));
        assert!(SeparationMethod::parse("wavelet", Some(8.0))
            .unwrap_err()
            .starts_with("cutoff_um"));
        assert!(SeparationMethod::parse("median", None)
            .unwrap_err()
            .starts_with("method"));
    }

    #[test]
    fn gaussian_separation_keeps_a_tilted_plane_in_the_datum_to_the_edges() {
        let grid = Sampling::square(surfstream_core::Shape::new(90, 120), 0.5).unwrap();
        let h: Vec<f32> = (0..90 * 120)
            .map(|i| (3.0 + 0.02 * (i % 120) as f64 - 0.01 * (i / 120) as f64) as f32)
            .collect();
        for method in [
            SeparationMethod::Gaussian { cutoff_um: 25.0 },
            SeparationMethod::RobustGaussian { cutoff_um: 25.0 },
        ] {
            let s = filter_separation(&h, grid, method, None).unwrap();
            let worst = s.roughness.iter().fold(0.0f32, |m, r| m.max(r.abs()));
            assert!(worst < 1e-4, "{method:?}: roughness of a plane {worst}");
        }
        assert!(filter_separation(&h, grid, SeparationMethod::Wavelet, None).is_err());
        let g = SeparationMethod::Gaussian { cutoff_um: 25.0 };
        assert!(filter_separation(&h, grid, g, Some(30.0)).is_err());
    }
}
