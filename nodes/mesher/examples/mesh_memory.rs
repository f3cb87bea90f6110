//! Peak memory of the adaptive mesher on a synthetic rough field (issue 17), in memory or
//! streamed: meshes a ROWS x COLS field (waviness plus noise, epsilon 5 % of Sq, a solid, as the
//! demo's mesher), writes the binary STL and the mesh on the grid as the node does, and prints
//! one JSON line with the process's peak resident memory (VmHWM) in bytes per sample.
//! A benchmark, not a test: run it alone, the figure is the process's own.
//!
//! `cargo run --release -p surfstream-mesher --example mesh_memory -- ROWS COLS MODE OUT_DIR [--discard]`
//!
//! MODE: `stream` | `memory` (the adaptive mesh), `grid-stream` | `grid-memory` (the full-grid
//! solid, `method = "grid"`).
//!
//! `--discard`: the STL and the .npy are encoded but thrown away (the machine's disk is shared;
//! a 4k x 4k field makes a 1.6 GB STL); the streaming mesher's spill file still goes to OUT_DIR.

use std::time::Instant;

use anyhow::{bail, Context, Result};
use surfstream_core::raster::{RasterView, Shape};
use surfstream_core::Pitch;
use surfstream_mesher::{
    check_closed, grid_solid, grid_streaming, mesh_height_field, mesh_streaming, write_stl_binary,
    Epsilon, MeshKind, MeshParams, MissingSamples, ScanPlacement, SolidParams,
};

fn vm_hwm_bytes() -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.split_whitespace().next()?.parse::<u64>().ok())
        .map_or(0, |kb| kb * 1024)
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() != 4 && !(args.len() == 5 && args[4] == "--discard") {
        bail!("usage: mesh_memory ROWS COLS stream|memory|grid-stream|grid-memory OUT_DIR [--discard]");
    }
    let discard = args.len() == 5;
    let rows: usize = args[0].parse().context("ROWS")?;
    let cols: usize = args[1].parse().context("COLS")?;
    let out = std::path::PathBuf::from(&args[3]);
    std::fs::create_dir_all(&out)?;
    let mut state: u64 = 0x9E37_79B9_7F4A_7C15;
    let heights_um: Vec<f32> = (0..rows * cols)
        .map(|k| {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            let r = (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5;
            let (x, y) = ((k % cols) as f64 / 300.0, (k / cols) as f64 / 300.0);
            (3.0 * (1.3 * x).sin() * (0.9 * y).cos() + 0.5 * (5.0 * x + 2.0 * y).sin() + 2.0 * r)
                as f32
        })
        .collect();
    let heights = RasterView::new(&heights_um, Shape::new(rows, cols))?;
    let at = ScanPlacement::new(Pitch::new(3.2592, 3.2592).expect("a positive pitch"))
        .with_z_offset(100.0);
    let params = MeshParams {
        epsilon: Epsilon::SqFraction(0.05),
        max_triangles: None,
        kind: MeshKind::Solid,
        missing: MissingSamples::Fill,
        solid: SolidParams::default(),
        block_samples: None,
    };
    let input_bytes = vm_hwm_bytes();
    let t0 = Instant::now();
    let stl = out.join("surface.stl");
    let npy = out.join("mesh_resampled.npy");
    let (triangles, watertight) = match args[2].as_str() {
        "stream" => {
            let mut m = mesh_streaming(heights, &at, &params, &out)?;
            let mut check = None;
            if discard {
                check = Some(m.write_stl(
                    &mut std::io::sink(),
                    false,
                    "surfstream surface",
                    heights,
                )?);
            } else {
                surfstream_io::npy::write_npy_abs(&npy, &m.resampled_um, rows, cols, 100.0)?;
                surfstream_core::fsutil::write_atomic(&stl, |w| {
                    check = Some(m.write_stl(w, false, "surfstream surface", heights)?);
                    Ok(())
                })?;
            }
            (m.counts.triangles, check.is_some_and(|c| c.watertight))
        }
        "memory" => {
            let m = mesh_height_field(heights, &at, &params)?;
            let abs = surfstream_core::frame::from_frame_heights(100.0, &m.resampled_um);
            if discard {
                write_stl_binary(std::io::sink(), &m.mesh, "surfstream surface")?;
            } else {
                surfstream_io::npy::write_npy_f64(&npy, &abs, rows, cols)?;
                surfstream_core::fsutil::write_atomic(&stl, |w| {
                    Ok(write_stl_binary(w, &m.mesh, "surfstream surface")?)
                })?;
            }
            drop(abs);
            let c = check_closed(&m.mesh);
            (m.mesh.triangles.len(), c.watertight)
        }
        "grid-stream" => {
            let g = grid_streaming(heights, &at, &params.solid)?;
            let check = if discard {
                g.write_stl(&mut std::io::sink(), false, "surfstream surface", heights)?
            } else {
                surfstream_io::npy::write_npy_abs(&npy, &heights_um, rows, cols, 100.0)?;
                let mut check = None;
                surfstream_core::fsutil::write_atomic(&stl, |w| {
                    check = Some(g.write_stl(w, false, "surfstream surface", heights)?);
                    Ok(())
                })?;
                check.context("nothing written")?
            };
            (g.counts.triangles, check.watertight)
        }
        "grid-memory" => {
            let m = grid_solid(heights, &at, &params.solid)?;
            if discard {
                write_stl_binary(std::io::sink(), &m, "surfstream surface")?;
            } else {
                let abs = surfstream_core::frame::from_frame_heights(100.0, &heights_um);
                surfstream_io::npy::write_npy_f64(&npy, &abs, rows, cols)?;
                surfstream_core::fsutil::write_atomic(&stl, |w| {
                    Ok(write_stl_binary(w, &m, "surfstream surface")?)
                })?;
            }
            (m.triangles.len(), check_closed(&m).watertight)
        }
        other => bail!("mode {other:?}: expected stream, memory, grid-stream or grid-memory"),
    };
    let peak = vm_hwm_bytes();
    let samples = (rows * cols) as f64;
    let line = MemoryLine {
        rows,
        cols,
        mode: &args[2],
        triangles,
        triangles_per_sample: triangles as f64 / samples,
        watertight,
        peak_rss_mb: peak as f64 / 1e6,
        peak_bytes_per_sample: peak as f64 / samples,
        before_meshing_bytes_per_sample: input_bytes as f64 / samples,
        wall_s: t0.elapsed().as_secs_f64(),
    };
    // Through a JSON value: keys sorted, as the line has always had them.
    println!("{}", serde_json::to_value(line)?);
    Ok(())
}

/// The one JSON line this prints.
#[derive(serde::Serialize)]
struct MemoryLine<'a> {
    rows: usize,
    cols: usize,
    mode: &'a str,
    triangles: usize,
    triangles_per_sample: f64,
    watertight: bool,
    peak_rss_mb: f64,
    peak_bytes_per_sample: f64,
    before_meshing_bytes_per_sample: f64,
    wall_s: f64,
}
