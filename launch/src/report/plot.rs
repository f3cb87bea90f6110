//! A tiny SVG plotting helper for the report's charts: a panel with linear or log10 axes,
//! ticks, grid lines, axis labels and polylines. Coordinates are SVG user units.

use std::fmt::Write as _;

use super::html::{esc, fixed, path_d, ticks};

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
        let inside =
            |v: f64, a: &Axis| v.is_finite() && v >= a.lo && v <= a.hi && (!a.log || v > 0.0);
        let d = path_d(points.iter().map(|&(x, y)| {
            (inside(x, &self.xa) && inside(y, &self.ya)).then(|| (self.px(x), self.py(y)))
        }));
        let _ = write!(
            s,
            "<path d=\"{d}\" fill=\"none\" stroke=\"{colour}\" stroke-width=\"{width}\" \
             stroke-linejoin=\"round\"/>"
        );
    }

    /// A legend entry (colour swatch and text) at row `k` in the panel's top right corner.
    pub fn legend(&self, s: &mut String, k: usize, colour: &str, text: &str) {
        let x = self.x + self.w - 240.0;
        let y = self.y + 10.0 + 18.0 * k as f64;
        let _ = write!(
            s,
            "<rect x=\"{:.1}\" y=\"{:.1}\" width=\"240\" height=\"18\" fill=\"#fff\" \
             fill-opacity=\"0.85\"/><line x1=\"{:.1}\" y1=\"{:.1}\" x2=\"{:.1}\" y2=\"{:.1}\" \
             stroke=\"{colour}\" stroke-width=\"3\"/><text x=\"{:.1}\" y=\"{:.1}\" \
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
