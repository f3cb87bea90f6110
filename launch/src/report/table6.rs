//! The reference study's Table 6 from run.json's `deviation`: per stage the grid it was judged
//! on and its verdict, the failures first, a compact matrix of deviations (regions x
//! parameters, judged cells marked) and the full table (measured, model, deviation for every
//! region and parameter) collapsed.

use std::fmt::Write as _;

use surfstream_core::metrology::Params;
use surfstream_core::record::{DeviationRecord, StageDeviation};
use surfstream_core::units::percent;

use super::html::{esc, fixed, pitch, sig, signed, table_raw, um};

/// Table 6's stages by name.
type Stages = std::collections::BTreeMap<String, StageDeviation>;

const PARAMS: [&str; 9] = ["Sa", "Sq", "Sp", "Sv", "Sz", "Ssk", "Sku", "Sdq", "Sdr"];

/// A parameter value with 3 significant figures and its unit, heights in nm below 1 µm ("-"
/// where not measured).
fn value(p: &str, params: &Option<Params>) -> String {
    let v = params.and_then(|m| m.by_name(p)).filter(|v| v.is_finite());
    match v {
        None => "-".into(),
        Some(x) => match p {
            "Ssk" | "Sku" | "Sdq" => sig(x, 3),
            "Sdr" => percent(x),
            _ => um(x),
        },
    }
}

fn badge(pass: bool) -> &'static str {
    if pass {
        "<span class=\"badge pass\">pass</span>"
    } else {
        "<span class=\"badge fail\">FAIL</span>"
    }
}

/// Whether a stage is judged (a stage that is not meshed is reported only).
fn stage_judged(st: &StageDeviation) -> bool {
    st.judged
}

/// The stage's own limit for `p` (the mesh: the model's tolerance), else the threshold.
fn limit(st: &StageDeviation, p: &str, threshold: f64) -> f64 {
    st.limits_pct.get(p).unwrap_or(threshold)
}

/// The verdict badge of a stage or region; "reported" where the stage is not judged.
fn verdict_badge(st: &StageDeviation, pass: bool) -> &'static str {
    if stage_judged(st) {
        badge(pass)
    } else {
        "<span class=\"badge\" title=\"not what the STL is made from: reported, not judged\">reported</span>"
    }
}

/// The row class: pass / fail, nothing where the stage is not judged.
fn row_class(st: &StageDeviation, pass: bool) -> String {
    match (stage_judged(st), pass) {
        (false, _) => String::new(),
        (true, true) => "pass".into(),
        (true, false) => "fail".into(),
    }
}

pub fn section(dev: Option<&DeviationRecord>) -> String {
    let dev = match dev {
        None => return String::new(),
        Some(DeviationRecord::Table(t)) => t,
        Some(DeviationRecord::NotComputed { error: e }) => {
            return format!(
            "<section id=\"table6\"><h2>Model vs measurement (Table 6)</h2><p class=\"bad\">Not \
             computed: {}</p></section>\n",
            esc(e)
        )
        }
    };
    let stages = &dev.stages;
    if stages.is_empty() {
        return String::new();
    }
    let e = dev.threshold_pct;
    let judged: Vec<&str> = dev.judged.iter().map(String::as_str).collect();
    let mut h = String::new();
    let _ = write!(
        h,
        "<section id=\"table6\"><h2>Model vs measurement (Table 6) {}</h2><p>Measured: <code>{}</code>. \
         A stage passes a region when |deviation| ≤ {} % for {}; the other parameters are \
         reported, not judged. {}</p>",
        badge(dev.pass),
        esc(&dev.measured),
        fixed(e, 1),
        judged.join(", "),
        esc(&dev.conventions),
    );

    h.push_str(&stages_table(stages));
    failures(&mut h, stages, &judged, e);
    at_a_glance(&mut h, stages, &judged, e);
    full_table(&mut h, stages, &judged, e);
    h
}

/// The stages: what each is judged on, its grid and pitch, regions passed, verdict.
fn stages_table(stages: &Stages) -> String {
    let rows: Vec<(String, Vec<String>)> = stages
        .iter()
        .map(|(name, st)| {
            let g = &st.grid;
            let failed = st.regions.values().filter(|r| !r.pass).count();
            let total = st.regions.len();
            (
                row_class(st, st.pass),
                vec![
                    format!("<b>{}</b>", esc(name)),
                    esc(&g.name),
                    format!("{} x {}", g.rows, g.cols),
                    pitch(g.pitch_x_um),
                    format!("{} of {total}", total - failed),
                    verdict_badge(st, st.pass).to_string(),
                ],
            )
        })
        .collect();
    table_raw(
        &[
            "stage",
            "judged on",
            "grid (rows x cols)",
            "pitch",
            "regions passed",
            "verdict",
        ],
        &rows,
    )
}

/// The failures, one row per judged parameter out of bounds.
fn failures(h: &mut String, stages: &Stages, judged: &[&str], e: f64) {
    let mut fails = Vec::new();
    for (stage, st) in stages {
        if !stage_judged(st) {
            continue;
        }
        for (region, r) in &st.regions {
            if r.pass {
                continue;
            }
            let mut any = false;
            for p in judged {
                let d = r.deviation(p);
                if d.is_some_and(|d| d.abs() <= limit(st, p, e)) {
                    continue;
                }
                any = true;
                fails.push((
                    "fail".to_string(),
                    vec![
                        esc(stage),
                        esc(region),
                        p.to_string(),
                        value(p, &r.measured),
                        value(p, &r.model),
                        d.map(|d| format!("{} %", signed(d, 2)))
                            .unwrap_or("-".into()),
                    ],
                ));
            }
            if !any {
                fails.push((
                    "fail".to_string(),
                    vec![
                        esc(stage),
                        esc(region),
                        "-".into(),
                        "-".into(),
                        "-".into(),
                        "no valid points in common".into(),
                    ],
                ));
            }
        }
    }
    if fails.is_empty() {
        h.push_str("<p>No judged parameter is out of bounds.</p>");
    } else {
        let _ = write!(h, "<h3>Out of bounds ({} judged values)</h3>", fails.len());
        h.push_str(&table_raw(
            &[
                "stage",
                "region",
                "parameter",
                "measured",
                "model",
                "deviation",
            ],
            &fails,
        ));
    }
}

/// Deviations at a glance: regions x parameters per stage.
fn at_a_glance(h: &mut String, stages: &Stages, judged: &[&str], e: f64) {
    h.push_str("<h3>Deviation (model - measured) / measured, %</h3><div class=\"flex\">");
    for (stage, st) in stages {
        let mut head = vec!["region"];
        head.extend(PARAMS);
        head.push("");
        let rows: Vec<(String, Vec<String>)> = (st.regions.iter())
            .map(|(region, r)| {
                let mut cells = vec![esc(region)];
                for p in PARAMS {
                    let d = r.deviation(p);
                    let text = d.map(|d| signed(d, 1)).unwrap_or("-".into());
                    let tip = format!(
                        "{p}: measured {}, model {}",
                        value(p, &r.measured),
                        value(p, &r.model)
                    );
                    cells.push(if judged.contains(&p) && stage_judged(st) {
                        let ok = d.is_some_and(|d| d.abs() <= limit(st, p, e));
                        format!(
                            "<span class=\"{}\" title=\"{}\">{text}</span>",
                            if ok { "ok" } else { "bad" },
                            esc(&tip)
                        )
                    } else {
                        format!(
                            "<span class=\"unjudged\" title=\"{}\">{text}</span>",
                            esc(&tip)
                        )
                    });
                }
                cells.push(verdict_badge(st, r.pass).to_string());
                (row_class(st, r.pass), cells)
            })
            .collect();
        let _ = write!(
            h,
            "<div><h4>{} {} <span class=\"note\">on the {}</span></h4>{}</div>",
            esc(stage),
            verdict_badge(st, st.pass),
            esc(&st.grid.name),
            table_raw(&head, &rows)
        );
    }
    let _ = write!(
        h,
        "</div><p class=\"note\">Bold columns are judged (±{} %, the mesh against the model's \
         tolerance); grey ones are reported only \
         (Ssk near 0 gives large relative deviations; slopes of a coarser grid differ by \
         construction). Hover a cell for the two values.</p>",
        fixed(e, 1)
    );
}

/// The full table: every stage, region and parameter.
fn full_table(h: &mut String, stages: &Stages, judged: &[&str], e: f64) {
    let mut all = Vec::new();
    for (stage, st) in stages {
        for (region, r) in &st.regions {
            for p in PARAMS {
                let d = r.deviation(p);
                let class = if !judged.contains(&p) || !stage_judged(st) {
                    ""
                } else if d.is_some_and(|d| d.abs() <= limit(st, p, e)) {
                    "pass"
                } else {
                    "fail"
                };
                all.push((
                    class.to_string(),
                    vec![
                        esc(stage),
                        esc(region),
                        if judged.contains(&p) {
                            format!("<b>{p}</b> (judged)")
                        } else {
                            p.to_string()
                        },
                        value(p, &r.measured),
                        value(p, &r.model),
                        d.map(|d| format!("{} %", signed(d, 2)))
                            .unwrap_or("-".into()),
                    ],
                ));
            }
        }
    }
    let _ = writeln!(
        h,
        "<details><summary>Full table: {} rows (every stage, region and parameter)</summary>{}</details></section>",
        all.len(),
        table_raw(
            &["stage", "region", "parameter", "measured", "model", "deviation"],
            &all
        )
    );
}
