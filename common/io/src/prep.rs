//! Pre-processing of a height map, as every metrology tool offers it: form removal (`level`),
//! ISO 16610 filtering (`filter`), `crop`, `rotate`, `fill` of not-measured points,
//! `threshold` and `outliers`. Each [`Step`] takes a [`Surface`] and returns a new one with
//! its pitch, units (µm) and NaN mask (NaN = not measured) carried through, plus a line saying
//! what it did ([`Done`]); [`run`] chains them (the `surfstream prep` verb and the Python
//! methods call it, so the two agree by construction).
//!
//! [`Step::parse`] reads the one text form both use: `level plane`, `level poly=3`,
//! `level sphere`, `level cylinder=x`, `filter l=80um`, `filter robust,l=0.08mm,s=2.5um`,
//! `crop x=10:210,y=0:100` (pixels, half-open) or `crop x=5um:50um,y=...`, `rotate 90`,
//! `rotate 12.5`, `fill laplace`, `threshold 0.5` or `threshold 0.5,1`, `outliers 3` or
//! `outliers median,3`.

use anyhow::{bail, Context, Result};
use surfstream_core::filter;
use surfstream_core::raster::Shape;
use surfstream_core::Sampling;

use crate::formats::{from_frame_heights, to_frame_heights, Surface};

/// The form a `level` step removes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Form {
    /// Least-squares polynomial of total order n (1 = plane), `surfstream_core::filter::form`.
    Polynomial(usize),
    /// Least-squares sphere (algebraic fit), the cap nearest the data.
    Sphere,
    /// Least-squares cylinder whose axis runs along x (`true`) or y (`false`), algebraic fit.
    Cylinder { axis_x: bool },
}

/// How `outliers` judges a point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum OutlierRule {
    /// `|z - mean| > n Sq` (population standard deviation), one pass.
    Mean(f64),
    /// `|z - median| > n 1.4826 MAD` (the MAD scaled to a normal sigma), one pass.
    Median(f64),
}

/// A rectangle of pixels, half-open: columns `col0..col1`, rows `row0..row1`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CropPx {
    pub col0: usize,
    pub col1: usize,
    pub row0: usize,
    pub row1: usize,
}

/// One end of a crop range: pixels, or µm from pixel 0 (rounded to the nearest pixel).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Bound {
    Px(usize),
    Um(f64),
}

/// One pre-processing step.
#[derive(Debug, Clone, PartialEq)]
pub enum Step {
    Level(Form),
    /// ISO 16610-61 Gaussian (or -71 robust, zeroth order) filtering: the primary surface is
    /// the S-filter's mean for `lambda_s_um` (the map itself without it); with `lambda_c_um`
    /// the result is primary minus its L-filter mean (the S-L surface: long wavelengths out),
    /// without it the primary surface.
    Filter {
        robust: bool,
        lambda_s_um: Option<f64>,
        lambda_c_um: Option<f64>,
    },
    /// Columns `x` and rows `y` kept.
    Crop {
        x: (Bound, Bound),
        y: (Bound, Bound),
    },
    /// Counter-clockwise in the x-y plane (y up), degrees.
    Rotate(f64),
    /// Fill the points not measured: Laplace (harmonic) interpolation.
    FillLaplace,
    /// Drop the lowest `lower_pct` % and the highest `upper_pct` % of the measured points.
    Threshold {
        lower_pct: f64,
        upper_pct: f64,
    },
    Outliers(OutlierRule),
}

/// What a step did: one line for the user, and the counts a test or a report reads.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Done {
    pub step: String,
    pub summary: String,
    /// Measured points that became not measured (threshold, outliers, rotate's edges).
    pub points_removed: usize,
    /// Not-measured points that were given a value (fill).
    pub points_filled: usize,
}

/// A length: a number in µm, or with the unit um / µm / mm / nm.
pub fn length_um(what: &str, text: &str) -> Result<f64> {
    let t = text.trim().to_ascii_lowercase();
    let (number, scale) = if let Some(n) = t.strip_suffix("mm") {
        (n, 1000.0)
    } else if let Some(n) = t.strip_suffix("nm") {
        (n, 1e-3)
    } else if let Some(n) = t.strip_suffix("um").or_else(|| t.strip_suffix("µm")) {
        (n, 1.0)
    } else {
        (t.as_str(), 1.0)
    };
    match number.trim().parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v * scale),
        _ => bail!(
            "{what} {text:?}: expected a positive length in um, or with a unit (\"80um\", \"0.08mm\", \"500nm\")"
        ),
    }
}

fn number(what: &str, text: &str, expected: &str) -> Result<f64> {
    match text.trim().parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        _ => bail!("{what} {text:?}: expected {expected}"),
    }
}

fn bound(what: &str, text: &str) -> Result<Bound> {
    let t = text.trim();
    if t.ends_with("um") || t.ends_with("µm") || t.ends_with("mm") || t.ends_with("nm") {
        // 0 um is a valid start: length_um wants > 0.
        let zero = t.trim_end_matches(|c: char| c.is_alphabetic() || c == 'µ');
        if zero.trim().parse::<f64>() == Ok(0.0) {
            return Ok(Bound::Um(0.0));
        }
        return length_um(what, t).map(Bound::Um);
    }
    t.parse::<usize>().map(Bound::Px).with_context(|| {
        format!("{what} {text:?}: expected a pixel index (0, 1, ...) or a length with its unit (\"12.5um\")")
    })
}

fn range(what: &str, text: &str) -> Result<(Bound, Bound)> {
    let Some((a, b)) = text.split_once(':') else {
        bail!("{what} {text:?}: expected START:END (pixels, END not included; or lengths such as 5um:50um)");
    };
    Ok((bound(what, a)?, bound(what, b)?))
}

impl Step {
    /// The steps' one text form (module doc): `name` and its argument.
    pub fn parse(name: &str, arg: &str) -> Result<Step> {
        let arg = arg.trim();
        Ok(match name {
            "level" => Step::Level(match arg {
                "plane" | "" => Form::Polynomial(1),
                "sphere" => Form::Sphere,
                "cylinder=x" | "cylinder" => Form::Cylinder { axis_x: true },
                "cylinder=y" => Form::Cylinder { axis_x: false },
                a => match a
                    .strip_prefix("poly=")
                    .or_else(|| a.strip_prefix("polynomial="))
                {
                    Some(n) => match n.trim().parse::<usize>() {
                        Ok(n) if n <= filter::MAX_ORDER => Form::Polynomial(n),
                        _ => bail!(
                            "level {a:?}: expected a polynomial order from 0 to {}",
                            filter::MAX_ORDER
                        ),
                    },
                    None => bail!(
                        "level {a:?}: expected plane, poly=N (N = 0..{}), sphere, cylinder=x or cylinder=y",
                        filter::MAX_ORDER
                    ),
                },
            }),
            "filter" => {
                let (mut robust, mut ls, mut lc) = (false, None, None);
                for part in arg.split(',').map(str::trim).filter(|p| !p.is_empty()) {
                    match part.split_once('=') {
                        None if part == "gaussian" => robust = false,
                        None if part == "robust" => robust = true,
                        Some(("l", v)) | Some(("lc", v)) => lc = Some(length_um("filter l", v)?),
                        Some(("s", v)) | Some(("ls", v)) => ls = Some(length_um("filter s", v)?),
                        _ => bail!(
                            "filter {arg:?}: unknown part {part:?}; expected [gaussian|robust,]l=LENGTH[,s=LENGTH] (e.g. l=80um, s=2.5um)"
                        ),
                    }
                }
                if ls.is_none() && lc.is_none() {
                    bail!("filter {arg:?}: no cutoff; give l=LENGTH (L-filter, lambda_c) and/or s=LENGTH (S-filter, lambda_s)");
                }
                if let (Some(s), Some(l)) = (ls, lc) {
                    if l <= s {
                        bail!("filter {arg:?}: l ({l} um) must be longer than s ({s} um)");
                    }
                }
                if robust && lc.is_none() {
                    bail!("filter {arg:?}: the robust filter is an L-filter: give l=LENGTH");
                }
                Step::Filter {
                    robust,
                    lambda_s_um: ls,
                    lambda_c_um: lc,
                }
            }
            "crop" => {
                let (mut x, mut y) = (None, None);
                for part in arg.split(',').map(str::trim) {
                    match part.split_once('=') {
                        Some(("x", r)) => x = Some(range("crop x", r)?),
                        Some(("y", r)) => y = Some(range("crop y", r)?),
                        _ => bail!("crop {arg:?}: expected x=START:END,y=START:END (pixels, END not included, or lengths such as 5um:50um)"),
                    }
                }
                let all = (Bound::Px(0), Bound::Px(usize::MAX));
                Step::Crop {
                    x: x.unwrap_or(all),
                    y: y.unwrap_or(all),
                }
            }
            "rotate" => Step::Rotate(number(
                "rotate",
                arg.trim_end_matches("deg"),
                "an angle in degrees, counter-clockwise (90, 180, 270, or any angle: bilinear)",
            )?),
            "fill" => match arg {
                "laplace" | "" => Step::FillLaplace,
                a => bail!("fill {a:?}: expected laplace (harmonic interpolation of the points not measured)"),
            },
            "threshold" => {
                let (lo, hi) = arg.split_once(',').unwrap_or((arg, arg));
                let pct = |t: &str| -> Result<f64> {
                    let v = number("threshold", t.trim_end_matches('%'), "a percentage from 0 to 50 (e.g. 0.5, or 0.5,1 for lower,upper)")?;
                    if !(0.0..50.0).contains(&v) {
                        bail!("threshold {t:?}: expected a percentage from 0 to 50");
                    }
                    Ok(v)
                };
                Step::Threshold {
                    lower_pct: pct(lo)?,
                    upper_pct: pct(hi)?,
                }
            }
            "outliers" => {
                let (rule, n) = match arg.split_once(',') {
                    Some((r, n)) => (r.trim(), n),
                    None => ("mean", if arg.is_empty() { "3" } else { arg }),
                };
                let n = number("outliers", n, "a positive number of standard deviations (e.g. 3)")?;
                if n <= 0.0 {
                    bail!("outliers {arg:?}: expected a positive number of standard deviations");
                }
                Step::Outliers(match rule {
                    "mean" => OutlierRule::Mean(n),
                    "median" => OutlierRule::Median(n),
                    r => bail!("outliers {r:?}: expected mean or median, then the number of standard deviations (median,3)"),
                })
            }
            other => bail!(
                "unknown step {other:?}: the steps are level, filter, crop, rotate, fill, threshold, outliers"
            ),
        })
    }

    /// Runs this step on `s`.
    pub fn apply(&self, s: &Surface) -> Result<(Surface, Done)> {
        if s.width == 0 || s.height == 0 {
            bail!("empty height map ({} x {}, rows x cols)", s.height, s.width);
        }
        match self {
            Step::Level(form) => level(s, *form),
            Step::Filter {
                robust,
                lambda_s_um,
                lambda_c_um,
            } => filtered(s, *robust, *lambda_s_um, *lambda_c_um),
            Step::Crop { x, y } => crop(s, *x, *y),
            Step::Rotate(deg) => rotate(s, *deg),
            Step::FillLaplace => fill_laplace(s),
            Step::Threshold {
                lower_pct,
                upper_pct,
            } => threshold(s, *lower_pct, *upper_pct),
            Step::Outliers(rule) => outliers(s, *rule),
        }
    }
}

/// Runs `steps` in order; each result is the next step's input.
pub fn run(s: &Surface, steps: &[Step]) -> Result<(Surface, Vec<Done>)> {
    let mut cur = s.clone();
    let mut done = Vec::with_capacity(steps.len());
    for (i, step) in steps.iter().enumerate() {
        let (next, d) = step
            .apply(&cur)
            .with_context(|| format!("step {} ({})", i + 1, step_name(step)))?;
        cur = next;
        done.push(d);
    }
    if !done.is_empty() {
        let text = done
            .iter()
            .map(|d| d.step.as_str())
            .collect::<Vec<_>>()
            .join("; ");
        cur.metadata.extra.insert("prep".into(), text);
    }
    Ok((cur, done))
}

fn step_name(step: &Step) -> &'static str {
    match step {
        Step::Level(_) => "level",
        Step::Filter { .. } => "filter",
        Step::Crop { .. } => "crop",
        Step::Rotate(_) => "rotate",
        Step::FillLaplace => "fill",
        Step::Threshold { .. } => "threshold",
        Step::Outliers(_) => "outliers",
    }
}

fn with_heights(s: &Surface, heights_um: Vec<f64>) -> Surface {
    Surface {
        heights_um,
        ..s.clone()
    }
}

fn sampling(s: &Surface) -> Result<Sampling> {
    Sampling::new(Shape::new(s.height, s.width), s.pitch_x_um, s.pitch_y_um)
        .map_err(|e| anyhow::anyhow!("{e}"))
}

fn measured(s: &Surface) -> impl Iterator<Item = (usize, f64)> + '_ {
    s.heights_um
        .iter()
        .copied()
        .enumerate()
        .filter(|(_, z)| z.is_finite())
}

/// Solves the small dense system `a x = b` (n <= 5) by Gaussian elimination with partial
/// pivoting; None when it is singular.
fn solve(mut a: Vec<Vec<f64>>, mut b: Vec<f64>) -> Option<Vec<f64>> {
    let n = b.len();
    let scale = a
        .iter()
        .flatten()
        .fold(0.0f64, |m, v| m.max(v.abs()))
        .max(f64::MIN_POSITIVE);
    for col in 0..n {
        let p = (col..n).max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))?;
        if a[p][col].abs() <= 1e-14 * scale {
            return None;
        }
        a.swap(col, p);
        b.swap(col, p);
        let pivot_row = a[col].clone();
        for r in col + 1..n {
            let f = a[r][col] / pivot_row[col];
            for (x, p) in a[r].iter_mut().zip(&pivot_row).skip(col) {
                *x -= f * p;
            }
            b[r] -= f * b[col];
        }
    }
    let mut x = vec![0.0; n];
    for r in (0..n).rev() {
        let s: f64 = (r + 1..n).map(|c| a[r][c] * x[c]).sum();
        x[r] = (b[r] - s) / a[r][r];
    }
    Some(x)
}

/// Least squares of `sum (f(p) . coef - g(p))^2` over the points: the normal equations.
fn least_squares(points: impl Iterator<Item = (Vec<f64>, f64)>, n: usize) -> Option<Vec<f64>> {
    let mut a = vec![vec![0.0; n]; n];
    let mut b = vec![0.0; n];
    for (f, g) in points {
        for i in 0..n {
            for j in 0..n {
                a[i][j] += f[i] * f[j];
            }
            b[i] += f[i] * g;
        }
    }
    solve(a, b)
}

fn level(s: &Surface, form: Form) -> Result<(Surface, Done)> {
    let valid = measured(s).count();
    match form {
        Form::Polynomial(order) => {
            // The filters run in f32 about the mean, as frames carry heights; the residual
            // is taken in f64 against the form.
            let grid = sampling(s)?;
            let (offset, h32) = to_frame_heights(&s.heights_um);
            let f =
                filter::fit_polynomial(&h32, grid, order).map_err(|e| anyhow::anyhow!("{e}"))?;
            let shape = f.evaluate(grid);
            let out: Vec<f64> = s
                .heights_um
                .iter()
                .zip(&shape)
                .map(|(&z, &f)| z - offset - f)
                .collect();
            let name = if order == 1 {
                "level plane".to_string()
            } else {
                format!("level poly={order}")
            };
            Ok((
                with_heights(s, out),
                Done {
                    summary: format!(
                        "{name}: least-squares polynomial of order {order} removed over {valid} measured points, residual RMS {} um",
                        sig(f.residual_rms_um)
                    ),
                    step: name,
                    points_removed: 0,
                    points_filled: 0,
                },
            ))
        }
        Form::Sphere | Form::Cylinder { .. } => level_quadric(s, form, valid),
    }
}

/// Sphere: `x^2 + y^2 + z^2 + D x + E y + F z + G = 0`; cylinder (axis x):
/// `y^2 + z^2 + E y + F z + G = 0` (axis y: x instead of y); algebraic least squares (Kasa),
/// coordinates about the map's centre and mean height. The residual is the height minus the
/// surface's cap on the side of the data.
fn level_quadric(s: &Surface, form: Form, valid: usize) -> Result<(Surface, Done)> {
    if valid < 5 {
        bail!("{valid} measured points: a sphere or cylinder fit needs at least 5");
    }
    let mean = measured(s).map(|(_, z)| z).sum::<f64>() / valid as f64;
    let (cx, cy) = (
        (s.width as f64 - 1.0) / 2.0 * s.pitch_x_um,
        (s.height as f64 - 1.0) / 2.0 * s.pitch_y_um,
    );
    let xy = |i: usize| {
        (
            (i % s.width) as f64 * s.pitch_x_um - cx,
            (i / s.width) as f64 * s.pitch_y_um - cy,
        )
    };
    // (lateral coordinates used, each point's lateral squared distance term).
    let (name, coef) = match form {
        Form::Sphere => (
            "level sphere",
            least_squares(
                measured(s).map(|(i, z)| {
                    let (x, y) = xy(i);
                    let z = z - mean;
                    (vec![x, y, z, 1.0], -(x * x + y * y + z * z))
                }),
                4,
            )
            .map(|c| (c[0], c[1], c[2], c[3])),
        ),
        Form::Cylinder { axis_x } => (
            if axis_x {
                "level cylinder=x"
            } else {
                "level cylinder=y"
            },
            least_squares(
                measured(s).map(|(i, z)| {
                    let (x, y) = xy(i);
                    let t = if axis_x { y } else { x };
                    let z = z - mean;
                    (vec![t, z, 1.0], -(t * t + z * z))
                }),
                3,
            )
            .map(|c| {
                if axis_x {
                    (0.0, c[0], c[1], c[2])
                } else {
                    (c[0], 0.0, c[1], c[2])
                }
            }),
        ),
        Form::Polynomial(_) => unreachable!("polynomial forms are fitted by level()"),
    };
    let Some((d, e, f, g)) = coef else {
        bail!("{name}: the fit is singular (the measured points lie on a plane or a line: use level plane)");
    };
    let (x0, y0, z0) = (-d / 2.0, -e / 2.0, -f / 2.0);
    let r2 = x0 * x0 + y0 * y0 + z0 * z0 - g;
    if !(r2.is_finite() && r2 > 0.0) {
        bail!("{name}: no real surface fits the measured points (radius^2 = {r2:e} um^2)");
    }
    let radius = r2.sqrt();
    // The cap on the data's side of the centre: the data's mean (0 here) lies above z0 when
    // z0 < 0 (a dome), below when z0 > 0 (a bowl).
    let sign = if z0 < 0.0 { 1.0 } else { -1.0 };
    let axis_x = matches!(form, Form::Cylinder { axis_x: true });
    let axis_y = matches!(form, Form::Cylinder { axis_x: false });
    let mut outside = 0usize;
    let out: Vec<f64> = s
        .heights_um
        .iter()
        .enumerate()
        .map(|(i, &z)| {
            let (x, y) = xy(i);
            let dx = if axis_x { 0.0 } else { x - x0 };
            let dy = if axis_y { 0.0 } else { y - y0 };
            let h2 = r2 - dx * dx - dy * dy;
            if h2 < 0.0 {
                outside += 1;
                return f64::NAN;
            }
            z - mean - (z0 + sign * h2.sqrt())
        })
        .collect();
    if outside > 0 {
        bail!(
            "{name}: the fitted surface (radius {} um) does not reach over {outside} points of the map: the data is not {}",
            sig(radius),
            if matches!(form, Form::Sphere) { "a spherical cap" } else { "a cylinder segment along that axis" }
        );
    }
    let rms = (out
        .iter()
        .filter(|z| z.is_finite())
        .map(|z| z * z)
        .sum::<f64>()
        / valid as f64)
        .sqrt();
    Ok((
        with_heights(s, out),
        Done {
            summary: format!(
                "{name}: algebraic least-squares {} (radius {} um) removed over {valid} measured points, residual RMS {} um",
                if matches!(form, Form::Sphere) { "sphere" } else { "cylinder" },
                sig(radius),
                sig(rms)
            ),
            step: name.into(),
            points_removed: 0,
            points_filled: 0,
        },
    ))
}

fn filtered(
    s: &Surface,
    robust: bool,
    lambda_s_um: Option<f64>,
    lambda_c_um: Option<f64>,
) -> Result<(Surface, Done)> {
    let grid = sampling(s)?;
    let (offset, h32) = to_frame_heights(&s.heights_um);
    let err = |e: filter::FilterError| anyhow::anyhow!("{e}");
    let primary = match lambda_s_um {
        Some(ls) => filter::gaussian_filter(&h32, grid, ls).map_err(err)?,
        None => h32.clone(),
    };
    let (out, mut step) = match lambda_c_um {
        Some(lc) => {
            let mean = if robust {
                filter::robust_gaussian_filter(&primary, grid, &filter::RobustSettings::new(lc))
                    .map_err(err)?
                    .mean
            } else {
                filter::gaussian_filter(&primary, grid, lc).map_err(err)?
            };
            // S-L: the primary minus its L-filter mean; heights relative (the mean surface,
            // and with it the offset, is what the L-filter takes away).
            let out: Vec<f64> = primary
                .iter()
                .zip(&mean)
                .map(|(&p, &m)| f64::from(p) - f64::from(m))
                .collect();
            let kind = if robust { "robust" } else { "gaussian" };
            (out, format!("filter {kind},l={}um", sig(lc)))
        }
        None => (
            from_frame_heights(offset, &primary),
            "filter gaussian".to_string(),
        ),
    };
    if let Some(ls) = lambda_s_um {
        step.push_str(&format!(",s={}um", sig(ls)));
    }
    let lost = out
        .iter()
        .zip(&s.heights_um)
        .filter(|(o, z)| !o.is_finite() && z.is_finite())
        .count();
    let what = match (lambda_s_um, lambda_c_um, robust) {
        (_, Some(_), false) => "ISO 16610-61 Gaussian S-L surface (primary minus its L-filter mean)",
        (_, Some(_), true) => "ISO 16610-71 robust Gaussian (zeroth order) S-L surface (primary minus its robust L-filter mean)",
        _ => "ISO 16610-61 Gaussian S-filter (primary surface)",
    };
    Ok((
        with_heights(s, out),
        Done {
            summary: format!(
                "{step}: {what}; {lost} measured points without enough support (< 5 % of the weights) became not measured"
            ),
            step,
            points_removed: lost,
            points_filled: 0,
        },
    ))
}

fn crop(s: &Surface, x: (Bound, Bound), y: (Bound, Bound)) -> Result<(Surface, Done)> {
    let px = |b: Bound, pitch: f64, n: usize| -> usize {
        match b {
            Bound::Px(p) => p.min(n),
            Bound::Um(u) => ((u / pitch).round() as usize).min(n),
        }
    };
    let r = CropPx {
        col0: px(x.0, s.pitch_x_um, s.width),
        col1: px(x.1, s.pitch_x_um, s.width),
        row0: px(y.0, s.pitch_y_um, s.height),
        row1: px(y.1, s.pitch_y_um, s.height),
    };
    if r.col0 >= r.col1 || r.row0 >= r.row1 {
        bail!(
            "crop: columns {}..{} and rows {}..{} of a {} x {} map (rows x cols) leave nothing: END must be beyond START",
            r.col0,
            r.col1,
            r.row0,
            r.row1,
            s.height,
            s.width
        );
    }
    let (w, h) = (r.col1 - r.col0, r.row1 - r.row0);
    let mut out = Vec::with_capacity(w * h);
    for row in r.row0..r.row1 {
        out.extend_from_slice(&s.heights_um[row * s.width + r.col0..row * s.width + r.col1]);
    }
    let origin = [r.col0 as f64 * s.pitch_x_um, r.row0 as f64 * s.pitch_y_um];
    let mut t = Surface {
        width: w,
        height: h,
        heights_um: out,
        ..s.clone()
    };
    if let Some(p) = &mut t.metadata.stage_position_um {
        p[0] += origin[0];
        p[1] += origin[1];
    }
    t.metadata.mask = None;
    t.metadata.extra.insert(
        "crop_origin_um".into(),
        format!("{},{}", origin[0], origin[1]),
    );
    let step = format!("crop x={}:{},y={}:{}", r.col0, r.col1, r.row0, r.row1);
    Ok((
        t,
        Done {
            summary: format!(
                "{step}: {h} x {w} (rows x cols) kept, pitch unchanged; pixel (0, 0) now at ({}, {}) um of the input's",
                sig(origin[0]),
                sig(origin[1])
            ),
            step,
            points_removed: 0,
            points_filled: 0,
        },
    ))
}

fn rotate(s: &Surface, deg: f64) -> Result<(Surface, Done)> {
    let quarter = deg / 90.0;
    let step = format!("rotate {}", sig(deg));
    if (quarter - quarter.round()).abs() < 1e-12 {
        let k = (quarter.round() as i64).rem_euclid(4);
        let (w, h) = (s.width, s.height);
        let mut t = s.clone();
        t.metadata.mask = None;
        // Pixel (0, 0) is another corner now: the file's stage position no longer applies.
        t.metadata.stage_position_um = None;
        t.heights_um = match k {
            0 => s.heights_um.clone(),
            // 90 CCW (y up): new (r', c') = old (r = h-1-c', c = r').
            1 => (0..w)
                .flat_map(|rn| (0..h).map(move |cn| s.heights_um[(h - 1 - cn) * w + rn]))
                .collect(),
            2 => s.heights_um.iter().rev().copied().collect(),
            // 270 CCW: new (r', c') = old (r = c', c = w-1-r').
            _ => (0..w)
                .flat_map(|rn| (0..h).map(move |cn| s.heights_um[cn * w + (w - 1 - rn)]))
                .collect(),
        };
        if k % 2 == 1 {
            t.width = h;
            t.height = w;
            t.pitch_x_um = s.pitch_y_um;
            t.pitch_y_um = s.pitch_x_um;
        }
        return Ok((
            t,
            Done {
                summary: format!(
                    "{step}: {} quarter turn(s) counter-clockwise (x towards y), exact (no interpolation); {} x {} (rows x cols)",
                    k, if k % 2 == 1 { w } else { h }, if k % 2 == 1 { h } else { w }
                ),
                step,
                points_removed: 0,
                points_filled: 0,
            },
        ));
    }
    if (s.pitch_x_um - s.pitch_y_um).abs() > 1e-9 * s.pitch_x_um {
        bail!(
            "rotate {deg}: an arbitrary angle needs a square pitch (this map: {} x {} um); rotate by 90-degree steps, or resample first",
            sig(s.pitch_x_um),
            sig(s.pitch_y_um)
        );
    }
    let (sin, cos) = deg.to_radians().sin_cos();
    let (w, h) = (s.width as f64, s.height as f64);
    // The output covers the rotated map's bounding box at the same pitch.
    let wn = ((w - 1.0) * cos.abs() + (h - 1.0) * sin.abs()).round() as usize + 1;
    let hn = ((w - 1.0) * sin.abs() + (h - 1.0) * cos.abs()).round() as usize + 1;
    let (cx, cy) = ((w - 1.0) / 2.0, (h - 1.0) / 2.0);
    let (cxn, cyn) = ((wn as f64 - 1.0) / 2.0, (hn as f64 - 1.0) / 2.0);
    let at = |c: usize, r: usize| s.heights_um[r * s.width + c];
    let mut out = Vec::with_capacity(wn * hn);
    for rn in 0..hn {
        for cn in 0..wn {
            let (u, v) = (cn as f64 - cxn, rn as f64 - cyn);
            // The source position: rotate back by -deg.
            let xs = cos * u + sin * v + cx;
            let ys = -sin * u + cos * v + cy;
            let (c0, r0) = (xs.floor(), ys.floor());
            let eps = 1e-9;
            if xs < -eps || ys < -eps || xs > w - 1.0 + eps || ys > h - 1.0 + eps {
                out.push(f64::NAN);
                continue;
            }
            let (c0, r0) = (
                (c0.max(0.0) as usize).min(s.width - 1),
                (r0.max(0.0) as usize).min(s.height - 1),
            );
            let (c1, r1) = ((c0 + 1).min(s.width - 1), (r0 + 1).min(s.height - 1));
            let (fx, fy) = (
                (xs - c0 as f64).clamp(0.0, 1.0),
                (ys - r0 as f64).clamp(0.0, 1.0),
            );
            let z = (1.0 - fy) * ((1.0 - fx) * at(c0, r0) + fx * at(c1, r0))
                + fy * ((1.0 - fx) * at(c0, r1) + fx * at(c1, r1));
            out.push(z);
        }
    }
    let mut t = Surface {
        width: wn,
        height: hn,
        heights_um: out,
        ..s.clone()
    };
    t.metadata.mask = None;
    t.metadata.stage_position_um = None;
    let outside = t.heights_um.iter().filter(|z| z.is_nan()).count();
    Ok((
        t,
        Done {
            summary: format!(
                "{step}: counter-clockwise (x towards y), bilinear interpolation of the 4 neighbours (not measured where any of them is); {hn} x {wn} (rows x cols) bounding box, {outside} points not measured (corners outside the input, and not-measured neighbours)"
            ),
            step,
            points_removed: 0,
            points_filled: 0,
        },
    ))
}

/// Largest number of relaxation sweeps of [`fill_laplace`].
pub const FILL_MAX_SWEEPS: usize = 20_000;

/// Laplace (harmonic) interpolation: every not-measured point becomes the mean of its 4
/// neighbours inside the map (measured points fixed; at the map's edge only the neighbours
/// that exist count, a zero-slope edge), solved by successive over-relaxation from an
/// onion-peel first guess, until no point moves more than 1e-10 of the height range.
fn fill_laplace(s: &Surface) -> Result<(Surface, Done)> {
    let (w, h) = (s.width, s.height);
    let holes: Vec<usize> = (0..w * h)
        .filter(|&i| !s.heights_um[i].is_finite())
        .collect();
    let valid = w * h - holes.len();
    if valid == 0 {
        bail!("fill: no measured point to interpolate from");
    }
    let mut z = s.heights_um.clone();
    let neighbours = |i: usize| {
        let (r, c) = (i / w, i % w);
        [
            (c > 0).then(|| i - 1),
            (c + 1 < w).then(|| i + 1),
            (r > 0).then(|| i - w),
            (r + 1 < h).then(|| i + w),
        ]
    };
    // Onion peel: each pass gives the holes next to known points the mean of those.
    let mut todo = holes.clone();
    while !todo.is_empty() {
        let known: Vec<(usize, f64)> = todo
            .iter()
            .filter_map(|&i| {
                let (sum, n) = neighbours(i)
                    .into_iter()
                    .flatten()
                    .filter(|&j| z[j].is_finite())
                    .fold((0.0, 0usize), |(s, n), j| (s + z[j], n + 1));
                (n > 0).then(|| (i, sum / n as f64))
            })
            .collect();
        for &(i, v) in &known {
            z[i] = v;
        }
        todo.retain(|&i| !z[i].is_finite());
    }
    let (lo, hi) = measured(s).fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), (_, v)| {
        (a.min(v), b.max(v))
    });
    let tol = 1e-10 * (hi - lo).max(1e-12);
    let omega = 1.9;
    let mut sweeps = 0usize;
    let mut converged = holes.is_empty();
    while !converged && sweeps < FILL_MAX_SWEEPS {
        sweeps += 1;
        let mut worst = 0.0f64;
        for &i in &holes {
            let (sum, n) = neighbours(i)
                .into_iter()
                .flatten()
                .fold((0.0, 0usize), |(s, n), j| (s + z[j], n + 1));
            let target = sum / n as f64;
            let delta = omega * (target - z[i]);
            z[i] += delta;
            worst = worst.max(delta.abs());
        }
        converged = worst <= tol;
    }
    let step = "fill laplace".to_string();
    let mut t = with_heights(s, z);
    t.metadata.mask = None;
    Ok((
        t,
        Done {
            summary: format!(
                "{step}: {} not-measured points given the Laplace (harmonic) interpolation of the measured ones (4 neighbours, zero slope at the map's edges; SOR, {sweeps} sweeps, {})",
                holes.len(),
                if converged {
                    "converged to 1e-10 of the height range".to_string()
                } else {
                    format!("stopped at {FILL_MAX_SWEEPS} sweeps before converging")
                }
            ),
            step,
            points_removed: 0,
            points_filled: holes.len(),
        },
    ))
}

fn threshold(s: &Surface, lower_pct: f64, upper_pct: f64) -> Result<(Surface, Done)> {
    let mut v: Vec<f64> = measured(s).map(|(_, z)| z).collect();
    if v.is_empty() {
        bail!("threshold: no measured point");
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    let n_lo = ((lower_pct / 100.0) * n as f64).floor() as usize;
    let n_hi = ((upper_pct / 100.0) * n as f64).floor() as usize;
    let (lo, hi) = (v[n_lo.min(n - 1)], v[(n - 1).saturating_sub(n_hi)]);
    let out: Vec<f64> = s
        .heights_um
        .iter()
        .map(|&z| if z < lo || z > hi { f64::NAN } else { z })
        .collect();
    let removed = out.iter().filter(|z| z.is_nan()).count() - (s.width * s.height - n);
    let step = format!("threshold {},{}", sig(lower_pct), sig(upper_pct));
    Ok((
        with_heights(s, out),
        Done {
            summary: format!(
                "{step}: the lowest {} % and highest {} % of the {n} measured points (material ratio, ISO 25178-3 style thresholding) kept between {} and {} um; {removed} points became not measured",
                sig(lower_pct),
                sig(upper_pct),
                sig(lo),
                sig(hi)
            ),
            step,
            points_removed: removed,
            points_filled: 0,
        },
    ))
}

fn outliers(s: &Surface, rule: OutlierRule) -> Result<(Surface, Done)> {
    let mut v: Vec<f64> = measured(s).map(|(_, z)| z).collect();
    if v.is_empty() {
        bail!("outliers: no measured point");
    }
    let n = v.len() as f64;
    let (centre, spread, how, k) = match rule {
        OutlierRule::Mean(k) => {
            let m = v.iter().sum::<f64>() / n;
            let sq = (v.iter().map(|z| (z - m) * (z - m)).sum::<f64>() / n).sqrt();
            (m, sq, "mean, Sq", k)
        }
        OutlierRule::Median(k) => {
            v.sort_by(f64::total_cmp);
            let med = median_sorted(&v);
            let mut dev: Vec<f64> = v.iter().map(|z| (z - med).abs()).collect();
            dev.sort_by(f64::total_cmp);
            (med, 1.4826 * median_sorted(&dev), "median, 1.4826 MAD", k)
        }
    };
    let limit = k * spread;
    let out: Vec<f64> = s
        .heights_um
        .iter()
        .map(|&z| {
            if (z - centre).abs() > limit {
                f64::NAN
            } else {
                z
            }
        })
        .collect();
    let removed = out.iter().filter(|z| z.is_nan()).count() - s.invalid_count();
    let step = match rule {
        OutlierRule::Mean(k) => format!("outliers {}", sig(k)),
        OutlierRule::Median(k) => format!("outliers median,{}", sig(k)),
    };
    Ok((
        with_heights(s, out),
        Done {
            summary: format!(
                "{step}: points farther than {} x the spread from the centre ({how}: {} um, {} um; one pass) became not measured: {removed}",
                sig(k),
                sig(centre),
                sig(spread)
            ),
            step,
            points_removed: removed,
            points_filled: 0,
        },
    ))
}

fn median_sorted(v: &[f64]) -> f64 {
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        (v[n / 2 - 1] + v[n / 2]) / 2.0
    }
}

/// `v` with 4 significant digits, as the step summaries print numbers.
pub fn sig(v: f64) -> String {
    if !v.is_finite() {
        return format!("{v}");
    }
    if v == 0.0 {
        return "0".into();
    }
    let e = v.abs().log10().floor() as i32;
    if (-4..6).contains(&e) {
        let decimals = (3 - e).max(0) as usize;
        let t = format!("{v:.decimals$}");
        if t.contains('.') {
            t.trim_end_matches('0').trim_end_matches('.').to_string()
        } else {
            t
        }
    } else {
        format!("{v:.3e}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::formats::Metadata;

    fn surface(rows: usize, cols: usize, f: impl Fn(f64, f64) -> f64, px: f64, py: f64) -> Surface {
        Surface {
            width: cols,
            height: rows,
            pitch_x_um: px,
            pitch_y_um: py,
            heights_um: (0..rows * cols)
                .map(|i| f((i % cols) as f64 * px, (i / cols) as f64 * py))
                .collect(),
            metadata: Metadata {
                format: "test".into(),
                pitch_known: true,
                ..Metadata::default()
            },
        }
    }

    fn p(name: &str, arg: &str) -> Step {
        Step::parse(name, arg).unwrap()
    }

    #[test]
    fn plane_and_polynomial_forms_come_out_exactly() {
        let s = surface(40, 50, |x, y| 3.0 + 0.01 * x - 0.02 * y, 0.5, 0.7);
        let (t, d) = p("level", "plane").apply(&s).unwrap();
        assert!(t.heights_um.iter().all(|z| z.abs() < 1e-5), "{}", d.summary);
        let s = surface(
            40,
            50,
            |x, y| 1e-3 * x * x + 2e-3 * x * y - 1e-3 * y * y,
            0.5,
            0.7,
        );
        let (t, _) = p("level", "poly=2").apply(&s).unwrap();
        assert!(t.heights_um.iter().all(|z| z.abs() < 1e-5));
        let (t, _) = p("level", "plane").apply(&s).unwrap();
        assert!(t.heights_um.iter().any(|z| z.abs() > 1e-2));
    }

    #[test]
    fn sphere_and_cylinder_forms_come_out() {
        let r = 500.0;
        let sph = |x: f64, y: f64| (r * r - (x - 30.0).powi(2) - (y - 20.0).powi(2)).sqrt() + 7.0;
        let s = surface(41, 61, sph, 1.0, 1.0);
        let (t, d) = p("level", "sphere").apply(&s).unwrap();
        assert!(t.heights_um.iter().all(|z| z.abs() < 1e-6), "{}", d.summary);
        assert!(d.summary.contains("radius 500 um"), "{}", d.summary);
        // A bowl (centre above) too.
        let s = surface(41, 61, |x, y| -sph(x, y), 1.0, 1.0);
        let (t, _) = p("level", "sphere").apply(&s).unwrap();
        assert!(t.heights_um.iter().all(|z| z.abs() < 1e-6));
        let cyl = |_x: f64, y: f64| (200.0f64 * 200.0 - (y - 10.0).powi(2)).sqrt();
        let s = surface(30, 40, cyl, 1.0, 1.0);
        let (t, _) = p("level", "cylinder=x").apply(&s).unwrap();
        assert!(t.heights_um.iter().all(|z| z.abs() < 1e-6));
        // A plane has no sphere: a clear error rather than a silent nonsense form.
        let flat = surface(10, 10, |x, _| x, 1.0, 1.0);
        assert!(p("level", "sphere").apply(&flat).is_err());
    }

    #[test]
    fn crop_keeps_pitch_and_moves_the_origin() {
        let mut s = surface(20, 30, |x, y| x + 100.0 * y, 0.5, 2.0);
        s.metadata.stage_position_um = Some([1000.0, 2000.0]);
        s.heights_um[5 * 30 + 7] = f64::NAN;
        let (t, d) = p("crop", "x=5:15,y=4:10").apply(&s).unwrap();
        assert_eq!((t.height, t.width), (6, 10), "{}", d.summary);
        assert_eq!((t.pitch_x_um, t.pitch_y_um), (0.5, 2.0));
        assert_eq!(t.heights_um[0], 5.0 * 0.5 + 100.0 * 4.0 * 2.0);
        assert!(t.heights_um[10 + 2].is_nan());
        assert_eq!(t.metadata.stage_position_um, Some([1002.5, 2008.0]));
        // In um, rounded to the pixel.
        let (t, _) = p("crop", "x=2.5um:7.5um").apply(&s).unwrap();
        assert_eq!((t.height, t.width), (20, 10));
        assert!(Step::parse("crop", "x=5").is_err());
        let e = p("crop", "x=20:10").apply(&s).unwrap_err().to_string();
        assert!(e.contains("leave nothing"), "{e}");
    }

    #[test]
    fn quarter_turns_are_exact_and_swap_the_pitch() {
        let mut s = surface(3, 4, |x, y| x + 10.0 * y, 1.0, 2.0);
        s.heights_um[1] = f64::NAN;
        let (t, _) = p("rotate", "90").apply(&s).unwrap();
        assert_eq!(
            (t.height, t.width, t.pitch_x_um, t.pitch_y_um),
            (4, 3, 2.0, 1.0)
        );
        // The old bottom-right corner (c = 3, r = 0) is the new top-right (r' = 3, c' = 2).
        assert_eq!(t.heights_um[3 * 3 + 2], s.heights_um[3]);
        let (back, _) = p("rotate", "-90").apply(&t).unwrap();
        assert_eq!(back.width, 4);
        for (a, b) in back.heights_um.iter().zip(&s.heights_um) {
            assert!(a == b || (a.is_nan() && b.is_nan()));
        }
        let (u, _) = p("rotate", "180").apply(&s).unwrap();
        assert_eq!(u.heights_um[0], s.heights_um[11]);
        // Arbitrary angles need a square pitch; bilinear keeps a plane a plane.
        assert!(p("rotate", "30").apply(&s).is_err());
        let s = surface(21, 31, |x, y| 0.3 * x - 0.1 * y, 1.0, 1.0);
        let (t, d) = p("rotate", "30").apply(&s).unwrap();
        assert!(t.width > 31 && t.height > 21, "{}", d.summary);
        // The centre keeps its height.
        let c = t.heights_um[(t.height / 2) * t.width + t.width / 2];
        assert!((c - (0.3 * 15.0 - 0.1 * 10.0)).abs() < 1e-9, "{c}");
    }

    #[test]
    fn fill_rebuilds_a_plane_and_leaves_measured_points_alone() {
        let mut s = surface(30, 40, |x, y| 2.0 + 0.5 * x - 0.25 * y, 1.0, 1.0);
        let truth = s.heights_um.clone();
        for r in 10..18 {
            for c in 12..25 {
                s.heights_um[r * 40 + c] = f64::NAN;
            }
        }
        let (t, d) = p("fill", "laplace").apply(&s).unwrap();
        assert_eq!(d.points_filled, 8 * 13, "{}", d.summary);
        for (a, b) in t.heights_um.iter().zip(&truth) {
            assert!((a - b).abs() < 1e-6, "{a} {b}");
        }
    }

    #[test]
    fn threshold_and_outliers_count_what_they_drop() {
        let mut s = surface(10, 10, |x, y| x + 10.0 * y, 1.0, 1.0);
        let (t, d) = p("threshold", "1,2").apply(&s).unwrap();
        assert_eq!(d.points_removed, 3);
        assert!(t.heights_um[0].is_nan() && t.heights_um[99].is_nan() && t.heights_um[98].is_nan());
        s.heights_um[50] = 1e4;
        let (t, d) = p("outliers", "3").apply(&s).unwrap();
        assert_eq!(d.points_removed, 1, "{}", d.summary);
        assert!(t.heights_um[50].is_nan());
        let (_, d) = p("outliers", "median,3").apply(&s).unwrap();
        assert_eq!(d.points_removed, 1, "{}", d.summary);
    }

    #[test]
    fn bad_steps_say_what_was_expected() {
        for (n, a, want) in [
            ("level", "cone", "expected plane, poly=N"),
            ("level", "poly=11", "order from 0 to 10"),
            ("filter", "l=-3um", "positive length"),
            ("filter", "l=2um,s=5um", "must be longer"),
            ("filter", "", "no cutoff"),
            ("rotate", "a lot", "angle in degrees"),
            ("fill", "kriging", "expected laplace"),
            ("threshold", "60", "0 to 50"),
            ("outliers", "-1", "positive"),
            ("smooth", "", "unknown step"),
        ] {
            let e = Step::parse(n, a).unwrap_err().to_string();
            assert!(e.contains(want), "{n} {a}: {e}");
        }
    }
}
