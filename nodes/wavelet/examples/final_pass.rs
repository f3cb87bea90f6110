//! The wavelet node's final pass on a synthetic panorama, in-memory (what the node ran before
//! the streamed pass: `analyse` + whole-map writers) or streamed (`final_separation_with`), to
//! compare time and peak memory. A benchmark, not a test: run each mode in its own process so
//! VmHWM is its own.
//!
//!     cargo run --release -p surfstream-wavelet --example final_pass -- streamed 5643 5636 /tmp/fp
//!     cargo run --release -p surfstream-wavelet --example final_pass -- in-memory 5643 5636 /tmp/fp
//!
//! OUT_DIR `-` writes no files (the rows go to the sink only; level stores in the temp dir).
//! Prints one JSON line: mode, size, seconds of the final pass, the process's VmHWM before
//! and after it (the panorama alone is 4 B/px), and bytes per pixel of the difference.

use std::time::Instant;

use anyhow::{bail, Context, Result};
use surfstream_core::frame::{FrameHeader, FrameKind, HeightMap};
use surfstream_core::raster::{RasterView, Shape};
use surfstream_io::output::{NpyHeights, OutputWriter, SurfaceOutput};
use surfstream_wavelet::{
    analyse, final_separation_with, BaseChoice, FinalRequest, LevelChoice, Mode, PoolOp,
    SeparationMethod, SeparationSettings, StreamOptions, Wavelet,
};

fn vm_hwm_mb() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|v| v.parse::<f64>().ok())
        })
        .map_or(f64::NAN, |kb| kb / 1024.0)
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [mode, rows, cols, out] = &args[..] else {
        bail!("usage: final_pass streamed|in-memory ROWS COLS OUT_DIR");
    };
    let rows: usize = rows.parse().context("ROWS")?;
    let cols: usize = cols.parse().context("COLS")?;
    let write = out != "-";
    let out = if write {
        std::path::PathBuf::from(out)
    } else {
        std::env::temp_dir()
    };
    std::fs::create_dir_all(&out)?;
    // A tilted wavy surface with texture and a few holes, like a stitched scan.
    let heights: Vec<f32> = (0..rows * cols)
        .map(|i| {
            let (r, c) = ((i / cols) as f32, (i % cols) as f32);
            if i % 4099 == 0 {
                f32::NAN
            } else {
                0.001 * c - 0.0005 * r
                    + (0.01 * c).sin()
                    + 0.2 * (0.3 * r).cos()
                    + ((i * 7919) % 97) as f32 * 1e-3
            }
        })
        .collect();
    let header = FrameHeader {
        kind: FrameKind::Panorama as u32,
        width: cols as u32,
        height: rows as u32,
        pitch_x_um: 0.5,
        pitch_y_um: 0.5,
        z_offset_um: 100.0,
        ..Default::default()
    };
    let pano = HeightMap { header, heights };
    let sym5 = Wavelet::by_name("sym5").context("sym5")?;
    let settings = SeparationSettings {
        method: SeparationMethod::Wavelet,
        lambda_s_um: None,
        base: BaseChoice::Named(sym5),
        level: LevelChoice::Fixed(8),
        mode: Mode::Symmetric,
        pool_block: 4,
        pool_op: PoolOp::Max,
    };
    let hwm_before = vm_hwm_mb();
    let t = Instant::now();
    let mut w = OutputWriter::new(&out);
    match mode.as_str() {
        "streamed" => {
            final_separation_with(
                &settings,
                pano.view(),
                FinalRequest {
                    files: write.then_some(&mut w),
                    publish_datum: false,
                    publish_roughness: false,
                    stream: StreamOptions {
                        spill_dir: Some(out.clone()),
                        ..StreamOptions::default()
                    },
                },
            )?;
        }
        "in-memory" => {
            let a = analyse(
                &pano.heights,
                rows,
                cols,
                settings.base,
                settings.level,
                settings.mode,
                4,
                PoolOp::Max,
            )?;
            if !write {
                // Keep the results alive until here, as the writers would.
                std::hint::black_box(&a);
                return finish(mode, rows, cols, hwm_before, t);
            }
            let shape = Shape::new(rows, cols);
            let pooled_shape = Shape::new(a.pooled.rows, a.pooled.cols);
            for (name, values, shape, npy) in [
                ("datum", &a.separation.datum, shape, NpyHeights::Absolute),
                (
                    "roughness",
                    &a.separation.roughness,
                    shape,
                    NpyHeights::RelativeF32,
                ),
                (
                    "pooled",
                    &a.pooled.heights,
                    pooled_shape,
                    NpyHeights::Absolute,
                ),
            ] {
                w.write_surface(&SurfaceOutput {
                    name,
                    heights: RasterView::new(values, shape)?,
                    z_offset_um: 100.0,
                    npy,
                    title: name,
                    x3p_pitch_um: None,
                })?;
            }
        }
        other => bail!("mode {other:?}: expected streamed or in-memory"),
    }
    finish(mode, rows, cols, hwm_before, t)
}

fn finish(mode: &str, rows: usize, cols: usize, hwm_before: f64, t: Instant) -> Result<()> {
    let secs = t.elapsed().as_secs_f64();
    let hwm = vm_hwm_mb();
    let px = (rows * cols) as f64;
    println!(
        "{{\"mode\": \"{mode}\", \"rows\": {rows}, \"cols\": {cols}, \"final_pass_s\": {secs:.2}, \"hwm_before_mb\": {hwm_before:.1}, \"hwm_mb\": {hwm:.1}, \"hwm_b_per_px\": {:.2}, \"final_pass_extra_b_per_px\": {:.2}}}",
        hwm * 1048576.0 / px,
        (hwm - hwm_before) * 1048576.0 / px
    );
    Ok(())
}
