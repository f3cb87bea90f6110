//! Issue 26: every number a user sees is right and labelled. The pitch travels with a .npy
//! (its sidecar), Gwyddion's text export is read as the grid it is, units are never assumed
//! silently, and the writers (.x3p metadata, .gsf, .tif) say what they hold.

use std::io::Read;
use std::path::Path;

use surfstream_io::formats::{read_surface, write_surface, Metadata, Surface};

fn surface(rows: usize, cols: usize, pitch: (f64, f64)) -> Surface {
    Surface {
        width: cols,
        height: rows,
        pitch_x_um: pitch.0,
        pitch_y_um: pitch.1,
        heights_um: (0..rows * cols)
            .map(|i| {
                if i == 3 {
                    f64::NAN
                } else {
                    (i as f64 * 0.37).sin() * 2.0 + 40.0
                }
            })
            .collect(),
        metadata: Metadata {
            format: "x3p".into(),
            pitch_known: true,
            ..Metadata::default()
        },
    }
}

fn same_heights(a: &[f64], b: &[f64], tol: f64) {
    assert_eq!(a.len(), b.len());
    for (k, (x, y)) in a.iter().zip(b).enumerate() {
        assert!(
            (x.is_nan() && y.is_nan()) || (x - y).abs() <= tol,
            "height {k}: {x} vs {y}"
        );
    }
}

#[test]
fn npy_keeps_its_pitch_in_a_sidecar_and_forgets_a_stale_one() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("a.npy");
    let mut s = surface(4, 5, (2.2797945189999997, 0.5));
    s.metadata.stage_position_um = Some([100.0, -20.0]);
    write_surface(&p, &s).unwrap();
    assert!(d.path().join("a.npy.json").is_file());
    let back = read_surface(&p).unwrap();
    assert!(back.metadata.pitch_known);
    assert_eq!(
        (back.pitch_x_um, back.pitch_y_um),
        (s.pitch_x_um, s.pitch_y_um)
    );
    assert_eq!(back.metadata.stage_position_um, Some([100.0, -20.0]));
    assert_eq!(back.metadata.extra["pitch_from"], "a.npy.json");
    same_heights(&back.heights_um, &s.heights_um, 0.0);
    // The same name written without a pitch: the old sidecar must not lend it one.
    s.metadata.pitch_known = false;
    write_surface(&p, &s).unwrap();
    assert!(!d.path().join("a.npy.json").exists());
    let back = read_surface(&p).unwrap();
    assert!(!back.metadata.pitch_known);
    assert_eq!(back.pitch_x_um, 1.0);
    // A sidecar that says nothing usable is an error naming it, not a silent 1 um.
    std::fs::write(
        d.path().join("a.npy.json"),
        r#"{"pitch_um": {"x": "half"}}"#,
    )
    .unwrap();
    let e = format!("{:#}", read_surface(&p).unwrap_err());
    assert!(e.contains("a.npy.json: pitch_um.x"), "{e}");
}

/// Gwyddion's "ASCII data matrix" export with the informational header, as Gwyddion writes
/// it: `# Channel:`, `# Width:`, `# Height:` (value and unit), `# Value units:`, then one
/// tab-separated line per row, values in the value unit.
fn gwyddion_text(
    rows: usize,
    cols: usize,
    width: &str,
    height: &str,
    unit: &str,
    z: &[f64],
) -> String {
    let mut t =
        format!("# Channel: Height\n# Width: {width}\n# Height: {height}\n# Value units: {unit}\n");
    for r in 0..rows {
        let line: Vec<String> = (0..cols)
            .map(|c| format!("{:e}", z[r * cols + c]))
            .collect();
        t.push_str(&line.join("\t"));
        t.push('\n');
    }
    t
}

#[test]
fn gwyddion_text_export_is_a_grid_with_its_pitch_and_unit() {
    let d = tempfile::tempdir().unwrap();
    // 9 rows x 12 cols: 12.34 um wide, 5.67 um high, heights in metres.
    let (rows, cols) = (9, 12);
    let z_m: Vec<f64> = (0..rows * cols).map(|i| (i as f64 - 50.0) * 1e-8).collect();
    let p = d.path().join("export.txt");
    std::fs::write(
        &p,
        gwyddion_text(rows, cols, "12.34 µm", "5.670 µm", "m", &z_m),
    )
    .unwrap();
    let s = read_surface(&p).unwrap();
    assert_eq!((s.height, s.width), (rows, cols));
    assert_eq!(s.invalid_count(), 0);
    assert!((s.pitch_x_um - 12.34 / 12.0).abs() < 1e-12);
    assert!((s.pitch_y_um - 5.67 / 9.0).abs() < 1e-12);
    assert_eq!(s.metadata.format, "gwyddion-text");
    assert!(s.metadata.pitch_known);
    // First stored row = row 0; heights in um.
    assert!((s.heights_um[0] - (-50.0e-8 * 1e6)).abs() < 1e-12);
    assert!((s.heights_um[rows * cols - 1] - (57.0e-8 * 1e6)).abs() < 1e-12);
    // Width in mm, values in nm, decimal commas (a locale's export).
    let z_nm: Vec<f64> = (0..6).map(|i| i as f64 * 10.0).collect();
    let text = gwyddion_text(2, 3, "0,003 mm", "2 mm", "nm", &z_nm).replace('.', ",");
    std::fs::write(&p, text).unwrap();
    let s = read_surface(&p).unwrap();
    assert_eq!((s.height, s.width), (2, 3));
    assert!((s.pitch_x_um - 1.0).abs() < 1e-9 && (s.pitch_y_um - 1000.0).abs() < 1e-9);
    assert!((s.heights_um[5] - 0.05).abs() < 1e-12);
    // Without a value unit, or with a unit that is not a length: refused, not guessed.
    std::fs::write(&p, "# Width: 1 um\n# Height: 1 um\n1 2\n3 4\n").unwrap();
    assert!(format!("{:#}", read_surface(&p).unwrap_err()).contains("Value units"));
    std::fs::write(
        &p,
        "# Width: 1 um\n# Height: 1 um\n# Value units: V\n1 2\n3 4\n",
    )
    .unwrap();
    assert!(format!("{:#}", read_surface(&p).unwrap_err()).contains("not a height map"));
    // Ragged rows name the line.
    std::fs::write(
        &p,
        "# Width: 1 um\n# Height: 1 um\n# Value units: m\n1 2\n3\n",
    )
    .unwrap();
    assert!(format!("{:#}", read_surface(&p).unwrap_err()).contains("line 5"));
    // A matrix without the header is refused (pitch and unit would be guesses).
    std::fs::write(&p, "1 2 3 4\n5 6 7 8\n").unwrap();
    let e = format!("{:#}", read_surface(&p).unwrap_err());
    assert!(e.contains("a matrix of heights"), "{e}");
}

#[test]
fn xyz_says_it_assumed_micrometres() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("p.xyz");
    std::fs::write(&p, "0 0 1\n1 0 2\n0 1 3\n1 1 4\n").unwrap();
    let s = read_surface(&p).unwrap();
    assert!(
        s.metadata
            .warnings
            .iter()
            .any(|w| w.contains("taken as micrometres")),
        "{:?}",
        s.metadata.warnings
    );
}

fn x3p_main_xml(path: &Path) -> String {
    let f = std::fs::File::open(path).unwrap();
    let mut z = zip::ZipArchive::new(f).unwrap();
    let mut xml = String::new();
    z.by_name("main.xml")
        .unwrap()
        .read_to_string(&mut xml)
        .unwrap();
    xml
}

fn tag<'a>(xml: &'a str, name: &str) -> &'a str {
    let open = format!("<{name}>");
    let a = xml.find(&open).unwrap_or_else(|| panic!("no <{name}>")) + open.len();
    let b = a + xml[a..].find(&format!("</{name}>")).unwrap();
    &xml[a..b]
}

fn is_iso8601(t: &str) -> bool {
    let b = t.as_bytes();
    b.len() >= 19
        && b[4] == b'-'
        && b[7] == b'-'
        && b[10] == b'T'
        && b[13] == b':'
        && b[16] == b':'
        && [0..4, 5..7, 8..10, 11..13, 14..16, 17..19]
            .iter()
            .all(|r| b[r.clone()].iter().all(u8::is_ascii_digit))
}

#[test]
fn x3p_record2_is_iso8601_and_claims_nothing_it_does_not_know() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("c.x3p");
    let mut s = surface(3, 4, (0.5, 0.5));
    s.metadata.format = "plu".into();
    s.metadata.instrument = Some("Sensofar Sneox1".into());
    s.metadata.date = Some("2021-03-04 10:23:05".into());
    write_surface(&p, &s).unwrap();
    let xml = x3p_main_xml(&p);
    assert_eq!(tag(&xml, "Date"), "2021-03-04T10:23:05");
    assert_eq!(tag(&xml, "Manufacturer"), "Sensofar Sneox1");
    // The calibration date is not the measurement's.
    assert_ne!(tag(&xml, "CalibrationDate"), tag(&xml, "Date"));
    assert!(
        tag(&xml, "Comment").contains("CalibrationDate not known"),
        "{xml}"
    );
    let back = read_surface(&p).unwrap();
    assert_eq!(back.metadata.instrument.as_deref(), Some("Sensofar Sneox1"));
    assert_eq!(back.metadata.serial, None);
    // A numeric date whose day and month cannot be told apart ("04/03/2021") is read day
    // first, and the comment says so (issue 35).
    s.metadata.date = Some("04/03/2021 10:23".into());
    write_surface(&p, &s).unwrap();
    let xml = x3p_main_xml(&p);
    assert_eq!(tag(&xml, "Date"), "2021-03-04T10:23:00");
    let comment = tag(&xml, "Comment");
    assert!(
        comment.contains("read day first") && comment.contains("04/03/2021"),
        "{comment}"
    );
    // A date that is no form read here: 1970-01-01 standing for unknown, never silent: said
    // in the comment with the source's text (and the file stays the same for the same surface).
    s.metadata.date = Some("the day after the storm".into());
    write_surface(&p, &s).unwrap();
    let xml = x3p_main_xml(&p);
    assert_eq!(tag(&xml, "Date"), "1970-01-01T00:00:00Z");
    let comment = tag(&xml, "Comment");
    assert!(
        comment.contains("measurement date not known")
            && comment.contains("the day after the storm"),
        "{comment}"
    );
    let again = std::fs::read(&p).unwrap();
    write_surface(&p, &s).unwrap();
    assert_eq!(std::fs::read(&p).unwrap(), again);
    assert!(is_iso8601(tag(&xml, "CalibrationDate")));
    // No required element is left empty (SurfaceTopography 1.27 fails on an empty <Model>).
    for name in ["Creator", "Manufacturer", "Model", "Serial", "Version"] {
        assert!(!tag(&xml, name).trim().is_empty(), "<{name}> empty: {xml}");
    }
    // The instruments' own date forms are read as the dates they are: a .plu's asctime.
    s.metadata.date = Some("Fri Mar 10 16:35:59 2023\0\0".into());
    s.metadata.instrument = None;
    s.metadata.extra.insert("creator".into(), "J. Doe".into());
    write_surface(&p, &s).unwrap();
    let xml = x3p_main_xml(&p);
    assert_eq!(tag(&xml, "Date"), "2023-03-10T16:35:59");
    assert_eq!(tag(&xml, "Creator"), "J. Doe");
    assert_eq!(tag(&xml, "Manufacturer"), "not available");
    let back = read_surface(&p).unwrap();
    assert_eq!(back.metadata.instrument, None);
}

#[test]
fn instrument_date_forms_become_iso8601() {
    use surfstream_io::formats::x3p::iso8601_date;
    for (text, want) in [
        ("2021-03-04 10:23:05", Some("2021-03-04T10:23:05")),
        ("2021-03-04", Some("2021-03-04T00:00:00")),
        ("Fri Mar 10 16:35:59 2023", Some("2023-03-10T16:35:59")),
        ("Mon Jan  2 08:05:00 2023\n", Some("2023-01-02T08:05:00")),
        ("10 Mar 2023 16:35:59", Some("2023-03-10T16:35:59")),
        ("March 10, 2023 16:35", Some("2023-03-10T16:35:00")),
        ("10.03.2023 16:35:59", Some("2023-03-10T16:35:59")),
        ("2023/03/10 16:35:59", Some("2023-03-10T16:35:59")),
        // Day or month first? Read day first (dd/mm/yyyy), and the X3P comment says so.
        ("04/03/2021 10:23", Some("2021-03-04T10:23:00")),
        ("10/03/2023 16:35", Some("2023-03-10T16:35:00")),
        (
            "2023-03-10T16:35:59+01:00",
            Some("2023-03-10T16:35:59+01:00"),
        ),
        ("Fri Feb 30 25:00:00 2023", None),
        ("yesterday", None),
        ("", None),
    ] {
        assert_eq!(iso8601_date(text).as_deref(), want, "{text:?}");
    }
}

#[test]
fn gsf_written_reads_back_by_gwyddions_layout() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("g.gsf");
    let mut s = surface(5, 7, (0.25, 0.75));
    s.metadata.stage_position_um = Some([12.5, -3.0]);
    write_surface(&p, &s).unwrap();
    let bytes = std::fs::read(&p).unwrap();
    // The documented layout: magic line, header, NULs up to a multiple of 4, float32 LE.
    assert!(bytes.starts_with(b"Gwyddion Simple Field 1.0\n"));
    let nul = bytes.iter().position(|&b| b == 0).unwrap();
    let start = (nul / 4 + 1) * 4;
    assert_eq!(bytes.len() - start, 5 * 7 * 4);
    let back = read_surface(&p).unwrap();
    assert_eq!((back.height, back.width), (5, 7));
    assert!((back.pitch_x_um - 0.25).abs() < 1e-9 && (back.pitch_y_um - 0.75).abs() < 1e-9);
    assert_eq!(
        back.metadata
            .stage_position_um
            .map(|p| p.map(|v| (v * 1e6).round() / 1e6)),
        Some([12.5, -3.0])
    );
    // float32 of metres: about 1e-7 relative.
    same_heights(&back.heights_um, &s.heights_um, 1e-5);
}

mod support;

/// .tif by tifffile and .gsf by Gwyddion's published layout, in Python: heights, shape and
/// pitch as written.
#[test]
fn float_tiff_and_gsf_read_back_by_an_independent_reader() {
    let d = tempfile::tempdir().unwrap();
    let s = surface(37, 53, (0.127656509837346, 0.314582113527746));
    let (tif, gsf, npy) = (
        d.path().join("s.tif"),
        d.path().join("s.gsf"),
        d.path().join("s.npy"),
    );
    for p in [&tif, &gsf, &npy] {
        write_surface(p, &s).unwrap();
    }
    let script = r#"
import json, sys, numpy as np, tifffile
tif, gsf, npy = sys.argv[1:4]
ref = np.load(npy)
with tifffile.TiffFile(tif) as t:
    p = t.pages[0]
    a = p.asarray()
    desc = json.loads(p.description)
    xr = p.tags["XResolution"].value
assert a.dtype == np.float32 and a.shape == ref.shape, (a.dtype, a.shape)
assert np.array_equal(np.isnan(a), np.isnan(ref))
assert np.nanmax(np.abs(a - ref)) < 1e-5
assert abs(desc["pitch_um"]["y"] - 0.314582113527746) < 1e-15
assert abs(xr[0] / xr[1] - 1e4 / 0.127656509837346) < 1e-3
b = open(gsf, "rb").read()
nul = b.index(b"\0")
hdr = b[:nul].decode().split("\n")
assert hdr[0] == "Gwyddion Simple Field 1.0"
kv = dict(l.split(" = ", 1) for l in hdr[1:] if l.strip())
start = (nul // 4 + 1) * 4
xres, yres = int(kv["XRes"]), int(kv["YRes"])
z = np.frombuffer(b[start:], "<f4").reshape(yres, xres) * 1e6
assert (yres, xres) == ref.shape and kv["ZUnits"] == "m" and kv["XYUnits"] == "m"
assert abs(float(kv["XReal"]) / xres * 1e6 - 0.127656509837346) < 1e-9
assert np.array_equal(np.isnan(z), np.isnan(ref)) and np.nanmax(np.abs(z - ref)) < 1e-4
# A TIFF of another writer (tifffile, big-endian, pitch as px/cm) for our reader.
tifffile.imwrite(sys.argv[4], ref.astype(">f4"), byteorder=">",
                 resolution=(1e4 / 0.127656509837346, 1e4 / 0.314582113527746), resolutionunit="CENTIMETER")
print("ok")
"#;
    let foreign = d.path().join("foreign.tif");
    let out = std::process::Command::new(support::python())
        .arg("-c")
        .arg(script)
        .args([&tif, &gsf, &npy, &foreign])
        .output()
        .unwrap();
    assert!(
        out.status.success() && String::from_utf8_lossy(&out.stdout).trim() == "ok",
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    // What convert writes, our reader reads: the same rows x cols, pitch and not-measured
    // points, heights to float32.
    for p in [&tif, &gsf] {
        let back = read_surface(p).unwrap();
        assert_eq!((back.height, back.width), (s.height, s.width), "{p:?}");
        assert!(
            (back.pitch_x_um - s.pitch_x_um).abs() < 1e-9 * s.pitch_x_um,
            "{p:?}"
        );
        assert!(
            (back.pitch_y_um - s.pitch_y_um).abs() < 1e-9 * s.pitch_y_um,
            "{p:?}"
        );
        same_heights(&back.heights_um, &s.heights_um, 1e-5);
        assert!(
            back.metadata.warnings.is_empty(),
            "{:?}",
            back.metadata.warnings
        );
    }
    let back = read_surface(&tif).unwrap();
    assert_eq!(
        back.pitch_x_um, s.pitch_x_um,
        "our description keeps the pitch exactly"
    );
    // tifffile's TIFF: the pitch from its resolution (u32 rationals: ~1e-7), heights as um
    // with a warning (a plain TIFF has no height unit).
    let f = read_surface(&foreign).unwrap();
    assert_eq!((f.height, f.width), (s.height, s.width));
    assert!(f.metadata.pitch_known);
    assert!(
        (f.pitch_x_um - s.pitch_x_um).abs() < 1e-6 * s.pitch_x_um,
        "{}",
        f.pitch_x_um
    );
    assert!(
        (f.pitch_y_um - s.pitch_y_um).abs() < 1e-6 * s.pitch_y_um,
        "{}",
        f.pitch_y_um
    );
    same_heights(&f.heights_um, &s.heights_um, 1e-5);
    assert!(f
        .metadata
        .warnings
        .iter()
        .any(|w| w.contains("no height unit")));
}
