//! finish.html: a standalone page of one finishing run: the wear map, the worn against the
//! original profile, the Abbott curves before and after, and the parameters.

use std::io::Write;
use std::path::Path;

use anyhow::{anyhow, Context, Result};
use base64::Engine;
use serde_json::Value;

/// The paper's measured part before and after 5 min of finishing, um.
pub const PAPER_BEFORE: [(&str, f64); 3] = [("Sa", 1.272), ("Sq", 1.624), ("Sz", 15.262)];
pub const PAPER_AFTER: [(&str, f64); 3] = [("Sa", 0.565), ("Sq", 0.708), ("Sz", 6.162)];

pub fn write_report(
    path: &Path,
    summary: &Value,
    original: &[f64],
    worn: &[f64],
    wear: &[f64],
    rows: usize,
    cols: usize,
) -> Result<()> {
    let png = heat_png(wear, rows, cols)?;
    let b64 = base64::engine::general_purpose::STANDARD.encode(png);
    let mid = rows / 2;
    let pitch = summary["setting"]["patch"]["pitch_um"][0]
        .as_f64()
        .unwrap_or(1.0);
    let prof_a: Vec<(f64, f64)> = (0..cols)
        .map(|c| (c as f64 * pitch, original[mid * cols + c]))
        .collect();
    let prof_b: Vec<(f64, f64)> = (0..cols)
        .map(|c| (c as f64 * pitch, worn[mid * cols + c]))
        .collect();
    let curve = |k: &str| -> Vec<(f64, f64)> {
        let a = &summary[k];
        let mr = a["material_ratio_pct"]
            .as_array()
            .cloned()
            .unwrap_or_default();
        let h = a["height_um"].as_array().cloned().unwrap_or_default();
        mr.iter()
            .zip(&h)
            .filter_map(|(m, h)| Some((m.as_f64()?, h.as_f64()?)))
            .collect()
    };
    let profile_svg = svg_lines(
        &[(&prof_a, "#888", "original"), (&prof_b, "#c0392b", "worn")],
        "x (um)",
        "height (um)",
    );
    let abbott_svg = svg_lines(
        &[
            (&curve("abbott_before"), "#888", "before"),
            (&curve("abbott_after"), "#c0392b", "after"),
        ],
        "material ratio (%)",
        "height (um)",
    );
    let mut rows_html = String::new();
    for key in [
        "Sa", "Sq", "Sz", "Sp", "Sv", "Sk", "Spk", "Svk", "Ssk", "Sku",
    ] {
        let b = summary["before"][key].as_f64().unwrap_or(f64::NAN);
        let a = summary["after"][key].as_f64().unwrap_or(f64::NAN);
        let paper = |t: &[(&str, f64)]| {
            t.iter()
                .find(|(k, _)| *k == key)
                .map_or(String::new(), |(_, v)| format!("{v:.3}"))
        };
        rows_html.push_str(&format!(
            "<tr><td>{key}</td><td>{b:.3}</td><td>{a:.3}</td><td>{}</td><td>{}</td></tr>",
            paper(&PAPER_BEFORE),
            paper(&PAPER_AFTER)
        ));
    }
    let max_depth = wear.iter().cloned().fold(0.0, f64::max);
    let partial = summary["partial"].as_bool().unwrap_or(false);
    let sim_ideal = summary["ideal_model"]["sim_wear_maps"]
        .as_f64()
        .map_or("not run".to_string(), |s| format!("{s:.3}"));
    let html = format!(
        "<!doctype html><html><head><meta charset=\"utf-8\"><title>surfstream finish</title>\
<style>body{{font-family:sans-serif;margin:24px;color:#222}}table{{border-collapse:collapse}}\
td,th{{border:1px solid #ccc;padding:3px 8px;text-align:right}}.row{{display:flex;gap:24px;flex-wrap:wrap}}\
figure{{margin:0}}figcaption{{font-size:13px;color:#555}}</style></head><body>\
<h1>Finishing simulation{}</h1>\
<p>Model: {}; {} of {} cycle(s); engine {:.1} s, surfstream {:.1} s; volume check {:.2e}; \
SIM(model vs ideal wear maps) {sim_ideal}.</p>\
<div class=\"row\"><figure><img src=\"data:image/png;base64,{b64}\" width=\"{}\" style=\"image-rendering:pixelated;border:1px solid #ccc\">\
<figcaption>Wear depth along z (Finnie), 0 (dark) to {max_depth:.3} um (light)</figcaption></figure>\
<figure>{profile_svg}<figcaption>Middle row: original (grey) and worn (red)</figcaption></figure>\
<figure>{abbott_svg}<figcaption>Abbott-Firestone curves before (grey) and after (red)</figcaption></figure></div>\
<h2>Parameters (um)</h2><table><tr><th>param</th><th>before</th><th>after</th><th>paper before</th><th>paper after (5 min)</th></tr>{rows_html}</table>\
</body></html>",
        if partial { " (partial: stopped)" } else { "" },
        html_escape(summary["model"].as_str().unwrap_or("")),
        summary["cycles_completed"],
        summary["cycles_requested"],
        summary["timings"]["engine_s"].as_f64().unwrap_or(0.0),
        summary["timings"]["surfstream_overhead_s"].as_f64().unwrap_or(0.0),
        summary["volume_check"]["relative_error"].as_f64().unwrap_or(f64::NAN),
        (cols * 2).clamp(200, 420),
    );
    let mut f =
        std::fs::File::create(path).with_context(|| format!("{}: cannot write", path.display()))?;
    f.write_all(html.as_bytes())
        .with_context(|| format!("{}: write failed", path.display()))
}

fn html_escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

/// A grey-to-orange ramp of `z` (0 .. max) as PNG bytes.
fn heat_png(z: &[f64], rows: usize, cols: usize) -> Result<Vec<u8>> {
    let max = z.iter().cloned().fold(0.0, f64::max);
    let mut px = Vec::with_capacity(rows * cols * 3);
    for &v in z {
        let t = if max > 0.0 {
            (v / max).clamp(0.0, 1.0)
        } else {
            0.0
        };
        // Dark blue -> orange -> pale yellow.
        let r = (30.0 + 225.0 * t.sqrt()) as u8;
        let g = (30.0 + 200.0 * t) as u8;
        let b = (80.0 * (1.0 - t) + 60.0 * t * t) as u8;
        px.extend_from_slice(&[r, g, b]);
    }
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, cols as u32, rows as u32);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut w = enc.write_header().map_err(|e| anyhow!("png: {e}"))?;
        w.write_image_data(&px).map_err(|e| anyhow!("png: {e}"))?;
    }
    Ok(out)
}

/// A small line chart of several series.
/// A named series: points, colour, label.
type Series<'a> = (&'a Vec<(f64, f64)>, &'a str, &'a str);

fn svg_lines(series: &[Series<'_>], xlabel: &str, ylabel: &str) -> String {
    let (w, h, m) = (420.0, 260.0, 40.0);
    let pts = series.iter().flat_map(|(s, _, _)| s.iter());
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for &(x, y) in pts {
        if x.is_finite() && y.is_finite() {
            x0 = x0.min(x);
            x1 = x1.max(x);
            y0 = y0.min(y);
            y1 = y1.max(y);
        }
    }
    if x0 >= x1 {
        x1 = x0 + 1.0;
    }
    if y0 >= y1 {
        y1 = y0 + 1.0;
    }
    let sx = |x: f64| m + (x - x0) / (x1 - x0) * (w - 1.5 * m);
    let sy = |y: f64| h - m - (y - y0) / (y1 - y0) * (h - 1.5 * m);
    let mut s = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" style=\"border:1px solid #ccc\">\
<text x=\"{}\" y=\"{}\" font-size=\"12\" text-anchor=\"middle\">{xlabel}</text>\
<text x=\"12\" y=\"{}\" font-size=\"12\" transform=\"rotate(-90 12 {})\" text-anchor=\"middle\">{ylabel}</text>\
<text x=\"{m}\" y=\"{}\" font-size=\"10\">{x0:.3}</text><text x=\"{}\" y=\"{}\" font-size=\"10\" text-anchor=\"end\">{x1:.3}</text>\
<text x=\"{}\" y=\"{}\" font-size=\"10\" text-anchor=\"end\">{y1:.2}</text><text x=\"{}\" y=\"{}\" font-size=\"10\" text-anchor=\"end\">{y0:.2}</text>",
        w / 2.0,
        h - 6.0,
        h / 2.0,
        h / 2.0,
        h - m + 14.0,
        w - 0.5 * m,
        h - m + 14.0,
        m - 2.0,
        0.5 * m + 4.0,
        m - 2.0,
        h - m,
    );
    for (data, color, _) in series {
        let p: Vec<String> = data
            .iter()
            .filter(|(x, y)| x.is_finite() && y.is_finite())
            .map(|&(x, y)| format!("{:.1},{:.1}", sx(x), sy(y)))
            .collect();
        s.push_str(&format!(
            "<polyline fill=\"none\" stroke=\"{color}\" stroke-width=\"1.2\" points=\"{}\"/>",
            p.join(" ")
        ));
    }
    s.push_str("</svg>");
    s
}
