//! ASCII XYZ: one point per line, `x y z` in micrometres (separated by spaces, tabs, commas or
//! semicolons, like the paper's Table 3). Lines starting with `#`, `%` or `//` and leading
//! non-numeric header lines are skipped; `nan` heights are invalid.
//!
//! The points must lie on a regular grid: the pitch along x (y) is the smallest spacing between
//! distinct x (y) values, refined over the whole span; every point must sit within 1 % of a
//! pitch of a grid node. Grid nodes with no point become NaN. Row index grows with y.
//! An `x y z` file carries no unit: x, y and z are taken as micrometres, with a warning.
//!
//! Gwyddion's text export ("ASCII data matrix", `File > Save As > .txt` with the
//! informational header) is a matrix, not points: `# Channel: NAME`, `# Width: 12.34 um`,
//! `# Height: 5.678 um`, `# Value units: m`, then one line per row of whitespace-separated
//! values in the value unit (decimal dot, or comma when exported with the locale's). It is
//! recognised by its `# Width:` / `# Height:` lines and read as a grid: pitch = width / cols,
//! height / rows; rows in file order (Gwyddion's first row is its y = 0). A matrix without that
//! header is refused (its pitch and unit would be guesses).

use anyhow::{bail, Context, Result};

use super::{Metadata, Surface};

/// A grid this many times larger than the number of points is a sparse cloud, not a map.
const MAX_FILL_FACTOR: usize = 64;
const GRID_TOLERANCE: f64 = 0.01;

struct Axis {
    origin: f64,
    pitch: f64,
    count: usize,
}

/// Detects the regular grid spanned by `values`.
fn axis(values: &[f64], name: &str) -> Result<Axis> {
    let mut v: Vec<f64> = values.to_vec();
    v.sort_by(f64::total_cmp);
    let (lo, hi) = (v[0], v[v.len() - 1]);
    let span = hi - lo;
    if span == 0.0 {
        return Ok(Axis {
            origin: lo,
            pitch: 1.0,
            count: 1,
        });
    }
    // Distinct values: gaps larger than a tiny fraction of the span (print rounding).
    let eps = span * 1e-9;
    let min_gap = v
        .windows(2)
        .map(|w| w[1] - w[0])
        .filter(|&d| d > eps)
        .fold(f64::INFINITY, f64::min);
    let steps = (span / min_gap).round();
    if !(1.0..=1e8).contains(&steps) {
        bail!("{name} values do not form a regular grid (span {span}, smallest spacing {min_gap})");
    }
    let pitch = span / steps;
    for &x in &v {
        let k = ((x - lo) / pitch).round();
        if ((x - lo) - k * pitch).abs() > GRID_TOLERANCE * pitch {
            bail!("{name} = {x} is not on the regular grid {lo} + k * {pitch} (within 1 % of a pitch)");
        }
    }
    Ok(Axis {
        origin: lo,
        pitch,
        count: steps as usize + 1,
    })
}

pub fn parse(data: &[u8]) -> Result<Surface> {
    let text = std::str::from_utf8(data).context("not UTF-8 text")?;
    if let Some(header) = GwyddionHeader::find(text)? {
        return parse_gwyddion_matrix(text, header);
    }
    let (mut xs, mut ys, mut zs) = (Vec::new(), Vec::new(), Vec::new());
    let mut seen_data = false;
    for (i, line) in text.lines().enumerate() {
        let l = line.trim();
        if l.is_empty() || l.starts_with('#') || l.starts_with('%') || l.starts_with("//") {
            continue;
        }
        let fields: Vec<&str> = l
            .split(|c: char| c.is_whitespace() || c == ',' || c == ';')
            .filter(|f| !f.is_empty())
            .collect();
        let parsed: Option<Vec<f64>> = fields.iter().map(|f| f.parse::<f64>().ok()).collect();
        match parsed {
            Some(p) if p.len() == 3 => {
                if !p[0].is_finite() || !p[1].is_finite() {
                    bail!(
                        "line {}: x and y must be finite numbers, found '{l}'",
                        i + 1
                    );
                }
                xs.push(p[0]);
                ys.push(p[1]);
                zs.push(if p[2].is_finite() { p[2] } else { f64::NAN });
                seen_data = true;
            }
            Some(p) if p.len() > 3 => bail!(
                "line {}: {} numbers: a matrix of heights, not 'x y z' points; its pitch and height \
                 unit are not in the file (export it from Gwyddion with the informational header: \
                 '# Width:', '# Height:', '# Value units:'; or save it as .gsf / .npy)",
                i + 1,
                p.len()
            ),
            _ if !seen_data => continue, // a header line
            _ => bail!(
                "line {}: expected three numbers 'x y z', found '{l}'",
                i + 1
            ),
        }
    }
    if xs.is_empty() {
        bail!("no 'x y z' lines found");
    }
    let ax = axis(&xs, "x")?;
    let ay = axis(&ys, "y")?;
    let cells = ax
        .count
        .checked_mul(ay.count)
        .filter(|&c| c <= xs.len().saturating_mul(MAX_FILL_FACTOR))
        .with_context(|| {
            format!(
                "the grid {} x {} is more than {MAX_FILL_FACTOR} times the {} points: a sparse point cloud, not a height map",
                ax.count,
                ay.count,
                xs.len()
            )
        })?;
    let mut heights_um = vec![f64::NAN; cells];
    let mut filled = vec![false; cells];
    for ((&x, &y), &z) in xs.iter().zip(&ys).zip(&zs) {
        let c = ((x - ax.origin) / ax.pitch).round() as usize;
        let r = ((y - ay.origin) / ay.pitch).round() as usize;
        let idx = r * ax.count + c;
        if filled[idx] {
            bail!("two points at grid node x = {x}, y = {y}");
        }
        filled[idx] = true;
        heights_um[idx] = z;
    }
    // A single row or column carries no pitch along its degenerate axis: use the other one.
    let (px, py) = match (ax.count, ay.count) {
        (1, 1) => (1.0, 1.0),
        (1, _) => (ay.pitch, ay.pitch),
        (_, 1) => (ax.pitch, ax.pitch),
        _ => (ax.pitch, ay.pitch),
    };
    let mut metadata = Metadata {
        format: "xyz".into(),
        pitch_known: ax.count > 1 || ay.count > 1,
        ..Metadata::default()
    };
    // A unit is never assumed silently (README: a warning whenever a unit is assumed).
    metadata
        .warnings
        .push("an 'x y z' file carries no unit: x, y and z taken as micrometres".into());
    metadata
        .extra
        .insert("origin_x_um".into(), ax.origin.to_string());
    metadata
        .extra
        .insert("origin_y_um".into(), ay.origin.to_string());
    Ok(Surface {
        width: ax.count,
        height: ay.count,
        pitch_x_um: px,
        pitch_y_um: py,
        heights_um,
        metadata,
    })
}

/// The informational header of Gwyddion's text export.
struct GwyddionHeader {
    channel: Option<String>,
    width_um: f64,
    height_um: f64,
    value_um: f64,
    value_unit: String,
}

impl GwyddionHeader {
    /// The header when the file's leading `#` lines have Gwyddion's `# Width:` and
    /// `# Height:`; None when they do not (an `x y z` file).
    fn find(text: &str) -> Result<Option<GwyddionHeader>> {
        let mut fields = std::collections::BTreeMap::new();
        for line in text.lines() {
            let l = line.trim();
            if l.is_empty() {
                continue;
            }
            let Some(comment) = l.strip_prefix('#') else {
                break;
            };
            if let Some((k, v)) = comment.split_once(':') {
                fields.insert(k.trim().to_ascii_lowercase(), v.trim().to_string());
            }
        }
        let (Some(w), Some(h)) = (fields.get("width"), fields.get("height")) else {
            return Ok(None);
        };
        let length = |name: &str, v: &str| -> Result<f64> {
            let v = v.replace(',', ".");
            let (num, unit) = v
                .split_once(char::is_whitespace)
                .map_or((v.as_str(), ""), |(n, u)| (n, u.trim()));
            let n: f64 = num.parse().ok().filter(|n: &f64| n.is_finite() && *n > 0.0).with_context(|| {
                format!("Gwyddion text header '# {name}: {v}': expected a positive length with a unit")
            })?;
            let scale = super::bytes::length_unit_um(unit).with_context(|| {
                format!("Gwyddion text header '# {name}: {v}': unit '{unit}' is not a length unit (m, mm, um, nm, ...)")
            })?;
            Ok(n * scale)
        };
        let width_um = length("Width", w)?;
        let height_um = length("Height", h)?;
        let value_unit = fields.get("value units").cloned().context(
            "Gwyddion text header: '# Width:' and '# Height:' but no '# Value units:' line: the height unit is unknown",
        )?;
        let value_um = super::bytes::length_unit_um(&value_unit).with_context(|| {
            format!("Gwyddion text header '# Value units: {value_unit}': expected a length unit (m, mm, um, nm, ...): not a height map")
        })?;
        Ok(Some(GwyddionHeader {
            channel: fields.get("channel").cloned(),
            width_um,
            height_um,
            value_um,
            value_unit,
        }))
    }
}

/// Gwyddion's text export: a matrix of heights under its header.
fn parse_gwyddion_matrix(text: &str, h: GwyddionHeader) -> Result<Surface> {
    let mut heights_um = Vec::new();
    let mut cols = 0usize;
    let mut rows = 0usize;
    for (i, line) in text.lines().enumerate() {
        let l = line.trim();
        if l.is_empty() || l.starts_with('#') {
            continue;
        }
        let before = heights_um.len();
        for f in l.split_whitespace() {
            // A locale's decimal comma ("1,25e-06"): Gwyddion separates values by whitespace.
            let v: f64 = f.replace(',', ".").parse().with_context(|| {
                format!(
                    "line {}: '{f}' is not a number (Gwyddion text matrix)",
                    i + 1
                )
            })?;
            heights_um.push(if v.is_finite() {
                v * h.value_um
            } else {
                f64::NAN
            });
        }
        let n = heights_um.len() - before;
        if rows == 0 {
            cols = n;
        } else if n != cols {
            bail!(
                "line {}: {n} values, but the matrix's first row has {cols}: every row of a Gwyddion text matrix has one length",
                i + 1
            );
        }
        rows += 1;
    }
    if rows == 0 || cols == 0 {
        bail!("Gwyddion text header but no matrix of values under it");
    }
    let mut metadata = Metadata {
        format: "gwyddion-text".into(),
        pitch_known: true,
        ..Metadata::default()
    };
    if let Some(c) = h.channel {
        metadata.extra.insert("channel".into(), c);
    }
    metadata.extra.insert("value_unit".into(), h.value_unit);
    Ok(Surface {
        width: cols,
        height: rows,
        pitch_x_um: h.width_um / cols as f64,
        pitch_y_um: h.height_um / rows as f64,
        heights_um,
        metadata,
    })
}
