//! `surfstream inspect | params | convert | compare`: reading instrument files and judging
//! surfaces (ISO 25178 parameters, SIM, SSIM). Thin shells over surfstream_io::formats,
//! ::metrology and ::similarity.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::Args;
use surfstream_core::metrology::{self, Grid};
use surfstream_core::similarity;
use surfstream_io::formats::{read_surface, write_surface, Surface};

#[derive(Args)]
pub struct InspectArgs {
    /// Height-map file (.datx, .dat, .x3p, .sur, .npy, .xyz).
    pub file: PathBuf,
    /// Print JSON instead of text.
    #[arg(long)]
    pub json: bool,
}

#[derive(Args)]
pub struct ParamsArgs {
    /// Height-map file.
    pub file: PathBuf,
    /// Subtract the least-squares plane first (otherwise only the mean is removed).
    #[arg(long)]
    pub level: bool,
    /// Print JSON: one key per parameter ("Sa", "Sq", ...), heights in um, Sdr in %.
    #[arg(long)]
    pub json: bool,
    /// Pitch in um for files that carry none (.npy); an error for files that do.
    #[arg(long)]
    pub pitch_um: Option<f64>,
}

#[derive(Args)]
pub struct ConvertArgs {
    /// Any readable height-map file.
    pub input: PathBuf,
    /// Output file, .x3p or .npy (missing folders are created).
    #[arg(short = 'o', long = "out", value_name = "OUT")]
    pub out: Option<PathBuf>,
    /// Deprecated: the output as a second argument (use -o).
    #[arg(hide = true, value_name = "OUTPUT")]
    pub output: Option<PathBuf>,
    /// Pitch in um for inputs that carry none (.npy); an error for inputs that do.
    #[arg(long)]
    pub pitch_um: Option<f64>,
}

#[derive(Args)]
pub struct CompareArgs {
    pub a: PathBuf,
    pub b: PathBuf,
    /// Print JSON instead of text.
    #[arg(long)]
    pub json: bool,
}

/// Reads `path`, applying `pitch_um` to files without a lateral calibration.
fn load(path: &Path, pitch_um: Option<f64>) -> Result<Surface> {
    let mut s = read_surface(path)?;
    for w in &s.metadata.warnings {
        eprintln!("{}: warning: {w}", path.display());
    }
    if let Some(p) = pitch_um {
        if !(p.is_finite() && p > 0.0) {
            bail!("--pitch-um {p}: expected a finite positive number");
        }
        if s.metadata.pitch_known {
            bail!(
                "{}: the file carries its pitch ({} x {} um); --pitch-um is only for files without one",
                path.display(),
                s.pitch_x_um,
                s.pitch_y_um
            );
        }
        s.pitch_x_um = p;
        s.pitch_y_um = p;
    }
    Ok(s)
}

fn grid(s: &Surface) -> Result<Grid<'_>> {
    Ok(Grid::new(
        &s.heights_um,
        s.height,
        s.width,
        s.pitch_x_um,
        s.pitch_y_um,
    )?)
}

pub fn inspect(a: InspectArgs) -> Result<()> {
    let s = load(&a.file, None)?;
    let valid: Vec<f64> = s
        .heights_um
        .iter()
        .copied()
        .filter(|z| !z.is_nan())
        .collect();
    let (lo, hi) = valid
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &z| {
            (l.min(z), h.max(z))
        });
    let info = serde_json::json!({
        "file": a.file.display().to_string(),
        "rows": s.height,
        "cols": s.width,
        "pitch_x_um": s.pitch_x_um,
        "pitch_y_um": s.pitch_y_um,
        "points": s.heights_um.len(),
        "invalid_points": s.invalid_count(),
        "min_um": if valid.is_empty() { None } else { Some(lo) },
        "max_um": if valid.is_empty() { None } else { Some(hi) },
        "metadata": s.metadata,
    });
    if a.json {
        println!("{}", serde_json::to_string_pretty(&info)?);
        return Ok(());
    }
    let m = &s.metadata;
    println!("file        {}", a.file.display());
    println!("format      {}", m.format);
    println!("shape       {} rows x {} cols", s.height, s.width);
    let pitch_note = if m.pitch_known {
        ""
    } else {
        " (not in the file: assumed)"
    };
    println!(
        "pitch       {} x {} um{pitch_note}",
        s.pitch_x_um, s.pitch_y_um
    );
    println!(
        "invalid     {} of {} points",
        s.invalid_count(),
        s.heights_um.len()
    );
    if !valid.is_empty() {
        println!("heights     {lo} .. {hi} um");
    }
    for (k, v) in [
        ("instrument", &m.instrument),
        ("serial", &m.serial),
        ("date", &m.date),
    ] {
        if let Some(v) = v {
            println!("{k:<11} {v}");
        }
    }
    if let Some(w) = m.wavelength_um {
        println!("wavelength  {w} um");
    }
    for (k, v) in &m.extra {
        println!("{k:<11} {v}");
    }
    Ok(())
}

pub fn params(a: ParamsArgs) -> Result<()> {
    let s = load(&a.file, a.pitch_um)?;
    let g = grid(&s).with_context(|| format!("{}", a.file.display()))?;
    let levelled;
    let g = if a.level {
        levelled = metrology::level_plane(&g).with_context(|| format!("{}", a.file.display()))?;
        Grid {
            heights_um: &levelled,
            ..g
        }
    } else {
        g
    };
    let p = metrology::params(&g).with_context(|| format!("{}", a.file.display()))?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&p)?);
        return Ok(());
    }
    println!(
        "{}: {} x {} px, pitch {} x {} um, {} valid points, {}",
        a.file.display(),
        s.height,
        s.width,
        s.pitch_x_um,
        s.pitch_y_um,
        s.heights_um.len() - s.invalid_count(),
        if a.level {
            "plane levelled"
        } else {
            "mean removed, not levelled"
        }
    );
    for (name, v) in p.named() {
        let unit = match name {
            "Ssk" | "Sku" | "Sdq" => "",
            "Sdr" => " %",
            _ => " um",
        };
        println!("{name:<4} {v:.10e}{unit}");
    }
    if s.invalid_count() > 0 {
        println!("(over valid points; Sdq and Sdr use only differences and cells whose points are all valid)");
    }
    Ok(())
}

pub fn convert(a: ConvertArgs) -> Result<()> {
    let Some(output) = a.out.or(a.output) else {
        bail!("convert: no output: write `convert IN -o OUT.x3p` (or .npy)");
    };
    let s = load(&a.input, a.pitch_um)?;
    write_surface(&output, &s)?;
    eprintln!(
        "{} -> {} ({} x {} px (rows x cols), pitch {:.4} x {:.4} um)",
        a.input.display(),
        output.display(),
        s.height,
        s.width,
        s.pitch_x_um,
        s.pitch_y_um
    );
    Ok(())
}

pub fn compare(a: CompareArgs) -> Result<()> {
    let x = load(&a.a, None)?;
    let y = load(&a.b, None)?;
    if (x.height, x.width) != (y.height, y.width) {
        bail!(
            "{} is {} x {} px but {} is {} x {} px: compare needs maps of the same shape",
            a.a.display(),
            x.height,
            x.width,
            a.b.display(),
            y.height,
            y.width
        );
    }
    let sim = metrology::sim(&x.heights_um, &y.heights_um)?;
    let (rms, n) = metrology::rms_difference(&x.heights_um, &y.heights_um)?;
    let xf: Vec<f32> = x.heights_um.iter().map(|&v| v as f32).collect();
    let yf: Vec<f32> = y.heights_um.iter().map(|&v| v as f32).collect();
    let ssim =
        similarity::ssim(&xf, &yf, x.height, x.width, None).map_err(|e| anyhow::anyhow!("{e}"))?;
    if a.json {
        let v = serde_json::json!({
            "SIM": sim, "SSIM": ssim.mssim, "SSIM_windows": ssim.windows, "SSIM_range_um": ssim.range_um,
            "rms_difference_um": rms, "points_compared": n,
        });
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!("SIM   {sim:.9} (normalised cross-correlation, eq. 12)");
        println!(
            "SSIM  {:.9} ({} windows, L = {} um)",
            ssim.mssim, ssim.windows, ssim.range_um
        );
        println!("RMS   {rms:.9e} um over {n} points valid in both");
    }
    Ok(())
}
