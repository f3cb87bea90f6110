//! `surfstream separate`: datum / roughness separation of one height map, on its own.
//!
//! Reads any map `formats::read_surface` reads, runs the pipeline's final separation
//! ([`surfstream_wavelet::separate_map`], the function the wavelet node's final pass calls:
//! streamed for a named wavelet at a fixed / default level, in memory for `auto` choices and
//! the filters) and writes
//! `datum.npy`, `roughness.npy`, `pooled.npy` (each with its pitch sidecar `NAME.npy.json`,
//! so `params` on them runs at the input's pitch) and `separate.json` (base, level, mode, energy
//! curve, RMSE ranking when the base is "auto", the level's equivalent cutoff, pooling bias)
//! into `--out`. `--method gaussian | robust-gaussian --cutoff-um L` separates by an ISO 16610
//! L-filter instead. datum.npy and roughness.npy are written row by row as the separation
//! gives them.
//!
//! The outputs are one [`OutputSet`]: every file is written under its temporary name and
//! they appear together, synced at one point (the files' data, whose write-back starts as
//! the rows are written, then the renames and the folder once); `--no-sync` skips the sync
//! for scratch outputs.

use std::path::PathBuf;

use anyhow::{anyhow, bail, Context, Result};
use clap::Args;
use serde::Serialize;
use surfstream_core::frame::{from_frame_heights, to_frame_heights};
use surfstream_core::fsutil::{Durability, OutputSet};
use surfstream_core::{Sampling, Shape};
use surfstream_io::formats::Surface;
use surfstream_io::npy::{write_npy_f64_into, NpyRowWriter};
use surfstream_io::sidecar::{write_sidecar_into, NpyGeometry};

use super::{file_help, load_surface, pitch_text, sig};
use surfstream_wavelet::{
    separate_map, LevelChoice, MapSummary, Pooled, SeparationMethod, SeparationSettings,
    SeparationSink, StreamOptions,
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
    /// Decomposition level, or "auto": the minimum of the approximation's energy proportion
    /// after plane levelling (paper Fig. 13). Default: 8, or the deepest level that fits the
    /// map when 8 does not; a level given that does not fit is lowered with a warning.
    #[arg(long)]
    pub level: Option<String>,
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
    /// Do not sync the outputs to the disk (scratch outputs): they still appear whole or not
    /// at all, but a power cut soon after the run may lose them. By default the run returns
    /// once every file is on the disk.
    #[arg(long = "no-sync")]
    pub no_sync: bool,
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

/// The options as the wavelet node's settings (one parser per option, shared with the node).
fn settings(a: &SeparateArgs) -> Result<SeparationSettings> {
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
    if a.pool == 0 {
        bail!("--pool 0: expected a block size of at least 1 px");
    }
    Ok(SeparationSettings {
        method,
        lambda_s_um,
        base: a.wavelet.parse().map_err(|e| anyhow!("--wavelet {e}"))?,
        level: match &a.level {
            Some(level) => level.parse().map_err(|e| anyhow!("--level {e}"))?,
            None => LevelChoice::Default,
        },
        mode: a.mode.parse().map_err(|e| anyhow!("--mode {e}"))?,
        pool_block: a.pool,
        pool_op: a.pool_op.parse().map_err(|e| anyhow!("--pool-op {e}"))?,
    })
}

/// `separate.json`: the separation's summary ([`MapSummary`], the node's too) with the input
/// and the files. Keys sorted when written, as run.json's.
#[derive(Serialize)]
struct SeparateJson {
    #[serde(flatten)]
    separation: MapSummary,
    /// Wavelet only, and then always (null when the level was not lowered); the filter
    /// methods have no level to lower.
    #[serde(skip_serializing_if = "Option::is_none")]
    warning: Option<Option<String>>,
    input: String,
    input_rows_cols: [usize; 2],
    pooled_rows_cols: [usize; 2],
    /// Heights inside the summary (pooling bias means) are relative to this; datum.npy and
    /// pooled.npy are absolute (f64), roughness.npy has no offset.
    z_offset_um: f64,
    pitch_um: [f64; 2],
    pooled_pitch_um: [f64; 2],
    files: [&'static str; 7],
}

/// The outputs' names, in `separate.json`'s `files`.
const FILES: [&str; 7] = [
    "datum.npy",
    "datum.npy.json",
    "roughness.npy",
    "roughness.npy.json",
    "pooled.npy",
    "pooled.npy.json",
    "separate.json",
];

pub fn run(a: SeparateArgs) -> Result<()> {
    let settings = settings(&a)?;
    let mut s = load_surface(&a.file, a.pitch_um, "separate", true)?.surface;
    a.mask.apply(&a.file, &mut s)?;
    // The separation takes f32 heights (as frames carry them, DESIGN §2) and runs in f64.
    // Instrument heights can sit tens of um up (MetroPro: ~50 um), where f32 keeps only
    // ~4e-6 um: remove the mean first, as frames do with z_offset_um, and add it back to
    // the datum and the pooled map, which are written in f64.
    // read_surface already made every non-finite height NaN, so the frame's NaN-skipping
    // mean is the same as skipping non-finite heights. The f64 heights are freed here.
    let (z_offset_um, heights) = to_frame_heights(&std::mem::take(&mut s.heights_um));
    let grid = Sampling::new(Shape::new(s.height, s.width), s.pitch_x_um, s.pitch_y_um)
        .with_context(|| format!("{}: pitch", a.file.display()))?;
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("{}: cannot create the output directory", a.out.display()))?;
    // The same separation as the pipeline's final pass (streamed where the node streams).
    // The whole map is in memory here, so a level store as large as the map (f32) stays in
    // memory too (at most two are held at once); larger ones spill into the output folder,
    // as the node's do.
    let stream = StreamOptions {
        spill_dir: Some(a.out.clone()),
        memory_store_max_bytes: std::mem::size_of_val(&heights[..])
            .max(StreamOptions::default().memory_store_max_bytes),
        ..StreamOptions::default()
    };
    let durability = if a.no_sync {
        Durability::NoSync
    } else {
        Durability::Synced
    };
    let mut outputs = OutputSet::new(durability);
    let mut sink = NpyPair::new(&a.out, z_offset_um, grid.rows(), grid.cols(), durability);
    let map = separate_map(&settings, &heights, &grid, &stream, &mut sink)
        .with_context(|| format!("{}: separation", a.file.display()))?;
    drop(heights);
    sink.finish_into(&mut outputs)?;
    if let Some(w) = &map.warning {
        eprintln!("{}: {w}", a.file.display());
    }
    write_pooled(&mut outputs, &a, &s, z_offset_um, &map.pooled)?;
    let line = summary_line(&map.summary);
    let pooled = [map.pooled.rows, map.pooled.cols];
    let pooled_pitch_um = [s.pitch_x_um * a.pool as f64, s.pitch_y_um * a.pool as f64];
    let record = SeparateJson {
        warning: matches!(map.summary, MapSummary::Wavelet(_)).then_some(map.warning),
        separation: map.summary,
        input: a.file.display().to_string(),
        input_rows_cols: [s.height, s.width],
        pooled_rows_cols: pooled,
        z_offset_um,
        pitch_um: [s.pitch_x_um, s.pitch_y_um],
        pooled_pitch_um,
        files: FILES,
    };
    let json = serde_json::to_string_pretty(&serde_json::to_value(&record)?)?;
    outputs.write(&a.out.join("separate.json"), |w| {
        use std::io::Write;
        w.write_all(json.as_bytes())?;
        Ok(())
    })?;
    outputs.commit()?;
    println!(
        "{}: {} rows x {} cols, pitch {}, {line}; wrote datum.npy, roughness.npy, pooled.npy \
         ({} rows x {} cols, pitch {}), each with its pitch sidecar NAME.npy.json, and separate.json to {}",
        a.file.display(),
        s.height,
        s.width,
        pitch_text(s.pitch_x_um, s.pitch_y_um),
        pooled[0],
        pooled[1],
        pitch_text(pooled_pitch_um[0], pooled_pitch_um[1]),
        a.out.display()
    );
    Ok(())
}

/// datum.npy (absolute f64) and roughness.npy (f32) written row by row as the separation
/// gives them.
struct NpyPair {
    dir: PathBuf,
    z_offset_um: f64,
    rows: usize,
    cols: usize,
    durability: Durability,
    writers: Option<(NpyRowWriter, NpyRowWriter)>,
}

impl NpyPair {
    fn new(
        dir: &std::path::Path,
        z_offset_um: f64,
        rows: usize,
        cols: usize,
        durability: Durability,
    ) -> Self {
        Self {
            dir: dir.to_path_buf(),
            z_offset_um,
            rows,
            cols,
            durability,
            writers: None,
        }
    }

    /// Hands both files to `outputs` (every row must have arrived).
    fn finish_into(&mut self, outputs: &mut OutputSet) -> Result<()> {
        let (d, r) = self
            .writers
            .take()
            .ok_or_else(|| anyhow!("{}: no datum was written", self.dir.display()))?;
        d.finish_into(outputs)?;
        r.finish_into(outputs)
    }
}

impl SeparationSink for NpyPair {
    fn begin(&mut self, _datum_title: &str) -> Result<()> {
        let mut datum = NpyRowWriter::create_f64(self.dir.join("datum.npy"), self.rows, self.cols)?;
        let mut roughness =
            NpyRowWriter::create_f32(self.dir.join("roughness.npy"), self.rows, self.cols)?;
        if self.durability == Durability::NoSync {
            datum = datum.without_writeback();
            roughness = roughness.without_writeback();
        }
        self.writers = Some((datum, roughness));
        Ok(())
    }

    fn push_rows(&mut self, datum: &[f32], roughness: &[f32]) -> Result<()> {
        let (d, r) = self
            .writers
            .as_mut()
            .ok_or_else(|| anyhow!("{}: rows before the files", self.dir.display()))?;
        d.push_abs_f64(datum, self.z_offset_um)?;
        r.push_f32(roughness)
    }
}

/// pooled.npy (absolute f64) and the pitch sidecar NAME.npy.json of every .npy, into
/// `outputs`.
fn write_pooled(
    outputs: &mut OutputSet,
    a: &SeparateArgs,
    s: &Surface,
    z_offset_um: f64,
    pooled: &Pooled,
) -> Result<()> {
    write_npy_f64_into(
        outputs,
        a.out.join("pooled.npy"),
        &from_frame_heights(z_offset_um, &pooled.heights),
        pooled.rows,
        pooled.cols,
    )?;
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
        write_sidecar_into(outputs, &a.out.join(name), &at(scale))?;
    }
    Ok(())
}

/// The choices in one line, for the terminal.
fn summary_line(summary: &MapSummary) -> String {
    match summary {
        MapSummary::Wavelet(w) => format!(
            "{} level {} ({}, equivalent cutoff {} um), level by min energy {}",
            w.choices.wavelet,
            w.choices.level,
            w.choices.mode,
            sig(w.equivalent_cutoff_um, 4),
            w.choices
                .level_min_energy
                .map_or("-".to_string(), |l| l.to_string()),
        ),
        MapSummary::Filter(f) => format!(
            "{} lambda_c {} um{}",
            f.method,
            sig(f.cutoff_um, 4),
            f.lambda_s_um
                .map_or(String::new(), |l| format!(", lambda_s {} um", sig(l, 4)))
        ),
    }
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
            level: Some("2".into()),
            mode: "symmetric".into(),
            pool: 4,
            pool_op: "max".into(),
            pitch_um: Some(0.5),
            out: out.clone(),
            no_sync: false,
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

    /// The verb's datum / roughness files hold the in-memory oracle's bits ([`analyse`]), on
    /// the streamed path (a fixed level) and on the in-memory one (level auto), for a map of
    /// more rows than one band of the whole-map writer and with holes.
    #[test]
    fn files_hold_the_oracles_bits_streamed_and_in_memory() {
        use surfstream_wavelet::{analyse, BaseChoice, LevelChoice, Mode, PoolOp, Wavelet};
        let d = tempfile::tempdir().unwrap();
        let input = d.path().join("in.npy");
        let (rows, cols) = (300, 90);
        let z: Vec<f64> = (0..rows * cols)
            .map(|i| {
                let (r, c) = ((i / cols) as f64, (i % cols) as f64);
                if i % 997 == 5 || i / cols == 150 {
                    f64::NAN
                } else {
                    40.0 + (c * 0.3).sin() + r * 0.05 + ((i * 7919) % 89) as f64 * 1e-3
                }
            })
            .collect();
        surfstream_io::npy::write_npy_f64(&input, &z, rows, cols).unwrap();
        let (z_offset_um, heights) = to_frame_heights(&z);
        let sym5 = Wavelet::by_name("sym5").unwrap();
        for (level, choice) in [
            ("3", LevelChoice::Fixed(3)),
            ("auto", LevelChoice::MinEnergy),
        ] {
            let out = d.path().join(format!("sep-{level}"));
            run(SeparateArgs {
                mask: Default::default(),
                file: input.clone(),
                method: "wavelet".into(),
                cutoff_um: None,
                lambda_s_um: None,
                wavelet: "sym5".into(),
                level: Some(level.into()),
                mode: "symmetric".into(),
                pool: 4,
                pool_op: "max".into(),
                pitch_um: Some(0.5),
                out: out.clone(),
                no_sync: level == "auto",
            })
            .unwrap();
            let oracle = analyse(
                &heights,
                rows,
                cols,
                BaseChoice::Named(sym5),
                choice,
                Mode::Symmetric,
                4,
                PoolOp::Max,
            )
            .unwrap();
            let datum = surfstream_io::npy::read_npy_f64(out.join("datum.npy")).unwrap();
            let roughness = surfstream_io::npy::read_npy(out.join("roughness.npy")).unwrap();
            let expected: Vec<u64> = from_frame_heights(z_offset_um, &oracle.separation.datum)
                .iter()
                .map(|v| v.to_bits())
                .collect();
            let got: Vec<u64> = datum.data.iter().map(|v| v.to_bits()).collect();
            assert!(got == expected, "level {level}: datum.npy");
            let expected: Vec<u32> = oracle
                .separation
                .roughness
                .iter()
                .map(|v| v.to_bits())
                .collect();
            let got: Vec<u32> = roughness.data.iter().map(|v| v.to_bits()).collect();
            assert!(got == expected, "level {level}: roughness.npy");
            let j: serde_json::Value =
                serde_json::from_str(&std::fs::read_to_string(out.join("separate.json")).unwrap())
                    .unwrap();
            assert_eq!(j["level"], oracle.separation.level, "level {level}");
            assert!(j["warning"].is_null(), "level {level}");
        }
    }
}
