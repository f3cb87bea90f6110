//! ASCII XYZ: one point per line, `x y z` in micrometres (separated by spaces, tabs, commas or
//! semicolons, like the paper's Table 3). Lines starting with `#`, `%` or `//` and leading
//! non-numeric header lines are skipped; `nan` heights are invalid.
//!
//! The points must lie on a regular grid: the pitch along x (y) is the smallest spacing between
//! distinct x (y) values, refined over the whole span; every point must sit within 1 % of a
//! pitch of a grid node. Grid nodes with no point become NaN. Row index grows with y.

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
