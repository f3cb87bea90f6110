//! The height distribution (histogram beside the Abbott-Firestone curve, sharing the height
//! axis) and the PSD, as inline SVG, from [`super::surface_stats`].

use std::fmt::Write as _;

use super::html::{length, um};
use super::surface_stats::{material_ratio_curve, radial_psd, Histogram};
use super::surfaces::Surface;
use surfstream_io::figure::{Axis, Panel};

/// Histogram (left, % of points per bin, drawn sideways so both panels share the height axis)
/// and the Abbott-Firestone curve (right, material ratio in %).
/// `histogram`: of the whole map at full resolution, with its finer counts; the curve is from
/// the map itself when `s` holds it whole, else from the finer counts (stated).
pub fn distribution(s: &Surface, histogram: &(Histogram, Vec<usize>)) -> Option<String> {
    let (h, fine) = histogram;
    let h = h.clone();
    let curve = if s.block == 1 {
        material_ratio_curve(&s.z, 400)
    } else {
        binned_material_ratio_curve(&h, fine, 400)
    };
    let total = h.total.max(1) as f64;
    let max_pct = h
        .counts
        .iter()
        .map(|&c| 100.0 * c as f64 / total)
        .fold(0.0, f64::max);
    let ya = Axis::linear(h.lo, h.hi, "height (µm)");
    let left = Panel {
        x: 80.0,
        y: 14.0,
        w: 200.0,
        h: 380.0,
        xa: Axis::linear(0.0, max_pct * 1.08, "points per bin (%)"),
        ya: ya.clone(),
    };
    let right = Panel {
        x: 360.0,
        y: 14.0,
        w: 300.0,
        h: 380.0,
        xa: Axis::linear(0.0, 100.0, "material ratio Mr (%)"),
        ya,
    };
    let mut g = String::from(
        "<svg class=\"chart half\" viewBox=\"0 0 680 450\" role=\"img\" \
         aria-label=\"height distribution and Abbott-Firestone curve\">",
    );
    left.axes(&mut g, true);
    let bw = h.bin_width();
    for (k, &c) in h.counts.iter().enumerate() {
        let (z0, z1) = (h.lo + k as f64 * bw, h.lo + (k + 1) as f64 * bw);
        let (y0, y1) = (left.py(z1), left.py(z0));
        let w = left.px(100.0 * c as f64 / total) - left.x;
        let _ = write!(
            g,
            "<rect x=\"{:.1}\" y=\"{y0:.1}\" width=\"{w:.1}\" height=\"{:.2}\" fill=\"#5b8fc9\"/>",
            left.x,
            (y1 - y0).max(0.5)
        );
    }
    right.axes(&mut g, true);
    right.line(&mut g, &curve, "#c0392b", 2.0);
    // The mean height (0: heights are relative to the mean) as a reference line.
    let y0 = right.py(0.0);
    if (right.y..=right.y + right.h).contains(&y0) {
        let _ = write!(
            g,
            "<line x1=\"{:.1}\" y1=\"{y0:.1}\" x2=\"{:.1}\" y2=\"{y0:.1}\" stroke=\"#555\" \
             stroke-dasharray=\"4,3\"/><text x=\"{:.1}\" y=\"{:.1}\" class=\"tick\">mean</text>",
            left.x,
            right.x + right.w,
            right.x + right.w - 36.0,
            y0 - 4.0
        );
    }
    g.push_str("</svg>");
    Some(format!(
        "<figure>{g}<figcaption>Heights of the {} ({} valid points, relative to the mean), \
         {} bins of {}. Abbott-Firestone curve: the share of the surface at or above each \
         height (ISO 25178-2 areal material ratio){}.</figcaption></figure>",
        s.name,
        h.total,
        h.counts.len(),
        um(bw),
        if s.block > 1 {
            format!(
                " (from the histogram of every point in {} bins: quantiles within a bin \
                 interpolated linearly)",
                fine.len()
            )
        } else {
            String::new()
        }
    ))
}

/// The Abbott-Firestone curve as [`material_ratio_curve`] gives it, from counts in equal bins
/// over `h.lo..=h.hi` instead of the sorted heights: the (1 - Mr) quantile is placed inside
/// its bin by linear interpolation (exact to a bin's width).
pub(super) fn binned_material_ratio_curve(
    h: &Histogram,
    fine: &[usize],
    n: usize,
) -> Vec<(f64, f64)> {
    let total: usize = fine.iter().sum();
    if total == 0 || n == 0 || fine.is_empty() {
        return Vec::new();
    }
    let width = (h.hi - h.lo) / fine.len() as f64;
    let last = (total - 1) as f64;
    (0..=n)
        .map(|k| {
            let mr = k as f64 / n as f64;
            // Order statistic (0-based, ascending) of the quantile.
            let pos = (1.0 - mr) * last;
            let mut below = 0usize;
            let mut c = h.hi;
            for (b, &count) in fine.iter().enumerate() {
                if count > 0 && pos < (below + count) as f64 {
                    let f = (pos - below as f64 + 0.5) / count as f64;
                    c = h.lo + (b as f64 + f.clamp(0.0, 1.0)) * width;
                    break;
                }
                below += count;
            }
            (mr * 100.0, c)
        })
        .collect()
}

/// The radially averaged PSD, log-log, against wavelength (long wavelengths left).
/// `wavelet_cutoff`: the wavelet level that split datum from roughness and its equivalent
/// cutoff (µm, run.json's `equivalent_cutoff_um`).
pub fn psd(s: &Surface, wavelet_cutoff: Option<(u64, f64)>) -> Option<String> {
    let bins = radial_psd(&s.z, s.rows, s.cols, s.pitch_x_um, s.pitch_y_um, 48);
    let pts: Vec<(f64, f64)> = bins
        .iter()
        .filter(|b| b.psd_um4 > 0.0)
        .map(|b| (b.wavelength_um(), b.psd_um4))
        .collect();
    if pts.len() < 2 {
        return None;
    }
    let (wl_lo, wl_hi) = pts.iter().fold((f64::INFINITY, 0.0f64), |(a, b), p| {
        (a.min(p.0), b.max(p.0))
    });
    let (p_lo, p_hi) = pts.iter().fold((f64::INFINITY, 0.0f64), |(a, b), p| {
        (a.min(p.1), b.max(p.1))
    });
    let mut xa = Axis::log(wl_lo, wl_hi, "wavelength (µm)");
    // Long wavelengths on the left: swap the ends.
    std::mem::swap(&mut xa.lo, &mut xa.hi);
    let panel = Panel {
        x: 86.0,
        y: 14.0,
        w: 560.0,
        h: 380.0,
        xa,
        ya: Axis::log(p_lo, p_hi, "PSD (µm⁴)"),
    };
    let mut g = String::from(
        "<svg class=\"chart half\" viewBox=\"0 0 680 450\" role=\"img\" aria-label=\"power spectral density\">",
    );
    panel.axes(&mut g, true);
    // Points of a swapped log axis: `line` checks lo <= v <= hi, so draw through px/py.
    let d = super::html::path_d(pts.iter().map(|&(x, y)| Some((panel.px(x), panel.py(y)))));
    let _ = write!(
        g,
        "<path d=\"{d}\" fill=\"none\" stroke=\"#6c3483\" stroke-width=\"2\"/>"
    );
    for &(x, y) in &pts {
        let _ = write!(
            g,
            "<circle cx=\"{:.1}\" cy=\"{:.1}\" r=\"2.2\" fill=\"#6c3483\"/>",
            panel.px(x),
            panel.py(y)
        );
    }
    let mut note = String::new();
    if s.block > 1 {
        let _ = write!(
            note,
            " Computed from the {0} x {0} block means of the {1} x {2} px map (pitch {3}):              wavelengths below {4} are not in it, and the shortest shown are damped by the              averaging.",
            s.block,
            s.file_shape.0,
            s.file_shape.1,
            length(s.pitch_x_um / s.block as f64),
            length(2.0 * s.pitch_x_um.max(s.pitch_y_um)),
        );
    }
    if let Some((level, cutoff_um)) = wavelet_cutoff {
        let x = panel.px(cutoff_um);
        // 4 significant figures, as the separate verb and the level warning state it.
        let cutoff = format!("{} µm", super::html::sig(cutoff_um, 4));
        if (panel.x..=panel.x + panel.w).contains(&x) {
            let _ = write!(
                g,
                "<line x1=\"{x:.1}\" y1=\"{:.1}\" x2=\"{x:.1}\" y2=\"{:.1}\" stroke=\"#e4572e\" \
                 stroke-dasharray=\"6,4\" stroke-width=\"1.5\"/><text x=\"{:.1}\" y=\"{:.1}\" \
                 class=\"tick\" fill=\"#e4572e\">level {level}: {}</text>",
                panel.y,
                panel.y + panel.h,
                x + 4.0,
                panel.y + 16.0,
                cutoff
            );
            let _ = write!(
                note,
                " Dashed: the equivalent cutoff of wavelet level {level} ({cutoff}, where the \
                 datum passes 50 % amplitude; run.json's equivalent_cutoff_um): longer \
                 wavelengths go to the datum, shorter to the roughness (the transition is \
                 about an octave wide).",
            );
        }
    }
    g.push_str("</svg>");
    Some(format!(
        "<figure>{g}<figcaption>Power spectral density of the {}: least-squares plane removed, \
         not-measured points set to the plane, Hann window, 2-D |FFT|² scaled to µm⁴ \
         (integrates to the mean square height), averaged over rings of equal wavelength \
         ({} log-spaced rings from {} to the Nyquist wavelength {}).{note}</figcaption></figure>",
        s.name,
        bins.len(),
        length(wl_hi),
        um(2.0 * s.pitch_x_um.max(s.pitch_y_um)),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_psd_marks_the_wavelet_level_at_its_equivalent_cutoff() {
        // 512 x 512 at 0.8148 um: wavelengths from ~1.6 to ~420 um, the demo's 208.9 um cutoff
        // among them (the level's 2^7 pitches would be 104.3 um).
        let (rows, cols, pitch) = (512, 512, 0.8148);
        let z: Vec<f64> = (0..rows * cols)
            .map(|i| {
                let (r, c) = ((i / cols) as f64, (i % cols) as f64);
                (c * 0.37).sin() + (r * 0.11).cos() * 2.0 + (r * c * 0.001).sin()
            })
            .collect();
        let s = Surface {
            name: "panorama",
            z,
            rows,
            cols,
            pitch_x_um: pitch,
            pitch_y_um: pitch,
            block: 1,
            file_shape: (rows, cols),
        };
        let f = psd(&s, Some((7, 208.861))).unwrap();
        assert!(f.contains(">level 7: 208.9 µm</text>"), "{f}");
        assert!(
            f.contains(
                "equivalent cutoff of wavelet level 7 (208.9 µm, where the datum passes 50 %"
            ),
            "{f}"
        );
        assert!(!f.contains("104.3"), "{f}");
    }
}
