//! The height maps as figures: the map itself (an indexed PNG from
//! [`surfstream_io::preview::encode_map_png`]) inside an SVG that draws what a reader needs to
//! read it: x and y axes in mm or um from the map's top-left corner (row 0 at the top, y
//! down: the one orientation of [`surfstream_io::figure`]), a scale bar, the colour
//! bar with its unit and its clipping (the 0.5 / 99.5 percentiles of the map's valid heights,
//! how many points saturate), the grey of "not measured" and how many points it covers. A
//! click on the map opens it at full size (the page's script).

use std::fmt::Write as _;

use surfstream_io::figure::{
    css_rgb, encode_map_png, esc, fixed, gradient_stops, ticks, viridis, NAN_RGB,
};
use surfstream_io::preview::{robust_range_um, ROBUST_HIGH_PERCENT, ROBUST_LOW_PERCENT};

use super::html::{base64, length, pitch, round_length, um};
use super::surfaces::Surface;

/// Longest side of an inlined map, px: near the figure's drawn width (860 CSS px), so the
/// page stays small (the demo's report: 11 MB with 2048 px maps inline).
const INLINE_SIDE_PX: usize = 800;
/// Longest side of the larger map a click opens (`report_maps/NAME.png` beside the page):
/// sized for a screen (issue 35: a 20 x 20 scan's maps at 2048 px were 30 MB); a larger map is
/// drawn from block means, its every height stays in `NAME.npy`.
const MAX_SIDE_PX: usize = 1600;
/// Folder, beside report.html, of the full-size maps.
pub const ZOOM_DIR: &str = "report_maps";
/// Width of the map inside the figure (SVG user units = CSS px at full width).
const MAP_W: f64 = 860.0;
/// Tallest map inside the figure.
const MAP_H_MAX: f64 = 640.0;
const LEFT: f64 = 64.0;
const TOP: f64 = 12.0;

/// A horizontal line to draw over the map (the profile cut), at row `row`.
pub struct Cut {
    pub row: usize,
    pub label: String,
}

/// One figure: `<figure>` with the SVG and a caption. `reference` says what the heights are
/// relative to.
pub fn figure(
    s: &Surface,
    title: &str,
    reference: &str,
    cut: Option<&Cut>,
    out: Option<&std::path::Path>,
) -> String {
    // Row 0 at the top (surfstream_io::figure): the rows go in as stored.
    let values: Vec<f32> = s.to_f32();
    let Some((lo, hi)) = robust_range_um(&values) else {
        return format!(
            "<figure class=\"map\"><figcaption><b>{}</b>: no measured point</figcaption></figure>",
            esc(title)
        );
    };
    // The full-size map, when the inline one is reduced: a file beside the page that a click
    // opens (the inline map when the file is missing, e.g. the page copied alone).
    let full = out
        .filter(|_| s.rows.max(s.cols) > INLINE_SIDE_PX)
        .and_then(|dir| {
            let m = encode_map_png(&values, s.rows, s.cols, MAX_SIDE_PX, (lo, hi)).ok()?;
            let block = m.block * s.block;
            let rel = format!("{ZOOM_DIR}/{}.png", s.name);
            let path = dir.join(&rel);
            surfstream_core::fsutil::write_atomic(&path, |w| {
                use std::io::Write as _;
                w.write_all(&m.png)?;
                Ok(())
            })
            .ok()?;
            Some((rel, m.rows, m.cols, block))
        });
    let map = match encode_map_png(&values, s.rows, s.cols, INLINE_SIDE_PX, (lo, hi)) {
        Ok(m) => m,
        Err(e) => {
            return format!(
                "<figure class=\"map\"><figcaption><b>{}</b>: {}</figcaption></figure>",
                esc(title),
                esc(&format!("{e:#}"))
            )
        }
    };
    let (n_valid, below, above) =
        values
            .iter()
            .filter(|v| v.is_finite())
            .fold((0usize, 0usize, 0usize), |(n, b, a), &v| {
                let v = v as f64;
                (n + 1, b + usize::from(v < lo), a + usize::from(v > hi))
            });
    let n_nan = values.len() - n_valid;
    let pct = |k: usize| 100.0 * k as f64 / values.len().max(1) as f64;

    let at = MapLayout::of(s);
    let id = s.name;
    let mut g = String::new();
    let _ = write!(
        g,
        "<svg class=\"mapsvg\" viewBox=\"0 0 {:.0} {:.0}\" role=\"img\" \
         aria-label=\"{t}\"><defs><linearGradient id=\"cb-{id}\" x1=\"0\" y1=\"1\" x2=\"0\" y2=\"0\">",
        at.width,
        at.height,
        t = esc(title)
    );
    g.push_str(&gradient_stops(viridis));
    let (mw, mh) = (at.mw, at.mh);
    let _ = write!(
        g,
        "</linearGradient></defs><image class=\"zoomable\" x=\"{LEFT}\" y=\"{TOP}\" \
         width=\"{mw:.1}\" height=\"{mh:.1}\" preserveAspectRatio=\"none\" \
         style=\"image-rendering:pixelated\" data-title=\"{t}\"{full_attr} \
         href=\"data:image/png;base64,{}\"><title>click to enlarge ({} x {} px, rows x cols)</title></image>\
         <rect x=\"{LEFT}\" y=\"{TOP}\" width=\"{mw:.1}\" height=\"{mh:.1}\" fill=\"none\" \
         stroke=\"#333\" stroke-width=\"1\"/>",
        base64(&map.png),
        full.as_ref().map_or(map.rows, |f| f.1),
        full.as_ref().map_or(map.cols, |f| f.2),
        t = esc(title),
        full_attr = full
            .as_ref()
            .map_or(String::new(), |f| format!(" data-full=\"{}\"", esc(&f.0)))
    );
    at.axes(&mut g);
    at.scale_bar(&mut g);
    if let Some(cut) = cut {
        at.cut_line(&mut g, cut, s.rows);
    }
    at.colour_bar(&mut g, id, (lo, hi));

    let (w_um, h_um) = (at.w_um, at.h_um);
    let caption = format!(
        "<b>{}</b>: {} x {} px (rows x cols), {} x {} at {} pitch, row 0 at the top (y down from the top edge); heights {}. \
         Colour scale clipped to the {ROBUST_LOW_PERCENT} / {ROBUST_HIGH_PERCENT} percentiles \
         of the measured heights, {} .. {}: {}&nbsp;% of the points lie below and {}&nbsp;% above \
         and take the end colours. Grey: not measured ({} points, {}&nbsp;%). {}\
         {}",
        esc(title),
        s.file_shape.0,
        s.file_shape.1,
        length(h_um),
        length(w_um),
        pitch(s.pitch_x_um / s.block as f64),
        esc(reference),
        um(lo),
        um(hi),
        fixed(pct(below), 2),
        fixed(pct(above), 2),
        n_nan,
        fixed(pct(n_nan), 2),
        if map.block * s.block > 1 {
            format!(
                "Drawn at {} x {} px, each the mean of {} x {} heights{}. ",
                map.rows,
                map.cols,
                map.block * s.block,
                map.block * s.block,
                if s.block > 1 {
                    " (the percentiles, saturation and not-measured counts are of these means)"
                } else {
                    ""
                }
            )
        } else {
            String::new()
        },
        match &full {
            Some((rel, r, c, 1)) => format!(
                "Click the map for full size: {r} x {c} px, the file {} beside this page.",
                esc(rel)
            ),
            Some((rel, r, c, k)) => format!(
                "Click the map for a larger view: {r} x {c} px, each the mean of {k} x {k} \
                 heights, the file {} beside this page (every height: {}.npy).",
                esc(rel),
                esc(s.name)
            ),
            None => "Click the map for full size.".into(),
        }
    );
    format!("<figure class=\"map\" id=\"map-{id}\">{g}<figcaption>{caption}</figcaption></figure>")
}

/// Where a map figure's parts go (SVG user units): the map keeps its aspect ratio in um, the
/// colour bar stands to its right, lengths are in mm from 2 mm up.
struct MapLayout {
    w_um: f64,
    h_um: f64,
    /// The map's drawn width and height.
    mw: f64,
    mh: f64,
    bar_x: f64,
    bar_w: f64,
    bar_top: f64,
    bar_h: f64,
    width: f64,
    height: f64,
    unit: &'static str,
    /// um per axis unit.
    div: f64,
}

impl MapLayout {
    fn of(s: &Surface) -> Self {
        let (w_um, h_um) = (s.width_um(), s.height_um());
        let mut mw = MAP_W;
        let mut mh = mw * h_um / w_um;
        if mh > MAP_H_MAX {
            mh = MAP_H_MAX;
            mw = mh * w_um / h_um;
        }
        let bar_x = LEFT + mw + 28.0;
        let bar_w = 22.0;
        let bar_top = TOP + 24.0;
        let bar_h = (mh - 24.0).max(160.0);
        let to_mm = w_um.max(h_um) >= 2000.0;
        let (unit, div) = if to_mm { ("mm", 1000.0) } else { ("µm", 1.0) };
        Self {
            w_um,
            h_um,
            mw,
            mh,
            bar_x,
            bar_w,
            bar_top,
            bar_h,
            width: bar_x + bar_w + 78.0,
            height: TOP + mh.max(bar_h + 24.0) + 58.0,
            unit,
            div,
        }
    }

    /// x along the bottom, y down the left, from the top-left corner (row 0 at the top).
    fn axes(&self, g: &mut String) {
        let (mw, mh, w_um, h_um) = (self.mw, self.mh, self.w_um, self.h_um);
        let (unit, div) = (self.unit, self.div);
        let (xt, xd) = ticks(0.0, w_um / div, 8);
        for v in &xt {
            let x = LEFT + v * div / w_um * mw;
            let _ = write!(
                g,
                "<line x1=\"{x:.1}\" y1=\"{y0:.1}\" x2=\"{x:.1}\" y2=\"{y1:.1}\" stroke=\"#333\"/>\
                 <text x=\"{x:.1}\" y=\"{ty:.1}\" class=\"tick\" text-anchor=\"middle\">{}</text>",
                fixed(*v, xd),
                y0 = TOP + mh,
                y1 = TOP + mh + 5.0,
                ty = TOP + mh + 18.0
            );
        }
        let _ = write!(
            g,
            "<text x=\"{:.1}\" y=\"{:.1}\" class=\"axis\" text-anchor=\"middle\">x ({unit})</text>",
            LEFT + mw / 2.0,
            TOP + mh + 36.0
        );
        let (yt, yd) = ticks(0.0, h_um / div, 8);
        for v in &yt {
            let y = TOP + v * div / h_um * mh;
            let _ = write!(
                g,
                "<line x1=\"{x0:.1}\" y1=\"{y:.1}\" x2=\"{LEFT}\" y2=\"{y:.1}\" stroke=\"#333\"/>\
                 <text x=\"{tx:.1}\" y=\"{ty:.1}\" class=\"tick\" text-anchor=\"end\">{}</text>",
                fixed(*v, yd),
                x0 = LEFT - 5.0,
                tx = LEFT - 8.0,
                ty = y + 4.0
            );
        }
        let _ = write!(
            g,
            "<text transform=\"translate(16 {:.1}) rotate(-90)\" class=\"axis\" \
             text-anchor=\"middle\">y ({unit})</text>",
            TOP + mh / 2.0
        );
    }

    /// A round length of about a fifth of the width, bottom right inside the map.
    fn scale_bar(&self, g: &mut String) {
        let (mw, mh, w_um) = (self.mw, self.mh, self.w_um);
        let target = w_um / 5.0;
        let mag = 10f64.powf(target.log10().floor());
        let bar_um = [5.0, 2.0, 1.0]
            .iter()
            .map(|m| m * mag)
            .find(|l| *l <= target)
            .unwrap_or(mag);
        let sb_w = bar_um / w_um * mw;
        let (sb_x, sb_y) = (LEFT + mw - sb_w - 14.0, TOP + mh - 16.0);
        let _ = write!(
            g,
            "<rect x=\"{:.1}\" y=\"{:.1}\" width=\"{:.1}\" height=\"30\" fill=\"#fff\" \
             fill-opacity=\"0.8\" rx=\"3\"/><rect x=\"{sb_x:.1}\" y=\"{sb_y:.1}\" width=\"{sb_w:.1}\" \
             height=\"5\" fill=\"#111\"/><text x=\"{:.1}\" y=\"{:.1}\" class=\"tick\" \
             text-anchor=\"middle\">{}</text>",
            sb_x - 8.0,
            sb_y - 18.0,
            sb_w + 16.0,
            sb_x + sb_w / 2.0,
            sb_y - 4.0,
            round_length(bar_um)
        );
    }

    /// The profile cut: a dashed line across the map at its row, labelled.
    fn cut_line(&self, g: &mut String, cut: &Cut, rows: usize) {
        let (mw, mh) = (self.mw, self.mh);
        let y = TOP + (cut.row as f64 + 0.5) / rows as f64 * mh;
        let _ = write!(
            g,
            "<line x1=\"{LEFT}\" y1=\"{y:.1}\" x2=\"{:.1}\" y2=\"{y:.1}\" stroke=\"#fff\" \
             stroke-width=\"2\" stroke-dasharray=\"8,5\"/><rect x=\"{:.1}\" y=\"{:.1}\" \
             width=\"{:.1}\" height=\"18\" fill=\"#fff\" fill-opacity=\"0.85\" rx=\"3\"/>\
             <text x=\"{:.1}\" y=\"{:.1}\" class=\"tick\">{}</text>",
            LEFT + mw,
            LEFT + 6.0,
            y - 22.0,
            7.0 * cut.label.len() as f64 + 10.0,
            LEFT + 11.0,
            y - 9.0,
            esc(&cut.label)
        );
    }

    /// Unit on top, ticks on the right, "not measured" swatch below; closes the SVG.
    fn colour_bar(&self, g: &mut String, id: &str, (lo, hi): (f64, f64)) {
        let (bar_x, bar_w, bar_top, bar_h) = (self.bar_x, self.bar_w, self.bar_top, self.bar_h);
        let _ = write!(
            g,
            "<text x=\"{:.1}\" y=\"{:.1}\" class=\"axis\" text-anchor=\"middle\">z (µm)</text>\
             <rect x=\"{bar_x:.1}\" y=\"{bar_top:.1}\" width=\"{bar_w}\" height=\"{bar_h:.1}\" \
             fill=\"url(#cb-{id})\" stroke=\"#333\"/>",
            bar_x + bar_w / 2.0,
            TOP + 12.0
        );
        let (zt, zd) = ticks(lo, hi, 8);
        for v in &zt {
            let y = bar_top + bar_h - (v - lo) / (hi - lo) * bar_h;
            let _ = write!(
                g,
                "<line x1=\"{x0:.1}\" y1=\"{y:.1}\" x2=\"{x1:.1}\" y2=\"{y:.1}\" stroke=\"#333\"/>\
                 <text x=\"{tx:.1}\" y=\"{ty:.1}\" class=\"tick\">{}</text>",
                fixed(*v, zd),
                x0 = bar_x + bar_w,
                x1 = bar_x + bar_w + 5.0,
                tx = bar_x + bar_w + 8.0,
                ty = y + 4.0
            );
        }
        let sw_y = bar_top + bar_h + 14.0;
        let _ = write!(
            g,
            "<rect x=\"{bar_x:.1}\" y=\"{sw_y:.1}\" width=\"{bar_w}\" height=\"14\" \
             fill=\"{}\" stroke=\"#333\"/><text x=\"{:.1}\" y=\"{:.1}\" \
             class=\"tick\">not</text><text x=\"{:.1}\" y=\"{:.1}\" class=\"tick\">measured</text></svg>",
            css_rgb(NAN_RGB),
            bar_x + bar_w + 6.0,
            sw_y + 6.0,
            bar_x + bar_w + 6.0,
            sw_y + 19.0,
        );
    }
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;

    /// The inline PNGs of a page or figure, decoded: (palette, indices, width).
    pub(in super::super) fn inline_pngs(html: &str) -> Vec<(Vec<u8>, Vec<u8>, u32)> {
        use base64::Engine as _;
        html.match_indices("data:image/png;base64,")
            .map(|(k, m)| {
                let rest = &html[k + m.len()..];
                let bytes = base64::engine::general_purpose::STANDARD
                    .decode(&rest[..rest.find('"').unwrap()])
                    .unwrap();
                let mut reader = png::Decoder::new(std::io::Cursor::new(bytes))
                    .read_info()
                    .unwrap();
                let palette = reader.info().palette.clone().unwrap().to_vec();
                let mut buf = vec![0; reader.output_buffer_size()];
                let info = reader.next_frame(&mut buf).unwrap();
                buf.truncate(info.buffer_size());
                (palette, buf, info.width)
            })
            .collect()
    }

    /// Issue 39: row 0 at the top, as the instrument and Python's plot() show it, the y axis
    /// reading 0 at the top edge; the profile cut drawn at its row from the top.
    #[test]
    fn maps_draw_row_0_at_the_top() {
        let (rows, cols) = (4, 4);
        // Row 0 high, the others low.
        let z: Vec<f64> = (0..rows * cols)
            .map(|i| if i < cols { 1.0 } else { 0.0 })
            .collect();
        let s = Surface {
            name: "panorama",
            z,
            rows,
            cols,
            pitch_x_um: 1.0,
            pitch_y_um: 1.0,
            block: 1,
            file_shape: (rows, cols),
        };
        let cut = Cut {
            row: 0,
            label: "cut".into(),
        };
        let f = figure(&s, "t", "mean", Some(&cut), None);
        let pngs = inline_pngs(&f);
        let (_, index, w) = &pngs[0];
        assert_eq!(*w, 4);
        assert_eq!(&index[..4], &[254; 4], "row 0 (high) in the top image row");
        assert_eq!(&index[12..], &[0; 4], "the last row (low) at the bottom");
        // The y axis: 0 at the top edge of the map (y = TOP).
        assert!(
            f.contains(&format!(
                "x2=\"{LEFT}\" y2=\"{TOP:.1}\" stroke=\"#333\"/><text x=\"{:.1}\" y=\"{:.1}\" \
                 class=\"tick\" text-anchor=\"end\">0.0</text>",
                LEFT - 8.0,
                TOP + 4.0
            )),
            "{f}"
        );
        // The cut on row 0 lies in the top quarter of the map.
        let at = MapLayout::of(&s);
        let y = TOP + 0.5 / rows as f64 * at.mh;
        assert!(f.contains(&format!(
            "y1=\"{y:.1}\" x2=\"{:.1}\" y2=\"{y:.1}\" stroke=\"#fff\"",
            LEFT + at.mw
        )));
        assert!(f.contains("row 0 at the top"));
    }

    /// Issue 35: the map a click opens is sized for a screen, at most 1600 px on its long
    /// side, from block means of the map (a map up to 1600 px stays at full size).
    #[test]
    fn the_larger_map_is_at_most_1600_px() {
        let d = tempfile::tempdir().unwrap();
        for (rows, cols, want, block) in
            [(1500, 1700, (750, 850), 2), (1000, 1600, (1000, 1600), 1)]
        {
            let z: Vec<f64> = (0..rows * cols).map(|i| (i % 977) as f64 * 1e-3).collect();
            let s = Surface {
                name: "panorama",
                z,
                rows,
                cols,
                pitch_x_um: 1.0,
                pitch_y_um: 1.0,
                block: 1,
                file_shape: (rows, cols),
            };
            let f = figure(&s, "t", "mean", None, Some(d.path()));
            let png = std::fs::read(d.path().join("report_maps/panorama.png")).unwrap();
            let reader = png::Decoder::new(std::io::Cursor::new(png))
                .read_info()
                .unwrap();
            let info = reader.info();
            assert_eq!((info.height as usize, info.width as usize), want);
            if block > 1 {
                assert!(f.contains("each the mean of 2 x 2 heights"), "{f}");
                assert!(f.contains("(every height: panorama.npy)"));
            } else {
                assert!(f.contains("Click the map for full size: 1000 x 1600 px"));
            }
        }
    }
}
