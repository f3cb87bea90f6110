//! `surfstream separate`: datum / roughness separation of one height map, on its own.
//!
//! Reads any map `formats::read_surface` reads, runs the wavelet node's library
//! ([`surfstream_wavelet::analyse`]: the same code as the pipeline's final pass) and writes
//! `datum.npy`, `roughness.npy`, `pooled.npy` (each with its pitch sidecar `NAME.npy.json`,
//! so `params` on them runs at the input's pitch) and `separate.json` (base, level, mode, energy
//! curve, RMSE ranking when the base is "auto", the level's equivalent cutoff, pooling bias)
//! into `--out`. `--method gaussian | robust-gaussian --cutoff-um L` separates by an ISO 16610
//! L-filter instead ([`surfstream_wavelet::filter_separation`], the node's code too).

use std::path::PathBuf;

use anyhow::{anyhow, bail, Context, Result};
use clap::Args;
use surfstream_core::filter::FilterError;
use surfstream_core::frame::{from_frame_heights, to_frame_heights};
use surfstream_core::fsutil::write_atomic;
use surfstream_core::{Sampling, Shape};
use surfstream_io::npy::{write_npy_abs_f64, write_npy_f32, write_npy_f64};
use surfstream_io::sidecar::{write_sidecar, NpyGeometry};

use super::{file_help, load_surface, pitch_text, sig};
use surfstream_wavelet::{
    analyse, equivalent_cutoff_um, filter_separation, level_lowered_warning, pool, pooling_bias,
    BaseChoice, LevelChoice, Mode, PoolOp, SeparationMethod, DEFAULT_LEVEL,
};

#[derive(Args)]
pub struct SeparateArgs {
    #[arg(help = file_help())]
    pub file: PathBuf,
    /// How the datum is separated: wavelet (the paper's low-pass, --wavelet / --level),
    /// gaussian (ISO 16610-61 L-filter) or robust-gaussian (ISO 16610-71, zeroth order).
    #[arg(long, default_value = "wavelet")]
    pub method: String,
    /// L-filter cutoff lambda_c for the filter methods: µm, or with a unit ("0.8mm", "250um").
    #[arg(long = "cutoff-um", value_name = "LENGTH")]
    pub cutoff_um: Option<String>,
    /// S-filter cutoff lambda_s for the filter methods (µm or with a unit); none by default.
    #[arg(long = "lambda-s-um", value_name = "LENGTH")]
    pub lambda_s_um: Option<String>,
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
    /// Pitch in um for a file that carries none (a .npy without its NAME.npy.json sidecar);
    /// refused when it disagrees with the file's own. Without it such a file is separated at
    /// 1 um with a warning (the equivalent cutoff and the outputs' sidecars say 1 um).
    #[arg(long)]
    pub pitch_um: Option<f64>,
    /// Output directory (created if needed).
    #[arg(short = 'o', long)]
    pub out: PathBuf,
    #[command(flatten)]
    pub mask: super::MaskArgs,
}

/// A length in µm: a number (µm) or a number with the unit "um", "µm" or "mm".
fn length_um(flag: &str, text: &str) -> Result<f64> {
    let t = text.trim().to_ascii_lowercase();
    let (number, scale) = if let Some(n) = t.strip_suffix("mm") {
        (n, 1000.0)
    } else if let Some(n) = t.strip_suffix("um").or_else(|| t.strip_suffix("µm")) {
        (n, 1.0)
    } else {
        (t.as_str(), 1.0)
    };
    match number.trim().parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v * scale),
        _ => bail!("{flag} {text:?}: expected a positive length in µm, or with a unit (\"0.8mm\", \"250um\")"),
    }
}

pub fn run(a: SeparateArgs) -> Result<()> {
    let cutoff_um = a
        .cutoff_um
        .as_deref()
        .map(|t| length_um("--cutoff-um", t))
        .transpose()?;
    let lambda_s_um = a
        .lambda_s_um
        .as_deref()
        .map(|t| length_um("--lambda-s-um", t))
        .transpose()?;
    let method = SeparationMethod::parse(&a.method, cutoff_um).map_err(|e| {
        anyhow!(
            "--method {}: {}",
            a.method,
            e.replace("cutoff_um", "--cutoff-um")
        )
    })?;
    if let Some(ls) = lambda_s_um {
        match method.cutoff_um() {
            None => bail!("--lambda-s-um: applies to --method gaussian or robust-gaussian"),
            Some(lc) if ls >= lc => {
                bail!("--lambda-s-um {ls}: expected a cutoff shorter than --cutoff-um {lc}")
            }
            Some(_) => {}
        }
    }
    // One parser per option, shared with the wavelet node's params.
    let base: BaseChoice = a.wavelet.parse().map_err(|e| anyhow!("--wavelet {e}"))?;
    let level: LevelChoice = a.level.parse().map_err(|e| anyhow!("--level {e}"))?;
    let mode: Mode = a.mode.parse().map_err(|e| anyhow!("--mode {e}"))?;
    let pool_op: PoolOp = a.pool_op.parse().map_err(|e| anyhow!("--pool-op {e}"))?;
    if a.pool == 0 {
        bail!("--pool 0: expected a block size of at least 1 px");
    }

    let mut s = load_surface(&a.file, a.pitch_um, "separate", true)?.surface;
    a.mask.apply(&a.file, &mut s)?;
    // The separation takes f32 heights (as frames carry them, DESIGN §2) and runs in f64.
    // Instrument heights can sit tens of um up (MetroPro: ~50 um), where f32 keeps only
    // ~4e-6 um: remove the mean first, as frames do with z_offset_um, and add it back to
    // the datum and the pooled map, which are written in f64.
    // read_surface already made every non-finite height NaN, so the frame's NaN-skipping
    // mean is the same as skipping non-finite heights.
    let (z_offset_um, heights) = to_frame_heights(&s.heights_um);
    let with_offset = |v: &[f32]| from_frame_heights(z_offset_um, v);
    let (datum, roughness, pooled, mut summary, line) = if method == SeparationMethod::Wavelet {
        let an = analyse(
            &heights, s.height, s.width, base, level, mode, a.pool, pool_op,
        )
        .with_context(|| format!("{}: separation", a.file.display()))?;
        let used = an.separation.level;
        let cutoff = equivalent_cutoff_um(&an.wavelet, used, s.pitch_x_um);
        let requested = match level {
            LevelChoice::Fixed(l) => Some(l),
            LevelChoice::Default => Some(DEFAULT_LEVEL),
            LevelChoice::MinEnergy => None,
        };
        let warning =
            requested.and_then(|r| level_lowered_warning(&an.wavelet, r, used, s.pitch_x_um));
        if let Some(w) = &warning {
            eprintln!("{}: {w}", a.file.display());
        }
        let mut summary = an.summary();
        if let Some(o) = summary.as_object_mut() {
            o.insert("method".into(), serde_json::json!("wavelet"));
            o.insert("equivalent_cutoff_um".into(), serde_json::json!(cutoff));
            o.insert(
                "equivalent_cutoff_definition".into(),
                serde_json::json!(surfstream_wavelet::live::CUTOFF_DEFINITION),
            );
            o.insert("warning".into(), serde_json::json!(warning));
        }
        let line = format!(
            "{} level {used} ({}, equivalent cutoff {} um), level by min energy {}",
            an.wavelet.name(),
            mode.name(),
            sig(cutoff, 4),
            an.level_min_energy
                .map_or("-".to_string(), |l| l.to_string()),
        );
        let sep = an.separation;
        (sep.datum, sep.roughness, an.pooled, summary, line)
    } else {
        let f = Sampling::new(Shape::new(s.height, s.width), s.pitch_x_um, s.pitch_y_um)
            .map_err(FilterError::from)
            .and_then(|grid| filter_separation(&heights, grid, method, lambda_s_um))
            .map_err(|e| anyhow!("{}: {} separation: {e}", a.file.display(), method.name()))?;
        let pooled = pool(&heights, s.height, s.width, a.pool, pool_op)
            .with_context(|| format!("{}: pooling", a.file.display()))?;
        let cutoff = method.cutoff_um().unwrap_or(f64::NAN);
        let summary = serde_json::json!({
            "method": method.name(),
            "cutoff_um": cutoff,
            "lambda_s_um": lambda_s_um,
            "plane_removed_um": f.plane_um,
            "robust_iterations": f.robust_iterations.map(|r| r.0),
            "robust_converged": f.robust_iterations.map(|r| r.1),
            "pool": a.pool,
            "pool_op": pool_op.name(),
            "pooled_rows_cols": [pooled.rows, pooled.cols],
            "pooling_bias": pooling_bias(&heights, &pooled.heights),
        });
        let line = format!(
            "{} lambda_c {} um{}",
            method.name(),
            sig(cutoff, 4),
            lambda_s_um.map_or(String::new(), |l| format!(", lambda_s {} um", sig(l, 4)))
        );
        (f.datum, f.roughness, pooled, summary, line)
    };

    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("{}: cannot create the output directory", a.out.display()))?;
    // Absolute f64 converted as it is written: no f64 copy of the whole datum.
    write_npy_abs_f64(
        a.out.join("datum.npy"),
        &datum,
        s.height,
        s.width,
        z_offset_um,
    )?;
    write_npy_f32(a.out.join("roughness.npy"), &roughness, s.height, s.width)?;
    write_npy_f64(
        a.out.join("pooled.npy"),
        &with_offset(&pooled.heights),
        pooled.rows,
        pooled.cols,
    )?;
    // The pitch travels with every output: NAME.npy.json beside each .npy.
    let at = |scale: f64| NpyGeometry {
        pitch_x_um: s.pitch_x_um * scale,
        pitch_y_um: s.pitch_y_um * scale,
        origin_um: s.metadata.stage_position_um,
    };
    for (name, scale) in [
        ("datum.npy", 1.0),
        ("roughness.npy", 1.0),
        ("pooled.npy", a.pool as f64),
    ] {
        write_sidecar(&a.out.join(name), &at(scale))?;
    }
    if let Some(o) = summary.as_object_mut() {
        o.insert(
            "input".into(),
            serde_json::json!(a.file.display().to_string()),
        );
        o.insert(
            "input_rows_cols".into(),
            serde_json::json!([s.height, s.width]),
        );
        if let Some(p) = o.remove("pooled_px") {
            // The library's [cols, rows]: as rows, cols like every size here.
            if let Some([c, r]) = p.as_array().map(|v| [v[0].clone(), v[1].clone()]) {
                o.insert("pooled_rows_cols".into(), serde_json::json!([r, c]));
            }
        }
        // Heights inside the summary (pooling bias means) are relative to this; datum.npy and
        // pooled.npy are absolute (f64), roughness.npy has no offset.
        o.insert("z_offset_um".into(), serde_json::json!(z_offset_um));
        o.insert(
            "pitch_um".into(),
            serde_json::json!([s.pitch_x_um, s.pitch_y_um]),
        );
        o.insert(
            "pooled_pitch_um".into(),
            serde_json::json!([s.pitch_x_um * a.pool as f64, s.pitch_y_um * a.pool as f64]),
        );
        o.insert(
            "files".into(),
            serde_json::json!([
                "datum.npy",
                "datum.npy.json",
                "roughness.npy",
                "roughness.npy.json",
                "pooled.npy",
                "pooled.npy.json",
                "separate.json"
            ]),
        );
    }
    let json = serde_json::to_string_pretty(&summary)?;
    write_atomic(&a.out.join("separate.json"), |w| {
        use std::io::Write;
        w.write_all(json.as_bytes())?;
        Ok(())
    })?;
    println!(
        "{}: {} rows x {} cols, pitch {}, {line}; wrote datum.npy, roughness.npy, pooled.npy \
         ({} rows x {} cols, pitch {}), each with its pitch sidecar NAME.npy.json, and separate.json to {}",
        a.file.display(),
        s.height,
        s.width,
        pitch_text(s.pitch_x_um, s.pitch_y_um),
        pooled.rows,
        pooled.cols,
        pitch_text(s.pitch_x_um * a.pool as f64, s.pitch_y_um * a.pool as f64),
        a.out.display()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn outputs_carry_the_pitch_and_sizes_are_rows_x_cols() {
        let d = tempfile::tempdir().unwrap();
        let input = d.path().join("in.npy");
        let (rows, cols) = (40, 64);
        let z: Vec<f64> = (0..rows * cols)
            .map(|i| ((i % cols) as f64 * 0.3).sin() + (i / cols) as f64 * 0.05)
            .collect();
        surfstream_io::npy::write_npy_f64(&input, &z, rows, cols).unwrap();
        let out = d.path().join("sep");
        run(SeparateArgs {
            mask: Default::default(),
            file: input,
            method: "wavelet".into(),
            cutoff_um: None,
            lambda_s_um: None,
            wavelet: "sym5".into(),
            level: "2".into(),
            mode: "symmetric".into(),
            pool: 4,
            pool_op: "max".into(),
            pitch_um: Some(0.5),
            out: out.clone(),
        })
        .unwrap();
        for (name, pitch, shape) in [
            ("datum.npy", 0.5, (rows, cols)),
            ("roughness.npy", 0.5, (rows, cols)),
            ("pooled.npy", 2.0, (rows / 4, cols / 4)),
        ] {
            let s = surfstream_io::formats::read_surface(&out.join(name)).unwrap();
            assert!(s.metadata.pitch_known, "{name}");
            assert_eq!((s.pitch_x_um, s.pitch_y_um), (pitch, pitch), "{name}");
            assert_eq!((s.height, s.width), shape, "{name}");
        }
        let j: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("separate.json")).unwrap())
                .unwrap();
        assert_eq!(j["input_rows_cols"], serde_json::json!([rows, cols]));
        assert_eq!(
            j["pooled_rows_cols"],
            serde_json::json!([rows / 4, cols / 4])
        );
        assert!(j.get("input_px").is_none() && j.get("pooled_px").is_none());
    }
}
