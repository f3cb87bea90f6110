//! Times the error-bounded mesher on a saved height field (a .npy in um, e.g. from
//! `mesh_anchor.py --save-inputs`) and prints one JSON line: median / min time over REPEATS,
//! triangles, achieved max and RMS vertical error, watertightness. Used by
//! `scripts/bench_mesh.py` to compare with pymeshlab in one run.
//!
//! `cargo run --release -p surfstream-mesher --example bench_adaptive FILE.npy STEP_UM EPSILON_UM [REPEATS [OUT.stl]]`
//! (OUT.stl: the last solid as binary STL in um, for an outside watertightness check).

use std::time::Instant;

use anyhow::{bail, Context, Result};
use surfstream_core::raster::{RasterView, Shape};
use surfstream_core::Pitch;
use surfstream_mesher::{
    check_closed, mesh_height_field, Epsilon, LengthUnit, MeshKind, MeshParams, MissingSamples,
    ScanPlacement, SolidParams,
};

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() < 3 {
        bail!("usage: bench_adaptive FILE.npy STEP_UM EPSILON_UM [REPEATS [OUT.stl]]");
    }
    let a = surfstream_io::npy::read_npy_f64(&args[0]).context(args[0].clone())?;
    let step_um: f64 = args[1].parse().context("STEP_UM")?;
    let epsilon_um: f64 = args[2].parse().context("EPSILON_UM")?;
    let repeats: usize = args
        .get(3)
        .map_or(Ok(3), |r| r.parse())
        .context("REPEATS")?;
    let heights_um: Vec<f32> = a.data.iter().map(|&h| h as f32).collect();
    let heights = RasterView::new(&heights_um, Shape::new(a.rows, a.cols))?;
    let at = ScanPlacement::new(Pitch::new(step_um, step_um).expect("a positive pitch"));
    let params = MeshParams {
        epsilon: Epsilon::Um(epsilon_um),
        max_triangles: None,
        kind: MeshKind::Solid,
        missing: MissingSamples::Fill,
        solid: SolidParams {
            units: LengthUnit::Um,
            base_depth_um: None,
            recentre: true,
        },
        block_samples: None,
    };
    let mut times = Vec::new();
    let mut cpu = Vec::new();
    let mut last = None;
    for _ in 0..repeats.max(1) {
        let (t0, c0) = (Instant::now(), cpu_s());
        let m = mesh_height_field(heights, &at, &params)?;
        times.push(t0.elapsed().as_secs_f64());
        cpu.push(cpu_s() - c0);
        last = Some(m);
    }
    cpu.sort_by(f64::total_cmp);
    let m = last.context("no run")?;
    times.sort_by(f64::total_cmp);
    if let Some(path) = args.get(4) {
        surfstream_core::fsutil::write_atomic(std::path::Path::new(path), |w| {
            Ok(surfstream_mesher::write_stl_binary(
                w,
                &m.mesh,
                "bench_adaptive",
            )?)
        })
        .with_context(|| path.clone())?;
    }
    let c = check_closed(&m.mesh);
    // The error is also measured in f64 against the f64 input (the f32 conversion of the
    // heights is part of what is measured: the STL stores f32 anyway).
    let resampled = &m.resampled_um;
    let (mut max64, mut sum2, mut n) = (0.0f64, 0.0f64, 0usize);
    for (r, h) in resampled.iter().zip(&a.data) {
        if h.is_finite() {
            let e = f64::from(*r) - h;
            max64 = max64.max(e.abs());
            sum2 += e * e;
            n += 1;
        }
    }
    let line = BenchLine {
        file: &args[0],
        grid: [a.cols, a.rows],
        step_um,
        epsilon_um,
        median_s: times[times.len() / 2],
        min_s: times[0],
        all_s: &times,
        cpu_median_s: cpu[cpu.len() / 2],
        rayon_threads: rayon::current_num_threads(),
        triangles: m.mesh.triangles.len(),
        surface_triangles: m.surface_triangles,
        max_err_um: m.fidelity.error.max_um,
        rms_err_um: m.fidelity.error.rms_um,
        max_err_vs_f64_input_um: max64,
        rms_err_vs_f64_input_um: (sum2 / n.max(1) as f64).sqrt(),
        bound_met: m.fidelity.bound_met,
        watertight: c.watertight,
        consistently_oriented: c.consistently_oriented,
        degenerate: c.degenerate_triangles,
        duplicate: c.duplicate_triangles,
    };
    // Through a JSON value: keys sorted, as the line has always had them.
    println!("{}", serde_json::to_value(line)?);
    Ok(())
}

/// CPU time (user + system) of this process so far, s, from /proc (10 ms resolution): the
/// machine is shared, so wall time alone says more about the load than about the code.
fn cpu_s() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    // Fields after the ")" that ends the command name: utime and stime are the 12th and 13th.
    let rest = stat.rsplit_once(')').map_or("", |(_, r)| r);
    let f: Vec<f64> = rest
        .split_whitespace()
        .skip(11)
        .take(2)
        .filter_map(|x| x.parse().ok())
        .collect();
    f.iter().sum::<f64>() / 100.0
}

/// The one JSON line this prints.
#[derive(serde::Serialize)]
struct BenchLine<'a> {
    file: &'a str,
    grid: [usize; 2],
    step_um: f64,
    epsilon_um: f64,
    median_s: f64,
    min_s: f64,
    all_s: &'a [f64],
    cpu_median_s: f64,
    rayon_threads: usize,
    triangles: usize,
    surface_triangles: usize,
    max_err_um: f64,
    rms_err_um: f64,
    max_err_vs_f64_input_um: f64,
    rms_err_vs_f64_input_um: f64,
    bound_met: bool,
    watertight: bool,
    consistently_oriented: bool,
    degenerate: usize,
    duplicate: usize,
}
