//! `surfstream prep IN OUT --level plane --filter l=80um ...`: the pre-processing steps of
//! surfstream_io::prep, in the order given, from one height-map file to another. A thin shell:
//! parsing and the steps are the library's (Python's methods call the same).

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use clap::Args;
use surfstream_io::formats::write_surface;
use surfstream_io::prep::{self, Step};

use super::{file_help, load_surface, pitch_text, WRITABLE, WRITABLE_WITH_PITCH};

/// The steps' help, shared by `--help` and the errors.
pub const STEPS_HELP: &str = "\
Steps, run in the order given (each keeps pitch, um and the not-measured points unless it says):
  --level plane | poly=N | sphere | cylinder=x | cylinder=y
        least-squares form removed (polynomial of total order N = 0..10; sphere and cylinder
        by algebraic least squares, the cylinder's axis along x or y)
  --filter [gaussian|robust,]l=LENGTH[,s=LENGTH]
        ISO 16610-61 Gaussian (robust: ISO 16610-71, zeroth order): with l (lambda_c) the S-L
        surface, primary minus its L-filter mean; s (lambda_s) alone: the primary surface.
        LENGTH in um, or with its unit: 80um, 0.08mm, 500nm
  --crop x=START:END,y=START:END
        pixels (END not included) or lengths (x=5um:50um); pitch kept, the origin moves
  --rotate DEG
        counter-clockwise (x towards y); 90-degree steps exact, other angles bilinear
        (square pitch only), the bounding box kept, corners not measured
  --fill laplace
        the not-measured points get the Laplace (harmonic) interpolation of the measured ones
  --threshold LOWER[,UPPER]
        drops the lowest LOWER % and the highest UPPER % of the measured points (material
        ratio), counted
  --outliers [mean|median,]N
        drops points farther than N standard deviations from the mean (Sq) or the median
        (1.4826 MAD), one pass, counted";

#[derive(Args)]
#[command(after_help = STEPS_HELP)]
pub struct PrepArgs {
    #[arg(help = file_help())]
    pub input: PathBuf,
    /// Output file: .x3p, .npy (+ its pitch sidecar), .gsf or .tif (by extension).
    pub output: PathBuf,
    /// Pitch in um for inputs that carry none (a .npy without its sidecar); refused when it
    /// disagrees with the input's own. Must come before the steps.
    #[arg(long)]
    pub pitch_um: Option<f64>,
    /// Print what each step did as JSON instead of text. Must come before the steps.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub mask: super::MaskArgs,
    /// The steps (see below), e.g. --level plane --filter l=80um.
    #[arg(
        trailing_var_arg = true,
        allow_hyphen_values = true,
        value_name = "--STEP ARG",
        required = true
    )]
    pub steps: Vec<String>,
}

/// `--level plane --fill --filter=l=8um` as steps: every `--NAME` takes the next word as its
/// argument unless that is another `--NAME` (or `--NAME=ARG`).
pub fn parse_steps(words: &[String]) -> Result<Vec<Step>> {
    let mut steps = Vec::new();
    let mut k = 0;
    while k < words.len() {
        let w = &words[k];
        let Some(flag) = w.strip_prefix("--") else {
            bail!("prep: {w:?} is not a step: steps are --NAME ARG (e.g. --level plane)\n\n{STEPS_HELP}");
        };
        let (name, arg) = match flag.split_once('=') {
            Some((n, a)) => (n, a.to_string()),
            None => match words.get(k + 1).filter(|n| !n.starts_with("--")) {
                Some(a) => {
                    k += 1;
                    (flag, a.clone())
                }
                None => (flag, String::new()),
            },
        };
        steps.push(Step::parse(name, &arg).with_context(|| format!("prep --{name}"))?);
        k += 1;
    }
    Ok(steps)
}

/// `prep --json`: what was read and written, and the steps done.
#[derive(serde::Serialize)]
struct PrepJson<'a> {
    input: String,
    output: String,
    rows: usize,
    cols: usize,
    pitch_x_um: f64,
    pitch_y_um: f64,
    invalid_points: usize,
    steps: &'a [prep::Done],
}

pub fn run(a: PrepArgs) -> Result<()> {
    let steps = parse_steps(&a.steps)?;
    let ext = a
        .output
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .unwrap_or_default();
    if !WRITABLE.contains(&ext.as_str()) {
        bail!(
            "{}: prep writes {}",
            a.output.display(),
            WRITABLE
                .iter()
                .map(|e| format!(".{e}"))
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    let loaded = load_surface(&a.input, a.pitch_um, "prep", true)?;
    if loaded.pitch_assumed && WRITABLE_WITH_PITCH.contains(&ext.as_str()) {
        bail!(
            "{}: the file carries no pitch, and a .{ext} stores one: give --pitch-um (before the steps)",
            a.input.display()
        );
    }
    let mut s = loaded.surface;
    if a.pitch_um.is_some() {
        s.metadata.pitch_known = true;
    }
    a.mask.apply(&a.input, &mut s)?;
    let (out, done) = prep::run(&s, &steps).with_context(|| format!("{}", a.input.display()))?;
    write_surface(&a.output, &out)?;
    if a.json {
        // Through a JSON value: its keys sorted, as the output has always had them.
        let v = serde_json::to_value(PrepJson {
            input: a.input.display().to_string(),
            output: a.output.display().to_string(),
            rows: out.height,
            cols: out.width,
            pitch_x_um: out.pitch_x_um,
            pitch_y_um: out.pitch_y_um,
            invalid_points: out.invalid_count(),
            steps: &done,
        })?;
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        for d in &done {
            println!("{}", d.summary);
        }
        println!(
            "{} -> {}: {} rows x {} cols, pitch {}, {} not measured",
            a.input.display(),
            a.output.display(),
            out.height,
            out.width,
            pitch_text(out.pitch_x_um, out.pitch_y_um),
            out.invalid_count()
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn words(s: &str) -> Vec<String> {
        s.split_whitespace().map(String::from).collect()
    }

    #[test]
    fn steps_read_in_order_with_or_without_arguments() {
        let s = parse_steps(&words(
            "--level plane --fill --filter=robust,l=0.08mm --crop x=0:10 --rotate 90",
        ))
        .unwrap();
        assert_eq!(s.len(), 5);
        assert_eq!(s[0], Step::parse("level", "plane").unwrap());
        assert_eq!(s[1], Step::FillLaplace);
        assert_eq!(
            s[2],
            Step::Filter {
                robust: true,
                lambda_s_um: None,
                lambda_c_um: Some(80.0)
            }
        );
        assert_eq!(s[4], Step::Rotate(90.0));
        let e = format!("{:#}", parse_steps(&words("plane")).unwrap_err());
        assert!(
            e.contains("is not a step") && e.contains("--level plane"),
            "{e}"
        );
        let e = format!("{:#}", parse_steps(&words("--level cone")).unwrap_err());
        assert!(
            e.contains("prep --level") && e.contains("expected plane"),
            "{e}"
        );
    }
}
