//! Times meshing a 1024 x 1024 field (the Zygo field size) and writing it as binary STL to a
//! file, the path a finished scan takes. Run with
//! `cargo run --release -p surfstream-mesher --example bench_mesh [SIZE] [REPEATS]`.
//! Prints the best of REPEATS (default 5) runs of each step; also times ASCII STL once.

use std::fs::File;
use std::io::BufWriter;
use std::time::{Duration, Instant};

use anyhow::Context;
use surfstream_core::raster::{RasterView, Shape};
use surfstream_core::Pitch;
use surfstream_mesher::{
    grid_solid, write_stl_ascii, write_stl_binary, ScanPlacement, SolidParams,
};

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let size: usize = args
        .next()
        .map_or(Ok(1024), |a| a.parse())
        .context("SIZE")?;
    let repeats: usize = args
        .next()
        .map_or(Ok(5), |a| a.parse())
        .context("REPEATS")?;

    // A rough, wavy surface with ~1 % dropouts, like a measured field.
    let heights_um: Vec<f32> = (0..size * size)
        .map(|k| {
            let (i, j) = ((k / size) as f32, (k % size) as f32);
            let hash = (k as u32).wrapping_mul(2_654_435_761) >> 16;
            if hash.is_multiple_of(100) {
                f32::NAN
            } else {
                1.3 * (0.02 * j).sin() * (0.013 * i).cos() + (hash % 1000) as f32 * 1e-3
            }
        })
        .collect();
    let heights = RasterView::new(&heights_um, Shape::new(size, size))?;
    let at = ScanPlacement::new(Pitch::new(0.8148, 0.8148).expect("a positive pitch"))
        .with_origin(114.21, 26.36)
        .with_z_offset(12_000.0);
    let params = SolidParams::default();
    let dir = tempfile::tempdir()?;
    let path = dir.path().join("surface.stl");

    let (mut mesh_best, mut write_best) = (Duration::MAX, Duration::MAX);
    let mut last = None;
    for _ in 0..repeats.max(1) {
        let t0 = Instant::now();
        let mesh = grid_solid(heights, &at, &params)?;
        let t1 = Instant::now();
        write_stl_binary(File::create(&path)?, &mesh, "surfstream solid")?;
        let t2 = Instant::now();
        mesh_best = mesh_best.min(t1 - t0);
        write_best = write_best.min(t2 - t1);
        last = Some(mesh);
    }
    let mesh = last.context("no run")?;
    let bytes = std::fs::metadata(&path)?.len();
    println!(
        "{size} x {size}: {} vertices, {} triangles, {} filled samples",
        mesh.vertices.len(),
        mesh.triangles.len(),
        mesh.filled_samples
    );
    println!(
        "grid_solid {:.1} ms, write_stl_binary {:.1} ms ({:.1} MB), total {:.1} ms (best of {repeats})",
        mesh_best.as_secs_f64() * 1e3,
        write_best.as_secs_f64() * 1e3,
        bytes as f64 / 1e6,
        (mesh_best + write_best).as_secs_f64() * 1e3,
    );

    let t = Instant::now();
    write_stl_ascii(
        BufWriter::new(File::create(&path)?),
        &mesh,
        "surfstream solid",
    )?;
    let ascii = t.elapsed();
    println!(
        "write_stl_ascii {:.1} ms ({:.1} MB)",
        ascii.as_secs_f64() * 1e3,
        std::fs::metadata(&path)?.len() as f64 / 1e6
    );
    Ok(())
}
