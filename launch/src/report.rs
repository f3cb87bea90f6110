//! `report.html`: one self-contained page for people, written beside run.json. PNG previews are
//! inlined as base64, the tile layout (stage vs registered positions) is inline SVG drawn from
//! run.json's tiles, and every table is taken from run.json, so the page needs no other file.

use std::fmt::Write as _;
use std::io::Write as _;
use std::path::Path;

use anyhow::{anyhow, Context, Result};
use serde_json::Value;

/// Writes `<out>/report.html` from `<out>/run.json` and the PNG previews present in `out`.
pub fn write(out: &Path) -> Result<()> {
    let run_path = out.join("run.json");
    let text = std::fs::read_to_string(&run_path)
        .with_context(|| format!("{}: reading run.json", run_path.display()))?;
    let run: Value = serde_json::from_str(&text)
        .with_context(|| format!("{}: not valid JSON", run_path.display()))?;
    let html = render(&run, out)?;
    let path = out.join("report.html");
    surfstream_core::fsutil::write_atomic(&path, |w| {
        w.write_all(html.as_bytes())
            .map_err(|e| anyhow!("{}: {e}", path.display()))
    })
}

/// The page for one run; `out` is where the PNG previews are looked for. One section after
/// the other; a section whose data run.json lacks is left out.
pub fn render(run: &Value, out: &Path) -> Result<String> {
    let mut h = String::new();
    header(&mut h, run);
    previews(&mut h, out);
    tile_layout(&mut h, run);
    registrations(&mut h, run);
    mesh(&mut h, run);
    deviation_tables(&mut h, &run["deviation"]);
    latencies(&mut h, run);
    stage_reports(&mut h, run);
    node_parameters(&mut h, run);
    h.push_str("</body></html>\n");
    Ok(h)
}

/// The document head (title, style) and the run's one-line summary.
fn header(h: &mut String, run: &Value) {
    let name = run["graph"]["name"].as_str().unwrap_or("run");
    let _ = write!(
        h,
        "<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\"><title>surfstream: {}</title>\n\
         <style>body{{font-family:sans-serif;margin:24px;color:#222;max-width:1340px}}\
         h1{{margin-bottom:4px}}h2{{border-bottom:1px solid #ccc;padding-bottom:2px;margin-top:28px}}\
         table{{border-collapse:collapse;font-size:13px;margin:6px 0}}\
         td,th{{border:1px solid #ccc;padding:2px 8px;text-align:right}}\
         th{{background:#f2f2f2}}td.k{{text-align:left;font-family:monospace}}\
         .previews{{display:flex;flex-wrap:wrap;gap:12px}}.previews figure{{margin:0}}\
         .previews img{{width:320px;border:1px solid #ccc;image-rendering:pixelated}}\
         figcaption{{font-size:13px;text-align:center}}.flex{{display:flex;gap:24px;flex-wrap:wrap;align-items:flex-start}}\
         </style></head><body>\n",
        esc(name)
    );
    let _ = writeln!(
        h,
        "<h1>surfstream run: {}</h1><p>mode {}, {:.2} s, surfstream {}, graph file {}</p>",
        esc(name),
        esc(run["mode"].as_str().unwrap_or("?")),
        run["elapsed_s"].as_f64().unwrap_or(0.0),
        esc(run["surfstream_version"].as_str().unwrap_or("?")),
        esc(run["graph"]["file"].as_str().unwrap_or("?")),
    );
}

/// The PNG previews present in `out`, inlined.
fn previews(h: &mut String, out: &Path) {
    h.push_str("<h2>Previews</h2><div class=\"previews\">");
    for (file, caption) in [
        ("panorama.png", "panorama"),
        ("datum.png", "datum"),
        ("roughness.png", "roughness"),
        ("pooled.png", "pooled"),
    ] {
        let p = out.join(file);
        if let Ok(bytes) = std::fs::read(&p) {
            let _ = write!(
                h,
                "<figure><img alt=\"{caption}\" src=\"data:image/png;base64,{}\"><figcaption>{caption}</figcaption></figure>",
                base64(&bytes)
            );
        }
    }
    h.push_str("</div>\n");
}

/// Stage vs registered tile positions: an SVG and a table.
fn tile_layout(h: &mut String, run: &Value) {
    if let Some(tiles) = run["tiles"].as_array().filter(|t| !t.is_empty()) {
        h.push_str("<h2>Tile layout</h2><div class=\"flex\">");
        h.push_str(&layout_svg(tiles, &run["scan"]));
        let rows: Vec<Vec<String>> = tiles
            .iter()
            .map(|t| {
                vec![
                    num(&t["index"]),
                    num(&t["row"]),
                    num(&t["col"]),
                    num(&t["stage_x_um"]),
                    num(&t["stage_y_um"]),
                    num(&t["x_um"]),
                    num(&t["y_um"]),
                    num(&t["placed_by"]),
                    num(&t["quality"]),
                ]
            })
            .collect();
        h.push_str(&table(
            &[
                "tile",
                "row",
                "col",
                "stage x um",
                "stage y um",
                "x um",
                "y um",
                "placed by",
                "quality",
            ],
            &rows,
        ));
        h.push_str("</div>\n");
    }
}

/// Every pair's registration.
fn registrations(h: &mut String, run: &Value) {
    if let Some(pairs) = run["pairs"].as_array().filter(|p| !p.is_empty()) {
        h.push_str("<h2>Registrations</h2>");
        let rows: Vec<Vec<String>> = pairs
            .iter()
            .map(|p| {
                vec![
                    format!("{}-{}", num(&p["a"]), num(&p["b"])),
                    num(&p["direction"]),
                    num(&p["ncc"]),
                    num(&p["accepted"]),
                    num(&p["offset_px"]),
                    num(&p["residual_px"]),
                ]
            })
            .collect();
        h.push_str(&table(
            &[
                "pair",
                "direction",
                "NCC",
                "accepted",
                "offset px",
                "residual px",
            ],
            &rows,
        ));
    }
}

/// The mesher's report and its fidelity (height field vs re-sampled mesh).
fn mesh(h: &mut String, run: &Value) {
    if let Some(mesh) = run["stages"]
        .as_object()
        .and_then(|s| s.values().find(|v| v.get("triangles").is_some()))
    {
        h.push_str("<h2>Mesh</h2><div class=\"flex\">");
        let f = &mesh["fidelity"];
        if f.is_object() {
            let rows: Vec<Vec<String>> = [
                ("Sa um", "sa_um"),
                ("Sq um", "sq_um"),
                ("Sz um", "sz_um"),
                ("Sdr %", "sdr_percent"),
            ]
            .iter()
            .map(|(label, k)| {
                vec![
                    (*label).to_string(),
                    num(&f["field"][k]),
                    num(&f["mesh"][k]),
                ]
            })
            .collect();
            h.push_str(&table(
                &["parameter", "height field", "mesh resampled"],
                &rows,
            ));
        }
        h.push_str(&kv_table(mesh, &["fidelity"]));
        h.push_str("</div>\n");
    }
}

/// Latency percentiles per path.
fn latencies(h: &mut String, run: &Value) {
    if let Some(lat) = run["latency_ms"].as_object() {
        h.push_str("<h2>Latencies (ms)</h2>");
        let mut rows = Vec::new();
        for (name, group) in lat {
            // Either a group of paths ({"hops": {"a_to_b": {p50...}}}) or one path.
            let paths: Vec<(&String, &Value)> = if group.get("p50").is_some() {
                vec![(name, group)]
            } else {
                group
                    .as_object()
                    .map(|g| g.iter().filter(|(_, p)| p.get("p50").is_some()).collect())
                    .unwrap_or_default()
            };
            {
                for (k, p) in paths {
                    rows.push(vec![
                        k.to_string(),
                        num(&p["p50"]),
                        num(&p["p95"]),
                        num(&p["max"]),
                        num(&p["n"]),
                    ]);
                }
            }
        }
        h.push_str(&table(&["path", "p50", "p95", "max", "n"], &rows));
    }
}

/// Whatever else the stages report (parameters, deviations, SSIM, wavelet levels), flattened.
fn stage_reports(h: &mut String, run: &Value) {
    if let Some(stages) = run["stages"].as_object() {
        h.push_str("<h2>Stage reports</h2><div class=\"flex\">");
        for (id, r) in stages {
            if r.get("triangles").is_some() {
                continue;
            }
            let _ = write!(h, "<div><h3>{}</h3>", esc(id));
            h.push_str(&kv_table(r, &["tiles", "pairs"]));
            h.push_str("</div>");
        }
        h.push_str("</div>\n");
    }
}

/// Every node's parameters.
fn node_parameters(h: &mut String, run: &Value) {
    if let Some(params) = run["parameters"].as_object() {
        h.push_str("<h2>Node parameters</h2><div class=\"flex\">");
        for (id, p) in params {
            let _ = write!(h, "<div><h3>{}</h3>", esc(id));
            h.push_str(&kv_table(p, &[]));
            h.push_str("</div>");
        }
        h.push_str("</div>\n");
    }
}

/// The ISO 25178 parameters of the measured panorama per region beside those of each model
/// stage and their deviation (the reference study's Table 6), from run.json's `deviation`.
fn deviation_tables(h: &mut String, dev: &Value) {
    let Some(stages) = dev["stages"].as_object().filter(|s| !s.is_empty()) else {
        return;
    };
    let judged: Vec<&str> = dev["judged"]
        .as_array()
        .map(|j| j.iter().filter_map(Value::as_str).collect())
        .unwrap_or_default();
    let _ = write!(
        h,
        "<h2>Parameters and deviation (Table 6)</h2><p>measured: {}; overall pass: {}; {}</p>\
         <div class=\"flex\">",
        esc(dev["measured"].as_str().unwrap_or("?")),
        num(&dev["pass"]),
        esc(dev["conventions"].as_str().unwrap_or("")),
    );
    for (stage, st) in stages {
        let mut rows = Vec::new();
        for (region, r) in st["regions"].as_object().into_iter().flatten() {
            for (param, measured) in r["measured"].as_object().into_iter().flatten() {
                let mark = if judged.contains(&param.as_str()) {
                    " *"
                } else {
                    ""
                };
                rows.push(vec![
                    region.clone(),
                    format!("{param}{mark}"),
                    num(measured),
                    num(&r["model"][param]),
                    num(&r["deviation_pct"][param]),
                ]);
            }
            rows.push(vec![
                region.clone(),
                "pass".into(),
                String::new(),
                String::new(),
                num(&r["pass"]),
            ]);
        }
        let _ = write!(
            h,
            "<div><h3>{} (pass: {})</h3>",
            esc(stage),
            num(&st["pass"])
        );
        h.push_str(&table(
            &[
                "region",
                "parameter (* judged)",
                "measured",
                "model",
                "deviation %",
            ],
            &rows,
        ));
        h.push_str("</div>");
    }
    h.push_str("</div>\n");
}

/// Stage (dashed) and registered (solid) tile outlines, to scale, y down as in the previews.
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
    let scale = 460.0 / (x1 - x0).max(y1 - y0).max(1e-9);
    let (sw, sh) = ((x1 - x0) * scale + 20.0, (y1 - y0) * scale + 40.0);
    let mut s = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{sw:.0}\" height=\"{sh:.0}\" \
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
                 <text x=\"{:.1}\" y=\"{:.1}\" font-size=\"13\" fill=\"{c}\">tile {} ({})</text>",
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
        "<text x=\"10\" y=\"{:.0}\" font-size=\"12\">solid: registered position; dashed: \
         stage position; {:.0} x {:.0} um</text></svg>",
        sh - 8.0,
        x1 - x0,
        y1 - y0
    );
    s
}

/// A two-column table of an object's scalar leaves (nested keys joined with '.'), skipping
/// the top-level keys in `skip` and long arrays.
fn kv_table(v: &Value, skip: &[&str]) -> String {
    let mut rows = Vec::new();
    flatten("", v, skip, &mut rows);
    if rows.is_empty() {
        return String::new();
    }
    table(&["field", "value"], &rows)
}

fn flatten(prefix: &str, v: &Value, skip: &[&str], rows: &mut Vec<Vec<String>>) {
    match v {
        Value::Object(m) => {
            for (k, x) in m {
                if prefix.is_empty() && skip.contains(&k.as_str()) {
                    continue;
                }
                let key = if prefix.is_empty() {
                    k.clone()
                } else {
                    format!("{prefix}.{k}")
                };
                flatten(&key, x, &[], rows);
            }
        }
        Value::Array(a) if a.len() > 6 || a.iter().any(|x| x.is_object()) => {
            rows.push(vec![prefix.to_string(), format!("[{} items]", a.len())]);
        }
        _ => rows.push(vec![prefix.to_string(), num(v)]),
    }
}

fn table(head: &[&str], rows: &[Vec<String>]) -> String {
    let mut s = String::from("<table><tr>");
    for c in head {
        let _ = write!(s, "<th>{}</th>", esc(c));
    }
    s.push_str("</tr>");
    for r in rows {
        s.push_str("<tr>");
        for (i, c) in r.iter().enumerate() {
            let class = if i == 0 { " class=\"k\"" } else { "" };
            let _ = write!(s, "<td{class}>{}</td>", esc(c));
        }
        s.push_str("</tr>");
    }
    s.push_str("</table>");
    s
}

/// A value as short text: numbers to 4 significant decimals, arrays inline.
fn num(v: &Value) -> String {
    match v {
        Value::Null => "-".into(),
        Value::Number(n) => match (n.as_i64(), n.as_f64()) {
            (Some(i), _) => i.to_string(),
            (None, Some(f)) if f != 0.0 && (f.abs() < 1e-3 || f.abs() >= 1e7) => format!("{f:.4e}"),
            (None, Some(f)) => format!("{f:.4}"),
            _ => n.to_string(),
        },
        Value::String(s) => s.clone(),
        Value::Bool(b) => b.to_string(),
        Value::Array(a) => format!("[{}]", a.iter().map(num).collect::<Vec<_>>().join(", ")),
        Value::Object(_) => "{...}".into(),
    }
}

fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// Standard base64 (RFC 4648) with padding.
fn base64(bytes: &[u8]) -> String {
    const A: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut s = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for c in bytes.chunks(3) {
        let n = (u32::from(c[0]) << 16)
            | (u32::from(*c.get(1).unwrap_or(&0)) << 8)
            | u32::from(*c.get(2).unwrap_or(&0));
        for k in 0..4 {
            if k <= c.len() {
                s.push(A[(n >> (18 - 6 * k)) as usize & 63] as char);
            } else {
                s.push('=');
            }
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_matches_rfc4648_vectors() {
        for (i, o) in [
            ("", ""),
            ("f", "Zg=="),
            ("fo", "Zm8="),
            ("foo", "Zm9v"),
            ("foob", "Zm9vYg=="),
            ("fooba", "Zm9vYmE="),
            ("foobar", "Zm9vYmFy"),
        ] {
            assert_eq!(base64(i.as_bytes()), o);
        }
    }

    #[test]
    fn renders_tiles_mesh_and_escapes() {
        let run = serde_json::json!({
            "graph": {"name": "t<x>", "file": "g.toml"}, "mode": "run", "elapsed_s": 1.0,
            "scan": {"pitch_x_um": 1.0, "pitch_y_um": 1.0, "tile_width_px": 100, "tile_height_px": 100},
            "tiles": [{"index": 0, "stage_x_um": 0.0, "stage_y_um": 0.0, "x_um": 1.0, "y_um": 2.0, "placed_by": "registration"}],
            "stages": {"mesher": {"triangles": 10, "fidelity": {"field": {"sq_um": 1.0}, "mesh": {"sq_um": 0.99}}}},
            "latency_ms": {"hops": {"a_to_b": {"p50": 1.0, "p95": 2.0, "max": 3.0, "n": 4}}},
            "deviation": {"measured": "panorama.npy", "pass": false, "judged": ["Sa"],
                "stages": {"pooled": {"pass": false, "regions": {"S1": {"pass": false,
                    "measured": {"Sa": 2.0, "Sdr": 10.0}, "model": {"Sa": 2.5, "Sdr": 9.0},
                    "deviation_pct": {"Sa": 25.0, "Sdr": -10.0}}}}}},
        });
        let h = render(&run, Path::new("/nonexistent")).unwrap();
        assert!(h.contains("t&lt;x&gt;") && !h.contains("t<x>"));
        assert!(h.contains("<svg") && h.contains("stroke-dasharray"));
        assert!(h.contains("<td>0.9900</td>"));
        assert!(h.contains("a_to_b"));
        assert!(h.contains("<h2>Parameters and deviation (Table 6)</h2>"));
        assert!(h.contains("<h3>pooled (pass: false)</h3>"));
        assert!(h.contains(
            "<td class=\"k\">S1</td><td>Sa *</td><td>2.0000</td><td>2.5000</td><td>25.0000</td>"
        ));
        assert!(h.contains("<td>Sdr</td><td>10.0000</td><td>9.0000</td><td>-10.0000</td>"));
    }
}
