//! run.json (DESIGN §6): the scan, every tile's final position and how it was placed, every
//! pair's registration, latencies, message counts, parameters and the files written.

use std::collections::BTreeMap;
use std::path::Path;
use std::time::Duration;

use anyhow::{anyhow, Result};
use serde_json::{json, Map, Value};
use surfstream_runtime::graph::GraphFile;
use surfstream_runtime::latency;
use surfstream_runtime::node::NodeReport;

/// Writes `<out>/run.json` and report.html (the verdict printed at the end reads run.json).
pub fn write(
    graph: &GraphFile,
    origin: &Path,
    reports: &[NodeReport],
    mode: &str,
    elapsed: Duration,
    deviation: crate::deviation::Settings,
) -> Result<()> {
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
    let mut run = crate::deviation::attach(out, run, deviation.threshold_percent)?;
    // After the deviation pass, which loads whole rasters in the launcher.
    run["peak_rss"] = peak_rss(graph, reports, mode);
    let path = out.join("run.json");
    surfstream_core::fsutil::write_atomic(&path, |w| {
        serde_json::to_writer_pretty(w, &run).map_err(|e| anyhow!("{}: {e}", path.display()))
    })?;
    crate::report::write(out)?;
    Ok(())
}

/// Peak resident memory (VmHWM) of the launcher and of every node as it finished, bytes. Under
/// `run` the nodes are threads of the launcher's process, so `process_bytes` is the run's
/// peak; under `launch` each node is its own process and the run held at most the sum.
fn peak_rss(graph: &GraphFile, reports: &[NodeReport], mode: &str) -> Value {
    let launcher = surfstream_runtime::node::peak_rss_bytes();
    let nodes: Map<String, Value> = reports
        .iter()
        .map(|r| (r.node_id.clone(), json!(r.peak_rss_bytes)))
        .collect();
    let node_sum: u64 = reports.iter().filter_map(|r| r.peak_rss_bytes).sum();
    let run_peak = if mode == "launch" {
        launcher.map(|l| l + node_sum)
    } else {
        launcher
    };
    json!({
        "process_bytes": launcher,
        "nodes_bytes": nodes,
        "run_bytes_at_most": run_peak,
        "memory_budget_gb": graph.graph.memory_budget_gb,
        "source": "VmHWM of /proc/self/status, read by each node as it finished and by the launcher after the deviation pass (the report.html written after it is not included)",
    })
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
                // Dot files (the run marker, the failure reserve) are bookkeeping, not outputs.
                let hidden = rel
                    .file_name()
                    .is_some_and(|n| n.to_string_lossy().starts_with('.'));
                if !hidden && !name.ends_with(".partial") && name != "run.json" {
                    files.push(name);
                }
            }
        }
    }
    Ok(files)
}
