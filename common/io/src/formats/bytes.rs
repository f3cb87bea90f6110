//! Bounds-checked reads of fixed-offset binary header fields: every read out of range is an
//! error naming the field, never a panic (the readers are fuzzed).

use anyhow::{bail, Result};

/// A whole file in memory with typed, bounds-checked field reads.
pub(crate) struct Bytes<'a> {
    pub data: &'a [u8],
}

impl<'a> Bytes<'a> {
    pub fn new(data: &'a [u8]) -> Self {
        Self { data }
    }

    /// `len` bytes at `offset`, or an error naming `field`.
    pub fn slice(&self, offset: usize, len: usize, field: &str) -> Result<&'a [u8]> {
        match offset.checked_add(len) {
            Some(end) if end <= self.data.len() => Ok(&self.data[offset..end]),
            _ => bail!(
                "field '{field}' needs bytes {offset}..{} but the file has only {} bytes",
                offset as u128 + len as u128,
                self.data.len()
            ),
        }
    }

    fn array<const N: usize>(&self, offset: usize, field: &str) -> Result<[u8; N]> {
        let s = self.slice(offset, N, field)?;
        let mut a = [0u8; N];
        a.copy_from_slice(s);
        Ok(a)
    }

    pub fn u16_be(&self, o: usize, f: &str) -> Result<u16> {
        Ok(u16::from_be_bytes(self.array(o, f)?))
    }
    pub fn i16_be(&self, o: usize, f: &str) -> Result<i16> {
        Ok(i16::from_be_bytes(self.array(o, f)?))
    }
    pub fn u32_be(&self, o: usize, f: &str) -> Result<u32> {
        Ok(u32::from_be_bytes(self.array(o, f)?))
    }
    pub fn f32_be(&self, o: usize, f: &str) -> Result<f32> {
        Ok(f32::from_be_bytes(self.array(o, f)?))
    }
    pub fn u16_le(&self, o: usize, f: &str) -> Result<u16> {
        Ok(u16::from_le_bytes(self.array(o, f)?))
    }
    pub fn u64_le(&self, o: usize, f: &str) -> Result<u64> {
        Ok(u64::from_le_bytes(self.array(o, f)?))
    }
    pub fn i16_le(&self, o: usize, f: &str) -> Result<i16> {
        Ok(i16::from_le_bytes(self.array(o, f)?))
    }
    pub fn i32_le(&self, o: usize, f: &str) -> Result<i32> {
        Ok(i32::from_le_bytes(self.array(o, f)?))
    }
    pub fn u32_le(&self, o: usize, f: &str) -> Result<u32> {
        Ok(u32::from_le_bytes(self.array(o, f)?))
    }
    pub fn f32_le(&self, o: usize, f: &str) -> Result<f32> {
        Ok(f32::from_le_bytes(self.array(o, f)?))
    }
    pub fn f64_le(&self, o: usize, f: &str) -> Result<f64> {
        Ok(f64::from_le_bytes(self.array(o, f)?))
    }

    /// A fixed-width text field, trailing NULs and spaces removed; Latin-1 decoded (Digital
    /// Surf writes "µm" as the single byte 0xB5).
    pub fn text(&self, offset: usize, len: usize, field: &str) -> Result<String> {
        let s = self.slice(offset, len, field)?;
        let end = s.iter().position(|&b| b == 0).unwrap_or(s.len());
        Ok(s[..end]
            .iter()
            .map(|&b| b as char)
            .collect::<String>()
            .trim()
            .to_string())
    }

    /// Like [`Bytes::text`], but a field whose bytes are valid UTF-8 is read as UTF-8: one
    /// format, two encodings in the wild (Digital Surf writes "µm" as the Latin-1 byte 0xB5,
    /// surfalize as the UTF-8 pair 0xC2 0xB5). A lone 0xB5 is not valid UTF-8, so Latin-1
    /// files still read as Latin-1.
    pub fn text_utf8_or_latin1(&self, offset: usize, len: usize, field: &str) -> Result<String> {
        let s = self.slice(offset, len, field)?;
        let end = s.iter().position(|&b| b == 0).unwrap_or(s.len());
        match std::str::from_utf8(&s[..end]) {
            Ok(t) => Ok(t.trim().to_string()),
            Err(_) => self.text(offset, len, field),
        }
    }
}

/// `a * b * c` as usize, or an error naming what overflowed (sizes from headers are untrusted).
pub(crate) fn checked_size(parts: &[usize], what: &str) -> Result<usize> {
    let mut n: usize = 1;
    for &p in parts {
        n = match n.checked_mul(p) {
            Some(v) => v,
            None => bail!("{what}: {parts:?} overflows"),
        };
    }
    Ok(n)
}

/// Micrometres per one `unit` (a length unit name as instruments write it), or None.
pub(crate) fn length_unit_um(unit: &str) -> Option<f64> {
    let u = unit.trim();
    Some(match u {
        "m" | "Meters" | "Metres" => 1e6,
        "cm" | "CentiMeters" => 1e4,
        "mm" | "MilliMeters" => 1e3,
        "um" | "\u{b5}m" | "\u{3bc}m" | "MicroMeters" | "Microns" => 1.0,
        "nm" | "NanoMeters" => 1e-3,
        "pm" | "PicoMeters" => 1e-6,
        "A" | "Angstroms" | "\u{c5}" => 1e-4,
        "in" | "Inches" => 25_400.0,
        "mil" | "Mils" => 25.4,
        _ => return None,
    })
}
