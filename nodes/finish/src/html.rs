//! finish.html: a standalone page of one finishing run for a process engineer: the setting and
//! timings (from finish.json), the wear map and the surface before/after with axes in µm and
//! colour bars, the worn against the original profile with the removed depth along the row,
//! the Abbott-Firestone curves before/after with their difference and a zoom on the peaks, and
//! the parameters beside the paper's.
//!
//! The drawing helpers (escaping, ticks, the viridis colour map, the map PNG, the plot
//! panels) are [`surfstream_io::figure`]'s, the same as report.html's: one colour for one
//! normalised height, one tick algorithm, row 0 at the top.
//!
//! Every number comes from finish.json's typed record ([`FinishSummary`]), so a renamed field
//! fails to compile here. A field finish.json holds as null (absent, or a NaN that serde_json
//! writes as null) prints "–".

use std::fmt::Write as _;
use std::io::Write;
use std::path::Path;

use anyhow::{anyhow, Context, Result};
use base64::Engine;
use surfstream_io::figure::{self, esc, labelled_ticks, Axis, Panel};

use crate::field::ApproachDistribution;
use crate::run::SurfaceParams;
use surfstream_core::record::finish::{
    same_time_s, AbbottSummary, Baseline, Baselines, FinishSummary, SeriesPoint,
};

/// The paper's measured part before and after 5 min of finishing, um.
pub const PAPER_BEFORE: [(&str, f64); 3] = [("Sa", 1.272), ("Sq", 1.624), ("Sz", 15.262)];
pub const PAPER_AFTER: [(&str, f64); 3] = [("Sa", 0.565), ("Sq", 0.708), ("Sz", 6.162)];

const GREY: &str = "#9a9a9a";
const RED: &str = "#c0392b";
const BLUE: &str = "#1f5fa8";
const GREEN: &str = "#2e8b57";
const PURPLE: &str = "#7d3c98";
/// Colours of a sweep's settings, in order.
const SWEEP_COLOURS: [&str; 6] = [RED, BLUE, GREEN, PURPLE, "#d68910", "#117a65"];

#[allow(clippy::too_many_arguments)]
pub fn write_report(
    path: &Path,
    summary: &FinishSummary,
    original: &[f64],
    worn: &[f64],
    wear: &[f64],
    ideal_wear: Option<&[f64]>,
    rows: usize,
    cols: usize,
) -> Result<()> {
    let html = render(summary, original, worn, wear, ideal_wear, rows, cols)?;
    let mut f =
        std::fs::File::create(path).with_context(|| format!("{}: cannot write", path.display()))?;
    f.write_all(html.as_bytes())
        .with_context(|| format!("{}: write failed", path.display()))
}

/// The figures of one finishing run (inline PNG maps and SVG plots), shared by finish.html
/// and the run's report.html.
pub struct Figures {
    pub wear_map: String,
    pub original_map: String,
    pub worn_map: String,
    pub profile_svg: String,
    pub removed_svg: String,
    pub abbott_svg: String,
    pub abbott_peak_svg: String,
    pub abbott_diff_svg: String,
    /// Mean of original - worn - wear: the re-levelling shift of worn.npy, um.
    pub level_shift_um: f64,
}

/// The figures from finish.json (`summary`) and the patch's maps (rows x cols).
pub fn figures(
    summary: &FinishSummary,
    original: &[f64],
    worn: &[f64],
    wear: &[f64],
    rows: usize,
    cols: usize,
) -> Result<Figures> {
    let n = rows * cols;
    if original.len() != n || worn.len() != n || wear.len() != n {
        return Err(anyhow!(
            "finish.html: maps must hold rows x cols = {rows} x {cols} = {n} values \
             (original {}, worn {}, wear {})",
            original.len(),
            worn.len(),
            wear.len()
        ));
    }
    let patch = PatchMaps {
        original,
        worn,
        wear,
        rows,
        cols,
        pitch_um: (summary.setting.as_ref())
            .map(|st| st.patch.pitch_um[0])
            .filter(|p| *p > 0.0)
            .unwrap_or(1.0),
        profile_row: most_worn_row(wear, rows, cols),
    };
    let [wear_map, original_map, worn_map] = patch.maps()?;
    let level_shift_um = patch.level_shift_um();
    let [profile_svg, removed_svg] = patch.profiles();
    let [abbott_svg, abbott_peak_svg, abbott_diff_svg] = abbott_figures(summary, level_shift_um);
    Ok(Figures {
        wear_map,
        original_map,
        worn_map,
        profile_svg,
        removed_svg,
        abbott_svg,
        abbott_peak_svg,
        abbott_diff_svg,
        level_shift_um,
    })
}

/// The patch's maps (rows x cols, checked), their pitch and the row the profiles follow.
struct PatchMaps<'a> {
    original: &'a [f64],
    worn: &'a [f64],
    wear: &'a [f64],
    rows: usize,
    cols: usize,
    pitch_um: f64,
    profile_row: usize,
}

/// The profile row: the one that lost most material, so the worn line visibly departs from
/// the original (a middle row may not have been touched at all by the few passes).
fn most_worn_row(wear: &[f64], rows: usize, cols: usize) -> usize {
    (0..rows)
        .map(|r| {
            let v: f64 = wear[r * cols..(r + 1) * cols]
                .iter()
                .filter(|v| v.is_finite())
                .sum();
            (r, v)
        })
        .fold(
            (rows / 2, 0.0),
            |best, (r, v)| if v > best.1 { (r, v) } else { best },
        )
        .0
}

impl PatchMaps<'_> {
    /// The wear on its own scale, before and after on one shared height scale so the two are
    /// compared colour for colour.
    fn maps(&self) -> Result<[String; 3]> {
        let (rows, cols, pitch, mid) = (self.rows, self.cols, self.pitch_um, self.profile_row);
        let wear_max = finite_max(self.wear).max(0.0);
        let wear_map = map_figure(
            self.wear,
            rows,
            cols,
            pitch,
            (0.0, if wear_max > 0.0 { wear_max } else { 1.0 }),
            Ramp::Heat,
            "wear depth along z (µm)",
            mid,
        )?;
        let (h0, h1) = {
            let (a0, a1) = finite_range(self.original);
            let (b0, b1) = finite_range(self.worn);
            let (lo, hi) = (a0.min(b0), a1.max(b1));
            if lo < hi {
                (lo, hi)
            } else {
                (lo, lo + 1.0)
            }
        };
        let height = |z: &[f64]| {
            map_figure(
                z,
                rows,
                cols,
                pitch,
                (h0, h1),
                Ramp::Viridis,
                "height (µm)",
                mid,
            )
        };
        // In page order: the colour bars' gradient ids count up.
        let original_map = height(self.original)?;
        let worn_map = height(self.worn)?;
        Ok([wear_map, original_map, worn_map])
    }

    /// The mean of original - worn - wear: worn.npy is re-levelled, so original − worn carries
    /// this shift on top of the wear.
    fn level_shift_um(&self) -> f64 {
        let d: Vec<f64> = (0..self.rows * self.cols)
            .map(|k| self.original[k] - self.worn[k] - self.wear[k])
            .filter(|v| v.is_finite())
            .collect();
        if d.is_empty() {
            0.0
        } else {
            d.iter().sum::<f64>() / d.len() as f64
        }
    }

    /// Profiles along the profile row: the original drawn thick underneath so the worn line on
    /// top never hides it; the removed depth (from the wear map itself, without the levelling
    /// shift) in its own panel because it is ~100x smaller.
    fn profiles(&self) -> [String; 2] {
        let (cols, mid, pitch) = (self.cols, self.profile_row, self.pitch_um);
        let along = |z: &[f64]| -> Vec<(f64, f64)> {
            (0..cols)
                .map(|c| (c as f64 * pitch, z[mid * cols + c]))
                .collect()
        };
        let (prof_a, prof_b, removed) = (along(self.original), along(self.worn), along(self.wear));
        let profile_svg = Plot {
            title: format!("Profile along row {mid} (y = {:.1} µm)", mid as f64 * pitch),
            xlabel: "x (µm)",
            ylabel: "height (µm)",
            series: vec![
                Series::line(&prof_a, GREY, 4.0, "original"),
                Series::line(&prof_b, RED, 1.2, "worn"),
            ],
            ..Plot::default()
        }
        .svg();
        let removed_svg = Plot {
            title: "Removed depth along the same row".into(),
            xlabel: "x (µm)",
            ylabel: "wear depth along z (µm)",
            series: vec![Series::area(&removed, BLUE, "removed")],
            y_from_zero: true,
            height: 190.0,
            ..Plot::default()
        }
        .svg();
        [profile_svg, removed_svg]
    }
}

/// An Abbott-Firestone curve as (material ratio %, height um), thinned: finish.json holds
/// ~10^4 points; ~1000 draw the same curve and keep the page light.
fn abbott_points(a: &AbbottSummary) -> Vec<(f64, f64)> {
    let (mr, h) = (&a.material_ratio_pct, &a.height_um);
    let step = (mr.len() / 1000).max(1);
    mr.iter()
        .zip(h)
        .enumerate()
        .filter(|(k, _)| k % step == 0 || *k + 1 == mr.len())
        .filter_map(|(_, (&m, &h))| Some((finite(m)?, finite(h)?)))
        .collect()
}

/// Abbott-Firestone: the two curves differ by a fraction of a µm over a range of ~12 µm, so
/// the difference and a zoom on the peak region (material ratio 0-20 %) carry the message.
fn abbott_figures(summary: &FinishSummary, level_shift_um: f64) -> [String; 3] {
    let ab_before = abbott_points(&summary.abbott_before);
    let ab_after = abbott_points(&summary.abbott_after);
    let ab_diff: Vec<(f64, f64)> = ab_before
        .iter()
        .zip(&ab_after)
        // The levelling shift taken out, so untouched valleys read zero.
        .map(|(b, a)| (b.0, b.1 - a.1 - level_shift_um))
        .collect();
    let peak = |v: &[(f64, f64)]| -> Vec<(f64, f64)> {
        v.iter().copied().filter(|(m, _)| *m <= 20.0).collect()
    };
    let abbott_svg = Plot {
        title: "Abbott-Firestone curves".into(),
        xlabel: "material ratio (%)",
        ylabel: "height (µm)",
        series: vec![
            Series::line(&ab_before, GREY, 4.0, "before"),
            Series::dashed(&ab_after, RED, 1.6, "after"),
        ],
        ..Plot::default()
    }
    .svg();
    let (pb, pa) = (peak(&ab_before), peak(&ab_after));
    let abbott_peak_svg = Plot {
        title: "Zoom on the peak region (0-20 %)".into(),
        xlabel: "material ratio (%)",
        ylabel: "height (µm)",
        series: vec![
            Series::line(&pb, GREY, 4.0, "before"),
            Series::line(&pa, RED, 1.6, "after"),
        ],
        ..Plot::default()
    }
    .svg();
    let abbott_diff_svg = Plot {
        title: "Height removed at each material ratio".into(),
        xlabel: "material ratio (%)",
        ylabel: "before − after (µm)",
        series: vec![Series::line(&ab_diff, BLUE, 1.6, "before − after")],
        y_from_zero: true,
        ..Plot::default()
    }
    .svg();
    [abbott_svg, abbott_peak_svg, abbott_diff_svg]
}

/// The page as a string (the file writer above and the tests share it); `ideal_wear` is the
/// ideal model's predicted wear on the same patch, drawn beside the high-fidelity one.
pub fn render(
    summary: &FinishSummary,
    original: &[f64],
    worn: &[f64],
    wear: &[f64],
    ideal_wear: Option<&[f64]>,
    rows: usize,
    cols: usize,
) -> Result<String> {
    let Figures {
        wear_map,
        original_map,
        worn_map,
        profile_svg,
        removed_svg,
        abbott_svg,
        abbott_peak_svg,
        abbott_diff_svg,
        level_shift_um,
    } = figures(summary, original, worn, wear, rows, cols)?;
    let params = parameter_table(summary);
    let setting = setting_table(summary);
    let cycles = cycles_table(summary);
    let field = field_section(summary);
    let predictions = predictions_section(summary);
    let ideal_maps = ideal_maps(summary, wear, ideal_wear, rows, cols)?;
    let scales = scales_section(summary);
    let partial = summary.partial;
    let (sa_b, sa_a) = (finite(summary.before.sa), finite(summary.after.sa));
    let headline = match (sa_b, sa_a) {
        (Some(b), Some(a)) => format!(
            "Sa {b:.3} → {a:.3} µm ({:+.1} %) over {} of {} cycle(s) standing for {} s of process time.",
            if b != 0.0 { (a - b) / b * 100.0 } else { 0.0 },
            summary.cycles_completed,
            summary.cycles_requested,
            num(summary.setting.as_ref().map(|st| st.process_time_s), 0),
        ),
        _ => "No roughness parameters in finish.json.".into(),
    };

    let mut html = String::new();
    write!(
        html,
        "<!doctype html><html><head><meta charset=\"utf-8\"><title>surfstream finish</title>\
<style>body{{font-family:sans-serif;margin:24px;color:#222}}\
table{{border-collapse:collapse;margin:6px 0 18px}}\
td,th{{border:1px solid #ccc;padding:3px 8px;text-align:right;font-size:13px}}\
td.k,th.k{{text-align:left}}td.t{{text-align:left;color:#555;max-width:360px}}\
.row{{display:flex;gap:22px;flex-wrap:wrap;align-items:flex-start;margin-bottom:18px}}\
figure{{margin:0;width:min-content}}figcaption{{font-size:13px;color:#555}}\
h2{{margin-top:26px;border-bottom:1px solid #ddd}}.warn{{color:#b03a00}}\
svg .tick{{font-size:11px;fill:#222}}svg .axis{{font-size:12px;fill:#111}}svg .grid{{stroke:#e4e4e4;stroke-width:1}}</style></head><body>\
<h1>Finishing simulation{}</h1><p><b>{}</b> Model: {}.</p>",
        if partial {
            " <span class=\"warn\">(partial: stopped early)</span>"
        } else {
            ""
        },
        headline,
        esc(&summary.model),
    )
    .ok();
    write!(
        html,
        "<h2>Setting, timings and checks</h2><div class=\"row\">{setting}</div>{scales}\
<h2>Wear and surface maps</h2><div class=\"row\">\
<figure>{wear_map}<figcaption>Wear depth along z (Finnie) over the patch, µm. \
The dashed line marks the profile row below (the row that lost most). Row 0 at the top.</figcaption></figure>\
<figure>{original_map}<figcaption>Surface before finishing (levelled patch), µm.</figcaption></figure>\
<figure>{worn_map}<figcaption>Worn surface after the last cycle, same colour scale as before.</figcaption></figure></div>\
<h2>Profile</h2><div class=\"row\"><figure>{profile_svg}<figcaption>Original (thick grey, underneath) \
and worn (thin red, on top): where the wear is small the red line runs inside the grey one.</figcaption></figure>\
<figure>{removed_svg}<figcaption>Depth removed along the same row (the wear map's row), µm. \
The worn surface is re-levelled after wear, so original − worn differs from this by \
{level_shift_um:+.4} µm everywhere.</figcaption></figure></div>\
<h2>Abbott-Firestone curves</h2><div class=\"row\">\
<figure>{abbott_svg}<figcaption>Before (thick grey) and after (dashed red).</figcaption></figure>\
<figure>{abbott_peak_svg}<figcaption>The peak region, where finishing acts first.</figcaption></figure>\
<figure>{abbott_diff_svg}<figcaption>Height lost at each material ratio: large at the left (peaks), \
zero at the right (valleys). The worn surface is re-levelled after wear; that shift \
({level_shift_um:+.4} µm) is taken out here.</figcaption></figure></div>\
<h2>Roughness parameters (µm, Ssk/Sku dimensionless, Smr %)</h2>\
<table><tr><th class=\"k\">param</th><th>before</th><th>predicted after</th><th>change</th>\
<th>paper before</th><th>paper after (5 min)</th></tr>{params}</table>\
{predictions}{ideal_maps}\
<h2>Contact field and calibration</h2>{field}\
<h2>Cycles</h2>{cycles}</body></html>"
    )
    .ok();
    Ok(html)
}

/// The two scales: the macro run's contacts on the part (what the prediction's rates and the
/// micro passes' samples come from), the patch model the micro passes ran on, which path the
/// cycles took, and how measured scans were registered.
fn scales_section(s: &FinishSummary) -> String {
    let mut h = String::from("<h2>The machine (macro run) and the patch model (micro passes)</h2>");
    if let Some(p) = &s.cycle_path {
        let _ = write!(h, "<p>Cycles: {}.</p>", esc(p));
    }
    let mut row = String::from("<div class=\"row\">");
    match &s.macro_run {
        Some(m) => {
            let c = &m.contacts;
            let pct = |name: &str, p: &crate::machine::Percentiles, unit: &str, dp: usize| {
                format!(
                    "<tr><td class=\"k\">{name}, {unit}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
                    num(p.p10, dp),
                    num(p.p50, dp),
                    num(p.p90, dp)
                )
            };
            let _ = write!(
                row,
                "<table><tr><th class=\"k\" colspan=\"4\">Macro run ({}, {}): {} media, {} s recorded after {} s settling, dt {:.2e} s{}</th></tr>\
<tr><th class=\"k\">contacts on the part's central region ({} mm²)</th><th>p10</th><th>p50</th><th>p90</th></tr>{}{}{}{}{}\
<tr><td class=\"k\">contacts (impacts / enduring)</td><td colspan=\"3\">{} ({} / {}), {} per mm² and s</td></tr>\
<tr><td class=\"k\">sliding work, J/(mm² s)</td><td colspan=\"3\">{:.3e}</td></tr>\
<tr><td class=\"k\">impact energy, J/(mm² s)</td><td colspan=\"3\">{:.3e}</td></tr>\
<tr><td class=\"k\">softened media keep</td><td class=\"t\" colspan=\"3\">{}</td></tr>\
<tr><td class=\"k\">not kept (from the micro passes)</td><td class=\"t\" colspan=\"3\">{}</td></tr>\
<tr><td class=\"k\">engine</td><td colspan=\"3\">{} s on {} rank(s), {:.2e} s per particle-step</td></tr></table>",
                esc(&m.engine),
                esc(&m.machine),
                m.media_count,
                num(m.simulated_s, 2),
                num(m.settle_s, 2),
                m.timestep_s,
                if m.partial { " <span class=\"warn\">(partial)</span>" } else { "" },
                num(m.region_area_mm2, 1),
                pct("normal speed", &c.normal_speed_m_s, "m/s", 4),
                pct("tangential speed", &c.tangential_speed_m_s, "m/s", 4),
                pct("normal force", &c.normal_force_n, "N", 4),
                pct("impact approach speed", &c.impact_normal_speed_m_s, "m/s", 4),
                pct("enduring contacts' force", &c.enduring_normal_force_n, "N", 4),
                c.count,
                c.impacts,
                c.enduring,
                num(c.rate_per_mm2_s, 3),
                c.sliding_work_j_per_mm2_s,
                c.impact_energy_j_per_mm2_s,
                esc(&m.softening.trusted.join("; ")),
                esc(&m.softening.not_trusted.join("; ")),
                num(m.cost.engine_s, 1),
                m.cost.ranks,
                m.cost.per_particle_step_s,
            );
        }
        None => row.push_str(
            "<p>No macro run (<code>--no-macro</code>): the rates are the barrel kinematics' assumptions.</p>",
        ),
    }
    if let Some(p) = &s.patch {
        let m = &p.model;
        let _ = write!(
            row,
            "<table><tr><th class=\"k\" colspan=\"2\">Patch model (first cycle)</th></tr>\
<tr><td class=\"k\">mesher</td><td class=\"t\">{}</td></tr>\
<tr><td class=\"k\">surface triangles</td><td>{}</td></tr>\
<tr><td class=\"k\">max |mesh − measured| / Sq</td><td>{} ({} µm; Sq {} µm)</td></tr>\
<tr><td class=\"k\">RMS error, µm</td><td>{}</td></tr>\
<tr><td class=\"k\">judged by</td><td class=\"t\">{}</td></tr>\
<tr><td class=\"k\">tolerance met (Sa, Sq, Sz and the pointwise bound per region)</td><td>{}</td></tr>\
<tr><td class=\"k\">smallest angle, °</td><td>{}</td></tr>\
<tr><td class=\"k\">LIGGGHTS curvature, °</td><td>{}</td></tr></table>",
            esc(&m.mesher),
            m.surface_triangles,
            num(m.max_error_over_sq, 3),
            num(m.max_error_um, 4),
            num(m.sq_um, 4),
            num(m.rms_error_um, 4),
            esc(if m.fidelity.is_empty() {
                "the mesher's (above)"
            } else {
                &m.fidelity
            }),
            m.tolerance_met.map_or("not judged".into(), |t| if t {
                "yes".to_string()
            } else {
                "no".to_string()
            }),
            num(m.min_angle_deg, 2),
            num(m.curvature_deg, 1),
        );
    }
    for r in &s.after_registrations {
        let _ = write!(
            row,
            "<table><tr><th class=\"k\" colspan=\"2\">Measured scan ({}) registered to the model</th></tr>\
<tr><td class=\"k\">file</td><td class=\"t\">{}</td></tr>\
<tr><td class=\"k\">offset, µm (x, y)</td><td>{}, {}</td></tr>\
<tr><td class=\"k\">NCC</td><td>{}</td></tr>\
<tr><td class=\"k\">model covered</td><td>{} %</td></tr></table>",
            esc(&r.role),
            esc(&r.source),
            num(r.offset_um[0], 2),
            num(r.offset_um[1], 2),
            num(r.ncc, 3),
            num(r.covered_fraction * 100.0, 1),
        );
    }
    row.push_str("</div>");
    h + &row
}

/// A finite number (finish.json writes NaN and infinities as null, which reads as absent).
fn finite(x: impl Into<Option<f64>>) -> Option<f64> {
    x.into().filter(|x| x.is_finite())
}

/// A number with `dp` decimals, or "–" when absent.
fn num(x: impl Into<Option<f64>>, dp: usize) -> String {
    finite(x).map_or_else(|| "–".to_string(), |x| format!("{x:.dp$}"))
}

/// A number in scientific notation, or "–".
fn sci(x: impl Into<Option<f64>>) -> String {
    finite(x).map_or_else(|| "–".to_string(), |x| format!("{x:.3e}"))
}

/// A text, count or flag, escaped, or "–" when absent.
fn text(v: Option<impl std::fmt::Display>) -> String {
    v.map_or_else(|| "–".into(), |v| esc(&v.to_string()))
}

/// The setting (media, action, patch, wear model), the timings and the checks as tables.
fn setting_table(s: &FinishSummary) -> String {
    format!("{}{}", setting_rows(s), timing_rows(s))
}

/// A row of the setting's tables: name, value, note.
fn row(k: &str, v: String, note: String) -> String {
    format!("<tr><td class=\"k\">{k}</td><td>{v}</td><td class=\"t\">{note}</td></tr>")
}

/// The cycles' acceleration factor: one value, or its range when the cycles differ.
fn acceleration_factors(s: &FinishSummary) -> String {
    let factors: Vec<f64> = s
        .cycles
        .iter()
        .filter_map(|c| finite(c.acceleration_factor))
        .collect();
    match (
        factors.iter().cloned().reduce(f64::min),
        factors.iter().cloned().reduce(f64::max),
    ) {
        (Some(lo), Some(hi)) if (hi - lo).abs() <= 1e-9 * hi.abs() => format!("{lo:.0}"),
        (Some(lo), Some(hi)) => format!("{lo:.0} – {hi:.0} (per cycle below)"),
        _ => "–".into(),
    }
}

/// The setting's table: media, action, patch, cycles, wear constants.
fn setting_rows(s: &FinishSummary) -> String {
    let st = s.setting.as_ref();
    let m = st.map(|st| &st.media);
    let a = st.map(|st| &st.action);
    let p = st.map(|st| &st.patch);
    let mut left = String::from("<table><tr><th class=\"k\" colspan=\"3\">Setting</th></tr>");
    left += &row(
        "media",
        format!(
            "{} mm, {} kg/m³",
            num(m.map(|m| m.diameter_mm), 2),
            num(m.map(|m| m.density_kg_m3), 0)
        ),
        format!(
            "E {} Pa, ν {}, restitution {}, friction {}",
            sci(m.map(|m| m.youngs_modulus_pa)),
            num(m.map(|m| m.poisson_ratio), 2),
            num(m.map(|m| m.restitution), 2),
            num(m.map(|m| m.friction), 2)
        ),
    );
    // With a macro run the passes draw its contacts: the barrel's assumed speed and pressure
    // are shown as what they are, not as the run's.
    let assumed = st.is_some_and(|st| !st.action_used);
    if let Some(st) = st.filter(|st| !st.contacts_from.is_empty()) {
        left += &row("contacts", "drawn".into(), esc(&st.contacts_from));
    }
    left += &row(
        if assumed {
            "media velocity (assumed, not used)"
        } else {
            "media velocity"
        },
        format!("{} m/s", num(a.map(|a| a.media_velocity_m_s), 3)),
        format!(
            "impact angle {}°; {}",
            num(a.map(|a| a.impact_angle_deg), 1),
            text(a.map(|a| &a.source))
        ),
    );
    left += &row(
        if assumed {
            "pressure (assumed, not used)"
        } else {
            "pressure"
        },
        format!("{} Pa", num(a.map(|a| a.pressure_pa), 0)),
        format!(
            "acceleration {} m/s²; press force on the patch {} N",
            num(a.map(|a| a.acceleration_m_s2), 1),
            num(st.map(|st| st.press_force_n), 4)
        ),
    );
    left += &row(
        "patch",
        format!(
            "{} × {} µm",
            num(p.map(|p| p.size_um[0]), 1),
            num(p.map(|p| p.size_um[1]), 1)
        ),
        format!(
            "{} × {} samples at {} µm; guard band {} µm; {}",
            num(p.map(|p| p.rows_cols[0] as f64), 0),
            num(p.map(|p| p.rows_cols[1] as f64), 0),
            num(p.map(|p| p.pitch_um[0]), 4),
            num(p.map(|p| p.guard_band_um), 1),
            text(p.map(|p| &p.boundary))
        ),
    );
    left += &row(
        "cycles",
        format!("{} of {}", s.cycles_completed, s.cycles_requested),
        format!(
            "process time {} s; time budget {} s; {} MPI rank(s)",
            num(st.map(|st| st.process_time_s), 0),
            num(st.map(|st| st.time_budget_s), 0),
            text(st.map(|st| st.ranks))
        ),
    );
    left += &row(
        "k (Finnie)",
        format!("{} 1/Pa", sci(st.map(|st| st.k_finnie_per_pa))),
        format!(
            "Archard K/H {} 1/Pa; {}",
            sci(st.map(|st| st.archard_k_over_h_per_pa)),
            text(st.map(|st| &st.wear_depth))
        ),
    );
    left += &row(
        "acceleration factor",
        acceleration_factors(s),
        text(st.map(|st| &st.acceleration)),
    );
    left += "</table>";
    left
}

/// The timings' and checks' table: engine and own time, volume check, calibration, SIM, wear.
fn timing_rows(s: &FinishSummary) -> String {
    let t = &s.timings;
    let mut right =
        String::from("<table><tr><th class=\"k\" colspan=\"3\">Timings and checks</th></tr>");
    right += &row(
        "engine (LIGGGHTS)",
        format!("{} s", num(t.engine_s, 1)),
        format!(
            "wall time; CPU {} s; {} s simulated",
            num(t.engine_cpu_s, 1),
            sci(t.simulated_s)
        ),
    );
    right += &row(
        "surfstream overhead",
        format!("{} s", num(t.surfstream_overhead_s, 1)),
        format!(
            "{} % of the engine's time (meshing, mapping, writing)",
            finite(t.overhead_share_of_engine)
                .map_or("–".into(), |x| format!("{:.1}", x * 100.0))
        ),
    );
    right += &row(
        "total",
        format!("{} s", num(t.total_s, 1)),
        match (
            finite(t.engine_s),
            finite(s.probe.as_ref().map(|p| p.engine_s)),
        ) {
            (Some(_), Some(pr)) => format!("includes a cost probe of {pr:.1} s"),
            _ => String::new(),
        },
    );
    let vc = s.volume_check.as_ref();
    right += &row(
        "volume check",
        sci(vc.map(|v| v.relative_error)),
        text(vc.map(|v| &v.what)),
    );
    right += &calibration_row(s);
    right += &row(
        "SIM between the ideal and high-fidelity predictions",
        num(s.ideal_model.as_ref().and_then(|i| i.sim_predictions), 3),
        format!(
            "paper's eq. 12 between the predicted wear maps of the two models (first cycle's DEM maps: {}); not against the real part",
            num(s.ideal_model.as_ref().and_then(|i| i.sim_wear_maps), 3)
        ),
    );
    let sim = s.sim.as_ref();
    right += &row(
        "SIM Finnie vs Archard",
        num(sim.and_then(|s| s.finnie_vs_archard), 3),
        format!(
            "SIM predicted worn vs measured after-finish scan (--after): {}",
            num(sim.and_then(|s| s.worn_vs_measured_after), 3)
        ),
    );
    let w = s.wear.as_ref();
    right += &row(
        "wear",
        format!("{} µm³", num(w.map(|w| w.finnie_volume_um3), 0)),
        format!(
            "max depth {} µm, mean {} µm",
            num(w.map(|w| w.max_depth_um), 3),
            num(w.map(|w| w.mean_depth_um), 4)
        ),
    );
    right += "</table>";
    right
}

/// The calibration's row: its kind, the target against the Sa reached, the fitted k.
fn calibration_row(s: &FinishSummary) -> String {
    let Some(cal) = &s.calibration else {
        return row("calibration", "none".into(), "k as given".into());
    };
    let short = match (finite(cal.target_sa_um), finite(s.after.sa)) {
        (Some(tg), Some(g)) if g > tg * 1.02 => {
            " <span class=\"warn\">(short of the target)</span>"
        }
        _ => "",
    };
    row(
        "calibration",
        esc(&cal.kind),
        format!(
            "target Sa {} µm, reached {} µm{short}; fitted k {} 1/Pa",
            num(cal.target_sa_um, 3),
            num(s.after.sa, 3),
            sci(cal.k_finnie_fitted_per_pa)
        ),
    )
}

fn cycles_table(s: &FinishSummary) -> String {
    if s.cycles.is_empty() {
        return "<p>No completed cycle.</p>".into();
    }
    let mut t = String::from(
        "<table><tr><th>cycle</th><th>passes</th><th>simulated (s)</th><th>engine (s)</th>\
<th>triangles</th><th>acceleration factor</th><th>k equivalent (1/Pa)</th><th>Sa after (µm)</th>\
<th>Spk after (µm)</th><th>volume check</th></tr>",
    );
    for c in &s.cycles {
        write!(
            t,
            "<tr><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td>\
<td>{}</td><td>{}</td><td>{}</td></tr>",
            c.cycle,
            c.passes,
            sci(c.simulated_s),
            num(c.engine_s, 1),
            c.triangles,
            num(c.acceleration_factor, 0),
            sci(c.k_finnie_equivalent_per_pa),
            num(c.after.sa, 3),
            num(c.after.spk, 3),
            sci(c.volume_check.relative_error),
        )
        .ok();
    }
    t += "</table>";
    t
}

/// The contact-field model's calibration (finish.json `calibration`, `contact_field`): the
/// fit, how well the contact field predicts where the DEM wore, and the wear-per-contact
/// table.
pub fn field_section(s: &FinishSummary) -> String {
    let mut t = format!(
        "<p>Wear model: <b>{}</b>.</p>",
        text(s.wear_model.as_deref())
    );
    if let Some(c) = &s.calibration {
        write!(
            t,
            "<table><tr><th class=\"k\">calibration</th><th>value</th></tr>\
<tr><td class=\"k\">target Sa (µm)</td><td>{}</td></tr>\
<tr><td class=\"k\">predicted Sa (µm)</td><td>{}</td></tr>\
<tr><td class=\"k\">relative error (tolerance ±{} %)</td><td>{}</td></tr>\
<tr><td class=\"k\">reached</td><td>{}</td></tr>\
<tr><td class=\"k\">fitted k_finnie (1/Pa)</td><td>{}</td></tr>\
<tr><td class=\"k\">fitted scale (× DEM k)</td><td>{}</td></tr></table>",
            num(c.target_sa_um, 4),
            num(c.sa_after_um, 4),
            num(c.tolerance_percent, 0),
            finite(c.relative_error).map_or("–".into(), |e| format!("{:+.2} %", e * 100.0)),
            text(c.reached),
            sci(c.k_finnie_fitted_per_pa),
            sci(c.fit.as_ref().map(|f| f.scale)),
        )
        .ok();
    }
    let Some(f) = &s.contact_field else {
        return t;
    };
    let m = &f.check_mean;
    let ap = f.approach.as_ref();
    let (approach_label, approach_values) = match ap {
        Some(ApproachDistribution::MacroSamples(sa)) => (
            "approach of the macro run's contacts p10 / p50 / p90 / max (µm)",
            format!(
                "{} / {} / {} / {}",
                num(sa.p10_um, 4),
                num(sa.p50_um, 4),
                num(sa.p90_um, 4),
                num(sa.max_um, 4)
            ),
        ),
        Some(ApproachDistribution::Kinematics(k)) => (
            "largest / mean-angle / static approach (µm, kinematics)",
            format!(
                "{} / {} / {}",
                num(k.full_speed_approach_um, 3),
                num(k.mean_angle_approach_um, 3),
                num(k.static_approach_um, 3)
            ),
        ),
        None => ("approach (µm)", "–".to_string()),
    };
    write!(
        t,
        "<table><tr><th class=\"k\">contact field</th><th>value</th></tr>\
<tr><td class=\"k\">ball radius (µm)</td><td>{}</td></tr>\
<tr><td class=\"k\">{}</td><td>{}</td></tr>\
<tr><td class=\"k\">reach below the envelope / step depth (µm)</td><td>{} / {}</td></tr>\
<tr><td class=\"k\">the envelope's Sa / Sq before (what reach-limited wear tends to, µm)</td><td>{} / {}</td></tr>\
<tr><td class=\"k\">impacts over the process on the patch</td><td>{}</td></tr>\
<tr><td class=\"k\">DEM impacts (all cycles)</td><td>{}</td></tr>\
<tr><td class=\"k\">AUC: the gap ranks the DEM's worn cells (mean of cycles)</td><td>{}</td></tr>\
<tr><td class=\"k\">DEM wear volume within reach</td><td>{}</td></tr>\
<tr><td class=\"k\">cells within reach / worn by the DEM</td><td>{} / {}</td></tr>\
<tr><td class=\"k\">cells worn after the process</td><td>{}</td></tr></table>",
        num(f.ball_radius_um, 0),
        approach_label,
        approach_values,
        num(f.reach_um, 3),
        num(f.step_depth_um, 3),
        num(f.envelope.as_ref().map(|e| e.sa_um), 3),
        num(f.envelope.as_ref().map(|e| e.sq_um), 3),
        num(f.impacts_over_process, 0),
        f.table.impacts,
        num(m.auc_gap_predicts_worn, 3),
        num(m.dem_volume_within_reach, 3),
        num(m.cells_within_reach, 3),
        num(m.dem_worn_cells, 3),
        num(f.worn_cells_after, 3),
    )
    .ok();
    t += "<table><tr><th>gap from (µm)</th><th>to</th><th>cells</th><th>expected contacts</th>\
<th>DEM worn cells</th><th>DEM depth sum (µm)</th><th>wear per contact measured (µm, DEM k)</th>\
<th>used (pooled: *)</th></tr>";
    for b in &f.table.bins {
        write!(
            t,
            "<tr><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}{}</td></tr>",
            num(b.gap_from_um, 3),
            num(b.gap_to_um, 3),
            b.cells,
            num(b.expected_contacts, 1),
            b.dem_worn_cells,
            num(b.dem_depth_sum_um, 4),
            sci(b.measured_wear_per_contact_um),
            sci(b.wear_per_contact_um),
            if b.pooled { " *" } else { "" },
        )
        .ok();
    }
    t += "</table>";
    if f.table.pooled_bins > 0 {
        write!(
            t,
            "<p class=\"note\">* {} of {} bins pooled with a neighbour so that the depth worn per impact \
does not rise with the gap (the contact field's own model: a contact that reaches a cell reaches every \
shallower cell deeper); the pooling keeps the DEM's volume.</p>",
            f.table.pooled_bins,
            f.table.bins.len()
        )
        .ok();
    }
    t
}

/// A series point's parameters for the page's plots and tables.
type SeriesParameter = (&'static str, fn(&SeriesPoint) -> f64);
const SERIES_PARAMETERS: [SeriesParameter; 6] = [
    ("Sa", |p| p.sa),
    ("Sq", |p| p.sq),
    ("Sz", |p| p.sz),
    ("Spk", |p| p.spk),
    ("Svk", |p| p.svk),
    ("Sk", |p| p.sk),
];

/// (time in min, value) of a series.
fn curve(points: &[SeriesPoint], f: fn(&SeriesPoint) -> f64) -> Vec<(f64, f64)> {
    points.iter().map(|p| (p.time_s / 60.0, f(p))).collect()
}

/// The predictions versus process time (finish.json `series`), the no-DEM baselines beside
/// them with the prediction's noise, what was fitted, and the sweep's settings.
pub fn predictions_section(s: &FinishSummary) -> String {
    if s.series.is_empty() {
        return "<h2>Predictions</h2><p>No prediction (the sampled map, no completed cycle, or stopped).</p>".into();
    }
    let mut h = String::from("<h2>Predictions versus process time</h2>");
    let fitted = if s.fitted.is_empty() {
        "nothing (the constants as given)".to_string()
    } else {
        s.fitted
            .iter()
            .map(|f| esc(f))
            .collect::<Vec<_>>()
            .join(", ")
    };
    if let Some(l) = &s.wear_laws {
        write!(
            h,
            "<p>Wear laws: Finnie for impacts at {} per m² and s, Archard for sliding at {} J/(m² s) (the impacts removed {:.1} % of the volume); rates from {}. One scale on both laws: {} ({}). <b>Fitted</b>: {fitted}. Every other number on this page is a <b>prediction</b> or an input.</p>",
            sci(l.impact_rate_per_m2_s),
            sci(l.sliding_work_j_per_m2_s),
            l.impact_share_of_volume * 100.0,
            esc(&l.rates_from),
            sci(l.scale),
            esc(&l.scale_is),
        )
        .ok();
    }
    let base = s.baselines.as_ref();
    // Sa, Sq, Sz versus time: the prediction, the two baselines.
    let mut plots = String::from("<div class=\"row\">");
    for (name, f) in &SERIES_PARAMETERS[..3] {
        let pred = curve(&s.series, *f);
        let cw = base
            .map(|b| curve(&b.constant_wear.series, *f))
            .unwrap_or_default();
        let pl = base
            .map(|b| curve(&b.plateau.series, *f))
            .unwrap_or_default();
        let mut series = vec![Series::line(&pred, RED, 2.0, "prediction (DEM)")];
        if base.is_some() {
            series.push(Series::dashed(&cw, BLUE, 1.5, "constant wear"));
            series.push(Series::dashed(&pl, GREEN, 1.5, "plateau cut"));
        }
        let svg = Plot {
            title: format!("{name} versus process time"),
            xlabel: "process time (min)",
            ylabel: "µm",
            series,
            ..Plot::default()
        }
        .svg();
        write!(plots, "<figure>{svg}</figure>").ok();
    }
    plots += "</div>";
    h += &plots;
    h += "<table><tr><th>time (s)</th>";
    for (name, _) in SERIES_PARAMETERS {
        write!(h, "<th>{name} (µm)</th>").ok();
    }
    h += "<th class=\"k\">label</th></tr>";
    for p in &s.series {
        write!(h, "<tr><td>{}</td>", num(p.time_s, 0)).ok();
        for (name, f) in SERIES_PARAMETERS {
            let mark = if p.fitted.iter().any(|x| x == name) {
                " (fitted)"
            } else {
                ""
            };
            write!(h, "<td>{}{mark}</td>", num(f(p), 3)).ok();
        }
        write!(
            h,
            "<td class=\"k\">{}</td></tr>",
            if p.fitted.is_empty() {
                "prediction".to_string()
            } else {
                format!("prediction; {} fitted", p.fitted.join(", "))
            }
        )
        .ok();
    }
    h += "</table>";
    if let Some(b) = base {
        h += &baselines_table(s, b);
    }
    h += &sweep_plots(s);
    h
}

/// The prediction after the process time beside both baselines and the paper, with the
/// noise and where the prediction is within it of a baseline.
fn baselines_table(s: &FinishSummary, b: &Baselines) -> String {
    let mut h = String::from(
        "<h3>What the DEM adds: the no-DEM baselines at the same Sa</h3>\
<table><tr><th class=\"k\">after the process time</th><th>prediction (DEM)</th>\
<th>constant wear</th><th>plateau cut</th><th>noise of the prediction</th><th>paper after (5 min)</th></tr>",
    );
    let noise = b.noise.as_ref();
    type Row = (&'static str, fn(&SurfaceParams) -> f64, Option<f64>);
    let rows: [Row; 6] = [
        ("Sa", |p| p.sa, None),
        ("Sq", |p| p.sq, noise.map(|n| n.sq)),
        ("Sz", |p| p.sz, noise.map(|n| n.sz)),
        ("Spk", |p| p.spk, noise.map(|n| n.spk)),
        ("Svk", |p| p.svk, noise.map(|n| n.svk)),
        ("Sk", |p| p.sk, noise.map(|n| n.sk)),
    ];
    for (name, f, n) in rows {
        let paper = PAPER_AFTER
            .iter()
            .find(|(k, _)| *k == name)
            .map_or(String::new(), |(_, v)| format!("{v:.3}"));
        let within = |list: &[String]| {
            if list.iter().any(|x| x == name) {
                " ≈"
            } else {
                ""
            }
        };
        write!(
            h,
            "<tr><td class=\"k\">{name} (µm)</td><td>{}</td><td>{}{}</td><td>{}{}</td><td>{}</td><td>{paper}</td></tr>",
            num(f(&s.after), 3),
            num(f(&b.constant_wear.after), 3),
            within(&b.constant_wear.within_noise),
            num(f(&b.plateau.after), 3),
            within(&b.plateau.within_noise),
            n.map_or("–".into(), |v| format!("± {v:.3}")),
        )
        .ok();
    }
    h += "</table>";
    h += &at_calibration_time(s, b);
    let say = |what: &str, base: &Baseline| -> String {
        let list = &base.within_noise;
        if !base.reached {
            return format!(
                "{what} <b>did not reach</b> the prediction's Sa at the calibration time (its fit stalls: a constant rate within a reach that covers almost every cell lowers the surface without smoothing it); its column is not at the same Sa. "
            );
        }
        if noise.is_none() {
            format!("{what}: no noise estimate (one cycle: no second DEM sample). ")
        } else if list.is_empty() {
            format!("{what}: the prediction differs from it by more than the noise in every parameter. ")
        } else {
            format!(
                "{what}: the prediction is <b>within noise</b> of it in {} (≈): there the DEM adds nothing measurable. ",
                list.join(", ")
            )
        }
    };
    write!(
        h,
        "<p>{}{}Constant wear: {} (fitted {} = {}). Plateau: {} (fitted {} = {}). Noise: {}.</p>",
        say("Constant wear", &b.constant_wear),
        say("Plateau cut", &b.plateau),
        esc(&b.constant_wear.what),
        esc(&b.constant_wear.fitted_parameter),
        sci(b.constant_wear.fitted_value),
        esc(&b.plateau.what),
        esc(&b.plateau.fitted_parameter),
        num(b.plateau.fitted_value, 4),
        noise.map_or("–".into(), |n| esc(&n.from)),
    )
    .ok();
    h
}

/// The prediction and both baselines at the calibration time (where all three have the same
/// Sa) beside the paper's part after 5 min, when the calibration time is not the process
/// time (else the table above is that).
fn at_calibration_time(s: &FinishSummary, b: &Baselines) -> String {
    let Some(t) = s.wear_laws.as_ref().map(|l| l.calibration_time_s) else {
        return String::new();
    };
    let at = |series: &[SeriesPoint]| SeriesPoint::at(series, t).cloned();
    let last = s.series.last().map(|p| p.time_s);
    let (Some(p), Some(c), Some(q)) = (
        at(&s.series),
        at(&b.constant_wear.series),
        at(&b.plateau.series),
    ) else {
        return String::new();
    };
    if last.is_some_and(|l| same_time_s(l, t)) {
        return String::new();
    }
    let mut h = format!(
        "<table><tr><th class=\"k\">at the calibration time, {t:.0} s</th><th>prediction (DEM)</th>\
<th>constant wear</th><th>plateau cut</th><th>paper after (5 min)</th></tr>"
    );
    for (name, f) in &SERIES_PARAMETERS {
        let paper = PAPER_AFTER
            .iter()
            .find(|(k, _)| k == name)
            .map_or(String::new(), |(_, v)| format!("{v:.3}"));
        let mark = if p.fitted.iter().any(|x| x == name) {
            " (fitted)"
        } else {
            ""
        };
        write!(
            h,
            "<tr><td class=\"k\">{name} (µm)</td><td>{}{mark}</td><td>{}</td><td>{}</td><td>{paper}</td></tr>",
            num(f(&p), 3),
            num(f(&c), 3),
            num(f(&q), 3)
        )
        .ok();
    }
    h += "</table>";
    h
}

/// Sa, Sq, Sz versus time for each setting of a sweep (one calibration, on the base).
fn sweep_plots(s: &FinishSummary) -> String {
    let Some(sw) = &s.sweep else {
        return String::new();
    };
    let mut h = format!(
        "<h3>Sweep of {}: one calibration, every setting predicted</h3><p>{}</p><div class=\"row\">",
        esc(&sw.parameter),
        esc(&sw.note)
    );
    let labels: Vec<String> = sw
        .settings
        .iter()
        .map(|st| {
            format!(
                "{} = {}{}",
                sw.parameter,
                st.value,
                if st.calibrated_here {
                    " (calibrated)"
                } else {
                    ""
                }
            )
        })
        .collect();
    for (name, f) in &SERIES_PARAMETERS[..3] {
        let curves: Vec<Vec<(f64, f64)>> =
            sw.settings.iter().map(|st| curve(&st.series, *f)).collect();
        let series = curves
            .iter()
            .zip(&labels)
            .enumerate()
            .map(|(k, (c, l))| Series::line(c, SWEEP_COLOURS[k % SWEEP_COLOURS.len()], 2.0, l))
            .collect();
        let svg = Plot {
            title: format!("{name} versus process time"),
            xlabel: "process time (min)",
            ylabel: "µm",
            series,
            ..Plot::default()
        }
        .svg();
        write!(h, "<figure>{svg}</figure>").ok();
    }
    write!(
        h,
        "</div><table><tr><th class=\"k\">setting</th><th>Sa at {:.0} s (µm)</th><th>Sa noise there (tables)</th><th>macro counting noise (floor)</th><th>Sa after the process</th><th>Sq</th><th>Sz</th><th class=\"k\">folder</th></tr>",
        sw.compared_at_s
    )
    .ok();
    for (st, l) in sw.settings.iter().zip(&labels) {
        write!(
            h,
            "<tr><td class=\"k\">{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td class=\"k\">{}</td></tr>",
            esc(l),
            num(st.sa_compared_um, 3),
            st.sa_noise_um.map_or("none (one cycle)".to_string(), |n| num(n, 3)),
            st.sa_macro_noise_um.map_or("none".to_string(), |n| num(n, 3)),
            num(st.after.sa, 3),
            num(st.after.sq, 3),
            num(st.after.sz, 3),
            esc(&st.dir)
        )
        .ok();
    }
    h += "</table>";
    if !sw.verdict.is_empty() {
        write!(
            h,
            "<p><b>Told apart?</b> {} (a setting's Sa noise: its odd and even cycles' DEM tables' predictions at the same constants, and the macro run's counting noise |dSa/dt| t / sqrt(impacts), a floor since media contacts cluster; a pair is apart when its difference exceeds both settings' noises added in quadrature).</p>",
            esc(&sw.verdict)
        )
        .ok();
    }
    h
}

/// The paper's comparison: the high-fidelity and the ideal model's predicted wear maps side
/// by side, on one colour scale, with the SIM between them named as what it is.
fn ideal_maps(
    s: &FinishSummary,
    wear: &[f64],
    ideal_wear: Option<&[f64]>,
    rows: usize,
    cols: usize,
) -> Result<String> {
    let (Some(iw), Some(run)) = (ideal_wear, s.ideal_model.as_ref()) else {
        return Ok(String::new());
    };
    if iw.len() != rows * cols {
        return Err(anyhow!(
            "finish.html: the ideal model's wear map holds {} values, expected {rows} x {cols}",
            iw.len()
        ));
    }
    let pitch = s
        .setting
        .as_ref()
        .map(|st| st.patch.pitch_um[0])
        .filter(|p| *p > 0.0)
        .unwrap_or(1.0);
    let hi = finite_max(wear).max(finite_max(iw)).max(1e-12);
    let a = map_figure(
        wear,
        rows,
        cols,
        pitch,
        (0.0, hi),
        Ramp::Heat,
        "wear depth along z (µm)",
        rows / 2,
    )?;
    let b = map_figure(
        iw,
        rows,
        cols,
        pitch,
        (0.0, hi),
        Ramp::Heat,
        "wear depth along z (µm)",
        rows / 2,
    )?;
    let measured = s.sim.as_ref().and_then(|x| x.worn_vs_measured_after);
    Ok(format!(
        "<h2>The paper's comparison: ideal (datum) and high-fidelity model in the same setting</h2>\
<div class=\"row\"><figure>{a}<figcaption>High-fidelity model: predicted wear over the process.</figcaption></figure>\
<figure>{b}<figcaption>Ideal (form-only) model: predicted wear, same laws, rates and scale.</figcaption></figure></div>\
<p>SIM between the ideal and high-fidelity predictions: <b>{}</b> (between their first cycle's DEM maps: {}). \
SIM against a measured after-finish scan: {}.</p>",
        num(run.sim_predictions, 3),
        num(run.sim_wear_maps, 3),
        measured.map_or("none given (--after FILE)".into(), |m| format!("{m:.3} (the predicted worn surface vs the scan)")),
    ))
}

/// A parameter's name and its field in [`SurfaceParams`].
type Parameter = (&'static str, fn(&SurfaceParams) -> f64);

/// The parameters of the page's table, in its order.
const PARAMETERS: [Parameter; 13] = [
    ("Sa", |p| p.sa),
    ("Sq", |p| p.sq),
    ("Sz", |p| p.sz),
    ("Sp", |p| p.sp),
    ("Sv", |p| p.sv),
    ("Sk", |p| p.sk),
    ("Spk", |p| p.spk),
    ("Svk", |p| p.svk),
    ("Ssk", |p| p.ssk),
    ("Sku", |p| p.sku),
    ("Smr1", |p| p.smr1),
    ("Smr2", |p| p.smr2),
    ("Sdq", |p| p.sdq),
];

pub fn parameter_table(s: &FinishSummary) -> String {
    let mut out = String::new();
    let sa_fitted = s
        .series
        .last()
        .is_some_and(|p| p.fitted.iter().any(|f| f == "Sa"));
    for (key, field) in PARAMETERS {
        let b = finite(field(&s.before));
        let a = finite(field(&s.after));
        if b.is_none() && a.is_none() {
            continue;
        }
        let paper = |t: &[(&str, f64)]| {
            t.iter()
                .find(|(k, _)| *k == key)
                .map_or(String::new(), |(_, v)| format!("{v:.3}"))
        };
        let change = match (b, a) {
            // Shape parameters near zero: a relative change means nothing, give the difference.
            (Some(b), Some(a)) if matches!(key, "Ssk" | "Sku") => format!("{:+.3}", a - b),
            (Some(b), Some(a)) if b.abs() > 1e-12 => format!("{:+.1} %", (a - b) / b * 100.0),
            _ => "–".into(),
        };
        write!(
            out,
            "<tr><td class=\"k\">{key}</td><td>{}</td><td>{}</td><td>{change}</td><td>{}</td><td>{}</td></tr>",
            b.map_or("–".into(), |v| format!("{v:.3}")),
            a.map_or("–".into(), |v| format!(
                "{v:.3}{}",
                if key == "Sa" && sa_fitted { " (fitted)" } else { "" }
            )),
            paper(&PAPER_BEFORE),
            paper(&PAPER_AFTER)
        )
        .ok();
    }
    out
}

fn finite_max(z: &[f64]) -> f64 {
    z.iter()
        .cloned()
        .filter(|v| v.is_finite())
        .fold(f64::MIN, f64::max)
}

fn finite_range(z: &[f64]) -> (f64, f64) {
    let lo = z
        .iter()
        .cloned()
        .filter(|v| v.is_finite())
        .fold(f64::MAX, f64::min);
    let hi = finite_max(z);
    if lo <= hi {
        (lo, hi)
    } else {
        (0.0, 1.0)
    }
}

#[derive(Clone, Copy)]
enum Ramp {
    /// Dark blue -> orange -> pale yellow: zero wear dark, deep wear bright.
    Heat,
    /// Heights: viridis, the colour map of every height map ([`figure::viridis`]).
    Viridis,
}

impl Ramp {
    fn rgb(self, t: f64) -> [u8; 3] {
        let t = t.clamp(0.0, 1.0);
        match self {
            Ramp::Heat => [
                (30.0 + 225.0 * t.sqrt()) as u8,
                (30.0 + 200.0 * t) as u8,
                (80.0 * (1.0 - t) + 60.0 * t * t) as u8,
            ],
            Ramp::Viridis => figure::viridis(t),
        }
    }
}

/// `z` (lo .. hi) through `ramp` as an indexed PNG at full resolution, row 0 at the top;
/// non-finite samples in the not-measured grey ([`figure::NAN_RGB`]).
fn map_png(z: &[f64], rows: usize, cols: usize, lo: f64, hi: f64, ramp: Ramp) -> Result<Vec<u8>> {
    let z32: Vec<f32> = z.iter().map(|&v| v as f32).collect();
    let m =
        figure::encode_map_png_with(&z32, rows, cols, rows.max(cols), (lo, hi), |t| ramp.rgb(t))?;
    Ok(m.png)
}

/// A map as SVG: the image with x/y axes in µm, a dashed marker on `mark_row` and a colour bar
/// with its ticks and unit.
#[allow(clippy::too_many_arguments)]
fn map_figure(
    z: &[f64],
    rows: usize,
    cols: usize,
    pitch_um: f64,
    (lo, hi): (f64, f64),
    ramp: Ramp,
    unit_label: &str,
    mark_row: usize,
) -> Result<String> {
    let png = map_png(z, rows, cols, lo, hi, ramp)?;
    let b64 = base64::engine::general_purpose::STANDARD.encode(png);
    let (ml, mt, mb) = (52.0, 12.0, 44.0);
    let side = 264.0;
    let (iw, ih) = if cols >= rows {
        (side, side * rows as f64 / cols.max(1) as f64)
    } else {
        (side * cols as f64 / rows.max(1) as f64, side)
    };
    let (cbx, cbw) = (ml + iw + 18.0, 16.0);
    let w = cbx + cbw + 72.0;
    let h = mt + ih + mb;
    let (wx, wy) = (cols as f64 * pitch_um, rows as f64 * pitch_um);
    let mut s = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w:.0}\" height=\"{h:.0}\" font-size=\"11\">\
<image x=\"{ml}\" y=\"{mt}\" width=\"{iw:.1}\" height=\"{ih:.1}\" preserveAspectRatio=\"none\" \
style=\"image-rendering:pixelated\" href=\"data:image/png;base64,{b64}\"/>\
<rect x=\"{ml}\" y=\"{mt}\" width=\"{iw:.1}\" height=\"{ih:.1}\" fill=\"none\" stroke=\"#444\"/>"
    );
    let my = mt + (mark_row as f64 + 0.5) / rows.max(1) as f64 * ih;
    write!(
        s,
        "<line x1=\"{ml}\" x2=\"{:.1}\" y1=\"{my:.1}\" y2=\"{my:.1}\" stroke=\"#fff\" stroke-width=\"1.2\" stroke-dasharray=\"5 4\"/>",
        ml + iw
    )
    .ok();
    for (v, label) in labelled_ticks(0.0, wx, 5) {
        let x = ml + v / wx * iw;
        write!(
            s,
            "<line x1=\"{x:.1}\" x2=\"{x:.1}\" y1=\"{:.1}\" y2=\"{:.1}\" stroke=\"#444\"/>\
<text x=\"{x:.1}\" y=\"{:.1}\" text-anchor=\"middle\">{}</text>",
            mt + ih,
            mt + ih + 4.0,
            mt + ih + 15.0,
            label
        )
        .ok();
    }
    // Row 0 at the top: y grows downwards from 0 at the top edge.
    for (v, label) in labelled_ticks(0.0, wy, 5) {
        let y = mt + v / wy * ih;
        write!(
            s,
            "<line x1=\"{:.1}\" x2=\"{ml}\" y1=\"{y:.1}\" y2=\"{y:.1}\" stroke=\"#444\"/>\
<text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"end\">{}</text>",
            ml - 4.0,
            ml - 6.0,
            y + 4.0,
            label
        )
        .ok();
    }
    write!(
        s,
        "<text class=\"xaxis\" x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"middle\" font-size=\"12\">x (µm)</text>\
<text class=\"yaxis\" x=\"14\" y=\"{:.1}\" text-anchor=\"middle\" font-size=\"12\" transform=\"rotate(-90 14 {:.1})\">y (µm)</text>",
        ml + iw / 2.0,
        h - 8.0,
        mt + ih / 2.0,
        mt + ih / 2.0
    )
    .ok();
    // Colour bar: a vertical gradient, low at the bottom.
    let id = format!(
        "cb{}",
        COLORBAR_ID.fetch_add(1, std::sync::atomic::Ordering::Relaxed)
    );
    s += &format!(
        "<defs><linearGradient id=\"{id}\" x1=\"0\" y1=\"1\" x2=\"0\" y2=\"0\">{}",
        figure::gradient_stops(|t| ramp.rgb(t))
    );
    write!(
        s,
        "</linearGradient></defs><g class=\"colorbar\"><rect x=\"{cbx:.1}\" y=\"{mt}\" width=\"{cbw}\" height=\"{ih:.1}\" \
fill=\"url(#{id})\" stroke=\"#444\"/>"
    )
    .ok();
    for (v, label) in labelled_ticks(lo, hi, 5) {
        let y = mt + ih - (v - lo) / (hi - lo) * ih;
        write!(
            s,
            "<line x1=\"{:.1}\" x2=\"{:.1}\" y1=\"{y:.1}\" y2=\"{y:.1}\" stroke=\"#444\"/>\
<text x=\"{:.1}\" y=\"{:.1}\">{}</text>",
            cbx + cbw,
            cbx + cbw + 4.0,
            cbx + cbw + 6.0,
            y + 4.0,
            label
        )
        .ok();
    }
    let lx = cbx + cbw + 50.0;
    let ly = mt + ih / 2.0;
    write!(
        s,
        "<text x=\"{lx:.1}\" y=\"{ly:.1}\" text-anchor=\"middle\" font-size=\"12\" \
transform=\"rotate(-90 {lx:.1} {ly:.1})\">{unit_label}</text></g></svg>"
    )
    .ok();
    Ok(s)
}

/// Distinct gradient ids when several maps share the page.
static COLORBAR_ID: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);

/// A named series of a line chart.
struct Series<'a> {
    points: &'a [(f64, f64)],
    color: &'a str,
    width: f64,
    dash: bool,
    fill: bool,
    label: &'a str,
}

impl<'a> Series<'a> {
    fn line(points: &'a [(f64, f64)], color: &'a str, width: f64, label: &'a str) -> Self {
        Series {
            points,
            color,
            width,
            dash: false,
            fill: false,
            label,
        }
    }
    fn dashed(points: &'a [(f64, f64)], color: &'a str, width: f64, label: &'a str) -> Self {
        Series {
            dash: true,
            ..Series::line(points, color, width, label)
        }
    }
    fn area(points: &'a [(f64, f64)], color: &'a str, label: &'a str) -> Self {
        Series {
            fill: true,
            ..Series::line(points, color, 1.2, label)
        }
    }
}

/// A line chart with ticked axes, grid and legend.
struct Plot<'a> {
    title: String,
    xlabel: &'a str,
    ylabel: &'a str,
    series: Vec<Series<'a>>,
    /// Include y = 0 in the range (for differences and depths).
    y_from_zero: bool,
    width: f64,
    height: f64,
}

impl Default for Plot<'_> {
    fn default() -> Self {
        Plot {
            title: String::new(),
            xlabel: "",
            ylabel: "",
            series: Vec::new(),
            y_from_zero: false,
            width: 440.0,
            height: 270.0,
        }
    }
}

impl Plot<'_> {
    /// The chart on a [`Panel`] of the shared figure helpers (the axes, lines, areas and
    /// legend report.html's charts draw with).
    fn svg(&self) -> String {
        let (w, h) = (self.width, self.height);
        // The left margin holds the tick labels and the y label (52 px left of the panel).
        let (ml, mr, mt, mb) = (72.0, 14.0, 26.0, 42.0);
        let (pw, ph) = (w - ml - mr, h - mt - mb);
        let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
        for &(x, y) in self.series.iter().flat_map(|s| s.points.iter()) {
            if x.is_finite() && y.is_finite() {
                x0 = x0.min(x);
                x1 = x1.max(x);
                y0 = y0.min(y);
                y1 = y1.max(y);
            }
        }
        if x0 > x1 {
            (x0, x1, y0, y1) = (0.0, 1.0, 0.0, 1.0);
        }
        if self.y_from_zero {
            y0 = y0.min(0.0);
            y1 = y1.max(0.0);
        }
        if x0 >= x1 {
            x1 = x0 + 1.0;
        }
        if y0 >= y1 {
            y1 = y0 + 1.0;
        }
        let pad = (y1 - y0) * 0.04;
        let panel = Panel {
            x: ml,
            y: mt,
            w: pw,
            h: ph,
            xa: Axis::linear(x0, x1, self.xlabel),
            ya: Axis::linear(y0 - pad, y1 + pad, self.ylabel),
        };
        let mut s = format!(
            "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" font-size=\"11\">\
<text x=\"{ml}\" y=\"16\" font-size=\"13\" font-weight=\"bold\">{}</text>",
            esc(&self.title)
        );
        panel.axes(&mut s, true);
        panel.zero_line(&mut s);
        const DASH: &str = "6 4";
        for ser in &self.series {
            if ser.fill {
                panel.area(&mut s, ser.points, ser.color, 0.3);
            }
            panel.line_styled(
                &mut s,
                ser.points,
                ser.color,
                ser.width,
                ser.dash.then_some(DASH),
            );
        }
        // The legend box as wide as its longest label (about 6.5 px a character at 11 px).
        let legend_w = (self.series.iter())
            .map(|ser| 40.0 + 6.5 * ser.label.chars().count() as f64)
            .fold(90.0, f64::max)
            .min(pw);
        for (k, ser) in self.series.iter().enumerate() {
            let dash = ser.dash.then_some(DASH);
            panel.legend_styled(&mut s, k, ser.color, ser.label, dash, legend_w);
        }
        s.push_str("</svg>");
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::example::{minimal, summary, typed};

    fn page(summary: &FinishSummary, rows: usize, cols: usize) -> String {
        let original: Vec<f64> = (0..rows * cols)
            .map(|k| ((k % cols) as f64 * 0.3).sin() * 2.0)
            .collect();
        // Wear only on peaks above 1 um: the removed-depth panel and the Abbott difference
        // must come out non-zero at the peaks.
        let wear: Vec<f64> = original.iter().map(|&h| (h - 1.0).max(0.0) * 0.5).collect();
        let worn: Vec<f64> = original.iter().zip(&wear).map(|(h, w)| h - w).collect();
        render(summary, &original, &worn, &wear, None, rows, cols).expect("page renders")
    }

    #[test]
    fn the_page_has_axes_colour_bars_and_the_setting_table() {
        let html = page(&summary(), 30, 40);
        // Three maps (wear, before, worn), each with a colour bar and µm axes.
        assert_eq!(html.matches("<g class=\"colorbar\">").count(), 3);
        assert_eq!(html.matches("<image ").count(), 3);
        assert!(
            html.matches(">x (µm)</text>").count() >= 5,
            "maps and profiles carry x in µm"
        );
        assert_eq!(html.matches(">y (µm)</text>").count(), 3);
        assert!(html.contains(">wear depth along z (µm)</text>"));
        assert_eq!(html.matches(">height (µm)</text>").count(), 2 + 1 + 2);
        // The x axis of a 40-column map at 0.5 um pitch ends at 20 um: ticks 0, 5, .., 20.
        assert!(html.contains(">20</text>") && html.contains(">15</text>"));
        // Distinct gradient ids, each referenced.
        let ids: std::collections::BTreeSet<&str> = html
            .match_indices("linearGradient id=\"")
            .map(|(k, m)| {
                let rest = &html[k + m.len()..];
                &rest[..rest.find('"').unwrap()]
            })
            .collect();
        assert_eq!(ids.len(), 3);
        for id in &ids {
            assert!(html.contains(&format!("url(#{id})")));
        }
        // The setting and timings from finish.json.
        for needle in [
            "3.00 mm, 2500 kg/m³",
            "1.618 m/s",
            "3997 Pa",
            "20.0 × 15.0 µm",
            "30 × 40 samples at 0.5000 µm",
            "2 of 3",
            "1 MPI rank(s)",
            "1.000e-10 1/Pa",
            "37760 – 97096",
            "314.4 s",
            "9.6 s",
            "3.1 % of the engine",
            "2.700e-14",
            "target Sa 0.584 µm, reached 1.269 µm",
            "short of the target",
            "9.010e-17",
            "partial",
            "includes a cost probe of 1.5 s",
            "<td>0.031</td>",
            "first cycle's DEM maps: 0.025",
            "SIM predicted worn vs measured after-finish scan (--after): –",
            "120 µm³",
            "<td>1.300</td><td>1.200</td>",
        ] {
            assert!(html.contains(needle), "page lacks {needle:?}");
        }
        // Both profiles and the removed depth, the Abbott before/after, the difference, the zoom.
        for needle in [
            ">original</text>",
            ">worn</text>",
            "wear depth along z (µm)",
            ">before</text>",
            ">after</text>",
            "before − after (µm)",
            "Zoom on the peak region",
        ] {
            assert!(html.contains(needle), "page lacks {needle:?}");
        }
        // The original is drawn first and thicker so the worn line cannot hide it.
        let grey = html
            .find(&format!("stroke=\"{GREY}\" stroke-width=\"4\""))
            .unwrap();
        let red = html
            .find(&format!("stroke=\"{RED}\" stroke-width=\"1.2\""))
            .unwrap();
        assert!(grey < red);
    }

    #[test]
    fn predictions_are_labelled_beside_their_baselines_and_the_sweep_is_plotted() {
        let s = crate::example::predicted();
        let (rows, cols) = (8, 8);
        let ideal = vec![0.1; rows * cols];
        let original = vec![0.0; rows * cols];
        let html = render(
            &s,
            &original,
            &original,
            &original,
            Some(&ideal),
            rows,
            cols,
        )
        .unwrap();
        for needle in [
            "Predictions versus process time",
            "<b>Fitted</b>: calibration.fit.scale, series[time_s = calibration time].Sa",
            "Sa versus process time",
            "Sq versus process time",
            "Sz versus process time",
            ">prediction (DEM)</text>",
            ">constant wear</text>",
            ">plateau cut</text>",
            "<td>0.740 (fitted)</td>",
            "prediction; Sa fitted",
            "within noise</b> of it in Sq",
            "Plateau cut: the prediction differs from it by more than the noise",
            "± 0.050",
            // The parameter table's after column: Sa fitted (the calibration holds at the end).
            "<td class=\"k\">Sa</td><td>1.316</td><td>0.740 (fitted)</td>",
            "Sweep of revolution-rpm",
            ">revolution-rpm = 300 (calibrated)</text>",
            ">revolution-rpm = 200</text>",
            "SIM between the ideal and high-fidelity predictions: <b>0.031</b>",
            "none given (--after FILE)",
        ] {
            assert!(html.contains(needle), "page lacks {needle:?}");
        }
        // Five predicted times, each labelled; the high-fidelity and ideal maps side by side.
        assert_eq!(html.matches("<td class=\"k\">prediction").count(), 5);
        assert!(html.contains("Ideal (form-only) model: predicted wear"));
        assert!(!html.contains("did not reach"));
        // A baseline whose fit stalled short of the prediction's Sa says so, not "same Sa".
        let mut stalled = s.clone();
        if let Some(b) = &mut stalled.baselines {
            b.constant_wear.reached = false;
        }
        let html = render(&stalled, &original, &original, &original, None, rows, cols).unwrap();
        assert!(html.contains("Constant wear <b>did not reach</b> the prediction's Sa"));
        assert!(!html.contains("Constant wear: the prediction"));
        // An older record's sweep has no noise: said in its column, no verdict claimed.
        let html = render(&s, &original, &original, &original, None, rows, cols).unwrap();
        assert!(html.contains("<td>none (one cycle)</td>"));
        assert!(!html.contains("Told apart?"));
        // With each setting's Sa noise, the page says which settings the DEM tells apart.
        let mut told = s.clone();
        if let Some(sw) = &mut told.sweep {
            sw.settings
                .iter_mut()
                .for_each(|st| st.sa_noise_um = Some(0.05));
            for (st, sa) in sw.settings.iter_mut().zip([0.9, 0.74]) {
                st.sa_compared_um = Some(sa);
            }
            // The macro run's counting noise has its own column and joins the pair's noise.
            sw.settings[0].sa_macro_noise_um = Some(0.0123);
            (sw.comparisons, sw.verdict) =
                crate::sweep::compare_settings(&sw.parameter, &sw.settings, 300.0, 1.3, None);
        }
        let html = render(&told, &original, &original, &original, None, rows, cols).unwrap();
        assert!(
            html.contains("<b>Told apart?</b> every pair of settings of revolution-rpm differs in Sa at 300 s by more than its noise: 200 vs 300 (-0.160 um, noise 0.072)"),
            "{}",
            &html[html.find("Sweep of").unwrap_or(0)..]
        );
        assert!(
            html.contains("<td>0.012</td>"),
            "the macro counting noise has a column"
        );
    }

    /// Issue 39: file names are escaped with the shared helper, quotes included, so a `"` in
    /// a name cannot end an attribute or a tag.
    #[test]
    fn a_quote_in_a_file_name_is_escaped() {
        let mut s = summary();
        s.model = "scans/part \"A\" <1>.x3p".into();
        let html = page(&s, 8, 8);
        assert!(
            html.contains("scans/part &quot;A&quot; &lt;1&gt;.x3p"),
            "the model's name escaped"
        );
        assert!(!html.contains("part \"A\""), "no raw quote from the name");
    }

    /// Issue 39: the height maps are viridis from the shared table (palette entry i is
    /// viridis(i / 254), the not-measured entry the shared grey), the colour bar its stops.
    #[test]
    fn height_maps_use_the_shared_viridis() {
        let html = page(&summary(), 8, 8);
        // The second map (before) is a height map.
        let pngs: Vec<Vec<u8>> = html
            .match_indices("data:image/png;base64,")
            .map(|(k, m)| {
                let rest = &html[k + m.len()..];
                base64::engine::general_purpose::STANDARD
                    .decode(&rest[..rest.find('"').unwrap()])
                    .unwrap()
            })
            .collect();
        assert_eq!(pngs.len(), 3);
        let dec = png::Decoder::new(std::io::Cursor::new(&pngs[1]));
        let reader = dec.read_info().unwrap();
        let palette = reader.info().palette.clone().unwrap().to_vec();
        for i in [0usize, 77, 127, 254] {
            assert_eq!(
                palette[i * 3..i * 3 + 3],
                figure::viridis(i as f64 / 254.0),
                "{i}"
            );
        }
        assert_eq!(palette[255 * 3..], figure::NAN_RGB);
        assert!(html.contains(&figure::gradient_stops(figure::viridis)));
    }

    #[test]
    fn a_summary_without_a_setting_or_calibration_still_renders() {
        let s = typed(minimal());
        let html = page(&s, 8, 8);
        assert!(html.contains("<g class=\"colorbar\">"));
        assert!(html.contains("calibration"));
        assert!(html.contains("No completed cycle."));
        assert!(
            html.contains("<td>– mm, – kg/m³</td>"),
            "absent setting as –"
        );
        assert!(render(&s, &[0.0; 3], &[0.0; 4], &[0.0; 4], None, 2, 2).is_err());
    }

    #[test]
    fn a_number_finish_json_holds_as_null_prints_as_absent() {
        // serde_json writes NaN as null: the page shows the same "–" for the value in memory
        // (process.rs renders the record) as for the file read back (the launcher's report).
        let mut s = summary();
        s.timings.engine_cpu_s = f64::NAN;
        s.after.spk = f64::NAN;
        let html = page(&s, 8, 8);
        assert!(!html.contains("NaN"), "NaN printed");
        assert!(html.contains("wall time; CPU – s"));
        assert!(html.contains("<td class=\"k\">Spk</td><td>1.510</td><td>–</td><td>–</td>"));
    }
}

#[cfg(test)]
mod rerender {
    /// Re-renders finish.html of an existing run: FINISH_OUT=DIR cargo test -- --ignored rerender
    #[test]
    #[ignore]
    fn rerender_an_out_dir() {
        let dir = std::path::PathBuf::from(std::env::var("FINISH_OUT").expect("FINISH_OUT"));
        let s =
            surfstream_core::record::finish::FinishSummary::read(&dir.join("finish.json")).unwrap();
        let rd = |f: &str| surfstream_io::npy::read_npy_f64(dir.join(f)).unwrap();
        let (o, w, f) = (rd("original.npy"), rd("worn.npy"), rd("wear.npy"));
        let ideal = dir
            .join("wear_ideal.npy")
            .is_file()
            .then(|| rd("wear_ideal.npy").data);
        let out = std::path::PathBuf::from(std::env::var("FINISH_HTML").expect("FINISH_HTML"));
        super::write_report(
            &out,
            &s,
            &o.data,
            &w.data,
            &f.data,
            ideal.as_deref(),
            o.rows,
            o.cols,
        )
        .unwrap();
    }
}
