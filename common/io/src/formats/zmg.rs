//! KLA Zeta (formerly Zeta Instruments) `.zmg`, binary, little-endian. Not a Zygo format: every
//! published reader names the Zeta optical profilers, and the file starts with
//! "Zeta-Instruments".
//!
//! No vendor description is published; three readers were written from real files and agree
//! on this layout: SurfaceTopography's `IO/ZMG.py` (MIT, the one followed here), Gwyddion's
//! `zmgfile.c` and surfalize's `zmg.py` (GPL, read for behaviour only):
//!
//! | offset | size | field |
//! |---|---|---|
//! | 0 | 16 | magic `Zeta-Instruments` (Gwyddion: followed by `_Zeta3D_file_type = `) |
//! | 85 | 4 | xres (u32) |
//! | 89 | 4 | yres (u32) |
//! | 97 | 4 | step_x, um per pixel (f32) |
//! | 101 | 4 | step_y, um per pixel (f32) |
//! | 105 | 4 | step_z, um per digit (f32) |
//! | 117 | 4 | comment_size (u32) |
//! | 131 | 68 | recipe name |
//! | 205 | comment_size | comment |
//! | 205 + comment_size | 2 * xres * yres | heights, row after row (x fastest) |
//!
//! Gwyddion starts the heights at a fixed byte 505, which is 205 + the comment_size of 300 its
//! files had; SurfaceTopography and surfalize use 205 + comment_size, as here. Further images
//! may follow the heights (Gwyddion notes some); they are ignored.
//!
//! What the readers do not settle: the heights are u16 for Gwyddion and SurfaceTopography,
//! i16 for surfalize; u16 is read here (raw values >= 32768 differ between the two). No
//! invalid-point marker is published, so every point is a height (no NaN). Orientation: the
//! first stored row is row 0 and the row index is y (no flip), as all three readers do.

use anyhow::{bail, Result};

use super::bytes::{checked_size, Bytes};
use super::{Metadata, Surface};

const MAGIC: &[u8; 16] = b"Zeta-Instruments";
const FIXED_HEADER_LEN: usize = 205;

pub fn parse(data: &[u8]) -> Result<Surface> {
    let b = Bytes::new(data);
    let magic = b.slice(0, 16, "magic")?;
    if magic != MAGIC {
        bail!(
            "field 'magic' is {:?}, expected \"Zeta-Instruments\"",
            String::from_utf8_lossy(magic)
        );
    }
    let xres = b.u32_le(85, "xres")? as usize;
    let yres = b.u32_le(89, "yres")? as usize;
    if xres == 0 || yres == 0 {
        bail!("fields 'xres' x 'yres' are {xres} x {yres}, expected positive");
    }
    let step_x = b.f32_le(97, "step_x")? as f64;
    let step_y = b.f32_le(101, "step_y")? as f64;
    let step_z = b.f32_le(105, "step_z")? as f64;
    for (name, v) in [("step_x", step_x), ("step_y", step_y)] {
        if !v.is_finite() || v <= 0.0 {
            bail!("field '{name}' is {v}, expected a finite positive pixel size in um");
        }
    }
    if !step_z.is_finite() || step_z == 0.0 {
        bail!("field 'step_z' is {step_z}, expected a finite non-zero um per digit");
    }
    let comment_size = b.u32_le(117, "comment_size")? as usize;
    let start = match FIXED_HEADER_LEN.checked_add(comment_size) {
        Some(s) if s <= data.len() => s,
        _ => bail!(
            "field 'comment_size' is {comment_size}: the comment would end past the {}-byte file",
            data.len()
        ),
    };
    let len = checked_size(&[xres, yres, 2], "fields 'xres' x 'yres' x 2 bytes")?;
    if len > data.len() - start {
        bail!(
            "fields 'xres' x 'yres' ({xres} x {yres}) need {len} bytes of heights from byte {start}, but the file has only {} bytes",
            data.len()
        );
    }
    let raw = b.slice(start, len, "height data")?;
    let heights_um: Vec<f64> = raw
        .chunks_exact(2)
        .map(|c| u16::from_le_bytes([c[0], c[1]]) as f64 * step_z)
        .collect();
    let mut metadata = Metadata {
        format: "zmg".into(),
        pitch_known: true,
        instrument: Some("KLA Zeta".into()),
        ..Metadata::default()
    };
    let recipe = b.text(131, 68, "recipe name")?;
    if !recipe.is_empty() {
        metadata.extra.insert("recipe".into(), recipe);
    }
    let comment = b.text(FIXED_HEADER_LEN, comment_size, "comment")?;
    if !comment.is_empty() {
        metadata.extra.insert("comment".into(), comment);
    }
    Ok(Surface {
        width: xres,
        height: yres,
        pitch_x_um: step_x,
        pitch_y_um: step_y,
        heights_um,
        metadata,
    })
}
