//! Simulates a scan and reports timings; optionally writes the truth and two reference
//! `run.json` files (tiles placed at their true and at their nominal positions) for
//! `bench/score_registration.py`.
//!
//! ```text
//! cargo run --release -p surfstream-replay --example simulate -- ROWS COLS [OUT_DIR]
//! ```

use std::time::Instant;

use anyhow::{bail, Context};
use rayon::prelude::*;
use surfstream_replay::SpecimenSurface;
use surfstream_replay::{acquire_tile, generate_virtual_specimen, plan_scan, truth_for};
use surfstream_replay::{SpecimenParams, StageParams};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() < 2 {
        bail!("usage: simulate ROWS COLS [OUT_DIR]");
    }
    let rows: usize = args[0].parse().context("ROWS: expected an integer")?;
    let cols: usize = args[1].parse().context("COLS: expected an integer")?;
    let stage = StageParams {
        rows,
        cols,
        ..StageParams::default()
    };
    let plan = plan_scan(&stage)?;
    let spec_params = plan.specimen_params(&SpecimenParams::default());
    let t0 = Instant::now();
    let specimen = generate_virtual_specimen(&spec_params)?;
    let t_spec = t0.elapsed();
    plan.check_specimen(&specimen)?;
    if std::env::var_os("SPECIMEN_ONLY").is_some() {
        println!(
            "specimen {} x {} px: {:.3} s, {} values in memory (roughness period {:?} px)",
            specimen.shape().cols,
            specimen.shape().rows,
            t_spec.as_secs_f64(),
            specimen.allocated_points(),
            specimen.period_px()
        );
        return Ok(());
    }
    println!(
        "specimen {} x {} px: {:.3} s",
        specimen.shape().cols,
        specimen.shape().rows,
        t_spec.as_secs_f64()
    );

    let t1 = Instant::now();
    let mut nan = 0usize;
    for tile in &plan.tiles {
        let t = acquire_tile(&specimen, tile, &stage);
        nan += t.iter().filter(|v| v.is_nan()).count();
    }
    let serial = t1.elapsed().as_secs_f64();
    let t2 = Instant::now();
    let tiles: Vec<Vec<f32>> = plan
        .tiles
        .par_iter()
        .map(|t| acquire_tile(&specimen, t, &stage))
        .collect();
    let parallel = t2.elapsed().as_secs_f64();
    let n = plan.tiles.len() as f64;
    println!(
        "{} tiles of {} x {} px: {:.1} ms per tile serial, {:.1} ms per tile with rayon; \
         NaN fraction {:.4}",
        tiles.len(),
        plan.tile_width_px,
        plan.tile_height_px,
        1e3 * serial / n,
        1e3 * parallel / n,
        nan as f64 / (n * (plan.tile_width_px * plan.tile_height_px) as f64)
    );

    let clean = StageParams {
        noise_um: 0.0,
        dropout_fraction: 0.0,
        dropout_blobs_mean: 0.0,
        ..stage.clone()
    };
    let t3 = Instant::now();
    for tile in &plan.tiles {
        std::hint::black_box(acquire_tile(&specimen, tile, &clean));
    }
    println!(
        "  of which resampling + pose: {:.1} ms per tile serial",
        1e3 * t3.elapsed().as_secs_f64() / n
    );

    if let Some(dir) = args.get(2) {
        let dir = std::path::Path::new(dir);
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        let truth = truth_for(&plan).with_specimen(&spec_params);
        std::fs::write(
            dir.join("ground_truth.json"),
            serde_json::to_string_pretty(&truth)?,
        )?;
        for (name, pick_true) in [("run_true.json", true), ("run_nominal.json", false)] {
            let run_tiles: Vec<RunTile> = plan
                .tiles
                .iter()
                .map(|t| {
                    let p = if pick_true {
                        t.true_origin_um
                    } else {
                        t.stage_position_um
                    };
                    RunTile {
                        index: t.index,
                        row: t.row,
                        col: t.col,
                        stage_x_um: t.stage_position_um[0],
                        stage_y_um: t.stage_position_um[1],
                        x_um: p[0],
                        y_um: p[1],
                        placed_by: if pick_true { "registration" } else { "stage" },
                    }
                })
                .collect();
            // Through a JSON value: keys sorted, as these files have always had them.
            let run = serde_json::to_value(RunTiles { tiles: run_tiles })?;
            std::fs::write(dir.join(name), serde_json::to_string_pretty(&run)?)?;
        }
        println!("wrote {}", dir.display());
    }
    Ok(())
}

/// A tile of run_true.json / run_nominal.json: run.json's tile fields a scorer reads.
#[derive(serde::Serialize)]
struct RunTile {
    index: usize,
    row: usize,
    col: usize,
    stage_x_um: f64,
    stage_y_um: f64,
    x_um: f64,
    y_um: f64,
    placed_by: &'static str,
}

/// run_true.json / run_nominal.json: a run.json with its tiles only.
#[derive(serde::Serialize)]
struct RunTiles {
    tiles: Vec<RunTile>,
}
