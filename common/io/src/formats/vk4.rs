//! Keyence `.vk4` (VK-X laser scanning confocal microscopes), binary, little-endian.
//!
//! Layout as SurfaceTopography's `IO/VK4.py` (MIT) describes it, checked against Gwyddion's
//! `keyence.c` (GPL: read for behaviour only); both cite Keyence's own description
//! (OSTI 1419732):
//!
//! | offset | size | field |
//! |---|---|---|
//! | 0 | 12 | header: magic `VK4_`, dll version (4 bytes), file type (4 zero bytes) |
//! | 12 | 72 | offset table, 18 x u32: setting, color_peak, color_light, light[3], height[3], ... |
//! | 84 | >= 304 | measurement conditions, u32 each: size, year, month, day, hour, minute, second, diff_utc_by_minutes, 30 more, then xy_length_unit, z_length_unit, xy_decimal_place, z_decimal_place, x_length_per_pixel (252), y_length_per_pixel (256), z_length_per_digit (260) |
//!
//! The height image at `height[0]` (offset table byte 36): width, height, bit_depth (8, 16 or
//! 32), compression, byte_size, palette_range_min, palette_range_max (u32 each), a 768-byte
//! palette, then `byte_size` = width * height * bit_depth / 8 bytes of unsigned heights, row
//! after row (x fastest). (SurfaceTopography's reader skips 7 * 8 header bytes before the
//! palette; Gwyddion's 796-byte minimum image header, 7 * 4 + 768, is the one used here.)
//!
//! Units: lateral pitch = x/y_length_per_pixel picometres, height = raw * z_length_per_digit
//! picometres; both converted to um. Neither published reader knows an invalid-point marker
//! (every raw value, 0 included, is a height), so none is applied here: a VK4 surface has no
//! NaN. Orientation: the first stored row is row 0, the row index is y (no flip), as both
//! readers do. Only the first height layer is read.

use anyhow::{bail, Result};

use super::bytes::{checked_size, Bytes};
use super::{Metadata, Surface};

const MAGIC: &[u8; 4] = b"VK4_";
const HEIGHT0_OFFSET_FIELD: usize = 36;
const MEAS_CONDS: usize = 84;
const IMAGE_HEADER_LEN: usize = 7 * 4 + 768;
const PM_TO_UM: f64 = 1e-6;

pub fn parse(data: &[u8]) -> Result<Surface> {
    let b = Bytes::new(data);
    let magic = b.slice(0, 4, "magic")?;
    if magic != MAGIC {
        bail!("field 'magic' is {magic:02x?}, expected \"VK4_\"");
    }
    let file_type = b.slice(8, 4, "file type")?;
    if file_type != [0, 0, 0, 0] {
        bail!("field 'file type' is {file_type:02x?}, expected 4 zero bytes (a normal, not an assembly, file)");
    }
    let dll = b.slice(4, 4, "dll version")?;
    let x_pm = b.u32_le(MEAS_CONDS + 42 * 4, "x_length_per_pixel")?;
    let y_pm = b.u32_le(MEAS_CONDS + 43 * 4, "y_length_per_pixel")?;
    let z_pm = b.u32_le(MEAS_CONDS + 44 * 4, "z_length_per_digit")?;
    for (name, v) in [
        ("x_length_per_pixel", x_pm),
        ("y_length_per_pixel", y_pm),
        ("z_length_per_digit", z_pm),
    ] {
        if v == 0 {
            bail!("field '{name}' is 0, expected a positive length in picometres");
        }
    }
    let off = b.u32_le(HEIGHT0_OFFSET_FIELD, "offset table height[0]")? as usize;
    if off == 0 {
        bail!("field 'offset table height[0]' is 0: the file holds no height image");
    }
    let width = b.u32_le(off, "height image width")? as usize;
    let height = b.u32_le(off + 4, "height image height")? as usize;
    let bits = b.u32_le(off + 8, "height image bit_depth")?;
    let compression = b.u32_le(off + 12, "height image compression")?;
    let byte_size = b.u32_le(off + 16, "height image byte_size")? as usize;
    if width == 0 || height == 0 {
        bail!("fields 'height image width' x 'height' are {width} x {height}, expected positive");
    }
    let point_bytes = match bits {
        8 => 1,
        16 => 2,
        32 => 4,
        other => bail!("field 'height image bit_depth' is {other}, expected 8, 16 or 32"),
    };
    let n = checked_size(&[width, height], "height image width * height")?;
    let len = checked_size(&[n, point_bytes], "height image data size")?;
    if byte_size != len {
        bail!(
            "field 'height image byte_size' is {byte_size}, expected width * height * bit_depth / 8 = {width} * {height} * {point_bytes} = {len}"
        );
    }
    let start = off
        .checked_add(IMAGE_HEADER_LEN)
        .filter(|&s| s <= data.len())
        .ok_or_else(|| {
            anyhow::anyhow!(
                "field 'offset table height[0]' is {off}: its {IMAGE_HEADER_LEN}-byte image header ends past the {}-byte file",
                data.len()
            )
        })?;
    let raw = b.slice(start, len, "height image data")?;
    let scale = z_pm as f64 * PM_TO_UM;
    let heights_um: Vec<f64> = match point_bytes {
        1 => raw.iter().map(|&v| v as f64 * scale).collect(),
        2 => raw
            .chunks_exact(2)
            .map(|c| u16::from_le_bytes([c[0], c[1]]) as f64 * scale)
            .collect(),
        _ => raw
            .chunks_exact(4)
            .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64 * scale)
            .collect(),
    };
    let mut metadata = Metadata {
        format: "vk4".into(),
        pitch_known: true,
        ..Metadata::default()
    };
    let year = b.u32_le(MEAS_CONDS + 4, "year")?;
    let month = b.u32_le(MEAS_CONDS + 8, "month")?;
    let day = b.u32_le(MEAS_CONDS + 12, "day")?;
    let hour = b.u32_le(MEAS_CONDS + 16, "hour")?;
    let minute = b.u32_le(MEAS_CONDS + 20, "minute")?;
    let second = b.u32_le(MEAS_CONDS + 24, "second")?;
    if year > 0 && (1..=12).contains(&month) && (1..=31).contains(&day) {
        metadata.date = Some(format!(
            "{year:04}-{month:02}-{day:02}T{hour:02}:{minute:02}:{second:02}"
        ));
    }
    metadata.extra.insert(
        "dll_version".into(),
        format!("{}.{}.{}.{}", dll[3], dll[2], dll[1], dll[0]),
    );
    metadata
        .extra
        .insert("compression".into(), compression.to_string());
    metadata.extra.insert("bit_depth".into(), bits.to_string());
    Ok(Surface {
        width,
        height,
        pitch_x_um: x_pm as f64 * PM_TO_UM,
        pitch_y_um: y_pm as f64 * PM_TO_UM,
        heights_um,
        metadata,
    })
}
