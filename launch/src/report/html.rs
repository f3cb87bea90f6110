//! Small HTML helpers of the report: tables, number formats, base64 and PNG encoding; the
//! escaping, the fixed-decimals format and the SVG paths are the figures' own
//! ([`surfstream_io::figure`], shared with finish.html), re-exported. Every number a person
//! reads goes through [`fixed`], [`um`] or [`sig`], so the page uses one precision per
//! quantity; heights have significant figures ([`surfstream_core::units`]).

use std::fmt::Write as _;

use anyhow::{Context, Result};
use serde_json::Value;

pub use surfstream_io::figure::{esc, fixed, path_d};

pub use surfstream_core::units::sig;

/// A height (or length) in micrometres with 3 significant figures, nm below 1 µm: "15.3 nm",
/// "1.51 µm", "15.2 µm", "1585 µm" ([`surfstream_core::units::height_unicode`]); "-" where
/// not finite.
pub fn um(v: f64) -> String {
    if v.is_finite() {
        surfstream_core::units::height_unicode(v)
    } else {
        "-".into()
    }
}

/// A pitch in um: four decimals (0.8148 µm), the precision instruments state it with.
pub fn pitch(v: f64) -> String {
    format!("{} µm", fixed(v, 4))
}

/// A signed percentage with `decimals` decimals, "+2.5", "-8.33"; zero shows unsigned.
pub fn signed(v: f64, decimals: usize) -> String {
    let s = fixed(v, decimals);
    if s == "-" || s.starts_with('-') || s.chars().all(|c| c == '0' || c == '.') {
        s
    } else {
        format!("+{s}")
    }
}

/// A round length (a scale bar's) with no more decimals than it needs: "200 µm", "1 mm",
/// "0.5 µm".
pub fn round_length(v_um: f64) -> String {
    let (v, unit) = if v_um >= 1000.0 {
        (v_um / 1000.0, "mm")
    } else {
        (v_um, "µm")
    };
    let s = format!("{v:.3}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    format!("{s} {unit}")
}

/// A length in um shown in mm when it is long: "1.585 mm" or "812 µm".
pub fn length(v_um: f64) -> String {
    if v_um.abs() >= 1000.0 {
        format!("{} mm", fixed(v_um / 1000.0, 3))
    } else {
        um(v_um)
    }
}

/// A JSON value as short text: numbers to 4 decimals (or 4 significant digits in exponent
/// form when tiny or huge), arrays inline; for the generic tables.
pub fn num(v: &Value) -> String {
    match v {
        Value::Null => "-".into(),
        Value::Number(n) => match (n.as_i64(), n.as_f64()) {
            (Some(i), _) => i.to_string(),
            (None, Some(f)) if f != 0.0 && (f.abs() < 1e-3 || f.abs() >= 1e7) => format!("{f:.3e}"),
            (None, Some(f)) => fixed(f, 4),
            _ => n.to_string(),
        },
        Value::String(s) => s.clone(),
        Value::Bool(b) => if *b { "yes" } else { "no" }.into(),
        Value::Array(a) => a.iter().map(num).collect::<Vec<_>>().join(" x "),
        Value::Object(_) => "{...}".into(),
    }
}

/// A table; the first column is a key (left aligned). Cells are escaped.
pub fn table(head: &[&str], rows: &[Vec<String>]) -> String {
    table_raw(
        head,
        &rows
            .iter()
            .map(|r| (String::new(), r.iter().map(|c| esc(c)).collect()))
            .collect::<Vec<_>>(),
    )
}

/// A table of (row class, cells already HTML).
pub fn table_raw(head: &[&str], rows: &[(String, Vec<String>)]) -> String {
    let mut s = String::from("<table><thead><tr>");
    for c in head {
        let _ = write!(s, "<th>{}</th>", esc(c));
    }
    s.push_str("</tr></thead><tbody>");
    for (class, r) in rows {
        if class.is_empty() {
            s.push_str("<tr>");
        } else {
            let _ = write!(s, "<tr class=\"{class}\">");
        }
        for (i, c) in r.iter().enumerate() {
            let class = if i == 0 { " class=\"k\"" } else { "" };
            let _ = write!(s, "<td{class}>{c}</td>");
        }
        s.push_str("</tr>");
    }
    s.push_str("</tbody></table>");
    s
}

/// Standard base64 (RFC 4648) with padding.
pub fn base64(bytes: &[u8]) -> String {
    use base64::Engine as _;
    base64::engine::general_purpose::STANDARD.encode(bytes)
}

/// An RGB image (3 bytes per pixel, row-major) as PNG bytes.
pub fn png_rgb(rgb: &[u8], width: usize, height: usize) -> Result<Vec<u8>> {
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, width as u32, height as u32);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut w = enc.write_header().context("PNG header")?;
        w.write_image_data(rgb).context("PNG data")?;
        w.finish().context("PNG end")?;
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use surfstream_io::figure::ticks;

    #[test]
    fn base64_matches_rfc4648_vectors() {
        for (i, o) in [
            ("", ""),
            ("f", "Zg=="),
            ("fo", "Zm8="),
            ("foo", "Zm9v"),
            ("foob", "Zm9vYg=="),
            ("fooba", "Zm9vYmE="),
            ("foobar", "Zm9vYmFy"),
        ] {
            assert_eq!(base64(i.as_bytes()), o);
        }
    }

    #[test]
    fn numbers_have_one_precision_per_quantity() {
        assert_eq!(um(1.3630563293), "1.36 µm");
        assert_eq!(um(15.2321), "15.2 µm");
        assert_eq!(um(0.015255), "15.3 nm");
        assert_eq!(um(f64::NAN), "-");
        assert_eq!(length(1584.83), "1.585 mm");
        assert_eq!(fixed(-0.0001, 2), "0.00");
        assert_eq!(signed(-0.04, 1), "0.0");
        assert_eq!(signed(2.54, 1), "+2.5");
        assert_eq!(signed(-8.333, 2), "-8.33");
        assert_eq!(round_length(200.0), "200 µm");
        assert_eq!(round_length(0.5), "0.5 µm");
        assert_eq!(round_length(2000.0), "2 mm");
        assert_eq!(pitch(0.8148), "0.8148 µm");
        assert_eq!(fixed(f64::NAN, 2), "-");
        let (t, d) = ticks(-0.37, 1.23, 8);
        assert_eq!(d, 1);
        assert_eq!(t.len(), 8);
        assert!((t[0] + 0.2).abs() < 1e-12 && (t[7] - 1.2).abs() < 1e-12);
        assert_eq!(
            path_d([Some((0.0, 1.0)), Some((2.0, 3.0)), None, Some((4.0, 5.0))]),
            "M0.0,1.0L2.0,3.0M4.0,5.0"
        );
    }
}
