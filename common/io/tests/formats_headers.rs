//! Issue 35, "Formats": header forms the readers met in the wild. `.sur` unit fields in
//! UTF-8 (surfalize's writer), Gwyddion text exports with a localized header, and Gwyddion
//! text matrices that give a pixel size.

use surfstream_io::formats::{self, parse_surface, read_surface, Format, Metadata, Surface};

fn toy_surface(w: usize, h: usize) -> Surface {
    let heights_um = (0..w * h)
        .map(|i| ((i * 37 % 101) as f64 - 50.0) * 0.013)
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

/// Writes `unit` into the three 16-byte `unit_step_*` fields of a .sur byte image.
fn set_step_units(bytes: &mut [u8], unit: &[u8]) {
    for o in [180, 196, 212] {
        bytes[o..o + 16].fill(0);
        bytes[o..o + unit.len()].copy_from_slice(unit);
    }
}

#[test]
fn sur_unit_fields_read_latin1_and_utf8_micro_sign() {
    let s = toy_surface(7, 5);
    let latin1 = formats::sur::encode_for_tests(&s, false, false);
    // Digital Surf's own encoding: "µm" = B5 6D.
    assert_eq!(&latin1[180..183], b"\xb5m\0");
    let a = parse_surface(&latin1, Format::Sur).unwrap();
    // surfalize's .sur writer: "µm" = C2 B5 6D (UTF-8).
    let mut utf8 = latin1.clone();
    set_step_units(&mut utf8, "µm".as_bytes());
    assert_eq!(&utf8[180..184], b"\xc2\xb5m\0");
    let b = parse_surface(&utf8, Format::Sur).unwrap();
    assert_eq!((b.width, b.height), (7, 5));
    assert_eq!(a.pitch_x_um, b.pitch_x_um);
    assert_eq!(a.pitch_y_um, b.pitch_y_um);
    assert_eq!(a.heights_um, b.heights_um);
    assert!((b.pitch_y_um - 0.75).abs() < 1e-6);
    // The Greek mu (U+03BC) in UTF-8 too; and nm to check a scale is applied.
    let mut mu = latin1.clone();
    set_step_units(&mut mu, "\u{3bc}m".as_bytes());
    assert_eq!(
        parse_surface(&mu, Format::Sur).unwrap().heights_um,
        a.heights_um
    );
    let mut nm = latin1.clone();
    set_step_units(&mut nm, b"nm");
    let c = parse_surface(&nm, Format::Sur).unwrap();
    assert!((c.pitch_x_um - 0.5e-3).abs() < 1e-9);
    // Anything else is still refused, naming the field and what is expected.
    let mut bad = latin1;
    set_step_units(&mut bad, b"\xc2\xb5s");
    let e = format!("{:#}", parse_surface(&bad, Format::Sur).unwrap_err());
    assert!(
        e.contains("unit_step_x") && e.contains("µs") && e.contains("length unit"),
        "{e}"
    );
}

fn fixture(name: &str) -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

/// The 4 x 5 matrix of both Gwyddion fixtures, in µm: (5 r + c² − 7) × 1e-8 m.
fn fixture_heights_um() -> Vec<f64> {
    (0..4)
        .flat_map(|r| (0..5).map(move |c| (5 * r + c * c - 7) as f64 * 1e-2))
        .collect()
}

fn close(a: &[f64], b: &[f64]) {
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(b) {
        assert!((x - y).abs() <= 1e-12, "{x} vs {y}");
    }
}

#[test]
fn gwyddion_text_export_with_a_german_header_is_a_grid() {
    // Breite / Höhe (Gwyddion's po/de.po); "Value units:" is untranslated in de.po.
    let s = read_surface(&fixture("gwyddion-de-export.txt")).unwrap();
    assert_eq!(s.metadata.format, "gwyddion-text");
    assert_eq!((s.height, s.width), (4, 5));
    assert_eq!(s.invalid_count(), 0);
    assert!((s.pitch_x_um - 10.0 / 5.0).abs() < 1e-12);
    assert!((s.pitch_y_um - 7.5 / 4.0).abs() < 1e-12);
    assert!(s.metadata.pitch_known);
    assert_eq!(s.metadata.extra["channel"], "Height");
    close(&s.heights_um, &fixture_heights_um());
}

#[test]
fn gwyddion_text_export_in_other_translations() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("export.txt");
    // French (po/fr.po: "Largeur :", "Hauteur :", "Unités :"), a locale's decimal comma.
    std::fs::write(
        &p,
        "# Canal : Topographie\n# Largeur : 3,000 µm\n# Hauteur : 2,000 µm\n# Unités : nm\n\
         1,5\t2\t-3\n4\t5\t6,25\n",
    )
    .unwrap();
    let s = read_surface(&p).unwrap();
    assert_eq!((s.height, s.width), (2, 3));
    assert!((s.pitch_x_um - 1.0).abs() < 1e-12 && (s.pitch_y_um - 1.0).abs() < 1e-12);
    close(&s.heights_um, &[1.5e-3, 2e-3, -3e-3, 4e-3, 5e-3, 6.25e-3]);
    // Russian and Czech keys; a German file whose value-unit key was translated after all.
    for header in [
        "# Канал: Height\n# Ширина: 4 mm\n# Высота: 2 mm\n# Единицы измерения: m\n",
        "# Kanál: Height\n# Šířka: 4 mm\n# Výška: 2 mm\n# Jednotky hodnot: m\n",
    ] {
        std::fs::write(&p, format!("{header}1 2\n3 4\n")).unwrap();
        let s = read_surface(&p).unwrap();
        assert!((s.pitch_x_um - 2000.0).abs() < 1e-9, "{header}");
        assert!((s.pitch_y_um - 1000.0).abs() < 1e-9, "{header}");
        assert_eq!(s.heights_um[3], 4e6);
    }
}

#[test]
fn gwyddion_header_that_is_not_read_is_refused_not_read_as_xyz() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("polish.txt");
    // Keys of a translation not in Gwyddion's po/ tables here (Polish): an error naming the
    // file and the header's lines, never an 'x y z' reading.
    std::fs::write(
        &p,
        "# Kanał: Height\n# Szerokość: 10.000 µm\n# Wysokość: 7.500 µm\n# Jednostki: m\n\
         1 2 3\n4 5 6\n7 8 9\n",
    )
    .unwrap();
    let e = format!("{:#}", read_surface(&p).unwrap_err());
    assert!(e.contains("polish.txt"), "{e}");
    assert!(e.contains("a Gwyddion text header"), "{e}");
    assert!(e.contains("'# Szerokość: 10.000 µm'"), "{e}");
    assert!(e.contains("Breite/Höhe"), "{e}");
    // Four columns: the same.
    std::fs::write(
        &p,
        "# Kanał: Height\n# Szerokość: 10.000 µm\n# Wysokość: 7.500 µm\n# Jednostki: m\n\
         1\t2\t3\t4\n5\t6\t7\t8\n",
    )
    .unwrap();
    let e = format!("{:#}", read_surface(&p).unwrap_err());
    assert!(e.contains("a Gwyddion text header"), "{e}");
    // A German header with the width but not the height names the missing key.
    std::fs::write(
        &p,
        "# Kanal: Height\n# Breite: 10.000 µm\n# Value units: m\n1 2 3\n4 5 6\n",
    )
    .unwrap();
    let e = format!("{:#}", read_surface(&p).unwrap_err());
    assert!(
        e.contains("'# Breite: 10.000 µm' gives the width") && e.contains("höhe"),
        "{e}"
    );
    // Width and height read, but a value-unit key not in the tables: named, not guessed.
    std::fs::write(
        &p,
        "# Kanal: Height\n# Breite: 1 um\n# Höhe: 1 um\n# Werte-Einheit: m\n1 2\n3 4\n",
    )
    .unwrap();
    let e = format!("{:#}", read_surface(&p).unwrap_err());
    assert!(
        e.contains("no '# Value units:' line") && e.contains("line 4 '# Werte-Einheit: m'"),
        "{e}"
    );
    // Gwyddion's XYZ export (Lateral units, three columns) is still 'x y z'.
    std::fs::write(
        &p,
        "# Channel: Height\n# Lateral units: m\n# Value units: m\n0 0 1\n1 0 2\n0 1 3\n1 1 4\n",
    )
    .unwrap();
    let s = read_surface(&p).unwrap();
    assert_eq!(
        (s.metadata.format.as_str(), s.width, s.height),
        ("xyz", 2, 2)
    );
    // So is an 'x y z' file with unrelated comments.
    std::fs::write(&p, "# Instrument: foo\n# Date: 2026-01-01\n0 0 1\n1 0 2\n").unwrap();
    assert_eq!(read_surface(&p).unwrap().metadata.format, "xyz");
}

#[test]
fn gwyddion_matrix_with_a_pixel_size_is_read_with_that_pitch() {
    let s = read_surface(&fixture("gwyddion-pixel-size.txt")).unwrap();
    assert_eq!(s.metadata.format, "gwyddion-text");
    assert_eq!((s.height, s.width), (4, 5));
    assert!((s.pitch_x_um - 0.369862).abs() < 1e-12, "{}", s.pitch_x_um);
    assert!((s.pitch_y_um - 0.369862).abs() < 1e-12);
    assert!(s.metadata.pitch_known);
    assert_eq!(s.metadata.extra["pitch_from"], "pixel size");
    close(&s.heights_um, &fixture_heights_um());
    assert!(
        s.metadata
            .warnings
            .iter()
            .any(|w| w.contains("taken as metres")),
        "{:?}",
        s.metadata.warnings
    );
    let d = tempfile::tempdir().unwrap();
    let p = d.path().join("m.txt");
    // Per axis, as comments, with a value unit (no warning then).
    std::fs::write(
        &p,
        "# pixel size x = 2 um\n# pixel size y: 3 um\n# Value units: nm\n1 2\n3 4\n",
    )
    .unwrap();
    let s = read_surface(&p).unwrap();
    assert_eq!((s.pitch_x_um, s.pitch_y_um), (2.0, 3.0));
    assert!(s.metadata.warnings.is_empty());
    assert_eq!(s.heights_um[3], 4e-3);
    // Only one axis: refused, naming what is read.
    std::fs::write(&p, "# pixel size x = 2 um\n1 2\n3 4\n").unwrap();
    let e = format!("{:#}", read_surface(&p).unwrap_err());
    assert!(e.contains("along x but none along y"), "{e}");
    // Width / height and a pixel size that disagree.
    std::fs::write(
        &p,
        "# Width: 4 um\n# Height: 4 um\n# Value units: m\npixel size=1 um\n1 2\n3 4\n",
    )
    .unwrap();
    let e = format!("{:#}", read_surface(&p).unwrap_err());
    assert!(e.contains("pixel size says 1 um"), "{e}");
    // No pitch at all: the error says which forms are read.
    std::fs::write(&p, "1 2 3 4\n5 6 7 8\n").unwrap();
    let e = format!("{:#}", read_surface(&p).unwrap_err());
    assert!(
        e.contains("m.txt")
            && e.contains("a matrix of heights")
            && e.contains("pixel size=")
            && e.contains("Breite/Höhe"),
        "{e}"
    );
    // A pixel size that is not a length.
    std::fs::write(&p, "pixel size=3 px\n1 2\n3 4\n").unwrap();
    let e = format!("{:#}", read_surface(&p).unwrap_err());
    assert!(
        e.contains("line 1 'pixel size=3 px'") && e.contains("length unit"),
        "{e}"
    );
}
