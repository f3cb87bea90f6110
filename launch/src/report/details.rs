//! The sections below the results: tile layout and registrations, the mesh, and, collapsed, the
//! latencies (with human names), the node reports (internal bookkeeping left out) and the node
//! parameters.

use std::collections::BTreeMap;
use std::fmt::Write as _;

use serde_json::Value;
use surfstream_core::record::{
    LevelledParams, MatcherPair, MeshReport, Percentiles, RunRecord, ScanRecord, TileRecord,
};
use surfstream_core::units::percent;

use super::html::{esc, fixed, num, pitch, table, table_raw, um};

/// Stage vs registered tile positions (an SVG to scale) and a table per tile.
pub fn tile_layout(run: &RunRecord) -> String {
    let tiles = &run.tiles;
    if tiles.is_empty() {
        return String::new();
    }
    let mut h = String::from("<section id=\"tiles\"><h2>Tile layout</h2><div class=\"flex\">");
    h.push_str(&layout_svg(tiles, run.scan.as_ref()));
    let rows: Vec<(String, Vec<String>)> = tiles
        .iter()
        .map(|t| {
            let (s, p) = (&t.source, t.placement.as_ref());
            let shift = match p {
                Some(p) => format!(
                    "{} / {}",
                    fixed(p.x_um - s.stage_x_um, 2),
                    fixed(p.y_um - s.stage_y_um, 2)
                ),
                None => "-".into(),
            };
            let by_stage = p.is_some_and(|p| p.placed_by == "stage");
            (
                if by_stage { "fail" } else { "" }.to_string(),
                vec![
                    s.index.to_string(),
                    format!("{} / {}", s.row, s.col),
                    format!("{} / {}", fixed(s.stage_x_um, 2), fixed(s.stage_y_um, 2)),
                    p.map_or("- / -".into(), |p| {
                        format!("{} / {}", fixed(p.x_um, 2), fixed(p.y_um, 2))
                    }),
                    shift,
                    match p {
                        _ if by_stage => "<b>stage (fallback)</b>".into(),
                        Some(p) => esc(&p.placed_by),
                        None => "?".into(),
                    },
                    p.map_or("-".into(), |p| fixed(p.quality, 4)),
                ],
            )
        })
        .collect();
    h.push_str(&table_raw(
        &[
            "tile",
            "row / col",
            "stage x / y (µm)",
            "registered x / y (µm)",
            "shift x / y (µm)",
            "placed by",
            "best NCC",
        ],
        &rows,
    ));
    h.push_str("</div>");
    if let Some(pairs) = Some(&run.pairs).filter(|p| !p.is_empty()) {
        h.push_str("<h3>Registrations (neighbour pairs)</h3>");
        h.push_str(&pair_table(pairs));
    }
    h.push_str("</section>\n");
    h
}

/// One column of the pair table: its title, whether a pair has it (a column no pair has is
/// left out), and the cell.
struct PairColumn {
    title: &'static str,
    present: fn(&MatcherPair) -> bool,
    cell: fn(&MatcherPair) -> String,
}

fn offset_cell(o: Option<[f64; 2]>, dp: usize) -> String {
    o.map_or("-".into(), |o| o.map(|v| fixed(v, dp)).join(" / "))
}

const PAIR_COLUMNS: [PairColumn; 8] = [
    PairColumn {
        title: "pair",
        present: |_| true,
        cell: |p| format!("{} - {}", p.a, p.b),
    },
    PairColumn {
        title: "direction",
        present: |_| true,
        cell: |p| esc(&p.direction),
    },
    PairColumn {
        title: "NCC",
        present: |_| true,
        cell: |p| fixed(p.ncc, 4),
    },
    PairColumn {
        title: "accepted",
        present: |_| true,
        cell: |p| if p.accepted { "yes" } else { "<b>no</b>" }.into(),
    },
    PairColumn {
        title: "nominal offset x / y (px)",
        present: |_| true,
        cell: |p| offset_cell(Some(p.nominal_offset_px), 2),
    },
    PairColumn {
        title: "measured offset x / y (px)",
        present: |_| true,
        cell: |p| offset_cell(p.offset_px, 2),
    },
    // The Lucas-Kanade refinement's standard deviation (pairs it refined); hundredths of a
    // pixel and below: four decimals.
    PairColumn {
        title: "sd (px)",
        present: |p| p.offset_sd_px.is_some(),
        cell: |p| p.offset_sd_px.map_or("-".into(), |sd| fixed(sd, 4)),
    },
    // The global solve's residual (links it took).
    PairColumn {
        title: "residual x / y (px)",
        present: |p| p.residual_px.is_some(),
        cell: |p| offset_cell(p.residual_px, 4),
    },
];

/// The neighbour pairs, one row each; a failed pair's row is marked.
fn pair_table(pairs: &[MatcherPair]) -> String {
    let columns: Vec<&PairColumn> = PAIR_COLUMNS
        .iter()
        .filter(|c| pairs.iter().any(c.present))
        .collect();
    let head: Vec<&str> = columns.iter().map(|c| c.title).collect();
    let rows: Vec<(String, Vec<String>)> = pairs
        .iter()
        .map(|p| {
            let class = if p.accepted { "" } else { "fail" };
            (
                class.to_string(),
                columns.iter().map(|c| (c.cell)(p)).collect(),
            )
        })
        .collect();
    table_raw(&head, &rows)
}

/// The mesher's report: size, closure and fidelity (height field vs the re-sampled mesh).
pub fn mesh(run: &RunRecord) -> String {
    let Some(m) = run.stage::<MeshReport>() else {
        return String::new();
    };
    let adaptive = m.adaptive();
    // Each fact as the page showed the report's value ("-": not in this mesher's report).
    let shown = |v: Option<Value>| v.map_or("-".into(), |v| num(&v));
    let mut h = String::from("<section id=\"mesh\"><h2>Mesh</h2><div class=\"flex\">");
    let facts: Vec<Vec<String>> = [
        ("file", num(&Value::from(m.file.as_str()))),
        ("surface meshed", num(&Value::from(m.surface.as_str()))),
        ("method", num(&Value::from(m.method.as_str()))),
        ("triangles", num(&Value::from(m.triangles))),
        ("vertices", num(&Value::from(m.vertices))),
        ("watertight", num(&Value::from(m.watertight))),
        (
            "consistently oriented",
            num(&Value::from(m.consistently_oriented)),
        ),
        (
            "kind",
            shown(adaptive.map(|a| Value::from(a.kind.as_str()))),
        ),
        (
            "format, units",
            format!(
                "{}, {}",
                num(&Value::from(m.format.as_str())),
                num(&Value::from(m.units.as_str()))
            ),
        ),
        (
            "grid (rows x cols)",
            // The mesher's grid_px is [cols, rows].
            format!("{} x {}", m.grid_px[1], m.grid_px[0]),
        ),
        ("pitch", pitch(m.pitch_um[0])),
        ("base depth", m.base_depth_um.map(um).unwrap_or("-".into())),
        (
            "not-measured samples filled",
            num(&Value::from(m.filled_samples)),
        ),
        (
            "triangle budget reached",
            shown(adaptive.map(|a| Value::from(a.budget_reached))),
        ),
        (
            "vertex to scan coordinates",
            format!(
                "{} with offset {} µm",
                shown(adaptive.map(|a| Value::from(a.offset_rule.as_str()))),
                (m.offset_um.iter())
                    .map(|&v| fixed(v, 3))
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        ),
    ]
    .into_iter()
    .filter(|(_, v)| v != "-" && v != "- with offset - µm")
    .map(|(k, v)| vec![k.to_string(), v])
    .collect();
    h.push_str(&table(&["", ""], &facts).replace("<thead><tr><th></th><th></th></tr></thead>", ""));
    if let Some(f) = adaptive.map(|a| a.fidelity) {
        let rows: Vec<Vec<String>> = ["Sa", "Sq", "Sz", "Sdr"]
            .iter()
            .map(|label| {
                let pick = |p: Option<LevelledParams>| {
                    p.map(|p| match *label {
                        "Sa" => p.sa_um,
                        "Sq" => p.sq_um,
                        "Sz" => p.sz_um,
                        _ => p.sdr_percent,
                    })
                };
                let show = |v: Option<f64>| {
                    v.filter(|x| !x.is_nan())
                        .map(|x| if *label == "Sdr" { percent(x) } else { um(x) })
                        .unwrap_or("-".into())
                };
                vec![
                    (*label).to_string(),
                    show(pick(f.field)),
                    show(pick(f.mesh)),
                ]
            })
            .collect();
        let meshed = &m.surface;
        let finite = |v: f64| if v.is_nan() { "-".into() } else { um(v) };
        let _ = write!(
            h,
            "<div><h3>Fidelity of the mesh ({meshed}, levelled)</h3>{}<p class=\"note\">Both \
             columns are levelled: the least-squares plane of the height field is removed from \
             both, so they differ from the key parameters above (mean removed, not levelled). \
             Vertical error of the mesh at every sample: max {}, rms {} (bound {}: {}).</p></div>",
            table(
                &[
                    "parameter",
                    "height field meshed (levelled)",
                    "mesh resampled (levelled)",
                ],
                &rows
            ),
            finite(f.error.max_um),
            finite(f.error.rms_um),
            finite(f.epsilon_um),
            if f.bound_met { "met" } else { "NOT met" },
        );
    }
    h.push_str("</div></section>\n");
    h
}

/// A latency path's key as words: "tile_to_panorama" -> "tile → panorama".
fn human(path: &str) -> String {
    path.replace("_to_", " → ")
        .replace('_', " ")
        .replace("<-", "←")
}

/// Latency percentiles per path, grouped, in ms, collapsed.
pub fn latencies(run: &RunRecord) -> String {
    let lat = &run.latency_ms;
    let group_name = |k: &str| match k {
        "hops" => "between stages",
        "final_frames" => "to the final results",
        "transport" => "transport (sent → received)",
        _ => "end to end",
    };
    let mut groups: Vec<(&str, Vec<Vec<String>>)> = Vec::new();
    let mut push = |group: &'static str, path: &str, p: &Percentiles| {
        let ms = |v: f64| fixed(v, 2);
        let row = vec![
            human(path),
            ms(p.p50),
            ms(p.p95),
            ms(p.max),
            p.n.to_string(),
        ];
        match groups.iter_mut().find(|g| g.0 == group) {
            Some(g) => g.1.push(row),
            None => groups.push((group, vec![row])),
        }
    };
    // In run.json's key order (the group names sort among the end-to-end paths), which is
    // the order the groups first appear in.
    type Row<'a> = (&'static str, &'a str, &'a Percentiles);
    let mut rows: BTreeMap<&str, Vec<Row>> = BTreeMap::new();
    for (path, p) in &lat.end_to_end {
        rows.insert(path, vec![(group_name("end"), path, p)]);
    }
    for (key, group) in [
        ("final_frames", &lat.final_frames),
        ("hops", &lat.hops),
        ("transport", &lat.transport),
    ] {
        let group_rows = group
            .iter()
            .map(|(path, p)| (group_name(key), path.as_str(), p));
        rows.insert(key, group_rows.collect());
    }
    for (group, path, p) in rows.into_values().flatten() {
        push(group, path, p);
    }
    let mut h = String::from(
        "<details id=\"latencies\"><summary>Latencies (p50 / p95 / max, ms)</summary><div class=\"flex\">",
    );
    for (group, rows) in groups {
        let _ = write!(
            h,
            "<div><h4>{}</h4>{}</div>",
            esc(group),
            table(
                &["path", "p50 (ms)", "p95 (ms)", "max (ms)", "frames"],
                &rows
            )
        );
    }
    h.push_str(
        "</div><p class=\"note\">From the acquisition time of the tile that caused each frame; \
         measured on this machine under its load at the time.</p></details>\n",
    );
    h
}

/// Keys that are bookkeeping for tools, not results for people.
fn internal(key: &str) -> bool {
    key.ends_with("_ns")
        || key.starts_with("live_")
        || key.contains("streaming")
        || matches!(
            key,
            "tiles" | "pairs" | "fusion_pairs" | "files" | "energy_curve" | "sources" | "sent"
        )
}

/// Every node's report (internal fields left out) and parameters, collapsed.
pub fn node_reports(run: &RunRecord) -> String {
    let mut h = String::from(
        "<details id=\"nodes\"><summary>Node reports and parameters</summary><div class=\"flex\">",
    );
    for (id, r) in &run.stages {
        let mut rows = Vec::new();
        flatten("", r, &mut rows);
        if let Some(p) = run.parameters.get(id).and_then(Value::as_object) {
            for (k, v) in p {
                rows.push(vec![format!("parameter {k}"), num(v)]);
            }
        }
        let _ = write!(
            h,
            "<div><h4>{}</h4>{}</div>",
            esc(id),
            table(&["field", "value"], &rows)
        );
    }
    h.push_str("</div></details>\n");
    h
}

fn flatten(prefix: &str, v: &Value, rows: &mut Vec<Vec<String>>) {
    match v {
        Value::Object(m) => {
            for (k, x) in m.iter().filter(|(k, _)| !internal(k)) {
                let key = if prefix.is_empty() {
                    k.clone()
                } else {
                    format!("{prefix}.{k}")
                };
                flatten(&key, x, rows);
            }
        }
        Value::Array(a) if a.len() > 6 || a.iter().any(|x| x.is_object()) => {
            rows.push(vec![prefix.to_string(), format!("[{} items]", a.len())]);
        }
        _ => rows.push(vec![prefix.to_string(), num(v)]),
    }
}

fn placed_by(t: &TileRecord) -> &str {
    t.placement.as_ref().map_or("?", |p| &p.placed_by)
}

/// Stage (dashed) and registered (solid) tile outlines, to scale, y down as in the maps.
fn layout_svg(tiles: &[TileRecord], scan: Option<&ScanRecord>) -> String {
    let (pitch_x, pitch_y) = scan.map_or((1.0, 1.0), ScanRecord::pitch_um);
    let (w_px, h_px) = scan.map_or((0, 0), ScanRecord::tile_px);
    let w_um = w_px as f64 * pitch_x;
    let h_um = h_px as f64 * pitch_y;
    let stage = |t: &TileRecord| Some((t.source.stage_x_um, t.source.stage_y_um));
    let placed = |t: &TileRecord| t.placement.as_ref().map(|p| (p.x_um, p.y_um));
    let mut xs = Vec::new();
    let mut ys = Vec::new();
    for t in tiles {
        for (x, y) in [stage(t), placed(t)].into_iter().flatten() {
            xs.extend([x, x + w_um]);
            ys.extend([y, y + h_um]);
        }
    }
    if xs.is_empty() || w_um <= 0.0 || h_um <= 0.0 {
        return String::new();
    }
    let (x0, x1) = (
        xs.iter().copied().fold(f64::INFINITY, f64::min),
        xs.iter().copied().fold(f64::NEG_INFINITY, f64::max),
    );
    let (y0, y1) = (
        ys.iter().copied().fold(f64::INFINITY, f64::min),
        ys.iter().copied().fold(f64::NEG_INFINITY, f64::max),
    );
    let scale = 420.0 / (x1 - x0).max(y1 - y0).max(1e-9);
    let (sw, sh) = ((x1 - x0) * scale + 20.0, (y1 - y0) * scale + 56.0);
    let mut s = format!(
        "<svg class=\"layout\" viewBox=\"0 0 {sw:.0} {sh:.0}\" width=\"{sw:.0}\" \
         style=\"border:1px solid #ccc;background:#fafafa\">"
    );
    let colours = [
        "#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b",
    ];
    for (k, t) in tiles.iter().enumerate() {
        let c = colours[k % colours.len()];
        if let Some((x, y)) = stage(t) {
            let _ = write!(
                s,
                "<rect x=\"{:.1}\" y=\"{:.1}\" width=\"{:.1}\" height=\"{:.1}\" fill=\"none\" \
                 stroke=\"{c}\" stroke-dasharray=\"5,4\" stroke-width=\"1\"/>",
                10.0 + (x - x0) * scale,
                10.0 + (y - y0) * scale,
                w_um * scale,
                h_um * scale
            );
        }
        if let Some((x, y)) = placed(t) {
            let _ = write!(
                s,
                "<rect x=\"{:.1}\" y=\"{:.1}\" width=\"{:.1}\" height=\"{:.1}\" fill=\"{c}\" \
                 fill-opacity=\"0.06\" stroke=\"{c}\" stroke-width=\"2\"/>\
                 <text x=\"{:.1}\" y=\"{:.1}\" class=\"tick\" fill=\"{c}\">tile {} ({})</text>",
                10.0 + (x - x0) * scale,
                10.0 + (y - y0) * scale,
                w_um * scale,
                h_um * scale,
                16.0 + (x - x0) * scale,
                28.0 + (y - y0) * scale,
                t.source.index,
                esc(placed_by(t)),
            );
        }
    }
    let _ = write!(
        s,
        "<text x=\"10\" y=\"{:.0}\" class=\"tick\">solid: registered; dashed: stage position</text>\
         <text x=\"10\" y=\"{:.0}\" class=\"tick\">{} x {} µm (y x x), y down as the stage moves</text></svg>",
        sh - 24.0,
        sh - 8.0,
        fixed(y1 - y0, 0),
        fixed(x1 - x0, 0)
    );
    s
}

#[cfg(test)]
mod tests {
    use serde_json::json;

    /// The pair table shows the refinement's standard deviation and the global solve's
    /// residual vector (it once printed "-" for every residual), and leaves out a column no
    /// pair has.
    #[test]
    fn the_pair_table_shows_sd_and_residual_vectors() {
        let pair = json!({ "a": 0, "b": 1, "direction": "horizontal",
            "nominal_offset_px": [921.6, 0.0], "offset_px": [919.78, 4.08], "ncc": 0.9978,
            "peak_ratio": 2.0, "accepted": true, "reason": null,
            "offset_sd_px": 0.00045, "residual_px": [0.00268, -0.00054] });
        let run = |pairs: serde_json::Value| {
            crate::runjson::test_record(json!({ "elapsed_s": 1.0,
                "scan": { "rows": 1, "cols": 2 }, "pairs": pairs, "files": [],
                "tiles": [
                    { "index": 0, "row": 0, "col": 0, "placed_by": "registration" },
                    { "index": 1, "row": 0, "col": 1, "placed_by": "registration" },
                ] }))
        };
        let h = super::tile_layout(&run(json!([pair.clone()])));
        assert!(h.contains("sd (px)"), "{h}");
        assert!(
            h.contains("0.0005") && h.contains("0.0027 / -0.0005"),
            "{h}"
        );
        let mut bare = pair;
        bare.as_object_mut().map(|o| {
            o.remove("offset_sd_px");
            o.remove("residual_px")
        });
        let h = super::tile_layout(&run(json!([bare])));
        assert!(
            !h.contains("sd (px)") && !h.contains("residual x / y"),
            "{h}"
        );
        assert!(h.contains("919.78 / 4.08"), "{h}");
    }
}
