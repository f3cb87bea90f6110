//! ISO 25178-71 Surface Data File `.sdf` (the EU BCR format it grew from: `aBCR-1.0`), written
//! by many profilers and by MountainsMap / Gwyddion / surfalize as an exchange format.
//!
//! Layout as ISO 25178-71 describes it (learned from SurfaceTopography's `SDF.py`, MIT, and
//! checked against surfalize's reader, GPL, behaviour only):
//! - ASCII variant, magic `aISO-1.0` or `aBCR-1.0`, then a header of `Name = value` lines:
//!   ManufacID, CreateDate, ModDate, NumPoints (points per profile, x), NumProfiles (y),
//!   Xscale, Yscale, Zscale (metres per unit), Zresolution, Compression, DataType, CheckType;
//!   a line `*` ends it. Then the data section: NumPoints * NumProfiles whitespace-separated
//!   numbers, profile after profile, `BAD` = not measured; `*` ends it; an optional trailer
//!   (free text / tags) ends with a last `*`.
//! - Binary variant, magic `bISO-1.0` or `bBCR-1.0`, then an 81-byte little-endian header
//!   (the magic included): ManufacID (10 bytes), CreateDate (12), ModDate (12), NumPoints u16,
//!   NumProfiles u16, Xscale, Yscale, Zscale, Zresolution f64, Compression u8, DataType u8,
//!   CheckType u8; then the points in the DataType: 0 u8, 1 u16, 2 u32, 3 f32, 4 i8, 5 i16,
//!   6 i32, 7 f64.
//! - Not measured: NaN (float types), the type's minimum for i16 / i32 and its maximum for
//!   u16 / u32 (as Gwyddion's `sdfile.c` does), `BAD` in ASCII files.
//! - height = value * Zscale metres; pitch = Xscale / Yscale metres.
//!
//! Profile 0 is y = 0 and rows are kept in file order, so row index grows with y.
//! Compressed files (Compression != 0) are refused.

use anyhow::{bail, Context, Result};

use super::bytes::{checked_size, Bytes};
use super::{Metadata, Surface};

const BINARY_HEADER_LEN: usize = 81;

pub fn parse(data: &[u8]) -> Result<Surface> {
    let magic = data.get(..8).unwrap_or(data);
    match magic {
        b"aISO-1.0" | b"aBCR-1.0" => parse_ascii(data),
        b"bISO-1.0" | b"bBCR-1.0" => parse_binary(data),
        _ => bail!(
            "magic: expected 'aISO-1.0', 'aBCR-1.0' (ASCII) or 'bISO-1.0', 'bBCR-1.0' (binary)"
        ),
    }
}

/// The header fields every reader needs, from either variant.
struct Header {
    num_points: usize,
    num_profiles: usize,
    xscale: f64,
    yscale: f64,
    zscale: f64,
    data_type: u8,
    compression: i64,
}

impl Header {
    fn check(&self) -> Result<usize> {
        if self.num_points == 0 || self.num_profiles == 0 {
            bail!(
                "fields 'NumPoints' x 'NumProfiles' are {} x {}, expected positive",
                self.num_points,
                self.num_profiles
            );
        }
        for (name, v) in [("Xscale", self.xscale), ("Yscale", self.yscale)] {
            if !v.is_finite() || v <= 0.0 {
                bail!("field '{name}' is {v}, expected a finite positive number (metres)");
            }
        }
        if !self.zscale.is_finite() || self.zscale == 0.0 {
            bail!(
                "field 'Zscale' is {}, expected a finite non-zero number (metres)",
                self.zscale
            );
        }
        if self.data_type > 7 {
            bail!("field 'DataType' is {}, expected 0..=7", self.data_type);
        }
        if self.compression != 0 {
            bail!(
                "field 'Compression' is {}: compressed SDF is not supported (expected 0)",
                self.compression
            );
        }
        checked_size(
            &[self.num_points, self.num_profiles],
            "NumPoints * NumProfiles",
        )
    }

    /// The raw value that marks a point not measured, for the integer types that have one.
    fn invalid_marker(&self) -> Option<f64> {
        match self.data_type {
            1 => Some(u16::MAX as f64),
            2 => Some(u32::MAX as f64),
            5 => Some(i16::MIN as f64),
            6 => Some(i32::MIN as f64),
            _ => None,
        }
    }

    fn surface(&self, raw: Vec<f64>, mut metadata: Metadata) -> Surface {
        let marker = self.invalid_marker();
        let scale_um = self.zscale * 1e6;
        let heights_um = raw
            .into_iter()
            .map(|v| {
                if Some(v) == marker {
                    f64::NAN
                } else {
                    v * scale_um
                }
            })
            .collect();
        metadata.format = "sdf".into();
        metadata.pitch_known = true;
        metadata
            .extra
            .insert("DataType".into(), self.data_type.to_string());
        Surface {
            width: self.num_points,
            height: self.num_profiles,
            pitch_x_um: self.xscale * 1e6,
            pitch_y_um: self.yscale * 1e6,
            heights_um,
            metadata,
        }
    }
}

fn parse_ascii(data: &[u8]) -> Result<Surface> {
    let text = std::str::from_utf8(&data[8..]).context("ASCII SDF: not ASCII / UTF-8 text")?;
    let (header_text, rest) = text
        .split_once('*')
        .context("header: no '*' line ends the header")?;
    let mut metadata = Metadata::default();
    let mut fields = std::collections::BTreeMap::new();
    for line in header_text.lines() {
        if line.trim().is_empty() {
            continue;
        }
        let (name, value) = line
            .split_once('=')
            .with_context(|| format!("header line '{}': expected 'Name = value'", line.trim()))?;
        fields.insert(name.trim().to_string(), value.trim().to_string());
    }
    let get = |name: &str| -> Result<&str> {
        fields
            .get(name)
            .map(|s| s.as_str())
            .with_context(|| format!("header field '{name}' is missing"))
    };
    let int = |name: &str| -> Result<i64> {
        let v = get(name)?;
        v.parse::<i64>()
            .with_context(|| format!("header field '{name}' is '{v}', expected an integer"))
    };
    let real = |name: &str| -> Result<f64> {
        let v = get(name)?;
        v.parse::<f64>()
            .with_context(|| format!("header field '{name}' is '{v}', expected a number"))
    };
    let count = |name: &str| -> Result<usize> {
        let v = int(name)?;
        usize::try_from(v)
            .with_context(|| format!("header field '{name}' is {v}, expected positive"))
    };
    let data_type = int("DataType")?;
    let header = Header {
        num_points: count("NumPoints")?,
        num_profiles: count("NumProfiles")?,
        xscale: real("Xscale")?,
        yscale: real("Yscale")?,
        zscale: real("Zscale")?,
        data_type: u8::try_from(data_type).unwrap_or(u8::MAX),
        compression: if fields.contains_key("Compression") {
            int("Compression")?
        } else {
            0
        },
    };
    let n = header.check()?;
    let (data_text, trailer) = rest
        .split_once('*')
        .context("data section: no '*' line ends it")?;
    // Values are pushed one by one: the header's count is never used to reserve memory.
    let mut raw = Vec::new();
    for (i, token) in data_text.split_ascii_whitespace().enumerate() {
        if i >= n {
            bail!("data section: more than NumPoints x NumProfiles = {n} values");
        }
        let v = if token.eq_ignore_ascii_case("BAD") {
            f64::NAN
        } else {
            token
                .parse::<f64>()
                .with_context(|| format!("data value {i} is '{token}', expected a number or BAD"))?
        };
        raw.push(v);
    }
    if raw.len() != n {
        bail!(
            "data section: {} values, expected NumPoints x NumProfiles = {} x {} = {n}",
            raw.len(),
            header.num_points,
            header.num_profiles
        );
    }
    for key in ["ManufacID", "CreateDate", "ModDate"] {
        if let Some(v) = fields.get(key) {
            metadata.extra.insert(key.into(), v.clone());
        }
    }
    let trailer = trailer.trim().trim_end_matches('*').trim();
    if !trailer.is_empty() {
        metadata.extra.insert("trailer".into(), trailer.to_string());
    }
    Ok(header.surface(raw, metadata))
}

fn parse_binary(data: &[u8]) -> Result<Surface> {
    let b = Bytes::new(data);
    let f64_le = |o: usize, f: &str| -> Result<f64> {
        let s = b.slice(o, 8, f)?;
        let mut a = [0u8; 8];
        a.copy_from_slice(s);
        Ok(f64::from_le_bytes(a))
    };
    let u16_le = |o: usize, f: &str| -> Result<usize> {
        let s = b.slice(o, 2, f)?;
        Ok(u16::from_le_bytes([s[0], s[1]]) as usize)
    };
    let header = Header {
        num_points: u16_le(42, "NumPoints")?,
        num_profiles: u16_le(44, "NumProfiles")?,
        xscale: f64_le(46, "Xscale")?,
        yscale: f64_le(54, "Yscale")?,
        zscale: f64_le(62, "Zscale")?,
        compression: b.slice(78, 1, "Compression")?[0] as i64,
        data_type: b.slice(79, 1, "DataType")?[0],
    };
    let n = header.check()?;
    let item = [1usize, 2, 4, 4, 1, 2, 4, 8][header.data_type as usize];
    let len = checked_size(&[n, item], "point data size")?;
    let raw_bytes = b.slice(
        BINARY_HEADER_LEN,
        len,
        "point data (NumPoints x NumProfiles)",
    )?;
    let raw: Vec<f64> = raw_bytes
        .chunks_exact(item)
        .map(|c| match header.data_type {
            0 => c[0] as f64,
            1 => u16::from_le_bytes([c[0], c[1]]) as f64,
            2 => u32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64,
            3 => f32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64,
            4 => c[0] as i8 as f64,
            5 => i16::from_le_bytes([c[0], c[1]]) as f64,
            6 => i32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64,
            _ => {
                let mut a = [0u8; 8];
                a.copy_from_slice(c);
                f64::from_le_bytes(a)
            }
        })
        .collect();
    let mut metadata = Metadata::default();
    metadata
        .extra
        .insert("ManufacID".into(), b.text(8, 10, "ManufacID")?);
    metadata
        .extra
        .insert("CreateDate".into(), b.text(18, 12, "CreateDate")?);
    Ok(header.surface(raw, metadata))
}
