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
//! height / rows; rows in file order (Gwyddion's first row is its y = 0). Gwyddion translates
//! these keys with the interface (`# Breite:`, `# Höhe:` in German, `# Largeur :` in French...):
//! every translation in Gwyddion's `po/` is read (see [`WIDTH_KEYS`]). A matrix whose header
//! gives a pixel size instead (`pixel size=3.69862e-007 m`, or `pixel size x=` / `y=`, with or
//! without `#`) is read with that pitch; without `# Value units:` its heights are taken as
//! metres, with a warning. A header that is Gwyddion's (a channel or value-unit key, or
//! two `# key: <length>` lines) but gives no pitch read here is refused naming its
//! lines, never read as `x y z`. A matrix without such a header is refused (its pitch and unit
//! would be guesses). Gwyddion's XYZ export (`# Lateral units:`, three columns) is `x y z`.

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
                 unit are not in the file (read are {PITCH_FORMS}; export it from Gwyddion with \
                 the informational header, or save it as .gsf / .npy)",
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

/// Gwyddion's header keys as its text export writes them: the English msgid and every
/// translation in Gwyddion's `po/*.po` (cs, de, es, fr, it, ko, ru; `de` and `es` leave
/// "Value units:" untranslated), lower case, without the colon.
const CHANNEL_KEYS: &[&str] = &[
    "channel",
    "kanal",
    "canal",
    "canale",
    "kanál",
    "канал",
    "채널",
];
const WIDTH_KEYS: &[&str] = &[
    "width",
    "breite",
    "largeur",
    "anchura",
    "larghezza",
    "šířka",
    "ширина",
    "폭",
];
const HEIGHT_KEYS: &[&str] = &[
    "height",
    "höhe",
    "hauteur",
    "altura",
    "altezza",
    "výška",
    "высота",
    "높이",
];
const VALUE_UNIT_KEYS: &[&str] = &[
    "value units",
    "unités",
    "unità valore",
    "jednotky hodnot",
    "единицы измерения",
    "값 단위",
];
/// Gwyddion's XYZ export ("# Lateral units:"): points, not a matrix; read as `x y z`.
const LATERAL_UNIT_KEYS: &[&str] = &[
    "lateral units",
    "laterale einheiten",
    "_laterale einheiten",
    "unités latérales",
    "unità laterali",
    "jednotky rozměrů",
    "единицы горизонтальных размеров",
];
/// A pixel size instead of the field's size: `pixel size=3.69862e-007 m` (one value: square
/// pixels) or one per axis.
const PIXEL_KEYS: &[&str] = &["pixel size", "pixelsize", "pixel_size"];
const PIXEL_X_KEYS: &[&str] = &["pixel size x", "x pixel size", "pixel_size_x", "xpixelsize"];
const PIXEL_Y_KEYS: &[&str] = &["pixel size y", "y pixel size", "pixel_size_y", "ypixelsize"];

/// What the error says is read, when a matrix has no pitch.
const PITCH_FORMS: &str = "Gwyddion's informational header '# Width: 10.0 µm' and \
     '# Height: 10.0 µm' (or its translations: Breite/Höhe, Largeur/Hauteur, Anchura/Altura, \
     Larghezza/Altezza, Šířka/Výška, Ширина/Высота), or a pixel size 'pixel size=3.7e-07 m' \
     (also 'pixel size x=' / 'pixel size y='), with '# Value units: m' for the heights";

/// One `key: value` or `key=value` line of the header before the data.
struct HeaderLine<'a> {
    line: usize,
    /// Lower case, inner whitespace collapsed, no colon.
    key: String,
    text: &'a str,
    value: &'a str,
}

/// The header lines (`#` comments and leading text lines) in `key: value` / `key=value`
/// form, and the index of the first data line (a line starting with a number).
fn header_lines(text: &str) -> (Vec<HeaderLine<'_>>, usize) {
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let l = line.trim();
        if l.is_empty() {
            continue;
        }
        let body = match l.strip_prefix('#') {
            Some(c) => c.trim(),
            None => {
                // As the 'x y z' reader splits: "1,5e-07" and "100.0,200.0,3" start data.
                let first = l
                    .split(|c: char| c.is_whitespace() || c == ',' || c == ';')
                    .next()
                    .unwrap_or("");
                if first.parse::<f64>().is_ok() {
                    return (out, i);
                }
                l
            }
        };
        let sep = body.find([':', '=']);
        if let Some(at) = sep {
            let key = body[..at].split_whitespace().collect::<Vec<_>>().join(" ");
            out.push(HeaderLine {
                line: i + 1,
                key: key.to_lowercase(),
                text: l,
                value: body[at + 1..].trim(),
            });
        }
    }
    let n = text.lines().count();
    (out, n)
}

/// `"10.000 µm"` as micrometres (a decimal comma accepted), or None.
fn length_um(v: &str) -> Option<f64> {
    let v = v.replace(',', ".");
    let (num, unit) = v
        .split_once(char::is_whitespace)
        .map_or((v.as_str(), ""), |(n, u)| (n, u.trim()));
    let n: f64 = num
        .parse()
        .ok()
        .filter(|n: &f64| n.is_finite() && *n > 0.0)?;
    Some(n * super::bytes::length_unit_um(unit)?)
}

/// The informational header of Gwyddion's text export.
struct GwyddionHeader {
    channel: Option<String>,
    pitch_x_um: Option<f64>,
    pitch_y_um: Option<f64>,
    width_um: Option<f64>,
    height_um: Option<f64>,
    value_um: f64,
    value_unit: String,
    /// Index of the first line of the matrix.
    data_start: usize,
    warnings: Vec<String>,
}

impl GwyddionHeader {
    /// The header when the file's leading lines are Gwyddion's (in any of its translations)
    /// or give a pixel size; None when they do not (an `x y z` file, Gwyddion's XYZ export
    /// among them). A header that is Gwyddion's but lacks what gives the pitch is an error
    /// naming the keys, never an `x y z` file.
    fn find(text: &str) -> Result<Option<GwyddionHeader>> {
        let (lines, data_start) = header_lines(text);
        let find = |keys: &[&str]| lines.iter().find(|h| keys.contains(&h.key.as_str()));
        let channel = find(CHANNEL_KEYS);
        let value = find(VALUE_UNIT_KEYS);
        let lateral = find(LATERAL_UNIT_KEYS);
        let (w, h) = (find(WIDTH_KEYS), find(HEIGHT_KEYS));
        let pixel = find(PIXEL_KEYS);
        let (pixel_x, pixel_y) = (find(PIXEL_X_KEYS), find(PIXEL_Y_KEYS));
        let first_row = text
            .lines()
            .nth(data_start)
            .map_or(0, |l| l.split_whitespace().count());
        let has_pixel = pixel.is_some() || pixel_x.is_some() || pixel_y.is_some();
        if lateral.is_some() && !has_pixel && first_row == 3 {
            return Ok(None); // Gwyddion's XYZ export: points.
        }
        let lengths: Vec<&HeaderLine> = lines
            .iter()
            .filter(|h| h.text.starts_with('#') && length_um(h.value).is_some())
            .collect();
        let gwyddion_like =
            lateral.is_none() && (channel.is_some() || value.is_some() || lengths.len() >= 2);
        let size_form = w.is_some() && h.is_some();
        if !size_form && !has_pixel {
            if !gwyddion_like {
                return Ok(None);
            }
            let mut seen: Vec<String> = lines
                .iter()
                .take(8)
                .map(|h| format!("line {} '{}'", h.line, h.text))
                .collect();
            if lines.len() > 8 {
                seen.push(format!("{} more", lines.len() - 8));
            }
            let missing = match (w, h) {
                (Some(f), None) => format!(
                    "'{}' gives the width, but no height line (one of {}) is in the header",
                    f.text,
                    HEIGHT_KEYS.join(", ")
                ),
                (None, Some(f)) => format!(
                    "'{}' gives the height, but no width line (one of {}) is in the header",
                    f.text,
                    WIDTH_KEYS.join(", ")
                ),
                _ => "no key in it gives the pitch".to_string(),
            };
            bail!(
                "a Gwyddion text header ({}) that is not read: {missing}; read are {PITCH_FORMS} \
                 (export from Gwyddion with the English interface, or save as .gsf)",
                seen.join(", ")
            );
        }
        let length = |f: &HeaderLine| -> Result<f64> {
            length_um(f.value).with_context(|| {
                format!(
                    "Gwyddion text header line {} '{}': expected a positive length with a length unit (m, mm, um, nm, ...)",
                    f.line, f.text
                )
            })
        };
        let (width_um, height_um) = match (w, h) {
            (Some(w), Some(h)) => (Some(length(w)?), Some(length(h)?)),
            _ => (None, None),
        };
        let both = pixel.map(&length).transpose()?;
        let pitch_x_um = pixel_x.map(&length).transpose()?.or(both);
        let pitch_y_um = pixel_y.map(&length).transpose()?.or(both);
        if !size_form {
            let (Some(_), Some(_)) = (pitch_x_um, pitch_y_um) else {
                let (given, other) = if pixel_x.is_some() {
                    ("x", "y")
                } else {
                    ("y", "x")
                };
                bail!(
                    "Gwyddion text header: a pixel size along {given} but none along {other} \
                     (read are {PITCH_FORMS})"
                );
            };
        }
        let mut warnings = Vec::new();
        let (value_unit, value_um) = match value {
            Some(v) => {
                let um = super::bytes::length_unit_um(v.value).with_context(|| {
                    format!(
                        "Gwyddion text header line {} '{}': expected a length unit (m, mm, um, nm, ...): not a height map",
                        v.line, v.text
                    )
                })?;
                (v.value.to_string(), um)
            }
            None if size_form => bail!(
                "Gwyddion text header: '# Width:' and '# Height:' but no '# Value units:' line \
                 (keys read: {}): the height unit is unknown; header lines: {}",
                VALUE_UNIT_KEYS.join(", "),
                lines
                    .iter()
                    .take(8)
                    .map(|h| format!("line {} '{}'", h.line, h.text))
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
            None => {
                warnings.push(
                    "the header gives a pixel size but no value unit ('# Value units:'): heights \
                     taken as metres, Gwyddion's unit for height data"
                        .into(),
                );
                ("m".to_string(), 1e6)
            }
        };
        Ok(Some(GwyddionHeader {
            channel: channel.map(|c| c.value.to_string()),
            pitch_x_um,
            pitch_y_um,
            width_um,
            height_um,
            value_um,
            value_unit,
            data_start,
            warnings,
        }))
    }
}

/// Gwyddion's text export: a matrix of heights under its header.
fn parse_gwyddion_matrix(text: &str, h: GwyddionHeader) -> Result<Surface> {
    let mut heights_um = Vec::new();
    let mut cols = 0usize;
    let mut rows = 0usize;
    for (i, line) in text.lines().enumerate().skip(h.data_start) {
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
        warnings: h.warnings,
        ..Metadata::default()
    };
    // The field's size over the matrix's, else the pixel size; both given must agree.
    let pitch = |size: Option<f64>, n: usize, pixel: Option<f64>, axis: &str| -> Result<f64> {
        match (size.map(|s| s / n as f64), pixel) {
            (Some(a), Some(b)) if (a - b).abs() > 1e-6 * a.max(b) => bail!(
                "Gwyddion text header: the size along {axis} over {n} points gives a pitch of                  {a} um but the pixel size says {b} um"
            ),
            (Some(a), _) | (None, Some(a)) => Ok(a),
            (None, None) => bail!("Gwyddion text header: no pitch along {axis}"),
        }
    };
    let pitch_x_um = pitch(h.width_um, cols, h.pitch_x_um, "x")?;
    let pitch_y_um = pitch(h.height_um, rows, h.pitch_y_um, "y")?;
    let from = if h.width_um.is_some() {
        "width and height"
    } else {
        "pixel size"
    };
    metadata.extra.insert("pitch_from".into(), from.into());
    if let Some(c) = h.channel {
        metadata.extra.insert("channel".into(), c);
    }
    metadata.extra.insert("value_unit".into(), h.value_unit);
    Ok(Surface {
        width: cols,
        height: rows,
        pitch_x_um,
        pitch_y_um,
        heights_um,
        metadata,
    })
}
