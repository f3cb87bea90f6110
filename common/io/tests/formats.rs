//! Readers on the real specimens (tests/data/specimens, reference values in its README), on
//! DATX files written by tests/data/make_synthetic_datx.py, and on every trap of
//! ../shared/notes/formats.md; corrupt, truncated and lying files give clear errors.

use std::io::{Cursor, Write};
use std::path::{Path, PathBuf};
use std::process::Command;

use surfstream_core::metrology::{params, Grid};
mod support;
use support::{optional_specimen, python, repo_root, specimen};
use surfstream_io::formats::{self, parse_surface, read_surface, Format, Metadata, Surface};

/// Runs the test environment's Python with the arguments `args` adds; its output, after
/// asserting that it succeeded (its stderr otherwise).
fn python_ok(args: impl FnOnce(&mut Command)) -> std::process::Output {
    let mut cmd = Command::new(python());
    args(&mut cmd);
    let out = cmd.output().expect("python runs");
    assert!(
        out.status.success(),
        "python failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// Population Sq of the valid heights about their mean, from the reader's f64 data.
fn sq_valid(z: &[f64]) -> f64 {
    let v: Vec<f64> = z.iter().copied().filter(|z| !z.is_nan()).collect();
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    (v.iter().map(|z| (z - mean).powi(2)).sum::<f64>() / n).sqrt()
}

fn rel(a: f64, b: f64) -> f64 {
    (a - b).abs() / b.abs()
}

fn min_max(z: &[f64]) -> (f64, f64) {
    z.iter()
        .filter(|z| !z.is_nan())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &z| {
            (a.min(z), b.max(z))
        })
}

#[test]
fn metropro_golden_and_not_8x() {
    let s = read_surface(&specimen("metropro-1.dat")).unwrap();
    assert_eq!((s.height, s.width), (480, 640));
    assert_eq!(s.invalid_count(), 0);
    assert!(
        rel(s.pitch_x_um, 1.09825203) < 1e-8,
        "pitch {}",
        s.pitch_x_um
    );
    // The 8x trap: R = 32768 for phase_res 1, not 4096.
    let sq = sq_valid(&s.heights_um);
    assert!(rel(sq, 0.07528822204734589) < 1e-9, "Sq {sq}");
    let (lo, hi) = min_max(&s.heights_um);
    assert!(
        rel(lo, 50.10827568297134) < 1e-9 && rel(hi, 51.47133201226055) < 1e-9,
        "{lo} {hi}"
    );
    assert_eq!(s.metadata.format, "metropro");
    assert!(s.metadata.wavelength_um.is_some_and(|w| w > 0.3 && w < 1.0));
    // The metrology module agrees (its own sums).
    let p =
        params(&Grid::new(&s.heights_um, s.height, s.width, s.pitch_x_um, s.pitch_y_um).unwrap())
            .unwrap();
    assert!(rel(p.sq, 0.07528822204734589) < 1e-9, "params Sq {}", p.sq);
}

#[test]
fn x3p_golden_int32_axes_anisotropic() {
    let s = read_surface(&specimen("x3p-2.x3p")).unwrap();
    assert_eq!((s.height, s.width), (650, 650));
    assert!(rel(s.pitch_x_um, 0.12765651) < 1e-7 && rel(s.pitch_y_um, 0.314582114) < 1e-7);
    assert!(rel(sq_valid(&s.heights_um), 0.0772803327) < 1e-9);
    let (lo, hi) = min_max(&s.heights_um);
    assert!(
        rel(lo, -0.314420687) < 1e-8 && rel(hi, 0.239915513) < 1e-8,
        "{lo} {hi}"
    );
    assert_eq!(
        s.metadata.instrument.as_deref(),
        Some("DIGITAL SURF Mountains Map Technology Software 6.2")
    );
    assert_eq!(s.metadata.date.as_deref(), Some("1970-01-01T01:00:00"));
}

#[test]
fn x3p_golden_int16_with_valid_bin() {
    // openGPS's sample (LGPL-3) is not in the repository: read where SURFSTREAM_SPECIMENS has it.
    let Some(path) = optional_specimen("sample4_bin.x3p") else {
        eprintln!("skipped: sample4_bin.x3p is not in SURFSTREAM_SPECIMENS");
        return;
    };
    let s = read_surface(&path).unwrap();
    assert_eq!((s.height, s.width), (4, 4));
    assert_eq!(s.invalid_count(), 1);
    assert!(rel(sq_valid(&s.heights_um), 610537.577) < 1e-9);
    let (lo, hi) = min_max(&s.heights_um);
    assert!(rel(lo, -808000.0) < 1e-12 && rel(hi, 1048000.0) < 1e-12);
}

#[test]
fn sur_golden_uncompressed_with_not_measured_points() {
    // SurfaceTopography's sur-2.sur (MIT): uncompressed int32, non_measured_points = 1.
    let s = read_surface(&specimen("sur-2.sur")).unwrap();
    assert_eq!((s.height, s.width), (484, 563));
    assert_eq!(s.invalid_count(), 117);
    assert!(rel(s.pitch_x_um, 3.4840002190321684) < 1e-12);
    assert!(rel(s.pitch_y_um, 3.4840002190321684) < 1e-12);
    // surfalize 0.19.2 (tests/data/specimens/README.md).
    assert!(rel(sq_valid(&s.heights_um), 0.017517881243588176) < 1e-9);
}

#[test]
fn sur_golden_uncompressed_surfalize_sample() {
    // surfalize's test file (GPL-3) is not in the repository: read where SURFSTREAM_SPECIMENS
    // has it.
    let Some(path) = optional_specimen("sur-uncompressed.sur") else {
        eprintln!("skipped: sur-uncompressed.sur is not in SURFSTREAM_SPECIMENS");
        return;
    };
    let s = read_surface(&path).unwrap();
    assert_eq!((s.height, s.width), (512, 512));
    assert_eq!(s.invalid_count(), 0);
    assert!(rel(s.pitch_x_um, 0.0195709163) < 1e-8 && rel(s.pitch_y_um, 0.0195802095) < 1e-8);
    assert!(rel(sq_valid(&s.heights_um), 0.119146667) < 1e-9);
    // offset_z (-1.4725e-5 mm) is applied in the z step unit (Gwyddion's convention); surfalize
    // adds it unscaled, so its min/max are ours + 14.72 nm - 0.0147 nm.
    let off = -1.472474559705006e-5 * 1e3;
    let (lo, hi) = min_max(&s.heights_um);
    assert!((lo - (-0.29727819530567245 + off)).abs() < 1e-9, "{lo}");
    assert!((hi - (0.3292170231361524 + off)).abs() < 1e-9, "{hi}");
}

#[test]
fn sur_invalid_marker_and_units() {
    let s = read_surface(&specimen("sur-3.sur")).unwrap();
    assert_eq!((s.height, s.width), (512, 512));
    // non_measured_points = 1, min_point 0: raw == -2 is invalid.
    assert_eq!(s.invalid_count(), 233009);
    // spacing 295546 nm -> 295.546 um; z step unit m.
    assert!(rel(s.pitch_x_um, 295.546) < 1e-6);
    let (_, hi) = min_max(&s.heights_um);
    assert!(
        rel(hi, 6992.35 + -0.0034143300727009773 * 1e6) < 1e-6,
        "{hi}"
    );
    assert_eq!(s.metadata.date.as_deref(), Some("2023-06-22T10:08:53"));
}

fn toy_surface(w: usize, h: usize) -> Surface {
    let heights_um = (0..w * h)
        .map(|i| {
            if i % 7 == 3 {
                f64::NAN
            } else {
                ((i * 37 % 101) as f64 - 50.0) * 0.013
            }
        })
        .collect();
    Surface {
        width: w,
        height: h,
        pitch_x_um: 0.5,
        pitch_y_um: 0.75,
        heights_um,
        metadata: Metadata::default(),
    }
}

fn same_heights(a: &[f64], b: &[f64], tol: f64) {
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(b) {
        assert!(
            x.is_nan() == y.is_nan() && (x.is_nan() || (x - y).abs() <= tol),
            "{x} vs {y}"
        );
    }
}

#[test]
fn sur_compressed_round_trip() {
    let s = toy_surface(13, 9);
    for compressed in [false, true] {
        let bytes = formats::sur::encode_for_tests(&s, compressed, true);
        let r = parse_surface(&bytes, Format::Sur).unwrap();
        assert_eq!((r.width, r.height), (13, 9));
        assert_eq!(r.metadata.extra["compressed"], compressed.to_string());
        same_heights(&r.heights_um, &s.heights_um, 1e-6); // spacing_z is f32
        assert!(rel(r.pitch_y_um, 0.75) < 1e-7);
    }
}

#[test]
fn sur_compressed_lying_lengths() {
    let s = toy_surface(13, 9);
    let bytes = formats::sur::encode_for_tests(&s, true, true);
    // Stream count far beyond the zone.
    let mut b = bytes.clone();
    b[512..516].copy_from_slice(&u32::MAX.to_le_bytes());
    let e = format!("{:#}", parse_surface(&b, Format::Sur).unwrap_err());
    assert!(e.contains("stream count"), "{e}");
    // First stream claims more raw bytes than the map holds.
    let mut b = bytes.clone();
    b[516..520].copy_from_slice(&1_000_000u32.to_le_bytes());
    let e = format!("{:#}", parse_surface(&b, Format::Sur).unwrap_err());
    assert!(e.contains("inflates past"), "{e}");
    // Corrupt zlib data.
    let mut b = bytes.clone();
    let n = b.len();
    for v in &mut b[n - 40..n - 10] {
        *v ^= 0x5a;
    }
    assert!(parse_surface(&b, Format::Sur).is_err());
}

fn x3p_parts(path: &Path) -> Vec<(String, Vec<u8>)> {
    let data = std::fs::read(path).unwrap();
    let mut z = zip::ZipArchive::new(Cursor::new(data)).unwrap();
    let mut out = Vec::new();
    for i in 0..z.len() {
        let mut f = z.by_index(i).unwrap();
        if f.is_dir() {
            continue;
        }
        let mut v = Vec::new();
        std::io::Read::read_to_end(&mut f, &mut v).unwrap();
        out.push((f.name().unwrap().to_string(), v));
    }
    out
}

fn x3p_from_parts(parts: &[(String, Vec<u8>)]) -> Vec<u8> {
    let mut w = zip::ZipWriter::new(Cursor::new(Vec::new()));
    for (name, bytes) in parts {
        w.start_file(name.as_str(), zip::write::SimpleFileOptions::default())
            .unwrap();
        w.write_all(bytes).unwrap();
    }
    w.finish().unwrap().into_inner()
}

/// The warnings about the file's integrity, without the one about physically absurd heights.
fn integrity_warnings(warnings: &[String]) -> Vec<&String> {
    warnings
        .iter()
        .filter(|w| !w.contains("physically absurd"))
        .collect()
}

#[test]
fn x3p_traps_subfolder_uppercase_md5_lying_checksums() {
    let parts = x3p_parts(&specimen("x3p-2.x3p"));
    let reference = parse_surface(&x3p_from_parts(&parts), Format::X3p).unwrap();
    // main.xml in a sub-folder, md5checksum.hex in upper case.
    let moved: Vec<(String, Vec<u8>)> = parts
        .iter()
        .map(|(n, b)| {
            let b = if n == "md5checksum.hex" {
                String::from_utf8(b.clone())
                    .unwrap()
                    .to_uppercase()
                    .replace("*MAIN.XML", "*main.xml")
                    .into_bytes()
            } else {
                b.clone()
            };
            (format!("scan_0001/{n}"), b)
        })
        .collect();
    let s = parse_surface(&x3p_from_parts(&moved), Format::X3p).unwrap();
    same_heights(&s.heights_um, &reference.heights_um, 0.0);
    // A checksum that fails is a warning naming what failed, and the data is read as stored
    // (the user wants the data, and to be told).
    let mut bad = parts.clone();
    for (n, b) in &mut bad {
        if n == "md5checksum.hex" {
            b[0] = if b[0] == b'0' { b'1' } else { b'0' };
        }
    }
    let s = parse_surface(&x3p_from_parts(&bad), Format::X3p).unwrap();
    same_heights(&s.heights_um, &reference.heights_um, 0.0);
    let integrity = integrity_warnings(&s.metadata.warnings);
    assert_eq!(integrity.len(), 1, "{:?}", s.metadata.warnings);
    assert!(integrity[0].contains("MD5 checksum of main.xml"));
    let mut bad = parts.clone();
    for (n, b) in &mut bad {
        if n == "bindata/data.bin" {
            b[0] ^= 1;
        }
    }
    let s = parse_surface(&x3p_from_parts(&bad), Format::X3p).unwrap();
    let integrity = integrity_warnings(&s.metadata.warnings);
    assert_eq!(integrity.len(), 1, "{:?}", s.metadata.warnings);
    assert!(integrity[0].contains("point data"));
    assert!(integrity_warnings(&reference.metadata.warnings).is_empty());
    // Truncated data.bin: the size is checked before anything is converted.
    let mut bad = parts.clone();
    for (n, b) in &mut bad {
        if n == "bindata/data.bin" {
            b.truncate(10);
        }
    }
    let e = format!(
        "{:#}",
        parse_surface(&x3p_from_parts(&bad), Format::X3p).unwrap_err()
    );
    assert!(
        e.contains("declares 3380000 bytes of point data") && e.contains("archive declares"),
        "{e}"
    );
    // A lying size that overflows.
    let mut bad = parts.clone();
    for (n, b) in &mut bad {
        if n == "main.xml" {
            *b = String::from_utf8(b.clone())
                .unwrap()
                .replace("<SizeX>650</SizeX>", "<SizeX>18446744073709551615</SizeX>")
                .into_bytes();
        }
    }
    bad.retain(|(n, _)| n != "md5checksum.hex");
    let e = format!(
        "{:#}",
        parse_surface(&x3p_from_parts(&bad), Format::X3p).unwrap_err()
    );
    assert!(e.contains("overflows"), "{e}");
}

/// main.xml of a float32 x3p (`root` element name, inline `DataList` or a `DataLink`).
fn x3p_main_xml(root: &str, cols: usize, rows: usize, record3_data: &str) -> String {
    format!(
        r#"<?xml version="1.0" encoding="UTF-8"?>
<p:{root} xmlns:p="http://www.opengps.eu/2008/ISO5436_2">
<Record1><Revision>ISO5436 - 2000</Revision><FeatureType>SUR</FeatureType><Axes>
<CX><AxisType>I</AxisType><DataType>D</DataType><Increment>1e-06</Increment><Offset>0</Offset></CX>
<CY><AxisType>I</AxisType><DataType>D</DataType><Increment>2e-06</Increment><Offset>0</Offset></CY>
<CZ><AxisType>A</AxisType><DataType>F</DataType><Increment>1</Increment><Offset>0</Offset></CZ>
</Axes></Record1>
<Record3><MatrixDimension><SizeX>{cols}</SizeX><SizeY>{rows}</SizeY><SizeZ>1</SizeZ></MatrixDimension>
{record3_data}</Record3>
<Record4><ChecksumFile>md5checksum.hex</ChecksumFile></Record4>
</p:{root}>"#
    )
}

/// What other tools write: Alicona's +inf for invalid float points, root `ISO5436`, point data
/// inline in main.xml, and a size claim the file cannot hold.
#[test]
fn x3p_real_world_variants() {
    // 3 columns x 2 rows, asymmetric, metres; +inf and -inf mark invalid points.
    let z_m: [f32; 6] = [1e-6, 2e-6, f32::INFINITY, 4e-6, f32::NEG_INFINITY, 6e-6];
    let data: Vec<u8> = z_m.iter().flat_map(|v| v.to_le_bytes()).collect();
    let link = "<DataLink><PointDataLink>bindata/data.bin</PointDataLink></DataLink>";
    for root in ["ISO5436_2", "ISO5436"] {
        let xml = x3p_main_xml(root, 3, 2, link);
        let bytes = x3p_from_parts(&[
            ("main.xml".into(), xml.into_bytes()),
            ("bindata/data.bin".into(), data.clone()),
        ]);
        let s = parse_surface(&bytes, Format::X3p).unwrap();
        assert_eq!((s.height, s.width), (2, 3));
        assert_eq!((s.pitch_x_um, s.pitch_y_um), (1.0, 2.0));
        assert_eq!(s.invalid_count(), 2, "{root}: inf is not measured");
        same_heights(
            &s.heights_um,
            &[1.0, 2.0, f64::NAN, 4.0, f64::NAN, 6.0],
            1e-6,
        );
        let p = params(
            &Grid::new(&s.heights_um, s.height, s.width, s.pitch_x_um, s.pitch_y_um).unwrap(),
        )
        .unwrap();
        assert!(p.sq.is_finite() && p.sp.is_finite(), "{p:?}");
        assert!(
            (p.sp - 6.0 + 3.25).abs() < 1e-5,
            "Sp over the four valid points: {p:?}"
        );
    }
    // Inline DataList: one Datum per point, empty = not measured, "x;y;z" also accepted.
    let list = "<DataList><Datum>1e-6</Datum><Datum>2e-6</Datum><Datum></Datum>\
                <Datum>;;4e-6</Datum><Datum/><Datum>6e-6</Datum></DataList>";
    let xml = x3p_main_xml("ISO5436_2", 3, 2, list);
    let s = parse_surface(
        &x3p_from_parts(&[("main.xml".into(), xml.into_bytes())]),
        Format::X3p,
    )
    .unwrap();
    same_heights(
        &s.heights_um,
        &[1.0, 2.0, f64::NAN, 4.0, f64::NAN, 6.0],
        1e-9,
    );
    let xml = x3p_main_xml("ISO5436_2", 4, 2, list);
    let e = format!(
        "{:#}",
        parse_surface(
            &x3p_from_parts(&[("main.xml".into(), xml.into_bytes())]),
            Format::X3p
        )
        .unwrap_err()
    );
    assert!(
        e.contains("DataList holds 6 Datum elements, MatrixDimension declares 8"),
        "{e}"
    );
    // SizeX = SizeY = 100000 with 24 bytes of data: a clear error before any allocation
    // (it used to abort the process on an 80 GB allocation).
    let xml = x3p_main_xml("ISO5436_2", 100_000, 100_000, link);
    let e = format!(
        "{:#}",
        parse_surface(
            &x3p_from_parts(&[
                ("main.xml".into(), xml.into_bytes()),
                ("bindata/data.bin".into(), data.clone()),
            ]),
            Format::X3p
        )
        .unwrap_err()
    );
    assert!(
        e.contains("MatrixDimension declares 40000000000 bytes"),
        "{e}"
    );
    assert!(e.contains("bindata/data.bin"), "{e}");
}

/// An 8-bit PNG of `width` x `height` pixels, `channels` 3 (RGB) or 4 (RGBA), rows top first.
fn png_bytes(width: u32, height: u32, channels: usize, pixels: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    let mut enc = png::Encoder::new(&mut out, width, height);
    enc.set_color(if channels == 4 {
        png::ColorType::Rgba
    } else {
        png::ColorType::Rgb
    });
    enc.set_depth(png::BitDepth::Eight);
    let mut w = enc.write_header().unwrap();
    w.write_image_data(pixels).unwrap();
    w.finish().unwrap();
    out
}

/// The x3ptools / FiX3P colour mask (`Record3/Mask`, `bindata/mask.png`): a colour is a region
/// label ("legend entries for each color of a mask"), not a validity flag. Every point is read
/// as measured; the regions are listed with their annotation and point count (pixel (i, j)
/// covers point (i, j)); `exclude_mask_regions` drops exactly the points of the named regions.
#[test]
fn x3p_mask_colours_are_region_labels_with_every_point_measured() {
    // 3 columns x 2 rows of float32 metres; point 4 is not measured (NaN in the data).
    let z_m: [f32; 6] = [1e-6, 2e-6, 3e-6, 4e-6, f32::NAN, 6e-6];
    let data: Vec<u8> = z_m.iter().flat_map(|v| v.to_le_bytes()).collect();
    let as_read = [1.0, 2.0, 3.0, 4.0, f64::NAN, 6.0];
    const BRONZE: [u8; 4] = [0xcd, 0x7f, 0x32, 255];
    const RED: [u8; 4] = [255, 0, 0, 255];
    const BLUE: [u8; 4] = [0, 0, 255, 255];
    const CLEAR: [u8; 4] = [9, 9, 9, 0];
    // Row 0: background, red, background; row 1: blue, background, transparent.
    let rgba: Vec<u8> = [BRONZE, RED, BRONZE, BLUE, BRONZE, CLEAR].concat();
    // As x3ptools writes it: colours with alpha, a colour repeated with an empty annotation.
    let mask = "<Mask><Background>#CD7F32</Background><Annotations>\
                <Annotation color=\"#FF0000FF\">damage</Annotation>\
                <Annotation color=\"#00ff00\">groove</Annotation>\
                <Annotation color=\"#ff0000\"/></Annotations></Mask>";
    let link =
        format!("<DataLink><PointDataLink>bindata/data.bin</PointDataLink></DataLink>{mask}");
    let read = |xml: String, png: Vec<u8>, png_name: &str| {
        parse_surface(
            &x3p_from_parts(&[
                ("main.xml".into(), xml.into_bytes()),
                ("bindata/data.bin".into(), data.clone()),
                (png_name.into(), png),
            ]),
            Format::X3p,
        )
    };
    let png = png_bytes(3, 2, 4, &rgba);
    let s = read(
        x3p_main_xml("ISO5436_2", 3, 2, &link),
        png.clone(),
        "bindata/mask.png",
    )
    .unwrap();
    // Every measured point is read: only the data's own NaN is not measured.
    same_heights(&s.heights_um, &as_read, 1e-6);
    assert!(s.metadata.warnings.is_empty(), "{:?}", s.metadata.warnings);
    let m = s.metadata.mask.as_ref().expect("the mask's regions");
    assert_eq!(m.image, "bindata/mask.png");
    let listed: Vec<(String, String, usize)> = m
        .regions
        .iter()
        .map(|r| (r.label(), r.colour.clone(), r.points))
        .collect();
    let row = |l: &str, c: &str, n: usize| (l.to_string(), c.to_string(), n);
    assert_eq!(
        listed,
        [
            // The transparent pixel is unpainted: it counts with the background.
            row("background", "#cd7f32", 4),
            row("damage", "#ff0000", 1),
            row("groove", "#00ff00", 0),
            row("#0000ff", "#0000ff", 1),
        ]
    );
    // inspect --json shows the regions (the per-point labels stay out of the JSON).
    let json = serde_json::to_value(&s.metadata).unwrap();
    assert_eq!(json["mask"]["regions"][1]["annotation"], "damage");
    assert_eq!(json["mask"]["regions"][0]["background"], true);
    assert!(json["mask"].get("labels").is_none());
    // Excluding drops exactly the labelled points, by name (any case), colour or "background".
    let excluded = |names: &[&str]| {
        let mut t = s.clone();
        let names: Vec<String> = names.iter().map(|n| n.to_string()).collect();
        let n = t
            .exclude_mask_regions(&names)
            .map_err(|e| format!("{e:#}"))?;
        Ok::<_, String>((n, t.heights_um))
    };
    let nan = f64::NAN;
    let (n, h) = excluded(&["damage"]).unwrap();
    assert_eq!(n, 1);
    same_heights(&h, &[1.0, nan, 3.0, 4.0, nan, 6.0], 1e-6);
    let (n, h) = excluded(&["#0000FF", " DAMAGE "]).unwrap();
    assert_eq!(n, 2);
    same_heights(&h, &[1.0, nan, 3.0, nan, nan, 6.0], 1e-6);
    let (n, h) = excluded(&["background"]).unwrap();
    assert_eq!(n, 3, "point 4 was not measured to begin with");
    same_heights(&h, &[nan, 2.0, nan, 4.0, nan, nan], 1e-6);
    let (n, h) = excluded(&["groove", "#cd7f32ff"]).unwrap();
    assert_eq!(n, 3);
    same_heights(&h, &[nan, 2.0, nan, 4.0, nan, nan], 1e-6);
    assert_eq!(excluded(&[]).unwrap().0, 0);
    // An unknown name is an error that lists the regions there are.
    let e = excluded(&["scratch"]).unwrap_err();
    assert!(
        e.contains("mask region 'scratch' is not in the mask (bindata/mask.png)")
            && e.contains("'background' #cd7f32 (4 points)")
            && e.contains("'damage' #ff0000 (1 points)")
            && e.contains("'groove' #00ff00 (0 points)")
            && e.contains("'#0000ff' #0000ff (1 points)"),
        "{e}"
    );
    assert!(excluded(&["#123456"])
        .unwrap_err()
        .contains("is not in the mask"));
    // Two colours under one name (x3ptools' logo example: three colours "fingerprint"): both go.
    let shared = link.replace("#00ff00\">groove", "#0000ff\">damage");
    let s2 = read(
        x3p_main_xml("ISO5436_2", 3, 2, &shared),
        png.clone(),
        "bindata/mask.png",
    )
    .unwrap();
    let mut t = s2.clone();
    assert_eq!(t.exclude_mask_regions(&["damage".into()]).unwrap(), 2);
    same_heights(&t.heights_um, &[1.0, nan, 3.0, nan, nan, 6.0], 1e-6);
    // A file without a mask: excluding is an error, reading is unchanged.
    let plain = read(
        x3p_main_xml(
            "ISO5436_2",
            3,
            2,
            "<DataLink><PointDataLink>bindata/data.bin</PointDataLink></DataLink>",
        ),
        Vec::new(),
        "bindata/other.bin",
    )
    .unwrap();
    assert!(plain.metadata.mask.is_none());
    let e = format!(
        "{:#}",
        plain
            .clone()
            .exclude_mask_regions(&["damage".into()])
            .unwrap_err()
    );
    assert!(e.contains("no colour mask"), "{e}");
    // Inline DataList, no Mask element: mask.png alone, default background #cd7f32, RGB PNG.
    let list = "<DataList><Datum>1e-6</Datum><Datum>2e-6</Datum><Datum>3e-6</Datum>\
                <Datum>4e-6</Datum><Datum></Datum><Datum>6e-6</Datum></DataList>";
    let rgb: Vec<u8> = rgba
        .chunks(4)
        .flat_map(|p| if p[3] == 0 { &BRONZE[..3] } else { &p[..3] })
        .copied()
        .collect();
    let s = read(
        x3p_main_xml("ISO5436_2", 3, 2, list),
        png_bytes(3, 2, 3, &rgb),
        "bindata/mask.png",
    )
    .unwrap();
    same_heights(&s.heights_um, &as_read, 1e-6);
    let m = s.metadata.mask.as_ref().unwrap();
    assert_eq!(m.regions.len(), 3, "background, #0000ff, #ff0000");
    assert_eq!(m.labels, [0, 2, 0, 1, 0, 0]);
    // A Link elsewhere, a white background: bronze is then a painted colour like the others.
    let linked = link.replace(
        "<Background>#CD7F32</Background>",
        "<Link>bindata/annot.png</Link><Background>#ffffff</Background>",
    );
    let mut s = read(
        x3p_main_xml("ISO5436_2", 3, 2, &linked),
        png.clone(),
        "bindata/annot.png",
    )
    .unwrap();
    assert_eq!(s.invalid_count(), 1, "only the data's own NaN");
    assert_eq!(s.exclude_mask_regions(&["#cd7f32".into()]).unwrap(), 2);
    // A mask of the wrong size, a corrupt PNG, a missing linked image, a bad colour: errors
    // that name what is wrong.
    let err =
        |xml: String, png: Vec<u8>, name: &str| format!("{:#}", read(xml, png, name).unwrap_err());
    let e = err(
        x3p_main_xml("ISO5436_2", 3, 2, &link),
        png_bytes(2, 3, 4, &rgba),
        "bindata/mask.png",
    );
    assert!(
        e.contains("bindata/mask.png") && e.contains("2 x 3 pixels") && e.contains("3 x 2"),
        "{e}"
    );
    let mut broken = png.clone();
    let len = broken.len();
    broken.truncate(len - 20);
    let e = err(
        x3p_main_xml("ISO5436_2", 3, 2, &link),
        broken,
        "bindata/mask.png",
    );
    assert!(e.contains("bindata/mask.png"), "{e}");
    let e = err(
        x3p_main_xml("ISO5436_2", 3, 2, &linked),
        png.clone(),
        "bindata/mask.png",
    );
    assert!(e.contains("Mask/Link names 'bindata/annot.png'"), "{e}");
    let e = err(
        x3p_main_xml("ISO5436_2", 3, 2, &link.replace("#CD7F32", "bronze")),
        png,
        "bindata/mask.png",
    );
    assert!(e.contains("Background is 'bronze'"), "{e}");
}

/// The writer keeps a colour mask: `convert` of a labelled X3P to X3P keeps the labels, in
/// x3ptools' layout (`Record3/Mask`, `bindata/mask.png`).
#[test]
fn x3p_colour_mask_round_trips_through_the_writer() {
    let (w, h) = (7, 5);
    let mut s = toy_surface(w, h);
    s.metadata.format = "x3p".into();
    let region = |colour: &str, annotation: Option<&str>, background: bool, points: usize| {
        formats::x3p::MaskRegion {
            colour: colour.into(),
            annotation: annotation.map(str::to_string),
            background,
            points,
        }
    };
    // A band of "scratch" in row 2, one "pore" point, the rest background.
    let labels: Vec<u16> = (0..w * h)
        .map(|i| match (i / w, i % w) {
            (2, _) => 1,
            (4, 6) => 2,
            _ => 0,
        })
        .collect();
    s.metadata.mask = Some(formats::x3p::ColourMask {
        image: "bindata/mask.png".into(),
        regions: vec![
            region("#cd7f32", None, true, w * h - w - 1),
            region("#1f376c", Some("scratch & dent"), false, w),
            region("#ffff00", Some("pore"), false, 1),
        ],
        labels: labels.clone(),
    });
    let bytes = formats::x3p::encode(&s).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("labelled.x3p");
    std::fs::write(&path, &bytes).unwrap();
    let parts = x3p_parts(&path);
    let xml = String::from_utf8(
        parts
            .iter()
            .find(|(n, _)| n == "main.xml")
            .unwrap()
            .1
            .clone(),
    )
    .unwrap();
    assert!(xml.contains("<Background>#cd7f32</Background>"), "{xml}");
    assert!(
        xml.contains("<Annotation color=\"#1f376c\">scratch &amp; dent</Annotation>"),
        "{xml}"
    );
    assert!(parts.iter().any(|(n, _)| n == "bindata/mask.png"));
    let back = parse_surface(&bytes, Format::X3p).unwrap();
    assert_eq!(back.metadata.mask, s.metadata.mask);
    same_heights(&back.heights_um, &s.heights_um, 1e-9);
    // Excluding on the copy read back drops the band and the pore.
    let mut t = back.clone();
    let n = t
        .exclude_mask_regions(&["Scratch & Dent".into(), "#FFFF00".into()])
        .unwrap();
    let measured_in_regions = (0..w * h)
        .filter(|&i| labels[i] != 0 && !s.heights_um[i].is_nan())
        .count();
    assert_eq!(n, measured_in_regions);
    for (i, z) in t.heights_um.iter().enumerate() {
        assert_eq!(
            z.is_nan(),
            labels[i] != 0 || s.heights_um[i].is_nan(),
            "point {i}"
        );
    }
}

#[test]
fn x3p_valid_bin_bit_order_lsb_first() {
    // sample4_bin.x3p marks exactly one point invalid; find which and check it against the
    // valid.bin bits read least significant bit first (where SURFSTREAM_SPECIMENS has the
    // LGPL-3 file; the file of ours below is always checked).
    if let Some(path) = optional_specimen("sample4_bin.x3p") {
        let parts = x3p_parts(&path);
        let valid = &parts
            .iter()
            .find(|(n, _)| n == "bindata/valid.bin")
            .unwrap()
            .1;
        let s = read_surface(&path).unwrap();
        for i in 0..16 {
            let bit = valid[i / 8] >> (i % 8) & 1;
            assert_eq!(bit == 0, s.heights_um[i].is_nan(), "point {i}");
        }
    } else {
        eprintln!("skipped the real file: sample4_bin.x3p is not in SURFSTREAM_SPECIMENS");
    }
    // And a file of ours with a pattern that MSB-first would read differently.
    let mut t = toy_surface(5, 3);
    t.heights_um[1] = f64::NAN;
    t.heights_um[8] = f64::NAN;
    let r = parse_surface(&formats::x3p::encode(&t).unwrap(), Format::X3p).unwrap();
    same_heights(&r.heights_um, &t.heights_um, 1e-15);
}

#[test]
fn x3p_write_round_trip_through_our_reader() {
    let mut t = toy_surface(17, 11);
    t.metadata.instrument = Some("ZeGage <Pro> & co".into());
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("pano.x3p");
    formats::write_surface(&p, &t).unwrap();
    let r = read_surface(&p).unwrap();
    assert_eq!((r.width, r.height), (17, 11));
    same_heights(&r.heights_um, &t.heights_um, 1e-15);
    assert!(rel(r.pitch_x_um, 0.5) < 1e-12 && rel(r.pitch_y_um, 0.75) < 1e-12);
    assert!(r
        .metadata
        .instrument
        .unwrap()
        .starts_with("ZeGage <Pro> & co"));
}

#[test]
fn x3p_writer_stores_incompressible_heights_and_deflates_holes() {
    // Measured f64 heights barely deflate (and inflating costs readers time): data.bin is then
    // stored; a map that is mostly NaN deflates well and is deflated. Both read back exactly,
    // the stored one through surfalize too.
    let (w, h) = (256, 200);
    let noisy = |i: usize| {
        let u = ((i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 11) as f64 / (1u64 << 53) as f64;
        47.0 + u
    };
    let mut stored = toy_surface(w, h);
    stored.heights_um = (0..w * h).map(noisy).collect();
    let mut holey = stored.clone();
    for (i, z) in holey.heights_um.iter_mut().enumerate() {
        if i % w >= 20 {
            *z = f64::NAN;
        }
    }
    let dir = tempfile::tempdir().unwrap();
    for (name, s, method) in [
        ("stored.x3p", &stored, zip::CompressionMethod::Stored),
        ("holey.x3p", &holey, zip::CompressionMethod::Deflated),
    ] {
        let p = dir.path().join(name);
        formats::write_surface(&p, s).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        let mut z = zip::ZipArchive::new(Cursor::new(bytes)).unwrap();
        assert_eq!(
            z.by_name("bindata/data.bin").unwrap().compression(),
            method,
            "{name}"
        );
        same_heights(&read_surface(&p).unwrap().heights_um, &s.heights_um, 1e-12);
    }
    let script = r#"
import sys, json, numpy as np
from surfalize import Surface
d = np.asarray(Surface.load(sys.argv[1]).data, dtype=np.float64)
print(json.dumps({"shape": list(d.shape), "sum": float(d.sum())}))
"#;
    let out = python_ok(|c| {
        c.arg("-c").arg(script).arg(dir.path().join("stored.x3p"));
    });
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["shape"], serde_json::json!([h, w]));
    let ours: f64 = stored.heights_um.iter().sum();
    assert!(rel(v["sum"].as_f64().unwrap(), ours) < 1e-12, "{v}");
}

#[test]
fn x3p_write_round_trip_through_surfalize() {
    let t = toy_surface(23, 19);
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("pano.x3p");
    formats::write_surface(&p, &t).unwrap();
    let script = r#"
import sys, json, numpy as np
from surfalize import Surface
s = Surface.load(sys.argv[1])
d = np.asarray(s.data, dtype=np.float64)
print(json.dumps({"shape": list(d.shape), "sx": s.step_x, "sy": s.step_y,
                  "data": [None if np.isnan(v) else float(v) for v in d.ravel()]}))
"#;
    let out = python_ok(|c| {
        c.arg("-c").arg(script).arg(&p);
    });
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["shape"], serde_json::json!([19, 23]));
    assert!(
        rel(v["sx"].as_f64().unwrap(), 0.5) < 1e-12 && rel(v["sy"].as_f64().unwrap(), 0.75) < 1e-12
    );
    let data: Vec<f64> = v["data"]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap_or(f64::NAN))
        .collect();
    same_heights(&data, &t.heights_um, 1e-12);
}

fn synthetic_datx() -> (tempfile::TempDir, Vec<PathBuf>) {
    let dir = tempfile::tempdir().unwrap();
    // The project's bench kit's generator, kept in the repository (tests/data/README.md).
    let script = repo_root().join("tests/data/make_synthetic_datx.py");
    let out = python_ok(|c| {
        c.arg(&script).arg(dir.path());
    });
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let files = v["files"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| PathBuf::from(f.as_str().unwrap()))
        .collect();
    (dir, files)
}

#[test]
fn datx_link_table_converters_no_data() {
    let (_dir, files) = synthetic_datx();
    assert_eq!(files.len(), 4, "fixed/vlen x contiguous/gzip");
    for f in &files {
        let s = read_surface(f).unwrap_or_else(|e| panic!("{}: {e:#}", f.display()));
        assert_eq!((s.height, s.width), (3, 4), "{}", f.display());
        assert_eq!(s.pitch_x_um, 1.0, "X Converter Parameters[1]");
        assert_eq!(s.pitch_y_um, 2.0, "Y Converter Parameters[1]");
        assert!(s.metadata.pitch_known);
        for (i, z) in s.heights_um.iter().enumerate() {
            if i == 6 {
                assert!(z.is_nan(), "No Data marker at row 1, column 2");
            } else {
                assert!((z - i as f64 * 1e-3).abs() < 1e-15, "NanoMeters -> um: {z}");
            }
        }
        assert_eq!(
            s.metadata.extra["surface_path"],
            "/Data/Surface/{00000000-0000-0000-0000-000000000001}"
        );
        assert!(rel(s.metadata.wavelength_um.unwrap(), 0.633) < 1e-12);
    }
}

#[test]
fn datx_fringes_and_decoy_surface() {
    // A file whose first /Data/Surface dataset is a decoy and whose height unit is Fringes:
    // the link table must be followed and height_m = value * S * O * lambda.
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("fringes.datx");
    let script = r#"
import sys, h5py, numpy as np
s = h5py.string_dtype()
with h5py.File(sys.argv[1], 'w') as h5:
    real = '/Data/Surface/{B}'
    md = np.array([('Root', 'Measurement', '{M}'), ('{M}', 'Surface', '{S}'), ('{S}', 'Path', real)],
                  dtype=[('Source', s), ('Link', s), ('Destination', s)])
    h5.create_dataset('MetaData', data=md)
    h5.create_dataset('/Data/Surface/{A}', data=np.full((2, 2), 99.0, 'f4'))
    z = np.array([[0, 1, 2], [3, np.nan, 5]], 'f4')
    ds = h5.create_dataset(real, data=z)
    cdt = np.dtype([('Category', s), ('BaseUnit', s), ('Parameters', h5py.vlen_dtype(np.float64))])
    def conv(cat, unit, p):
        c = np.empty(1, dtype=cdt); c[0] = (cat, unit, np.array(p, 'f8')); return c
    ds.attrs['X Converter'] = conv('LateralCat', 'Pixels', [0, 0.5e-6, 0, 0])
    ds.attrs['Y Converter'] = conv('LateralCat', 'Pixels', [0, 0.5e-6, 0, 0])
    ds.attrs['Z Converter'] = conv('HeightCat', 'Fringes', [0, 6.33e-7, 0.5, 1.0])
    ds.attrs['Unit'] = np.array(['Fringes'], dtype=s)
    ds.attrs['No Data'] = np.array([np.finfo(np.float32).max], 'f4')
"#;
    python_ok(|c| {
        c.arg("-c").arg(script).arg(&p);
    });
    let s = read_surface(&p).unwrap();
    assert_eq!((s.height, s.width), (2, 3));
    let k = 6.33e-7 * 0.5 * 1.0 * 1e6;
    assert!(s.heights_um[4].is_nan());
    for i in [0, 1, 2, 3, 5] {
        assert!(
            (s.heights_um[i] - i as f64 * k).abs() < 1e-12,
            "{}",
            s.heights_um[i]
        );
    }
    assert_eq!(s.pitch_x_um, 0.5);
}

#[test]
fn datx_chunked_gzip_big_endian_read_in_parallel() {
    // Mx writes gzip-chunked datasets; the chunks are inflated in parallel and the byte order
    // converted by the HDF5 reader. Chunks that overhang the edges (37 x 23 in 5 x 4 chunks),
    // big- and little-endian, f32 and f64, with a NaN and a No Data value.
    let dir = tempfile::tempdir().unwrap();
    let script = r#"
import sys, h5py, numpy as np
s = 'S64'
for path, dt in zip(sys.argv[1:], ['>f4', '<f4', '>f8', '<f8']):
    with h5py.File(path, 'w') as h5:
        real = '/Data/Surface/{S}'
        md = np.array([(b'Root', b'Measurement', b'{M}'), (b'{M}', b'Surface', b'{S}'), (b'{S}', b'Path', real.encode())],
                      dtype=[('Source', s), ('Link', s), ('Destination', s)])
        h5.create_dataset('MetaData', data=md)
        z = (np.arange(37 * 23).reshape(37, 23) * 0.25 - 7.0).astype(dt)
        z[3, 4] = np.nan
        z[30, 20] = np.finfo(dt).max
        ds = h5.create_dataset(real, data=z, chunks=(5, 4), compression='gzip', dtype=dt)
        cdt = np.dtype([('Category', s), ('BaseUnit', s), ('Parameters', h5py.vlen_dtype(np.float64))])
        def conv(cat, unit, p):
            c = np.empty(1, dtype=cdt); c[0] = (cat.encode(), unit.encode(), np.array(p, 'f8')); return c
        ds.attrs['X Converter'] = conv('LateralCat', 'Pixels', [0, 0.5e-6, 0, 0])
        ds.attrs['Y Converter'] = conv('LateralCat', 'Pixels', [0, 0.5e-6, 0, 0])
        ds.attrs['Unit'] = np.array([b'NanoMeters'], dtype=s)
        ds.attrs['No Data'] = np.array([np.finfo(dt).max], dt)
"#;
    let paths: Vec<PathBuf> = ["be32", "le32", "be64", "le64"]
        .iter()
        .map(|n| dir.path().join(format!("{n}.datx")))
        .collect();
    python_ok(|c| {
        c.arg("-c").arg(script).args(&paths);
    });
    for p in &paths {
        let s = read_surface(p).unwrap();
        assert_eq!((s.height, s.width), (37, 23), "{}", p.display());
        for (i, &h) in s.heights_um.iter().enumerate() {
            let (r, c) = (i / 23, i % 23);
            if (r, c) == (3, 4) || (r, c) == (30, 20) {
                assert!(h.is_nan(), "{}: ({r}, {c}) = {h}", p.display());
            } else {
                let want = (i as f64 * 0.25 - 7.0) * 1e-3;
                assert!(
                    (h - want).abs() < 1e-12,
                    "{}: ({r}, {c}) = {h}",
                    p.display()
                );
            }
        }
    }
}

#[test]
fn datx_instrument_serial_date() {
    // Mx keeps them as "Data Context.Data Attributes.*" attributes of an attribute group:
    // (a) named by the link table, variable-length strings; (b) no link, a group under
    // /Attributes, fixed-length strings; (c) the synthetic files have none: fields absent,
    // wavelength from the Z Converter.
    let dir = tempfile::tempdir().unwrap();
    let script = r#"
import sys, h5py, numpy as np
def write(path, vlen, linked):
    s = h5py.string_dtype() if vlen else 'S64'
    enc = (lambda x: x) if vlen else (lambda x: x.encode())
    real = '/Data/Surface/{S1}'
    rows = [('Root', 'Measurement', '{M}'), ('{M}', 'Surface', '{S}'), ('{S}', 'Path', real)]
    group = '/Attributes/{A1}'
    if linked:
        rows += [('{M}', 'Attributes', '{A}'), ('{A}', 'Path', group)]
    md = np.array([tuple(enc(v) for v in r) for r in rows],
                  dtype=[('Source', s), ('Link', s), ('Destination', s)])
    with h5py.File(path, 'w') as h5:
        h5.create_dataset('MetaData', data=md)
        ds = h5.create_dataset(real, data=np.arange(6, dtype='f8').reshape(2, 3))
        cdt = np.dtype([('Category', s), ('BaseUnit', s), ('Parameters', h5py.vlen_dtype(np.float64))])
        def conv(cat, unit, p):
            c = np.empty(1, dtype=cdt); c[0] = (enc(cat), enc(unit), np.array(p, 'f8')); return c
        ds.attrs['X Converter'] = conv('LateralCat', 'Pixels', [0, 1e-6, 0, 0])
        ds.attrs['Y Converter'] = conv('LateralCat', 'Pixels', [0, 1e-6, 0, 0])
        ds.attrs['Z Converter'] = conv('HeightCat', 'MicroMeters', [0, 5.5e-7, 0.5, 1.0])
        ds.attrs['Unit'] = np.array([enc('MicroMeters')], dtype=s)
        if not linked:
            h5.create_group('/Attributes/{A0}')   # an empty decoy group first
        g = h5.create_group(group)
        p = 'Data Context.Data Attributes.'
        g.attrs[p + 'System Type'] = np.array([enc('NewView 9000')], dtype=s)
        g.attrs[p + 'System Serial Number'] = np.array([enc('NV-12345')], dtype=s)
        g.attrs[p + 'Time Stamp'] = np.array([enc('2025-03-14 09:26:53')], dtype=s)
        g.attrs[p + 'Acquisition Mode'] = np.array([enc('CSI')], dtype=s)
        g.attrs[p + 'Camera Gain:Value'] = np.array([2.0])
write(sys.argv[1], True, True)
write(sys.argv[2], False, False)
"#;
    let (a, b) = (
        dir.path().join("linked.datx"),
        dir.path().join("group.datx"),
    );
    python_ok(|c| {
        c.arg("-c").arg(script).arg(&a).arg(&b);
    });
    for (f, group) in [(&a, "/Attributes/{A1}"), (&b, "/Attributes/{A1}")] {
        let s = read_surface(f).unwrap_or_else(|e| panic!("{}: {e:#}", f.display()));
        let m = &s.metadata;
        assert_eq!(
            m.instrument.as_deref(),
            Some("NewView 9000"),
            "{}",
            f.display()
        );
        assert_eq!(m.serial.as_deref(), Some("NV-12345"));
        assert_eq!(m.date.as_deref(), Some("2025-03-14 09:26:53"));
        assert_eq!(m.extra["acquisition_mode"], "CSI");
        assert_eq!(m.extra["attributes_path"], group);
        assert!((m.wavelength_um.unwrap() - 0.55).abs() < 1e-12);
        assert_eq!(s.heights_um[5], 5.0);
    }
    let (_d, synthetic) = synthetic_datx();
    let m = read_surface(&synthetic[0]).unwrap().metadata;
    assert_eq!((m.instrument, m.serial, m.date), (None, None, None));
    assert!(!m.extra.contains_key("attributes_path"));
}

#[test]
fn datx_corrupt_and_truncated() {
    let (_dir, files) = synthetic_datx();
    let bytes = std::fs::read(&files[0]).unwrap();
    for cut in [0, 8, 100, bytes.len() / 2, bytes.len() - 1] {
        assert!(
            parse_surface(&bytes[..cut], Format::Datx).is_err(),
            "truncated at {cut}"
        );
    }
    let e = format!(
        "{:#}",
        parse_surface(b"not an hdf5 file at all", Format::Datx).unwrap_err()
    );
    assert!(e.contains("HDF5"), "{e}");
}

fn metropro_header(w: u16, h: u16, phase_res: i16) -> Vec<u8> {
    let mut b = vec![0u8; 834];
    b[0..4].copy_from_slice(&[0x88, 0x1B, 0x03, 0x6F]);
    b[4..6].copy_from_slice(&1u16.to_be_bytes());
    b[6..10].copy_from_slice(&834u32.to_be_bytes());
    b[68..70].copy_from_slice(&w.to_be_bytes());
    b[70..72].copy_from_slice(&h.to_be_bytes());
    b[72..76].copy_from_slice(&(4 * w as u32 * h as u32).to_be_bytes());
    b[164..168].copy_from_slice(&0.5f32.to_be_bytes());
    b[168..172].copy_from_slice(&6.33e-7f32.to_be_bytes());
    b[176..180].copy_from_slice(&1.0f32.to_be_bytes());
    b[184..188].copy_from_slice(&1e-6f32.to_be_bytes());
    b[218..220].copy_from_slice(&phase_res.to_be_bytes());
    b
}

#[test]
fn metropro_phase_res_table_sign_invalid_and_lies() {
    for (phase_res, r) in [(0i16, 4096.0), (1, 32768.0), (2, 131072.0)] {
        let mut b = metropro_header(2, 1, phase_res);
        b.extend_from_slice(&1000i32.to_be_bytes());
        b.extend_from_slice(&2147483640i32.to_be_bytes());
        let s = parse_surface(&b, Format::MetroPro).unwrap();
        let expect = 1000.0 * 0.5f32 as f64 * 6.33e-7f32 as f64 / r * 1e6;
        assert!(
            rel(s.heights_um[0], expect) < 1e-15,
            "phase_res {phase_res}"
        );
        assert!(s.heights_um[1].is_nan());
        // sign != 0 negates.
        b[232..234].copy_from_slice(&1i16.to_be_bytes());
        assert!(
            rel(
                parse_surface(&b, Format::MetroPro).unwrap().heights_um[0],
                -expect
            ) < 1e-15
        );
    }
    let mut b = metropro_header(2, 1, 3);
    b.extend_from_slice(&[0; 8]);
    assert!(
        format!("{:#}", parse_surface(&b, Format::MetroPro).unwrap_err()).contains("phase_res")
    );
    // Counts larger than the file.
    let mut b = metropro_header(10000, 10000, 1);
    b.extend_from_slice(&[0; 8]);
    let e = format!("{:#}", parse_surface(&b, Format::MetroPro).unwrap_err());
    assert!(e.contains("phase data") && e.contains("only"), "{e}");
    // Magic and header size disagree.
    let mut b = metropro_header(2, 1, 1);
    b[3] = 0x71;
    assert!(
        format!("{:#}", parse_surface(&b, Format::MetroPro).unwrap_err())
            .contains("inconsistent header")
    );
    // cn_n_bytes lies.
    let mut b = metropro_header(2, 1, 1);
    b[72..76].copy_from_slice(&12u32.to_be_bytes());
    assert!(
        format!("{:#}", parse_surface(&b, Format::MetroPro).unwrap_err()).contains("cn_n_bytes")
    );
}

#[test]
fn truncated_specimens_fail_cleanly() {
    for (name, format) in [
        ("metropro-1.dat", Format::MetroPro),
        ("sur-2.sur", Format::Sur),
        ("x3p-2.x3p", Format::X3p),
    ] {
        let b = std::fs::read(specimen(name)).unwrap();
        for cut in [0, 3, 100, 511, 600, b.len() / 2, b.len() - 1] {
            let e = parse_surface(&b[..cut], format);
            assert!(e.is_err(), "{name} cut at {cut} read without error");
        }
    }
    // The error from read_surface names the file.
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("cut.sur");
    std::fs::write(&p, &std::fs::read(specimen("sur-2.sur")).unwrap()[..1000]).unwrap();
    let e = format!("{:#}", read_surface(&p).unwrap_err());
    assert!(e.contains("cut.sur") && e.contains("point data"), "{e}");
}

#[test]
fn xyz_regular_grid_with_gaps() {
    // Table-3-like columns, a missing node and a NaN height; shuffled order; comma separated.
    let mut lines = vec!["# x y z (um)".to_string(), "X,Y,Z".to_string()];
    for r in 0..3 {
        for c in 0..4 {
            if (r, c) == (1, 1) {
                continue;
            }
            let z = if (r, c) == (2, 3) {
                "nan".to_string()
            } else {
                format!("{}", r * 10 + c)
            };
            lines.push(format!(
                "{:.6},{:.6},{z}",
                100.0 + c as f64 * 0.8148,
                50.0 + r as f64 * 1.5
            ));
        }
    }
    lines.swap(3, 9);
    let s = parse_surface(lines.join("\n").as_bytes(), Format::Xyz).unwrap();
    assert_eq!((s.width, s.height), (4, 3));
    assert!(rel(s.pitch_x_um, 0.8148) < 1e-6 && rel(s.pitch_y_um, 1.5) < 1e-9);
    assert!(s.heights_um[5].is_nan() && s.heights_um[11].is_nan());
    assert_eq!(s.heights_um[6], 12.0);
    assert_eq!(s.invalid_count(), 2);
    // Off-grid point, duplicate point, sparse cloud: errors.
    assert!(format!(
        "{:#}",
        parse_surface(b"0 0 1\n1 0 1\n2.5 0 1\n", Format::Xyz).unwrap_err()
    )
    .contains("not on the regular grid"));
    assert!(format!(
        "{:#}",
        parse_surface(b"0 0 1\n1 0 1\n1 0 2\n", Format::Xyz).unwrap_err()
    )
    .contains("two points"));
    assert!(format!(
        "{:#}",
        parse_surface(b"0 0 1\n1 0 1\n100000 100000 1\n", Format::Xyz).unwrap_err()
    )
    .contains("sparse"));
    assert!(format!(
        "{:#}",
        parse_surface(b"0 0 1\n1 0 oops\n", Format::Xyz).unwrap_err()
    )
    .contains("line 2"));
}

#[test]
fn npy_and_unknown_extension() {
    let dir = tempfile::tempdir().unwrap();
    let t = toy_surface(6, 5);
    let p = dir.path().join("a.npy");
    formats::write_surface(&p, &t).unwrap();
    let r = read_surface(&p).unwrap();
    same_heights(&r.heights_um, &t.heights_um, 0.0);
    assert!(!r.metadata.pitch_known);
    let e = format!("{:#}", read_surface(&dir.path().join("a.png")).unwrap_err());
    assert!(e.contains("a.png") && e.contains("unsupported"), "{e}");
}

/// Found by `cargo fuzz run datx` (2026-11-21): /MetaData dataspaces claiming 3 TB and 8 GB
/// in files of a few KB. The reader refuses them before allocating, with an error naming the
/// file and the dataset (the 8 GB one was allocated and zeroed before the size check).
#[test]
fn datx_lying_dataspace_is_a_clear_error() {
    for name in [
        "fuzz-datx-3tb-dataspace.datx",
        "fuzz-datx-8gb-metadata.datx",
    ] {
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/fixtures")
            .join(name);
        let err = format!("{:#}", read_surface(&path).unwrap_err());
        assert!(err.contains(name), "{err}");
        assert!(err.contains("/MetaData: declares"), "{err}");
    }
}

/// Inputs that lie (issue 36): an X3P with two descriptions and a MetroPro file whose
/// wavelength is negative (which flipped every height's sign) are refused, naming what.
#[test]
fn two_main_xml_and_a_negative_wavelength_are_refused() {
    let mut parts = x3p_parts(&specimen("x3p-2.x3p"));
    let main = parts
        .iter()
        .find(|(n, _)| n == "main.xml")
        .expect("main.xml")
        .1
        .clone();
    parts.push(("copy/main.xml".to_string(), main));
    let e = format!(
        "{:#}",
        parse_surface(&x3p_from_parts(&parts), Format::X3p).expect_err("two main.xml read")
    );
    assert!(
        e.contains("2 main.xml entries") && e.contains("copy/main.xml"),
        "{e}"
    );

    let mut dat = std::fs::read(specimen("metropro-1.dat")).unwrap();
    let wavelength = f32::from_be_bytes(dat[168..172].try_into().unwrap());
    assert!(wavelength > 0.0);
    dat[168..172].copy_from_slice(&(-wavelength).to_be_bytes());
    let e = format!(
        "{:#}",
        parse_surface(&dat, Format::MetroPro).expect_err("a negative wavelength was read")
    );
    assert!(e.contains("wavelength_in") && e.contains("positive"), "{e}");
}

/// Issue 36: the point data entry's size in the zip directory is checked against main.xml's
/// MatrixDimension before anything is allocated or inflated (a 3 MB file declaring 20 000 x
/// 20 000 points took 30 s and 3 GB before its short data was found). Here the data holds one
/// row fewer than declared: refused naming both sizes, not after inflating.
#[test]
fn x3p_point_data_shorter_than_declared_is_refused_from_the_zip_directory() {
    let (cols, rows) = (64usize, 64usize);
    let data: Vec<u8> = (0..cols * (rows - 1))
        .flat_map(|i| ((i % 97) as f32 * 1e-7).to_le_bytes())
        .collect();
    let link = "<DataLink><PointDataLink>bindata/data.bin</PointDataLink></DataLink>";
    let xml = x3p_main_xml("ISO5436_2", cols, rows, link);
    let bytes = x3p_from_parts(&[
        ("main.xml".into(), xml.into_bytes()),
        ("bindata/data.bin".into(), data.clone()),
    ]);
    let e = format!(
        "{:#}",
        parse_surface(&bytes, Format::X3p).expect_err("short point data read")
    );
    assert!(
        e.contains(&format!("declares {} bytes of point data", cols * rows * 4))
            && e.contains(&format!(
                "archive declares zip entry 'bindata/data.bin' as {} bytes",
                data.len()
            )),
        "{e}"
    );
}
