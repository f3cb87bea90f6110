//! Times the tolerance's judging of one mesh in every region (`judge_regions`, and a search's
//! checkpoint with the measured side kept, `RegionJudge::judge`) on a saved
//! panorama and roughness (.npy, um), the mesh being the panorama plus a small ripple.
//!
//! `cargo run --release -p surfstream-mesher --example bench_judge PANORAMA.npy ROUGHNESS.npy [REPEATS]`

use std::time::Instant;

use anyhow::{Context, Result};
use surfstream_core::raster::Shape;
use surfstream_mesher::tolerance::{default_region_px, judge_regions, windows, RegionJudge};

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let read = |p: &String| -> Result<(Vec<f32>, Shape)> {
        let a = surfstream_io::npy::read_npy_f64(p).context(p.clone())?;
        let shape = Shape {
            rows: a.rows,
            cols: a.cols,
        };
        Ok((a.data.iter().map(|&v| v as f32).collect(), shape))
    };
    let (z, shape) = read(args.first().context("PANORAMA.npy")?)?;
    let (g, _) = read(args.get(1).context("ROUGHNESS.npy")?)?;
    let repeats: usize = args.get(2).map_or(Ok(5), |r| r.parse())?;
    let m: Vec<f32> = (z.iter().enumerate())
        .map(|(i, &v)| v + 0.01 * ((i % 97) as f32 / 97.0 - 0.5))
        .collect();
    let regions = windows(shape, default_region_px(shape));
    let mut times = Vec::new();
    for _ in 0..repeats {
        let t = Instant::now();
        let fits = judge_regions(&z, &m, Some(&g), shape, &regions, None);
        times.push(t.elapsed().as_secs_f64());
        std::hint::black_box(fits);
    }
    let judge = RegionJudge::new(&z, Some(&g), shape, &regions, None);
    let mut mesh_side = Vec::new();
    for _ in 0..repeats {
        let t = Instant::now();
        std::hint::black_box(judge.judge(&m));
        mesh_side.push(t.elapsed().as_secs_f64());
    }
    for t in [&mut times, &mut mesh_side] {
        t.sort_by(f64::total_cmp);
    }
    println!(
        "{} regions, {} x {}: judge_regions median {:.4} s (min {:.4}); a checkpoint (the \
         measured side kept) median {:.4} s (min {:.4})",
        regions.len(),
        shape.rows,
        shape.cols,
        times[times.len() / 2],
        times[0],
        mesh_side[mesh_side.len() / 2],
        mesh_side[0]
    );
    Ok(())
}
