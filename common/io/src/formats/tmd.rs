//! TrueMap / GelSight `.tmd` ("Binary TrueMap Data File v2.0").
//!
//! Layout as GelSight publishes it in its MATLAB toolbox (`readtmd.m` / `writetmd.m`, gsmatlab),
//! agreeing with SurfaceTopography's `TMD.py` (MIT), all little-endian:
//! - 32 bytes: `Binary TrueMap Data File v2.0` then `\r\n\0`;
//! - a comment, NUL-terminated, of any length (GelSight writes just the NUL; TrueMap v6 writes
//!   a 24-byte `Created by TrueMap v6 ...\r\n\0`);
//! - cols u32, rows u32, length_x f32, length_y f32, offset_x f32, offset_y f32 (millimetres);
//! - rows * cols float32 heights in millimetres, row after row, x fastest.
//!
//! Pitch = length / count. Units: GelSight documents millimetres for lengths and heights;
//! read as such (SurfaceTopography reports the same numbers as micrometres: readers disagree).
//! No invalid marker is defined: NaN / inf heights are not measured. Rows are kept in file
//! order (row 0 = y = 0), so row index grows with y.

use anyhow::{bail, Context, Result};

use super::bytes::{checked_size, Bytes};
use super::{Metadata, Surface};

const MAGIC: &[u8] = b"Binary TrueMap Data File v2.0";
const MAGIC_FIELD_LEN: usize = 32;
const MM_TO_UM: f64 = 1e3;

pub fn parse(data: &[u8]) -> Result<Surface> {
    if !data.starts_with(MAGIC) {
        bail!("magic: expected 'Binary TrueMap Data File v2.0'");
    }
    let b = Bytes::new(data);
    if b.slice(MAGIC.len(), 3, "magic line end")? != b"\r\n\0" {
        bail!("magic: expected '\\r\\n\\0' after 'Binary TrueMap Data File v2.0'");
    }
    let comment_len = data[MAGIC_FIELD_LEN..]
        .iter()
        .position(|&b| b == 0)
        .context("comment: no NUL byte ends it")?;
    let comment = String::from_utf8_lossy(&data[MAGIC_FIELD_LEN..MAGIC_FIELD_LEN + comment_len])
        .trim()
        .to_string();
    let h = MAGIC_FIELD_LEN + comment_len + 1;
    let cols = b.u32_le(h, "cols")? as usize;
    let rows = b.u32_le(h + 4, "rows")? as usize;
    let length_x = b.f32_le(h + 8, "length_x")? as f64;
    let length_y = b.f32_le(h + 12, "length_y")? as f64;
    let offset_x = b.f32_le(h + 16, "offset_x")? as f64;
    let offset_y = b.f32_le(h + 20, "offset_y")? as f64;
    if cols == 0 || rows == 0 {
        bail!("fields 'cols' x 'rows' are {cols} x {rows}, expected positive");
    }
    for (name, v) in [("length_x", length_x), ("length_y", length_y)] {
        if !v.is_finite() || v <= 0.0 {
            bail!("field '{name}' is {v}, expected a finite positive length (mm)");
        }
    }
    let n = checked_size(&[cols, rows], "cols * rows")?;
    let len = checked_size(&[n, 4], "cols * rows * 4 bytes")?;
    let raw = b.slice(h + 24, len, "heights (cols x rows float32)")?;
    let heights_um = raw
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64 * MM_TO_UM)
        .collect();
    let mut metadata = Metadata {
        format: "tmd".into(),
        pitch_known: true,
        ..Metadata::default()
    };
    // Readers disagree by x1000 on this format: say which reading this is, every time.
    metadata.warnings.push(
        "lengths and heights read as millimetres (GelSight's toolbox); SurfaceTopography reads \
         the same numbers as micrometres: check a known dimension (pitch, step height)"
            .into(),
    );
    if !comment.is_empty() {
        metadata.extra.insert("comment".into(), comment);
    }
    metadata
        .extra
        .insert("offset_x_um".into(), (offset_x * MM_TO_UM).to_string());
    metadata
        .extra
        .insert("offset_y_um".into(), (offset_y * MM_TO_UM).to_string());
    Ok(Surface {
        width: cols,
        height: rows,
        pitch_x_um: length_x * MM_TO_UM / cols as f64,
        pitch_y_um: length_y * MM_TO_UM / rows as f64,
        heights_um,
        metadata,
    })
}
