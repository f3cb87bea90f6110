//! STL writers: binary (compact; EDEM, Yade, MercuryDPM, recent LIGGGHTS) and ASCII (what older
//! LIGGGHTS releases read).
//!
//! STL stores f32 coordinates and no unit: both writers state the unit and the recentring
//! offset in the header (binary) or on the `solid` line (ASCII), see [`stl_header`]. Normals are
//! computed per face in f64 from the f64 vertices and only then rounded to f32. Triangles are
//! encoded in parallel blocks and handed to the writer in large `write_all` calls, so an
//! unbuffered `File` is fine and the memory used stays bounded whatever the mesh size.

use std::io::Write;

use rayon::prelude::*;

use crate::error::Result;
use crate::geom;
use crate::solid::{LengthUnit, SolidMesh};

/// Bytes of a binary STL record: normal, three vertices (12 f32) and a 2-byte attribute.
const RECORD_BYTES: usize = 50;
/// Triangles encoded per block (~1.6 MB binary, ~8 MB ASCII): enough work for rayon to share out
/// per block, while the memory the writers hold stays bounded whatever the mesh size.
const BLOCK_TRIANGLES: usize = 1 << 15;
/// Triangles formatted per rayon task in the ASCII writer.
const ASCII_TASK_TRIANGLES: usize = 1 << 10;

/// Size in bytes of a binary STL holding `triangles` triangles: 80-byte header, u32 count,
/// 50 bytes per triangle.
pub fn binary_stl_len(triangles: usize) -> u64 {
    84 + RECORD_BYTES as u64 * triangles as u64
}

/// The self-description written into an STL: `"<label>, units=<unit>, offset_um=<x>,<y>,<z>"`
/// (the offset to 1 nm), at most 80 ASCII bytes. The unit and offset fit for any offset below
/// 1e15 um; the label is shortened if needed, non-printable or non-ASCII characters in it become '?', and a label
/// that starts with "solid" is prefixed with "binary " because readers take a binary file whose
/// header starts with "solid" for ASCII. A label that already ends in a unit and offset
/// (a header made by this function) loses them first, so the description is never repeated:
/// `stl_header(m, &stl_header(m, l)) == stl_header(m, l)`.
pub fn stl_header(mesh: &SolidMesh, label: &str) -> String {
    header_for(mesh.units, mesh.offset_um, label)
}

/// [`stl_header`] of a mesh in `units` recentred by `offset_um`.
pub(crate) fn header_for(units: LengthUnit, offset_um: [f64; 3], label: &str) -> String {
    let mut label = clean_label(bare_label(label));
    if label.len() >= 5 && label[..5].eq_ignore_ascii_case("solid") {
        label.insert_str(0, "binary ");
    }
    let suffix = format!(
        "units={}, offset_um={}",
        units.symbol(),
        offset_text(offset_um)
    );
    label.truncate(80usize.saturating_sub(suffix.len() + 2)); // ASCII: bytes are chars
    let mut header = if label.is_empty() {
        suffix
    } else {
        format!("{label}, {suffix}")
    };
    header.truncate(80);
    header
}

/// `label` without a trailing `units=..., offset_um=...` description (what [`stl_header`]
/// appends), so callers may pass either a plain label or a finished header.
fn bare_label(label: &str) -> &str {
    let cut = if label.starts_with("units=") {
        Some(0)
    } else {
        label.find(", units=").or_else(|| label.find(" units="))
    };
    match cut {
        Some(k) => label[..k].trim_end_matches([',', ' ']),
        None => label,
    }
}

/// The label as printable ASCII, trimmed.
fn clean_label(label: &str) -> String {
    let cleaned: String = label
        .chars()
        .map(|c| {
            if c == ' ' || c.is_ascii_graphic() {
                c
            } else {
                '?'
            }
        })
        .collect();
    cleaned.trim().to_string()
}

fn offset_text(offset_um: [f64; 3]) -> String {
    let [x, y, z] = offset_um;
    format!("{x:.3},{y:.3},{z:.3}")
}

/// Writes `mesh` as binary STL: an 80-byte header holding [`stl_header`] (zero padded), the
/// triangle count, and per triangle its f64-computed unit normal and its corners as f32 in the
/// mesh's units. Exactly [`binary_stl_len`] bytes. Errors if the mesh is malformed (see
/// [`SolidMesh::validate`]) or the writer fails.
pub fn write_stl_binary<W: Write>(w: W, mesh: &SolidMesh, header_text: &str) -> Result<()> {
    mesh.validate()?;
    // validate() checked that the count fits in u32.
    let mut out = StlSink::new(
        w,
        false,
        mesh.units,
        mesh.offset_um,
        header_text,
        mesh.triangles.len() as u32,
    )?;
    for tris in mesh.triangles.chunks(BLOCK_TRIANGLES) {
        for t in tris {
            out.push(t.map(|v| mesh.vertices[v as usize]))?;
        }
    }
    out.finish()
}

/// An STL file written one triangle at a time (corners in the mesh's units, f64): the header
/// first (a binary file needs the triangle count up front), then the triangles, encoded in
/// parallel blocks of [`BLOCK_TRIANGLES`] and handed to the writer in large `write_all` calls,
/// so the memory held stays bounded whatever the mesh size. The in-memory writers go through
/// it too, so a streamed file and a written [`SolidMesh`] are the same bytes.
pub(crate) struct StlSink<W: Write> {
    w: W,
    ascii: bool,
    /// The solid's name on the ASCII `solid` / `endsolid` lines.
    name: String,
    pending: Vec<[[f64; 3]; 3]>,
    buf: Vec<u8>,
    /// Triangles the header announced, and those written.
    announced: u64,
    written: u64,
}

impl<W: Write> StlSink<W> {
    /// Writes the header of a binary (`ascii` false) or ASCII STL of `triangles` triangles.
    pub(crate) fn new(
        mut w: W,
        ascii: bool,
        units: LengthUnit,
        offset_um: [f64; 3],
        header_text: &str,
        triangles: u32,
    ) -> Result<Self> {
        let mut name = String::new();
        if ascii {
            // The first word is the solid's name; the rest says units and offset. No length
            // limit here.
            name = match clean_label(bare_label(header_text)).replace(' ', "_") {
                n if n.is_empty() => "surfstream".to_string(),
                n => n,
            };
            let details = format!(
                "units={} offset_um={}",
                units.symbol(),
                offset_text(offset_um)
            );
            writeln!(w, "solid {name} {details}")?;
        } else {
            let mut header = [0u8; 80];
            let text = header_for(units, offset_um, header_text);
            header[..text.len()].copy_from_slice(text.as_bytes());
            w.write_all(&header)?;
            w.write_all(&triangles.to_le_bytes())?;
        }
        Ok(Self {
            w,
            ascii,
            name,
            pending: Vec::with_capacity(BLOCK_TRIANGLES.min(triangles as usize)),
            buf: Vec::new(),
            announced: u64::from(triangles),
            written: 0,
        })
    }

    /// Adds one triangle (corners counter-clockwise seen from outside, in the mesh's units).
    pub(crate) fn push(&mut self, corners: [[f64; 3]; 3]) -> Result<()> {
        self.pending.push(corners);
        if self.pending.len() == BLOCK_TRIANGLES {
            self.flush_block()?;
        }
        Ok(())
    }

    fn flush_block(&mut self) -> Result<()> {
        let tris = &self.pending;
        if self.ascii {
            let texts: Vec<Vec<u8>> = tris
                .par_chunks(ASCII_TASK_TRIANGLES)
                .map(|part| {
                    // ~250 bytes per facet with 9-digit numbers.
                    let mut s = Vec::with_capacity(part.len() * 256);
                    for c in part {
                        s.extend_from_slice(b"facet normal");
                        push_xyz(&mut s, geom::unit_normal(c[0], c[1], c[2]));
                        s.extend_from_slice(b"\n outer loop\n");
                        for corner in c {
                            s.extend_from_slice(b"  vertex");
                            push_xyz(&mut s, *corner);
                            s.push(b'\n');
                        }
                        s.extend_from_slice(b" endloop\nendfacet\n");
                    }
                    s
                })
                .collect();
            for text in &texts {
                self.w.write_all(text)?;
            }
        } else {
            self.buf.resize(tris.len() * RECORD_BYTES, 0);
            self.buf
                .par_chunks_mut(RECORD_BYTES)
                .zip(tris.par_iter())
                .for_each(|(record, c)| {
                    let normal = geom::unit_normal(c[0], c[1], c[2]);
                    let values = [normal, c[0], c[1], c[2]];
                    for (slot, v) in record[..48]
                        .chunks_exact_mut(4)
                        .zip(values.iter().flatten())
                    {
                        slot.copy_from_slice(&(*v as f32).to_le_bytes());
                    }
                    record[48..].fill(0); // attribute byte count: unused
                });
            self.w.write_all(&self.buf)?;
        }
        self.written += tris.len() as u64;
        self.pending.clear();
        Ok(())
    }

    /// Writes what is pending and the end of the file; errors if the count differs from the
    /// header's.
    pub(crate) fn finish(mut self) -> Result<()> {
        self.flush_block()?;
        if self.written != self.announced {
            return Err(crate::MeshError::InvalidMesh(format!(
                "STL: {} triangles written but the header announced {}",
                self.written, self.announced
            )));
        }
        if self.ascii {
            writeln!(self.w, "endsolid {}", self.name)?;
        }
        self.w.flush()?;
        Ok(())
    }
}

/// Writes `mesh` as ASCII STL. The `solid` line carries the label (spaces replaced by '_') and
/// the unit and offset as `key=value` words, which readers ignore or keep as the name.
/// Coordinates and normals are the same f32 values as in the binary file, printed in scientific
/// notation with nine significant digits (trailing zeros dropped, e.g. `-5e-1`,
/// `1.24999997e-3`), which reads
/// back to exactly the same f32, so both formats describe the same triangles. Errors as
/// [`write_stl_binary`].
pub fn write_stl_ascii<W: Write>(w: W, mesh: &SolidMesh, header_text: &str) -> Result<()> {
    mesh.validate()?;
    let mut out = StlSink::new(
        w,
        true,
        mesh.units,
        mesh.offset_um,
        header_text,
        mesh.triangles.len() as u32,
    )?;
    for t in &mesh.triangles {
        out.push(t.map(|v| mesh.vertices[v as usize]))?;
    }
    out.finish()
}

/// Appends " x y z" (each rounded to f32, see [`push_f32`]).
fn push_xyz(out: &mut Vec<u8>, v: [f64; 3]) {
    for c in v {
        out.push(b' ');
        push_f32(out, c as f32);
    }
}

/// 10^k for k = 0..=40 (exact up to 10^22; beyond, within a few ulps, far below the 1e-9 that
/// nine digits need).
const POW10: [f64; 41] = {
    let mut table = [1.0f64; 41];
    let mut k = 1;
    while k < table.len() {
        table[k] = table[k - 1] * 10.0;
        k += 1;
    }
    table
};

/// Appends `v` as `d.dddddddde-X`: nine significant digits, trailing zeros dropped.
///
/// Why not `{:e}`: std's shortest round-trip formatting is several times slower, and an ASCII
/// STL of a 1024 x 1024 field holds 25 M numbers. Nine significant digits always identify an
/// f32 (f32 needs at most 9), and the f64 arithmetic below is accurate to ~1e-14 relative, so
/// even a last digit rounded the wrong way at a tie (1e-8 relative at worst) stays well inside
/// half an f32 ulp (>= 3e-8 relative): the text reads back to the very same f32.
fn push_f32(out: &mut Vec<u8>, v: f32) {
    let a = f64::from(v).abs();
    // Zero, and magnitudes a mesh never has (f32 subnormals, > 1e30): std's exact formatting.
    if !(1e-30..=1e30).contains(&a) {
        let _ = write!(out, "{v:e}"); // writing into a Vec cannot fail
        return;
    }
    // a = m * 10^(e - 8) with m a 9-digit integer; log10 may be off by one at powers of 10.
    // |e - 8| <= 39 in the range above, so the table covers it.
    let scaled = |e: i32| {
        let k = e - 8;
        let m = if k >= 0 {
            a / POW10[k as usize]
        } else {
            a * POW10[k.unsigned_abs() as usize]
        };
        m.round() as u64
    };
    let mut e = a.log10().floor() as i32;
    let mut m = scaled(e);
    if m >= 1_000_000_000 {
        e += 1;
        m = scaled(e);
    } else if m < 100_000_000 {
        e -= 1;
        m = scaled(e);
    }
    if m >= 1_000_000_000 {
        // 9.999999999..e(e) rounded up to 10.00000000e(e): renormalise.
        m /= 10;
        e += 1;
    }
    // Sign, first digit, '.', 8 digits, 'e', '-', 2 exponent digits: at most 15 bytes.
    let mut buf = [0u8; 16];
    let mut n = 0;
    if v < 0.0 {
        buf[0] = b'-';
        n = 1;
    }
    let mut digits = [b'0'; 9];
    for d in digits.iter_mut().rev() {
        *d += (m % 10) as u8;
        m /= 10;
    }
    let mut end = 9;
    while end > 1 && digits[end - 1] == b'0' {
        end -= 1;
    }
    buf[n] = digits[0];
    n += 1;
    if end > 1 {
        buf[n] = b'.';
        buf[n + 1..n + end].copy_from_slice(&digits[1..end]);
        n += end;
    }
    buf[n] = b'e';
    n += 1;
    if e < 0 {
        buf[n] = b'-';
        n += 1;
    }
    let e = e.unsigned_abs();
    if e >= 10 {
        buf[n] = b'0' + (e / 10) as u8;
        n += 1;
    }
    buf[n] = b'0' + (e % 10) as u8;
    n += 1;
    out.extend_from_slice(&buf[..n]);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mesh(offset_um: [f64; 3]) -> SolidMesh {
        SolidMesh {
            vertices: vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
            triangles: vec![[0, 1, 2]],
            offset_um,
            units: LengthUnit::Mm,
            filled_samples: 0,
            top_triangles: 1,
            base_depth_um: 10.0,
        }
    }

    #[test]
    fn header_keeps_units_and_offset_and_never_starts_with_solid() {
        let m = mesh([123456789.0, -98765.4321, 0.5]);
        let h = stl_header(
            &m,
            "solid surfstream with a very long label that cannot fit at all",
        );
        assert!(h.len() <= 80, "{h}");
        assert!(h.starts_with("binary solid"), "{h}");
        assert!(
            h.ends_with("units=mm, offset_um=123456789.000,-98765.432,0.500"),
            "{h}"
        );
        assert_eq!(
            stl_header(&m, ""),
            "units=mm, offset_um=123456789.000,-98765.432,0.500"
        );
        assert!(stl_header(&m, "naïve\ttab").starts_with("na?ve?tab, "));
    }

    /// The callers used to pass a finished header as the label, which came out as
    /// "surfstream surface, units=mm, offse, units=mm, ..." (issue 13): the header is idempotent
    /// and the file's 80 bytes say unit and offset exactly once, NUL padded.
    #[test]
    fn header_of_a_header_is_the_header_and_the_file_says_it_once() {
        let m = mesh([211.27764, -5.5, -15.134544]);
        let h = stl_header(&m, "surfstream surface");
        assert_eq!(
            h,
            "surfstream surface, units=mm, offset_um=211.278,-5.500,-15.135"
        );
        assert_eq!(stl_header(&m, &h), h);
        assert_eq!(stl_header(&m, &stl_header(&m, "")), stl_header(&m, ""));
        let mut out = Vec::new();
        write_stl_binary(&mut out, &m, &h).unwrap();
        let text = &out[..80];
        assert_eq!(&text[..h.len()], h.as_bytes());
        assert!(text[h.len()..].iter().all(|&b| b == 0));
        let mut ascii = Vec::new();
        write_stl_ascii(&mut ascii, &m, &h).unwrap();
        let first = String::from_utf8(ascii).unwrap();
        let first = first.lines().next().unwrap().to_string();
        assert_eq!(
            first,
            "solid surfstream_surface units=mm offset_um=211.278,-5.500,-15.135"
        );
    }

    #[test]
    fn ascii_numbers_read_back_to_the_same_f32() {
        let check = |v: f32| {
            let mut s = Vec::new();
            push_f32(&mut s, v);
            let s = String::from_utf8(s).unwrap();
            let back = s.parse::<f32>().ok().map(f32::to_bits);
            assert_eq!(back, Some(v.to_bits()), "{v:e} -> {s}");
        };
        // A spread over every binade of both signs, including subnormals and extremes.
        for bits in (0..0x7f80_0000u32).step_by(7919) {
            check(f32::from_bits(bits));
            check(-f32::from_bits(bits));
        }
        // Around powers of ten, where the exponent estimate and the rounding carry can slip.
        for k in -30..=30 {
            let p = 10f32.powi(k);
            let (mut below, mut above) = (p, p);
            for _ in 0..50 {
                below = f32::from_bits(below.to_bits() - 1);
                check(below);
                check(above);
                above = f32::from_bits(above.to_bits() + 1);
            }
        }
        for v in [
            0.0,
            -0.0,
            1.0,
            0.5,
            -1.25e-3,
            0.8148e-3,
            f32::MAX,
            f32::MIN_POSITIVE,
        ] {
            check(v);
        }
        let mut s = Vec::new();
        for v in [1.0f32, -0.5, -1.25e-3, 123456.79, 0.0] {
            push_f32(&mut s, v);
            s.push(b' ');
        }
        let s = String::from_utf8(s).unwrap();
        // -1.25e-3 is not exact in f32: nine digits show its true value.
        assert_eq!(s, "1e0 -5e-1 -1.24999997e-3 1.23456789e5 0e0 ");
    }

    #[test]
    fn refuses_out_of_range_indices() {
        let mut m = mesh([0.0; 3]);
        m.triangles[0][2] = 7;
        let mut out = Vec::new();
        assert!(write_stl_binary(&mut out, &m, "x").is_err());
        assert!(write_stl_ascii(&mut out, &m, "x").is_err());
    }

    #[test]
    fn ascii_solid_line_names_the_solid_and_states_units() {
        let m = mesh([1.0, 2.0, 3.0]);
        let mut out = Vec::new();
        write_stl_ascii(&mut out, &m, "surfstream solid").unwrap();
        let text = String::from_utf8(out).unwrap();
        let mut lines = text.lines();
        assert_eq!(
            lines.next(),
            Some("solid surfstream_solid units=mm offset_um=1.000,2.000,3.000")
        );
        assert_eq!(lines.next(), Some("facet normal 0e0 0e0 1e0"));
        assert_eq!(text.lines().last(), Some("endsolid surfstream_solid"));
    }
}
