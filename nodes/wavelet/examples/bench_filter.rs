//! Timing of the ISO 16610-61 Gaussian filter (`surfstream_core::filter`) on one .npy map, for
//! `scripts/bench_filter.py`, which runs scipy.ndimage.gaussian_filter on the same array in
//! the same run:
//!
//! ```text
//! cargo build --release -p surfstream-wavelet --example bench_filter
//! target/release/examples/bench_filter IN.npy PITCH_UM CUTOFF_UM REPS [gaussian|robust]
//! ```
//!
//! Prints one JSON line: the median seconds of one filter application (planning included,
//! reading the file excluded) over REPS runs after one warm-up, and the thread count.

use std::time::Instant;

use anyhow::{anyhow, bail, Context, Result};
use surfstream_core::filter::{gaussian_filter, robust_gaussian_filter, RobustSettings};
use surfstream_core::{Sampling, Shape};

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() < 4 {
        bail!("usage: bench_filter IN.npy PITCH_UM CUTOFF_UM REPS [gaussian|robust]");
    }
    let a = surfstream_io::npy::read_npy(&args[0]).with_context(|| args[0].clone())?;
    let pitch: f64 = args[1].parse().context("PITCH_UM")?;
    let cutoff: f64 = args[2].parse().context("CUTOFF_UM")?;
    let reps: usize = args[3].parse().context("REPS")?;
    let robust = match args.get(4).map(String::as_str) {
        None | Some("gaussian") => false,
        Some("robust") => true,
        Some(o) => bail!("filter {o:?}: expected gaussian or robust"),
    };
    let grid = Sampling::square(Shape::new(a.rows, a.cols), pitch)?;
    let mut times = Vec::new();
    let mut check = 0.0f64;
    for i in 0..=reps {
        let t = Instant::now();
        let out = if robust {
            robust_gaussian_filter(&a.data, grid, &RobustSettings::new(cutoff))
                .map_err(|e| anyhow!("{e}"))?
                .mean
        } else {
            gaussian_filter(&a.data, grid, cutoff).map_err(|e| anyhow!("{e}"))?
        };
        let dt = t.elapsed().as_secs_f64();
        check = f64::from(out[out.len() / 2]);
        if i > 0 {
            times.push(dt);
        }
    }
    times.sort_by(f64::total_cmp);
    println!(
        "{{\"tool\": \"surfstream\", \"filter\": \"{}\", \"rows\": {}, \"cols\": {}, \"cutoff_um\": {cutoff}, \"seconds\": {}, \"threads\": {}, \"centre_value\": {check}}}",
        if robust { "robust" } else { "gaussian" },
        a.rows,
        a.cols,
        times[times.len() / 2],
        rayon::current_num_threads()
    );
    Ok(())
}
