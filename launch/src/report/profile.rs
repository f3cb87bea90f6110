//! The profile cut: one row through the middle of the panorama (the dashed line on the
//! panorama map), heights vs x: the panorama with the datum over it, and the roughness (their
//! difference) below on its own scale. Gaps are not-measured points.

use std::fmt::Write as _;

use super::html::{length, pitch};
use super::surfaces::Surfaces;
use surfstream_io::figure::{Axis, Panel};

/// The row the profile runs along, on the panorama as held (block means when decimated).
pub fn row(s: &Surfaces) -> Option<usize> {
    let p = s.panorama.as_ref()?;
    Some(
        s.profile
            .as_ref()
            .map_or(p.rows / 2, |c| c.row / p.block.max(1)),
    )
}

pub fn section(s: &Surfaces) -> Option<String> {
    let p = s.panorama.as_ref()?;
    // The cut at full resolution, read from the files.
    let cut = s.profile.as_ref()?;
    let r = cut.row;
    let (pitch_x_um, pitch_y_um) = (p.pitch_x_um / p.block as f64, p.pitch_y_um / p.block as f64);
    let cols = cut.panorama.len();
    let to_mm = p.width_um() >= 2000.0;
    let (unit, div) = if to_mm { ("mm", 1000.0) } else { ("µm", 1.0) };
    let xs = |cols: usize, pitch: f64| -> Vec<f64> {
        (0..cols).map(|c| (c as f64 + 0.5) * pitch / div).collect()
    };
    let x = xs(cols, pitch_x_um);
    let series =
        |z: &[f64]| -> Vec<(f64, f64)> { x.iter().copied().zip(z.iter().copied()).collect() };
    let pano = series(&cut.panorama);
    let datum = cut.datum.as_deref().map(series);
    let rough = cut.roughness.as_deref().map(series);
    let range = |pts: &[(f64, f64)]| {
        pts.iter()
            .map(|p| p.1)
            .filter(|v| v.is_finite())
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
                (a.min(v), b.max(v))
            })
    };
    let (lo, hi) = range(&pano);
    if !lo.is_finite() {
        return None;
    }
    let pad = (hi - lo) * 0.05;
    let xa = Axis::linear(0.0, p.width_um() / div, &format!("x ({unit})"));
    let top = Panel {
        x: 80.0,
        y: 14.0,
        w: 1000.0,
        h: 250.0,
        xa: xa.clone(),
        ya: Axis::linear(lo - pad, hi + pad, "height (µm)"),
    };
    let mut g = String::new();
    let total_h = if rough.is_some() { 530.0 } else { 310.0 };
    let _ = write!(
        g,
        "<svg class=\"chart\" viewBox=\"0 0 1100 {total_h:.0}\" role=\"img\" aria-label=\"profile cut\">"
    );
    top.axes(&mut g, rough.is_none());
    top.line(&mut g, &pano, "#1f5fa8", 1.0);
    top.legend(&mut g, 0, "#1f5fa8", "panorama (measured)");
    if let Some(d) = &datum {
        top.line(&mut g, d, "#e4572e", 2.0);
        top.legend(&mut g, 1, "#e4572e", "datum (wavelet)");
    }
    if let Some(rr) = &rough {
        let (a, b) = range(rr);
        let m = a.abs().max(b.abs()).max(1e-6) * 1.05;
        let bottom = Panel {
            x: 80.0,
            y: 284.0,
            w: 1000.0,
            h: 190.0,
            xa,
            ya: Axis::linear(-m, m, "roughness (µm)"),
        };
        bottom.axes(&mut g, true);
        bottom.line(&mut g, rr, "#2a8c55", 1.0);
        bottom.legend(&mut g, 0, "#2a8c55", "roughness = panorama - datum");
    }
    g.push_str("</svg>");
    Some(format!(
        "<figure class=\"wide\">{g}<figcaption>Row {r} of {} (y = {} down from the top edge, where row 0 is, the \
         dashed line on the panorama), {} long, {} points at {} pitch; heights relative to the \
         panorama's mean. Gaps: not measured.</figcaption></figure>",
        p.file_shape.0,
        length((r as f64 + 0.5) * pitch_y_um),
        length(p.width_um()),
        cols,
        pitch(pitch_x_um),
    ))
}
