//! The sections below the results: tile layout and registrations, the mesh, and, collapsed, the
//! latencies (with human names), the node reports (internal bookkeeping left out) and the node
//! parameters.

use std::fmt::Write as _;

use serde_json::Value;

use super::html::{esc, fixed, num, table, table_raw, um};

/// Stage vs registered tile positions (an SVG to scale) and a table per tile.
pub fn tile_layout(run: &Value) -> String {
    let Some(tiles) = run["tiles"].as_array().filter(|t| !t.is_empty()) else {
        return String::new();
    };
    let mut h = String::from("<section id=\"tiles\"><h2>Tile layout</h2><div class=\"flex\">");
    h.push_str(&layout_svg(tiles, &run["scan"]));
    let rows: Vec<(String, Vec<String>)> = tiles
        .iter()
        .map(|t| {
            let f = |k: &str| t[k].as_f64();
            let shift = match (f("x_um"), f("y_um"), f("stage_x_um"), f("stage_y_um")) {
                (Some(x), Some(y), Some(sx), Some(sy)) => {
                    format!("{} / {}", fixed(x - sx, 2), fixed(y - sy, 2))
                }
                _ => "-".into(),
            };
            let by_stage = t["placed_by"] == "stage";
            (
                if by_stage { "fail" } else { "" }.to_string(),
                vec![
                    num(&t["index"]),
                    format!("{} / {}", num(&t["row"]), num(&t["col"])),
                    format!(
                        "{} / {}",
                        f("stage_x_um").map(|v| fixed(v, 2)).unwrap_or("-".into()),
                        f("stage_y_um").map(|v| fixed(v, 2)).unwrap_or("-".into())
                    ),
                    format!(
                        "{} / {}",
                        f("x_um").map(|v| fixed(v, 2)).unwrap_or("-".into()),
                        f("y_um").map(|v| fixed(v, 2)).unwrap_or("-".into())
                    ),
                    shift,
                    if by_stage {
                        "<b>stage (fallback)</b>".into()
                    } else {
                        esc(t["placed_by"].as_str().unwrap_or("?"))
                    },
                    f("quality").map(|q| fixed(q, 4)).unwrap_or("-".into()),
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
    if let Some(pairs) = run["pairs"].as_array().filter(|p| !p.is_empty()) {
        let rows: Vec<(String, Vec<String>)> = pairs
            .iter()
            .map(|p| {
                let off = |k: &str| {
                    p[k].as_array()
                        .map(|a| {
                            a.iter()
                                .map(|v| v.as_f64().map(|v| fixed(v, 2)).unwrap_or("-".into()))
                                .collect::<Vec<_>>()
                                .join(" / ")
                        })
                        .unwrap_or("-".into())
                };
                let accepted = p["accepted"] == true;
                (
                    if accepted { "" } else { "fail" }.to_string(),
                    vec![
                        format!("{} - {}", num(&p["a"]), num(&p["b"])),
                        esc(p["direction"].as_str().unwrap_or("?")),
                        p["ncc"].as_f64().map(|v| fixed(v, 4)).unwrap_or("-".into()),
                        if accepted { "yes" } else { "<b>no</b>" }.into(),
                        off("nominal_offset_px"),
                        off("offset_px"),
                        p["residual_px"]
                            .as_f64()
                            .map(|v| fixed(v, 3))
                            .unwrap_or("-".into()),
                    ],
                )
            })
            .collect();
        let mut head = vec![
            "pair",
            "direction",
            "NCC",
            "accepted",
            "nominal offset x / y (px)",
            "measured offset x / y (px)",
            "residual (px)",
        ];
        let mut rows = rows;
        if pairs.iter().all(|p| p["residual_px"].is_null()) {
            head.pop();
            rows.iter_mut().for_each(|r| {
                r.1.pop();
            });
        }
        h.push_str("<h3>Registrations (neighbour pairs)</h3>");
        h.push_str(&table_raw(&head, &rows));
    }
    h.push_str("</section>\n");
    h
}

/// The mesher's report: size, closure and fidelity (height field vs the re-sampled mesh).
pub fn mesh(run: &Value) -> String {
    let Some(m) = run["stages"]
        .as_object()
        .and_then(|s| s.values().find(|v| v.get("triangles").is_some()))
    else {
        return String::new();
    };
    let mut h = String::from("<section id=\"mesh\"><h2>Mesh</h2><div class=\"flex\">");
    let facts: Vec<Vec<String>> = [
        ("file", num(&m["file"])),
        ("surface meshed", num(&m["surface"])),
        ("method", num(&m["method"])),
        ("triangles", num(&m["triangles"])),
        ("vertices", num(&m["vertices"])),
        ("watertight", num(&m["watertight"])),
        ("consistently oriented", num(&m["consistently_oriented"])),
        ("kind", num(&m["kind"])),
        (
            "format, units",
            format!("{}, {}", num(&m["format"]), num(&m["units"])),
        ),
        (
            "grid (rows x cols)",
            // The mesher's grid_px is [cols, rows].
            match (m["grid_px"][1].as_u64(), m["grid_px"][0].as_u64()) {
                (Some(r), Some(c)) => format!("{r} x {c}"),
                _ => "-".into(),
            },
        ),
        (
            "pitch",
            m["pitch_um"][0].as_f64().map(um).unwrap_or("-".into()),
        ),
        (
            "base depth",
            m["base_depth_um"].as_f64().map(um).unwrap_or("-".into()),
        ),
        ("not-measured samples filled", num(&m["filled_samples"])),
        ("triangle budget reached", num(&m["budget_reached"])),
        (
            "vertex to scan coordinates",
            format!(
                "{} with offset {} µm",
                num(&m["offset_rule"]),
                m["offset_um"]
                    .as_array()
                    .map(|a| a
                        .iter()
                        .map(|v| v.as_f64().map(|v| fixed(v, 3)).unwrap_or("-".into()))
                        .collect::<Vec<_>>()
                        .join(", "))
                    .unwrap_or("-".into())
            ),
        ),
    ]
    .into_iter()
    .filter(|(_, v)| v != "-" && v != "- with offset - µm")
    .map(|(k, v)| vec![k.to_string(), v])
    .collect();
    h.push_str(&table(&["", ""], &facts).replace("<thead><tr><th></th><th></th></tr></thead>", ""));
    let f = &m["fidelity"];
    if f.is_object() {
        let rows: Vec<Vec<String>> = [
            ("Sa", "sa_um"),
            ("Sq", "sq_um"),
            ("Sz", "sz_um"),
            ("Sdr", "sdr_percent"),
        ]
        .iter()
        .map(|(label, k)| {
            let show = |v: &Value| {
                v.as_f64()
                    .map(|x| {
                        if *label == "Sdr" {
                            format!("{} %", fixed(x, 3))
                        } else {
                            um(x)
                        }
                    })
                    .unwrap_or("-".into())
            };
            vec![
                (*label).to_string(),
                show(&f["field"][k]),
                show(&f["mesh"][k]),
            ]
        })
        .collect();
        let meshed = m["surface"].as_str().unwrap_or("pooled");
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
            f["error"]["max_um"].as_f64().map(um).unwrap_or("-".into()),
            f["error"]["rms_um"].as_f64().map(um).unwrap_or("-".into()),
            f["epsilon_um"].as_f64().map(um).unwrap_or("-".into()),
            if f["bound_met"] == true {
                "met"
            } else {
                "NOT met"
            },
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
pub fn latencies(run: &Value) -> String {
    let Some(lat) = run["latency_ms"].as_object() else {
        return String::new();
    };
    let group_name = |k: &str| match k {
        "hops" => "between stages",
        "final_frames" => "to the final results",
        "transport" => "transport (sent → received)",
        _ => "end to end",
    };
    let mut groups: Vec<(&str, Vec<Vec<String>>)> = Vec::new();
    let mut push = |group: &'static str, path: &str, p: &Value| {
        let ms = |k: &str| p[k].as_f64().map(|v| fixed(v, 2)).unwrap_or("-".into());
        let row = vec![human(path), ms("p50"), ms("p95"), ms("max"), num(&p["n"])];
        match groups.iter_mut().find(|g| g.0 == group) {
            Some(g) => g.1.push(row),
            None => groups.push((group, vec![row])),
        }
    };
    for (name, v) in lat {
        if v.get("p50").is_some() {
            push(group_name("end"), name, v);
        } else if let Some(m) = v.as_object() {
            for (path, p) in m.iter().filter(|(_, p)| p.get("p50").is_some()) {
                push(group_name(name), path, p);
            }
        }
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
pub fn node_reports(run: &Value) -> String {
    let mut h = String::from(
        "<details id=\"nodes\"><summary>Node reports and parameters</summary><div class=\"flex\">",
    );
    for (id, r) in run["stages"].as_object().into_iter().flatten() {
        let mut rows = Vec::new();
        flatten("", r, &mut rows);
        if let Some(p) = run["parameters"][id.as_str()].as_object() {
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

/// Stage (dashed) and registered (solid) tile outlines, to scale, y down as in the maps.
fn layout_svg(tiles: &[Value], scan: &Value) -> String {
    let pitch_x = scan["pitch_x_um"].as_f64().unwrap_or(1.0);
    let pitch_y = scan["pitch_y_um"].as_f64().unwrap_or(1.0);
    let w_um = scan["tile_width_px"].as_f64().unwrap_or(0.0) * pitch_x;
    let h_um = scan["tile_height_px"].as_f64().unwrap_or(0.0) * pitch_y;
    let pos = |t: &Value, x: &str, y: &str| Some((t[x].as_f64()?, t[y].as_f64()?));
    let mut xs = Vec::new();
    let mut ys = Vec::new();
    for t in tiles {
        for (x, y) in [pos(t, "stage_x_um", "stage_y_um"), pos(t, "x_um", "y_um")]
            .into_iter()
            .flatten()
        {
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
        if let Some((x, y)) = pos(t, "stage_x_um", "stage_y_um") {
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
        if let Some((x, y)) = pos(t, "x_um", "y_um") {
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
                num(&t["index"]),
                esc(t["placed_by"].as_str().unwrap_or("?")),
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
