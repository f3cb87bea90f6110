//! Time `Panorama::place` on a 10 x 5 serpentine of 1024 x 1024 px tiles at 10 % overlap and
//! sub-pixel positions, to show that the work per tile does not grow with the panorama.
//!
//! Run: `cargo run --release -p surfstream-fusion --example bench_place [REPEATS]`
//! Each repeat places the whole scan into a fresh panorama; per tile the fastest repeat is
//! reported (the least disturbed by the machine). Tiles that had to grow the canvas are marked:
//! their time includes the amortised reallocation.

use std::time::Instant;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use surfstream_core::raster::{RasterView, Shape};
use surfstream_core::Pitch;
use surfstream_fusion::{render, BlendParams, Panorama, PlaneCorrection, TileInput};

const COLS: usize = 10;
const ROWS: usize = 5;
const TILE_PX: usize = 1024;
const OVERLAP: f64 = 0.10;
fn pitch() -> Pitch {
    Pitch::square(PITCH_UM).expect("a positive pitch")
}

const PITCH_UM: f64 = 0.8148;

struct Tile {
    heights: Vec<f32>,
    x_um: f64,
    y_um: f64,
    plane: PlaneCorrection,
}

/// Smooth waviness plus a little noise and 0.1 % dropouts, like a profiler field.
fn make_tiles() -> Vec<Tile> {
    let mut rng = ChaCha8Rng::seed_from_u64(42);
    let step_um = TILE_PX as f64 * (1.0 - OVERLAP) * PITCH_UM;
    let mut specs = Vec::new();
    for r in 0..ROWS {
        for i in 0..COLS {
            let c = if r % 2 == 0 { i } else { COLS - 1 - i };
            let x = c as f64 * step_um + rng.gen_range(-2.0..2.0) * PITCH_UM;
            let y = r as f64 * step_um + rng.gen_range(-2.0..2.0) * PITCH_UM;
            let plane = PlaneCorrection {
                piston_um: rng.gen_range(-1.0..1.0),
                tilt_x_um_per_px: rng.gen_range(-1e-3..1e-3),
                tilt_y_um_per_px: rng.gen_range(-1e-3..1e-3),
            };
            specs.push((x, y, plane, rng.gen::<u64>()));
        }
    }
    specs
        .into_par_iter()
        .map(|(x_um, y_um, plane, seed)| {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let mut heights = vec![0.0f32; TILE_PX * TILE_PX];
            for (r, row) in heights.chunks_mut(TILE_PX).enumerate() {
                for (c, z) in row.iter_mut().enumerate() {
                    let (x, y) = (x_um + c as f64 * PITCH_UM, y_um + r as f64 * PITCH_UM);
                    let surface = (x * 0.013).sin() + 0.5 * (y * 0.021 + 0.3 * x * 0.01).cos();
                    let p = plane.piston_um
                        + plane.tilt_x_um_per_px * (c as f64 - 511.5)
                        + plane.tilt_y_um_per_px * (r as f64 - 511.5);
                    *z = if rng.gen_bool(0.001) {
                        f32::NAN
                    } else {
                        (surface + p + rng.gen_range(-0.01..0.01)) as f32
                    };
                }
            }
            Tile {
                heights,
                x_um,
                y_um,
                plane,
            }
        })
        .collect()
}

fn input(index: usize, t: &Tile) -> TileInput<'_> {
    TileInput {
        index: index as u32,
        heights: RasterView::new(&t.heights, Shape::new(TILE_PX, TILE_PX))
            .expect("a tile of TILE_PX x TILE_PX heights"),
        x_um: t.x_um,
        y_um: t.y_um,
        plane: t.plane,
        z_offset_um: 0.0,
    }
}

/// CPU time (ns) this process's threads have run so far, from /proc/self/task/*/schedstat
/// (Linux). Unlike wall time it does not count time lost to other processes on a busy
/// machine. `None` where /proc is unavailable.
fn cpu_ns() -> Option<u64> {
    let mut total = 0u64;
    for task in std::fs::read_dir("/proc/self/task").ok()? {
        let stat = std::fs::read_to_string(task.ok()?.path().join("schedstat")).ok()?;
        total += stat.split_whitespace().next()?.parse::<u64>().ok()?;
    }
    Some(total)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let repeats: usize = match std::env::args().nth(1) {
        Some(s) => s.parse()?,
        None => 3,
    };
    let tiles = make_tiles();
    let params = BlendParams::from_overlap_fraction(TILE_PX, TILE_PX, OVERLAP);
    let n = tiles.len();
    let mut best_ms = vec![f64::INFINITY; n];
    let mut best_cpu_ms = vec![f64::INFINITY; n];
    let mut grew = vec![false; n];
    let mut canvas = (0, 0);
    // Placing into canvas memory that an earlier tile already touched: the pure resampling and
    // blending cost, without the kernel's first-touch page faults of fresh canvas memory.
    let mut warm_ms = [f64::INFINITY; 2];
    for _ in 0..repeats {
        let mut pano = Panorama::new(pitch(), params)?;
        for (i, t) in tiles.iter().enumerate() {
            let before = (pano.width(), pano.height());
            let cpu_start = cpu_ns();
            let start = Instant::now();
            pano.place(input(i, t))?;
            let ms = start.elapsed().as_secs_f64() * 1e3;
            if let (Some(a), Some(b)) = (cpu_start, cpu_ns()) {
                best_cpu_ms[i] = best_cpu_ms[i].min(b.saturating_sub(a) as f64 / 1e6);
            }
            best_ms[i] = best_ms[i].min(ms);
            grew[i] = (pano.width(), pano.height()) != before;
        }
        canvas = (pano.width(), pano.height());
        for (k, i) in [1, n - 1].into_iter().enumerate() {
            let again = TileInput {
                index: 1000 + i as u32,
                ..input(i, &tiles[i])
            };
            let start = Instant::now();
            pano.place(again)?;
            warm_ms[k] = warm_ms[k].min(start.elapsed().as_secs_f64() * 1e3);
        }
    }

    // The same scan with the canvas pre-sized from the nominal scan extent (reserve_um): no
    // growth, so every tile pays only for its own pixels plus first touch of canvas memory.
    let mut reserved_ms = vec![f64::INFINITY; n];
    for _ in 0..repeats {
        let mut pano = Panorama::new(pitch(), params)?;
        let step_um = TILE_PX as f64 * (1.0 - OVERLAP) * PITCH_UM;
        let tile_um = TILE_PX as f64 * PITCH_UM;
        pano.reserve_um(
            -5.0,
            -5.0,
            (COLS - 1) as f64 * step_um + tile_um + 5.0,
            (ROWS - 1) as f64 * step_um + tile_um + 5.0,
        )?;
        for (i, t) in tiles.iter().enumerate() {
            let start = Instant::now();
            pano.place(input(i, t))?;
            reserved_ms[i] = reserved_ms[i].min(start.elapsed().as_secs_f64() * 1e3);
        }
    }

    let inputs: Vec<TileInput> = tiles.iter().enumerate().map(|(i, t)| input(i, t)).collect();
    let cpu_start = cpu_ns();
    let start = Instant::now();
    let raster = render(pitch(), &inputs, params)?;
    let render_ms = start.elapsed().as_secs_f64() * 1e3;
    let render_cpu_ms = match (cpu_start, cpu_ns()) {
        (Some(a), Some(b)) => b.saturating_sub(a) as f64 / 1e6,
        _ => f64::NAN,
    };

    let steady_of = |v: &[f64]| {
        let mut s: Vec<f64> = (1..n).filter(|&i| !grew[i]).map(|i| v[i]).collect();
        s.sort_by(f64::total_cmp);
        s
    };
    let (steady, steady_cpu) = (steady_of(&best_ms), steady_of(&best_cpu_ms));
    let median = |v: &[f64]| {
        if v.is_empty() {
            f64::NAN
        } else {
            v[v.len() / 2]
        }
    };
    let mark = |i: usize| if grew[i] { " (grew the canvas)" } else { "" };
    println!(
        "place(), {COLS} x {ROWS} serpentine of {TILE_PX} px tiles, {:.0} % overlap, \
         {} rayon threads, best of {repeats}",
        OVERLAP * 100.0,
        rayon::current_num_threads()
    );
    println!("  (wall time; cpu = CPU time summed over all threads of the process)");
    for (name, i) in [("tile  2", 1), ("tile 50", n - 1)] {
        println!(
            "  {name}: {:7.2} ms, cpu {:7.2} ms{}",
            best_ms[i],
            best_cpu_ms[i],
            mark(i)
        );
    }
    println!(
        "  tile 2 / tile 50 placed again over touched memory: {:.2} / {:.2} ms",
        warm_ms[0], warm_ms[1]
    );
    println!(
        "  tiles 2..50 without growth ({}): median {:.2} ms (cpu {:.2}), max {:.2} ms (cpu {:.2})",
        steady.len(),
        median(&steady),
        median(&steady_cpu),
        steady.last().copied().unwrap_or(f64::NAN),
        steady_cpu.last().copied().unwrap_or(f64::NAN),
    );
    let mut sorted = reserved_ms[1..].to_vec();
    sorted.sort_by(f64::total_cmp);
    println!(
        "  with reserve_um (no growth): tile 2 {:.2} ms, tile 50 {:.2} ms, tiles 2..50 median \
         {:.2} ms, max {:.2} ms",
        reserved_ms[1],
        reserved_ms[n - 1],
        median(&sorted),
        sorted.last().copied().unwrap_or(f64::NAN)
    );
    let growth: Vec<String> = (0..n)
        .filter(|&i| grew[i])
        .map(|i| format!("{} ({:.1} ms)", i + 1, best_ms[i]))
        .collect();
    println!("  tiles that grew the canvas: {}", growth.join(", "));
    println!(
        "  final canvas {} x {} px, panorama {} x {} px",
        canvas.0,
        canvas.1,
        raster.heights.cols(),
        raster.heights.rows()
    );
    println!("render() of all {n} tiles: {render_ms:.0} ms, cpu {render_cpu_ms:.0} ms");
    Ok(())
}
