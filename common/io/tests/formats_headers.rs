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
