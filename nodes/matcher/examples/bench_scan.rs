//! Times the default registration (phase correlation, NCC-verified candidates, sub-pixel) on
//! every grid-neighbour pair of a scan directory, the same tiles the anchors time
//! (`stitch_anchors.py generate-scale` writes 3 x 3 grids of 1024 px tiles), and the global
//! solve (positions and z) over the scan. Prints the per-pair median over `RUNS` rounds, the
//! error against ground_truth.json when it is beside scan.toml, and the thread count.
//!
//! `RAYON_NUM_THREADS=1 cargo run --release -p surfstream-matcher --example bench_scan -- DIR/scan.toml [RUNS]`

#[path = "support/scan.rs"]
mod support;

use std::path::Path;
use std::time::Instant;

use anyhow::{anyhow, Result};
use support::{median, Scan};
use surfstream_core::raster::RasterView;
use surfstream_matcher::{
    solve_planes, solve_positions, Link, PhaseCorrelator, PhaseParams, ScanTruth, SolveParams,
};

/// CPU time of the whole process (all threads, user + system), s, from /proc/self/stat (clock
/// ticks, assumed 100 per second as on Linux); `None` elsewhere. Wall time alone says little on
/// a loaded machine.
fn process_cpu_s() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the command name (which may hold spaces) start at "state" (field 3).
    let rest = &stat[stat.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let utime: f64 = f.get(11)?.parse().ok()?;
    let stime: f64 = f.get(12)?.parse().ok()?;
    Some((utime + stime) / 100.0)
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let scan = Path::new(
        args.get(1)
            .ok_or_else(|| anyhow!("usage: bench_scan SCAN.toml [RUNS]"))?,
    );
    let runs: usize = args.get(2).map(|s| s.parse()).transpose()?.unwrap_or(5);
    // `--pairs` as third argument: print every pair's answer and candidates (first round).
    let verbose = args.get(3).is_some_and(|s| s == "--pairs");
    let dir = scan.parent().unwrap_or(Path::new("."));
    let tiles = Scan::load(scan)?;
    let truth = ScanTruth::read(&dir.join("ground_truth.json")).ok();
    let pairs = tiles.neighbour_pairs();
    let params = PhaseParams::default();
    let mut corr = PhaseCorrelator::new();
    let mut per_pair_ms = Vec::new();
    let mut offsets = vec![None; pairs.len()];
    let cpu0 = process_cpu_s();
    for _ in 0..runs {
        for (k, &(a, b)) in pairs.iter().enumerate() {
            let nominal = tiles.nominal_offset_px(a, b);
            let t0 = Instant::now();
            let r = corr.register(tiles.raster(a)?, tiles.raster(b)?, nominal, &params);
            per_pair_ms.push(t0.elapsed().as_secs_f64() * 1e3);
            offsets[k] = r.offset_px;
            if verbose && per_pair_ms.len() <= pairs.len() {
                let t = truth
                    .as_ref()
                    .and_then(|t| t.true_offset_px(a as u64, b as u64));
                let err = |o: [f64; 2]| t.map(|t| [o[0] - t[0], o[1] - t[1]]);
                println!(
                    "pair {a}-{b}: offset {:?} err {:?} ncc {:.3} roundness {:.3} {:?}",
                    r.offset_px,
                    r.offset_px.and_then(err),
                    r.ncc,
                    r.peak_roundness,
                    r.rejection.as_ref().map(|e| e.to_string())
                );
                for c in &r.candidates {
                    let o = [c.offset_px[0] as f64, c.offset_px[1] as f64];
                    println!(
                        "    candidate {:?} err {:?} peak {:.3} ncc {:.3}",
                        c.offset_px,
                        err(o),
                        c.peak,
                        c.ncc
                    );
                }
            }
        }
    }
    let cpu_per_pair_ms = cpu0
        .zip(process_cpu_s())
        .map(|(t0, t1)| (t1 - t0) * 1e3 / per_pair_ms.len() as f64);
    let stage_px: Vec<[f64; 2]> = (0..tiles.tiles.len()).map(|i| tiles.stage_px(i)).collect();
    let links: Vec<Link> = pairs
        .iter()
        .zip(&offsets)
        .filter_map(|(&(a, b), o)| {
            o.map(|offset_px| Link {
                a,
                b,
                offset_px,
                sigma_px: 0.05,
            })
        })
        .collect();
    let t0 = Instant::now();
    let sol = solve_positions(&stage_px, &links, &SolveParams::default())?;
    let solve_ms = t0.elapsed().as_secs_f64() * 1e3;
    let rasters: Vec<RasterView<'_, f32>> = (0..tiles.tiles.len())
        .map(|i| tiles.raster(i))
        .collect::<Result<_>>()?;
    let t0 = Instant::now();
    let planes = solve_planes(&rasters, &sol.positions_px, &pairs, 0, 2)?;
    let z_ms = t0.elapsed().as_secs_f64() * 1e3;
    println!(
        "{}: {} tiles of {} px (rows x cols), {} pairs, {} accepted, threads {}",
        scan.display(),
        tiles.tiles.len(),
        tiles.shape,
        pairs.len(),
        links.len(),
        rayon::current_num_threads()
    );
    println!(
        "per pair: median {:.1} ms over {} registrations; global positions {:.2} ms, z alignment {:.1} ms (rms {:.4} -> {:.4} um)",
        median(per_pair_ms.clone()),
        per_pair_ms.len(),
        solve_ms,
        z_ms,
        planes.rms_before_um,
        planes.rms_residual_um
    );
    if let Some(c) = cpu_per_pair_ms {
        println!("per pair: process CPU (all threads) {c:.1} ms, mean over the registrations");
    }
    if let Some(t) = truth {
        let mut worst: f64 = 0.0;
        for (&(a, b), o) in pairs.iter().zip(&offsets) {
            if let (Some(o), Some(t)) = (o, t.true_offset_px(a as u64, b as u64)) {
                worst = worst.max((o[0] - t[0]).hypot(o[1] - t[1]));
            }
        }
        println!("worst pair error vs ground truth: {worst:.3} px");
    }
    Ok(())
}
