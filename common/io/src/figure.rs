//! Figures: the one place report.html (launch/src/report), finish.html
//! (nodes/finish/src/html.rs) and the PNG previews ([`crate::preview`]) take their drawing
//! helpers from, so the same quantity looks the same on every page.
//!
//! - Text: [`esc`] escapes `& < > " '` (safe in element text and in quoted attributes);
//!   [`fixed`] writes a number with a fixed number of decimals ("-0.0" as "0.0").
//! - Axes: [`ticks`] is the one "nice numbers" algorithm (steps of 1, 2 or 5 times a power of
//!   ten, at least `(hi - lo) / n`), [`labelled_ticks`] the ticks with their labels.
//! - Colour: [`viridis`] (matplotlib's 256-entry table, [`VIRIDIS`]) for heights, [`NAN_RGB`]
//!   for not-measured points, [`gradient_stops`] for an SVG colour bar of any colour map.
//! - Maps: [`encode_map_png`] (viridis) and [`encode_map_png_with`] (any colour map) write a
//!   height map as an indexed PNG, reduced by NaN-aware block means.
//! - Plots: [`Axis`] and [`Panel`] draw linear or log10 axes, grid, ticks, labels, polylines
//!   ([`path_d`]), areas and legend entries in SVG (the classes `tick`, `axis` and `grid` are
//!   the page's CSS).
//!
//! Orientation, for every map on every page: **row 0 at the top**, column 0 at the left, as
//! the instrument shows a measurement and as Python's `plot()` (matplotlib's `imshow`) draws
//! it. x grows to the right, y grows downwards from the top edge (y = row x pitch), and the
//! y axis is labelled so: 0 at the top. PNG rows are written top first, so a map's rows go in
//! as stored, never reversed.

use std::fmt::Write as _;

use anyhow::{bail, Context, Result};

// ---------------------------------------------------------------------------------------------
// Text

/// `s` escaped for HTML and SVG text and for attribute values in either quote.
pub fn esc(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

/// `v` with `decimals` decimals, "-" when not finite; "-0.000" shows as "0.000".
pub fn fixed(v: f64, decimals: usize) -> String {
    if !v.is_finite() {
        return "-".into();
    }
    let s = format!("{v:.decimals$}");
    if s.starts_with('-') && s[1..].chars().all(|c| c == '0' || c == '.') {
        s[1..].to_string()
    } else {
        s
    }
}

// ---------------------------------------------------------------------------------------------
// Axes

/// About `n` "nice" tick values (1, 2 or 5 times a power of ten) inside `lo..=hi`, and the
/// number of decimals their labels need. The one tick algorithm of every figure.
pub fn ticks(lo: f64, hi: f64, n: usize) -> (Vec<f64>, usize) {
    let raw = (hi - lo) / n.max(1) as f64;
    if !(raw > 0.0 && raw.is_finite()) {
        return (Vec::new(), 0);
    }
    let mag = 10f64.powf(raw.log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0]
        .iter()
        .map(|m| m * mag)
        .find(|s| *s >= raw * (1.0 - 1e-9))
        .unwrap_or(10.0 * mag);
    let decimals = (-(step.log10().floor())).clamp(0.0, 9.0) as usize;
    let first = (lo / step).ceil() as i64;
    let last = (hi / step).floor() as i64;
    ((first..=last).map(|i| i as f64 * step).collect(), decimals)
}

/// [`ticks`] with their labels, each with the decimals the step needs.
pub fn labelled_ticks(lo: f64, hi: f64, n: usize) -> Vec<(f64, String)> {
    let (values, decimals) = ticks(lo, hi, n);
    values
        .into_iter()
        .map(|v| (v, fixed(v, decimals)))
        .collect()
}

// ---------------------------------------------------------------------------------------------
// Colour

/// Colour of not-measured (non-finite) heights.
pub const NAN_RGB: [u8; 3] = [128, 128, 128];

/// Viridis colour of `t` in 0..1 (clamped; NaN gives the first colour).
pub fn viridis(t: f64) -> [u8; 3] {
    let i = if t.is_nan() {
        0.0
    } else {
        (t.clamp(0.0, 1.0) * 255.0).round()
    };
    VIRIDIS[i as usize]
}

/// A colour as CSS `rgb(r,g,b)`.
pub fn css_rgb([r, g, b]: [u8; 3]) -> String {
    format!("rgb({r},{g},{b})")
}

/// The 17 `<stop>`s (offsets 0, 1/16, .., 1) of an SVG `linearGradient` through `colour`, for
/// a colour bar.
pub fn gradient_stops(colour: impl Fn(f64) -> [u8; 3]) -> String {
    let mut s = String::new();
    for k in 0..=16 {
        let t = k as f64 / 16.0;
        let _ = write!(
            s,
            "<stop offset=\"{t:.4}\" stop-color=\"{}\"/>",
            css_rgb(colour(t))
        );
    }
    s
}

/// Viridis, 256 entries (matplotlib's colour map by Nathaniel J. Smith, Stefan van der Walt and
/// Eric Firing, released under CC0; rounded to 8 bits).
#[rustfmt::skip]
pub const VIRIDIS: [[u8; 3]; 256] = [
    [68, 1, 84], [68, 2, 86], [69, 4, 87], [69, 5, 89],
    [70, 7, 90], [70, 8, 92], [70, 10, 93], [70, 11, 94],
    [71, 13, 96], [71, 14, 97], [71, 16, 99], [71, 17, 100],
    [71, 19, 101], [72, 20, 103], [72, 22, 104], [72, 23, 105],
    [72, 24, 106], [72, 26, 108], [72, 27, 109], [72, 28, 110],
    [72, 29, 111], [72, 31, 112], [72, 32, 113], [72, 33, 115],
    [72, 35, 116], [72, 36, 117], [72, 37, 118], [72, 38, 119],
    [72, 40, 120], [72, 41, 121], [71, 42, 122], [71, 44, 122],
    [71, 45, 123], [71, 46, 124], [71, 47, 125], [70, 48, 126],
    [70, 50, 126], [70, 51, 127], [70, 52, 128], [69, 53, 129],
    [69, 55, 129], [69, 56, 130], [68, 57, 131], [68, 58, 131],
    [68, 59, 132], [67, 61, 132], [67, 62, 133], [66, 63, 133],
    [66, 64, 134], [66, 65, 134], [65, 66, 135], [65, 68, 135],
    [64, 69, 136], [64, 70, 136], [63, 71, 136], [63, 72, 137],
    [62, 73, 137], [62, 74, 137], [62, 76, 138], [61, 77, 138],
    [61, 78, 138], [60, 79, 138], [60, 80, 139], [59, 81, 139],
    [59, 82, 139], [58, 83, 139], [58, 84, 140], [57, 85, 140],
    [57, 86, 140], [56, 88, 140], [56, 89, 140], [55, 90, 140],
    [55, 91, 141], [54, 92, 141], [54, 93, 141], [53, 94, 141],
    [53, 95, 141], [52, 96, 141], [52, 97, 141], [51, 98, 141],
    [51, 99, 141], [50, 100, 142], [50, 101, 142], [49, 102, 142],
    [49, 103, 142], [49, 104, 142], [48, 105, 142], [48, 106, 142],
    [47, 107, 142], [47, 108, 142], [46, 109, 142], [46, 110, 142],
    [46, 111, 142], [45, 112, 142], [45, 113, 142], [44, 113, 142],
    [44, 114, 142], [44, 115, 142], [43, 116, 142], [43, 117, 142],
    [42, 118, 142], [42, 119, 142], [42, 120, 142], [41, 121, 142],
    [41, 122, 142], [41, 123, 142], [40, 124, 142], [40, 125, 142],
    [39, 126, 142], [39, 127, 142], [39, 128, 142], [38, 129, 142],
    [38, 130, 142], [38, 130, 142], [37, 131, 142], [37, 132, 142],
    [37, 133, 142], [36, 134, 142], [36, 135, 142], [35, 136, 142],
    [35, 137, 142], [35, 138, 141], [34, 139, 141], [34, 140, 141],
    [34, 141, 141], [33, 142, 141], [33, 143, 141], [33, 144, 141],
    [33, 145, 140], [32, 146, 140], [32, 146, 140], [32, 147, 140],
    [31, 148, 140], [31, 149, 139], [31, 150, 139], [31, 151, 139],
    [31, 152, 139], [31, 153, 138], [31, 154, 138], [30, 155, 138],
    [30, 156, 137], [30, 157, 137], [31, 158, 137], [31, 159, 136],
    [31, 160, 136], [31, 161, 136], [31, 161, 135], [31, 162, 135],
    [32, 163, 134], [32, 164, 134], [33, 165, 133], [33, 166, 133],
    [34, 167, 133], [34, 168, 132], [35, 169, 131], [36, 170, 131],
    [37, 171, 130], [37, 172, 130], [38, 173, 129], [39, 173, 129],
    [40, 174, 128], [41, 175, 127], [42, 176, 127], [44, 177, 126],
    [45, 178, 125], [46, 179, 124], [47, 180, 124], [49, 181, 123],
    [50, 182, 122], [52, 182, 121], [53, 183, 121], [55, 184, 120],
    [56, 185, 119], [58, 186, 118], [59, 187, 117], [61, 188, 116],
    [63, 188, 115], [64, 189, 114], [66, 190, 113], [68, 191, 112],
    [70, 192, 111], [72, 193, 110], [74, 193, 109], [76, 194, 108],
    [78, 195, 107], [80, 196, 106], [82, 197, 105], [84, 197, 104],
    [86, 198, 103], [88, 199, 101], [90, 200, 100], [92, 200, 99],
    [94, 201, 98], [96, 202, 96], [99, 203, 95], [101, 203, 94],
    [103, 204, 92], [105, 205, 91], [108, 205, 90], [110, 206, 88],
    [112, 207, 87], [115, 208, 86], [117, 208, 84], [119, 209, 83],
    [122, 209, 81], [124, 210, 80], [127, 211, 78], [129, 211, 77],
    [132, 212, 75], [134, 213, 73], [137, 213, 72], [139, 214, 70],
    [142, 214, 69], [144, 215, 67], [147, 215, 65], [149, 216, 64],
    [152, 216, 62], [155, 217, 60], [157, 217, 59], [160, 218, 57],
    [162, 218, 55], [165, 219, 54], [168, 219, 52], [170, 220, 50],
    [173, 220, 48], [176, 221, 47], [178, 221, 45], [181, 222, 43],
    [184, 222, 41], [186, 222, 40], [189, 223, 38], [192, 223, 37],
    [194, 223, 35], [197, 224, 33], [200, 224, 32], [202, 225, 31],
    [205, 225, 29], [208, 225, 28], [210, 226, 27], [213, 226, 26],
    [216, 226, 25], [218, 227, 25], [221, 227, 24], [223, 227, 24],
    [226, 228, 24], [229, 228, 25], [231, 228, 25], [234, 229, 26],
    [236, 229, 27], [239, 229, 28], [241, 229, 29], [244, 230, 30],
    [246, 230, 32], [248, 230, 33], [251, 231, 35], [253, 231, 37],
];

// ---------------------------------------------------------------------------------------------
// Maps

/// The map alone (no title, no colour bar), as [`encode_map_png`] returns it.
#[derive(Debug, Clone, PartialEq)]
pub struct MapPng {
    /// An 8-bit indexed PNG: palette entries 0..=254 are the colour map (viridis) from `range_um.0` to
    /// `range_um.1` (heights outside saturate), entry 255 is [`NAN_RGB`] (not measured).
    pub png: Vec<u8>,
    pub rows: usize,
    pub cols: usize,
    /// Each pixel is the NaN-aware mean of a `block x block` block of heights.
    pub block: usize,
}

/// The height map alone, reduced by NaN-aware block means until its longer side is at most
/// `max_side_px`, coloured over `range_um` (low, high), as an indexed PNG (a third of the
/// size of RGB, for pages that inline it). Row 0 at the top, as in
/// [`crate::preview::write_preview_png`].
pub fn encode_map_png(
    heights: &[f32],
    rows: usize,
    cols: usize,
    max_side_px: usize,
    range_um: (f64, f64),
) -> Result<MapPng> {
    encode_map_png_with(heights, rows, cols, max_side_px, range_um, viridis)
}

/// [`encode_map_png`] through any colour map: palette entry `i` (0..=254) is
/// `colour(i / 254)`, entry 255 is [`NAN_RGB`].
pub fn encode_map_png_with(
    heights: &[f32],
    rows: usize,
    cols: usize,
    max_side_px: usize,
    range_um: (f64, f64),
    colour: impl Fn(f64) -> [u8; 3],
) -> Result<MapPng> {
    if rows == 0 || cols == 0 || rows.checked_mul(cols) != Some(heights.len()) {
        bail!(
            "height map is {rows} x {cols} but has {} values",
            heights.len()
        );
    }
    let (lo, hi) = range_um;
    if !(lo.is_finite() && hi.is_finite() && lo < hi) {
        bail!("colour range {lo} .. {hi} um is not an increasing pair of finite numbers");
    }
    let block = rows.max(cols).div_ceil(max_side_px.max(1)).max(1);
    let (small, s_rows, s_cols) = if block > 1 {
        let (m, r, c) = block_mean(heights, rows, cols, block);
        (std::borrow::Cow::Owned(m), r, c)
    } else {
        (std::borrow::Cow::Borrowed(heights), rows, cols)
    };
    let index: Vec<u8> = small
        .iter()
        .map(|&v| {
            if v.is_finite() {
                ((v as f64 - lo) / (hi - lo) * 254.0)
                    .round()
                    .clamp(0.0, 254.0) as u8
            } else {
                255
            }
        })
        .collect();
    let mut palette = Vec::with_capacity(256 * 3);
    for i in 0..255 {
        palette.extend_from_slice(&colour(i as f64 / 254.0));
    }
    palette.extend_from_slice(&NAN_RGB);
    let mut png_bytes = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut png_bytes, s_cols as u32, s_rows as u32);
        enc.set_color(png::ColorType::Indexed);
        enc.set_depth(png::BitDepth::Eight);
        enc.set_palette(palette);
        let mut w = enc.write_header().context("PNG encoding failed")?;
        w.write_image_data(&index).context("PNG encoding failed")?;
        w.finish().context("PNG encoding failed")?;
    }
    Ok(MapPng {
        png: png_bytes,
        rows: s_rows,
        cols: s_cols,
        block,
    })
}

/// Means of `block x block` blocks of finite values (NaN where a block has none); edge blocks
/// average what they hold.
pub(crate) fn block_mean(
    heights: &[f32],
    rows: usize,
    cols: usize,
    block: usize,
) -> (Vec<f32>, usize, usize) {
    let out_rows = rows.div_ceil(block);
    let out_cols = cols.div_ceil(block);
    let mut out = Vec::with_capacity(out_rows * out_cols);
    let mut sum = vec![0.0f64; out_cols];
    let mut count = vec![0u32; out_cols];
    for br in 0..out_rows {
        sum.iter_mut().for_each(|s| *s = 0.0);
        count.iter_mut().for_each(|n| *n = 0);
        for r in br * block..((br + 1) * block).min(rows) {
            let row = &heights[r * cols..(r + 1) * cols];
            for (c, &v) in row.iter().enumerate() {
                if v.is_finite() {
                    sum[c / block] += v as f64;
                    count[c / block] += 1;
                }
            }
        }
        out.extend(sum.iter().zip(&count).map(|(&s, &n)| {
            if n > 0 {
                (s / n as f64) as f32
            } else {
                f32::NAN
            }
        }));
    }
    (out, out_rows, out_cols)
}
// ---------------------------------------------------------------------------------------------
// Plots

/// An SVG polyline's points attribute; `None` points break the line into segments, so the
/// result is one `d` of a path.
pub fn path_d(points: impl IntoIterator<Item = Option<(f64, f64)>>) -> String {
    let mut d = String::new();
    let mut pen_down = false;
    for p in points {
        match p {
            Some((x, y)) if x.is_finite() && y.is_finite() => {
                let _ = write!(d, "{}{x:.1},{y:.1}", if pen_down { "L" } else { "M" });
                pen_down = true;
            }
            _ => pen_down = false,
        }
    }
    d
}

/// A plot axis: its range, linear or log10, and its label.
#[derive(Debug, Clone)]
pub struct Axis {
    pub lo: f64,
    pub hi: f64,
    pub log: bool,
    pub label: String,
}

impl Axis {
    pub fn linear(lo: f64, hi: f64, label: &str) -> Self {
        let (lo, hi) = if hi > lo {
            (lo, hi)
        } else {
            (lo - 0.5, lo + 0.5)
        };
        Self {
            lo,
            hi,
            log: false,
            label: label.into(),
        }
    }

    /// A log10 axis spanning whole decades around `lo..hi` (both > 0).
    pub fn log(lo: f64, hi: f64, label: &str) -> Self {
        let lo = 10f64.powf(lo.max(1e-300).log10().floor());
        let hi = 10f64.powf(hi.max(lo * 10.0).log10().ceil());
        Self {
            lo,
            hi,
            log: true,
            label: label.into(),
        }
    }

    /// 0..1 along the axis.
    fn frac(&self, v: f64) -> f64 {
        if self.log {
            (v.log10() - self.lo.log10()) / (self.hi.log10() - self.lo.log10())
        } else {
            (v - self.lo) / (self.hi - self.lo)
        }
    }

    /// Tick values and their labels.
    fn ticks(&self, n: usize) -> Vec<(f64, String)> {
        if self.log {
            let (a, b) = (
                self.lo.log10().round() as i32,
                self.hi.log10().round() as i32,
            );
            let (a, b) = (a.min(b), a.max(b));
            let every = ((b - a) as usize).div_ceil(n.max(1)).max(1);
            // One style per axis: plain numbers when every tick reads well so, else powers.
            let plain = (-2..=3).contains(&a) && (-2..=3).contains(&b);
            (a..=b)
                .filter(|k| ((k - a) as usize).is_multiple_of(every))
                .map(|k| {
                    let label = if plain {
                        fixed(10f64.powi(k), (-k).max(0) as usize)
                    } else {
                        format!("10<tspan dy=\"-6\" font-size=\"9\">{k}</tspan>")
                    };
                    (10f64.powi(k), label)
                })
                .collect()
        } else {
            let (t, d) = ticks(self.lo, self.hi, n);
            t.into_iter().map(|v| (v, fixed(v, d))).collect()
        }
    }
}

/// A plotting area at (x, y) of size (w, h).
pub struct Panel {
    pub x: f64,
    pub y: f64,
    pub w: f64,
    pub h: f64,
    pub xa: Axis,
    pub ya: Axis,
}

impl Panel {
    pub fn px(&self, v: f64) -> f64 {
        self.x + self.xa.frac(v) * self.w
    }
    pub fn py(&self, v: f64) -> f64 {
        self.y + self.h - self.ya.frac(v) * self.h
    }

    /// Frame, grid, ticks and axis labels; `x_labels` false leaves the x tick labels and
    /// axis label out (a panel stacked above another).
    pub fn axes(&self, s: &mut String, x_labels: bool) {
        let _ = write!(
            s,
            "<rect x=\"{:.1}\" y=\"{:.1}\" width=\"{:.1}\" height=\"{:.1}\" fill=\"#fff\" \
             stroke=\"#444\"/>",
            self.x, self.y, self.w, self.h
        );
        for (v, label) in self.xa.ticks(8) {
            let x = self.px(v);
            let _ = write!(
                s,
                "<line x1=\"{x:.1}\" y1=\"{:.1}\" x2=\"{x:.1}\" y2=\"{:.1}\" class=\"grid\"/>",
                self.y,
                self.y + self.h
            );
            if x_labels {
                let _ = write!(
                    s,
                    "<text x=\"{x:.1}\" y=\"{:.1}\" class=\"tick\" text-anchor=\"middle\">{label}</text>",
                    self.y + self.h + 16.0
                );
            }
        }
        for (v, label) in self.ya.ticks(6) {
            let y = self.py(v);
            let _ = write!(
                s,
                "<line x1=\"{:.1}\" y1=\"{y:.1}\" x2=\"{:.1}\" y2=\"{y:.1}\" class=\"grid\"/>\
                 <text x=\"{:.1}\" y=\"{:.1}\" class=\"tick\" text-anchor=\"end\">{label}</text>",
                self.x,
                self.x + self.w,
                self.x - 6.0,
                y + 4.0
            );
        }
        if x_labels {
            let _ = write!(
                s,
                "<text x=\"{:.1}\" y=\"{:.1}\" class=\"axis\" text-anchor=\"middle\">{}</text>",
                self.x + self.w / 2.0,
                self.y + self.h + 36.0,
                esc(&self.xa.label)
            );
        }
        let _ = write!(
            s,
            "<text transform=\"translate({:.1} {:.1}) rotate(-90)\" class=\"axis\" \
             text-anchor=\"middle\">{}</text>",
            self.x - 52.0,
            self.y + self.h / 2.0,
            esc(&self.ya.label)
        );
    }

    /// A polyline through the points inside the axes' ranges (others break the line).
    pub fn line(&self, s: &mut String, points: &[(f64, f64)], colour: &str, width: f64) {
        self.line_styled(s, points, colour, width, None);
    }

    /// [`Panel::line`], dashed when `dash` is an SVG `stroke-dasharray` ("6 4").
    pub fn line_styled(
        &self,
        s: &mut String,
        points: &[(f64, f64)],
        colour: &str,
        width: f64,
        dash: Option<&str>,
    ) {
        let d = self.path(points);
        let dash = dash.map_or(String::new(), |d| {
            format!(" stroke-dasharray=\"{}\"", esc(d))
        });
        let _ = write!(
            s,
            "<path d=\"{d}\" fill=\"none\" stroke=\"{colour}\" stroke-width=\"{width}\" \
             stroke-linejoin=\"round\"{dash}/>"
        );
    }

    /// The area between the points and y = 0 (or the nearer end of the y range), filled with
    /// `colour` at `opacity`; points outside the ranges are left out.
    pub fn area(&self, s: &mut String, points: &[(f64, f64)], colour: &str, opacity: f64) {
        let inside: Vec<(f64, f64)> = points
            .iter()
            .copied()
            .filter(|&(x, y)| self.inside(x, &self.xa) && self.inside(y, &self.ya))
            .collect();
        let (Some(first), Some(last)) = (inside.first(), inside.last()) else {
            return;
        };
        let base = self.py(0.0_f64.clamp(self.ya.lo, self.ya.hi));
        let mut d = format!("M{:.1},{base:.1}", self.px(first.0));
        for &(x, y) in &inside {
            let _ = write!(d, "L{:.1},{:.1}", self.px(x), self.py(y));
        }
        let _ = write!(d, "L{:.1},{base:.1}Z", self.px(last.0));
        let _ = write!(
            s,
            "<path d=\"{d}\" fill=\"{colour}\" fill-opacity=\"{opacity}\" stroke=\"none\"/>"
        );
    }

    /// A horizontal line at y = 0 when 0 lies inside the y range.
    pub fn zero_line(&self, s: &mut String) {
        if !self.ya.log && self.ya.lo < 0.0 && self.ya.hi > 0.0 {
            let y = self.py(0.0);
            let _ = write!(
                s,
                "<line x1=\"{:.1}\" y1=\"{y:.1}\" x2=\"{:.1}\" y2=\"{y:.1}\" stroke=\"#888\"/>",
                self.x,
                self.x + self.w
            );
        }
    }

    fn inside(&self, v: f64, a: &Axis) -> bool {
        v.is_finite() && v >= a.lo && v <= a.hi && (!a.log || v > 0.0)
    }

    /// The path through the points inside the ranges.
    fn path(&self, points: &[(f64, f64)]) -> String {
        path_d(points.iter().map(|&(x, y)| {
            (self.inside(x, &self.xa) && self.inside(y, &self.ya)).then(|| (self.px(x), self.py(y)))
        }))
    }

    /// A legend entry (colour swatch and text) at row `k` in the panel's top right corner.
    pub fn legend(&self, s: &mut String, k: usize, colour: &str, text: &str) {
        self.legend_styled(s, k, colour, text, None, 240.0);
    }

    /// [`Panel::legend`] with a dashed swatch when `dash` is given, in a box `width` wide (its
    /// right edge on the panel's).
    pub fn legend_styled(
        &self,
        s: &mut String,
        k: usize,
        colour: &str,
        text: &str,
        dash: Option<&str>,
        width: f64,
    ) {
        let x = self.x + self.w - width;
        let y = self.y + 10.0 + 18.0 * k as f64;
        let dash = dash.map_or(String::new(), |d| {
            format!(" stroke-dasharray=\"{}\"", esc(d))
        });
        let _ = write!(
            s,
            "<rect x=\"{:.1}\" y=\"{:.1}\" width=\"{width}\" height=\"18\" fill=\"#fff\" \
             fill-opacity=\"0.85\"/><line x1=\"{:.1}\" y1=\"{:.1}\" x2=\"{:.1}\" y2=\"{:.1}\" \
             stroke=\"{colour}\" stroke-width=\"3\"{dash}/><text x=\"{:.1}\" y=\"{:.1}\" \
             class=\"tick\">{}</text>",
            x - 6.0,
            y - 4.0,
            x,
            y + 5.0,
            x + 22.0,
            y + 5.0,
            x + 28.0,
            y + 9.0,
            esc(text)
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn escaping_covers_both_quotes() {
        assert_eq!(
            esc(r#"a&b <i> "x" 'y'"#),
            "a&amp;b &lt;i&gt; &quot;x&quot; &#39;y&#39;"
        );
        // Safe inside either quote: no raw quote survives.
        let attr = format!("<a title=\"{}\">", esc("scan \"3\".x3p"));
        assert_eq!(attr.matches('"').count(), 2, "{attr}");
    }

    #[test]
    fn fixed_and_labelled_ticks() {
        assert_eq!(fixed(-0.0001, 2), "0.00");
        assert_eq!(fixed(f64::NAN, 2), "-");
        let t = labelled_ticks(-0.37, 1.23, 8);
        let labels: Vec<&str> = t.iter().map(|x| x.1.as_str()).collect();
        assert_eq!(
            labels,
            ["-0.2", "0.0", "0.2", "0.4", "0.6", "0.8", "1.0", "1.2"]
        );
        // Steps of 1, 2 or 5: 0..20 in about 5 ticks is 0, 5, .., 20.
        let t = labelled_ticks(0.0, 20.0, 5);
        assert_eq!(
            t.iter().map(|x| x.1.as_str()).collect::<Vec<_>>(),
            ["0", "5", "10", "15", "20"]
        );
        assert!(ticks(1.0, 1.0, 5).0.is_empty());
        assert!(ticks(f64::NAN, 1.0, 5).0.is_empty());
    }

    #[test]
    fn the_colour_map_is_viridis_and_the_gradient_follows_it() {
        assert_eq!(viridis(0.0), [68, 1, 84]);
        assert_eq!(viridis(1.0), [253, 231, 37]);
        assert_eq!(viridis(0.5), VIRIDIS[128]);
        assert_eq!(viridis(f64::NAN), VIRIDIS[0]);
        let g = gradient_stops(viridis);
        assert_eq!(g.matches("<stop ").count(), 17);
        assert!(g.starts_with("<stop offset=\"0.0000\" stop-color=\"rgb(68,1,84)\"/>"));
        assert!(g.ends_with("<stop offset=\"1.0000\" stop-color=\"rgb(253,231,37)\"/>"));
    }

    #[test]
    fn a_map_png_of_any_colour_map_keeps_the_not_measured_entry() {
        let h = [0.0f32, 1.0, f32::NAN, 0.5];
        let m = encode_map_png_with(&h, 2, 2, 10, (0.0, 1.0), |t| [(t * 254.0) as u8, 0, 0])
            .expect("encode");
        let dec = png::Decoder::new(std::io::Cursor::new(&m.png));
        let reader = dec.read_info().expect("png header");
        let palette = reader.info().palette.clone().expect("palette").to_vec();
        assert_eq!(&palette[255 * 3..], &NAN_RGB);
        assert_eq!(&palette[254 * 3..255 * 3], &[254, 0, 0]);
    }

    #[test]
    fn panel_lines_break_outside_the_ranges_and_areas_close_on_zero() {
        assert_eq!(
            path_d([Some((0.0, 1.0)), Some((2.0, 3.0)), None, Some((4.0, 5.0))]),
            "M0.0,1.0L2.0,3.0M4.0,5.0"
        );
        let p = Panel {
            x: 0.0,
            y: 0.0,
            w: 100.0,
            h: 100.0,
            xa: Axis::linear(0.0, 10.0, "x"),
            ya: Axis::linear(-1.0, 1.0, "y <m>"),
        };
        let mut s = String::new();
        p.line(&mut s, &[(0.0, 0.0), (5.0, 2.0), (10.0, 1.0)], "#111", 2.0);
        assert_eq!(
            s,
            "<path d=\"M0.0,50.0M100.0,0.0\" fill=\"none\" stroke=\"#111\" stroke-width=\"2\" \
             stroke-linejoin=\"round\"/>"
        );
        let mut s = String::new();
        p.line_styled(&mut s, &[(0.0, 0.0), (10.0, 1.0)], "#111", 1.5, Some("6 4"));
        assert!(s.ends_with("stroke-dasharray=\"6 4\"/>"), "{s}");
        let mut s = String::new();
        p.area(&mut s, &[(0.0, 0.5), (10.0, 0.5)], "#222", 0.3);
        assert!(
            s.contains("d=\"M0.0,50.0L0.0,25.0L100.0,25.0L100.0,50.0Z\""),
            "{s}"
        );
        let mut s = String::new();
        p.axes(&mut s, true);
        assert!(s.contains(">y &lt;m&gt;</text>"), "labels are escaped: {s}");
        let mut s = String::new();
        p.zero_line(&mut s);
        assert!(s.contains("y1=\"50.0\""), "{s}");
    }
}
