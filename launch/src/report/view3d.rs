//! The 3-D view: a static oblique render of the model surface (the pooled map the mesher
//! meshed), by a small software rasteriser, so the page needs no WebGL or script library and
//! stays one file that works offline.
//!
//! Orthographic camera 35° above the surface, turned 30° about the vertical from the maps'
//! bottom edge (the last row, the largest y, nearest the viewer: the maps draw row 0 at the
//! top, [`surfstream_io::figure`]); heights exaggerated so the colour range is
//! 5 % of the longer side (the factor is stated); two triangles per grid cell, flat-shaded
//! (Lambert, light from the far left, above) in the maps' viridis colours, depth-buffered, and
//! a grey base block under the surface; drawn at twice the size and box-filtered down.

use std::fmt::Write as _;

use surfstream_io::figure::viridis;
use surfstream_io::preview::robust_range_um;

use super::html::{base64, esc, fixed, length, png_rgb};
use super::surfaces::Surface;

/// Output size, px.
const WIDTH: usize = 960;
const HEIGHT: usize = 560;
/// Supersampling factor.
const SS: usize = 2;
/// Longest side of the grid that is drawn (larger maps are block averaged).
const MAX_GRID: usize = 512;
const AZIMUTH_DEG: f64 = 30.0;
const ELEVATION_DEG: f64 = 35.0;
/// The colour range is drawn this share of the longer side high.
const RELIEF: f64 = 0.05;

/// A rendered view and what it shows.
pub struct Render {
    pub png: Vec<u8>,
    pub exaggeration: f64,
    pub grid: (usize, usize),
    pub block: usize,
    /// Axes and scale drawn over the image: SVG elements in output pixels.
    pub overlay: String,
}

struct Raster {
    w: usize,
    h: usize,
    rgb: Vec<f32>,
    depth: Vec<f64>,
}

impl Raster {
    /// Fills a screen-space triangle (x, y, depth) with `colour`, nearer (larger depth) wins.
    fn triangle(&mut self, p: [(f64, f64, f64); 3], colour: [f32; 3]) {
        let (x0, x1) = (
            p.iter().map(|q| q.0).fold(f64::INFINITY, f64::min),
            p.iter().map(|q| q.0).fold(f64::NEG_INFINITY, f64::max),
        );
        let (y0, y1) = (
            p.iter().map(|q| q.1).fold(f64::INFINITY, f64::min),
            p.iter().map(|q| q.1).fold(f64::NEG_INFINITY, f64::max),
        );
        let area = (p[1].0 - p[0].0) * (p[2].1 - p[0].1) - (p[2].0 - p[0].0) * (p[1].1 - p[0].1);
        if area.abs() < 1e-12 || !area.is_finite() {
            return;
        }
        let cx0 = x0.floor().max(0.0) as usize;
        let cy0 = y0.floor().max(0.0) as usize;
        let cx1 = (x1.ceil() as usize).min(self.w.saturating_sub(1));
        let cy1 = (y1.ceil() as usize).min(self.h.saturating_sub(1));
        if x1 < 0.0 || y1 < 0.0 {
            return;
        }
        for y in cy0..=cy1 {
            let py = y as f64 + 0.5;
            for x in cx0..=cx1 {
                let px = x as f64 + 0.5;
                let w0 = ((p[1].0 - px) * (p[2].1 - py) - (p[2].0 - px) * (p[1].1 - py)) / area;
                let w1 = ((p[2].0 - px) * (p[0].1 - py) - (p[0].0 - px) * (p[2].1 - py)) / area;
                let w2 = 1.0 - w0 - w1;
                if w0 < -1e-9 || w1 < -1e-9 || w2 < -1e-9 {
                    continue;
                }
                let d = w0 * p[0].2 + w1 * p[1].2 + w2 * p[2].2;
                let i = y * self.w + x;
                if d > self.depth[i] {
                    self.depth[i] = d;
                    self.rgb[i * 3..i * 3 + 3].copy_from_slice(&colour);
                }
            }
        }
    }
}

/// NaN-aware block means, `f` x `f`.
fn block_mean(s: &Surface, f: usize) -> (Vec<f64>, usize, usize) {
    let (rows, cols) = (s.rows.div_ceil(f), s.cols.div_ceil(f));
    let mut out = vec![f64::NAN; rows * cols];
    for r in 0..rows {
        for c in 0..cols {
            let (mut sum, mut n) = (0.0, 0usize);
            for rr in r * f..((r + 1) * f).min(s.rows) {
                for &v in &s.row(rr)[c * f..((c + 1) * f).min(s.cols)] {
                    if v.is_finite() {
                        sum += v;
                        n += 1;
                    }
                }
            }
            if n > 0 {
                out[r * cols + c] = sum / n as f64;
            }
        }
    }
    (out, rows, cols)
}

/// Two significant digits, so the stated factor is the one used.
fn round2(v: f64) -> f64 {
    let mag = 10f64.powf(v.abs().log10().floor() - 1.0);
    (v / mag).round() * mag
}

/// The camera: the orthographic projection of world points (um, heights already exaggerated)
/// to supersampled screen pixels, fitted so the whole block fills the image.
struct Camera {
    /// cos / sin of the azimuth and the elevation.
    ca: f64,
    sa: f64,
    ce: f64,
    se: f64,
    /// The block's centre, um.
    cx: f64,
    cy: f64,
    /// Screen px per um, and the screen origin.
    k: f64,
    ox: f64,
    oy: f64,
}

impl Camera {
    /// A camera that fits the block (`w_um` x `h_um`, from `base_z` up to `top_z`) in the
    /// supersampled image.
    fn fitted(w_um: f64, h_um: f64, base_z: f64, top_z: f64) -> Self {
        let (a, e) = (AZIMUTH_DEG.to_radians(), ELEVATION_DEG.to_radians());
        let mut cam = Self {
            ca: a.cos(),
            sa: a.sin(),
            ce: e.cos(),
            se: e.sin(),
            cx: w_um / 2.0,
            cy: h_um / 2.0,
            k: 1.0,
            ox: 0.0,
            oy: 0.0,
        };
        // Fit the block's corners (top at the colour range's top, bottom at the base).
        let mut bounds = (
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
        );
        for (x, y) in [(0.0, 0.0), (w_um, 0.0), (0.0, h_um), (w_um, h_um)] {
            for zz in [base_z, top_z] {
                let (u, v, _) = cam.project(x, y, zz);
                bounds = (
                    bounds.0.min(u),
                    bounds.1.max(u),
                    bounds.2.min(v),
                    bounds.3.max(v),
                );
            }
        }
        let (w, h) = (WIDTH * SS, HEIGHT * SS);
        let margin = 24.0 * SS as f64;
        cam.k = ((w as f64 - 2.0 * margin) / (bounds.1 - bounds.0))
            .min((h as f64 - 2.0 * margin) / (bounds.3 - bounds.2));
        cam.ox = (w as f64 - cam.k * (bounds.1 - bounds.0)) / 2.0 - cam.k * bounds.0;
        cam.oy = (h as f64 + cam.k * (bounds.3 - bounds.2)) / 2.0 + cam.k * bounds.2;
        cam
    }

    /// World (x right, y toward the viewer, z up: the last row, the maps' bottom edge, in
    /// front, row 0 at the back, as the maps draw row 0 at the top) -> (u right, v up, depth
    /// toward the viewer).
    fn project(&self, x: f64, y: f64, zz: f64) -> (f64, f64, f64) {
        let (xw, yw) = (x - self.cx, y - self.cy);
        let xr = xw * self.ca + yw * self.sa;
        let yr = -xw * self.sa + yw * self.ca;
        (xr, zz * self.ce - yr * self.se, yr * self.ce + zz * self.se)
    }

    /// Supersampled screen pixels and depth.
    fn screen(&self, x: f64, y: f64, zz: f64) -> (f64, f64, f64) {
        let (u, v, d) = self.project(x, y, zz);
        (self.ox + self.k * u, self.oy - self.k * v, d)
    }

    /// Output pixels (after the box filter).
    fn px(&self, x: f64, y: f64, zz: f64) -> (f64, f64) {
        let (u, v, _) = self.screen(x, y, zz);
        (u / SS as f64, v / SS as f64)
    }
}

/// Flat Lambert shading, light from the far left (y grows toward the viewer), above.
fn shade(nx: f64, ny: f64, nz: f64) -> f32 {
    // Normalised once, not per drawn cell.
    static LIGHT: std::sync::LazyLock<[f64; 3]> = std::sync::LazyLock::new(|| {
        let l = [-0.8f64, -1.0, 1.3];
        let n = (l[0] * l[0] + l[1] * l[1] + l[2] * l[2]).sqrt();
        [l[0] / n, l[1] / n, l[2] / n]
    });
    let light = &*LIGHT;
    let n = (nx * nx + ny * ny + nz * nz).sqrt();
    (0.45 + 0.55 * ((nx * light[0] + ny * light[1] + nz * light[2]) / n).max(0.0)) as f32
}

/// The grid to draw: block means of the surface, their spacing and the colour range.
struct ViewGrid {
    z: Vec<f64>,
    rows: usize,
    cols: usize,
    /// Spacing, um.
    dx: f64,
    dy: f64,
    /// The colour range, um.
    lo: f64,
    hi: f64,
    /// Height exaggeration.
    ex: f64,
    /// The base block's bottom (exaggerated).
    base_z: f64,
}

impl ViewGrid {
    fn at(&self, r: usize, c: usize) -> f64 {
        self.z[r * self.cols + c]
    }

    /// Two triangles per cell, coloured by the cell's mean height, shaded by its slope.
    fn draw_surface(&self, ras: &mut Raster, cam: &Camera) {
        let (dx, dy, ex) = (self.dx, self.dy, self.ex);
        for r in 0..self.rows - 1 {
            for c in 0..self.cols - 1 {
                let q = [
                    self.at(r, c),
                    self.at(r, c + 1),
                    self.at(r + 1, c),
                    self.at(r + 1, c + 1),
                ];
                if q.iter().any(|v| !v.is_finite()) {
                    continue;
                }
                let dzdx = (q[1] - q[0] + q[3] - q[2]) / (2.0 * dx) * ex;
                let dzdy = (q[2] - q[0] + q[3] - q[1]) / (2.0 * dy) * ex;
                let mean = (q[0] + q[1] + q[2] + q[3]) / 4.0;
                let rgb = viridis((mean - self.lo) / (self.hi - self.lo));
                let s = shade(-dzdx, -dzdy, 1.0);
                let colour = [
                    rgb[0] as f32 / 255.0 * s,
                    rgb[1] as f32 / 255.0 * s,
                    rgb[2] as f32 / 255.0 * s,
                ];
                let (x0, x1, y0, y1) = (
                    c as f64 * dx,
                    (c + 1) as f64 * dx,
                    r as f64 * dy,
                    (r + 1) as f64 * dy,
                );
                let p00 = cam.screen(x0, y0, q[0] * ex);
                let p01 = cam.screen(x1, y0, q[1] * ex);
                let p10 = cam.screen(x0, y1, q[2] * ex);
                let p11 = cam.screen(x1, y1, q[3] * ex);
                ras.triangle([p00, p01, p11], colour);
                ras.triangle([p00, p11, p10], colour);
            }
        }
    }

    /// The base block's four sides, from the surface edge down to the base.
    fn draw_sides(&self, ras: &mut Raster, cam: &Camera) {
        let (rows, cols) = (self.rows, self.cols);
        let side = |ras: &mut Raster, pts: &[(f64, f64, f64)], normal: (f64, f64)| {
            let s = shade(normal.0, normal.1, 0.0) * 0.9;
            let colour = [0.72 * s, 0.72 * s, 0.74 * s];
            for p in pts.windows(2) {
                let (a0, b0) = (p[0], p[1]);
                if !(a0.2.is_finite() && b0.2.is_finite()) {
                    continue;
                }
                let ta = cam.screen(a0.0, a0.1, a0.2 * self.ex);
                let tb = cam.screen(b0.0, b0.1, b0.2 * self.ex);
                let ba = cam.screen(a0.0, a0.1, self.base_z);
                let bb = cam.screen(b0.0, b0.1, self.base_z);
                ras.triangle([ta, tb, bb], colour);
                ras.triangle([ta, bb, ba], colour);
            }
        };
        let edge = |f: &dyn Fn(usize) -> (usize, usize), n: usize| -> Vec<(f64, f64, f64)> {
            (0..n)
                .map(|i| {
                    let (r, c) = f(i);
                    // Corners at cell positions: the edge sits at the outer cell boundary.
                    (
                        c as f64 * self.dx,
                        r as f64 * self.dy,
                        self.at(r.min(rows - 1), c.min(cols - 1)),
                    )
                })
                .collect()
        };
        side(ras, &edge(&|i| (rows - 1, i), cols), (0.0, 1.0));
        side(ras, &edge(&|i| (0, i), cols), (0.0, -1.0));
        side(ras, &edge(&|i| (i, 0), rows), (-1.0, 0.0));
        side(ras, &edge(&|i| (i, cols - 1), rows), (1.0, 0.0));
    }

    /// Axes along the base's front (y = the map's height) and left edges, and a z scale bar
    /// at the front-left corner, as SVG in output pixels.
    fn overlay(&self, cam: &Camera) -> String {
        let (w_um, h_um) = (self.cols as f64 * self.dx, self.rows as f64 * self.dy);
        let (base_z, hi, ex) = (self.base_z, self.hi, self.ex);
        let mut overlay = String::new();
        let xs: Vec<(f64, (f64, f64))> = [0.0, 0.5, 1.0]
            .iter()
            .map(|f| (f * w_um, cam.px(f * w_um, h_um, base_z)))
            .collect();
        axis(
            &mut overlay,
            cam.px(0.0, h_um, base_z),
            cam.px(w_um, h_um, base_z),
            "x (µm)",
            &xs,
            (0.0, 16.0),
            "middle",
        );
        // y from the front-left corner (y = h_um, labelled by x) back to row 0 (y = 0).
        let ys: Vec<(f64, (f64, f64))> = [0.5, 0.0]
            .iter()
            .map(|f| (f * h_um, cam.px(0.0, f * h_um, base_z)))
            .collect();
        axis(
            &mut overlay,
            cam.px(0.0, h_um, base_z),
            cam.px(0.0, 0.0, base_z),
            "y (µm)",
            &ys,
            (-10.0, 10.0),
            "end",
        );
        // z: a bar of a round height, drawn at the exaggerated scale, labelled in true µm.
        let z_bar = round2((hi - self.lo) / 2.0);
        if z_bar.is_finite() && z_bar > 0.0 {
            let top = cam.px(0.0, h_um, hi * ex);
            let bottom = cam.px(0.0, h_um, hi * ex - z_bar * ex);
            let x = top.0 - 14.0;
            let _ = write!(
                overlay,
                "<line x1=\"{x:.1}\" y1=\"{:.1}\" x2=\"{x:.1}\" y2=\"{:.1}\" stroke=\"#222\" stroke-width=\"3\"/>\
                 <text x=\"{:.1}\" y=\"{:.1}\" class=\"tick\" text-anchor=\"end\">z {} µm</text>",
                top.1,
                bottom.1,
                x - 6.0,
                (top.1 + bottom.1) / 2.0 + 4.0,
                fixed(z_bar, if z_bar >= 10.0 { 0 } else { 2 })
            );
        }
        overlay
    }
}

/// One axis: a line from `a` to `b`, a dot and a label at each tick, the axis' name at its
/// middle. Tick labels sit outside the block: below the front (x) edge, left of the left (y)
/// edge, the two visible base edges; their shared corner is labelled once (by x).
fn axis(
    o: &mut String,
    a: (f64, f64),
    b: (f64, f64),
    label: &str,
    ticks_um: &[(f64, (f64, f64))],
    off: (f64, f64),
    anchor: &str,
) {
    let _ = write!(
        o,
        "<line x1=\"{:.1}\" y1=\"{:.1}\" x2=\"{:.1}\" y2=\"{:.1}\" stroke=\"#222\" stroke-width=\"1.5\"/>",
        a.0, a.1, b.0, b.1
    );
    for (v, p) in ticks_um {
        let _ = write!(
            o,
            "<circle cx=\"{:.1}\" cy=\"{:.1}\" r=\"2.5\" fill=\"#222\"/><text x=\"{:.1}\" y=\"{:.1}\" class=\"tick\" text-anchor=\"{anchor}\">{}</text>",
            p.0,
            p.1,
            p.0 + off.0,
            p.1 + off.1,
            fixed(*v, if *v >= 100.0 { 0 } else { 1 })
        );
    }
    let (mx, my) = ((a.0 + b.0) / 2.0, (a.1 + b.1) / 2.0);
    let _ = write!(
        o,
        "<text x=\"{:.1}\" y=\"{:.1}\" class=\"axis\" text-anchor=\"{anchor}\">{label}</text>",
        mx + 2.2 * off.0,
        my + 2.2 * off.1
    );
}

/// Box filter SS x SS down to the output size, 8-bit RGB.
fn box_filter(ras: &Raster) -> Vec<u8> {
    let w = ras.w;
    let mut out = vec![0u8; WIDTH * HEIGHT * 3];
    for y in 0..HEIGHT {
        for x in 0..WIDTH {
            for ch in 0..3 {
                let mut acc = 0.0f32;
                for sy in 0..SS {
                    for sx in 0..SS {
                        acc += ras.rgb[((y * SS + sy) * w + x * SS + sx) * 3 + ch];
                    }
                }
                out[(y * WIDTH + x) * 3 + ch] =
                    (acc / (SS * SS) as f32 * 255.0).round().clamp(0.0, 255.0) as u8;
            }
        }
    }
    out
}

/// The oblique view of `s` (see the module doc); `None` when there is nothing to draw (fewer
/// than 2 x 2 cells, no measured point, a flat surface).
pub fn render(s: &Surface) -> Option<Render> {
    let block = s.rows.max(s.cols).div_ceil(MAX_GRID).max(1);
    let (z, rows, cols) = block_mean(s, block);
    if rows < 2 || cols < 2 {
        return None;
    }
    let (dx, dy) = (s.pitch_x_um * block as f64, s.pitch_y_um * block as f64);
    let zf: Vec<f32> = z.iter().map(|&v| v as f32).collect();
    let (lo, hi) = robust_range_um(&zf)?;
    let (w_um, h_um) = (cols as f64 * dx, rows as f64 * dy);
    let ex = round2(RELIEF * w_um.max(h_um) / (hi - lo));
    if !(ex.is_finite() && ex > 0.0) {
        return None;
    }
    let base_z = (lo - 0.25 * (hi - lo)) * ex;
    let grid = ViewGrid {
        z,
        rows,
        cols,
        dx,
        dy,
        lo,
        hi,
        ex,
        base_z,
    };
    let cam = Camera::fitted(w_um, h_um, base_z, hi * ex);
    let (w, h) = (WIDTH * SS, HEIGHT * SS);
    let mut ras = Raster {
        w,
        h,
        rgb: vec![1.0; w * h * 3],
        depth: vec![f64::NEG_INFINITY; w * h],
    };
    grid.draw_surface(&mut ras, &cam);
    grid.draw_sides(&mut ras, &cam);
    let out = box_filter(&ras);
    Some(Render {
        png: png_rgb(&out, WIDTH, HEIGHT).ok()?,
        exaggeration: ex,
        grid: (rows, cols),
        block,
        overlay: grid.overlay(&cam),
    })
}

/// The section's figure.
pub fn figure(s: &Surface, what: &str) -> Option<String> {
    let r = render(s)?;
    let mut f = String::new();
    let _ = write!(
        f,
        "<figure class=\"wide\"><div style=\"position:relative;max-width:960px\">\
         <img class=\"zoomable view3d\" alt=\"3-D view of the {n}\" \
         data-title=\"3-D view of the {n}\" src=\"data:image/png;base64,{}\">\
         <svg viewBox=\"0 0 {WIDTH} {HEIGHT}\" style=\"position:absolute;left:0;top:0;width:100%;height:100%;pointer-events:none\">{overlay}</svg></div>\
         <figcaption>The {} ({} x {}, y x x), seen from its front edge (the maps' bottom edge: the last row, y largest; row 0 at the back) turned \
         {AZIMUTH_DEG}° and {ELEVATION_DEG}° above it; heights exaggerated <b>{} x</b>; \
         colours as in the maps (viridis over the 0.5 / 99.5 percentiles), shaded by a light \
         from the far left; grey: the base block. Drawn from a {} x {} grid{}. Static render, \
         click for full size.</figcaption></figure>",
        base64(&r.png),
        esc(what),
        length(s.height_um()),
        length(s.width_um()),
        fixed(r.exaggeration, if r.exaggeration < 10.0 { 1 } else { 0 }),
        r.grid.0,
        r.grid.1,
        if r.block * s.block > 1 {
            format!(" (block means of {0} x {0} points)", r.block * s.block)
        } else {
            String::new()
        },
        n = esc(s.name),
        overlay = r.overlay,
    );
    Some(f)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn renders_a_surface_with_colour_and_background() {
        let (rows, cols) = (40, 60);
        let z: Vec<f64> = (0..rows * cols)
            .map(|i| ((i % cols) as f64 * 0.3).sin() + ((i / cols) as f64 * 0.2).cos())
            .collect();
        let s = Surface {
            name: "pooled",
            z,
            rows,
            cols,
            pitch_x_um: 2.0,
            pitch_y_um: 2.0,
            block: 1,
            file_shape: (rows, cols),
        };
        let r = render(&s).expect("render");
        assert_eq!((r.grid, r.block), ((40, 60), 1));
        // Exaggeration: the colour range spans 5 % of 120 um.
        assert!(
            r.exaggeration > 1.0 && r.exaggeration < 20.0,
            "{}",
            r.exaggeration
        );
        let dec = png::Decoder::new(std::io::Cursor::new(&r.png));
        let mut reader = dec.read_info().expect("png");
        let mut buf = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut buf).expect("frame");
        assert_eq!((info.width, info.height), (WIDTH as u32, HEIGHT as u32));
        let px = |x: usize, y: usize| &buf[(y * WIDTH + x) * 3..(y * WIDTH + x) * 3 + 3];
        assert_eq!(px(2, 2), &[255, 255, 255], "background in the corner");
        let centre = px(WIDTH / 2, HEIGHT / 2);
        assert_ne!(centre, &[255, 255, 255], "the surface covers the centre");
        assert!(round2(13.456) == 13.0 && round2(0.0876) == 0.088);
    }
}
