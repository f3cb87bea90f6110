//! Gwyddion Simple Field `.gsf` (Gwyddion 2.20+, and scripts that export for it).
//!
//! Layout as published in the Gwyddion user guide ("Simple Field Files"):
//! - the magic line `Gwyddion Simple Field 1.0\n`;
//! - a text header of `name = value` lines, each ended by `\n` (whitespace around the name,
//!   the `=` and at the end of the value is ignored; names are case-sensitive). `XRes` and
//!   `YRes` (positive integers) are mandatory; `XReal` / `YReal` (physical size, default 1),
//!   `XOffset` / `YOffset`, `XYUnits` / `ZUnits` (base SI units, e.g. `m`) and `Title` are
//!   optional; anything else is kept as metadata;
//! - one to four NUL bytes, so the data starts at a multiple of 4 from the file start;
//! - `XRes * YRes` little-endian IEEE float32, row by row from the top row, each row left to
//!   right.
//!
//! Gwyddion's first row is the top of the image and its y axis points down the rows, so the
//! file's row 0 is y = 0 and row index grows with y: rows are kept in file order.
//! Pitch = XReal / XRes (um). Units: `XYUnits` / `ZUnits` are taken as length units; a file
//! without them is read as metres (Gwyddion's base unit for heights), with a warning in the
//! metadata. Not-finite values (NaN, inf) are not measured.

use anyhow::{bail, Context, Result};

use super::bytes::{checked_size, length_unit_um};
use super::{Metadata, Surface};

const MAGIC: &[u8] = b"Gwyddion Simple Field 1.0\n";

pub fn parse(data: &[u8]) -> Result<Surface> {
    if !data.starts_with(MAGIC) {
        bail!("magic line: expected 'Gwyddion Simple Field 1.0' followed by a line feed");
    }
    let header_end = data
        .iter()
        .position(|&b| b == 0)
        .context("header: no NUL byte ends the text header")?;
    let header =
        std::str::from_utf8(&data[MAGIC.len()..header_end]).context("header: not UTF-8 text")?;
    let mut xres = None;
    let mut yres = None;
    let (mut xreal, mut yreal) = (1.0f64, 1.0f64);
    let (mut xy_unit, mut z_unit) = (None, None);
    let (mut xoff, mut yoff) = (None, None);
    let mut metadata = Metadata {
        format: "gsf".into(),
        pitch_known: true,
        ..Metadata::default()
    };
    for line in header.split('\n') {
        if line.trim().is_empty() {
            continue;
        }
        let (name, value) = line
            .split_once('=')
            .with_context(|| format!("header line '{line}': expected 'name = value'"))?;
        let (name, value) = (name.trim(), value.trim());
        match name {
            "XRes" => xres = Some(positive_int(name, value)?),
            "YRes" => yres = Some(positive_int(name, value)?),
            "XReal" => xreal = positive_real(name, value)?,
            "YReal" => yreal = positive_real(name, value)?,
            "XYUnits" => xy_unit = Some(value.to_string()),
            "ZUnits" => z_unit = Some(value.to_string()),
            "XOffset" => xoff = Some(finite_real(name, value)?),
            "YOffset" => yoff = Some(finite_real(name, value)?),
            _ => {
                metadata.extra.insert(name.to_string(), value.to_string());
            }
        }
    }
    let width = xres.context("header field 'XRes' is missing (mandatory)")?;
    let height = yres.context("header field 'YRes' is missing (mandatory)")?;
    let n = checked_size(&[width, height], "XRes * YRes")?;
    // One to four NULs align the data start to a multiple of 4.
    let data_start = (header_end / 4 + 1) * 4;
    if data[header_end..data_start.min(data.len())]
        .iter()
        .any(|&b| b != 0)
    {
        bail!("NUL padding: expected NUL bytes up to offset {data_start}");
    }
    let data_len = checked_size(&[n, 4], "XRes * YRes * 4 bytes")?;
    let available = data.len().saturating_sub(data_start);
    if available != data_len {
        bail!(
            "data: XRes x YRes = {width} x {height} needs {data_len} bytes of float32 after offset {data_start}, the file has {available}"
        );
    }
    let mut unit_um = |field: &str, unit: Option<String>| -> Result<f64> {
        match unit.as_deref() {
            None | Some("") => {
                metadata
                    .warnings
                    .push(format!("'{field}' missing: taken as metres"));
                Ok(1e6)
            }
            Some(u) => length_unit_um(u).with_context(|| {
                format!(
                    "header field '{field}' is '{u}', expected a length unit (m, mm, um, nm, ...)"
                )
            }),
        }
    };
    let uxy = unit_um("XYUnits", xy_unit)?;
    let uz = unit_um("ZUnits", z_unit)?;
    if let (Some(x), Some(y)) = (xoff, yoff) {
        metadata.stage_position_um = Some([x * uxy, y * uxy]);
    }
    let heights_um = data[data_start..]
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64 * uz)
        .collect();
    Ok(Surface {
        width,
        height,
        pitch_x_um: xreal * uxy / width as f64,
        pitch_y_um: yreal * uxy / height as f64,
        heights_um,
        metadata,
    })
}

fn positive_int(name: &str, value: &str) -> Result<usize> {
    match value.parse::<usize>() {
        Ok(v) if v > 0 => Ok(v),
        _ => bail!("header field '{name}' is '{value}', expected a positive integer"),
    }
}

fn finite_real(name: &str, value: &str) -> Result<f64> {
    match value.parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        _ => bail!("header field '{name}' is '{value}', expected a finite number"),
    }
}

fn positive_real(name: &str, value: &str) -> Result<f64> {
    match value.parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        _ => bail!("header field '{name}' is '{value}', expected a finite positive number"),
    }
}

/// Writes `s` as a Gwyddion Simple Field: lengths and heights in metres (Gwyddion's base
/// units, `XYUnits = m`, `ZUnits = m`), float32, rows in surfstream's order (row 0 = the
/// file's first row), NaN kept for points not measured (Gwyddion masks them on import).
pub fn write(path: &std::path::Path, s: &Surface) -> Result<()> {
    use std::io::Write;
    if s.width == 0 || s.height == 0 || s.heights_um.len() != s.width * s.height {
        bail!(
            "{}: cannot write a {} x {} px surface with {} heights",
            path.display(),
            s.height,
            s.width,
            s.heights_um.len()
        );
    }
    let mut header = String::from("Gwyddion Simple Field 1.0\n");
    let m_per_um = 1e-6;
    let mut line = |k: &str, v: String| header.push_str(&format!("{k} = {v}\n"));
    line("XRes", s.width.to_string());
    line("YRes", s.height.to_string());
    line(
        "XReal",
        format!("{:e}", s.pitch_x_um * s.width as f64 * m_per_um),
    );
    line(
        "YReal",
        format!("{:e}", s.pitch_y_um * s.height as f64 * m_per_um),
    );
    if let Some([x, y]) = s.metadata.stage_position_um {
        line("XOffset", format!("{:e}", x * m_per_um));
        line("YOffset", format!("{:e}", y * m_per_um));
    }
    line("XYUnits", "m".into());
    line("ZUnits", "m".into());
    line("Title", "Height".into());
    if !s.metadata.pitch_known {
        line("Comment", "pitch not known: 1 um assumed".into());
    }
    let mut bytes = header.into_bytes();
    // One to four NULs: the data start at a multiple of 4.
    let pad = 4 - bytes.len() % 4;
    bytes.extend(std::iter::repeat_n(0u8, pad));
    bytes.reserve(s.heights_um.len() * 4);
    for &z in &s.heights_um {
        bytes.extend_from_slice(&((z * m_per_um) as f32).to_le_bytes());
    }
    surfstream_core::fsutil::write_atomic(path, |w| {
        w.write_all(&bytes)
            .with_context(|| format!("{}: write failed", path.display()))
    })
}
