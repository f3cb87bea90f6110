//! Float32 TIFF out: one grey channel of heights in micrometres, what ImageJ/Fiji,
//! MountainsMap and Python's tifffile open as a height image; and TIFF in ([`parse`]): ours
//! with its pitch and unit, any other single-channel uncompressed height TIFF (strips or tiles)
//! with a warning.
//!
//! Baseline TIFF 6.0, little-endian, uncompressed, `SampleFormat = 3` (IEEE float),
//! `BitsPerSample = 32`, strips of whole rows; the first stored row is surfstream's row 0.
//! The pitch goes in `XResolution` / `YResolution` (pixels per centimetre,
//! `ResolutionUnit = 3`) and, exactly, in `ImageDescription` as JSON
//! (`{"pitch_um": {"x": .., "y": ..}, "height_unit": "um", ...}`). NaN marks points not
//! measured.
//!
//! Who reads the pitch (issue 35): tifffile and ImageJ/Fiji take `XResolution` /
//! `YResolution` with `ResolutionUnit` (ImageJ shows it in cm). Gwyddion (2.62, its generic
//! `tiffbig` loader) reads no physical size from a plain TIFF at all: the dimensions come from
//! its import dialog, or from its last settings when run non-interactively (a 512 px map came
//! in 1 m wide, unitless). Gwyddion users should take `.gsf` (Gwyddion reads its pitch) or
//! `.x3p`.

use std::io::Write;
use std::path::Path;

use anyhow::{bail, Context, Result};

use crate::formats::{Metadata, Surface};

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

/// surfstream's `ImageDescription` as written. Fields in key order (the text has always listed
/// its keys sorted).
#[derive(serde::Serialize)]
struct TiffDescription<'a> {
    axes: &'a str,
    height_unit: &'a str,
    pitch_known: bool,
    pitch_um: PitchUm,
    writer: &'a str,
}

/// The pitch in um: x = spacing of the columns, y = of the rows.
#[derive(serde::Serialize)]
struct PitchUm {
    x: f64,
    y: f64,
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
    let description = serde_json::to_string(&TiffDescription {
        axes: "row 0 = first stored row = smallest y",
        height_unit: "um",
        pitch_known: s.metadata.pitch_known,
        pitch_um: PitchUm {
            x: s.pitch_x_um,
            y: s.pitch_y_um,
        },
        writer: concat!("surfstream ", env!("CARGO_PKG_VERSION")),
    })?;
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

/// The pixel bytes of a stripped image, `need` bytes in all, from `StripOffsets` (273) and
/// `StripByteCounts` (279): `values(tag)` reads a tag, `bytes(offset, count)` the file.
fn strips<'d>(
    values: &impl Fn(u16) -> Result<Option<Vec<u64>>>,
    need: usize,
    bytes: impl Fn(usize, usize) -> Option<&'d [u8]>,
) -> Result<Vec<u8>> {
    let offsets = values(273)?.context("no StripOffsets (tag 273)")?;
    let counts = values(279)?.context("no StripByteCounts (tag 279)")?;
    if offsets.len() != counts.len() {
        bail!(
            "{} StripOffsets but {} StripByteCounts",
            offsets.len(),
            counts.len()
        );
    }
    let mut raw = Vec::with_capacity(need);
    for (&o, &c) in offsets.iter().zip(&counts) {
        let (o, c) = (o as usize, c as usize);
        let strip = bytes(o, c).with_context(|| {
            format!("a strip of {c} bytes at byte {o} runs past the end of the file")
        })?;
        raw.extend_from_slice(strip);
        if raw.len() >= need {
            break;
        }
    }
    if raw.len() < need {
        bail!(
            "the strips (StripByteCounts, tag 279) hold {} bytes, expected {need} (ImageLength x ImageWidth x bytes per sample)",
            raw.len()
        );
    }
    Ok(raw)
}

/// The pixel bytes of a tiled image in row-major order, from `TileWidth` (322), `TileLength`
/// (323), `TileOffsets` (324) and `TileByteCounts` (325): tiles left to right, then top to
/// bottom, each `TileWidth x TileLength` samples, the right and bottom ones padded.
fn tiles<'d>(
    values: &impl Fn(u16) -> Result<Option<Vec<u64>>>,
    (rows, cols, bytes_per): (usize, usize, usize),
    bytes: impl Fn(usize, usize) -> Option<&'d [u8]>,
) -> Result<Vec<u8>> {
    let one = |tag: u16, name: &str| -> Result<usize> {
        let v = values(tag)?.with_context(|| format!("a tiled TIFF without {name} (tag {tag})"))?;
        Ok(v[0] as usize)
    };
    let (tw, tl) = (one(322, "TileWidth")?, one(323, "TileLength")?);
    // TIFF 6.0: multiples of 16; any positive size is read.
    if tw == 0 || tl == 0 || tw > 1 << 16 || tl > 1 << 16 {
        bail!("TileWidth {tw} x TileLength {tl}: expected positive tile sizes up to 65536");
    }
    let offsets = values(324)?.context("a tiled TIFF without TileOffsets (tag 324)")?;
    let counts = values(325)?.context("a tiled TIFF without TileByteCounts (tag 325)")?;
    let (across, down) = (cols.div_ceil(tw), rows.div_ceil(tl));
    if offsets.len() != across * down || counts.len() != offsets.len() {
        bail!(
            "{} TileOffsets and {} TileByteCounts, expected {across} x {down} = {} tiles of {tw} x {tl} for {rows} x {cols} px",
            offsets.len(),
            counts.len(),
            across * down
        );
    }
    let tile_bytes = tw * tl * bytes_per;
    let mut raw = vec![0u8; rows * cols * bytes_per];
    for (k, (&o, &c)) in offsets.iter().zip(&counts).enumerate() {
        let (o, c) = (o as usize, c as usize);
        if c < tile_bytes {
            bail!("tile {k}: TileByteCounts {c}, expected {tile_bytes} ({tw} x {tl} x {bytes_per}; only uncompressed tiles are read)");
        }
        let tile = bytes(o, tile_bytes).with_context(|| {
            format!("tile {k}: {tile_bytes} bytes at byte {o} run past the end of the file")
        })?;
        let (r0, c0) = ((k / across) * tl, (k % across) * tw);
        let width = tw.min(cols - c0) * bytes_per;
        for r in 0..tl.min(rows - r0) {
            let to = ((r0 + r) * cols + c0) * bytes_per;
            raw[to..to + width].copy_from_slice(&tile[r * tw * bytes_per..][..width]);
        }
    }
    Ok(raw)
}

/// One IFD entry: (type, count, the 4 value bytes or the offset).
type Entry = (u16, u32, [u8; 4]);

/// Reads a TIFF image of heights: the first IFD, one sample per pixel, uncompressed strips or
/// tiles, IEEE float (32 / 64 bit) or integer (8 / 16 / 32 bit, signed or not), either byte
/// order.
/// The pitch and height unit are those of surfstream's `ImageDescription` JSON when it is
/// there; else the pitch from `XResolution` / `YResolution` with `ResolutionUnit` inch or cm,
/// and heights read as um with a warning (a plain TIFF has no height unit); without a
/// resolution unit the pitch is unknown (1 um, `pitch_known` false).
pub fn parse(data: &[u8]) -> Result<Surface> {
    let le = match data.get(..4) {
        Some(b"II*\0") => true,
        Some(b"MM\0*") => false,
        Some(b"II+\0") | Some(b"MM\0+") => bail!("BigTIFF is not read: save a classic TIFF"),
        _ => bail!("not a TIFF file (expected the magic 'II*\\0' or 'MM\\0*')"),
    };
    let u16_at = |o: usize| -> Result<u16> {
        let b: [u8; 2] = data
            .get(o..o + 2)
            .and_then(|b| b.try_into().ok())
            .with_context(|| format!("file truncated at byte {o} (a 16-bit field)"))?;
        Ok(if le {
            u16::from_le_bytes(b)
        } else {
            u16::from_be_bytes(b)
        })
    };
    let u32_at = |o: usize| -> Result<u32> {
        let b: [u8; 4] = data
            .get(o..o + 4)
            .and_then(|b| b.try_into().ok())
            .with_context(|| format!("file truncated at byte {o} (a 32-bit field)"))?;
        Ok(if le {
            u32::from_le_bytes(b)
        } else {
            u32::from_be_bytes(b)
        })
    };
    let ifd = u32_at(4)? as usize;
    let n = u16_at(ifd)? as usize;
    let mut tags = std::collections::BTreeMap::<u16, Entry>::new();
    for k in 0..n {
        let e = ifd + 2 + 12 * k;
        let value: [u8; 4] = data
            .get(e + 8..e + 12)
            .and_then(|b| b.try_into().ok())
            .with_context(|| format!("IFD entry {k} truncated"))?;
        tags.insert(u16_at(e)?, (u16_at(e + 2)?, u32_at(e + 4)?, value));
    }
    let word = |v: [u8; 4], typ: u16| -> u32 {
        match (typ, le) {
            (3, true) => u16::from_le_bytes([v[0], v[1]]) as u32,
            (3, false) => u16::from_be_bytes([v[0], v[1]]) as u32,
            (_, true) => u32::from_le_bytes(v),
            (_, false) => u32::from_be_bytes(v),
        }
    };
    // The values of a SHORT / LONG tag (inline when they fit in 4 bytes).
    let values = |tag: u16| -> Result<Option<Vec<u64>>> {
        let Some(&(typ, count, v)) = tags.get(&tag) else {
            return Ok(None);
        };
        let size = match typ {
            3 => 2,
            4 => 4,
            _ => bail!("tag {tag}: type {typ}, expected SHORT (3) or LONG (4)"),
        };
        let count = count as usize;
        if count == 0 {
            bail!("tag {tag}: no values");
        }
        if count * size <= 4 {
            return Ok(Some(
                (0..count)
                    .map(|k| {
                        let mut b = [0u8; 4];
                        b[..size].copy_from_slice(&v[k * size..(k + 1) * size]);
                        u64::from(word(b, typ))
                    })
                    .collect(),
            ));
        }
        let at = word(v, 4) as usize;
        if data.len() < at || (data.len() - at) / size < count {
            bail!("tag {tag}: {count} values at byte {at} run past the end of the file");
        }
        (0..count)
            .map(|k| {
                Ok(if size == 2 {
                    u64::from(u16_at(at + 2 * k)?)
                } else {
                    u64::from(u32_at(at + 4 * k)?)
                })
            })
            .collect::<Result<Vec<u64>>>()
            .map(Some)
    };
    let one = |tag: u16, name: &str, default: Option<u64>| -> Result<u64> {
        match values(tag)? {
            Some(v) => Ok(v[0]),
            None => default.with_context(|| format!("no {name} (tag {tag})")),
        }
    };
    let cols = one(256, "ImageWidth", None)? as usize;
    let rows = one(257, "ImageLength", None)? as usize;
    let bits = one(258, "BitsPerSample", Some(1))?;
    let compression = one(259, "Compression", Some(1))?;
    let samples = one(277, "SamplesPerPixel", Some(1))?;
    let format = one(339, "SampleFormat", Some(1))?;
    if compression != 1 {
        bail!("Compression {compression}: only uncompressed TIFF (Compression 1) is read");
    }
    if samples != 1 {
        bail!("SamplesPerPixel {samples}: a height map has one sample per pixel (a colour image is not heights)");
    }
    let bytes_per = match (format, bits) {
        (3, 32) | (1, 32) | (2, 32) => 4,
        (3, 64) => 8,
        (1, 16) | (2, 16) => 2,
        (1, 8) | (2, 8) => 1,
        _ => bail!(
            "SampleFormat {format} with BitsPerSample {bits}: expected float 32/64 bit or integers of 8/16/32 bit"
        ),
    };
    if rows == 0 || cols == 0 {
        bail!("an empty image ({rows} x {cols}, rows x cols)");
    }
    let points = rows
        .checked_mul(cols)
        .filter(|p| p.checked_mul(bytes_per).is_some_and(|b| b <= data.len()))
        .with_context(|| {
            format!(
                "ImageLength {rows} x ImageWidth {cols} x {bytes_per} bytes is more than the file's {} bytes",
                data.len()
            )
        })?;
    let raw = if tags.contains_key(&322) || tags.contains_key(&324) {
        tiles(&values, (rows, cols, bytes_per), |o: usize, c: usize| {
            data.get(o..o.checked_add(c)?)
        })?
    } else {
        strips(&values, points * bytes_per, |o: usize, c: usize| {
            data.get(o..o.checked_add(c)?)
        })?
    };
    let mut raw = raw;
    raw.truncate(points * bytes_per);
    let heights: Vec<f64> = raw
        .chunks_exact(bytes_per)
        .map(|b| {
            let mut a = [0u8; 8];
            a[..bytes_per].copy_from_slice(b);
            if !le {
                a[..bytes_per].reverse();
            }
            match (format, bytes_per) {
                (3, 4) => f64::from(f32::from_le_bytes([a[0], a[1], a[2], a[3]])),
                (3, _) => f64::from_le_bytes(a),
                (2, 4) => f64::from(i32::from_le_bytes([a[0], a[1], a[2], a[3]])),
                (2, 2) => f64::from(i16::from_le_bytes([a[0], a[1]])),
                (2, _) => f64::from(a[0] as i8),
                (_, 4) => f64::from(u32::from_le_bytes([a[0], a[1], a[2], a[3]])),
                (_, 2) => f64::from(u16::from_le_bytes([a[0], a[1]])),
                _ => f64::from(a[0]),
            }
        })
        .collect();
    let description = tags.get(&270).and_then(|&(typ, count, v)| {
        let at = word(v, 4) as usize;
        let bytes = if count <= 4 {
            v.get(..count as usize)?
        } else {
            data.get(at..at.checked_add(count as usize)?)?
        };
        (typ == 2).then(|| {
            String::from_utf8_lossy(bytes)
                .trim_end_matches('\0')
                .to_string()
        })
    });
    let ours = description
        .as_deref()
        .and_then(|d| serde_json::from_str::<serde_json::Value>(d).ok())
        .filter(|j| j.get("pitch_um").is_some() && j.get("height_unit").is_some());
    let mut metadata = Metadata {
        format: "tif".into(),
        ..Metadata::default()
    };
    let (mut pitch_x_um, mut pitch_y_um) = (1.0, 1.0);
    if let Some(j) = &ours {
        let get = |k: &str| {
            j["pitch_um"][k]
                .as_f64()
                .filter(|v| v.is_finite() && *v > 0.0)
        };
        let (Some(x), Some(y)) = (get("x"), get("y")) else {
            bail!("ImageDescription: pitch_um.x / .y are not positive numbers");
        };
        (pitch_x_um, pitch_y_um) = (x, y);
        metadata.pitch_known = j["pitch_known"].as_bool().unwrap_or(true);
        if j["height_unit"].as_str() != Some("um") {
            bail!(
                "ImageDescription: height_unit {}, expected \"um\"",
                j["height_unit"]
            );
        }
        if let Some(w) = j["writer"].as_str() {
            metadata.extra.insert("writer".into(), w.to_string());
        }
    } else {
        let rational = |tag: u16| -> Option<f64> {
            let &(typ, _, v) = tags.get(&tag)?;
            let at = word(v, 4) as usize;
            (typ == 5).then_some(())?;
            let (n, d) = (u32_at(at).ok()?, u32_at(at + 4).ok()?);
            (n > 0 && d > 0).then(|| f64::from(n) / f64::from(d))
        };
        let unit_um = match one(296, "ResolutionUnit", Some(2))? {
            2 => Some(25_400.0),
            3 => Some(10_000.0),
            _ => None,
        };
        if let (Some(u), Some(xr), Some(yr)) = (unit_um, rational(282), rational(283)) {
            (pitch_x_um, pitch_y_um) = (u / xr, u / yr);
            metadata.pitch_known = true;
        }
        metadata.warnings.push(
            "a TIFF without surfstream's description carries no height unit: heights read as um"
                .into(),
        );
        if let Some(d) = description.filter(|d| !d.is_empty()) {
            metadata.extra.insert("description".into(), d);
        }
    }
    Ok(Surface {
        width: cols,
        height: rows,
        pitch_x_um,
        pitch_y_um,
        heights_um: heights,
        metadata,
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
            // The typed description writes the text the JSON value it replaces wrote.
            let before_typed = serde_json::json!({
                "pitch_um": { "x": s.pitch_x_um, "y": s.pitch_y_um },
                "pitch_known": true,
                "height_unit": "um",
                "axes": "row 0 = first stored row = smallest y",
                "writer": concat!("surfstream ", env!("CARGO_PKG_VERSION")),
            });
            assert_eq!(desc, before_typed.to_string());
            // And our reader: pitch exact, heights as f32, NaN kept.
            let back = parse(&std::fs::read(&p).unwrap()).unwrap();
            assert_eq!((back.height, back.width), (rows, cols));
            assert_eq!(
                (back.pitch_x_um, back.pitch_y_um),
                (0.5, 2.2797945189999997)
            );
            assert!(back.metadata.pitch_known && back.metadata.warnings.is_empty());
            for (a, b) in back.heights_um.iter().zip(&heights) {
                assert!(a.is_nan() && b.is_nan() || *a == f64::from(*b as f32));
            }
            // Every truncation fails cleanly.
            let bytes = std::fs::read(&p).unwrap();
            // (The last 4 bytes, the next-IFD pointer, are not needed.)
            for cut in [0, 4, 7, 9, bytes.len() / 2, bytes.len() - 6] {
                assert!(parse(&bytes[..cut]).is_err(), "cut at {cut}");
            }
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
