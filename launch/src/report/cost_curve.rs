//! The fidelity-cost curve of the model (issue 22): every mesh the mesher's tolerance search
//! made, triangles against the worst Sa / Sq / Sz deviation and the worst pointwise residual
//! over the regions, the chosen mesh marked, with what each costs a DEM step in LIGGGHTS.

use std::fmt::Write as _;

use surfstream_core::record::{CurvePointRecord, MeshReport, RunRecord};

use super::html::esc;
use surfstream_io::figure::{Axis, Panel};

/// LIGGGHTS' cost of one mesh triangle per time step, us: measured with the Debian
/// `liggghts` 3.8 binary on this project's machine (docs/model.md gives the command and the
/// runs: a particle bed settling on an ASCII STL sheet, two mesh sizes, the difference in time
/// per step divided by the difference in triangles).
pub const LIGGGHTS_US_PER_TRIANGLE_STEP: f64 = 0.022;

const COLOURS: [(&str, &str); 3] = [("Sa", "#1f77b4"), ("Sq", "#2ca02c"), ("Sz", "#d62728")];
/// The roughness the mesh carries (mesh - datum), when the mesher judged it.
const ROUGHNESS_COLOUR: &str = "#ff7f0e";

/// The section, or nothing when the mesher made no curve.
pub fn section(run: &RunRecord) -> String {
    let Some(t) = run.stage::<MeshReport>().and_then(|m| m.tolerance) else {
        return String::new();
    };
    let pts: Vec<(f64, [f64; 4], bool, &CurvePointRecord)> = (t.curve.iter())
        .map(|c| {
            (
                c.surface_triangles as f64,
                [
                    c.worst_sa_pct.abs(),
                    c.worst_sq_pct.abs(),
                    c.worst_sz_pct.abs(),
                    c.worst_residual_pct_of_sq,
                ],
                c.chosen,
                c,
            )
        })
        .filter(|p| p.0 > 0.0)
        .collect();
    if pts.is_empty() {
        return String::new();
    }
    let tol = &t.tolerance;
    let limits = [tol.sa_pct, tol.sq_pct, tol.sz_pct];
    // The worst roughness deviation per mesh, and its limit, when the search judged it.
    let roughness: Vec<(f64, f64)> = pts
        .iter()
        .filter_map(|p| p.3.worst_roughness_pct.map(|r| (p.0, r.abs())))
        .collect();
    let roughness_limit = tol.roughness_pct.filter(|_| !roughness.is_empty());
    let (lo, hi) = pts.iter().fold((f64::INFINITY, 0.0f64), |(a, b), p| {
        (a.min(p.0), b.max(p.0))
    });
    let dev_hi = pts
        .iter()
        .flat_map(|p| p.1[..3].iter().copied())
        .chain(limits)
        .chain(roughness.iter().map(|r| r.1))
        .chain(roughness_limit)
        .filter(|v| v.is_finite())
        .fold(0.0f64, f64::max);
    let res_hi = pts
        .iter()
        .map(|p| p.1[3])
        .chain(tol.residual_pct)
        .filter(|v| v.is_finite())
        .fold(0.0f64, f64::max);
    let top = Panel {
        x: 86.0,
        y: 14.0,
        w: 760.0,
        h: 250.0,
        xa: Axis::log(lo, hi, "surface triangles"),
        ya: Axis::linear(0.0, (dev_hi * 1.1).max(0.5), "worst |deviation| (%)"),
    };
    let bottom = Panel {
        y: 290.0,
        h: 150.0,
        ya: Axis::linear(0.0, (res_hi * 1.1).max(1.0), "residual (% of Sq)"),
        ..top_clone(&top)
    };
    let mut g = String::from(
        "<svg class=\"chart\" viewBox=\"0 0 880 500\" role=\"img\" aria-label=\"fidelity-cost curve\">",
    );
    top.axes(&mut g, false);
    bottom.axes(&mut g, true);
    for (k, (name, colour)) in COLOURS.iter().enumerate() {
        let line: Vec<(f64, f64)> = pts.iter().map(|p| (p.0, p.1[k])).collect();
        top.line(&mut g, &line, colour, 2.0);
        for &(x, y) in &line {
            dot(&mut g, &top, x, y, colour);
        }
        dashed(&mut g, &top, limits[k], colour);
        top.legend(
            &mut g,
            k,
            colour,
            &format!("worst |{name}| (dashed: tolerance {} %)", limits[k]),
        );
    }
    if let Some(limit) = roughness_limit {
        top.line(&mut g, &roughness, ROUGHNESS_COLOUR, 2.0);
        for &(x, y) in &roughness {
            dot(&mut g, &top, x, y, ROUGHNESS_COLOUR);
        }
        dashed(&mut g, &top, limit, ROUGHNESS_COLOUR);
        top.legend(
            &mut g,
            COLOURS.len(),
            ROUGHNESS_COLOUR,
            &format!("worst |roughness| (dashed: {limit} %)"),
        );
    }
    let res: Vec<(f64, f64)> = pts.iter().map(|p| (p.0, p.1[3])).collect();
    if let Some(limit) = tol.residual_pct {
        dashed(&mut g, &bottom, limit, "#6c3483");
    }
    bottom.line(&mut g, &res, "#6c3483", 2.0);
    for &(x, y) in &res {
        dot(&mut g, &bottom, x, y, "#6c3483");
    }
    if let Some(c) = pts.iter().find(|p| p.2) {
        let x = top.px(c.0);
        let _ = write!(
            g,
            "<line x1=\"{x:.1}\" y1=\"{:.1}\" x2=\"{x:.1}\" y2=\"{:.1}\" stroke=\"#111\" \
             stroke-width=\"1.5\"/><text x=\"{:.1}\" y=\"{:.1}\" class=\"tick\">chosen</text>",
            top.y,
            bottom.y + bottom.h,
            x + 4.0,
            top.y + 14.0
        );
    }
    g.push_str("</svg>");
    let mut table = String::from(
        "<table><tr><th>surface triangles</th><th>per measured px</th><th>bound (x Sq)</th>\
         <th>worst Sa %</th><th>worst Sq %</th><th>worst Sz %</th><th>worst residual (% of Sq)</th>\
         <th>worst roughness %</th><th>worst region</th><th>passes</th><th>LIGGGHTS mesh cost per step</th></tr>",
    );
    for (tri, _, chosen, c) in &pts {
        let _ = write!(
            table,
            "<tr class=\"{}\"><td>{}{}</td><td>{:.3}</td><td>{:.3}</td><td>{:+.2}</td><td>{:+.2}</td>\
             <td>{:+.2}</td><td>{:.1}</td><td>{}</td><td class=\"k\">{}</td><td>{}</td><td>{:.1} ms</td></tr>",
            if c.pass { "pass" } else { "fail" },
            *tri as u64,
            if *chosen { " (chosen)" } else { "" },
            c.triangles_per_measured_px,
            c.epsilon_sq_fraction,
            c.worst_sa_pct,
            c.worst_sq_pct,
            c.worst_sz_pct,
            c.worst_residual_pct_of_sq,
            c.worst_roughness_pct
                .map_or("-".to_string(), |r| format!("{r:+.2}")),
            esc(&c.worst_region),
            if c.over_budget {
                "over budget"
            } else if c.pass {
                "yes"
            } else {
                "no"
            },
            tri * LIGGGHTS_US_PER_TRIANGLE_STEP / 1000.0
        );
    }
    table.push_str("</table>");
    let reason = (t.reason.as_deref())
        .map(|r| format!("<p class=\"bad\">Tolerance not met: {}</p>", esc(r)))
        .unwrap_or_default();
    format!(
        "<section id=\"cost\"><h2>Fidelity-cost curve of the model</h2>{reason}<figure>{g}\
         <figcaption>Every mesh the tolerance search made (greedy insertion on the full-resolution \
         surface at a series of vertical bounds): top, the worst |deviation| of Sa, Sq and Sz over \
         the {} judged regions (mesh interpolated at every measured point, mean removed), dashed \
         the tolerance; in orange, when the measured roughness was given, the worst deviation of \
         the roughness the mesh carries (mesh - datum against the measured roughness); bottom, \
         the worst pointwise residual RMS in percent of the region's Sq, dashed its bound. The \
         search keeps the mesh with the fewest triangles within {:.0} % of the tolerance in every \
         region (vertical line). A DEM step's cost grows with the triangles: in LIGGGHTS about \
         {LIGGGHTS_US_PER_TRIANGLE_STEP} µs per triangle per time step (measured, \
         docs/model.md), the last column.</figcaption></figure>{table}</section>",
        t.regions,
        t.target_share * 100.0,
    )
}

fn top_clone(p: &Panel) -> Panel {
    Panel {
        x: p.x,
        y: p.y,
        w: p.w,
        h: p.h,
        xa: p.xa.clone(),
        ya: p.ya.clone(),
    }
}

fn dot(g: &mut String, p: &Panel, x: f64, y: f64, colour: &str) {
    if x.is_finite() && y.is_finite() && y >= p.ya.lo && y <= p.ya.hi {
        let _ = write!(
            g,
            "<circle cx=\"{:.1}\" cy=\"{:.1}\" r=\"3\" fill=\"{colour}\"/>",
            p.px(x),
            p.py(y)
        );
    }
}

/// A dashed horizontal line at `value` across the panel (a limit).
fn dashed(g: &mut String, p: &Panel, value: f64, colour: &str) {
    if value.is_finite() {
        let y = p.py(value);
        let _ = write!(
            g,
            "<line x1=\"{:.1}\" y1=\"{y:.1}\" x2=\"{:.1}\" y2=\"{y:.1}\" stroke=\"{colour}\" \
             stroke-dasharray=\"5,4\" stroke-width=\"1.2\"/>",
            p.x,
            p.x + p.w
        );
    }
}
