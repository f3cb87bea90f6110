//! Latency summaries (DESIGN §2: every frame knows its causing tile's acquisition time).
//!
//! From the traces that every node keeps ([`crate::node::NodeStats`]) this computes, per stage
//! output, the end-to-end latency from tile acquisition, the per-hop latency between stages
//! for the same tile, and the transport cost of every channel (receive time - send time).

use std::collections::BTreeMap;

use crate::node::NodeReport;
use surfstream_core::frame::flags;
/// The records run.json's `latency_ms` is made of (shared with its readers).
pub use surfstream_core::record::{LatencySummary, Percentiles};

/// Nearest-rank percentiles of durations in nanoseconds, reported in ms.
pub fn percentiles_ms(samples_ns: &[u64]) -> Option<Percentiles> {
    if samples_ns.is_empty() {
        return None;
    }
    let mut v = samples_ns.to_vec();
    v.sort_unstable();
    let rank = |p: f64| {
        let idx = ((p / 100.0) * v.len() as f64).ceil() as usize;
        v[idx.clamp(1, v.len()) - 1] as f64 / 1e6
    };
    Some(Percentiles {
        p50: rank(50.0),
        p95: rank(95.0),
        max: rank(100.0),
        n: v.len(),
    })
}

/// The stage outputs of the default pipeline, in order, as (name, node kind, port).
const STAGES: &[(&str, &str, &str)] = &[
    ("registration", "matcher", "registrations"),
    ("panorama", "fusion", "panorama"),
    ("datum", "wavelet", "datum"),
    ("roughness", "wavelet", "roughness"),
    ("pooled", "wavelet", "pooled"),
];

/// Computes the summary from all node reports of one run. `mesh_done` is the mesher's
/// (causing tile's acquisition time, mesh written time) if a mesh was written.
pub fn summarize(reports: &[NodeReport], mesh_done: Option<(u64, u64)>) -> LatencySummary {
    let mut s = LatencySummary::default();
    // First send time per (stage, tile), ignoring end-of-scan markers.
    let mut first_sent: BTreeMap<&str, BTreeMap<u32, u64>> = BTreeMap::new();
    for (stage, kind, port) in STAGES {
        let mut samples = Vec::new();
        let mut finals = Vec::new();
        let mut first = BTreeMap::new();
        for r in reports.iter().filter(|r| r.node_kind == *kind) {
            for e in r.stats.sent.get(*port).into_iter().flatten() {
                if e.flags & flags::END_OF_SCAN != 0 || e.t_acquired_ns == 0 {
                    continue;
                }
                let latency = e.t_sent_ns.saturating_sub(e.t_acquired_ns);
                if e.flags & flags::FINAL != 0 {
                    finals.push(latency);
                    continue;
                }
                samples.push(latency);
                first.entry(e.tile_index).or_insert(e.t_sent_ns);
            }
        }
        if let Some(p) = percentiles_ms(&samples) {
            s.end_to_end.insert(format!("tile_to_{stage}"), p);
        }
        if let Some(p) = percentiles_ms(&finals) {
            s.final_frames
                .insert(format!("last_tile_to_final_{stage}"), p);
        }
        first_sent.insert(stage, first);
    }
    if let Some((t_acq, t_done)) = mesh_done {
        if let Some(p) = percentiles_ms(&[t_done.saturating_sub(t_acq)]) {
            s.final_frames.insert("last_tile_to_mesh".into(), p);
        }
    }
    for pair in [
        ("registration", "panorama"),
        ("panorama", "datum"),
        ("datum", "pooled"),
    ] {
        let (a, b) = (&first_sent[pair.0], &first_sent[pair.1]);
        let samples: Vec<u64> = b
            .iter()
            .filter_map(|(t, tb)| a.get(t).map(|ta| tb.saturating_sub(*ta)))
            .collect();
        if let Some(p) = percentiles_ms(&samples) {
            s.hops.insert(format!("{}_to_{}", pair.0, pair.1), p);
        }
    }
    // Transport: every received event knows when it was sent.
    for r in reports {
        for (port, events) in &r.stats.received {
            let samples: Vec<u64> = events
                .iter()
                .filter_map(|e| e.t_received_ns.map(|t| t.saturating_sub(e.t_sent_ns)))
                .collect();
            if let Some(p) = percentiles_ms(&samples) {
                s.transport.insert(format!("{} <- {}", r.node_id, port), p);
            }
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearest_rank() {
        let v: Vec<u64> = (1..=100).map(|i| i * 1_000_000).collect();
        let p = percentiles_ms(&v).unwrap();
        assert_eq!((p.p50, p.p95, p.max, p.n), (50.0, 95.0, 100.0, 100));
        assert!(percentiles_ms(&[]).is_none());
        let p = percentiles_ms(&[3_000_000]).unwrap();
        assert_eq!((p.p50, p.max), (3.0, 3.0));
    }
}
