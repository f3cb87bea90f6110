//! Digital Surf `.sur` (MountainsMap): a little-endian 512-byte header, a comment zone, a
//! private zone, then int16 / int32 points, row after row (first stored row = row 0), plain or
//! zlib-compressed ("DSCOMPRESSED").
//!
//! Heights: z = (raw * spacing_z + offset_z) in `unit_step_z`, converted to um. offset_z is taken
//! in the z step unit, as Gwyddion does; surfalize 0.19.2 adds it unscaled. Relative parameters
//! (Sq, ...) do not depend on it. When `non_measured_points` == 1, raw == min_point - 2 is
//! invalid (NaN). Only the first object of a multi-object file is read. The unit fields are
//! read as UTF-8 when their bytes are valid UTF-8 (surfalize writes "µm" as 0xC2 0xB5), else
//! as Latin-1 (Digital Surf: the single byte 0xB5).

use std::io::Read;

use anyhow::{bail, Context, Result};
use rayon::prelude::*;

use super::bytes::{checked_size, length_unit_um, Bytes};
use super::{Metadata, Surface};

const HEADER_LEN: usize = 512;

pub fn parse(data: &[u8]) -> Result<Surface> {
    let b = Bytes::new(data);
    let code = b.text(0, 12, "code")?;
    let compressed = match code.as_str() {
        "DIGITAL SURF" => false,
        "DSCOMPRESSED" => true,
        other => bail!("field 'code' is '{other}', expected 'DIGITAL SURF' or 'DSCOMPRESSED'"),
    };
    let studiable_type = b.i16_le(18, "studiable_type")?;
    if studiable_type != 2 {
        bail!("field 'studiable_type' is {studiable_type}, expected 2 (surface); profiles and series are not read");
    }
    let non_measured = b.i16_le(86, "non_measured_points")?;
    let bits = b.i16_le(98, "bits_per_point")?;
    let min_point = b.i32_le(100, "min_point")?;
    let width_raw = b.i32_le(108, "n_points_per_line")?;
    let height_raw = b.i32_le(112, "n_lines")?;
    if width_raw <= 0 || height_raw <= 0 {
        bail!("fields 'n_points_per_line' x 'n_lines' are {width_raw} x {height_raw}, expected positive");
    }
    let (width, height) = (width_raw as usize, height_raw as usize);
    let n = checked_size(&[width, height], "n_points_per_line * n_lines")?;
    let spacing_x = b.f32_le(120, "spacing_x")? as f64;
    let spacing_y = b.f32_le(124, "spacing_y")? as f64;
    let spacing_z = b.f32_le(128, "spacing_z")? as f64;
    let unit_x = b.text_utf8_or_latin1(180, 16, "unit_step_x")?;
    let unit_y = b.text_utf8_or_latin1(196, 16, "unit_step_y")?;
    let unit_z = b.text_utf8_or_latin1(212, 16, "unit_step_z")?;
    let offset_z = b.f32_le(474, "offset_z")? as f64;
    let compressed_size = b.u32_le(324, "compressed_data_size")? as usize;
    let comment_len = b.i16_le(334, "length_comment")?;
    let private_len = b.i16_le(336, "length_private")?;
    if comment_len < 0 || private_len < 0 {
        bail!("fields 'length_comment' {comment_len} / 'length_private' {private_len} must not be negative");
    }
    let unit_um = |u: &str, field: &str| -> Result<f64> {
        length_unit_um(u).with_context(|| {
            format!("field '{field}' is '{u}', expected a length unit (m, mm, um, nm, ...)")
        })
    };
    let (ux, uy, uz) = (
        unit_um(&unit_x, "unit_step_x")?,
        unit_um(&unit_y, "unit_step_y")?,
        unit_um(&unit_z, "unit_step_z")?,
    );
    for (name, v) in [
        ("spacing_x", spacing_x),
        ("spacing_y", spacing_y),
        ("spacing_z", spacing_z),
    ] {
        if !v.is_finite() || v <= 0.0 {
            bail!("field '{name}' is {v}, expected a finite positive number");
        }
    }
    if !offset_z.is_finite() {
        bail!("field 'offset_z' is {offset_z}, expected a finite number");
    }
    let point_bytes = match bits {
        16 => 2,
        32 => 4,
        other => bail!("field 'bits_per_point' is {other}, expected 16 or 32"),
    };
    let raw_len = checked_size(&[n, point_bytes], "point data size")?;
    let start = HEADER_LEN + comment_len as usize + private_len as usize;
    let inflated;
    let raw: &[u8] = if compressed {
        let zone = b.slice(
            start,
            compressed_size,
            "compressed data (compressed_data_size)",
        )?;
        inflated = inflate_streams(zone, raw_len)?;
        &inflated
    } else {
        b.slice(start, raw_len, "point data")?
    };
    let invalid_raw = if non_measured == 1 {
        min_point.checked_sub(2)
    } else {
        None
    };
    let scale = spacing_z * uz;
    let offset_um = offset_z * uz;
    let convert = |v: i32| -> f64 {
        if Some(v) == invalid_raw {
            f64::NAN
        } else {
            v as f64 * scale + offset_um
        }
    };
    let heights_um: Vec<f64> = if point_bytes == 2 {
        raw.chunks_exact(2)
            .map(|c| convert(i16::from_le_bytes([c[0], c[1]]) as i32))
            .collect()
    } else {
        raw.chunks_exact(4)
            .map(|c| convert(i32::from_le_bytes([c[0], c[1], c[2], c[3]])))
            .collect()
    };
    let mut metadata = Metadata {
        format: "sur".into(),
        pitch_known: true,
        ..Metadata::default()
    };
    let object_name = b.text(20, 30, "object_name")?;
    if !object_name.is_empty() {
        metadata.extra.insert("object_name".into(), object_name);
    }
    let operator = b.text(50, 20, "operator_name")?;
    if !operator.is_empty() {
        metadata.extra.insert("operator".into(), operator);
    }
    // Date: seconds, minutes, hours, day, month, year as i16 at 306..316.
    let (sec, min, hour) = (
        b.i16_le(306, "second")?,
        b.i16_le(308, "minute")?,
        b.i16_le(310, "hour")?,
    );
    let (day, month, year) = (
        b.i16_le(312, "day")?,
        b.i16_le(314, "month")?,
        b.i16_le(316, "year")?,
    );
    if year > 0 && (1..=12).contains(&month) && (1..=31).contains(&day) {
        metadata.date = Some(format!(
            "{year:04}-{month:02}-{day:02}T{hour:02}:{min:02}:{sec:02}"
        ));
    }
    metadata
        .extra
        .insert("compressed".into(), compressed.to_string());
    metadata
        .extra
        .insert("offset_z_um".into(), offset_um.to_string());
    Ok(Surface {
        width,
        height,
        pitch_x_um: spacing_x * ux,
        pitch_y_um: spacing_y * uy,
        heights_um,
        metadata,
    })
}

/// DSCOMPRESSED zone: u32 stream count, (raw_len, zip_len) u32 pairs, then the zlib streams;
/// the inflated streams concatenated must be exactly `expected` bytes.
fn inflate_streams(zone: &[u8], expected: usize) -> Result<Vec<u8>> {
    let z = Bytes::new(zone);
    let count = z.u32_le(0, "compressed stream count")? as usize;
    let table_len = count
        .checked_mul(8)
        .and_then(|v| v.checked_add(4))
        .filter(|&v| v <= zone.len())
        .with_context(|| {
            format!(
                "compressed stream count {count} does not fit in the {}-byte compressed zone",
                zone.len()
            )
        })?;
    // The table first (every length checked against the zone and the expected total), then
    // the streams inflated in parallel: each is an independent zlib stream.
    let mut streams = Vec::with_capacity(count);
    let (mut pos, mut total) = (table_len, 0usize);
    for i in 0..count {
        let raw_len = z.u32_le(4 + 8 * i, "stream raw length")? as usize;
        let zip_len = z.u32_le(8 + 8 * i, "stream compressed length")? as usize;
        total = match total.checked_add(raw_len) {
            Some(t) if t <= expected => t,
            _ => bail!("compressed stream {i} inflates past the {expected} bytes of point data"),
        };
        let stream = z.slice(pos, zip_len, "compressed stream")?;
        pos += zip_len;
        streams.push((i, raw_len, stream));
    }
    let parts: Vec<Vec<u8>> = streams
        .par_iter()
        .map(|&(i, raw_len, stream)| -> Result<Vec<u8>> {
            // Deflate expands at most ~1032x: a lying raw length cannot reserve more than that.
            let mut part = Vec::with_capacity(raw_len.min(stream.len().saturating_mul(1032)));
            // Bound the inflation by the declared length (+1 to detect a lying length).
            flate2::read::ZlibDecoder::new(stream)
                .take(raw_len as u64 + 1)
                .read_to_end(&mut part)
                .with_context(|| format!("compressed stream {i}: zlib data corrupt"))?;
            if part.len() != raw_len {
                bail!(
                    "compressed stream {i}: inflated to {} bytes, header says {raw_len}",
                    part.len()
                );
            }
            Ok(part)
        })
        .collect::<Result<_>>()?;
    let out = parts.concat();
    if out.len() != expected {
        bail!(
            "compressed data inflated to {} bytes, expected {expected} (points x bytes per point)",
            out.len()
        );
    }
    Ok(out)
}

/// Writes `s` as an uncompressed (or compressed) .sur byte image; for tests and fixtures.
#[doc(hidden)]
pub fn encode_for_tests(s: &Surface, compressed: bool, non_measured: bool) -> Vec<u8> {
    let mut h = vec![0u8; HEADER_LEN];
    let put = |h: &mut Vec<u8>, o: usize, b: &[u8]| h[o..o + b.len()].copy_from_slice(b);
    put(
        &mut h,
        0,
        if compressed {
            b"DSCOMPRESSED"
        } else {
            b"DIGITAL SURF"
        },
    );
    put(&mut h, 14, &1i16.to_le_bytes());
    put(&mut h, 16, &1i16.to_le_bytes());
    put(&mut h, 18, &2i16.to_le_bytes());
    put(&mut h, 86, &(non_measured as i16).to_le_bytes());
    put(&mut h, 98, &32i16.to_le_bytes());
    let spacing_z = 1e-3f32; // nm steps in um
    let raw: Vec<i32> = s
        .heights_um
        .iter()
        .map(|&z| {
            if z.is_nan() {
                i32::MIN
            } else {
                (z / spacing_z as f64).round() as i32
            }
        })
        .collect();
    let min = raw
        .iter()
        .copied()
        .filter(|&v| v != i32::MIN)
        .min()
        .unwrap_or(0);
    let raw: Vec<i32> = raw
        .iter()
        .map(|&v| if v == i32::MIN { min - 2 } else { v })
        .collect();
    put(&mut h, 100, &min.to_le_bytes());
    put(&mut h, 108, &(s.width as i32).to_le_bytes());
    put(&mut h, 112, &(s.height as i32).to_le_bytes());
    put(&mut h, 116, &((s.width * s.height) as i32).to_le_bytes());
    put(&mut h, 120, &(s.pitch_x_um as f32).to_le_bytes());
    put(&mut h, 124, &(s.pitch_y_um as f32).to_le_bytes());
    put(&mut h, 128, &spacing_z.to_le_bytes());
    for o in [180, 196, 212, 228, 244, 260] {
        put(&mut h, o, b"\xb5m");
    }
    let mut data: Vec<u8> = raw.iter().flat_map(|v| v.to_le_bytes()).collect();
    if compressed {
        use std::io::Write;
        // Two streams, to exercise the stream table.
        let half = data.len() / 2;
        let mut zone = Vec::new();
        let parts = [&data[..half], &data[half..]];
        let zipped: Vec<Vec<u8>> = parts
            .iter()
            .map(|p| {
                let mut e =
                    flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::fast());
                e.write_all(p).expect("write to Vec");
                e.finish().expect("finish to Vec")
            })
            .collect();
        zone.extend_from_slice(&2u32.to_le_bytes());
        for (p, zp) in parts.iter().zip(&zipped) {
            zone.extend_from_slice(&(p.len() as u32).to_le_bytes());
            zone.extend_from_slice(&(zp.len() as u32).to_le_bytes());
        }
        for zp in &zipped {
            zone.extend_from_slice(zp);
        }
        put(&mut h, 324, &(zone.len() as u32).to_le_bytes());
        data = zone;
    }
    h.extend_from_slice(&data);
    h
}
