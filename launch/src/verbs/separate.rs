//! `surfstream separate`: datum / roughness separation of one height map, on its own.
//!
//! Reads any map `formats::read_surface` reads, runs the wavelet node's library
//! ([`surfstream_wavelet::analyse`]: the same code as the pipeline's final pass) and writes
//! `datum.npy`, `roughness.npy`, `pooled.npy` and `separate.json` (base, level, mode, energy
//! curve, RMSE ranking when the base is "auto", pooling bias) into `--out`.

use std::path::PathBuf;

use anyhow::{anyhow, bail, Context, Result};
use clap::Args;
use surfstream_core::frame::{from_frame_heights, to_frame_heights};
use surfstream_core::fsutil::write_atomic;
use surfstream_io::formats::read_surface;
use surfstream_io::npy::{write_npy_f32, write_npy_f64};
use surfstream_wavelet::{analyse, BaseChoice, LevelChoice, Mode, PoolOp};

#[derive(Args)]
pub struct SeparateArgs {
    /// Height-map file (.npy, or an instrument format `surfstream inspect` reads).
    pub file: PathBuf,
    /// Wavelet base: db1..db10, sym2..sym10, coif1..coif5, or "auto" (minimum reconstruction
    /// RMSE, the paper's eq. 10; note that it ranks floating-point round-off).
    #[arg(long, default_value = "sym5")]
    pub wavelet: String,
    /// Decomposition level (clamped to the largest useful level of the map), or "auto": the
    /// minimum of the approximation's energy proportion after plane levelling (paper Fig. 13).
    #[arg(long, default_value = "8")]
    pub level: String,
    /// Border extension: symmetric (PyWavelets' default) or periodization.
    #[arg(long, default_value = "symmetric")]
    pub mode: String,
    /// Pooling block size, px.
    #[arg(long, default_value_t = 4)]
    pub pool: usize,
    /// Pooling operation: max (the paper) or mean.
    #[arg(long = "pool-op", default_value = "max")]
    pub pool_op: String,
    /// Output directory (created if needed).
    #[arg(short = 'o', long)]
    pub out: PathBuf,
}

pub fn run(a: SeparateArgs) -> Result<()> {
    // One parser per option, shared with the wavelet node's params.
    let base: BaseChoice = a.wavelet.parse().map_err(|e| anyhow!("--wavelet {e}"))?;
    let level: LevelChoice = a.level.parse().map_err(|e| anyhow!("--level {e}"))?;
    let mode: Mode = a.mode.parse().map_err(|e| anyhow!("--mode {e}"))?;
    let pool_op: PoolOp = a.pool_op.parse().map_err(|e| anyhow!("--pool-op {e}"))?;
    if a.pool == 0 {
        bail!("--pool 0: expected a block size of at least 1 px");
    }

    let s = read_surface(&a.file)?;
    // The separation takes f32 heights (as frames carry them, DESIGN §2) and runs in f64.
    // Instrument heights can sit tens of um up (MetroPro: ~50 um), where f32 keeps only
    // ~4e-6 um: remove the mean first, as frames do with z_offset_um, and add it back to
    // the datum and the pooled map, which are written in f64.
    // read_surface already made every non-finite height NaN, so the frame's NaN-skipping
    // mean is the same as skipping non-finite heights.
    let (z_offset_um, heights) = to_frame_heights(&s.heights_um);
    let with_offset = |v: &[f32]| from_frame_heights(z_offset_um, v);
    let an = analyse(
        &heights, s.height, s.width, base, level, mode, a.pool, pool_op,
    )
    .with_context(|| format!("{}: separation", a.file.display()))?;

    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("{}: cannot create the output directory", a.out.display()))?;
    let sep = &an.separation;
    write_npy_f64(
        a.out.join("datum.npy"),
        &with_offset(&sep.datum),
        s.height,
        s.width,
    )?;
    write_npy_f32(
        a.out.join("roughness.npy"),
        &sep.roughness,
        s.height,
        s.width,
    )?;
    write_npy_f64(
        a.out.join("pooled.npy"),
        &with_offset(&an.pooled.heights),
        an.pooled.rows,
        an.pooled.cols,
    )?;
    let mut summary = an.summary();
    if let Some(o) = summary.as_object_mut() {
        o.insert(
            "input".into(),
            serde_json::json!(a.file.display().to_string()),
        );
        o.insert("input_px".into(), serde_json::json!([s.width, s.height]));
        // Heights inside the summary (pooling bias means) are relative to this; datum.npy and
        // pooled.npy are absolute (f64), roughness.npy has no offset.
        o.insert("z_offset_um".into(), serde_json::json!(z_offset_um));
        o.insert(
            "pitch_um".into(),
            serde_json::json!([s.pitch_x_um, s.pitch_y_um]),
        );
        o.insert(
            "files".into(),
            serde_json::json!(["datum.npy", "roughness.npy", "pooled.npy", "separate.json"]),
        );
    }
    let json = serde_json::to_string_pretty(&summary)?;
    write_atomic(&a.out.join("separate.json"), |w| {
        use std::io::Write;
        w.write_all(json.as_bytes())?;
        Ok(())
    })?;
    println!(
        "{}: {} x {} px, {} level {} ({}), level by min energy {}; wrote datum.npy, roughness.npy, pooled.npy ({} x {}), separate.json to {}",
        a.file.display(),
        s.width,
        s.height,
        an.wavelet.name(),
        sep.level,
        mode.name(),
        an.level_min_energy.map_or("-".to_string(), |l| l.to_string()),
        an.pooled.cols,
        an.pooled.rows,
        a.out.display()
    );
    Ok(())
}
