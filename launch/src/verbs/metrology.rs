//! `surfstream inspect | params | convert | compare`: reading instrument files and judging
//! surfaces (ISO 25178 parameters, SIM, SSIM). Thin shells over surfstream_io::formats,
//! ::metrology and ::similarity.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{bail, Result};
use clap::Args;
use serde::Serialize;
use surfstream_core::metrology::{self, Grid, ParamValue};
use surfstream_core::record;
use surfstream_core::similarity;
use surfstream_core::units::{self, sig};
use surfstream_io::formats::{write_surface, Metadata, Surface};

use super::{file_help, load_surface, pitch_text, Loaded, WRITABLE_WITH_PITCH};

#[derive(Args)]
pub struct InspectArgs {
    #[arg(help = file_help())]
    pub file: PathBuf,
    /// Print JSON instead of text.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub mask: super::MaskArgs,
}

#[derive(Args)]
pub struct ParamsArgs {
    /// Height-map files (any readable format), one record per file in the order given; or a
    /// folder: every readable file in it, one table row per file (a file that cannot be read
    /// is named on stderr and the exit status is 1).
    #[arg(required = true, value_name = "FILE|DIR")]
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
    /// Pitch in um for files that carry none (a .npy without its NAME.npy.json sidecar);
    /// refused when it disagrees with a file's own. Without it such files are computed at
    /// 1 um with a warning.
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
    /// Any readable height-map file, or a folder: every readable file in it is converted
    /// into the folder -o names, as --to says (a table, one row per file).
    #[arg(value_name = "IN|DIR")]
    pub input: PathBuf,
    /// Output file: .x3p, .npy (+ its pitch sidecar NAME.npy.json), .gsf (Gwyddion) or
    /// .tif (float32 TIFF, um); for a folder input, the output folder (missing folders are
    /// created).
    #[arg(short = 'o', long = "out", value_name = "OUT")]
    pub out: Option<PathBuf>,
    /// For a folder input: the format to write (x3p, npy, gsf, tif).
    #[arg(long, value_name = "EXT", default_value = "x3p")]
    pub to: String,
    /// Deprecated: the output as a second argument (use -o).
    #[arg(hide = true, value_name = "OUTPUT")]
    pub output: Option<PathBuf>,
    /// Pitch in um for inputs that carry none (a .npy without its sidecar); refused when it
    /// disagrees with the input's own. Needed for such inputs to .x3p, .gsf or .tif (they
    /// store a pitch).
    #[arg(long)]
    pub pitch_um: Option<f64>,
    #[command(flatten)]
    pub mask: super::MaskArgs,
}

#[derive(Args)]
pub struct CompareArgs {
    /// The first height map (any readable format; e.g. a panorama).
    pub a: PathBuf,
    /// The second, of the same rows x cols and pitch as A (e.g. its datum, or a reference);
    /// maps whose pitches differ by more than 1e-6 relative are refused (no resampling).
    /// SIM and SSIM are symmetric; the RMS difference is over the points valid in both.
    pub b: PathBuf,
    /// Print JSON instead of text.
    #[arg(long)]
    pub json: bool,
}

/// `inspect --json`. Written through [`record::to_value`], keys sorted like every JSON
/// surfstream writes.
#[derive(Serialize)]
struct InspectJson<'a> {
    file: String,
    rows: usize,
    cols: usize,
    pitch_x_um: f64,
    pitch_y_um: f64,
    points: usize,
    invalid_points: usize,
    /// None when no sample is valid.
    min_um: Option<f64>,
    max_um: Option<f64>,
    metadata: &'a Metadata,
}

/// One file of `params --json` / `--jsonl`: the parameters by name beside the file's fields
/// (written through [`record::to_value`], keys sorted).
#[derive(Serialize)]
struct ParamsJson<'a> {
    file: &'a str,
    rows: usize,
    cols: usize,
    pitch_x_um: f64,
    pitch_y_um: f64,
    pitch_assumed: bool,
    valid_points: usize,
    /// "plane levelled" or "mean removed".
    surface: &'static str,
    /// Each parameter's value (NaN, undefined, e.g. Str when the ACF does not decay inside
    /// the map, is written as null).
    #[serde(flatten)]
    values: BTreeMap<&'static str, f64>,
    /// Each parameter's unit.
    units: BTreeMap<&'static str, &'static str>,
    /// Why some values are undefined; absent when none is.
    #[serde(skip_serializing_if = "<[String]>::is_empty")]
    notes: &'a [String],
}

/// `compare --json`.
#[derive(Serialize)]
struct CompareJson {
    #[serde(rename = "SIM")]
    sim: f64,
    #[serde(rename = "SSIM")]
    ssim: f64,
    #[serde(rename = "SSIM_windows")]
    ssim_windows: usize,
    #[serde(rename = "SSIM_range_um")]
    ssim_range_um: f64,
    rms_difference_um: f64,
    points_compared: usize,
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
    let mut s = load_surface(&a.file, None, "inspect", false)?.surface;
    a.mask.apply(&a.file, &mut s)?;
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
    if a.json {
        let info = InspectJson {
            file: a.file.display().to_string(),
            rows: s.height,
            cols: s.width,
            pitch_x_um: s.pitch_x_um,
            pitch_y_um: s.pitch_y_um,
            points: s.heights_um.len(),
            invalid_points: s.invalid_count(),
            min_um: (!valid.is_empty()).then_some(lo),
            max_um: (!valid.is_empty()).then_some(hi),
            metadata: &s.metadata,
        };
        println!(
            "{}",
            serde_json::to_string_pretty(&record::to_value(&info)?)?
        );
        return Ok(());
    }
    let m = &s.metadata;
    println!("file        {}", a.file.display());
    println!("format      {}", m.format);
    println!("shape       {} rows x {} cols", s.height, s.width);
    let pitch_note = if m.pitch_known {
        String::new()
    } else {
        format!(
            " (not in the file: assumed; give --pitch-um to the other verbs, or keep a {} sidecar beside it)",
            surfstream_io::sidecar::sidecar_path(&a.file)
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default()
        )
    };
    println!(
        "pitch       {}{pitch_note}",
        pitch_text(s.pitch_x_um, s.pitch_y_um)
    );
    println!(
        "invalid     {} of {} points",
        s.invalid_count(),
        s.heights_um.len()
    );
    if !valid.is_empty() {
        println!("heights     {} .. {}", units::height(lo), units::height(hi));
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
    /// Why some values are undefined (feature parameters without a significant motif).
    notes: Vec<String>,
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
    let loaded = load_surface(path, a.pitch_um, "params", true)?;
    let (mut s, pitch_assumed) = (loaded.surface, loaded.pitch_assumed);
    a.mask.apply(path, &mut s)?;
    let g = grid(&s)?;
    let levelled;
    let g = if a.level {
        levelled = metrology::level_plane(&g)?;
        Grid::of(&levelled, g.sampling())?
    } else {
        g
    };
    let values = if a.all {
        metrology::all_params_pruned(&g, a.pruning_pct)?.named()
    } else {
        basic_named(&metrology::params(&g)?)
    };
    let notes = feature_notes(&values, a.level, a.pruning_pct);
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
        notes,
    })
}

/// Why feature parameters are undefined, when they are: no motif survives as significant.
fn feature_notes(values: &[ParamValue], levelled: bool, pruning_pct: f64) -> Vec<String> {
    let undefined: Vec<&str> = values
        .iter()
        .filter(|v| {
            v.family == "feature" && (v.value.is_nan() || (v.name == "Spd" && v.value == 0.0))
        })
        .map(|v| v.name)
        .collect();
    if undefined.is_empty() {
        return Vec::new();
    }
    let why = format!(
        "{} undefined (Spd = 0: no significant hill): after Wolf pruning at {pruning_pct} % of Sz \
         every remaining hill or dale touches the map's border or a gap, so none counts",
        undefined.join(", ")
    );
    vec![if levelled {
        why
    } else {
        format!(
            "{why}; the surface is not levelled, and a tilt or form drains every motif to the \
             low edge: --level (plane first) usually defines them"
        )
    }]
}

/// A parameter as the text output shows it, (value, unit): 3 significant figures, heights and
/// lengths in um read in nm below 1 um ("5.12", "nm"), as the verdict and report.html print
/// them ([`surfstream_core::units`]). `--json`, `--jsonl` and `--csv` keep the numbers.
fn param_text(value: f64, unit: &str) -> (String, String) {
    if unit == "um" && value.is_finite() {
        let t = units::height(value);
        if let Some((number, unit)) = t.split_once(' ') {
            return (number.to_string(), unit.to_string());
        }
    }
    (sig(value, units::HEIGHT_DIGITS), unit.to_string())
}

/// A number with 6 significant digits, fixed-point where that reads well (the CSV's).
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

fn json_record(r: &ParamsRecord) -> Result<serde_json::Value, record::RecordError> {
    record::to_value(&ParamsJson {
        file: &r.file,
        rows: r.rows,
        cols: r.cols,
        pitch_x_um: r.pitch_x_um,
        pitch_y_um: r.pitch_y_um,
        pitch_assumed: r.pitch_assumed,
        valid_points: r.valid_points,
        surface: if r.levelled {
            "plane levelled"
        } else {
            "mean removed"
        },
        values: r.values.iter().map(|v| (v.name, v.value)).collect(),
        units: r.values.iter().map(|v| (v.name, v.unit)).collect(),
        notes: &r.notes,
    })
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
        let v = records
            .iter()
            .map(json_record)
            .collect::<Result<Vec<_>, _>>()?;
        let doc = if v.len() == 1 {
            v.into_iter().next().unwrap_or_default()
        } else {
            serde_json::Value::Array(v)
        };
        out = serde_json::to_string_pretty(&doc)?;
        out.push('\n');
    } else if a.jsonl {
        for r in records {
            writeln!(out, "{}", serde_json::to_string(&json_record(r)?)?)?;
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
                "{}: {} rows x {} cols, pitch {}{}, {} valid points, {}",
                r.file,
                r.rows,
                r.cols,
                pitch_text(r.pitch_x_um, r.pitch_y_um),
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
                let (value, unit) = param_text(v.value, v.unit);
                writeln!(out, "    {:<12} {value:>10} {unit}", v.name)?;
            }
            if r.valid_points < r.rows * r.cols {
                writeln!(out, "  (over the valid points; Sdq and Sdr use only differences and cells whose points are all valid)")?;
            }
            for n in &r.notes {
                writeln!(out, "  note: {n}")?;
            }
        }
    }
    Ok(out)
}

/// Buffers of 1 MiB and more straight from the kernel and back to it when freed. glibc's
/// default threshold slides up to the largest buffer freed (32 MiB), after which the feature
/// segmentations' map-sized working sets come from the heap and stay there: `params --all`
/// of a 4096^2 map peaked 11 % higher (301 against 271 MB; the same values either way).
fn large_buffers_from_the_kernel() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets an allocator parameter; called before the work starts.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 1 << 20);
    }
}

pub fn params(a: ParamsArgs) -> Result<()> {
    large_buffers_from_the_kernel();
    if !(a.pruning_pct.is_finite() && a.pruning_pct >= 0.0) {
        bail!(
            "--pruning-pct {}: expected a finite number >= 0",
            a.pruning_pct
        );
    }
    // A folder stands for its readable files; a batch over a folder reports a file that
    // cannot be read and goes on (exit status 1 at the end).
    let mut files = Vec::new();
    let mut folder = false;
    for f in &a.files {
        if f.is_dir() {
            folder = true;
            files.extend(super::readable_files(f)?);
        } else {
            files.push(f.clone());
        }
    }
    let mut records = Vec::with_capacity(files.len());
    let mut failures = Vec::new();
    for f in &files {
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
    // Explicit files: any failure fails the whole (nothing written). A folder: the readable
    // ones are still tabled, unless none was.
    let partial_batch = folder && !records.is_empty();
    if !failures.is_empty() && !partial_batch {
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
    let plain = !(a.json || a.jsonl || a.csv);
    let text = if folder && plain {
        render_table(&records)
    } else {
        render(&records, &a)?
    };
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
    if !failures.is_empty() {
        for f in &failures {
            eprintln!("error: {f}");
        }
        bail!(
            "{} of {} file(s) could not be read (the others are in the table)",
            failures.len(),
            files.len()
        );
    }
    Ok(())
}

/// The records of a folder batch as one aligned table: a row per file, a column per
/// parameter (unit in the header), shape as rows x cols, pitch to 4 significant digits.
fn render_table(records: &[ParamsRecord]) -> String {
    let mut head = vec![
        "file".to_string(),
        "rows x cols".into(),
        "pitch [um]".into(),
        "surface".into(),
    ];
    if let Some(r) = records.first() {
        head.extend(r.values.iter().map(|v| {
            if v.unit.is_empty() {
                v.name.to_string()
            } else {
                format!("{} [{}]", v.name, v.unit)
            }
        }));
    }
    let mut rows = vec![head];
    for r in records {
        let pitch = pitch_text(r.pitch_x_um, r.pitch_y_um);
        let mut row = vec![
            r.file.clone(),
            format!("{} x {}", r.rows, r.cols),
            format!(
                "{}{}",
                pitch.trim_end_matches(" um").trim_end_matches(" um (x, y)"),
                if r.pitch_assumed { " (assumed)" } else { "" }
            ),
            if r.levelled {
                "levelled"
            } else {
                "mean removed"
            }
            .into(),
        ];
        // In the header's unit (a column is one unit), 3 significant figures.
        row.extend(r.values.iter().map(|v| sig(v.value, units::HEIGHT_DIGITS)));
        rows.push(row);
    }
    let ncol = rows.iter().map(Vec::len).max().unwrap_or(0);
    let width: Vec<usize> = (0..ncol)
        .map(|c| {
            rows.iter()
                .filter_map(|r| r.get(c))
                .map(|t| t.chars().count())
                .max()
                .unwrap_or(0)
        })
        .collect();
    let mut out = String::new();
    for r in &rows {
        let cells: Vec<String> = r
            .iter()
            .enumerate()
            .map(|(c, t)| {
                if c == 0 {
                    format!("{t:<w$}", w = width[c])
                } else {
                    format!("{t:>w$}", w = width[c])
                }
            })
            .collect();
        out.push_str(cells.join("  ").trim_end());
        out.push('\n');
    }
    for r in records {
        for n in &r.notes {
            out.push_str(&format!("note: {}: {n}\n", r.file));
        }
    }
    out
}

/// Reads one input and writes one output; the line `convert` prints for it.
fn convert_one(
    input: &Path,
    output: &Path,
    pitch_um: Option<f64>,
    mask: &super::MaskArgs,
) -> Result<String> {
    let loaded = load_surface(input, pitch_um, "convert", false)?;
    let mut s = loaded.surface;
    mask.apply(input, &mut s)?;
    let ext = output
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .unwrap_or_default();
    if loaded.pitch_assumed && WRITABLE_WITH_PITCH.contains(&ext.as_str()) {
        bail!(
            "{}: the file carries no pitch, and a .{ext} stores one: give --pitch-um (or write .npy, \
             which keeps no pitch until one is known)",
            input.display()
        );
    }
    if pitch_um.is_some() {
        // The pitch given is now the surface's own: written into the output (x3p, the npy
        // sidecar, ...).
        s.metadata.pitch_known = true;
    }
    write_surface(output, &s)?;
    let sidecar = if ext == "npy" && s.metadata.pitch_known {
        format!(
            " + {}",
            surfstream_io::sidecar::sidecar_path(output)
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default()
        )
    } else {
        String::new()
    };
    Ok(format!(
        "{} -> {}{sidecar} ({} rows x {} cols, pitch {}{})",
        input.display(),
        output.display(),
        s.height,
        s.width,
        pitch_text(s.pitch_x_um, s.pitch_y_um),
        if s.metadata.pitch_known {
            ""
        } else {
            ", not known"
        }
    ))
}

pub fn convert(a: ConvertArgs) -> Result<()> {
    let Some(output) = a.out.or(a.output) else {
        bail!("convert: no output: write `convert IN -o OUT.x3p`");
    };
    eprintln!("{}", convert_one(&a.input, &output, a.pitch_um, &a.mask)?);
    Ok(())
}

/// `convert DIR -o OUTDIR --to EXT`: every readable file of DIR, one table row each; a file
/// that cannot be converted is named and the others go on (exit status 1 at the end).
pub fn convert_folder(a: ConvertArgs) -> Result<()> {
    let Some(out_dir) = a.out.clone().or(a.output.clone()) else {
        bail!("convert: no output folder: write `convert DIR -o OUTDIR --to x3p`");
    };
    let ext = a.to.trim_start_matches('.').to_ascii_lowercase();
    if !super::WRITABLE.contains(&ext.as_str()) {
        bail!(
            "--to {}: expected one of {}",
            a.to,
            super::WRITABLE.join(", ")
        );
    }
    if out_dir.is_file() {
        bail!(
            "{}: is a file; convert DIR writes into a folder (-o OUTDIR)",
            out_dir.display()
        );
    }
    let files = super::readable_files(&a.input)?;
    let mut rows = Vec::new();
    let mut failures = 0usize;
    for f in &files {
        let stem = f
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        let target = out_dir.join(format!("{stem}.{ext}"));
        match convert_one(f, &target, a.pitch_um, &a.mask) {
            Ok(_) => {
                let s = surfstream_io::formats::read_surface(&target);
                let (shape, pitch) = s.map_or(("?".into(), "?".into()), |s| {
                    (
                        format!("{} x {}", s.height, s.width),
                        pitch_text(s.pitch_x_um, s.pitch_y_um),
                    )
                });
                rows.push([
                    f.display().to_string(),
                    target.display().to_string(),
                    shape,
                    pitch,
                    "ok".into(),
                ]);
            }
            Err(e) => {
                failures += 1;
                rows.push([
                    f.display().to_string(),
                    "-".into(),
                    "-".into(),
                    "-".into(),
                    format!("error: {e:#}"),
                ]);
            }
        }
    }
    let head = ["input", "output", "rows x cols", "pitch", "status"].map(String::from);
    let width: Vec<usize> = (0..5)
        .map(|c| {
            rows.iter()
                .chain([&head])
                .map(|r| r[c].chars().count())
                .max()
                .unwrap_or(0)
        })
        .collect();
    for r in [&head].into_iter().chain(rows.iter()) {
        let line: Vec<String> = (0..5)
            .map(|c| format!("{:<w$}", r[c], w = width[c]))
            .collect();
        println!("{}", line.join("  ").trim_end());
    }
    if failures > 0 {
        bail!(
            "{failures} of {} file(s) not converted (named in the table)",
            files.len()
        );
    }
    Ok(())
}

/// Two pitches further apart than this, relative, are not the same pitch for `compare`.
const COMPARE_PITCH_TOLERANCE: f64 = 1e-6;

/// SIM, SSIM and the RMS difference pair sample (i, j) of one map with sample (i, j) of the
/// other: the same place on the part only when both maps have the same pitch. Maps whose
/// pitches (x or y) differ by more than [`COMPARE_PITCH_TOLERANCE`] relative are refused,
/// naming both files and both pitches: surfstream has no resampling that would bring one map
/// onto the other's grid. A file without a pitch (a bare .npy) cannot be checked: said on
/// stderr when the other has one.
fn check_compare_pitch(pa: &Path, a: &Loaded, pb: &Path, b: &Loaded) -> Result<()> {
    let (x, y) = (&a.surface, &b.surface);
    match (a.pitch_assumed, b.pitch_assumed) {
        (true, true) => return Ok(()),
        (true, false) | (false, true) => {
            let bare = if a.pitch_assumed { pa } else { pb };
            eprintln!(
                "{}: note: the file carries no pitch; compare cannot check that both maps have \
                 the same one",
                bare.display()
            );
            return Ok(());
        }
        (false, false) => {}
    }
    // 9 significant digits: enough to show a 1e-6 difference, not the f32 storage's noise.
    let g = |v: f64| format!("{v:.8e}").parse::<f64>().unwrap_or(v);
    let differs = |p: f64, q: f64| (p - q).abs() > COMPARE_PITCH_TOLERANCE * p.abs().max(q.abs());
    if differs(x.pitch_x_um, y.pitch_x_um) || differs(x.pitch_y_um, y.pitch_y_um) {
        bail!(
            "{} has a pitch of {} x {} um (x, y) but {} has {} x {} um (x, y): compare pairs \
             the samples of both maps point by point, which is the same place only at the same \
             pitch (they differ by more than {COMPARE_PITCH_TOLERANCE:e} relative); surfstream \
             has no resampling to put one map on the other's grid: resample one of them to \
             the other's pitch first (e.g. in Gwyddion), or compare maps of one instrument setting",
            pa.display(),
            g(x.pitch_x_um),
            g(x.pitch_y_um),
            pb.display(),
            g(y.pitch_x_um),
            g(y.pitch_y_um)
        );
    }
    Ok(())
}

pub fn compare(a: CompareArgs) -> Result<()> {
    // SIM, SSIM and the RMS difference compare samples: both maps must share their pitch.
    let la = load_surface(&a.a, None, "compare", false)?;
    let lb = load_surface(&a.b, None, "compare", false)?;
    check_compare_pitch(&a.a, &la, &a.b, &lb)?;
    let (x, y) = (la.surface, lb.surface);
    if (x.height, x.width) != (y.height, y.width) {
        bail!(
            "{} is {} x {} px (rows x cols) but {} is {} x {} px: compare needs maps of the same shape",
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
        let v = record::to_value(&CompareJson {
            sim,
            ssim: ssim.mssim,
            ssim_windows: ssim.windows,
            ssim_range_um: ssim.range_um,
            rms_difference_um: rms,
            points_compared: n,
        })?;
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!("SIM   {sim:.6} (normalised cross-correlation, eq. 12)");
        println!(
            "SSIM  {:.6} ({} windows, L = {})",
            ssim.mssim,
            ssim.windows,
            units::height(ssim.range_um)
        );
        println!("RMS   {} over {n} points valid in both", units::height(rms));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn npy(dir: &Path, name: &str, rows: usize, cols: usize) -> PathBuf {
        let p = dir.join(name);
        let z: Vec<f64> = (0..rows * cols)
            .map(|i| ((i % cols) as f64 * 0.7).sin() * 3.0 + (i / cols) as f64 * 0.02)
            .collect();
        surfstream_io::npy::write_npy_f64(&p, &z, rows, cols).unwrap();
        p
    }

    fn gsf(dir: &Path, name: &str, pitch_x_um: f64, pitch_y_um: f64) -> PathBuf {
        let p = dir.join(name);
        // 12 x 12: SSIM's window is 11 x 11.
        let heights_um = (0..12 * 12).map(|i| ((i * 7) % 11) as f64 * 0.1).collect();
        let s = Surface {
            width: 12,
            height: 12,
            pitch_x_um,
            pitch_y_um,
            heights_um,
            metadata: Metadata {
                pitch_known: true,
                ..Metadata::default()
            },
        };
        write_surface(&p, &s).unwrap();
        p
    }

    fn compare_of(a: &Path, b: &Path) -> Result<()> {
        compare(CompareArgs {
            a: a.to_path_buf(),
            b: b.to_path_buf(),
            json: true,
        })
    }

    #[test]
    fn compare_refuses_maps_of_different_pitch() {
        let d = tempfile::tempdir().unwrap();
        // Issue 35: 295.5 um against 0.0196 um was compared without a word.
        let coarse = gsf(d.path(), "coarse.gsf", 295.5, 295.5);
        let fine = gsf(d.path(), "fine.gsf", 0.0196, 0.0196);
        let e = format!("{:#}", compare_of(&coarse, &fine).unwrap_err());
        assert!(
            e.contains("coarse.gsf has a pitch of 295.5 x 295.5 um (x, y)")
                && e.contains("fine.gsf has 0.0196 x 0.0196 um (x, y)")
                && e.contains("no resampling"),
            "{e}"
        );
        // Only y differs: refused too.
        let tall = gsf(d.path(), "tall.gsf", 295.5, 300.0);
        let e = format!("{:#}", compare_of(&coarse, &tall).unwrap_err());
        assert!(e.contains("tall.gsf has 295.5 x 300 um"), "{e}");
        // Within 1e-6 relative (f32 storage round-off): compared.
        let same = gsf(d.path(), "same.gsf", 295.5 * (1.0 + 2e-7), 295.5);
        compare_of(&coarse, &same).unwrap();
        // 1e-5 relative apart: refused.
        let near = gsf(d.path(), "near.gsf", 295.5 * (1.0 + 1e-5), 295.5);
        assert!(compare_of(&coarse, &near).is_err());
        // A file without a pitch cannot be checked: compared (and said on stderr).
        let bare = npy(d.path(), "bare.npy", 12, 12);
        compare_of(&coarse, &bare).unwrap();
        compare_of(&bare, &fine).unwrap();
    }

    #[test]
    fn convert_refuses_to_invent_a_pitch_and_carries_a_known_one() {
        let d = tempfile::tempdir().unwrap();
        let bare = npy(d.path(), "bare.npy", 6, 7);
        for ext in ["x3p", "gsf", "tif"] {
            let e = convert_one(
                &bare,
                &d.path().join(format!("o.{ext}")),
                None,
                &Default::default(),
            )
            .unwrap_err()
            .to_string();
            assert!(
                e.contains(&format!(
                    "the file carries no pitch, and a .{ext} stores one: give --pitch-um"
                )),
                "{e}"
            );
        }
        // With --pitch-um: the x3p says it; back to .npy, the sidecar keeps it.
        let x3p = d.path().join("o.x3p");
        let line = convert_one(&bare, &x3p, Some(0.75), &Default::default()).unwrap();
        assert!(
            line.contains("(6 rows x 7 cols, pitch 0.7500 um)"),
            "{line}"
        );
        let back = d.path().join("back.npy");
        let line = convert_one(&x3p, &back, None, &Default::default()).unwrap();
        assert!(line.contains("+ back.npy.json"), "{line}");
        let s = surfstream_io::formats::read_surface(&back).unwrap();
        assert!(s.metadata.pitch_known && (s.pitch_x_um - 0.75).abs() < 1e-12);
        // A pitchless .npy to .npy: no sidecar, no claim.
        let line =
            convert_one(&bare, &d.path().join("copy.npy"), None, &Default::default()).unwrap();
        assert!(line.ends_with("pitch 1.000 um, not known)"), "{line}");
        assert!(!d.path().join("copy.npy.json").exists());
    }

    fn args(files: Vec<PathBuf>) -> ParamsArgs {
        ParamsArgs {
            mask: Default::default(),
            files,
            all: true,
            level: false,
            json: false,
            csv: false,
            jsonl: false,
            out: None,
            pitch_um: Some(1.0),
            pruning_pct: 5.0,
        }
    }

    #[test]
    fn params_table_is_rows_x_cols_and_feature_nulls_say_why() {
        let d = tempfile::tempdir().unwrap();
        let a = args(vec![]);
        // A steep ramp: every motif drains to the low edge; nothing significant is left.
        let p = d.path().join("ramp.npy");
        let z: Vec<f64> = (0..20 * 30)
            .map(|i| (i % 30) as f64 * 10.0 + ((i * 7) % 5) as f64 * 0.01)
            .collect();
        surfstream_io::npy::write_npy_f64(&p, &z, 20, 30).unwrap();
        let r = params_of(&p, &a).unwrap();
        let spd = r.values.iter().find(|v| v.name == "Spd").unwrap().value;
        if spd == 0.0 || spd.is_nan() {
            assert!(!r.notes.is_empty());
            assert!(r.notes[0].contains("--level"), "{:?}", r.notes);
        }
        let t = render_table(&[r]);
        let mut lines = t.lines();
        let head = lines.next().unwrap();
        assert!(
            head.contains("rows x cols") && head.contains("Sa [um]"),
            "{head}"
        );
        let row = lines.next().unwrap();
        assert!(row.contains("20 x 30") && row.contains(" 1.000 "), "{row}");
    }

    #[test]
    fn feature_notes_name_the_reason() {
        let v = |name: &'static str, value: f64| ParamValue {
            name,
            value,
            unit: "um",
            family: "feature",
        };
        let values = [v("Spd", 0.0), v("S10z", f64::NAN), v("S5p", f64::NAN)];
        let n = feature_notes(&values, false, 5.0);
        assert_eq!(n.len(), 1);
        assert!(
            n[0].starts_with("Spd, S10z, S5p undefined") && n[0].contains("--level"),
            "{n:?}"
        );
        let n = feature_notes(&values, true, 5.0);
        assert!(!n[0].contains("--level"));
        assert!(feature_notes(&[v("Spd", 0.2)], false, 5.0).is_empty());
    }
}
