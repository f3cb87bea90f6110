//! Times `register_pair` on synthetic 1024 x 1024 tiles at 10, 20 and 30 % overlap (horizontal
//! and vertical neighbours), median of 11 runs, on one rayon thread and on the default pool.
//!
//! `cargo run --release -p surfstream-matcher --example bench_pair -- [TILE_PX] [RUNS]`

#[path = "../tests/support/mod.rs"]
mod support;

use std::time::Instant;

use surfstream_matcher::{register_pair, PhaseCorrelator, PhaseParams, RasterRef};
use support::{make_pair, surface_size, Pair, PairSpec, Surface};

fn median_ms(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// (reused correlator, one-shot register_pair) medians in ms, and the worst error in px.
fn time_pair(pair: &Pair, runs: usize, params: &PhaseParams) -> (f64, f64, f64) {
    let a = RasterRef {
        heights: &pair.a,
        width: pair.w,
        height: pair.h,
    };
    let b = RasterRef {
        heights: &pair.b,
        width: pair.w,
        height: pair.h,
    };
    let mut corr = PhaseCorrelator::new();
    let mut worst = 0.0f64;
    // Warm-up (plans, buffers, rayon pool).
    corr.register(a, b, pair.nominal_offset_px, params);
    let mut reused = Vec::with_capacity(runs);
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
    let mut oneshot = Vec::with_capacity(runs);
    for _ in 0..runs {
        let t = Instant::now();
        let _ = register_pair(a, b, pair.nominal_offset_px, params);
        oneshot.push(t.elapsed().as_secs_f64() * 1e3);
    }
    (median_ms(reused), median_ms(oneshot), worst)
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let tile: usize = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(1024);
    let runs: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(11);
    let params = PhaseParams::default();
    let single = match rayon::ThreadPoolBuilder::new().num_threads(1).build() {
        Ok(p) => p,
        Err(e) => {
            eprintln!("cannot build a one-thread pool: {e}");
            std::process::exit(1);
        }
    };
    println!(
        "register_pair, {tile} x {tile} px tiles, median of {runs}; default pool = {} threads",
        rayon::current_num_threads()
    );
    println!(
        "{:>8} {:>11} {:>12} {:>12} {:>12} {:>12} {:>10}",
        "overlap", "neighbour", "1 thr reuse", "1 thr once", "all reuse", "all once", "max err px"
    );
    for overlap in [0.1, 0.2, 0.3] {
        let surface = Surface::rough(surface_size(tile, overlap), 42, 40.0, 0.8, 0.25);
        for horizontal in [true, false] {
            let spec = PairSpec {
                noise_um: 0.05,
                nan_fraction: 0.05,
                ..PairSpec::new(tile, overlap, horizontal, 9)
            };
            let pair = make_pair(&surface, &spec);
            let (r1, o1, e1) = single.install(|| time_pair(&pair, runs, &params));
            let (rn, on, en) = time_pair(&pair, runs, &params);
            println!(
                "{:>7.0}% {:>11} {:>9.2} ms {:>9.2} ms {:>9.2} ms {:>9.2} ms {:>10.3}",
                overlap * 100.0,
                if horizontal { "horizontal" } else { "vertical" },
                r1,
                o1,
                rn,
                on,
                e1.max(en)
            );
        }
    }
}
