//! Alicona `.al3d` (InfiniteFocus / MeX): a tagged text header and a float32 depth image.
//!
//! Layout as Alicona's AL3D 1.0 specification describes it (learned from SurfaceTopography's
//! `AL3D.py`, MIT, and checked against surfalize and Bio-Formats' `AliconaReader`, behaviour
//! only):
//! - 17 bytes of magic `AliconaImaging\0\r\n`;
//! - tags of 52 bytes each: key (20 bytes, NUL-padded), value (30 bytes, NUL-padded, as text),
//!   `\r\n`. The first is `Version`, the second `TagCount` = the number of tags that follow.
//!   Used here: `Cols`, `Rows`, `PixelSizeXMeter`, `PixelSizeYMeter`, `DepthImageOffset`
//!   (absolute byte offset of the depth image), `InvalidPixelValue` (a float, often `nan`),
//!   `TextureImageOffset`;
//! - at DepthImageOffset: `Rows` rows of float32 little-endian depths in metres; each row is
//!   padded so its length in bytes is a multiple of 8 (`Cols` rounded up to even). A file whose
//!   depth image ends without the padding (as surfalize writes) is read unpadded, with a
//!   warning in the metadata.
//!
//! A depth equal to InvalidPixelValue (or NaN) is not measured. Rows are kept in file order
//! (row 0 = y = 0), so row index grows with y. The texture and icon images are not read.

use std::collections::BTreeMap;

use anyhow::{bail, Context, Result};

use super::bytes::{checked_size, Bytes};
use super::{Metadata, Surface};

const MAGIC: &[u8] = b"AliconaImaging\0\r\n";
const TAG_LEN: usize = 52;

pub fn parse(data: &[u8]) -> Result<Surface> {
    if !data.starts_with(MAGIC) {
        bail!("magic: expected 'AliconaImaging' followed by NUL, CR, LF");
    }
    let b = Bytes::new(data);
    let tag = |i: usize| -> Result<(String, String)> {
        let off = MAGIC.len() + i * TAG_LEN;
        let raw = b.slice(off, TAG_LEN, &format!("tag {i} (52 bytes)"))?;
        if &raw[50..] != b"\r\n" {
            bail!("tag {i} at offset {off}: expected CR LF at its end");
        }
        Ok((
            b.text(off, 20, "tag key")?,
            b.text(off + 20, 30, "tag value")?,
        ))
    };
    let (key, version) = tag(0)?;
    if key != "Version" {
        bail!("tag 0 is '{key}', expected 'Version'");
    }
    let (key, count) = tag(1)?;
    if key != "TagCount" {
        bail!("tag 1 is '{key}', expected 'TagCount'");
    }
    let count: usize = count
        .parse()
        .with_context(|| format!("tag 'TagCount' is '{count}', expected a count"))?;
    let tags_end = count
        .checked_add(2)
        .and_then(|c| c.checked_mul(TAG_LEN))
        .and_then(|l| l.checked_add(MAGIC.len()));
    if tags_end.is_none_or(|e| e > data.len()) {
        bail!(
            "tag 'TagCount' is {count}: {count} tags of 52 bytes do not fit in the {}-byte file",
            data.len()
        );
    }
    let mut tags = BTreeMap::new();
    for i in 0..count {
        let (k, v) = tag(i + 2)?;
        tags.insert(k, v);
    }
    let get = |name: &str| -> Result<&str> {
        tags.get(name)
            .map(|s| s.as_str())
            .with_context(|| format!("tag '{name}' is missing"))
    };
    let count_tag = |name: &str| -> Result<usize> {
        let v = get(name)?;
        v.parse::<usize>()
            .with_context(|| format!("tag '{name}' is '{v}', expected a non-negative integer"))
    };
    let real = |name: &str| -> Result<f64> {
        let v = get(name)?;
        parse_real(v).with_context(|| format!("tag '{name}' is '{v}', expected a number"))
    };
    let cols = count_tag("Cols")?;
    let rows = count_tag("Rows")?;
    if cols == 0 || rows == 0 {
        bail!("tags 'Cols' x 'Rows' are {cols} x {rows}, expected positive");
    }
    let pitch_x_m = real("PixelSizeXMeter")?;
    let pitch_y_m = real("PixelSizeYMeter")?;
    for (name, v) in [
        ("PixelSizeXMeter", pitch_x_m),
        ("PixelSizeYMeter", pitch_y_m),
    ] {
        if !v.is_finite() || v <= 0.0 {
            bail!("tag '{name}' is {v}, expected a finite positive size (metres)");
        }
    }
    let offset = count_tag("DepthImageOffset")?;
    let invalid = match tags.get("InvalidPixelValue") {
        Some(v) => parse_real(v)
            .with_context(|| format!("tag 'InvalidPixelValue' is '{v}', expected a number"))?,
        None => f64::NAN,
    };
    let mut metadata = Metadata {
        format: "al3d".into(),
        pitch_known: true,
        ..Metadata::default()
    };
    metadata.extra.insert("Version".into(), version);
    // Rows padded to a multiple of 8 bytes: Cols rounded up to even.
    let padded_cols = cols.checked_add(cols % 2).context("tag 'Cols' overflows")?;
    let padded_len = checked_size(&[rows, padded_cols, 4], "Rows * padded Cols * 4 bytes")?;
    let plain_len = checked_size(&[rows, cols, 4], "Rows * Cols * 4 bytes")?;
    let available = data.len().saturating_sub(offset);
    let stride = if available >= padded_len {
        padded_cols
    } else if available >= plain_len {
        metadata
            .warnings
            .push("depth rows are not padded to 8 bytes as AL3D 1.0 specifies".into());
        cols
    } else {
        bail!(
            "depth image: 'Rows' x 'Cols' = {rows} x {cols} float32 (rows padded to 8 bytes) needs {padded_len} bytes at 'DepthImageOffset' {offset}, the file has {available}"
        );
    };
    let depth = b.slice(
        offset,
        checked_size(&[rows, stride, 4], "depth image")?,
        "depth image",
    )?;
    let mut heights_um = Vec::with_capacity(rows * cols);
    for row in depth.chunks_exact(stride * 4) {
        for c in row[..cols * 4].chunks_exact(4) {
            let z = f32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64;
            // Compared in f32, as stored: the marker written as text rounds the same way.
            let is_invalid = z.is_nan() || z as f32 == invalid as f32;
            heights_um.push(if is_invalid { f64::NAN } else { z * 1e6 });
        }
    }
    for key in ["TextureImageOffset", "NumberOfPlanes", "Magnification"] {
        if let Some(v) = tags.get(key) {
            metadata.extra.insert(key.into(), v.clone());
        }
    }
    Ok(Surface {
        width: cols,
        height: rows,
        pitch_x_um: pitch_x_m * 1e6,
        pitch_y_um: pitch_y_m * 1e6,
        heights_um,
        metadata,
    })
}

/// A number as Alicona writes it (`nan` / `NaN` included).
fn parse_real(v: &str) -> Option<f64> {
    let v = v.trim();
    if v.eq_ignore_ascii_case("nan") {
        return Some(f64::NAN);
    }
    v.parse().ok()
}
