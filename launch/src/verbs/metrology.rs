//! `surfstream inspect | params | convert | compare`: reading instrument files and judging
//! surfaces (ISO 25178 parameters, SIM, SSIM). Thin shells over surfstream_io::formats,
//! ::metrology and ::similarity.

use std::path::{Path, PathBuf};

use anyhow::{bail, Result};
use clap::Args;
use surfstream_core::metrology::{self, Grid, ParamValue};
use surfstream_core::similarity;
use surfstream_io::formats::{read_surface, write_surface, Surface};

#[derive(Args)]
pub struct InspectArgs {
    /// Height-map file (.datx, .dat, .x3p, .sur, .npy, .xyz).
    pub file: PathBuf,
    /// Print JSON instead of text.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub mask: super::MaskArgs,
}

#[derive(Args)]
pub struct ParamsArgs {
    /// Height-map files (any readable format); one record per file, in the order given.
    #[arg(required = true)]
    pub files: Vec<PathBuf>,
    /// Every ISO 25178-2 parameter: height, hybrid, spatial (Sal Str Std), functional (Sk
    /// family, volumes, Smr(c), Smc(mr)) and feature (Spd Spc S5p S5v S10z Sda Sha Sdv Shv).
    /// Without it: Sa Sq Sp Sv Sz Ssk Sku Sdq Sdr.
    #[arg(long)]
    pub all: bool,
    /// Subtract the least-squares plane first (otherwise only the mean is removed).
    #[arg(long)]
    pub level: bool,
    /// JSON: one object per file (an array for several files), values at full precision,
    /// units in "units".
    #[arg(long, conflicts_with_all = ["csv", "jsonl"])]
    pub json: bool,
    /// CSV: a header naming each column with its unit, one row per file.
    #[arg(long, conflicts_with = "jsonl")]
    pub csv: bool,
    /// JSON lines: one object per file per line.
    #[arg(long)]
    pub jsonl: bool,
    /// Write to this file instead of standard output (parent folders created; nothing is
    /// written when any file fails).
    #[arg(short = 'o', long = "out")]
    pub out: Option<PathBuf>,
    /// Pitch in um for files that carry none (.npy); an error for files that do. Without it
    /// such files are computed at 1 um with a warning.
    #[arg(long)]
    pub pitch_um: Option<f64>,
    /// Wolf pruning threshold of the feature parameters, % of Sz (ISO 25178-3: 5).
    #[arg(long, default_value_t = 5.0)]
    pub pruning_pct: f64,
    #[command(flatten)]
    pub mask: super::MaskArgs,
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
    #[command(flatten)]
    pub mask: super::MaskArgs,
}

#[derive(Args)]
pub struct CompareArgs {
    pub a: PathBuf,
    pub b: PathBuf,
    /// Print JSON instead of text.
    #[arg(long)]
    pub json: bool,
}

/// Reads `path`, applying `pitch_um` to files without a lateral calibration and dropping the
/// mask regions `mask` names.
fn load(path: &Path, pitch_um: Option<f64>, mask: &super::MaskArgs) -> Result<Surface> {
    let mut s = read_surface(path)?;
    for w in &s.metadata.warnings {
        eprintln!("{}: warning: {w}", path.display());
    }
    mask.apply(path, &mut s)?;
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
    let s = load(&a.file, None, &a.mask)?;
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
        "pitch       x {:.4} um, y {:.4} um{pitch_note}",
        s.pitch_x_um, s.pitch_y_um
    );
    println!(
        "invalid     {} of {} points",
        s.invalid_count(),
        s.heights_um.len()
    );
    if !valid.is_empty() {
        println!("heights     {lo:.4} .. {hi:.4} um");
    }
    if let Some(mask) = &m.mask {
        print_mask_regions(mask, !a.mask.mask_exclude.is_empty());
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
        println!("wavelength  {w:.4} um");
    }
    for (k, v) in &m.extra {
        println!("{k:<11} {v}");
    }
    Ok(())
}

/// The labelled regions of an X3P colour mask, one line each.
fn print_mask_regions(mask: &surfstream_io::formats::x3p::ColourMask, excluded: bool) {
    let note = if excluded {
        "--mask-exclude applied above"
    } else {
        "labels only: every point read as measured; --mask-exclude NAME|#rrggbb drops one"
    };
    println!(
        "mask        {}, {} regions ({note})",
        mask.image,
        mask.regions.len()
    );
    let width = mask
        .regions
        .iter()
        .map(|r| r.label().chars().count())
        .max()
        .unwrap_or(0);
    for r in &mask.regions {
        let label = r.label();
        let pad = width.saturating_sub(label.chars().count());
        println!(
            "  {label}{:pad$}  {}  {:>9} points{}",
            "",
            r.colour,
            r.points,
            if r.background { "  (background)" } else { "" }
        );
    }
}

/// One file's parameters, ready to print.
struct ParamsRecord {
    file: String,
    rows: usize,
    cols: usize,
    pitch_x_um: f64,
    pitch_y_um: f64,
    pitch_assumed: bool,
    valid_points: usize,
    levelled: bool,
    values: Vec<ParamValue>,
}

fn basic_named(p: &metrology::Params) -> Vec<ParamValue> {
    let unit = |name: &str| match name {
        "Ssk" | "Sku" | "Sdq" => "",
        "Sdr" => "%",
        _ => "um",
    };
    let family = |name: &str| match name {
        "Sdq" | "Sdr" => "hybrid",
        _ => "height",
    };
    p.named()
        .into_iter()
        .map(|(name, value)| ParamValue {
            name,
            value,
            unit: unit(name),
            family: family(name),
        })
        .collect()
}

fn params_of(path: &Path, a: &ParamsArgs) -> Result<ParamsRecord> {
    let s = load(path, a.pitch_um, &a.mask)?;
    let pitch_assumed = !s.metadata.pitch_known && a.pitch_um.is_none();
    if pitch_assumed {
        eprintln!(
            "{}: warning: the file carries no pitch; assumed {} x {} um (give --pitch-um)",
            path.display(),
            s.pitch_x_um,
            s.pitch_y_um
        );
    }
    let g = grid(&s)?;
    let levelled;
    let g = if a.level {
        levelled = metrology::level_plane(&g)?;
        Grid {
            heights_um: &levelled,
            ..g
        }
    } else {
        g
    };
    let values = if a.all {
        metrology::all_params_pruned(&g, a.pruning_pct)?.named()
    } else {
        basic_named(&metrology::params(&g)?)
    };
    Ok(ParamsRecord {
        file: path.display().to_string(),
        rows: s.height,
        cols: s.width,
        pitch_x_um: s.pitch_x_um,
        pitch_y_um: s.pitch_y_um,
        pitch_assumed,
        valid_points: s.heights_um.len() - s.invalid_count(),
        levelled: a.level,
        values,
    })
}

/// A number with 6 significant digits, fixed-point where that reads well.
fn sig6(v: f64) -> String {
    if v.is_nan() {
        return "NaN".into();
    }
    if v == 0.0 {
        return "0".into();
    }
    let e = v.abs().log10().floor() as i32;
    if (-4..6).contains(&e) {
        format!("{v:.*}", (5 - e).max(0) as usize)
    } else {
        format!("{v:.5e}")
    }
}

fn json_record(r: &ParamsRecord) -> serde_json::Value {
    let mut m = serde_json::Map::new();
    m.insert("file".into(), r.file.clone().into());
    m.insert("rows".into(), r.rows.into());
    m.insert("cols".into(), r.cols.into());
    m.insert("pitch_x_um".into(), r.pitch_x_um.into());
    m.insert("pitch_y_um".into(), r.pitch_y_um.into());
    m.insert("pitch_assumed".into(), r.pitch_assumed.into());
    m.insert("valid_points".into(), r.valid_points.into());
    m.insert(
        "surface".into(),
        if r.levelled {
            "plane levelled"
        } else {
            "mean removed"
        }
        .into(),
    );
    let mut units = serde_json::Map::new();
    for v in &r.values {
        // NaN (undefined, e.g. Str when the ACF does not decay inside the map) becomes null.
        m.insert(v.name.into(), serde_json::json!(v.value));
        units.insert(v.name.into(), v.unit.into());
    }
    m.insert("units".into(), units.into());
    serde_json::Value::Object(m)
}

fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

fn render(records: &[ParamsRecord], a: &ParamsArgs) -> Result<String> {
    use std::fmt::Write as _;
    let mut out = String::new();
    if a.json {
        let v: Vec<_> = records.iter().map(json_record).collect();
        let doc = if v.len() == 1 {
            v.into_iter().next().unwrap_or_default()
        } else {
            serde_json::Value::Array(v)
        };
        out = serde_json::to_string_pretty(&doc)?;
        out.push('\n');
    } else if a.jsonl {
        for r in records {
            writeln!(out, "{}", serde_json::to_string(&json_record(r))?)?;
        }
    } else if a.csv {
        let mut head = vec![
            "file".to_string(),
            "rows".into(),
            "cols".into(),
            "pitch_x [um]".into(),
            "pitch_y [um]".into(),
            "pitch_assumed".into(),
            "valid_points".into(),
            "surface".into(),
        ];
        if let Some(r) = records.first() {
            for v in &r.values {
                head.push(if v.unit.is_empty() {
                    v.name.to_string()
                } else {
                    format!("{} [{}]", v.name, v.unit)
                });
            }
        }
        writeln!(
            out,
            "{}",
            head.iter()
                .map(|h| csv_field(h))
                .collect::<Vec<_>>()
                .join(",")
        )?;
        for r in records {
            let mut row = vec![
                csv_field(&r.file),
                r.rows.to_string(),
                r.cols.to_string(),
                r.pitch_x_um.to_string(),
                r.pitch_y_um.to_string(),
                r.pitch_assumed.to_string(),
                r.valid_points.to_string(),
                if r.levelled {
                    "plane levelled"
                } else {
                    "mean removed"
                }
                .into(),
            ];
            // Undefined values are empty cells.
            row.extend(r.values.iter().map(|v| {
                if v.value.is_nan() {
                    String::new()
                } else {
                    sig6(v.value)
                }
            }));
            writeln!(out, "{}", row.join(","))?;
        }
    } else {
        for (k, r) in records.iter().enumerate() {
            if k > 0 {
                out.push('\n');
            }
            writeln!(
                out,
                "{}: {} rows x {} cols, pitch {} x {} um{}, {} valid points, {}",
                r.file,
                r.rows,
                r.cols,
                r.pitch_x_um,
                r.pitch_y_um,
                if r.pitch_assumed { " (assumed)" } else { "" },
                r.valid_points,
                if r.levelled {
                    "plane levelled"
                } else {
                    "mean removed, not levelled"
                }
            )?;
            let mut family = "";
            for v in &r.values {
                if a.all && v.family != family {
                    family = v.family;
                    writeln!(out, "  {family}")?;
                }
                writeln!(out, "    {:<12} {:>14} {}", v.name, sig6(v.value), v.unit)?;
            }
            if r.valid_points < r.rows * r.cols {
                writeln!(out, "  (over the valid points; Sdq and Sdr use only differences and cells whose points are all valid)")?;
            }
        }
    }
    Ok(out)
}

pub fn params(a: ParamsArgs) -> Result<()> {
    if !(a.pruning_pct.is_finite() && a.pruning_pct >= 0.0) {
        bail!(
            "--pruning-pct {}: expected a finite number >= 0",
            a.pruning_pct
        );
    }
    let mut records = Vec::with_capacity(a.files.len());
    let mut failures = Vec::new();
    for f in &a.files {
        match params_of(f, &a) {
            Ok(r) => records.push(r),
            Err(e) => {
                // Readers name the file already; others (a computation) get it here.
                let msg = format!("{e:#}");
                let name = f.display().to_string();
                failures.push(if msg.contains(&name) {
                    msg
                } else {
                    format!("{name}: {msg}")
                });
            }
        }
    }
    if !failures.is_empty() {
        for f in &failures[..failures.len() - 1] {
            eprintln!("error: {f}");
        }
        bail!(
            "{}{}",
            failures[failures.len() - 1],
            if a.out.is_some() {
                " (nothing written)"
            } else {
                ""
            }
        );
    }
    let text = render(&records, &a)?;
    match &a.out {
        Some(path) => {
            surfstream_core::fsutil::write_atomic(path, |w| {
                use std::io::Write as _;
                w.write_all(text.as_bytes())?;
                Ok(())
            })?;
            eprintln!("{} file(s) -> {}", records.len(), path.display());
        }
        None => print!("{text}"),
    }
    Ok(())
}

pub fn convert(a: ConvertArgs) -> Result<()> {
    let Some(output) = a.out.or(a.output) else {
        bail!("convert: no output: write `convert IN -o OUT.x3p` (or .npy)");
    };
    let s = load(&a.input, a.pitch_um, &a.mask)?;
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
    let x = load(&a.a, None, &Default::default())?;
    let y = load(&a.b, None, &Default::default())?;
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
        println!("SIM   {sim:.6} (normalised cross-correlation, eq. 12)");
        println!(
            "SSIM  {:.6} ({} windows, L = {:.4} um)",
            ssim.mssim, ssim.windows, ssim.range_um
        );
        println!("RMS   {rms:.6} um over {n} points valid in both");
    }
    Ok(())
}
