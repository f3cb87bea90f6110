//! Times the default registration (phase correlation, NCC-verified candidates, sub-pixel) on
//! every grid-neighbour pair of a scan directory, the same tiles the anchors time
//! (`stitch_anchors.py generate-scale` writes 3 x 3 grids of 1024 px tiles), and the global
//! solve (positions and z) over the scan. Prints the per-pair median over `RUNS` rounds, the
//! error against ground_truth.json when it is beside scan.toml, and the thread count.
//!
//! `RAYON_NUM_THREADS=1 cargo run --release -p surfstream-matcher --example bench_scan -- DIR/scan.toml [RUNS]`

use std::path::Path;
use std::time::Instant;

use anyhow::{anyhow, Context, Result};
use surfstream_matcher::{
    solve_planes, solve_positions, Link, PhaseCorrelator, PhaseParams, RasterRef, SolveParams,
};

struct Tile {
    row: i64,
    col: i64,
    stage_um: [f64; 2],
    heights: Vec<f32>,
    width: usize,
    height: usize,
}

fn raster(t: &Tile) -> RasterRef<'_> {
    RasterRef {
        heights: &t.heights,
        width: t.width,
        height: t.height,
    }
}

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

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
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
    let text = std::fs::read_to_string(scan).with_context(|| format!("{}", scan.display()))?;
    let doc: toml::Table = toml::from_str(&text).with_context(|| format!("{}", scan.display()))?;
    let head = doc["scan"]
        .as_table()
        .ok_or_else(|| anyhow!("{}: no [scan]", scan.display()))?;
    let num = |t: &toml::Table, k: &str| -> Result<f64> {
        t.get(k)
            .and_then(|v| v.as_float().or_else(|| v.as_integer().map(|i| i as f64)))
            .ok_or_else(|| anyhow!("{}: field {k}: expected a number", scan.display()))
    };
    let pitch = [num(head, "pitch_x_um")?, num(head, "pitch_y_um")?];
    let mut tiles = Vec::new();
    for t in doc["tile"]
        .as_array()
        .ok_or_else(|| anyhow!("no [[tile]]"))?
    {
        let t = t
            .as_table()
            .ok_or_else(|| anyhow!("tile: expected a table"))?;
        let file = t["file"]
            .as_str()
            .ok_or_else(|| anyhow!("tile.file: expected a string"))?;
        let a = surfstream_common::npy::read_npy(dir.join(file))?;
        tiles.push(Tile {
            row: num(t, "row")? as i64,
            col: num(t, "col")? as i64,
            stage_um: [num(t, "stage_x_um")?, num(t, "stage_y_um")?],
            heights: a.data,
            width: a.cols,
            height: a.rows,
        });
    }
    let truth: Option<Vec<[f64; 2]>> = std::fs::read_to_string(dir.join("ground_truth.json"))
        .ok()
        .and_then(|s| serde_json::from_str::<serde_json::Value>(&s).ok())
        .and_then(|g| {
            g["tiles"]
                .as_array()?
                .iter()
                .map(|t| {
                    Some([
                        t["true_origin_px"][0].as_f64()?,
                        t["true_origin_px"][1].as_f64()?,
                    ])
                })
                .collect()
        });
    let mut pairs = Vec::new();
    for (b, tb) in tiles.iter().enumerate() {
        for (a, ta) in tiles.iter().enumerate().take(b) {
            if (ta.row - tb.row).abs() + (ta.col - tb.col).abs() == 1 {
                pairs.push((a, b));
            }
        }
    }
    let params = PhaseParams::default();
    let mut corr = PhaseCorrelator::new();
    let mut per_pair_ms = Vec::new();
    let mut offsets = vec![None; pairs.len()];
    let cpu0 = process_cpu_s();
    for _ in 0..runs {
        for (k, &(a, b)) in pairs.iter().enumerate() {
            let nominal = [
                (tiles[b].stage_um[0] - tiles[a].stage_um[0]) / pitch[0],
                (tiles[b].stage_um[1] - tiles[a].stage_um[1]) / pitch[1],
            ];
            let t0 = Instant::now();
            let r = corr.register(raster(&tiles[a]), raster(&tiles[b]), nominal, &params);
            per_pair_ms.push(t0.elapsed().as_secs_f64() * 1e3);
            offsets[k] = r.offset_px;
            if verbose && per_pair_ms.len() <= pairs.len() {
                let t = truth.as_ref();
                let err = |o: [f64; 2]| {
                    t.map(|t| [o[0] - (t[b][0] - t[a][0]), o[1] - (t[b][1] - t[a][1])])
                };
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
    let stage_px: Vec<[f64; 2]> = tiles
        .iter()
        .map(|t| [t.stage_um[0] / pitch[0], t.stage_um[1] / pitch[1]])
        .collect();
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
    let rasters: Vec<RasterRef<'_>> = tiles.iter().map(raster).collect();
    let t0 = Instant::now();
    let planes = solve_planes(&rasters, &sol.positions_px, &pairs, 0, 2)?;
    let z_ms = t0.elapsed().as_secs_f64() * 1e3;
    println!(
        "{}: {} tiles {}x{} px, {} pairs, {} accepted, threads {}",
        scan.display(),
        tiles.len(),
        tiles[0].width,
        tiles[0].height,
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
            if let Some(o) = o {
                let e = (o[0] - (t[b][0] - t[a][0])).hypot(o[1] - (t[b][1] - t[a][1]));
                worst = worst.max(e);
            }
        }
        println!("worst pair error vs ground truth: {worst:.3} px");
    }
    Ok(())
}
