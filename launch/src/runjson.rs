//! run.json (DESIGN §6): the scan, every tile's final position and how it was placed, every
//! pair's registration, latencies, message counts, parameters and the files written.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;
use std::time::Duration;

use anyhow::{anyhow, Result};
use serde_json::{json, Map, Value};
use surfstream_runtime::graph::GraphFile;
use surfstream_runtime::latency;
use surfstream_runtime::node::NodeReport;

/// Writes `<out>/run.json`; returns a short human summary.
pub fn write(
    graph: &GraphFile,
    origin: &Path,
    reports: &[NodeReport],
    mode: &str,
    elapsed: Duration,
    deviation: crate::deviation::Settings,
) -> Result<String> {
    let out = &graph.graph.out_dir;
    let by_kind = |k: &str| reports.iter().find(|r| r.node_kind == k).map(|r| &r.report);

    // Tiles: stage facts from the source, placement from the matcher, joined on index.
    let mut tiles: BTreeMap<u64, Map<String, Value>> = BTreeMap::new();
    for kind in ["replay", "matcher"] {
        if let Some(Value::Array(list)) = by_kind(kind).and_then(|r| r.get("tiles")) {
            for t in list {
                if let (Some(i), Some(obj)) =
                    (t.get("index").and_then(Value::as_u64), t.as_object())
                {
                    tiles.entry(i).or_default().extend(obj.clone());
                }
            }
        }
    }
    let mesh_done = by_kind("mesher").and_then(|m| {
        Some((
            m.get("t_acquired_ns")?.as_u64()?,
            m.get("t_written_ns")?.as_u64()?,
        ))
    });
    let lat = latency::summarize(reports, mesh_done);
    let messages: Map<String, Value> = reports
        .iter()
        .map(|r| {
            let count = |m: &BTreeMap<String, Vec<_>>| -> Map<String, Value> {
                m.iter().map(|(k, v)| (k.clone(), json!(v.len()))).collect()
            };
            (
                r.node_id.clone(),
                json!({
                    "received": count(&r.stats.received),
                    "sent": count(&r.stats.sent),
                    "deliveries": r.stats.deliveries,
                }),
            )
        })
        .collect();
    let stages: Map<String, Value> = reports
        .iter()
        .map(|r| (r.node_id.clone(), r.report.clone()))
        .collect();
    let parameters: Map<String, Value> = graph
        .nodes
        .iter()
        .map(|n| {
            (
                n.id.clone(),
                serde_json::to_value(&n.params).unwrap_or(Value::Null),
            )
        })
        .collect();
    let mut files = list_files(out)?;
    files.push("run.json".into());
    files.sort();
    let run = json!({
        "surfstream_version": env!("CARGO_PKG_VERSION"),
        "mode": mode,
        "graph": { "name": graph.graph.name, "file": origin.display().to_string() },
        "scan": by_kind("replay").and_then(|r| r.get("scan")).cloned().unwrap_or(Value::Null),
        "tiles": tiles.into_values().collect::<Vec<_>>(),
        "pairs": by_kind("matcher").and_then(|r| r.get("pairs")).cloned().unwrap_or(json!([])),
        "latency_ms": lat,
        "messages": messages,
        "stages": stages,
        "parameters": parameters,
        "files": files,
        "elapsed_s": elapsed.as_secs_f64(),
    });
    let run = crate::deviation::attach(out, run, deviation.threshold_percent)?;
    let path = out.join("run.json");
    surfstream_core::fsutil::write_atomic(&path, |w| {
        serde_json::to_writer_pretty(w, &run).map_err(|e| anyhow!("{}: {e}", path.display()))
    })?;
    crate::report::write(out)?;
    Ok(summary(&run, &lat, out))
}

fn list_files(dir: &Path) -> Result<Vec<String>> {
    let mut files = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let entries = std::fs::read_dir(&d).map_err(|e| anyhow!("{}: {e}", d.display()))?;
        for e in entries.flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else if let Ok(rel) = p.strip_prefix(dir) {
                let name = rel.display().to_string();
                if !name.ends_with(".partial") && name != "run.json" {
                    files.push(name);
                }
            }
        }
    }
    Ok(files)
}

fn summary(run: &Value, lat: &latency::LatencySummary, out: &Path) -> String {
    let mut s = String::new();
    let tiles = run["tiles"].as_array().map(Vec::len).unwrap_or(0);
    let by_stage = run["tiles"]
        .as_array()
        .map(|t| t.iter().filter(|t| t["placed_by"] == "stage").count())
        .unwrap_or(0);
    let _ = writeln!(
        s,
        "surfstream: done in {:.2} s: {tiles} tiles ({by_stage} placed by stage position)",
        run["elapsed_s"].as_f64().unwrap_or(0.0)
    );
    let _ = writeln!(
        s,
        "latency (ms)                 p50       p95       max     n"
    );
    let rows = lat
        .end_to_end
        .iter()
        .chain(lat.hops.iter())
        .chain(lat.final_frames.iter());
    for (name, p) in rows {
        let _ = writeln!(
            s,
            "  {name:<24} {:>8.2}  {:>8.2}  {:>8.2}  {:>4}",
            p.p50, p.p95, p.max, p.n
        );
    }
    let _ = write!(s, "outputs in {} (run.json lists them)", out.display());
    s
}
