//! Times `register_pair` on synthetic 1024 x 1024 tiles at 10, 20 and 30 % overlap (horizontal
//! and vertical neighbours), 21 runs each (median and min of the wall time, and the CPU time),
//! on a one-thread rayon pool and on the default pool (`RAYON_NUM_THREADS` or all cores).
//!
//! `cargo run --release -p surfstream-matcher --example bench_pair -- [TILE_PX] [RUNS]`

#[path = "../tests/support/mod.rs"]
mod support;

use std::time::Instant;

use support::{make_pair, Pair, PairSpec};
use surfstream_core::raster::{RasterView, Shape};
use surfstream_matcher::{register_pair, PhaseCorrelator, PhaseParams};

/// (median, min) of the samples.
fn stats_ms(mut v: Vec<f64>) -> (f64, f64) {
    v.sort_by(f64::total_cmp);
    (v[v.len() / 2], v[0])
}

/// CPU time (user + system) consumed so far by the calling thread, ms; Linux only
/// (`/proc/thread-self/stat`, clock ticks of 10 ms), `None` elsewhere.
fn thread_cpu_ms() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/thread-self/stat").ok()?;
    // Fields after the parenthesised command name; utime and stime are fields 14 and 15.
    let rest = &stat[stat.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks: f64 = f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?;
    Some(ticks * 10.0)
}

struct Timing {
    /// Reused correlator: median, min (ms).
    reused: (f64, f64),
    /// One-shot `register_pair` (plans and buffers built per call): median, min (ms).
    oneshot: (f64, f64),
    /// CPU time per reused-correlator call on this thread (ms), when measurable: robust to
    /// other processes competing for the cores, meaningful on a one-thread pool only.
    cpu_ms: Option<f64>,
    /// Worst |measured - true| over x and y (px).
    worst_err_px: f64,
}

fn time_pair(pair: &Pair, runs: usize, params: &PhaseParams) -> Timing {
    let a = RasterView::new(&pair.a, Shape::new(pair.h, pair.w)).expect("synthetic tile");
    let b = RasterView::new(&pair.b, Shape::new(pair.h, pair.w)).expect("synthetic tile");
    let mut corr = PhaseCorrelator::new();
    let mut worst = 0.0f64;
    // Warm-up (plans, buffers, rayon pool).
    corr.register(a, b, pair.nominal_offset_px, params);
    let mut reused = Vec::with_capacity(runs);
    let cpu0 = thread_cpu_ms();
    for _ in 0..runs {
        let t = Instant::now();
        let r = corr.register(a, b, pair.nominal_offset_px, params);
        reused.push(t.elapsed().as_secs_f64() * 1e3);
        match r.offset_px {
            Some(o) => {
                let e = (o[0] - pair.true_offset_px[0])
                    .abs()
                    .max((o[1] - pair.true_offset_px[1]).abs());
                worst = worst.max(e);
            }
            None => worst = f64::INFINITY,
        }
    }
    let cpu_ms = match (cpu0, thread_cpu_ms()) {
        (Some(t0), Some(t1)) => Some((t1 - t0) / runs as f64),
        _ => None,
    };
    let mut oneshot = Vec::with_capacity(runs);
    for _ in 0..runs {
        let t = Instant::now();
        let _ = register_pair(a, b, pair.nominal_offset_px, params);
        oneshot.push(t.elapsed().as_secs_f64() * 1e3);
    }
    Timing {
        reused: stats_ms(reused),
        oneshot: stats_ms(oneshot),
        cpu_ms,
        worst_err_px: worst,
    }
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let tile: usize = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(1024);
    let runs: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(21);
    let params = PhaseParams::default();
    let single = match rayon::ThreadPoolBuilder::new().num_threads(1).build() {
        Ok(p) => p,
        Err(e) => {
            eprintln!("cannot build a one-thread pool: {e}");
            std::process::exit(1);
        }
    };
    println!(
        "register_pair, {tile} x {tile} px tiles, {runs} runs each; default pool = {} threads",
        rayon::current_num_threads()
    );
    println!(
        "wall times in ms as median / min; 'reuse' = one PhaseCorrelator for all runs, 'once' = \
         register_pair; '1 thread CPU' = CPU time per reused call on the one-thread pool"
    );
    println!(
        "{:>8} {:>11} {:>17} {:>12} {:>17} {:>17} {:>17} {:>10}",
        "overlap",
        "neighbour",
        "1 thread reuse",
        "1 thread CPU",
        "1 thread once",
        "pool reuse",
        "pool once",
        "max err px"
    );
    let ms = |t: (f64, f64)| format!("{:7.2} / {:7.2}", t.0, t.1);
    for overlap in [0.1, 0.2, 0.3] {
        for horizontal in [true, false] {
            let spec = PairSpec::new(tile, overlap, horizontal, 9);
            let pair = make_pair(&spec.surface(40.0, 0.8, 0.25), &spec);
            let one = single.install(|| time_pair(&pair, runs, &params));
            let all = time_pair(&pair, runs, &params);
            println!(
                "{:>7.0}% {:>11} {:>17} {:>12} {:>17} {:>17} {:>17} {:>10.3}",
                overlap * 100.0,
                if horizontal { "horizontal" } else { "vertical" },
                ms(one.reused),
                one.cpu_ms
                    .map(|v| format!("{v:9.2} ms"))
                    .unwrap_or_else(|| "n/a".into()),
                ms(one.oneshot),
                ms(all.reused),
                ms(all.oneshot),
                one.worst_err_px.max(all.worst_err_px)
            );
        }
    }
}
