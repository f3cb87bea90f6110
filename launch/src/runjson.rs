//! run.json (DESIGN §6): the scan, every tile's final position and how it was placed, every
//! pair's registration, latencies, message counts, parameters and the files written.

use std::collections::BTreeMap;
use std::path::Path;
use std::time::Duration;

use anyhow::{anyhow, Result};
#[cfg(test)]
use serde_json::Value;
use surfstream_core::record::{
    self, GraphRef, MatcherReport, MeshReport, MessageCounts, NodeRecord, OutputChoice, OverPlan,
    PeakRss, ReplayReport, RunRecord, TileRecord,
};
use surfstream_runtime::graph::GraphFile;
use surfstream_runtime::latency;
use surfstream_runtime::memory::node_shares;
use surfstream_runtime::node::NodeReport;

/// How a run ended: what run.json says of it besides the nodes' reports.
pub struct RunEnd<'a> {
    /// "launch" or "run".
    pub mode: &'a str,
    pub elapsed: Duration,
    pub deviation: crate::deviation::Settings,
    pub outputs: &'a crate::outputs::RunOutputs,
}

/// Writes `<out>/run.json` and report.html (the verdict printed at the end reads run.json),
/// then removes what the output set does not keep (after Table 6 and the report read it):
/// run.json lists the files that stay.
pub fn write(
    graph: &GraphFile,
    origin: &Path,
    reports: &[NodeReport],
    end: &RunEnd<'_>,
) -> Result<()> {
    let RunEnd {
        mode,
        elapsed,
        deviation,
        outputs,
    } = *end;
    let out = &graph.graph.out_dir;
    let replay: Option<ReplayReport> = read_report(reports)?;
    let matcher: Option<MatcherReport> = read_report(reports)?;

    // Tiles: stage facts from the source, placement from the matcher, joined on index.
    let mut tiles: BTreeMap<u32, TileRecord> = replay
        .iter()
        .flat_map(|r| &r.tiles)
        .map(|t| {
            let tile = TileRecord {
                source: t.clone(),
                placement: None,
            };
            (t.index, tile)
        })
        .collect();
    for t in matcher.iter().flat_map(|m| &m.tiles) {
        if let Some(tile) = tiles.get_mut(&t.index) {
            tile.placement = Some(t.placement.clone());
        }
    }
    // The mesher's report is read for its two times only (the stages keep every report as
    // the node wrote it).
    let mesh_done = read_report::<MeshReport>(reports)?.map(|m| (m.t_acquired_ns, m.t_written_ns));
    let messages = reports
        .iter()
        .map(|r| {
            let count = |m: &BTreeMap<String, Vec<_>>| -> BTreeMap<String, u64> {
                m.iter().map(|(k, v)| (k.clone(), v.len() as u64)).collect()
            };
            let counts = MessageCounts {
                received: count(&r.stats.received),
                sent: count(&r.stats.sent),
                deliveries: r.stats.deliveries.clone(),
            };
            (r.node_id.clone(), counts)
        })
        .collect();
    let stages = reports
        .iter()
        .map(|r| (r.node_id.clone(), r.report.clone()))
        .collect();
    let parameters = graph
        .nodes
        .iter()
        .map(|n| Ok((n.id.clone(), record::to_value(&n.params)?)))
        .collect::<Result<_, record::RecordError>>()?;
    let mut files = list_files(out)?;
    files.push("run.json".into());
    files.sort();
    let mut run = RunRecord {
        surfstream_version: env!("CARGO_PKG_VERSION").into(),
        mode: mode.into(),
        graph: GraphRef {
            name: graph.graph.name.clone(),
            file: origin.display().to_string(),
        },
        scan: replay.map(|r| r.scan),
        tiles: tiles.into_values().collect(),
        pairs: matcher.map(|m| m.pairs).unwrap_or_default(),
        latency_ms: latency::summarize(reports, mesh_done),
        messages,
        stages,
        parameters,
        files,
        outputs: None,
        elapsed_s: elapsed.as_secs_f64(),
        deviation: None,
        peak_rss: None,
    };
    let full = outputs.choice == OutputChoice::Full;
    crate::deviation::attach(out, &mut run, deviation.threshold_percent, full)?;
    let removals = crate::outputs::plan(out, outputs.choice, &outputs.carried)?;
    run.files
        .retain(|f| !crate::outputs::is_removed(f, &removals));
    run.outputs = Some(crate::outputs::record(outputs.choice, &removals));
    // After the deviation pass, which loads whole rasters in the launcher.
    run.peak_rss = Some(peak_rss(graph, reports, mode));
    let path = out.join("run.json");
    // Through a JSON value: its keys come out sorted, as in every run.json so far.
    let value = record::to_value(&run)?;
    surfstream_core::fsutil::write_atomic(&path, |w| {
        serde_json::to_writer_pretty(w, &value).map_err(|e| anyhow!("{}: {e}", path.display()))
    })?;
    crate::report::write(out)?;
    crate::outputs::remove(out, &removals)
}

/// The report of the first node of `T`'s kind as its record; a report that does not read as
/// its record is a bug in that node, named.
fn read_report<T: NodeRecord>(reports: &[NodeReport]) -> Result<Option<T>> {
    reports
        .iter()
        .find(|r| r.node_kind == T::NODE_KIND && !r.report.is_null())
        .map(|r| record::from_value(&r.report, &format!("node '{}' report", r.node_id)))
        .transpose()
        .map_err(|e| anyhow!(e))
}

/// Peak resident memory (VmHWM) of the launcher and of every node as it finished, bytes, each
/// against its share of the memory plan. Under `run` the nodes are threads of the launcher's
/// process, so `process_bytes` is the run's peak and is set against the whole budget; under
/// `launch` each node is its own process, set against its share, and the run held at most the
/// sum.
fn peak_rss(graph: &GraphFile, reports: &[NodeReport], mode: &str) -> PeakRss {
    let launcher = surfstream_runtime::node::peak_rss_bytes();
    let nodes: Vec<(&str, &str, Option<u64>)> = reports
        .iter()
        .map(|r| (r.node_id.as_str(), r.node_kind.as_str(), r.peak_rss_bytes))
        .collect();
    let budget = graph.graph.memory_budget_gb.map(|gb| (gb * 1e9) as u64);
    peak_record(launcher, &nodes, budget, mode, graph.graph.memory_budget_gb)
}

/// [`peak_rss`] from its figures: the launcher's peak, each node's (id, kind, peak), the budget.
fn peak_record(
    launcher: Option<u64>,
    nodes: &[(&str, &str, Option<u64>)],
    budget_bytes: Option<u64>,
    mode: &str,
    memory_budget_gb: Option<f64>,
) -> PeakRss {
    let node_sum: u64 = nodes.iter().filter_map(|n| n.2).sum();
    let run_peak = if mode == "launch" {
        launcher.map(|l| l + node_sum)
    } else {
        launcher
    };
    let kinds: Vec<&str> = nodes.iter().map(|n| n.1).collect();
    let shares: Vec<u64> = budget_bytes
        .map(|b| node_shares(b, &kinds))
        .unwrap_or_default();
    let over_plan = match (budget_bytes, mode) {
        (None, _) => Vec::new(),
        (Some(b), "run") => launcher
            .filter(|&p| p > b)
            .map(|p| OverPlan {
                part: "run".into(),
                peak_bytes: p,
                share_bytes: b,
            })
            .into_iter()
            .collect(),
        (Some(_), _) => nodes
            .iter()
            .zip(&shares)
            .filter_map(|(n, &share)| {
                n.2.filter(|&p| p > share).map(|p| OverPlan {
                    part: n.0.into(),
                    peak_bytes: p,
                    share_bytes: share,
                })
            })
            .collect(),
    };
    PeakRss {
        process_bytes: launcher,
        nodes_bytes: nodes.iter().map(|n| (n.0.to_string(), n.2)).collect(),
        run_bytes_at_most: run_peak,
        memory_budget_gb,
        shares_bytes: nodes
            .iter()
            .zip(&shares)
            .map(|(n, &s)| (n.0.to_string(), s))
            .collect(),
        over_plan,
        source: "VmHWM of /proc/self/status, read by each node as it finished and by the launcher after the deviation pass (the report.html written after it is not included); shares: the memory plan's (surfstream_runtime::memory::node_shares)".into(),
    }
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

/// A whole run record from the fields a test cares about: `partial`'s keys over a complete
/// record; its scan, tiles and latency merged over complete ones (a tile with `placed_by` gets
/// a matcher placement).
#[cfg(test)]
pub(crate) fn test_record(partial: Value) -> RunRecord {
    use serde_json::json;
    fn merge(base: &mut Value, over: &Value) {
        if let (Some(b), Some(o)) = (base.as_object_mut(), over.as_object()) {
            for (k, v) in o {
                b.insert(k.clone(), v.clone());
            }
        }
    }
    let mut run = json!({
        "surfstream_version": "0", "mode": "run", "graph": { "name": "g", "file": "g.toml" },
        "scan": null, "tiles": [], "pairs": [], "messages": {}, "stages": {}, "parameters": {},
        "files": [], "elapsed_s": 0.0,
    });
    merge(&mut run, &partial);
    if partial["scan"].is_object() {
        let mut scan = json!({ "source": "simulated", "name": "g", "rows": 1, "cols": 1,
            "tile_width_px": 8, "tile_height_px": 8, "pitch_x_um": 1.0, "pitch_y_um": 1.0,
            "overlap": [0.1, 0.1], "specimen": "generated", "truth_file": "truth.json" });
        merge(&mut scan, &partial["scan"]);
        run["scan"] = scan;
    }
    let tiles: Vec<Value> = partial["tiles"]
        .as_array()
        .into_iter()
        .flatten()
        .map(|t| {
            let mut tile = json!({ "index": 0, "row": 0, "col": 0, "stage_x_um": 0.0,
                "stage_y_um": 0.0 });
            if t.get("placed_by").is_some() {
                let placed = json!({ "x_um": 0.0, "y_um": 0.0, "placed_by": "registration",
                    "links_tried": 1, "piston_um": 0.0, "tilt_x_um_per_px": 0.0,
                    "tilt_y_um_per_px": 0.0 });
                merge(&mut tile, &placed);
                tile["streaming"] = placed;
                merge(&mut tile, &json!({ "links_accepted": 1, "quality": 0.9 }));
            }
            merge(&mut tile, t);
            tile
        })
        .collect();
    run["tiles"] = json!(tiles);
    let mut latency = json!({ "final_frames": {}, "hops": {}, "transport": {} });
    merge(&mut latency, &partial["latency_ms"]);
    run["latency_ms"] = latency;
    for st in run["stages"]
        .as_object_mut()
        .into_iter()
        .flat_map(|s| s.values_mut())
    {
        if st.get("triangles").is_some() {
            *st = test_mesh_report(st, merge);
        }
    }
    if partial["deviation"].is_object() {
        run["deviation"] = test_table6(&partial["deviation"], merge);
    }
    serde_json::from_value(run).expect("a complete run record")
}

/// A complete Table 6 from the fields a test gives (the rest: empty, passing, 5 %).
#[cfg(test)]
fn test_table6(partial: &Value, merge: fn(&mut Value, &Value)) -> Value {
    use serde_json::json;
    let complete = |base: Value, over: &Value| {
        let mut base = base;
        merge(&mut base, over);
        base
    };
    let mut dev = complete(
        json!({ "measured": "panorama.npy", "threshold_pct": 5.0, "model_tolerance_pct": null,
            "judged": ["Sa", "Sq", "Sz"], "conventions": "", "regions": [], "stages": {},
            "pass": true }),
        partial,
    );
    let regions: Vec<Value> = (partial["regions"].as_array().into_iter().flatten())
        .map(|r| {
            complete(
                json!({ "name": "", "row0": 0, "col0": 0, "rows": 0, "cols": 0 }),
                r,
            )
        })
        .collect();
    dev["regions"] = json!(regions);
    let params = |p: &Value| {
        p.is_object().then(|| {
            let none = ["Sa", "Sq", "Sp", "Sv", "Sz", "Ssk", "Sku", "Sdq", "Sdr"]
                .map(|k| (k.to_string(), Value::Null));
            complete(Value::Object(none.into_iter().collect()), p)
        })
    };
    for st in dev["stages"]
        .as_object_mut()
        .into_iter()
        .flat_map(|s| s.values_mut())
    {
        let grid = complete(
            json!({ "name": "panorama grid", "rows": 0, "cols": 0, "cell_px": 1,
                "pitch_x_um": 1.0, "pitch_y_um": 1.0 }),
            &st["grid"],
        );
        let mut full = complete(
            json!({ "regions": {}, "pass": true, "judged": true, "note": "",
                "measured": "panorama.npy", "limits_pct": { "Sa": 5.0, "Sq": 5.0, "Sz": 5.0 },
                "worst_region": null, "worst_residual_rms_pct_of_sq": null }),
            st,
        );
        full["grid"] = grid;
        for r in full["regions"]
            .as_object_mut()
            .into_iter()
            .flat_map(|r| r.values_mut())
        {
            let mut region = complete(
                json!({ "measured": null, "model": null, "deviation_pct": {},
                    "residual_rms_pct_of_sq": null, "pass": true }),
                r,
            );
            for side in ["measured", "model"] {
                region[side] = params(&region[side]).unwrap_or(Value::Null);
            }
            *r = region;
        }
        *st = full;
    }
    dev
}

/// A complete mesher report from the fields a test gives (the rest: zero, empty or null).
#[cfg(test)]
fn test_mesh_report(partial: &Value, merge: fn(&mut Value, &Value)) -> Value {
    use serde_json::json;
    let complete = |base: Value, over: &Value| {
        let mut base = base;
        merge(&mut base, over);
        base
    };
    let mut m = complete(
        json!({ "file": "surface.stl", "resampled": "mesh_resampled.npy", "sources": {},
            "t_acquired_ns": 0, "t_written_ns": 0, "live_frames_skipped": 0,
            "format": "binary", "units": "mm", "offset_um": [0.0, 0.0, 0.0], "triangles": 0,
            "top_triangles": 0, "vertices": 0, "filled_samples": 0, "base_depth_um": null,
            "watertight": true, "consistently_oriented": true, "grid_px": [0, 0],
            "pitch_um": [1.0, 1.0], "surface": "panorama", "method": "grid" }),
        partial,
    );
    let params = |p: &Value| {
        p.is_object().then(|| {
            let none = json!({ "sa_um": null, "sq_um": null, "sz_um": null, "sdr_percent": null });
            complete(none, p)
        })
    };
    if partial["fidelity"].is_object() {
        let f = &partial["fidelity"];
        let mut fidelity = complete(
            json!({ "epsilon_um": null, "bound_met": true, "field": null, "mesh": null }),
            f,
        );
        fidelity["error"] = complete(
            json!({ "max_um": null, "rms_um": null, "samples": 0, "uncovered": 0 }),
            &f["error"],
        );
        for side in ["field", "mesh"] {
            fidelity[side] = params(&f[side]).unwrap_or(Value::Null);
        }
        m = complete(
            json!({ "kind": "solid", "offset_rule": "", "surface_triangles": 0,
                "missing_samples": 0, "missing": "fill", "budget_reached": false }),
            &m,
        );
        if partial.get("method").is_none() {
            m["method"] = json!("adaptive");
        }
        m["fidelity"] = fidelity;
    }
    if partial["tolerance"].is_object() {
        let t = &partial["tolerance"];
        let mut tolerance = complete(
            json!({ "target_share": 0.5, "region_px": 0, "regions": 0, "measured_px": 0,
                "met": true, "surface_triangles": 0, "triangles_per_measured_px": null,
                "epsilon_um": null, "reason": null, "region_fits": [], "curve": [] }),
            t,
        );
        let fits: Vec<Value> = (t["region_fits"].as_array().into_iter().flatten())
            .map(|w| {
                complete(
                    json!({ "region": "", "samples": 0, "measured_um": [null, null, null],
                        "deviation_pct": [null, null, null], "residual_pct_of_sq": null }),
                    w,
                )
            })
            .collect();
        tolerance["region_fits"] = json!(fits);
        m["tolerance"] = tolerance;
    }
    if partial["outliers"].is_object() {
        m["outliers"] = complete(
            json!({ "rule": "", "threshold_um": null, "count": 0, "largest": [], "sz_um": null,
                "sz_without_spikes_um": null, "sz_effect_pct": null, "policy": "keep",
                "removed": 0 }),
            &partial["outliers"],
        );
    }
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    const MB: u64 = 1_000_000;

    fn graph_nodes() -> Vec<(&'static str, &'static str, Option<u64>)> {
        vec![
            ("stage", "replay", Some(40 * MB)),
            ("fusion", "fusion", Some(200 * MB)),
            ("mesher", "mesher", Some(90 * MB)),
            ("recorder", "recorder", None),
        ]
    }

    #[test]
    fn under_launch_each_node_is_set_against_its_share() {
        // 400 MB: fusion and mesher 100 MB each, stage and recorder 100 MB each.
        let p = peak_record(
            Some(30 * MB),
            &graph_nodes(),
            Some(400 * MB),
            "launch",
            Some(0.4),
        );
        assert_eq!(p.shares_bytes["fusion"], 100 * MB);
        assert_eq!(p.shares_bytes["stage"], 100 * MB);
        assert_eq!(p.shares_bytes.values().sum::<u64>(), 400 * MB);
        assert_eq!(
            p.over_plan,
            [OverPlan {
                part: "fusion".into(),
                peak_bytes: 200 * MB,
                share_bytes: 100 * MB
            }]
        );
        assert_eq!(p.run_bytes_at_most, Some(360 * MB));
    }

    #[test]
    fn under_run_the_one_process_is_set_against_the_budget() {
        let within = peak_record(Some(390 * MB), &graph_nodes(), Some(400 * MB), "run", None);
        assert!(within.over_plan.is_empty(), "{:?}", within.over_plan);
        let over = peak_record(Some(450 * MB), &graph_nodes(), Some(400 * MB), "run", None);
        assert_eq!(over.over_plan.len(), 1);
        assert_eq!(over.over_plan[0].part, "run");
        assert_eq!(over.over_plan[0].share_bytes, 400 * MB);
        let unplanned = peak_record(Some(450 * MB), &graph_nodes(), None, "run", None);
        assert!(unplanned.shares_bytes.is_empty() && unplanned.over_plan.is_empty());
    }
}
