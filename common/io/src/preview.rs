//! PNG previews of height maps with a colour scale.
//!
//! [`write_preview_png`] draws a row-major height map (micrometres, NaN = not measured) as an RGB
//! PNG: row 0 at the top, column 0 at the left (scan y grows downwards, x to the right), heights
//! coloured with the viridis colour map, not-measured pixels in a neutral grey
//! ([`NAN_RGB`]), a vertical colour bar on the right labelled in micrometres, an optional
//! title at the top and, under the map, a legend: the grey of "not measured" and how the
//! colour range was chosen (the clipping percentiles, or "fixed"). Text uses a small built-in 5 x 7 bitmap font, so previews need no system
//! fonts.
//!
//! - Colour range: given explicitly ([`PreviewOptions::range_um`]) or, by default, robust
//!   percentiles of the valid (finite) heights: the [`ROBUST_LOW_PERCENT`] = 0.5 % and
//!   [`ROBUST_HIGH_PERCENT`] = 99.5 % points (linear interpolation between order statistics),
//!   so a few spikes or dropout artefacts do not wash out the picture. Heights outside the range
//!   saturate to the end colours. For maps with more than [`PERCENTILE_SAMPLE_LIMIT`] values the
//!   percentiles are taken over an evenly strided subsample of that size. A map without valid
//!   heights gets the range 0..1 um; a flat map gets its value +- 0.5 um.
//! - Size: a map whose longer side exceeds [`PreviewOptions::max_side_px`] (default 1024) is
//!   reduced by block averaging (an integer factor; NaN-aware: a block is the mean of its valid
//!   heights and NaN only if it has none). A map whose longer side is below
//!   [`PreviewOptions::min_side_px`] (default 256) is enlarged by an integer factor (nearest
//!   neighbour), so tiny maps stay visible.
//! - The file is written atomically ([`surfstream_core::fsutil::write_atomic`]).
//!
//! The colour map, the not-measured grey, the ticks and the map PNG are [`crate::figure`]'s
//! (one colour map and one orientation for every figure), re-exported here.

use std::io::Write;
use std::path::Path;

use anyhow::{bail, Context, Result};

use crate::figure::block_mean;
// The figure helpers previews draw with, under the names callers know them by.
pub use crate::figure::{encode_map_png, ticks, viridis, MapPng, NAN_RGB, VIRIDIS};

/// Lower robust percentile of the default colour range, in percent.
pub const ROBUST_LOW_PERCENT: f64 = 0.5;
/// Upper robust percentile of the default colour range, in percent.
pub const ROBUST_HIGH_PERCENT: f64 = 99.5;
/// At most this many heights are sorted for the percentiles (a strided subsample beyond).
pub const PERCENTILE_SAMPLE_LIMIT: usize = 1 << 22;

const BACKGROUND_RGB: [u8; 3] = [255, 255, 255];
const TEXT_RGB: [u8; 3] = [0, 0, 0];
const FRAME_RGB: [u8; 3] = [64, 64, 64];
/// Margin around everything, px.
const MARGIN_PX: usize = 8;
/// Width of the colour bar, px.
const BAR_WIDTH_PX: usize = 16;
/// Length of a tick mark, px.
const TICK_PX: usize = 4;

/// How to draw a preview.
#[derive(Debug, Clone, PartialEq)]
pub struct PreviewOptions {
    /// The longer side of the map area is at most this many pixels (larger maps are block
    /// averaged). Default 1024.
    pub max_side_px: usize,
    /// Maps whose longer side is shorter than this are enlarged by an integer factor. Default 256;
    /// 0 or 1 disables enlarging.
    pub min_side_px: usize,
    /// Colour range (low, high) in micrometres; `None` = robust percentiles of the data.
    pub range_um: Option<(f64, f64)>,
    /// Text drawn above the map (printable ASCII; other characters show as '?').
    pub title: Option<String>,
    /// Draw the colour bar with its labels. Default true.
    pub colour_bar: bool,
}

impl Default for PreviewOptions {
    fn default() -> Self {
        Self {
            max_side_px: 1024,
            min_side_px: 256,
            range_um: None,
            title: None,
            colour_bar: true,
        }
    }
}

/// What was drawn.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PreviewInfo {
    /// Height drawn in the first viridis colour (dark purple), um.
    pub min_um: f64,
    /// Height drawn in the last viridis colour (yellow), um.
    pub max_um: f64,
    /// Size of the whole image.
    pub width_px: u32,
    pub height_px: u32,
    /// Where the map sits in the image (its top-left pixel) and its size in pixels.
    pub map_left_px: u32,
    pub map_top_px: u32,
    pub map_width_px: u32,
    pub map_height_px: u32,
    /// Each map pixel is the mean of a `block x block` block of heights (1 = no reduction).
    pub block: u32,
    /// Each (reduced) height is drawn as `zoom x zoom` pixels (1 = no enlargement).
    pub zoom: u32,
}

/// An RGB image in memory (row-major, 3 bytes per pixel).
#[derive(Debug, Clone, PartialEq)]
pub struct PreviewImage {
    pub rgb: Vec<u8>,
    pub info: PreviewInfo,
}

/// Renders the preview of a `rows x cols` row-major height map and writes it as a PNG.
pub fn write_preview_png(
    path: impl AsRef<Path>,
    heights: &[f32],
    rows: usize,
    cols: usize,
    opts: &PreviewOptions,
) -> Result<PreviewInfo> {
    let path = path.as_ref();
    let image = render_preview(heights, rows, cols, opts)
        .with_context(|| format!("{}: cannot draw preview", path.display()))?;
    write_image_png(path, &image)
}

/// Writes a rendered preview as an RGB PNG, atomically.
fn write_image_png(path: &Path, image: &PreviewImage) -> Result<PreviewInfo> {
    let info = image.info;
    surfstream_core::fsutil::write_atomic(path, |w| {
        let mut enc = png::Encoder::new(&mut *w, info.width_px, info.height_px);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        enc.add_text_chunk("Software".into(), "surfstream".into())
            .and_then(|()| {
                enc.add_text_chunk(
                    "Comment".into(),
                    format!("viridis colour range {} .. {} um", info.min_um, info.max_um),
                )
            })
            .with_context(|| format!("{}: PNG encoding failed", path.display()))?;
        let mut writer = enc
            .write_header()
            .with_context(|| format!("{}: PNG encoding failed", path.display()))?;
        writer
            .write_image_data(&image.rgb)
            .with_context(|| format!("{}: PNG encoding failed", path.display()))?;
        writer
            .finish()
            .with_context(|| format!("{}: PNG encoding failed", path.display()))?;
        w.flush()
            .with_context(|| format!("{}: write failed", path.display()))?;
        Ok(())
    })?;
    Ok(info)
}

/// Builds the preview of a map that arrives row by row (never whole in memory): the same
/// image as [`render_preview`] of the whole map. It keeps one row of block sums, the reduced
/// map (at most `max_side_px` squared) and the percentile subsample (at most
/// [`PERCENTILE_SAMPLE_LIMIT`] values): a bounded amount whatever the map's size.
#[derive(Debug, Clone)]
pub struct PreviewBuilder {
    rows: usize,
    cols: usize,
    opts: PreviewOptions,
    block: usize,
    next_row: usize,
    sum: Vec<f64>,
    count: Vec<u32>,
    small: Vec<f32>,
    stride: usize,
    sample: Vec<f32>,
}

impl PreviewBuilder {
    pub fn new(rows: usize, cols: usize, opts: &PreviewOptions) -> Result<Self> {
        let n = rows.checked_mul(cols).unwrap_or(0);
        if n == 0 {
            bail!("empty or oversized height map ({rows} x {cols})");
        }
        check_options(opts)?;
        let block = rows.max(cols).div_ceil(opts.max_side_px).max(1);
        let out_cols = cols.div_ceil(block);
        Ok(Self {
            rows,
            cols,
            opts: opts.clone(),
            block,
            next_row: 0,
            sum: vec![0.0; out_cols],
            count: vec![0; out_cols],
            small: Vec::with_capacity(rows.div_ceil(block) * out_cols),
            stride: n.div_ceil(PERCENTILE_SAMPLE_LIMIT).max(1),
            sample: Vec::new(),
        })
    }

    /// The next whole rows of the map.
    pub fn push_rows(&mut self, heights: &[f32]) -> Result<()> {
        let cols = self.cols;
        if !heights.len().is_multiple_of(cols) || self.next_row + heights.len() / cols > self.rows {
            bail!(
                "preview: {} values are not whole rows of {cols} within {} x {cols} ({} rows in)",
                heights.len(),
                self.rows,
                self.next_row
            );
        }
        for row in heights.chunks_exact(cols) {
            let r = self.next_row;
            if self.opts.range_um.is_none() {
                // The values robust_range_um samples: flat indices that are multiples of stride.
                let first = r * cols;
                let mut c = (self.stride - first % self.stride) % self.stride;
                while c < cols {
                    let v = row[c];
                    if v.is_finite() {
                        self.sample.push(v);
                    }
                    c += self.stride;
                }
            }
            // block_mean's sums, in its order (rows down, columns across).
            for (c, &v) in row.iter().enumerate() {
                if v.is_finite() {
                    self.sum[c / self.block] += v as f64;
                    self.count[c / self.block] += 1;
                }
            }
            self.next_row += 1;
            if self.next_row.is_multiple_of(self.block) || self.next_row == self.rows {
                self.small
                    .extend(self.sum.iter().zip(&self.count).map(|(&s, &n)| {
                        if n > 0 {
                            (s / n as f64) as f32
                        } else {
                            f32::NAN
                        }
                    }));
                self.sum.iter_mut().for_each(|s| *s = 0.0);
                self.count.iter_mut().for_each(|n| *n = 0);
            }
        }
        Ok(())
    }

    /// The image, once every row arrived.
    pub fn render(mut self) -> Result<PreviewImage> {
        if self.next_row != self.rows {
            bail!("preview: {} of {} rows arrived", self.next_row, self.rows);
        }
        let range = match self.opts.range_um {
            Some(r) => r,
            None => robust_range_of_sample(&mut self.sample).unwrap_or((0.0, 1.0)),
        };
        let (s_rows, s_cols) = (
            self.rows.div_ceil(self.block),
            self.cols.div_ceil(self.block),
        );
        render_reduced(
            &self.small,
            s_rows,
            s_cols,
            self.block,
            self.rows.max(self.cols),
            range,
            &self.opts,
        )
    }

    /// Renders and writes the PNG (atomically), as [`write_preview_png`] does.
    pub fn write_png(self, path: impl AsRef<Path>) -> Result<PreviewInfo> {
        let path = path.as_ref();
        let image = self
            .render()
            .with_context(|| format!("{}: cannot draw preview", path.display()))?;
        write_image_png(path, &image)
    }
}

fn check_options(opts: &PreviewOptions) -> Result<()> {
    if opts.max_side_px == 0 {
        bail!("max_side_px must be at least 1");
    }
    if let Some((lo, hi)) = opts.range_um {
        if !(lo.is_finite() && hi.is_finite() && lo < hi) {
            bail!("colour range {lo} .. {hi} um is not an increasing pair of finite numbers");
        }
    }
    Ok(())
}

/// Renders the preview into memory (what [`write_preview_png`] writes).
pub fn render_preview(
    heights: &[f32],
    rows: usize,
    cols: usize,
    opts: &PreviewOptions,
) -> Result<PreviewImage> {
    if rows == 0 || cols == 0 {
        bail!("empty height map ({rows} x {cols})");
    }
    if rows.checked_mul(cols) != Some(heights.len()) {
        bail!(
            "height map is {rows} x {cols} but has {} values (expected {})",
            heights.len(),
            rows as u128 * cols as u128
        );
    }
    check_options(opts)?;
    let range = match opts.range_um {
        Some(r) => r,
        None => robust_range_um(heights).unwrap_or((0.0, 1.0)),
    };

    // Reduce or enlarge.
    let longer = rows.max(cols);
    let block = longer.div_ceil(opts.max_side_px).max(1);
    let (small, s_rows, s_cols) = if block > 1 {
        let (m, r, c) = block_mean(heights, rows, cols, block);
        (std::borrow::Cow::Owned(m), r, c)
    } else {
        (std::borrow::Cow::Borrowed(heights), rows, cols)
    };
    render_reduced(&small, s_rows, s_cols, block, longer, range, opts)
}

/// Draws the reduced map `small` (`s_rows x s_cols`, the map reduced by `block`; `longer` the
/// map's longer side) over the colour range `(min_um, max_um)`.
fn render_reduced(
    small: &[f32],
    s_rows: usize,
    s_cols: usize,
    block: usize,
    longer: usize,
    (min_um, max_um): (f64, f64),
    opts: &PreviewOptions,
) -> Result<PreviewImage> {
    let zoom = if block == 1 && opts.min_side_px > longer {
        (opts.min_side_px / longer)
            .min(opts.max_side_px / longer)
            .max(1)
    } else {
        1
    };
    let map_w = s_cols * zoom;
    let map_h = s_rows * zoom;

    // Layout.
    let scale = if map_h >= 320 { 2 } else { 1 };
    let glyph_h = 7 * scale;
    let map_left = MARGIN_PX;
    let map_top = MARGIN_PX
        + if opts.title.is_some() {
            glyph_h + MARGIN_PX
        } else {
            0
        };
    let ticks = if opts.colour_bar {
        nice_ticks(min_um, max_um)
    } else {
        Vec::new()
    };
    let labels: Vec<String> = ticks.iter().map(|t| t.1.clone()).collect();
    let label_w = labels
        .iter()
        .map(|l| text_width(l, scale))
        .max()
        .unwrap_or(0)
        .max(text_width("um", scale));
    let bar_left = map_left + map_w + 2 * MARGIN_PX;
    let (content_w, content_h) = if opts.colour_bar {
        let bar_area_h = map_h.max(96 * scale);
        (
            bar_left + BAR_WIDTH_PX + TICK_PX + 3 + label_w + MARGIN_PX,
            bar_area_h,
        )
    } else {
        (map_left + map_w + MARGIN_PX, map_h)
    };
    let title_w = opts
        .title
        .as_deref()
        .map(|t| 2 * MARGIN_PX + text_width(t, scale))
        .unwrap_or(0);
    // Under the map: the colour of "not measured" and how the colour range was chosen.
    let legend = opts.colour_bar.then(|| {
        if opts.range_um.is_some() {
            "not measured. colour range fixed".to_string()
        } else {
            format!("not measured. colour clip: {ROBUST_LOW_PERCENT} / {ROBUST_HIGH_PERCENT} %")
        }
    });
    let swatch_w = 2 * glyph_h;
    let legend_w = legend
        .as_deref()
        .map(|l| 2 * MARGIN_PX + swatch_w + 6 + text_width(l, scale))
        .unwrap_or(0);
    let legend_h = if legend.is_some() {
        glyph_h + MARGIN_PX
    } else {
        0
    };
    let width = content_w.max(title_w).max(legend_w);
    let height = map_top + content_h + legend_h + MARGIN_PX;
    if width > u32::MAX as usize
        || height > u32::MAX as usize
        || width
            .checked_mul(height)
            .and_then(|n| n.checked_mul(3))
            .is_none()
    {
        bail!("preview of {width} x {height} px is too large");
    }
    let mut canvas = Canvas::new(width, height);

    // The map.
    let span = max_um - min_um;
    for r in 0..s_rows {
        for c in 0..s_cols {
            let v = small[r * s_cols + c];
            let rgb = if v.is_finite() {
                viridis((v as f64 - min_um) / span)
            } else {
                NAN_RGB
            };
            canvas.fill(map_left + c * zoom, map_top + r * zoom, zoom, zoom, rgb);
        }
    }
    canvas.frame(map_left, map_top, map_w, map_h, FRAME_RGB);

    // The colour bar: top = max, bottom = min.
    if opts.colour_bar {
        let bar_top = map_top + 12 * scale;
        let bar_bottom = map_top + content_h - 4 * scale; // inclusive
        let bar_h = bar_bottom - bar_top;
        for y in bar_top..=bar_bottom {
            let t = (bar_bottom - y) as f64 / bar_h as f64;
            canvas.fill(bar_left, y, BAR_WIDTH_PX, 1, viridis(t));
        }
        canvas.frame(bar_left, bar_top, BAR_WIDTH_PX, bar_h + 1, FRAME_RGB);
        canvas.text(bar_left, map_top, "um", scale, TEXT_RGB);
        for (value, label) in &ticks {
            let frac = (value - min_um) / span;
            let y = bar_bottom - (frac * bar_h as f64).round() as usize;
            canvas.fill(bar_left + BAR_WIDTH_PX, y, TICK_PX, 1, TEXT_RGB);
            let ty = (y + 1).saturating_sub(glyph_h / 2 + 1);
            canvas.text(
                bar_left + BAR_WIDTH_PX + TICK_PX + 3,
                ty,
                label,
                scale,
                TEXT_RGB,
            );
        }
    }
    if let Some(title) = &opts.title {
        canvas.text(MARGIN_PX, MARGIN_PX, title, scale, TEXT_RGB);
    }
    if let Some(legend) = &legend {
        let y = map_top + content_h + MARGIN_PX;
        canvas.fill(MARGIN_PX, y, swatch_w, glyph_h, NAN_RGB);
        canvas.frame(MARGIN_PX, y, swatch_w, glyph_h, FRAME_RGB);
        canvas.text(MARGIN_PX + swatch_w + 6, y, legend, scale, TEXT_RGB);
    }

    let info = PreviewInfo {
        min_um,
        max_um,
        width_px: width as u32,
        height_px: height as u32,
        map_left_px: map_left as u32,
        map_top_px: map_top as u32,
        map_width_px: map_w as u32,
        map_height_px: map_h as u32,
        block: block as u32,
        zoom: zoom as u32,
    };
    Ok(PreviewImage {
        rgb: canvas.rgb,
        info,
    })
}

/// The default colour range: the [`ROBUST_LOW_PERCENT`] and [`ROBUST_HIGH_PERCENT`] percentiles
/// of the finite heights, widened to +- 0.5 um around a flat map. `None` if no height is finite.
pub fn robust_range_um(heights: &[f32]) -> Option<(f64, f64)> {
    let stride = heights.len().div_ceil(PERCENTILE_SAMPLE_LIMIT).max(1);
    let mut sample: Vec<f32> = heights
        .iter()
        .step_by(stride)
        .copied()
        .filter(|v| v.is_finite())
        .collect();
    robust_range_of_sample(&mut sample)
}

/// [`robust_range_um`] of its (finite) subsample.
fn robust_range_of_sample(sample: &mut [f32]) -> Option<(f64, f64)> {
    if sample.is_empty() {
        return None;
    }
    let lo = percentile(sample, ROBUST_LOW_PERCENT / 100.0);
    let hi = percentile(sample, ROBUST_HIGH_PERCENT / 100.0);
    if hi > lo {
        Some((lo, hi))
    } else {
        Some((lo - 0.5, lo + 0.5))
    }
}

/// The `p` (0..1) quantile with linear interpolation between order statistics (numpy's default).
fn percentile(values: &mut [f32], p: f64) -> f64 {
    let pos = p * (values.len() - 1) as f64;
    let k = pos.floor() as usize;
    let frac = pos - k as f64;
    let (_, &mut at_k, above) = values.select_nth_unstable_by(k, |a, b| a.total_cmp(b));
    let at_k = at_k as f64;
    if frac == 0.0 || above.is_empty() {
        return at_k;
    }
    let next = above.iter().copied().fold(f32::INFINITY, f32::min) as f64;
    at_k + frac * (next - at_k)
}

/// At most about eight nice ticks inside `lo..=hi`, with their labels.
fn nice_ticks(lo: f64, hi: f64) -> Vec<(f64, String)> {
    crate::figure::labelled_ticks(lo, hi, 8)
}

// ---------------------------------------------------------------------------------------------
// Drawing

struct Canvas {
    w: usize,
    h: usize,
    rgb: Vec<u8>,
}

impl Canvas {
    fn new(w: usize, h: usize) -> Self {
        let mut rgb = Vec::with_capacity(w * h * 3);
        for _ in 0..w * h {
            rgb.extend_from_slice(&BACKGROUND_RGB);
        }
        Self { w, h, rgb }
    }

    fn fill(&mut self, x: usize, y: usize, w: usize, h: usize, rgb: [u8; 3]) {
        for yy in y..(y + h).min(self.h) {
            let row = &mut self.rgb[yy * self.w * 3..(yy + 1) * self.w * 3];
            for xx in x..(x + w).min(self.w) {
                row[xx * 3..xx * 3 + 3].copy_from_slice(&rgb);
            }
        }
    }

    /// A 1-px frame just outside the rectangle (x, y, w, h).
    fn frame(&mut self, x: usize, y: usize, w: usize, h: usize, rgb: [u8; 3]) {
        if x == 0 || y == 0 {
            return;
        }
        self.fill(x - 1, y - 1, w + 2, 1, rgb);
        self.fill(x - 1, y + h, w + 2, 1, rgb);
        self.fill(x - 1, y, 1, h, rgb);
        self.fill(x + w, y, 1, h, rgb);
    }

    fn text(&mut self, x: usize, y: usize, text: &str, scale: usize, rgb: [u8; 3]) {
        for (i, ch) in text.chars().enumerate() {
            let g = glyph(ch);
            let gx = x + i * 6 * scale;
            for (row, bits) in g.iter().enumerate() {
                for col in 0..5 {
                    if bits & (0b10000 >> col) != 0 {
                        self.fill(gx + col * scale, y + row * scale, scale, scale, rgb);
                    }
                }
            }
        }
    }
}

fn text_width(text: &str, scale: usize) -> usize {
    let n = text.chars().count();
    if n == 0 {
        0
    } else {
        (6 * n - 1) * scale
    }
}

/// The 5 x 7 glyph of `ch`: seven rows, bit 4 = leftmost column. Unknown characters draw as '?'.
fn glyph(ch: char) -> [u8; 7] {
    let ch = if ch == '\u{b5}' || ch == '\u{3bc}' {
        'u'
    } else {
        ch
    }; // micro sign
    FONT.iter()
        .find(|(c, _)| *c == ch)
        .map(|(_, g)| *g)
        .unwrap_or(QUESTION)
}

const QUESTION: [u8; 7] = [
    0b01110, 0b10001, 0b00001, 0b00010, 0b00100, 0b00000, 0b00100,
];

#[rustfmt::skip]
const FONT: &[(char, [u8; 7])] = &[
    (' ', [0b00000, 0b00000, 0b00000, 0b00000, 0b00000, 0b00000, 0b00000]),
    ('0', [0b01110, 0b10001, 0b10011, 0b10101, 0b11001, 0b10001, 0b01110]),
    ('1', [0b00100, 0b01100, 0b00100, 0b00100, 0b00100, 0b00100, 0b01110]),
    ('2', [0b01110, 0b10001, 0b00001, 0b00010, 0b00100, 0b01000, 0b11111]),
    ('3', [0b11111, 0b00010, 0b00100, 0b00010, 0b00001, 0b10001, 0b01110]),
    ('4', [0b00010, 0b00110, 0b01010, 0b10010, 0b11111, 0b00010, 0b00010]),
    ('5', [0b11111, 0b10000, 0b11110, 0b00001, 0b00001, 0b10001, 0b01110]),
    ('6', [0b00110, 0b01000, 0b10000, 0b11110, 0b10001, 0b10001, 0b01110]),
    ('7', [0b11111, 0b00001, 0b00010, 0b00100, 0b01000, 0b01000, 0b01000]),
    ('8', [0b01110, 0b10001, 0b10001, 0b01110, 0b10001, 0b10001, 0b01110]),
    ('9', [0b01110, 0b10001, 0b10001, 0b01111, 0b00001, 0b00010, 0b01100]),
    ('.', [0b00000, 0b00000, 0b00000, 0b00000, 0b00000, 0b01100, 0b01100]),
    (',', [0b00000, 0b00000, 0b00000, 0b00000, 0b01100, 0b00100, 0b01000]),
    (':', [0b00000, 0b01100, 0b01100, 0b00000, 0b01100, 0b01100, 0b00000]),
    ('-', [0b00000, 0b00000, 0b00000, 0b11111, 0b00000, 0b00000, 0b00000]),
    ('+', [0b00000, 0b00100, 0b00100, 0b11111, 0b00100, 0b00100, 0b00000]),
    ('=', [0b00000, 0b00000, 0b11111, 0b00000, 0b11111, 0b00000, 0b00000]),
    ('_', [0b00000, 0b00000, 0b00000, 0b00000, 0b00000, 0b00000, 0b11111]),
    ('/', [0b00000, 0b00001, 0b00010, 0b00100, 0b01000, 0b10000, 0b00000]),
    ('(', [0b00010, 0b00100, 0b01000, 0b01000, 0b01000, 0b00100, 0b00010]),
    (')', [0b01000, 0b00100, 0b00010, 0b00010, 0b00010, 0b00100, 0b01000]),
    ('%', [0b11000, 0b11001, 0b00010, 0b00100, 0b01000, 0b10011, 0b00011]),
    ('#', [0b01010, 0b01010, 0b11111, 0b01010, 0b11111, 0b01010, 0b01010]),
    ('\'', [0b00100, 0b00100, 0b01000, 0b00000, 0b00000, 0b00000, 0b00000]),
    ('?', QUESTION),
    ('A', [0b01110, 0b10001, 0b10001, 0b11111, 0b10001, 0b10001, 0b10001]),
    ('B', [0b11110, 0b10001, 0b10001, 0b11110, 0b10001, 0b10001, 0b11110]),
    ('C', [0b01110, 0b10001, 0b10000, 0b10000, 0b10000, 0b10001, 0b01110]),
    ('D', [0b11100, 0b10010, 0b10001, 0b10001, 0b10001, 0b10010, 0b11100]),
    ('E', [0b11111, 0b10000, 0b10000, 0b11110, 0b10000, 0b10000, 0b11111]),
    ('F', [0b11111, 0b10000, 0b10000, 0b11110, 0b10000, 0b10000, 0b10000]),
    ('G', [0b01110, 0b10001, 0b10000, 0b10111, 0b10001, 0b10001, 0b01111]),
    ('H', [0b10001, 0b10001, 0b10001, 0b11111, 0b10001, 0b10001, 0b10001]),
    ('I', [0b01110, 0b00100, 0b00100, 0b00100, 0b00100, 0b00100, 0b01110]),
    ('J', [0b00111, 0b00010, 0b00010, 0b00010, 0b00010, 0b10010, 0b01100]),
    ('K', [0b10001, 0b10010, 0b10100, 0b11000, 0b10100, 0b10010, 0b10001]),
    ('L', [0b10000, 0b10000, 0b10000, 0b10000, 0b10000, 0b10000, 0b11111]),
    ('M', [0b10001, 0b11011, 0b10101, 0b10101, 0b10001, 0b10001, 0b10001]),
    ('N', [0b10001, 0b10001, 0b11001, 0b10101, 0b10011, 0b10001, 0b10001]),
    ('O', [0b01110, 0b10001, 0b10001, 0b10001, 0b10001, 0b10001, 0b01110]),
    ('P', [0b11110, 0b10001, 0b10001, 0b11110, 0b10000, 0b10000, 0b10000]),
    ('Q', [0b01110, 0b10001, 0b10001, 0b10001, 0b10101, 0b10010, 0b01101]),
    ('R', [0b11110, 0b10001, 0b10001, 0b11110, 0b10100, 0b10010, 0b10001]),
    ('S', [0b01111, 0b10000, 0b10000, 0b01110, 0b00001, 0b00001, 0b11110]),
    ('T', [0b11111, 0b00100, 0b00100, 0b00100, 0b00100, 0b00100, 0b00100]),
    ('U', [0b10001, 0b10001, 0b10001, 0b10001, 0b10001, 0b10001, 0b01110]),
    ('V', [0b10001, 0b10001, 0b10001, 0b10001, 0b10001, 0b01010, 0b00100]),
    ('W', [0b10001, 0b10001, 0b10001, 0b10101, 0b10101, 0b10101, 0b01010]),
    ('X', [0b10001, 0b10001, 0b01010, 0b00100, 0b01010, 0b10001, 0b10001]),
    ('Y', [0b10001, 0b10001, 0b10001, 0b01010, 0b00100, 0b00100, 0b00100]),
    ('Z', [0b11111, 0b00001, 0b00010, 0b00100, 0b01000, 0b10000, 0b11111]),
    ('a', [0b00000, 0b00000, 0b01110, 0b00001, 0b01111, 0b10001, 0b01111]),
    ('b', [0b10000, 0b10000, 0b10110, 0b11001, 0b10001, 0b10001, 0b11110]),
    ('c', [0b00000, 0b00000, 0b01110, 0b10000, 0b10000, 0b10001, 0b01110]),
    ('d', [0b00001, 0b00001, 0b01101, 0b10011, 0b10001, 0b10001, 0b01111]),
    ('e', [0b00000, 0b00000, 0b01110, 0b10001, 0b11111, 0b10000, 0b01110]),
    ('f', [0b00110, 0b01001, 0b01000, 0b11100, 0b01000, 0b01000, 0b01000]),
    ('g', [0b00000, 0b01111, 0b10001, 0b10001, 0b01111, 0b00001, 0b01110]),
    ('h', [0b10000, 0b10000, 0b10110, 0b11001, 0b10001, 0b10001, 0b10001]),
    ('i', [0b00100, 0b00000, 0b01100, 0b00100, 0b00100, 0b00100, 0b01110]),
    ('j', [0b00010, 0b00000, 0b00110, 0b00010, 0b00010, 0b10010, 0b01100]),
    ('k', [0b10000, 0b10000, 0b10010, 0b10100, 0b11000, 0b10100, 0b10010]),
    ('l', [0b01100, 0b00100, 0b00100, 0b00100, 0b00100, 0b00100, 0b01110]),
    ('m', [0b00000, 0b00000, 0b11010, 0b10101, 0b10101, 0b10001, 0b10001]),
    ('n', [0b00000, 0b00000, 0b10110, 0b11001, 0b10001, 0b10001, 0b10001]),
    ('o', [0b00000, 0b00000, 0b01110, 0b10001, 0b10001, 0b10001, 0b01110]),
    ('p', [0b00000, 0b00000, 0b11110, 0b10001, 0b11110, 0b10000, 0b10000]),
    ('q', [0b00000, 0b00000, 0b01101, 0b10011, 0b01111, 0b00001, 0b00001]),
    ('r', [0b00000, 0b00000, 0b10110, 0b11001, 0b10000, 0b10000, 0b10000]),
    ('s', [0b00000, 0b00000, 0b01110, 0b10000, 0b01110, 0b00001, 0b11110]),
    ('t', [0b01000, 0b01000, 0b11100, 0b01000, 0b01000, 0b01001, 0b00110]),
    ('u', [0b00000, 0b00000, 0b10001, 0b10001, 0b10001, 0b10011, 0b01101]),
    ('v', [0b00000, 0b00000, 0b10001, 0b10001, 0b10001, 0b01010, 0b00100]),
    ('w', [0b00000, 0b00000, 0b10001, 0b10001, 0b10101, 0b10101, 0b01010]),
    ('x', [0b00000, 0b00000, 0b10001, 0b01010, 0b00100, 0b01010, 0b10001]),
    ('y', [0b00000, 0b00000, 0b10001, 0b10001, 0b01111, 0b00001, 0b01110]),
    ('z', [0b00000, 0b00000, 0b11111, 0b00010, 0b00100, 0b01000, 0b11111]),
];

#[cfg(test)]
mod tests {
    use super::*;

    fn decode_png(path: &Path) -> (u32, u32, Vec<u8>) {
        let file = std::fs::File::open(path).expect("open png");
        let decoder = png::Decoder::new(std::io::BufReader::new(file));
        let mut reader = decoder.read_info().expect("png header");
        let mut buf = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut buf).expect("png frame");
        assert_eq!(info.color_type, png::ColorType::Rgb);
        assert_eq!(info.bit_depth, png::BitDepth::Eight);
        buf.truncate(info.buffer_size());
        (info.width, info.height, buf)
    }

    fn pixel(rgb: &[u8], width: u32, x: u32, y: u32) -> [u8; 3] {
        let i = (y as usize * width as usize + x as usize) * 3;
        [rgb[i], rgb[i + 1], rgb[i + 2]]
    }

    #[test]
    fn small_preview_decodes_with_nan_grey_and_viridis_ends() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("p.png");
        // 4 x 6 ramp, with the min at (0, 0), the max at (3, 5) and a NaN at (1, 2).
        let (rows, cols) = (4usize, 6usize);
        let mut h: Vec<f32> = (0..rows * cols).map(|i| i as f32 * 0.1).collect();
        h[cols + 2] = f32::NAN;
        let opts = PreviewOptions {
            range_um: Some((0.0, 2.3)),
            title: Some("Tile 0: Sa 1.3 um".into()),
            ..Default::default()
        };
        let info = write_preview_png(&path, &h, rows, cols, &opts).expect("write");
        assert!(!dir.path().join("p.png.partial").exists());
        let (w, hgt, rgb) = decode_png(&path);
        assert_eq!((w, hgt), (info.width_px, info.height_px));
        // Enlarged to at least min_side_px on the longer side, by an integer factor.
        assert_eq!(info.zoom, 256 / 6);
        assert_eq!(
            (info.map_width_px, info.map_height_px),
            (6 * info.zoom, 4 * info.zoom)
        );
        assert!(
            w > info.map_left_px + info.map_width_px + BAR_WIDTH_PX as u32,
            "room for the colour bar"
        );
        let at = |r: u32, c: u32| {
            let z = info.zoom;
            pixel(
                &rgb,
                w,
                info.map_left_px + c * z + z / 2,
                info.map_top_px + r * z + z / 2,
            )
        };
        assert_eq!(at(0, 0), VIRIDIS[0]);
        assert_eq!(at(3, 5), VIRIDIS[255]);
        assert_eq!(at(1, 2), NAN_RGB);
        assert_eq!(VIRIDIS[0], [68, 1, 84]);
        assert_eq!(VIRIDIS[255], [253, 231, 37]);
        // Title text is drawn (some black pixels above the map).
        let title_rows = &rgb[..(info.map_top_px as usize * w as usize * 3)];
        assert!(title_rows.chunks(3).any(|p| p == TEXT_RGB));
    }

    #[test]
    fn legend_under_the_map_shows_the_not_measured_grey() {
        let h = vec![1.0f32; 300 * 400];
        let img = render_preview(&h, 300, 400, &PreviewOptions::default()).expect("render");
        let i = img.info;
        let below = i.map_top_px + i.map_height_px + 1;
        let rows = &img.rgb[(below * i.width_px) as usize * 3..];
        assert!(rows.chunks(3).any(|p| p == NAN_RGB), "grey swatch");
        assert!(rows.chunks(3).any(|p| p == TEXT_RGB), "legend text");
        // The legend fits beside the colour bar: it does not widen the image.
        let no_bar = PreviewOptions {
            colour_bar: false,
            ..Default::default()
        };
        let plain = render_preview(&h, 300, 400, &no_bar).expect("render");
        assert!(i.width_px > plain.info.width_px);
        assert!(i.width_px < plain.info.width_px + 120, "{} px", i.width_px);
    }

    #[test]
    fn map_png_is_indexed_viridis_with_a_not_measured_entry() {
        // 4 x 6, block 2 (max side 3): the block at (0, 2) is all NaN.
        let mut h: Vec<f32> = (0..24).map(|i| i as f32 * 0.1).collect();
        for (r, c) in [(0, 4), (0, 5), (1, 4), (1, 5)] {
            h[r * 6 + c] = f32::NAN;
        }
        let m = encode_map_png(&h, 4, 6, 3, (0.0, 2.3)).expect("encode");
        assert_eq!((m.rows, m.cols, m.block), (2, 3, 2));
        let dec = png::Decoder::new(std::io::Cursor::new(&m.png));
        let mut reader = dec.read_info().expect("png header");
        let palette = reader.info().palette.clone().expect("palette").to_vec();
        assert_eq!(&palette[255 * 3..], &NAN_RGB);
        assert_eq!(&palette[..3], &VIRIDIS[0]);
        assert_eq!(&palette[254 * 3..255 * 3], &VIRIDIS[255]);
        let mut buf = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut buf).expect("frame");
        assert_eq!(info.color_type, png::ColorType::Indexed);
        buf.truncate(info.buffer_size());
        // Block (0, 0): mean of 0.0, 0.1, 0.6, 0.7 = 0.35 -> 0.35 / 2.3 * 254 = 38.65 -> 39.
        assert_eq!(buf[0], 39);
        assert_eq!(buf[2], 255);
        // Block (1, 2): mean of 1.6, 1.7, 2.2, 2.3 = 1.95 -> 215.35 -> 215.
        assert_eq!(buf[5], 215);
        assert!(encode_map_png(&h, 4, 5, 3, (0.0, 1.0)).is_err());
        assert!(encode_map_png(&h, 4, 6, 3, (1.0, 1.0)).is_err());
    }

    #[test]
    fn robust_range_ignores_outliers_and_nan() {
        let mut h: Vec<f32> = (0..1000).map(|i| i as f32 / 999.0).collect();
        h[10] = 1e6;
        h[20] = -1e6;
        h[30] = f32::NAN;
        let (lo, hi) = robust_range_um(&h).expect("range");
        assert!(lo > -0.01 && lo < 0.02, "{lo}");
        assert!(hi > 0.98 && hi < 1.01, "{hi}");
        assert_eq!(robust_range_um(&[f32::NAN; 4]), None);
        assert_eq!(robust_range_um(&[2.0; 4]), Some((1.5, 2.5)));
        // numpy.percentile([0, 1, 2, 3], [0.5, 99.5]) = [0.015, 2.985]
        let (lo, hi) = robust_range_um(&[3.0, 0.0, 2.0, 1.0]).expect("range");
        assert!(
            (lo - 0.015).abs() < 1e-9 && (hi - 2.985).abs() < 1e-9,
            "{lo} {hi}"
        );
    }

    #[test]
    fn large_maps_are_block_averaged_nan_aware() {
        let (rows, cols) = (300usize, 500usize);
        let mut h = vec![1.0f32; rows * cols];
        // Top-left 100 x 100 block: half NaN, half 3.0 -> mean 3.0; a fully NaN block stays NaN.
        for r in 0..100 {
            for c in 0..100 {
                h[r * cols + c] = if c % 2 == 0 { f32::NAN } else { 3.0 };
            }
            for c in 100..200 {
                h[r * cols + c] = f32::NAN;
            }
        }
        let opts = PreviewOptions {
            max_side_px: 5,
            range_um: Some((1.0, 3.0)),
            colour_bar: false,
            ..Default::default()
        };
        let img = render_preview(&h, rows, cols, &opts).expect("render");
        let info = img.info;
        assert_eq!(
            (info.block, info.zoom, info.map_width_px, info.map_height_px),
            (100, 1, 5, 3)
        );
        let px = |c: u32, r: u32| {
            pixel(
                &img.rgb,
                info.width_px,
                info.map_left_px + c,
                info.map_top_px + r,
            )
        };
        assert_eq!(px(0, 0), VIRIDIS[255]);
        assert_eq!(px(1, 0), NAN_RGB);
        assert_eq!(px(2, 0), VIRIDIS[0]);
        assert_eq!(px(4, 2), VIRIDIS[0]);
    }

    #[test]
    fn builder_from_rows_draws_the_same_image() {
        // Block 1 (zoomed), block 3 with a strided percentile sample (> 2^22 values), and a
        // fixed range; rows pushed in uneven pieces.
        for (rows, cols, range) in [
            (37usize, 53usize, None),
            (2100, 2050, None),
            (1500, 1030, Some((-1.0, 2.0))),
        ] {
            let h: Vec<f32> = (0..rows * cols)
                .map(|i| {
                    let (r, c) = ((i / cols) as f32, (i % cols) as f32);
                    if i % 97 == 5 || r as usize == rows / 2 {
                        f32::NAN
                    } else {
                        (0.01 * c).sin() + 0.002 * r + ((i * 7919) % 101) as f32 * 1e-3
                    }
                })
                .collect();
            let opts = PreviewOptions {
                title: Some("t".into()),
                range_um: range,
                ..Default::default()
            };
            let whole = render_preview(&h, rows, cols, &opts).unwrap();
            let mut b = PreviewBuilder::new(rows, cols, &opts).unwrap();
            let mut r = 0;
            for n in [1usize, 5, 64, 3].iter().cycle() {
                if r == rows {
                    break;
                }
                let k = (*n).min(rows - r);
                b.push_rows(&h[r * cols..(r + k) * cols]).unwrap();
                r += k;
            }
            let streamed = b.render().unwrap();
            assert_eq!(whole.info, streamed.info, "{rows} x {cols}");
            assert!(whole.rgb == streamed.rgb, "{rows} x {cols}");
        }
        let mut b = PreviewBuilder::new(4, 3, &PreviewOptions::default()).unwrap();
        assert!(b.push_rows(&[0.0; 4]).is_err());
        b.push_rows(&[0.0; 6]).unwrap();
        assert!(b.clone().render().is_err());
        assert!(b.push_rows(&[0.0; 9]).is_err());
    }

    #[test]
    fn block_mean_handles_ragged_edges() {
        let h = [1.0, 2.0, 3.0, 4.0, 5.0, f32::NAN, 7.0, 8.0, 9.0];
        let (m, r, c) = block_mean(&h, 3, 3, 2);
        assert_eq!((r, c), (2, 2));
        assert_eq!(m[0], (1.0 + 2.0 + 4.0 + 5.0) / 4.0);
        assert_eq!(m[1], 3.0); // (3, NaN) -> 3
        assert_eq!(m[2], 7.5);
        assert_eq!(m[3], 9.0);
    }

    #[test]
    fn ticks_are_nice_and_inside_the_range() {
        let t = nice_ticks(-0.37, 1.23);
        let labels: Vec<&str> = t.iter().map(|x| x.1.as_str()).collect();
        assert_eq!(
            labels,
            ["-0.2", "0.0", "0.2", "0.4", "0.6", "0.8", "1.0", "1.2"]
        );
        let t = nice_ticks(12.0, 130.0);
        assert_eq!(
            t.iter().map(|x| x.1.as_str()).collect::<Vec<_>>(),
            ["20", "40", "60", "80", "100", "120"]
        );
        assert!(nice_ticks(1.0, 1.0).is_empty());
    }

    #[test]
    fn bad_inputs_are_errors() {
        let o = PreviewOptions::default();
        assert!(render_preview(&[1.0; 5], 2, 3, &o).is_err());
        assert!(render_preview(&[], 0, 3, &o).is_err());
        let bad = PreviewOptions {
            range_um: Some((2.0, 1.0)),
            ..Default::default()
        };
        assert!(render_preview(&[1.0; 6], 2, 3, &bad).is_err());
        let dir = tempfile::tempdir().expect("tempdir");
        let e =
            write_preview_png(dir.path().join("x.png"), &[1.0; 5], 2, 3, &o).expect_err("error");
        assert!(format!("{e:#}").contains("x.png"), "{e:#}");
        assert!(!dir.path().join("x.png").exists());
    }

    #[test]
    fn every_font_glyph_fits_five_columns() {
        for (c, g) in FONT {
            assert!(g.iter().all(|row| *row < 32), "glyph {c:?}");
        }
        assert_eq!(glyph('\u{b5}'), glyph('u'));
        assert_eq!(glyph('\u{263a}'), QUESTION);
    }
}
