//! Bruker / Veeco / Digital Instruments Nanoscope (`.di`, `.spm`, `.001`...): a Latin-1 text
//! header of `\*Section` and `\Key: value` lines up to `\*File list end`, then binary images.
//!
//! Read as SurfaceTopography's `IO/DI.py` (MIT, 1.27.1) reads it, checked on its public
//! samples (tests/data/specimens/README.md):
//!
//! - The first section is `File list` (`Version` in hex, `Date`); the scanner section
//!   (`Scanner list` / `Microscope list`) and scan section (`Ciao scan list`, `AFM list`, ...)
//!   hold the soft scales (`\@Sens. Zsens: V 20.82646 nm/V`) and the whole scan's
//!   `Samps/line`, `Lines`, `Slow Axis Size`.
//! - Each image section (`Ciao image list`, `AFM image list`, ...): `Data offset`,
//!   `Data length`, `Bytes/pixel` (2 or 4; from version 0x09200000 data are 32-bit when the
//!   length says so), `Samps/line`, `Number of lines`, `Scan Size` ("500 500 nm", "10 ~m";
//!   `~m` = um), `@2:Image Data` (the channel: `S [Height] "Height"`) and `@2:Z scale`
//!   (`V [Sens. Zsens] (0.0050354 V/LSB) 2.910461 V`).
//! - Height per count = Z-scale value / 256^bytes_per_pixel (in its unit, e.g. V) x the soft
//!   scale named in brackets (e.g. nm/V): a channel whose soft unit is no length per the
//!   Z-scale unit is no height map. Z offset is not applied (as SurfaceTopography).
//! - Data: i16 or i32 little-endian, x fastest. Rows kept in stored order (first stored row =
//!   row 0); SurfaceTopography flips them to Gwyddion's image order (its `fliplr`), so its
//!   row `ny - 1 - r` is our row `r`.
//! - The first image section holding heights is read; metadata `channels` lists them all. Text data (`?*` files), force curves and unevenly spaced profiles are refused.

use anyhow::{bail, Context, Result};

use super::bytes::{checked_size, length_unit_um, Bytes};
use super::{Metadata, Surface};

const VERSION_32BIT: u64 = 0x0920_0000;
/// A header longer than this is no Nanoscope header (they are tens of kB).
const MAX_HEADER_BYTES: usize = 1 << 22;

struct Section {
    name: String,
    entries: Vec<(String, String)>,
}

impl Section {
    fn get(&self, key: &str) -> Option<&str> {
        // The last of repeated keys, as a dict would keep it.
        self.entries
            .iter()
            .rev()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v.as_str())
    }
}

/// A `@` value: `V [soft scale] (hard scale) hard value`.
struct AtValue<'a> {
    kind: char,
    soft_scale: Option<&'a str>,
    hard_value: &'a str,
}

pub fn parse(data: &[u8]) -> Result<Surface> {
    if data.starts_with(b"?*") {
        bail!("a Nanoscope file with its data stored as text ('?*'): only binary data are read");
    }
    let sections = header(data)?;
    let merged = |names: &[&str]| -> Section {
        let mut s = Section {
            name: names[0].into(),
            entries: Vec::new(),
        };
        for sec in sections.iter().filter(|s| names.contains(&s.name.as_str())) {
            s.entries.extend(sec.entries.iter().cloned());
        }
        s
    };
    let file_list = merged(&["file list", "ec file list"]);
    let scanner = merged(&["scanner list", "microscope list"]);
    let scan = merged(&["ciao scan list", "afm list", "stm list", "nc afm list"]);
    let equipment = merged(&["equipment list"]);
    let operating_mode = sections
        .iter()
        .rev()
        .find_map(|s| s.get("operating mode"))
        .unwrap_or_default()
        .trim()
        .to_string();
    let version = file_list
        .get("version")
        .and_then(|v| u64::from_str_radix(v.trim().trim_start_matches("0x"), 16).ok())
        .unwrap_or(0);
    let start_context = file_list.get("start context").unwrap_or_default().trim();
    if operating_mode == "Force" || start_context == "FOL" {
        bail!("the file holds force curves (operating mode Force), not a height map");
    }
    if start_context.ends_with("VAR") && operating_mode != "Force Volume" {
        bail!("the file holds unevenly spaced profiles (start context '{start_context}'), not a height map");
    }
    let global = match (
        scan.get("samps/line")
            .and_then(|v| v.trim().parse::<usize>().ok()),
        scan.get("lines")
            .and_then(|v| v.trim().parse::<usize>().ok()),
    ) {
        (Some(nx), Some(ny)) => Some((nx, ny)),
        _ => None,
    };
    // Newer files store the slow axis size separately; the second number of "Scan size" can
    // then be wrong. (fast size, slow size, in the fast size's unit.)
    let slow_axis = match (scan.get("slow axis size"), scan.get("scan size")) {
        (Some(slow), Some(fast)) => {
            let (fast, fast_unit) = size_and_unit(fast, "scan list 'Scan Size'")?;
            let (slow, slow_unit) = size_and_unit(slow, "scan list 'Slow Axis Size'")?;
            match (length_unit_um(&fast_unit), length_unit_um(&slow_unit)) {
                (Some(f), Some(s)) => Some((fast * f, slow * s)),
                _ => None,
            }
        }
        _ => None,
    };

    let image_names = [
        "ciao image list",
        "afm image list",
        "stm image list",
        "ncafm image list",
        "image list",
    ];
    let mut channels = Vec::new();
    let mut first: Option<Surface> = None;
    for (i, sec) in sections
        .iter()
        .filter(|s| image_names.contains(&s.name.as_str()))
        .enumerate()
    {
        let name = channel_name(sec)?.unwrap_or_else(|| format!("image {i}"));
        let s = image(data, sec, i, version, global, slow_axis, &scanner, &scan)
            .with_context(|| format!("image section {i} ('{name}')"))?;
        channels.push(format!(
            "{name}{}",
            if s.is_some() { "" } else { " (no height)" }
        ));
        if first.is_none() {
            first = s;
        }
    }
    let mut s = first.with_context(|| {
        format!(
            "no image section holds heights (a Z scale whose soft scale is a length per unit); channels: {}",
            if channels.is_empty() {
                "none".to_string()
            } else {
                channels.join(", ")
            }
        )
    })?;
    // Every AFM file holds several channels: listed, not warned about.
    s.metadata
        .extra
        .insert("channels".into(), channels.join(", "));
    let m = &mut s.metadata;
    m.instrument = equipment
        .get("microscope")
        .or(equipment.get("description"))
        .map(|v| format!("Bruker {}", v.trim()));
    m.serial = scanner
        .get("serial number")
        .or(scan.get("serial number"))
        .map(|v| v.trim().to_string())
        .filter(|v| !v.is_empty());
    if let Some(d) = file_list.get("date") {
        m.extra.insert("date_text".into(), d.trim().to_string());
        m.date = super::date::iso8601_date(d);
    }
    if let Some(v) = file_list.get("version") {
        m.extra.insert("version".into(), v.trim().to_string());
    }
    Ok(s)
}

/// The header's sections, in order, keys lower-cased, values trimmed.
fn header(data: &[u8]) -> Result<Vec<Section>> {
    let mut sections: Vec<Section> = Vec::new();
    let mut at = 0usize;
    loop {
        if at >= data.len() {
            bail!(
                "the header ends at byte {} without its '\\*File list end' line: truncated or not a Nanoscope file",
                data.len()
            );
        }
        if at > MAX_HEADER_BYTES {
            bail!("no '\\*File list end' line in the first {MAX_HEADER_BYTES} bytes: not a Nanoscope file");
        }
        let end = data[at..]
            .iter()
            .position(|&b| b == b'\n')
            .map_or(data.len(), |p| at + p);
        let line: String = data[at..end].iter().map(|&b| b as char).collect();
        let line = line.trim();
        at = end + 1;
        if line.eq_ignore_ascii_case("\\*File list end") {
            break;
        }
        if line.is_empty() {
            // SurfaceTopography ends the header here too; the data offsets are checked below.
            break;
        }
        if let Some(name) = line.strip_prefix("\\*") {
            let name = name.to_lowercase();
            if sections.is_empty() && name != "file list" && name != "ec file list" {
                bail!("the header starts with section '{name}', expected 'File list': not a Nanoscope file");
            }
            sections.push(Section {
                name,
                entries: Vec::new(),
            });
        } else if let Some(entry) = line.strip_prefix('\\') {
            let Some(section) = sections.last_mut() else {
                bail!("the header starts with '{line}', expected the section '\\*File list': not a Nanoscope file");
            };
            let (key, value) = entry.split_once(": ").unwrap_or((entry, ""));
            section.entries.push((
                key.trim_end_matches(':').to_lowercase(),
                value.trim().into(),
            ));
        } else {
            bail!(
                "header line at byte {} does not start with a backslash: '{}'",
                end - line.len(),
                line.chars().take(60).collect::<String>()
            );
        }
    }
    if sections.is_empty() {
        bail!("the header has no sections");
    }
    Ok(sections)
}

/// The channel name of an image section (`@2:Image Data: S [Height] "Height"`).
fn channel_name(sec: &Section) -> Result<Option<String>> {
    for key in ["@2:image data", "@3:image data", "@4:image data"] {
        if let Some(v) = sec.get(key) {
            let v = at_value(v, key)?;
            return Ok(Some(
                v.soft_scale
                    .map(str::to_string)
                    .unwrap_or_else(|| v.hard_value.trim_matches('"').to_string()),
            ));
        }
    }
    Ok(sec.get("image data").map(str::to_string))
}

/// The surface of one image section, or None when its data are no heights.
#[allow(clippy::too_many_arguments)]
fn image(
    data: &[u8],
    sec: &Section,
    index: usize,
    version: u64,
    global: Option<(usize, usize)>,
    slow_axis: Option<(f64, f64)>,
    scanner: &Section,
    scan: &Section,
) -> Result<Option<Surface>> {
    let int = |key: &str| -> Result<usize> {
        let v = sec
            .get(key)
            .with_context(|| format!("field '{key}' is missing"))?;
        v.trim()
            .parse::<usize>()
            .with_context(|| format!("field '{key}' is '{v}', expected a whole number"))
    };
    let (mut nx, mut ny) = (int("samps/line")?, int("number of lines")?);
    let scan_size = sec
        .get("scan size")
        .context("field 'Scan Size' is missing")?;
    let (mut sx_um, mut sy_um) = scan_sizes_um(scan_size)?;
    if let Some((fast_um, slow_um)) = slow_axis {
        (sx_um, sy_um) = (fast_um, slow_um);
    }
    let offset = int("data offset")?;
    let length = int("data length")?;
    let bytes_per_pixel = match sec.get("bytes/pixel") {
        None => 2,
        Some(_) => int("bytes/pixel")?,
    };
    if bytes_per_pixel != 2 && bytes_per_pixel != 4 {
        bail!("field 'Bytes/pixel' is {bytes_per_pixel}, expected 2 or 4");
    }
    let n = checked_size(&[nx, ny], "'Samps/line' x 'Number of lines'")?;
    let mut elsize = bytes_per_pixel;
    if version >= VERSION_32BIT && length >= n.saturating_mul(4) {
        elsize = 4;
    }
    // Some files give wrong sizes in the image sections; the scan's are then right.
    if let Some((gx, gy)) = global {
        let local = n.saturating_mul(elsize);
        let whole = gx.saturating_mul(gy).saturating_mul(elsize);
        if length != local && (length == whole || (local > length && length >= whole)) {
            if slow_axis.is_none() {
                sx_um *= gx as f64 / nx as f64;
                sy_um *= gy as f64 / ny as f64;
            }
            (nx, ny) = (gx, gy);
        } else if slow_axis.is_some() && nonsquare_aspect(sec) && ny < gy {
            // A scan stopped early ("Capture Now"): the slow axis size is the full scan's.
            sy_um *= ny as f64 / gy as f64;
        }
    }
    if nx == 0 || ny == 0 {
        bail!("fields 'Samps/line' x 'Number of lines' are {nx} x {ny}, expected positive");
    }
    let n = checked_size(&[nx, ny], "'Samps/line' x 'Number of lines'")?;
    let need = checked_size(&[n, elsize], "image data size")?;
    if need > length {
        bail!(
            "field 'Data length' is {length} bytes, but {nx} x {ny} points of {elsize} bytes need {need}"
        );
    }
    let z_key = if sec.get("@4:z scale").is_some() {
        "@4:z scale"
    } else {
        "@2:z scale"
    };
    let z_scale = sec
        .get(z_key)
        .context("field '@2:Z scale' is missing (Nanoscope 4.2 and earlier files are not read)")?;
    let z = at_value(z_scale, z_key)?;
    let (hard_value, hard_unit) = number_and_unit(z.hard_value, z_key)?;
    let hard_scale = hard_value / 256f64.powi(bytes_per_pixel as i32);
    let Some(quantity) = z.soft_scale else {
        return Ok(None);
    };
    let soft_key = format!("@{}", quantity.to_lowercase());
    let Some(soft) = scanner.get(&soft_key).or(scan.get(&soft_key)) else {
        return Ok(None);
    };
    let soft = at_value(soft, &soft_key)?;
    if soft.kind != 'V' {
        bail!(
            "soft scale '{soft_key}' is of type '{}', expected 'V' (a value)",
            soft.kind
        );
    }
    let (soft_scale, soft_unit) = number_and_unit(soft.hard_value, &soft_key)?;
    let Some((height_unit, per_unit)) = soft_unit.split_once('/') else {
        return Ok(None);
    };
    let Some(height_um) = length_unit_um(&mangle_unit(height_unit)) else {
        return Ok(None);
    };
    let hard_to_soft = unit_ratio(&hard_unit, per_unit).with_context(|| {
        format!("'{z_key}' is in '{hard_unit}' but soft scale '{soft_key}' is per '{per_unit}'")
    })?;
    let step_um = hard_scale * hard_to_soft * soft_scale * height_um;
    if !step_um.is_finite() || step_um == 0.0 {
        bail!(
            "'{z_key}' x '{soft_key}' give a height step of {step_um} um, expected finite non-zero"
        );
    }
    let b = Bytes::new(data);
    let raw = b.slice(
        offset,
        need,
        &format!("image {index} data ('Data offset' {offset}, {need} bytes)"),
    )?;
    let heights_um: Vec<f64> = if elsize == 2 {
        raw.chunks_exact(2)
            .map(|c| i16::from_le_bytes([c[0], c[1]]) as f64 * step_um)
            .collect()
    } else {
        raw.chunks_exact(4)
            .map(|c| i32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64 * step_um)
            .collect()
    };
    let mut metadata = Metadata {
        format: "di".into(),
        pitch_known: true,
        ..Metadata::default()
    };
    if let Some(name) = channel_name(sec)? {
        metadata.extra.insert("channel".into(), name);
    }
    metadata
        .extra
        .insert("height_step_um".into(), format!("{step_um:e}"));
    Ok(Some(Surface {
        width: nx,
        height: ny,
        pitch_x_um: sx_um / nx as f64,
        pitch_y_um: sy_um / ny as f64,
        heights_um,
        metadata,
    }))
}

fn nonsquare_aspect(sec: &Section) -> bool {
    match sec.get("aspect ratio").map(str::trim) {
        None | Some("1:1") => false,
        Some(a) => a
            .split(':')
            .next()
            .and_then(|r| r.trim().parse::<f64>().ok())
            .is_some_and(|r| r > 0.0 && r != 1.0),
    }
}

/// `V [soft] (hard) value`: the parts of a `@` value.
fn at_value<'a>(value: &'a str, key: &str) -> Result<AtValue<'a>> {
    let v = value.trim();
    let mut chars = v.chars();
    let kind = chars
        .next()
        .with_context(|| format!("field '{key}' is empty"))?;
    let mut rest = chars.as_str().trim();
    let mut soft_scale = None;
    if let Some(r) = rest.strip_prefix('[') {
        let end = r
            .find(']')
            .with_context(|| format!("field '{key}' = '{v}': no ']' after its soft scale"))?;
        soft_scale = Some(r[..end].trim()).filter(|s| !s.is_empty());
        rest = r[end + 1..].trim();
    }
    if rest.starts_with('(') {
        // Units may hold parentheses themselves, e.g. log(Arb).
        let mut level = 0i32;
        let mut close = None;
        for (i, c) in rest.char_indices() {
            match c {
                '(' => level += 1,
                ')' => {
                    level -= 1;
                    if level == 0 {
                        close = Some(i);
                        break;
                    }
                }
                _ => {}
            }
        }
        let close =
            close.with_context(|| format!("field '{key}' = '{v}': unbalanced parentheses"))?;
        rest = rest[close + 1..].trim();
    }
    Ok(AtValue {
        kind,
        soft_scale,
        hard_value: rest,
    })
}

/// "2.910461 V" -> (2.910461, "V").
fn number_and_unit(v: &str, key: &str) -> Result<(f64, String)> {
    let v = v.trim();
    let (num, unit) = v.split_once(char::is_whitespace).unwrap_or((v, ""));
    let x: f64 = num
        .parse()
        .with_context(|| format!("field '{key}': '{v}' does not start with a number"))?;
    Ok((x, unit.trim().to_string()))
}

/// "500 500 nm", "10 ~m" (square scan) -> (size x, size y) in um.
fn scan_sizes_um(v: &str) -> Result<(f64, f64)> {
    let parts: Vec<&str> = v.split_whitespace().collect();
    let sx: f64 = parts
        .first()
        .and_then(|p| p.parse().ok())
        .with_context(|| format!("field 'Scan Size' is '{v}', expected a size and a unit"))?;
    let (sy, unit) = match parts.get(1).and_then(|p| p.parse::<f64>().ok()) {
        Some(sy) => (sy, parts[2..].join(" ")),
        None => (sx, parts[1..].join(" ")),
    };
    let um = length_unit_um(&mangle_unit(&unit))
        .with_context(|| format!("field 'Scan Size' is '{v}': unit '{unit}' is no length unit"))?;
    for (axis, s) in [("x", sx), ("y", sy)] {
        if !s.is_finite() || s <= 0.0 {
            bail!("field 'Scan Size' is '{v}': the {axis} size is not a positive number");
        }
    }
    Ok((sx * um, sy * um))
}

fn size_and_unit(v: &str, field: &str) -> Result<(f64, String)> {
    let (x, unit) = number_and_unit(v, field)?;
    Ok((x, mangle_unit(&unit)))
}

/// Nanoscope writes um as "~m".
fn mangle_unit(u: &str) -> String {
    u.trim().replace('~', "\u{b5}")
}

/// How many `to` one `from` is, for the units the Z scale and soft scales use (lengths,
/// volts, degrees, ...): equal units are 1.
fn unit_ratio(from: &str, to: &str) -> Option<f64> {
    let (from, to) = (mangle_unit(from), mangle_unit(to));
    if from == to {
        return Some(1.0);
    }
    if let (Some(a), Some(b)) = (length_unit_um(&from), length_unit_um(&to)) {
        return Some(a / b);
    }
    let volts = |u: &str| match u {
        "V" => Some(1.0),
        "mV" => Some(1e-3),
        "\u{b5}V" | "uV" => Some(1e-6),
        _ => None,
    };
    Some(volts(&from)? / volts(&to)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn at_values_split_into_soft_scale_and_hard_value() {
        let v = at_value("V [Sens. Zsens] (0.005035400 V/LSB) 2.910461 V", "k").unwrap();
        assert_eq!(
            (v.kind, v.soft_scale, v.hard_value),
            ('V', Some("Sens. Zsens"), "2.910461 V")
        );
        let v = at_value("V (0.1 log(Arb)/LSB) 3 log(Arb)", "k").unwrap();
        assert_eq!((v.soft_scale, v.hard_value), (None, "3 log(Arb)"));
        assert!(at_value("V [Sens. Zsens (0.1 V/LSB) 2 V", "k").is_err());
        assert!(at_value("V (0.1 V/LSB 2 V", "k").is_err());
        assert_eq!(scan_sizes_um("10 ~m").unwrap(), (10.0, 10.0));
        assert_eq!(scan_sizes_um("500 250 nm").unwrap(), (0.5, 0.25));
        assert!(scan_sizes_um("500 250 V").is_err());
        assert_eq!(unit_ratio("mV", "V"), Some(1e-3));
        assert_eq!(unit_ratio("\u{ba}", "V"), None);
    }
}
