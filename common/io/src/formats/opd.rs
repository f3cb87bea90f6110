//! Bruker (formerly Veeco) Wyko `.opd` (Vision software, white-light interferometers), binary,
//! little-endian: a directory of named blocks, then the blocks' contents in directory order.
//!
//! Layout as SurfaceTopography's `IO/OPD.py` (MIT) describes it, checked against Gwyddion's
//! `opdfile.c` (GPL: read for behaviour only):
//!
//! - 2 bytes (`01 00`), then 24-byte block descriptors: name (16 bytes, NUL-padded), type (u16),
//!   length (u32), flags (u16). The first descriptor is "Directory" (type 1); its length is
//!   24 x the number of descriptors, itself included.
//! - Block contents follow the directory (at byte 2 + directory length), one after another in
//!   descriptor order, each `length` bytes (zero-length blocks take no space).
//! - Types: 3 array, 5 text, 6 short (i16; a "short" of length 4 is an i32, as Gwyddion
//!   found), 7 float (f32), 8 double, 12 long (i32). A float block "ImageModificat~0" whose
//!   descriptor says 40 bytes holds 4 (Gwyddion's finding); read as 4. Gwyddion also notes
//!   that a type-15 block shifts the positions of what follows it; that is not handled (such
//!   a file reads wrong or fails the size checks, as in Gwyddion).
//! - Heights: the first array named "OPD", "SAMPLE_DATA", "RAW_DATA", "RAW DATA" or "Raw":
//!   nx, ny, element size (u16 each: 4 = f32, 2 = i16, 1 = u8), then nx * ny elements,
//!   column after column (x slowest), each column from the largest y to the smallest.
//! - Scales: "Wavelength" (f32, nm, required), "Mult" (short, default 1), "Pixel_size" (f32,
//!   mm, required), "Aspect" (f32, default 1: pitch_y = Pixel_size * Aspect).
//!   height_nm = value * Wavelength / Mult.
//!
//! Invalid points: f32 values >= 1e38 or not finite (Gwyddion's rule; SurfaceTopography masks
//! |value| >= 1e32, which agrees on the FLT_MAX markers Vision writes), i16 values >= 32766.
//! u8 arrays have no marker.
//!
//! Orientation: both readers put the first stored value of each column at the largest row
//! index (SurfaceTopography flips the y axis with `fliplr`, Gwyddion fills rows from the
//! bottom), so here too: stored column i, element k -> row ny - 1 - k, column i, and the row
//! index grows with y.

use anyhow::{bail, Result};

use super::bytes::{checked_size, Bytes};
use super::{Metadata, Surface};

const BLOCK_LEN: usize = 24;
const DIR_START: usize = 2;
const TYPE_DIRECTORY: u16 = 1;
const TYPE_ARRAY: u16 = 3;
const TYPE_SHORT: u16 = 6;
const TYPE_FLOAT: u16 = 7;
const TYPE_LONG: u16 = 12;
const HEIGHT_BLOCKS: [&str; 5] = ["OPD", "SAMPLE_DATA", "RAW_DATA", "RAW DATA", "Raw"];
const BAD_FLOAT: f32 = 1e38;
const BAD_INT16: i16 = 32766;

/// A directory entry and where its contents sit in the file.
struct Block {
    name: String,
    kind: u16,
    start: usize,
    len: usize,
}

pub fn parse(data: &[u8]) -> Result<Surface> {
    let b = Bytes::new(data);
    let dir = read_descriptor(&b, DIR_START)?;
    if dir.0 != "Directory" || dir.1 != TYPE_DIRECTORY {
        bail!(
            "first block is '{}' of type {}, expected 'Directory' of type 1",
            dir.0,
            dir.1
        );
    }
    let dir_len = dir.2;
    if dir_len % BLOCK_LEN != 0 || dir_len < BLOCK_LEN {
        bail!("field 'Directory length' is {dir_len}, expected a positive multiple of {BLOCK_LEN}");
    }
    let mut offset = DIR_START
        .checked_add(dir_len)
        .filter(|&end| end <= data.len())
        .ok_or_else(|| {
            anyhow::anyhow!(
                "field 'Directory length' is {dir_len}: the directory would end past the {}-byte file",
                data.len()
            )
        })?;
    // The directory fits in the file, so the block list is bounded by the file's length.
    let mut blocks = Vec::with_capacity(dir_len / BLOCK_LEN - 1);
    for k in 1..dir_len / BLOCK_LEN {
        let (name, kind, mut len) = read_descriptor(&b, DIR_START + k * BLOCK_LEN)?;
        if name == "ImageModificat~0" && kind == TYPE_FLOAT && len == 40 {
            // Vision writes this float's length as 40 but stores 4 bytes (Gwyddion's finding
            // on real files); taking 40 would shift every later block.
            len = 4;
        }
        let start = offset;
        offset = match start.checked_add(len) {
            Some(end) if end <= data.len() => end,
            _ => bail!(
                "block '{name}' claims {len} bytes from byte {start}, past the end of the {}-byte file",
                data.len()
            ),
        };
        if len > 0 {
            blocks.push(Block {
                name,
                kind,
                start,
                len,
            });
        }
    }
    let find = |name: &str| blocks.iter().find(|bl| bl.name == name);
    let float = |name: &str| -> Result<Option<f64>> {
        let Some(bl) = find(name) else {
            return Ok(None);
        };
        if bl.kind != TYPE_FLOAT || bl.len != 4 {
            bail!(
                "block '{name}' is of type {} and {} bytes, expected a float (type 7, 4 bytes)",
                bl.kind,
                bl.len
            );
        }
        Ok(Some(b.f32_le(bl.start, name)? as f64))
    };
    let wavelength_nm = float("Wavelength")?.ok_or_else(|| {
        anyhow::anyhow!("block 'Wavelength' is missing: heights cannot be scaled")
    })?;
    let pixel_mm = float("Pixel_size")?
        .ok_or_else(|| anyhow::anyhow!("block 'Pixel_size' is missing: the pitch is unknown"))?;
    let aspect = float("Aspect")?.unwrap_or(1.0);
    let mult = match find("Mult") {
        None => 1.0,
        Some(bl) if (bl.kind == TYPE_SHORT || bl.kind == TYPE_LONG) && bl.len == 2 => {
            b.i16_le(bl.start, "Mult")? as f64
        }
        Some(bl) if (bl.kind == TYPE_SHORT || bl.kind == TYPE_LONG) && bl.len == 4 => {
            b.i32_le(bl.start, "Mult")? as f64
        }
        Some(bl) => bail!(
            "block 'Mult' is of type {} and {} bytes, expected a short (type 6, 2 bytes)",
            bl.kind,
            bl.len
        ),
    };
    for (name, v) in [
        ("Wavelength", wavelength_nm),
        ("Pixel_size", pixel_mm),
        ("Aspect", aspect),
        ("Mult", mult),
    ] {
        if !v.is_finite() || v <= 0.0 {
            bail!("block '{name}' is {v}, expected a finite positive number");
        }
    }
    let Some(array) = blocks
        .iter()
        .find(|bl| bl.kind == TYPE_ARRAY && HEIGHT_BLOCKS.contains(&bl.name.as_str()))
    else {
        bail!("no height array block (one of {HEIGHT_BLOCKS:?} of type 3) in the directory");
    };
    if array.len < 6 {
        bail!(
            "block '{}' is {} bytes, expected at least 6 (nx, ny, element size)",
            array.name,
            array.len
        );
    }
    let nx = u16_le(&b, array.start, "array nx")? as usize;
    let ny = u16_le(&b, array.start + 2, "array ny")? as usize;
    let elsize = u16_le(&b, array.start + 4, "array element size")? as usize;
    if nx == 0 || ny == 0 {
        bail!("fields 'array nx' x 'array ny' are {nx} x {ny}, expected positive");
    }
    if !matches!(elsize, 1 | 2 | 4) {
        bail!("field 'array element size' is {elsize}, expected 1 (u8), 2 (i16) or 4 (f32)");
    }
    let n = checked_size(&[nx, ny], "array nx * ny")?;
    let len = checked_size(&[n, elsize], "array data size")?;
    if len > array.len - 6 {
        bail!(
            "block '{}' holds {} bytes of points but nx x ny x element size = {nx} x {ny} x {elsize} = {len}",
            array.name,
            array.len - 6
        );
    }
    let raw = b.slice(array.start + 6, len, "array data")?;
    let scale_um = wavelength_nm / mult * 1e-3;
    let value = |i: usize| -> f64 {
        let c = &raw[i * elsize..(i + 1) * elsize];
        match elsize {
            4 => {
                let v = f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
                if v.is_finite() && v < BAD_FLOAT {
                    v as f64 * scale_um
                } else {
                    f64::NAN
                }
            }
            2 => {
                let v = i16::from_le_bytes([c[0], c[1]]);
                if v < BAD_INT16 {
                    v as f64 * scale_um
                } else {
                    f64::NAN
                }
            }
            _ => c[0] as f64 * scale_um,
        }
    };
    let mut heights_um = vec![f64::NAN; n];
    for col in 0..nx {
        for k in 0..ny {
            heights_um[(ny - 1 - k) * nx + col] = value(col * ny + k);
        }
    }
    let mut metadata = Metadata {
        format: "opd".into(),
        pitch_known: true,
        wavelength_um: Some(wavelength_nm * 1e-3),
        ..Metadata::default()
    };
    metadata
        .extra
        .insert("height_block".into(), array.name.clone());
    metadata.extra.insert("mult".into(), mult.to_string());
    if let Some(bl) = find("Title").filter(|bl| bl.kind == 5) {
        let title = b.text(bl.start, bl.len, "Title")?;
        if !title.is_empty() {
            metadata.extra.insert("title".into(), title);
        }
    }
    Ok(Surface {
        width: nx,
        height: ny,
        pitch_x_um: pixel_mm * 1e3,
        pitch_y_um: pixel_mm * aspect * 1e3,
        heights_um,
        metadata,
    })
}

/// Name, type and length of the descriptor at `at`.
fn read_descriptor(b: &Bytes, at: usize) -> Result<(String, u16, usize)> {
    let name = b.text(at, 16, "block name")?;
    let kind = u16_le(b, at + 16, "block type")?;
    let len = b.u32_le(at + 18, "block length")? as usize;
    Ok((name, kind, len))
}

fn u16_le(b: &Bytes, at: usize, field: &str) -> Result<u16> {
    let s = b.slice(at, 2, field)?;
    Ok(u16::from_le_bytes([s[0], s[1]]))
}
