//! Golden tests for the readers of issue 12's "open" group: Gwyddion .gsf and .gwy, ISO 25178-71
//! .sdf (ASCII and binary), TrueMap / GelSight .tmd and Alicona .al3d.
//!
//! Every fixture is written here from the format's published layout (see each reader's module
//! doc), from one asymmetric 5 x 3 surface with two points not measured, so a transpose, a flip
//! or a wrong unit fails. Each reader must give the shape, pitch, every height, the invalid
//! count, the orientation, and Sa / Sq / Sp / Sv equal to a plain-loop computation over the valid
//! points. Truncated and lying files give clear errors; a deterministic corruption sweep
//! (every truncation, thousands of seeded byte mutations) stands in for the fuzz targets on
//! machines without nightly Rust: any panic fails the test.

use surfstream_core::metrology::{params, Grid};
use surfstream_io::formats::{parse_surface, Format, Surface};

const COLS: usize = 5;
const ROWS: usize = 3;
const PITCH_X_UM: f64 = 0.5;
const PITCH_Y_UM: f64 = 0.75;
/// Not measured in every fixture: (row 1, col 2) and (row 2, col 4).
const INVALID: [(usize, usize); 2] = [(1, 2), (2, 4)];

/// The true heights in um, row-major (row index = y); None = not measured. Distinct values,
/// no symmetry: row 0 col 1 differs from row 1 col 0 and from row 2 col 1.
fn truth() -> Vec<Option<f64>> {
    let mut z = Vec::new();
    for r in 0..ROWS {
        for c in 0..COLS {
            if INVALID.contains(&(r, c)) {
                z.push(None);
            } else {
                z.push(Some(
                    0.25 * c as f64 - 1.5 * r as f64
                        + 0.125 * (r * r * c) as f64
                        + 0.0625 * c as f64 * c as f64,
                ));
            }
        }
    }
    z
}

fn rel(a: f64, b: f64) -> f64 {
    if a == b {
        0.0
    } else {
        (a - b).abs() / a.abs().max(b.abs())
    }
}

/// Checks a read surface against the truth; `stored` maps a true height (um) to what the file
/// can hold (float32 rounding, integer steps), as read back in um.
fn check(s: &Surface, stored: impl Fn(f64) -> f64, format: &str) {
    assert_eq!(s.metadata.format, format);
    assert_eq!((s.height, s.width), (ROWS, COLS), "rows x cols");
    assert!(
        rel(s.pitch_x_um, PITCH_X_UM) < 1e-6,
        "pitch x {}",
        s.pitch_x_um
    );
    assert!(
        rel(s.pitch_y_um, PITCH_Y_UM) < 1e-6,
        "pitch y {}",
        s.pitch_y_um
    );
    let expected: Vec<Option<f64>> = truth().into_iter().map(|z| z.map(&stored)).collect();
    for (i, (got, want)) in s.heights_um.iter().zip(&expected).enumerate() {
        match want {
            None => assert!(
                got.is_nan(),
                "point {i} (row {}, col {}) should be invalid, got {got}",
                i / COLS,
                i % COLS
            ),
            Some(w) => assert!(
                (got - w).abs() <= 1e-9 * w.abs().max(1.0),
                "point {i} (row {}, col {}): got {got}, expected {w}",
                i / COLS,
                i % COLS
            ),
        }
    }
    assert_eq!(s.invalid_count(), INVALID.len());
    // Orientation, spelled out: row 0 col 1 and row 1 col 0 (a transpose swaps them), row 2
    // col 0 (a flip in y moves it to row 0).
    let at = |r: usize, c: usize| s.heights_um[r * COLS + c];
    assert!(
        (at(0, 1) - stored(0.3125)).abs() < 1e-9,
        "row 0 col 1 = {}",
        at(0, 1)
    );
    assert!(
        (at(1, 0) - stored(-1.5)).abs() < 1e-9,
        "row 1 col 0 = {}",
        at(1, 0)
    );
    assert!(
        (at(2, 0) - stored(-3.0)).abs() < 1e-9,
        "row 2 col 0 = {}",
        at(2, 0)
    );

    // Sa, Sq, Sp, Sv by plain loops over the expected valid heights (not the reader's output).
    let valid: Vec<f64> = expected.iter().flatten().copied().collect();
    let n = valid.len() as f64;
    let mut mean = 0.0;
    for z in &valid {
        mean += z;
    }
    mean /= n;
    let (mut sa, mut sq, mut sp, mut sv) = (0.0f64, 0.0f64, f64::MIN, f64::MAX);
    for z in &valid {
        let c = z - mean;
        sa += c.abs();
        sq += c * c;
        sp = sp.max(c);
        sv = sv.min(c);
    }
    let (sa, sq, sv) = (sa / n, (sq / n).sqrt(), -sv);
    let p =
        params(&Grid::new(&s.heights_um, s.height, s.width, s.pitch_x_um, s.pitch_y_um).unwrap())
            .unwrap();
    for (name, got, want) in [
        ("Sa", p.sa, sa),
        ("Sq", p.sq, sq),
        ("Sp", p.sp, sp),
        ("Sv", p.sv, sv),
    ] {
        assert!(
            rel(got, want) < 1e-6,
            "{name}: params {got}, plain loops {want}"
        );
    }
}

/// What a float32 in `unit_um` micrometres holds of a true height in um.
fn via_f32(unit_um: f64) -> impl Fn(f64) -> f64 {
    move |z| ((z / unit_um) as f32) as f64 * unit_um
}

/// `data` with the first `from` replaced by `to` (same length: offsets stay).
fn replace_bytes(data: &[u8], from: &[u8], to: &[u8]) -> Vec<u8> {
    assert_eq!(from.len(), to.len());
    let at = data
        .windows(from.len())
        .position(|w| w == from)
        .expect("pattern in fixture");
    let mut out = data.to_vec();
    out[at..at + to.len()].copy_from_slice(to);
    out
}

fn err(data: &[u8], format: Format) -> String {
    match parse_surface(data, format) {
        Ok(s) => panic!(
            "{format:?}: expected an error, read {} x {}",
            s.height, s.width
        ),
        Err(e) => format!("{e:#}"),
    }
}

/// Every truncation and `mutations` seeded single-byte changes: Ok or Err, never a panic, and
/// an Ok surface is consistent.
fn corruption_sweep(fixture: &[u8], format: Format, mutations: usize) {
    for len in 0..fixture.len() {
        if let Ok(s) = parse_surface(&fixture[..len], format) {
            assert_eq!(s.heights_um.len(), s.width * s.height);
        }
    }
    let mut state: u64 = 0x9E37_79B9_7F4A_7C15 ^ fixture.len() as u64;
    let mut next = || {
        // Knuth's MMIX LCG; the high bits are the good ones.
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 33) as usize
    };
    for _ in 0..mutations {
        let mut bytes = fixture.to_vec();
        let pos = next() % bytes.len();
        // Half the time a boundary value (0, 0xFF, 0x7F, 0x80), else any byte.
        let v = next();
        bytes[pos] = if v % 2 == 0 {
            [0u8, 0xFF, 0x7F, 0x80][(v >> 1) % 4]
        } else {
            (v >> 1) as u8
        };
        if let Ok(s) = parse_surface(&bytes, format) {
            assert_eq!(s.heights_um.len(), s.width * s.height);
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Gwyddion Simple Field .gsf

fn gsf_fixture(header_extra: &str, xres: usize, yres: usize) -> Vec<u8> {
    let mut out = format!(
        "Gwyddion Simple Field 1.0\nXRes = {xres}\nYRes = {yres}\nXReal = {}\nYReal = {}\nXYUnits = m\nZUnits = m\nTitle = open fixture\n{header_extra}",
        COLS as f64 * PITCH_X_UM * 1e-6,
        ROWS as f64 * PITCH_Y_UM * 1e-6
    )
    .into_bytes();
    // One to four NULs, so the data starts at a multiple of 4.
    out.push(0);
    while out.len() % 4 != 0 {
        out.push(0);
    }
    for z in truth() {
        let v = z.map_or(f32::NAN, |z| (z * 1e-6) as f32);
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

#[test]
fn gsf_golden() {
    // Header lengths that need 1, 2, 3 and 4 NULs of padding.
    for pad in ["", "A=1\n", "AB=1\n", "ABC=1\n"] {
        let data = gsf_fixture(pad, COLS, ROWS);
        let s = parse_surface(&data, Format::Gsf).unwrap();
        check(&s, via_f32(1e6), "gsf");
        assert_eq!(
            s.metadata.extra.get("Title").map(String::as_str),
            Some("open fixture")
        );
    }
    assert_eq!(Format::from_path("a/b.GSF".as_ref()).unwrap(), Format::Gsf);
}

#[test]
fn gsf_truncated_lying_and_wrong() {
    let data = gsf_fixture("", COLS, ROWS);
    let e = err(&data[..data.len() - 3], Format::Gsf);
    assert!(e.contains("XRes x YRes = 5 x 3 needs 60 bytes"), "{e}");
    let e = err(&gsf_fixture("", 100_000, 100_000), Format::Gsf);
    assert!(e.contains("XRes x YRes = 100000 x 100000"), "{e}");
    let e = err(&gsf_fixture("", 0, ROWS), Format::Gsf);
    assert!(e.contains("'XRes' is '0'"), "{e}");
    let e = err(b"Gwyddion Simple Field 1.0\nYRes = 3\n\0\0", Format::Gsf);
    assert!(e.contains("'XRes' is missing"), "{e}");
    let e = err(b"Gwyddion Simple Field 2.0\n", Format::Gsf);
    assert!(e.contains("magic line"), "{e}");
    let e = err(
        &replace_bytes(&data, b"ZUnits = m", b"ZUnits = V"),
        Format::Gsf,
    );
    assert!(e.contains("'ZUnits' is 'V'"), "{e}");
}

#[test]
fn gsf_corruption_sweep() {
    corruption_sweep(&gsf_fixture("", COLS, ROWS), Format::Gsf, 3000);
}

// ---------------------------------------------------------------------------------------------
// Gwyddion native .gwy

/// A component of a serialized GWY object: name, type byte, value bytes.
fn component(out: &mut Vec<u8>, name: &str, kind: u8, value: &[u8]) {
    out.extend_from_slice(name.as_bytes());
    out.push(0);
    out.push(kind);
    out.extend_from_slice(value);
}

/// A serialized object: type name, NUL, u32 size of the components, the components.
fn object(type_name: &str, components: &[u8]) -> Vec<u8> {
    let mut out = type_name.as_bytes().to_vec();
    out.push(0);
    out.extend_from_slice(&(components.len() as u32).to_le_bytes());
    out.extend_from_slice(components);
    out
}

fn si_unit(unit: &str) -> Vec<u8> {
    let mut c = Vec::new();
    let mut s = unit.as_bytes().to_vec();
    s.push(0);
    component(&mut c, "unitstr", b's', &s);
    object("GwySIUnit", &c)
}

fn data_field(xres: i32, yres: i32, values: &[f64], claimed_count: u32) -> Vec<u8> {
    let mut c = Vec::new();
    component(&mut c, "xres", b'i', &xres.to_le_bytes());
    component(&mut c, "yres", b'i', &yres.to_le_bytes());
    component(
        &mut c,
        "xreal",
        b'd',
        &(COLS as f64 * PITCH_X_UM * 1e-6).to_le_bytes(),
    );
    component(
        &mut c,
        "yreal",
        b'd',
        &(ROWS as f64 * PITCH_Y_UM * 1e-6).to_le_bytes(),
    );
    component(&mut c, "xoff", b'd', &0f64.to_le_bytes());
    component(&mut c, "si_unit_xy", b'o', &si_unit("m"));
    component(&mut c, "si_unit_z", b'o', &si_unit("m"));
    let mut d = claimed_count.to_le_bytes().to_vec();
    for v in values {
        d.extend_from_slice(&v.to_le_bytes());
    }
    component(&mut c, "data", b'D', &d);
    object("GwyDataField", &c)
}

/// A container as Gwyddion saves one: a second channel after the first, a mask on the first
/// (1 = masked), a title, a bool and an int array it does not need. Masked points hold a finite
/// height (GWY files may not hold NaN): only the mask makes them invalid.
fn gwy_fixture_with(xres: i32, yres: i32, claimed_count: u32) -> Vec<u8> {
    let heights: Vec<f64> = truth()
        .iter()
        .map(|z| z.map_or(123.0, |z| z * 1e-6))
        .collect();
    let mask: Vec<f64> = truth()
        .iter()
        .map(|z| if z.is_some() { 0.0 } else { 1.0 })
        .collect();
    let mut c = Vec::new();
    component(&mut c, "/0/data/title", b's', b"Height\0");
    component(&mut c, "/0/data/visible", b'b', &[1]);
    component(
        &mut c,
        "/0/meta",
        b'I',
        &[2, 0, 0, 0, 7, 0, 0, 0, 9, 0, 0, 0],
    );
    component(&mut c, "/1/data", b'o', &data_field(2, 1, &[5.0, 6.0], 2));
    component(
        &mut c,
        "/0/data",
        b'o',
        &data_field(xres, yres, &heights, claimed_count),
    );
    component(
        &mut c,
        "/0/mask",
        b'o',
        &data_field(COLS as i32, ROWS as i32, &mask, 15),
    );
    let mut out = b"GWYP".to_vec();
    out.extend_from_slice(&object("GwyContainer", &c));
    out
}

fn gwy_fixture() -> Vec<u8> {
    gwy_fixture_with(COLS as i32, ROWS as i32, (COLS * ROWS) as u32)
}

#[test]
fn gwy_golden() {
    let s = parse_surface(&gwy_fixture(), Format::Gwy).unwrap();
    check(&s, |z| z * 1e-6 * 1e6, "gwy");
    assert_eq!(
        s.metadata.extra.get("title").map(String::as_str),
        Some("Height")
    );
    assert_eq!(
        s.metadata.extra.get("channel").map(String::as_str),
        Some("0")
    );
    assert!(s.metadata.warnings.is_empty(), "{:?}", s.metadata.warnings);
}

#[test]
fn gwy_truncated_lying_and_wrong() {
    let data = gwy_fixture();
    let e = err(&data[..data.len() / 2], Format::Gwy);
    assert!(e.contains("object 'GwyContainer' claims"), "{e}");
    // xres x yres that the data array does not hold.
    let e = err(&gwy_fixture_with(100_000, 100_000, 15), Format::Gwy);
    assert!(e.contains("expected xres x yres = 100000 x 100000"), "{e}");
    // A data array count the object cannot hold.
    let e = err(
        &gwy_fixture_with(COLS as i32, ROWS as i32, u32::MAX),
        Format::Gwy,
    );
    assert!(e.contains("component 'data'"), "{e}");
    let e = err(&gwy_fixture_with(-5, ROWS as i32, 15), Format::Gwy);
    assert!(e.contains("'xres' is -5"), "{e}");
    let e = err(b"GWYO\0\0\0\0", Format::Gwy);
    assert!(e.contains("GWYO"), "{e}");
    let mut c = Vec::new();
    component(&mut c, "/0/graph", b's', b"x\0");
    let mut empty = b"GWYP".to_vec();
    empty.extend_from_slice(&object("GwyContainer", &c));
    let e = err(&empty, Format::Gwy);
    assert!(e.contains("no channel"), "{e}");
    // Nesting deep enough to overflow a careless recursive reader.
    let mut deep = object("GwySIUnit", &[]);
    for _ in 0..2_000 {
        let mut c = Vec::new();
        component(&mut c, "o", b'o', &deep);
        deep = object("GwyContainer", &c);
    }
    let mut data = b"GWYP".to_vec();
    data.extend_from_slice(&deep);
    let e = err(&data, Format::Gwy);
    assert!(e.contains("nested deeper"), "{e}");
}

#[test]
fn gwy_corruption_sweep() {
    corruption_sweep(&gwy_fixture(), Format::Gwy, 4000);
}

// ---------------------------------------------------------------------------------------------
// ISO 25178-71 .sdf

/// Heights stored as int16 steps of 1/16 um (Zscale = 62.5 nm): every true height is exact.
const SDF_ZSCALE_M: f64 = 62.5e-9;

fn sdf_ascii(magic: &str, num_points: usize, num_profiles: usize, extra: &str) -> Vec<u8> {
    let mut s = format!(
        "{magic}\nManufacID = Fixture\nCreateDate = 241120261200\nModDate = 241120261200\nNumPoints = {num_points}\nNumProfiles = {num_profiles}\nXscale = {:e}\nYscale = {:e}\nZscale = {SDF_ZSCALE_M:e}\nZresolution = -1\nCompression = 0\nDataType = 5\nCheckType = 0\n{extra}*\n",
        PITCH_X_UM * 1e-6,
        PITCH_Y_UM * 1e-6
    );
    for (i, z) in truth().iter().enumerate() {
        match z {
            Some(z) => s.push_str(&format!("{} ", (z * 1e-6 / SDF_ZSCALE_M).round() as i64)),
            None => s.push_str("BAD "),
        }
        if i % COLS == COLS - 1 {
            s.push('\n');
        }
    }
    s.push_str("*\n<OperatorName>Tom Jones</OperatorName>\n*\n");
    s.into_bytes()
}

fn sdf_binary(num_points: u16, num_profiles: u16, data_type: u8, compression: u8) -> Vec<u8> {
    let mut out = b"bISO-1.0".to_vec();
    out.extend_from_slice(b"Fixture\0\0\0");
    out.extend_from_slice(b"241120261200");
    out.extend_from_slice(b"241120261200");
    out.extend_from_slice(&num_points.to_le_bytes());
    out.extend_from_slice(&num_profiles.to_le_bytes());
    out.extend_from_slice(&(PITCH_X_UM * 1e-6).to_le_bytes());
    out.extend_from_slice(&(PITCH_Y_UM * 1e-6).to_le_bytes());
    let zscale = if data_type == 7 { 1e-6 } else { SDF_ZSCALE_M };
    out.extend_from_slice(&zscale.to_le_bytes());
    out.extend_from_slice(&(-1f64).to_le_bytes());
    out.extend_from_slice(&[compression, data_type, 0]);
    assert_eq!(out.len(), 81);
    for z in truth() {
        match data_type {
            // 5, and int16 points under the wrong DataType of the error cases.
            5 | 9 => {
                let v = z.map_or(i16::MIN, |z| (z * 1e-6 / SDF_ZSCALE_M).round() as i16);
                out.extend_from_slice(&v.to_le_bytes());
            }
            6 => {
                let v = z.map_or(i32::MIN, |z| (z * 1e-6 / SDF_ZSCALE_M).round() as i32);
                out.extend_from_slice(&v.to_le_bytes());
            }
            7 => out.extend_from_slice(&z.unwrap_or(f64::NAN).to_le_bytes()),
            _ => unreachable!("fixture data types: 5, 6, 7 (9 for errors)"),
        }
    }
    out
}

#[test]
fn sdf_golden_ascii_and_binary() {
    // int16 steps of 62.5 nm hold every true height exactly.
    let steps = |z: f64| (z * 1e-6 / SDF_ZSCALE_M).round() * SDF_ZSCALE_M * 1e6;
    for magic in ["aISO-1.0", "aBCR-1.0"] {
        let s = parse_surface(&sdf_ascii(magic, COLS, ROWS, ""), Format::Sdf).unwrap();
        check(&s, steps, "sdf");
        assert!(s
            .metadata
            .extra
            .get("trailer")
            .is_some_and(|t| t.contains("Tom Jones")));
    }
    for data_type in [5, 6] {
        let s = parse_surface(
            &sdf_binary(COLS as u16, ROWS as u16, data_type, 0),
            Format::Sdf,
        )
        .unwrap();
        check(&s, steps, "sdf");
    }
    let s = parse_surface(&sdf_binary(COLS as u16, ROWS as u16, 7, 0), Format::Sdf).unwrap();
    check(&s, |z| z, "sdf");
}

#[test]
fn sdf_truncated_lying_and_wrong() {
    let b = sdf_binary(COLS as u16, ROWS as u16, 5, 0);
    let e = err(&b[..b.len() - 1], Format::Sdf);
    assert!(e.contains("point data"), "{e}");
    let e = err(&sdf_binary(u16::MAX, u16::MAX, 6, 0), Format::Sdf);
    assert!(e.contains("point data") && e.contains("needs bytes"), "{e}");
    let e = err(&sdf_binary(COLS as u16, ROWS as u16, 5, 1), Format::Sdf);
    assert!(e.contains("compressed SDF is not supported"), "{e}");
    let e = err(&sdf_binary(COLS as u16, ROWS as u16, 9, 0), Format::Sdf);
    assert!(e.contains("'DataType' is 9"), "{e}");
    let e = err(&sdf_binary(0, ROWS as u16, 5, 0), Format::Sdf);
    assert!(e.contains("'NumPoints' x 'NumProfiles' are 0 x 3"), "{e}");
    let e = err(&sdf_ascii("aISO-1.0", 100_000, 100_000, ""), Format::Sdf);
    assert!(
        e.contains("15 values, expected NumPoints x NumProfiles = 100000 x 100000"),
        "{e}"
    );
    let e = err(&sdf_ascii("aISO-1.0", 4, ROWS, ""), Format::Sdf);
    assert!(e.contains("more than NumPoints x NumProfiles = 12"), "{e}");
    let a = sdf_ascii("aISO-1.0", COLS, ROWS, "");
    let text = String::from_utf8_lossy(&a).replace("NumPoints = 5\n", "");
    let e = err(text.as_bytes(), Format::Sdf);
    assert!(e.contains("'NumPoints' is missing"), "{e}");
    let second_star = a
        .iter()
        .enumerate()
        .filter(|(_, &b)| b == b'*')
        .nth(1)
        .unwrap()
        .0;
    let e = err(&a[..second_star], Format::Sdf);
    assert!(e.contains("data section"), "{e}");
    let e = err(b"xISO-1.0", Format::Sdf);
    assert!(e.contains("magic"), "{e}");
}

#[test]
fn sdf_corruption_sweep() {
    corruption_sweep(&sdf_ascii("aISO-1.0", COLS, ROWS, ""), Format::Sdf, 3000);
    corruption_sweep(
        &sdf_binary(COLS as u16, ROWS as u16, 5, 0),
        Format::Sdf,
        3000,
    );
    corruption_sweep(
        &sdf_binary(COLS as u16, ROWS as u16, 7, 0),
        Format::Sdf,
        2000,
    );
}

// ---------------------------------------------------------------------------------------------
// TrueMap / GelSight .tmd

fn tmd_fixture(comment: &[u8], cols: u32, rows: u32) -> Vec<u8> {
    let mut out = b"Binary TrueMap Data File v2.0\r\n\0".to_vec();
    out.extend_from_slice(comment);
    out.push(0);
    out.extend_from_slice(&cols.to_le_bytes());
    out.extend_from_slice(&rows.to_le_bytes());
    out.extend_from_slice(&((COLS as f64 * PITCH_X_UM * 1e-3) as f32).to_le_bytes());
    out.extend_from_slice(&((ROWS as f64 * PITCH_Y_UM * 1e-3) as f32).to_le_bytes());
    out.extend_from_slice(&0.25f32.to_le_bytes());
    out.extend_from_slice(&0f32.to_le_bytes());
    for z in truth() {
        let v = z.map_or(f32::NAN, |z| (z * 1e-3) as f32);
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

#[test]
fn tmd_golden_truemap_and_gelsight_comments() {
    // TrueMap v6: a 24-byte comment field ending "\r\n\0"; GelSight: just the NUL.
    for comment in [&b"Created by TrueMap v6\r\n"[..], &b""[..]] {
        let s =
            parse_surface(&tmd_fixture(comment, COLS as u32, ROWS as u32), Format::Tmd).unwrap();
        check(&s, via_f32(1e3), "tmd");
        assert_eq!(
            s.metadata.extra.get("offset_x_um").map(String::as_str),
            Some("250")
        );
    }
}

#[test]
fn tmd_truncated_lying_and_wrong() {
    let data = tmd_fixture(b"", COLS as u32, ROWS as u32);
    let e = err(&data[..data.len() - 2], Format::Tmd);
    assert!(e.contains("heights (cols x rows float32)"), "{e}");
    let e = err(&tmd_fixture(b"", 100_000, 100_000), Format::Tmd);
    assert!(
        e.contains("heights (cols x rows float32)") && e.contains("needs bytes"),
        "{e}"
    );
    let e = err(&tmd_fixture(b"", 0, 3), Format::Tmd);
    assert!(e.contains("'cols' x 'rows' are 0 x 3"), "{e}");
    let e = err(&data[..40], Format::Tmd);
    assert!(e.contains("'rows'") || e.contains("'cols'"), "{e}");
    let e = err(b"Binary TrueMap Data File v2.0\r\n", Format::Tmd);
    assert!(e.contains("magic line end"), "{e}");
    let e = err(b"Binary TrueMap Data File v2.0\r\n\0no nul", Format::Tmd);
    assert!(e.contains("comment"), "{e}");
}

#[test]
fn tmd_corruption_sweep() {
    corruption_sweep(
        &tmd_fixture(b"Created by TrueMap v6\r\n", COLS as u32, ROWS as u32),
        Format::Tmd,
        3000,
    );
}

// ---------------------------------------------------------------------------------------------
// Alicona .al3d

/// One 52-byte tag: key (20, NUL-padded), value (30, NUL-padded), CR LF.
fn al3d_tag(out: &mut Vec<u8>, key: &str, value: &str) {
    let mut k = key.as_bytes().to_vec();
    k.resize(20, 0);
    let mut v = value.as_bytes().to_vec();
    v.resize(30, 0);
    out.extend_from_slice(&k);
    out.extend_from_slice(&v);
    out.extend_from_slice(b"\r\n");
}

const AL3D_INVALID: f32 = -999.0;

/// `padded`: rows padded to 8 bytes as the specification says (Cols 5 -> 6 floats a row).
fn al3d_fixture(cols: &str, rows: &str, tag_count: &str, padded: bool) -> Vec<u8> {
    let mut out = b"AliconaImaging\0\r\n".to_vec();
    al3d_tag(&mut out, "Version", "1");
    al3d_tag(&mut out, "TagCount", tag_count);
    let offset = 17 + 11 * 52 + 64;
    al3d_tag(&mut out, "Cols", cols);
    al3d_tag(&mut out, "Rows", rows);
    al3d_tag(&mut out, "NumberOfPlanes", "0");
    al3d_tag(
        &mut out,
        "PixelSizeXMeter",
        &format!("{:e}", PITCH_X_UM * 1e-6),
    );
    al3d_tag(
        &mut out,
        "PixelSizeYMeter",
        &format!("{:e}", PITCH_Y_UM * 1e-6),
    );
    al3d_tag(&mut out, "IconOffset", "0");
    al3d_tag(&mut out, "TextureImageOffset", "0");
    al3d_tag(&mut out, "DepthImageOffset", &offset.to_string());
    al3d_tag(&mut out, "InvalidPixelValue", &format!("{AL3D_INVALID}"));
    // A comment block, then padding to the depth image.
    out.extend_from_slice(b"fixture comment");
    out.resize(offset - 2, 0);
    out.extend_from_slice(b"\r\n");
    for (i, z) in truth().iter().enumerate() {
        let v = z.map_or(AL3D_INVALID, |z| (z * 1e-6) as f32);
        out.extend_from_slice(&v.to_le_bytes());
        if padded && i % COLS == COLS - 1 {
            // The pad float: a value that would show if read as a point.
            out.extend_from_slice(&1.0e3f32.to_le_bytes());
        }
    }
    out
}

#[test]
fn al3d_golden_padded_and_unpadded_rows() {
    let s = parse_surface(&al3d_fixture("5", "3", "9", true), Format::Al3d).unwrap();
    check(&s, via_f32(1e6), "al3d");
    assert!(s.metadata.warnings.is_empty(), "{:?}", s.metadata.warnings);
    let s = parse_surface(&al3d_fixture("5", "3", "9", false), Format::Al3d).unwrap();
    check(&s, via_f32(1e6), "al3d");
    assert!(s.metadata.warnings.iter().any(|w| w.contains("not padded")));
}

#[test]
fn al3d_truncated_lying_and_wrong() {
    let data = al3d_fixture("5", "3", "9", true);
    // Short of even the unpadded image.
    let e = err(&data[..data.len() - 16], Format::Al3d);
    assert!(e.contains("depth image: 'Rows' x 'Cols' = 3 x 5"), "{e}");
    let e = err(&al3d_fixture("100000", "100000", "9", true), Format::Al3d);
    assert!(e.contains("'Rows' x 'Cols' = 100000 x 100000"), "{e}");
    let e = err(&al3d_fixture("5", "3", "4000000000", true), Format::Al3d);
    assert!(e.contains("'TagCount' is 4000000000"), "{e}");
    let e = err(&al3d_fixture("5", "-3", "9", true), Format::Al3d);
    assert!(e.contains("'Rows' is '-3'"), "{e}");
    let e = err(&data[..300], Format::Al3d);
    assert!(e.contains("'TagCount' is 9"), "{e}");
    let mut bad = data.clone();
    bad[17 + 52 + 50] = b' ';
    let e = err(&bad, Format::Al3d);
    assert!(e.contains("tag 1") && e.contains("CR LF"), "{e}");
    let e = err(b"AliconaImaging\r\n", Format::Al3d);
    assert!(e.contains("magic"), "{e}");
}

#[test]
fn al3d_corruption_sweep() {
    corruption_sweep(&al3d_fixture("5", "3", "9", true), Format::Al3d, 3000);
}

#[test]
fn extensions_pick_the_open_readers() {
    for (name, format) in [
        ("t.gsf", Format::Gsf),
        ("t.GWY", Format::Gwy),
        ("t.sdf", Format::Sdf),
        ("t.tmd", Format::Tmd),
        ("t.AL3D", Format::Al3d),
    ] {
        assert_eq!(Format::from_path(name.as_ref()).unwrap(), format, "{name}");
    }
}
