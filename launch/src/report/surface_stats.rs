//! The statistics the report's charts plot: the height histogram, the Abbott-Firestone
//! (material ratio) curve and the radially averaged power spectral density.
//!
//! These are small stand-ins: the full ISO 25178 set and a PSD are being written in
//! `surfstream_core::metrology` (branch h-params); when that lands, `material_ratio_curve`,
//! `height_histogram` and `radial_psd` are meant to be replaced by the library's, with the
//! charts unchanged.

use surfstream_core::metrology::psd::real_dft2_half_plane;
use surfstream_core::metrology::{level_plane, Grid};

/// Counts of heights in `bins` equal bins over `lo..=hi` (the valid heights' full range).
#[derive(Debug, Clone, PartialEq)]
pub struct Histogram {
    pub lo: f64,
    pub hi: f64,
    pub counts: Vec<usize>,
    pub total: usize,
}

impl Histogram {
    pub fn bin_width(&self) -> f64 {
        (self.hi - self.lo) / self.counts.len().max(1) as f64
    }
}

/// The histogram of the finite values of `z`; `None` without any. The report streams it from
/// the file (surfaces.rs); this is the reference its test compares with.
#[cfg(test)]
pub fn height_histogram(z: &[f64], bins: usize) -> Option<Histogram> {
    let (lo, hi) = z
        .iter()
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    if !lo.is_finite() || bins == 0 {
        return None;
    }
    let (lo, hi) = if hi > lo {
        (lo, hi)
    } else {
        (lo - 0.5, lo + 0.5)
    };
    let mut counts = vec![0usize; bins];
    let mut total = 0;
    for &v in z.iter().filter(|v| v.is_finite()) {
        let k = (((v - lo) / (hi - lo)) * bins as f64) as usize;
        counts[k.min(bins - 1)] += 1;
        total += 1;
    }
    Some(Histogram {
        lo,
        hi,
        counts,
        total,
    })
}

/// The Abbott-Firestone curve (ISO 25178-2 areal material ratio): `n + 1` points (Mr in %,
/// height c) with Mr(c) = the share of valid points at or above c, from Mr = 0 % (the
/// highest point) to 100 % (the lowest). Heights are the (1 - Mr) quantiles, linear
/// interpolation between order statistics.
pub fn material_ratio_curve(z: &[f64], n: usize) -> Vec<(f64, f64)> {
    let mut v: Vec<f64> = z.iter().copied().filter(|v| v.is_finite()).collect();
    if v.is_empty() || n == 0 {
        return Vec::new();
    }
    v.sort_by(f64::total_cmp);
    let last = (v.len() - 1) as f64;
    (0..=n)
        .map(|k| {
            let mr = k as f64 / n as f64;
            let pos = (1.0 - mr) * last;
            let i = pos.floor() as usize;
            let f = pos - i as f64;
            let c = if i + 1 < v.len() {
                v[i] + f * (v[i + 1] - v[i])
            } else {
                v[i]
            };
            (mr * 100.0, c)
        })
        .collect()
}

/// One bin of the radially averaged PSD.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PsdBin {
    /// Spatial frequency at the bin's centre (geometric mean of its edges), 1/um.
    pub frequency_per_um: f64,
    /// Mean of the 2-D PSD over the frequencies in the bin, um^4 (um^2 per 1/um^2).
    pub psd_um4: f64,
    /// How many 2-D frequencies fell in the bin.
    pub count: usize,
}

impl PsdBin {
    pub fn wavelength_um(&self) -> f64 {
        1.0 / self.frequency_per_um
    }
}

/// The radially averaged 2-D power spectral density of a height map (rows x cols, pitch in
/// um, NaN = not measured): the least-squares plane removed, not-measured points set to the
/// plane (zero), a separable Hann window against leakage, |FFT|^2 scaled so that the 2-D PSD
/// integrates over frequency to the windowed mean square height (Parseval: dx dy / (N M) |F|^2
/// / mean(w^2)), then averaged in `bins` logarithmic rings from the longest wavelength (the
/// map's shorter side) to the Nyquist wavelength (two pitches). DC is left out; empty rings
/// are dropped.
pub fn radial_psd(
    z: &[f64],
    rows: usize,
    cols: usize,
    pitch_x_um: f64,
    pitch_y_um: f64,
    bins: usize,
) -> Vec<PsdBin> {
    if rows < 4 || cols < 4 || bins == 0 {
        return Vec::new();
    }
    let Ok(grid) = Grid::new(z, rows, cols, pitch_x_um, pitch_y_um) else {
        return Vec::new();
    };
    let Ok(levelled) = level_plane(&grid) else {
        return Vec::new();
    };
    let hann = |n: usize| -> Vec<f64> {
        (0..n)
            .map(|i| 0.5 - 0.5 * (2.0 * std::f64::consts::PI * (i as f64 + 0.5) / n as f64).cos())
            .collect()
    };
    let (wr, wc) = (hann(rows), hann(cols));
    let mut w2 = 0.0;
    let mut data: Vec<f64> = Vec::with_capacity(rows * cols);
    for r in 0..rows {
        for c in 0..cols {
            let w = wr[r] * wc[c];
            w2 += w * w;
            let v = levelled[r * cols + c];
            data.push(if v.is_finite() { v * w } else { 0.0 });
        }
    }
    let mean_w2 = w2 / (rows * cols) as f64;
    // The real field's DFT on the half plane kx = 0..cols/2 (core's parallel real FFT): the
    // other half is its point mirror, with the same |X|^2 at the same |f|.
    let half = cols / 2 + 1;
    let data = real_dft2_half_plane(&data, rows, cols);
    let scale = pitch_x_um * pitch_y_um / (rows * cols) as f64 / mean_w2;
    let (dfx, dfy) = (
        1.0 / (cols as f64 * pitch_x_um),
        1.0 / (rows as f64 * pitch_y_um),
    );
    let f_lo = dfx.max(dfy);
    let f_hi = 0.5 / pitch_x_um.max(pitch_y_um);
    if f_hi <= f_lo {
        return Vec::new();
    }
    let (l0, l1) = (f_lo.ln(), f_hi.ln());
    let mut sum = vec![0.0; bins];
    let mut count = vec![0usize; bins];
    let signed = |k: usize, n: usize| {
        if k <= n / 2 {
            k as f64
        } else {
            k as f64 - n as f64
        }
    };
    for r in 0..rows {
        let fy = signed(r, rows) * dfy;
        for c in 0..half {
            let fx = c as f64 * dfx;
            let f = (fx * fx + fy * fy).sqrt();
            if f < f_lo || f > f_hi {
                continue;
            }
            let b = (((f.ln() - l0) / (l1 - l0)) * bins as f64) as usize;
            let b = b.min(bins - 1);
            // kx = 0 and an even width's Nyquist column have no mirror in the other half.
            let weight = if c == 0 || (cols.is_multiple_of(2) && c == cols / 2) {
                1
            } else {
                2
            };
            sum[b] += weight as f64 * data[r * half + c].norm_sqr() * scale;
            count[b] += weight;
        }
    }
    (0..bins)
        .filter(|&b| count[b] > 0)
        .map(|b| {
            let centre = l0 + (b as f64 + 0.5) / bins as f64 * (l1 - l0);
            PsdBin {
                frequency_per_um: centre.exp(),
                psd_um4: sum[b] / count[b] as f64,
                count: count[b],
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn histogram_counts_every_valid_point() {
        let z = [0.0, 1.0, 2.0, 3.0, f64::NAN, 4.0];
        let h = height_histogram(&z, 4).unwrap();
        assert_eq!((h.lo, h.hi, h.total), (0.0, 4.0, 5));
        assert_eq!(h.counts, vec![1, 1, 1, 2]);
        assert_eq!(height_histogram(&[f64::NAN], 4), None);
    }

    #[test]
    fn material_ratio_runs_from_the_highest_to_the_lowest_point() {
        let z: Vec<f64> = (0..=100).map(|i| i as f64).chain([f64::NAN]).collect();
        let c = material_ratio_curve(&z, 4);
        assert_eq!(
            c,
            vec![
                (0.0, 100.0),
                (25.0, 75.0),
                (50.0, 50.0),
                (75.0, 25.0),
                (100.0, 0.0)
            ]
        );
    }

    #[test]
    fn psd_peaks_at_the_wavelength_and_integrates_to_the_mean_square() {
        // A 16 um wave along x (32 px at 0.5 um) of amplitude 2 um: mean square 2 um^2.
        let (rows, cols, pitch) = (128, 256, 0.5);
        let z: Vec<f64> = (0..rows * cols)
            .map(|i| 2.0 * (2.0 * std::f64::consts::PI * (i % cols) as f64 / 32.0).sin())
            .collect();
        let psd = radial_psd(&z, rows, cols, pitch, pitch, 40);
        let peak = psd
            .iter()
            .max_by(|a, b| a.psd_um4.total_cmp(&b.psd_um4))
            .unwrap();
        let ratio = peak.wavelength_um() / 16.0;
        assert!(
            (0.9..1.1).contains(&ratio),
            "peak at {} um",
            peak.wavelength_um()
        );
        // Parseval over the rings: sum of PSD x (number of frequencies) x dfx dfy = the
        // windowed mean square (Hann: the wave's 2 um^2, leakage stays inside the rings).
        let (dfx, dfy) = (1.0 / (cols as f64 * pitch), 1.0 / (rows as f64 * pitch));
        let ms: f64 = psd
            .iter()
            .map(|b| b.psd_um4 * b.count as f64 * dfx * dfy)
            .sum();
        assert!((ms - 2.0).abs() < 0.1, "integrated PSD {ms} um^2");
    }
}
