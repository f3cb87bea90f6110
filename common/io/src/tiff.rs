//! Float32 TIFF out: one grey channel of heights in micrometres, what ImageJ/Fiji,
//! MountainsMap and Python's tifffile open as a height image.
//!
//! Baseline TIFF 6.0, little-endian, uncompressed, `SampleFormat = 3` (IEEE float),
//! `BitsPerSample = 32`, strips of whole rows; the first stored row is surfstream's row 0.
//! The pitch goes in `XResolution` / `YResolution` (pixels per centimetre,
//! `ResolutionUnit = 3`) and, exactly, in `ImageDescription` as JSON
//! (`{"pitch_um": {"x": .., "y": ..}, "height_unit": "um", ...}`). NaN marks points not
//! measured.

use std::io::Write;
use std::path::Path;

use anyhow::{bail, Context, Result};

use crate::formats::Surface;

/// Rows per strip: strips of about 64 KiB, as libtiff writes them.
fn rows_per_strip(cols: usize) -> usize {
    (65536 / (cols * 4)).max(1)
}

/// `v` as a TIFF RATIONAL (u32 / u32), as exact as the u32 numerator allows.
fn rational(v: f64) -> (u32, u32) {
    let mut den: u64 = 1_000_000;
    while den > 1 && v * den as f64 > u32::MAX as f64 {
        den /= 10;
    }
    let num = (v * den as f64).round().clamp(1.0, u32::MAX as f64) as u32;
    (num, den as u32)
}

/// Writes `s` as a float32 TIFF (see the module doc).
pub fn write(path: &Path, s: &Surface) -> Result<()> {
    let (rows, cols) = (s.height, s.width);
    if rows == 0 || cols == 0 || s.heights_um.len() != rows * cols {
        bail!(
            "{}: cannot write a {rows} x {cols} px surface with {} heights",
            path.display(),
            s.heights_um.len()
        );
    }
    let data_len = rows as u64 * cols as u64 * 4;
    if data_len > u32::MAX as u64 / 2 {
        bail!(
            "{}: {rows} x {cols} px is too large for a classic TIFF (4 GiB offsets); write .x3p or .npy",
            path.display()
        );
    }
    let description = serde_json::json!({
        "pitch_um": { "x": s.pitch_x_um, "y": s.pitch_y_um },
        "pitch_known": s.metadata.pitch_known,
        "height_unit": "um",
        "axes": "row 0 = first stored row = smallest y",
        "writer": concat!("surfstream ", env!("CARGO_PKG_VERSION")),
    })
    .to_string();
    let mut desc = description.into_bytes();
    desc.push(0);

    let rps = rows_per_strip(cols);
    let strips = rows.div_ceil(rps);
    // Layout: header (8), pixel data, then the out-of-line tag values, then the IFD.
    let data_off: u64 = 8;
    let mut extra: Vec<u8> = Vec::new();
    let extra_off = data_off + data_len;
    let put_extra = |bytes: &[u8], extra: &mut Vec<u8>| -> u32 {
        if extra.len() % 2 == 1 {
            extra.push(0); // word alignment
        }
        let at = extra_off + extra.len() as u64;
        extra.extend_from_slice(bytes);
        at as u32
    };
    let strip_offsets: Vec<u8> = (0..strips)
        .flat_map(|k| ((data_off + (k * rps * cols * 4) as u64) as u32).to_le_bytes())
        .collect();
    let strip_counts: Vec<u8> = (0..strips)
        .flat_map(|k| (((rps.min(rows - k * rps)) * cols * 4) as u32).to_le_bytes())
        .collect();
    let rat = |pitch_um: f64| {
        let (n, d) = rational(1e4 / pitch_um);
        [n.to_le_bytes(), d.to_le_bytes()].concat()
    };
    let desc_at = put_extra(&desc, &mut extra);
    let xres_at = put_extra(&rat(s.pitch_x_um), &mut extra);
    let yres_at = put_extra(&rat(s.pitch_y_um), &mut extra);
    let (offsets_value, counts_value) = if strips == 1 {
        (
            u32::from_le_bytes(strip_offsets[..4].try_into().unwrap_or_default()),
            u32::from_le_bytes(strip_counts[..4].try_into().unwrap_or_default()),
        )
    } else {
        (
            put_extra(&strip_offsets, &mut extra),
            put_extra(&strip_counts, &mut extra),
        )
    };
    const SHORT: u16 = 3;
    const LONG: u16 = 4;
    const ASCII: u16 = 2;
    const RATIONAL: u16 = 5;
    // (tag, type, count, value or offset), in ascending tag order.
    let entries: [(u16, u16, u32, u32); 14] = [
        (256, LONG, 1, cols as u32),
        (257, LONG, 1, rows as u32),
        (258, SHORT, 1, 32),
        (259, SHORT, 1, 1),
        (262, SHORT, 1, 1),
        (270, ASCII, desc.len() as u32, desc_at),
        (273, LONG, strips as u32, offsets_value),
        (277, SHORT, 1, 1),
        (278, LONG, 1, rps as u32),
        (279, LONG, strips as u32, counts_value),
        (282, RATIONAL, 1, xres_at),
        (283, RATIONAL, 1, yres_at),
        (296, SHORT, 1, 3),
        (339, SHORT, 1, 3),
    ];
    if extra.len() % 2 == 1 {
        extra.push(0);
    }
    let ifd_off = extra_off + extra.len() as u64;
    let mut ifd = Vec::with_capacity(2 + entries.len() * 12 + 4);
    ifd.extend_from_slice(&(entries.len() as u16).to_le_bytes());
    for (tag, typ, count, value) in entries {
        ifd.extend_from_slice(&tag.to_le_bytes());
        ifd.extend_from_slice(&typ.to_le_bytes());
        ifd.extend_from_slice(&count.to_le_bytes());
        if typ == SHORT && count == 1 {
            ifd.extend_from_slice(&(value as u16).to_le_bytes());
            ifd.extend_from_slice(&[0, 0]);
        } else {
            ifd.extend_from_slice(&value.to_le_bytes());
        }
    }
    ifd.extend_from_slice(&0u32.to_le_bytes()); // no next IFD
    let mut head = Vec::with_capacity(8);
    head.extend_from_slice(b"II*\0");
    head.extend_from_slice(&(ifd_off as u32).to_le_bytes());
    surfstream_core::fsutil::write_atomic(path, |w| {
        let fail = || format!("{}: write failed", path.display());
        w.write_all(&head).with_context(fail)?;
        let mut buf = Vec::with_capacity(cols * 4);
        for row in s.heights_um.chunks(cols) {
            buf.clear();
            for &z in row {
                buf.extend_from_slice(&(z as f32).to_le_bytes());
            }
            w.write_all(&buf).with_context(fail)?;
        }
        w.write_all(&extra).with_context(fail)?;
        w.write_all(&ifd).with_context(fail)?;
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::formats::Metadata;

    /// Reads back what [`write`] wrote, by the TIFF 6.0 layout (a reader of its own, so the
    /// test fails when an offset or a count is wrong).
    fn read_back(bytes: &[u8]) -> (usize, usize, Vec<f32>, String) {
        let u16_at = |o: usize| u16::from_le_bytes([bytes[o], bytes[o + 1]]);
        let u32_at = |o: usize| u32::from_le_bytes(bytes[o..o + 4].try_into().unwrap());
        assert_eq!(&bytes[..4], b"II*\0");
        let ifd = u32_at(4) as usize;
        let n = u16_at(ifd) as usize;
        let mut tags = std::collections::BTreeMap::new();
        for k in 0..n {
            let e = ifd + 2 + 12 * k;
            tags.insert(u16_at(e), (u16_at(e + 2), u32_at(e + 4), u32_at(e + 8)));
        }
        let (cols, rows) = (tags[&256].2 as usize, tags[&257].2 as usize);
        assert_eq!(tags[&258].2 & 0xffff, 32);
        assert_eq!(tags[&339].2 & 0xffff, 3);
        let strips = tags[&273].1 as usize;
        let offsets: Vec<usize> = if strips == 1 {
            vec![tags[&273].2 as usize]
        } else {
            (0..strips)
                .map(|k| u32_at(tags[&273].2 as usize + 4 * k) as usize)
                .collect()
        };
        let counts: Vec<usize> = if strips == 1 {
            vec![tags[&279].2 as usize]
        } else {
            (0..strips)
                .map(|k| u32_at(tags[&279].2 as usize + 4 * k) as usize)
                .collect()
        };
        let mut v = Vec::new();
        for (o, c) in offsets.iter().zip(&counts) {
            for q in bytes[*o..*o + *c].chunks_exact(4) {
                v.push(f32::from_le_bytes(q.try_into().unwrap()));
            }
        }
        let (_, len, at) = tags[&270];
        let desc =
            String::from_utf8(bytes[at as usize..at as usize + len as usize - 1].to_vec()).unwrap();
        (rows, cols, v, desc)
    }

    #[test]
    fn float_tiff_reads_back_by_the_layout() {
        let d = tempfile::tempdir().unwrap();
        for (rows, cols) in [(3usize, 2usize), (700, 90)] {
            let heights: Vec<f64> = (0..rows * cols)
                .map(|i| {
                    if i == 1 {
                        f64::NAN
                    } else {
                        i as f64 * 0.25 - 7.0
                    }
                })
                .collect();
            let s = Surface {
                width: cols,
                height: rows,
                pitch_x_um: 0.5,
                pitch_y_um: 2.2797945189999997,
                heights_um: heights.clone(),
                metadata: Metadata {
                    pitch_known: true,
                    ..Metadata::default()
                },
            };
            let p = d.path().join("a.tif");
            write(&p, &s).unwrap();
            let (r, c, v, desc) = read_back(&std::fs::read(&p).unwrap());
            assert_eq!((r, c), (rows, cols));
            assert_eq!(v.len(), heights.len());
            assert!(v[1].is_nan());
            assert_eq!(v[rows * cols - 1], heights[rows * cols - 1] as f32);
            let j: serde_json::Value = serde_json::from_str(&desc).unwrap();
            assert_eq!(j["pitch_um"]["y"], 2.2797945189999997);
        }
    }

    #[test]
    fn rationals_keep_the_pitch() {
        let (n, d) = rational(1e4 / 0.5);
        assert_eq!(n as f64 / d as f64, 20000.0);
        let (n, d) = rational(1e4 / 0.01);
        assert!((n as f64 / d as f64 - 1e6).abs() < 1e-3);
    }
}
