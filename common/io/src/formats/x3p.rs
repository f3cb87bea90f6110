//! ISO 25178-72 X3P: a zip of `main.xml` (the description), `md5checksum.hex` (MD5 of
//! main.xml), `bindata/data.bin` (little-endian points, x fastest, then y) and optionally
//! `bindata/valid.bin` (one bit per point, least significant bit first, 1 = valid).
//!
//! Row index = y index of the file (the first stored line is row 0), so a panorama written by
//! [`write`] reads back identically. Both MD5 checksums are verified (upper or lower case hex);
//! the error says which one failed. Integer z = Offset + int * Increment (metres).
//!
//! Validity is the standard's: `valid.bin`, NaN in float data, an empty `Datum`. The colour
//! mask x3ptools and FiX3P add (`Record3/Mask`, `bindata/mask.png`) labels regions and is read
//! as labels ([`ColourMask`]): it never makes a point "not measured" unless a user asks
//! ([`ColourMask::exclude`], `--mask-exclude`).

use std::io::{Cursor, Read, Seek, Write};
use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};
use md5::{Digest, Md5};

use super::bytes::checked_size;
use super::{Metadata, Surface};
use crate::figure::esc;

const NAMESPACE: &str = "http://www.opengps.eu/2008/ISO5436_2";
/// main.xml larger than this is not a description but an attack.
const MAX_XML_BYTES: u64 = 16 << 20;

fn hex(digest: &[u8]) -> String {
    use std::fmt::Write as _;
    digest.iter().fold(String::new(), |mut s, b| {
        let _ = write!(s, "{b:02x}");
        s
    })
}

fn md5_hex(data: &[u8]) -> String {
    hex(&Md5::digest(data))
}

/// Reads `name` from the archive, refusing more than `limit` bytes (zip sizes are untrusted).
fn read_entry<R: Read + Seek>(
    zip: &mut zip::ZipArchive<R>,
    name: &str,
    limit: u64,
) -> Result<Vec<u8>> {
    let entry = zip
        .by_name(name)
        .with_context(|| format!("zip entry '{name}'"))?;
    let mut out = Vec::new();
    entry
        .take(limit + 1)
        .read_to_end(&mut out)
        .with_context(|| format!("zip entry '{name}': cannot decompress"))?;
    if out.len() as u64 > limit {
        bail!("zip entry '{name}' is larger than the {limit} bytes expected");
    }
    Ok(out)
}

/// Inflated bytes handed from the inflating thread to the hashing / converting one at a time
/// (a multiple of every point size, so no point straddles two chunks).
const CHUNK_BYTES: usize = 1 << 18;

/// Reads the point data entry `name` (exactly `data_bytes` expected) and converts it to
/// heights, while a second thread hashes it (MD5, when `want_md5`) and converts what is already
/// inflated: inflating, hashing and converting overlap instead of adding up. Returns the
/// heights, the number of bytes read and the hex MD5.
fn read_points<R: Read + Seek>(
    zip: &mut zip::ZipArchive<R>,
    name: &str,
    data_bytes: usize,
    want_md5: bool,
    ztype: ZType,
    to_um: impl Fn(f64) -> f64 + Send + Sync,
) -> Result<(Vec<f64>, usize, Option<String>)> {
    let mut entry = zip
        .by_name(name)
        .with_context(|| format!("zip entry '{name}'"))?;
    check_entry_declares(name, data_bytes, entry.size())?;
    check_entry_can_hold(
        name,
        data_bytes,
        entry.compressed_size(),
        entry.compression(),
    )?;
    let (tx, rx) = std::sync::mpsc::sync_channel::<Vec<u8>>(4);
    std::thread::scope(|scope| {
        let worker = scope.spawn(|| {
            let mut md5 = want_md5.then(Md5::new);
            // Sized by the checked size from main.xml, not by anything the zip claims.
            let mut heights = Vec::with_capacity(data_bytes / ztype.bytes());
            for chunk in rx {
                if let Some(h) = md5.as_mut() {
                    h.update(&chunk);
                }
                convert(ztype, &chunk, &to_um, &mut heights);
            }
            (heights, md5.map(|h| hex(&h.finalize())))
        });
        let mut total = 0usize;
        let read = (|| -> Result<()> {
            loop {
                let mut buf = vec![0u8; CHUNK_BYTES];
                let mut filled = 0;
                while filled < buf.len() {
                    let k = entry
                        .read(&mut buf[filled..])
                        .with_context(|| format!("zip entry '{name}': cannot decompress"))?;
                    if k == 0 {
                        break;
                    }
                    filled += k;
                }
                total += filled;
                if total > data_bytes {
                    bail!("zip entry '{name}' is larger than the {data_bytes} bytes expected");
                }
                if filled == 0 {
                    return Ok(());
                }
                buf.truncate(filled);
                if tx.send(buf).is_err() {
                    bail!("zip entry '{name}': the converting thread stopped");
                }
                if filled < CHUNK_BYTES {
                    return Ok(());
                }
            }
        })();
        drop(tx);
        let (heights, md5) = worker
            .join()
            .map_err(|_| anyhow!("zip entry '{name}': the converting thread panicked"))?;
        read.map(|()| (heights, total, md5))
    })
}

/// Refuses a point data entry whose size in the archive's directory is not the size main.xml's
/// MatrixDimension implies, before anything is allocated or inflated for it: a 3 MB file that
/// declares 20 000 x 20 000 points took 30 s and 3 GB before its short data was found.
fn check_entry_declares(name: &str, data_bytes: usize, declared_bytes: u64) -> Result<()> {
    if declared_bytes != data_bytes as u64 {
        bail!(
            "main.xml: MatrixDimension declares {data_bytes} bytes of point data, but the \
             archive declares zip entry '{name}' as {declared_bytes} bytes (uncompressed): \
             expected the two to agree"
        );
    }
    Ok(())
}

/// Deflate expands at most about 1032:1; a stored entry not at all.
const MAX_DEFLATE_RATIO: u64 = 1032;

/// Refuses a size claim (main.xml's SizeX * SizeY) that the archive entry cannot hold, before
/// anything is allocated for it: a 100000 x 100000 claim in a 3 MB file is an error, not an
/// 80 GB allocation.
fn check_entry_can_hold(
    name: &str,
    data_bytes: usize,
    compressed_bytes: u64,
    method: zip::CompressionMethod,
) -> Result<()> {
    let ratio = if method == zip::CompressionMethod::Stored {
        1
    } else {
        MAX_DEFLATE_RATIO
    };
    let most = compressed_bytes.saturating_mul(ratio).saturating_add(64);
    if data_bytes as u64 > most {
        bail!(
            "main.xml: MatrixDimension declares {data_bytes} bytes of point data, but zip entry \
             '{name}' ({compressed_bytes} bytes stored, {method:?}) can hold at most {most}"
        );
    }
    Ok(())
}

/// Little-endian points to heights in um (a trailing partial point is left out: the caller
/// checks the total size).
fn convert(ztype: ZType, raw: &[u8], to_um: &impl Fn(f64) -> f64, out: &mut Vec<f64>) {
    match ztype {
        ZType::I16 => out.extend(
            raw.chunks_exact(2)
                .map(|c| to_um(i16::from_le_bytes([c[0], c[1]]) as f64)),
        ),
        ZType::I32 => out.extend(
            raw.chunks_exact(4)
                .map(|c| to_um(i32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64)),
        ),
        ZType::F32 => out.extend(
            raw.chunks_exact(4)
                .map(|c| to_um(f32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64)),
        ),
        ZType::F64 => out.extend(raw.chunks_exact(8).map(|c| {
            let mut a = [0u8; 8];
            a.copy_from_slice(c);
            to_um(f64::from_le_bytes(a))
        })),
    }
}

/// Child element of `node` with local name `name` (children are unqualified in X3P).
fn child<'a, 'i>(node: roxmltree::Node<'a, 'i>, name: &str) -> Option<roxmltree::Node<'a, 'i>> {
    node.children()
        .find(|c| c.is_element() && c.tag_name().name() == name)
}

fn need<'a, 'i>(node: roxmltree::Node<'a, 'i>, path: &[&str]) -> Result<roxmltree::Node<'a, 'i>> {
    let mut n = node;
    for (i, p) in path.iter().enumerate() {
        n = child(n, p)
            .with_context(|| format!("main.xml: element '{}' missing", path[..=i].join("/")))?;
    }
    Ok(n)
}

fn text_of(node: roxmltree::Node, path: &[&str]) -> Option<String> {
    let mut n = node;
    for p in path {
        n = child(n, p)?;
    }
    n.text()
        .map(|t| t.trim().to_string())
        .filter(|t| !t.is_empty())
}

fn number(node: roxmltree::Node, path: &[&str]) -> Result<Option<f64>> {
    match text_of(node, path) {
        None => Ok(None),
        Some(t) => {
            let v: f64 = t.parse().map_err(|_| {
                anyhow!("main.xml: '{}' is '{t}', expected a number", path.join("/"))
            })?;
            if !v.is_finite() {
                bail!(
                    "main.xml: '{}' is {v}, expected a finite number",
                    path.join("/")
                );
            }
            Ok(Some(v))
        }
    }
}

#[derive(Clone, Copy)]
enum ZType {
    I16,
    I32,
    F32,
    F64,
}

impl ZType {
    fn bytes(self) -> usize {
        match self {
            ZType::I16 => 2,
            ZType::I32 | ZType::F32 => 4,
            ZType::F64 => 8,
        }
    }
}

pub fn parse(data: &[u8]) -> Result<Surface> {
    let mut zip = zip::ZipArchive::new(Cursor::new(data)).context("not a zip archive")?;
    let names: Vec<String> = zip
        .file_names()
        .filter_map(|n| n.ok())
        .map(|n| n.into_owned())
        .collect();
    // main.xml may sit in a sub-folder; two descriptions are an ambiguity, not a choice
    // (issue 36: the second was read silently).
    let mains: Vec<&String> = names
        .iter()
        .filter(|n| *n == "main.xml" || n.ends_with("/main.xml"))
        .collect();
    if mains.len() > 1 {
        bail!(
            "the archive holds {} main.xml entries ({}): expected one description",
            mains.len(),
            mains
                .iter()
                .map(|n| format!("'{n}'"))
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    let main_name = mains
        .first()
        .map(|n| n.to_string())
        .context("no main.xml in the archive")?;
    let folder = &main_name[..main_name.len() - "main.xml".len()];
    let xml_bytes = read_entry(&mut zip, &main_name, MAX_XML_BYTES)?;
    // A checksum that does not match is a warning, not a refusal: the user wants the data, and
    // to be told.
    let mut warnings = Vec::new();
    let sum_name = format!("{folder}md5checksum.hex");
    if names.contains(&sum_name) {
        let sum_file = read_entry(&mut zip, &sum_name, 4096)?;
        let sum_text = String::from_utf8_lossy(&sum_file);
        let expected = sum_text.split_whitespace().next().unwrap_or("");
        let actual = md5_hex(&xml_bytes);
        if !expected.eq_ignore_ascii_case(&actual) {
            warnings.push(format!("MD5 checksum of main.xml fails: md5checksum.hex says '{expected}', main.xml hashes to {actual}; the data is read as stored"));
        }
    }
    let xml = std::str::from_utf8(&xml_bytes).context("main.xml is not UTF-8")?;
    let doc = roxmltree::Document::parse(xml).context("main.xml is not well-formed XML")?;
    let root = doc.root_element();
    // Some writers name the root after the 2000 standard, ISO5436, with the same records.
    if !matches!(root.tag_name().name(), "ISO5436_2" | "ISO5436") {
        bail!(
            "main.xml: root element is '{}', expected ISO5436_2 (or ISO5436)",
            root.tag_name().name()
        );
    }
    if root
        .tag_name()
        .namespace()
        .is_some_and(|ns| ns != NAMESPACE)
    {
        bail!("main.xml: root namespace is not {NAMESPACE}");
    }
    let r1 = need(root, &["Record1"])?;
    let feature = text_of(r1, &["FeatureType"]).unwrap_or_default();
    if feature != "SUR" {
        bail!("main.xml: Record1/FeatureType is '{feature}', expected SUR (profiles and point clouds are not read)");
    }
    let axes = need(r1, &["Axes"])?;
    for ax in ["CX", "CY"] {
        let t = text_of(axes, &[ax, "AxisType"]).unwrap_or_default();
        if t != "I" {
            bail!("main.xml: Axes/{ax}/AxisType is '{t}', expected I (incremental); absolute lateral axes are not read");
        }
    }
    let pitch_x_m =
        number(axes, &["CX", "Increment"])?.context("main.xml: Axes/CX/Increment missing")?;
    let pitch_y_m =
        number(axes, &["CY", "Increment"])?.context("main.xml: Axes/CY/Increment missing")?;
    if pitch_x_m <= 0.0 || pitch_y_m <= 0.0 {
        bail!("main.xml: Axes CX/CY Increment are {pitch_x_m} / {pitch_y_m}, expected positive");
    }
    // Where point (0, 0) is, when the file says: x = Offset + i * Increment.
    let stage_position_um = match (
        number(axes, &["CX", "Offset"])?,
        number(axes, &["CY", "Offset"])?,
    ) {
        (Some(x), Some(y)) => Some([x * 1e6, y * 1e6]),
        _ => None,
    };
    let ztype = match text_of(axes, &["CZ", "DataType"]).as_deref() {
        Some("I") => ZType::I16,
        Some("L") => ZType::I32,
        Some("F") => ZType::F32,
        Some("D") => ZType::F64,
        other => bail!("main.xml: Axes/CZ/DataType is {other:?}, expected I, L, F or D"),
    };
    let z_increment = number(axes, &["CZ", "Increment"])?.unwrap_or(1.0);
    let z_offset = number(axes, &["CZ", "Offset"])?.unwrap_or(0.0);
    let r3 = need(root, &["Record3"])?;
    let dims = need(r3, &["MatrixDimension"])?;
    let size = |n: &str| -> Result<usize> {
        let t = text_of(dims, &[n])
            .with_context(|| format!("main.xml: MatrixDimension/{n} missing"))?;
        t.parse::<usize>().map_err(|_| {
            anyhow!("main.xml: MatrixDimension/{n} is '{t}', expected a non-negative integer")
        })
    };
    let (width, height, layers) = (size("SizeX")?, size("SizeY")?, size("SizeZ")?);
    if width == 0 || height == 0 || layers != 1 {
        bail!("main.xml: MatrixDimension is {width} x {height} x {layers}, expected SizeX, SizeY > 0 and SizeZ = 1");
    }
    let n = checked_size(&[width, height], "SizeX * SizeY")?;
    let data_bytes = checked_size(&[n, ztype.bytes()], "point data size")?;
    let to_um = |v: f64| (z_offset + v * z_increment) * 1e6;
    let Some(link) = child(r3, "DataLink") else {
        let list =
            child(r3, "DataList").context("main.xml: Record3 has neither DataLink nor DataList")?;
        let heights_um = parse_data_list(list, n, &to_um)?;
        let mask = read_mask(&mut zip, &names, folder, r3, (width, height), &mut warnings)?;
        return Ok(finish(
            root,
            r1,
            (width, height),
            (pitch_x_m, pitch_y_m),
            stage_position_um,
            heights_um,
            warnings,
            mask,
        ));
    };
    let point_link =
        text_of(link, &["PointDataLink"]).context("main.xml: DataLink/PointDataLink missing")?;
    let entry_name = |l: &str| -> Result<String> {
        let with_folder = format!("{folder}{l}");
        let found = [with_folder.as_str(), l]
            .into_iter()
            .find(|c| names.iter().any(|n| n == c))
            .map(|c| c.to_string());
        found.with_context(|| format!("main.xml names '{l}', which is not in the archive"))
    };
    let data_name = entry_name(&point_link)?;
    let point_sum = text_of(link, &["MD5ChecksumPointData"]);
    let (mut heights_um, read_bytes, actual_sum) = read_points(
        &mut zip,
        &data_name,
        data_bytes,
        point_sum.is_some(),
        ztype,
        to_um,
    )?;
    if read_bytes != data_bytes {
        bail!(
            "{data_name} has {read_bytes} bytes, expected {width} x {height} x {} = {data_bytes}",
            ztype.bytes()
        );
    }
    if let (Some(sum), Some(actual)) = (point_sum, actual_sum) {
        if !sum.eq_ignore_ascii_case(&actual) {
            warnings.push(format!("MD5 checksum of the point data ({data_name}) fails: main.xml says '{sum}', the data hashes to {actual}; the data is read as stored"));
        }
    }
    let valid = match text_of(link, &["ValidPointsLink"]) {
        None => None,
        Some(l) => {
            let name = entry_name(&l)?;
            let bits = read_entry(&mut zip, &name, n.div_ceil(8) as u64)?;
            if bits.len() != n.div_ceil(8) {
                bail!(
                    "{name} has {} bytes, expected {} (one bit per point)",
                    bits.len(),
                    n.div_ceil(8)
                );
            }
            if let Some(sum) = text_of(link, &["MD5ChecksumValidPoints"]) {
                let actual = md5_hex(&bits);
                if !sum.eq_ignore_ascii_case(&actual) {
                    warnings.push(format!("MD5 checksum of the valid points ({name}) fails: main.xml says '{sum}', the data hashes to {actual}; the mask is used as stored"));
                }
            }
            Some(bits)
        }
    };
    if let Some(bits) = valid {
        for (i, z) in heights_um.iter_mut().enumerate() {
            if bits[i / 8] >> (i % 8) & 1 == 0 {
                *z = f64::NAN;
            }
        }
    }
    let mask = read_mask(&mut zip, &names, folder, r3, (width, height), &mut warnings)?;
    Ok(finish(
        root,
        r1,
        (width, height),
        (pitch_x_m, pitch_y_m),
        stage_position_um,
        heights_um,
        warnings,
        mask,
    ))
}

/// Background colour of a mask without `Record3/Mask/Background` (x3ptools' and FiX3P's default).
const DEFAULT_MASK_BACKGROUND: [u8; 3] = [0xcd, 0x7f, 0x32];

/// "#rrggbb" (case-insensitive) to RGB.
fn parse_colour(text: &str) -> Option<[u8; 3]> {
    let hex = text.trim().strip_prefix('#')?;
    if hex.len() != 6 || !hex.is_ascii() {
        return None;
    }
    let byte = |i: usize| u8::from_str_radix(&hex[i..i + 2], 16).ok();
    Some([byte(0)?, byte(2)?, byte(4)?])
}

/// One colour of an X3P colour mask: a region of the surface an annotator labelled.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct MaskRegion {
    /// "#rrggbb", lower case.
    pub colour: String,
    /// The `Annotation` naming this colour in main.xml (the first non-empty one), if any.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub annotation: Option<String>,
    /// The mask's `Background` colour (fully transparent pixels count here too: nothing was
    /// painted there).
    pub background: bool,
    /// Points of this colour in the image (0 for an annotation no pixel carries).
    pub points: usize,
}

impl MaskRegion {
    /// How a user names the region: its annotation, else "background", else its colour.
    pub fn label(&self) -> String {
        match (&self.annotation, self.background) {
            (Some(a), _) => a.clone(),
            (None, true) => "background".into(),
            (None, false) => self.colour.clone(),
        }
    }
}

/// An X3P colour mask read as region labels (x3ptools / FiX3P: "annotations are legend entries
/// for each color of a mask"): every point stays as measured; [`ColourMask::exclude`] drops
/// the regions a user names.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ColourMask {
    /// The zip entry of the image, e.g. "bindata/mask.png".
    pub image: String,
    /// Background first, then the annotated colours in main.xml's order, then painted colours
    /// without an annotation.
    pub regions: Vec<MaskRegion>,
    /// Per point (row-major like the heights): index into `regions`.
    #[serde(skip)]
    pub labels: Vec<u16>,
}

impl ColourMask {
    /// The regions `spec` names: `#rrggbb` (or `#rrggbbaa`, alpha ignored) by colour, else an
    /// annotation (case-insensitive; several colours may share one) or "background".
    pub fn find(&self, spec: &str) -> Vec<usize> {
        let spec = spec.trim();
        if spec.starts_with('#') {
            let rgb = parse_colour(spec).or_else(|| {
                (spec.len() == 9)
                    .then(|| spec.get(..7).and_then(parse_colour))
                    .flatten()
            });
            let Some(rgb) = rgb else {
                return Vec::new();
            };
            let hex = colour_hex(rgb);
            return (0..self.regions.len())
                .filter(|&i| self.regions[i].colour == hex)
                .collect();
        }
        let named: Vec<usize> = (0..self.regions.len())
            .filter(|&i| {
                self.regions[i]
                    .annotation
                    .as_deref()
                    .is_some_and(|a| a.trim().eq_ignore_ascii_case(spec))
            })
            .collect();
        if !named.is_empty() || !spec.eq_ignore_ascii_case("background") {
            return named;
        }
        (0..self.regions.len())
            .filter(|&i| self.regions[i].background)
            .collect()
    }

    /// "'break-off' #1f376c (20900 points), ..." for messages.
    pub fn describe(&self) -> String {
        self.regions
            .iter()
            .map(|r| format!("'{}' {} ({} points)", r.label(), r.colour, r.points))
            .collect::<Vec<_>>()
            .join(", ")
    }

    /// Sets the heights of every region named in `specs` (see [`ColourMask::find`]) to NaN
    /// (not measured) and returns how many points that dropped. A name that matches no region
    /// is an error that lists the regions there are.
    pub fn exclude(&self, heights_um: &mut [f64], specs: &[String]) -> Result<usize> {
        if heights_um.len() != self.labels.len() {
            bail!(
                "the mask labels {} points, the surface has {}",
                self.labels.len(),
                heights_um.len()
            );
        }
        let mut drop = vec![false; self.regions.len()];
        for spec in specs {
            let found = self.find(spec);
            if found.is_empty() {
                bail!(
                    "mask region '{}' is not in the mask ({}); its regions are {} (name one by \
                     its annotation, 'background', or its colour #rrggbb)",
                    spec.trim(),
                    self.image,
                    self.describe()
                );
            }
            for i in found {
                drop[i] = true;
            }
        }
        let mut dropped = 0;
        for (z, &l) in heights_um.iter_mut().zip(&self.labels) {
            if drop.get(l as usize).copied().unwrap_or(false) && !z.is_nan() {
                *z = f64::NAN;
                dropped += 1;
            }
        }
        Ok(dropped)
    }
}

fn colour_hex(rgb: [u8; 3]) -> String {
    format!("#{:02x}{:02x}{:02x}", rgb[0], rgb[1], rgb[2])
}

/// Most distinct colours a mask may hold to be read as labels (one u16 label per point).
const MAX_MASK_COLOURS: usize = u16::MAX as usize;

/// The optional colour mask of x3ptools and FiX3P (an extension beside ISO 25178-72, whose
/// schema has no mask: validity there is `ValidPointsLink` / `bindata/valid.bin`, or NaN in
/// float data): `Record3/Mask` (`Background` colour, `Annotations/Annotation color="#rrggbb"`
/// naming each painted colour, optional `Link` to the image) and a PNG, `bindata/mask.png` by
/// default, SizeX pixels wide and SizeY tall, pixel (column i, row j) covering point (i, j) of
/// data.bin. A colour is a region label, not a validity flag: every point keeps its height,
/// and the regions (colour, annotation, point count) are returned for the user to see and,
/// on request, drop ([`ColourMask::exclude`]).
fn read_mask<R: Read + Seek>(
    zip: &mut zip::ZipArchive<R>,
    names: &[String],
    folder: &str,
    r3: roxmltree::Node,
    (width, height): (usize, usize),
    warnings: &mut Vec<String>,
) -> Result<Option<ColourMask>> {
    let mask = child(r3, "Mask");
    let link = mask
        .and_then(|m| text_of(m, &["Link"]))
        .unwrap_or_else(|| "bindata/mask.png".into());
    let Some(name) = [format!("{folder}{link}"), link.clone()]
        .into_iter()
        .find(|c| names.iter().any(|n| n == c))
    else {
        if mask.is_some_and(|m| child(m, "Link").is_some()) {
            bail!("main.xml: Record3/Mask/Link names '{link}', which is not in the archive");
        }
        return Ok(None);
    };
    let background = match mask.and_then(|m| text_of(m, &["Background"])) {
        None => DEFAULT_MASK_BACKGROUND,
        Some(t) => parse_colour(&t).with_context(|| {
            format!("main.xml: Record3/Mask/Background is '{t}', expected a colour #rrggbb")
        })?,
    };
    let n = width * height;
    // A PNG of width x height points holds at most 8 bytes a point (16-bit RGBA) before
    // deflate; anything larger is not this mask.
    let limit = (n as u64).saturating_mul(8).saturating_add(1 << 20);
    let png_bytes = read_entry(zip, &name, limit)?;
    let rgba = decode_mask_png(&png_bytes, width, height).with_context(|| name.clone())?;
    // Regions: the background, then each annotated colour in main.xml's order (x3ptools
    // repeats a colour with an empty annotation: the first non-empty text names it).
    let mut regions = vec![MaskRegion {
        colour: colour_hex(background),
        annotation: None,
        background: true,
        points: 0,
    }];
    let mut index: std::collections::HashMap<[u8; 3], u16> = Default::default();
    index.insert(background, 0);
    let annotations = mask
        .and_then(|m| child(m, "Annotations"))
        .into_iter()
        .flat_map(|a| a.children())
        .filter(|c| c.is_element() && c.tag_name().name() == "Annotation");
    for a in annotations {
        let Some(colour) = a.attribute("color").map(str::trim) else {
            continue;
        };
        // x3ptools writes R colours as #rrggbbaa; the alpha does not name another region.
        let rgb = parse_colour(colour).or_else(|| {
            (colour.len() == 9)
                .then(|| colour.get(..7).and_then(parse_colour))
                .flatten()
        });
        let Some(rgb) = rgb else {
            warnings.push(format!(
                "main.xml: Record3/Mask/Annotations: colour '{colour}' is not #rrggbb; that \
                 annotation is ignored"
            ));
            continue;
        };
        let text = a.text().map(str::trim).filter(|t| !t.is_empty());
        let i = *index.entry(rgb).or_insert_with(|| {
            regions.push(MaskRegion {
                colour: colour_hex(rgb),
                annotation: None,
                background: false,
                points: 0,
            });
            (regions.len() - 1) as u16
        });
        let r = &mut regions[i as usize];
        if r.annotation.is_none() {
            r.annotation = text.map(str::to_string);
        }
    }
    let mut labels = Vec::with_capacity(n);
    let mut unannotated: Vec<[u8; 3]> = Vec::new();
    for px in rgba.chunks_exact(4) {
        let rgb = if px[3] == 0 {
            background
        } else {
            [px[0], px[1], px[2]]
        };
        let i = match index.get(&rgb) {
            Some(&i) => i,
            None => {
                if regions.len() >= MAX_MASK_COLOURS {
                    warnings.push(format!(
                        "{name} holds more than {MAX_MASK_COLOURS} colours: it is not a \
                         label mask and is ignored (every point is read as measured)"
                    ));
                    return Ok(None);
                }
                regions.push(MaskRegion {
                    colour: colour_hex(rgb),
                    annotation: None,
                    background: false,
                    points: 0,
                });
                unannotated.push(rgb);
                let i = (regions.len() - 1) as u16;
                index.insert(rgb, i);
                i
            }
        };
        regions[i as usize].points += 1;
        labels.push(i);
    }
    // Painted colours without an annotation go last, ordered by colour (stable output
    // whatever the pixel order).
    let first_unannotated = regions.len() - unannotated.len();
    if unannotated.len() > 1 {
        let mut order: Vec<usize> = (first_unannotated..regions.len()).collect();
        order.sort_by(|&p, &q| regions[p].colour.cmp(&regions[q].colour));
        let mut remap: Vec<u16> = (0..regions.len() as u16).collect();
        for (k, &old) in order.iter().enumerate() {
            remap[old] = (first_unannotated + k) as u16;
        }
        let tail: Vec<MaskRegion> = order.iter().map(|&i| regions[i].clone()).collect();
        regions.truncate(first_unannotated);
        regions.extend(tail);
        for l in labels.iter_mut() {
            *l = remap[*l as usize];
        }
    }
    Ok(Some(ColourMask {
        image: name,
        regions,
        labels,
    }))
}

/// The mask image as 8-bit RGBA, after checking its size against the point grid (from the PNG
/// header, before the pixels are decoded).
fn decode_mask_png(bytes: &[u8], width: usize, height: usize) -> Result<Vec<u8>> {
    // The decoder's own buffers are bounded by the point grid, not by its 64 MiB default.
    let limits = png::Limits {
        bytes: (width * height).saturating_mul(8).max(64 << 20),
    };
    let mut decoder = png::Decoder::new_with_limits(Cursor::new(bytes), limits);
    decoder.set_transformations(png::Transformations::normalize_to_color8());
    let mut reader = decoder
        .read_info()
        .map_err(|e| anyhow!("not a readable PNG: {e}"))?;
    let info = reader.info();
    if (info.width as usize, info.height as usize) != (width, height) {
        bail!(
            "the mask image is {} x {} pixels (width x height), the point grid SizeX x SizeY is \
             {width} x {height}",
            info.width,
            info.height
        );
    }
    let mut buf = vec![0u8; reader.output_buffer_size()];
    let frame = reader
        .next_frame(&mut buf)
        .map_err(|e| anyhow!("cannot decode the PNG: {e}"))?;
    buf.truncate(frame.buffer_size());
    let channels = match frame.color_type {
        png::ColorType::Grayscale => 1,
        png::ColorType::GrayscaleAlpha => 2,
        png::ColorType::Rgb => 3,
        png::ColorType::Rgba => 4,
        png::ColorType::Indexed => bail!("palette PNG left unexpanded"),
    };
    if frame.bit_depth != png::BitDepth::Eight || buf.len() != width * height * channels {
        bail!(
            "decoded to {} bytes at {:?} bits, expected {width} x {height} x {channels} bytes",
            buf.len(),
            frame.bit_depth
        );
    }
    Ok(buf
        .chunks_exact(channels)
        .flat_map(|p| match channels {
            1 => [p[0], p[0], p[0], 255],
            2 => [p[0], p[0], p[0], p[1]],
            3 => [p[0], p[1], p[2], 255],
            _ => [p[0], p[1], p[2], p[3]],
        })
        .collect())
}

/// Inline point data (Record3/DataList, one `Datum` per point, x fastest): each holds the z
/// value (or "x;y;z" with empty incremental coordinates); an empty Datum is a point not measured.
fn parse_data_list(
    list: roxmltree::Node,
    n: usize,
    to_um: &impl Fn(f64) -> f64,
) -> Result<Vec<f64>> {
    let datums = list
        .children()
        .filter(|c| c.is_element() && c.tag_name().name() == "Datum");
    // Count before allocating: the size claim must match what the file holds.
    let found = datums.clone().count();
    if found != n {
        bail!("main.xml: DataList holds {found} Datum elements, MatrixDimension declares {n}");
    }
    let mut heights = Vec::with_capacity(n);
    for (i, d) in datums.enumerate() {
        let text = d.text().unwrap_or("").trim();
        let z = text.rsplit(';').next().unwrap_or("").trim();
        if z.is_empty() {
            heights.push(f64::NAN);
            continue;
        }
        let v: f64 = z
            .parse()
            .map_err(|_| anyhow!("main.xml: DataList/Datum[{i}] is '{text}', expected a number"))?;
        heights.push(to_um(v));
    }
    Ok(heights)
}

/// The surface with the metadata of Record1/Record2.
#[allow(clippy::too_many_arguments)]
fn finish(
    root: roxmltree::Node,
    r1: roxmltree::Node,
    (width, height): (usize, usize),
    (pitch_x_m, pitch_y_m): (f64, f64),
    stage_position_um: Option<[f64; 2]>,
    heights_um: Vec<f64>,
    warnings: Vec<String>,
    mask: Option<ColourMask>,
) -> Surface {
    let r2 = child(root, "Record2");
    let instrument = r2.and_then(|r| {
        // "not available" is what writers (Digital Surf's, ours) put in a required element
        // they have nothing for: not a part of the instrument's name.
        let parts: Vec<String> = ["Manufacturer", "Model", "Version"]
            .iter()
            .filter_map(|p| text_of(r, &["Instrument", p]))
            .filter(|t| t != NOT_AVAILABLE)
            .collect();
        (!parts.is_empty()).then(|| parts.join(" "))
    });
    let mut metadata = Metadata {
        format: "x3p".into(),
        pitch_known: true,
        instrument,
        serial: r2
            .and_then(|r| text_of(r, &["Instrument", "Serial"]))
            .filter(|t| t != NOT_AVAILABLE),
        date: r2.and_then(|r| text_of(r, &["Date"])),
        ..Metadata::default()
    };
    if let Some(r) = r2 {
        // The Instrument's elements one by one too, so an X3P written back keeps them apart
        // (`instrument` joins them).
        for (key, path) in [
            ("creator", &["Creator"][..]),
            ("comment", &["Comment"][..]),
            ("calibration_date", &["CalibrationDate"][..]),
            (INSTRUMENT_KEYS[0], &["Instrument", "Manufacturer"][..]),
            (INSTRUMENT_KEYS[1], &["Instrument", "Model"][..]),
            (INSTRUMENT_KEYS[2], &["Instrument", "Version"][..]),
            ("probing_system", &["ProbingSystem", "Type"][..]),
            (
                "probing_identification",
                &["ProbingSystem", "Identification"][..],
            ),
        ] {
            if let Some(t) = text_of(r, path).filter(|t| t != NOT_AVAILABLE) {
                metadata.extra.insert(key.into(), t);
            }
        }
        // Our own stand-ins for an unknown date (said in our Comment) are not dates.
        let comment = metadata
            .extra
            .get("comment")
            .filter(|c| c.starts_with("written by surfstream"))
            .cloned()
            .unwrap_or_default();
        if comment.contains("CalibrationDate not known") {
            metadata.extra.remove("calibration_date");
        }
        if comment.contains("measurement date not known") {
            metadata.date = None;
        }
    }
    if let Some(rev) = text_of(r1, &["Revision"]) {
        metadata.extra.insert("revision".into(), rev);
    }
    metadata.warnings = warnings;
    metadata.stage_position_um = stage_position_um;
    metadata.mask = mask;
    Surface {
        width,
        height,
        pitch_x_um: pitch_x_m * 1e6,
        pitch_y_um: pitch_y_m * 1e6,
        heights_um,
        metadata,
    }
}

/// Adds `name` to the archive deflated when that saves at least 10 %, else stored (every zip
/// reader accepts both). Measured f64 heights barely deflate (a 1024^2 map by ~5 % at best,
/// and level 1 can even grow it), while inflating costs a reader ~30 ms; NaN borders and flat
/// regions compress well. The entry is deflated once, into a scratch archive, and copied raw.
fn put_entry<W: Write + Seek>(zw: &mut zip::ZipWriter<W>, name: &str, bytes: &[u8]) -> Result<()> {
    let deflated = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated)
        .compression_level(Some(1));
    let ctx = || format!("zip entry {name}");
    let mut scratch = zip::ZipWriter::new(Cursor::new(Vec::new()));
    scratch.start_file(name, deflated).with_context(ctx)?;
    scratch.write_all(bytes).with_context(ctx)?;
    let scratch = scratch.finish().with_context(ctx)?.into_inner();
    let mut scratch = zip::ZipArchive::new(Cursor::new(scratch)).with_context(ctx)?;
    let entry = scratch.by_index_raw(0).with_context(ctx)?;
    if (entry.compressed_size() as f64) < 0.9 * bytes.len() as f64 {
        zw.raw_copy_file(entry).with_context(ctx)?;
    } else {
        drop(entry);
        let stored = zip::write::SimpleFileOptions::default()
            .compression_method(zip::CompressionMethod::Stored);
        zw.start_file(name, stored).with_context(ctx)?;
        zw.write_all(bytes).with_context(ctx)?;
    }
    Ok(())
}

/// The X3P byte image of `s`: float64 heights in metres, NaN points marked invalid in
/// `bindata/valid.bin` (and left NaN in data.bin), ISO5436 - 2000 revision (what every reader
/// accepts); a colour mask read from an X3P is written back (`Record3/Mask`,
/// `bindata/mask.png`), so `convert` keeps the labels.
pub fn encode(s: &Surface) -> Result<Vec<u8>> {
    Ok(encode_noting(s)?.0)
}

/// [`encode`], and what the user should be told about the file (a source date that could not
/// be read: [`super::date`]).
pub fn encode_noting(s: &Surface) -> Result<(Vec<u8>, Vec<String>)> {
    let n = checked_size(&[s.width, s.height], "width * height")?;
    if s.heights_um.len() != n || n == 0 {
        bail!(
            "surface has {} heights, expected {} x {} > 0",
            s.heights_um.len(),
            s.width,
            s.height
        );
    }
    let data: Vec<u8> = s
        .heights_um
        .iter()
        .flat_map(|z| (z * 1e-6).to_le_bytes())
        .collect();
    let any_invalid = s.heights_um.iter().any(|z| z.is_nan());
    let mut valid = vec![0u8; n.div_ceil(8)];
    for (i, z) in s.heights_um.iter().enumerate() {
        if !z.is_nan() {
            valid[i / 8] |= 1 << (i % 8);
        }
    }
    let (xml, warnings) = main_xml(
        s,
        &md5_hex(&data),
        any_invalid.then(|| md5_hex(&valid)).as_deref(),
    );
    let mut zw = zip::ZipWriter::new(Cursor::new(Vec::new()));
    let mut put = |name: &str, bytes: &[u8]| put_entry(&mut zw, name, bytes);
    put("main.xml", xml.as_bytes())?;
    put(
        "md5checksum.hex",
        format!("{} *main.xml\n", md5_hex(xml.as_bytes())).as_bytes(),
    )?;
    put("bindata/data.bin", &data)?;
    if any_invalid {
        put("bindata/valid.bin", &valid)?;
    }
    if let Some(png) = mask_png(s)? {
        put(MASK_IMAGE, &png)?;
    }
    Ok((
        zw.finish().context("finishing the zip")?.into_inner(),
        warnings,
    ))
}

/// main.xml of `s` (its size, pitch and metadata; the heights are not read) with the MD5
/// checksums of data.bin and, when some point is invalid, valid.bin. Also returns what the
/// user should be told (a source date not read, or read with an assumption).
fn main_xml(s: &Surface, data_md5: &str, valid_md5: Option<&str>) -> (String, Vec<String>) {
    let valid_link = match valid_md5 {
        Some(md5) => format!(
            "\n      <ValidPointsLink>bindata/valid.bin</ValidPointsLink>\n      <MD5ChecksumValidPoints>{md5}</MD5ChecksumValidPoints>"
        ),
        None => String::new(),
    };
    let mask = mask_xml(s);
    let m = &s.metadata;
    let mut warnings = Vec::new();
    // Record2 holds what the source file said: Date is ISO 8601, the measurement's when it can
    // be read as a date (issue 35: the instruments' forms, `super::date`); otherwise 1970-01-01
    // standing for unknown, said in Comment (and, when the source had a date that could not be
    // read, in a warning). Not the time of writing: Date is when the surface was measured, and
    // the same surface must give the same file (a run's panorama.x3p, byte for byte).
    const UNKNOWN_DATE: &str = "1970-01-01T00:00:00Z";
    let (date, date_note) = match m.date.as_deref().map(|d| (d, super::date::read_date(d))) {
        Some((_, Some(d))) => match d.assumed {
            Some(a) => {
                let note = format!("Date {a}");
                warnings.push(note.clone());
                (d.iso, format!("; {note}"))
            }
            None => (d.iso, String::new()),
        },
        Some((text, None)) => {
            let note = format!(
                "the source's date {:?} is not a date form read here (ISO 8601 / RFC 3339, asctime, \
                 '10 Mar 2023', dd.mm.yyyy, dd/mm/yyyy, yyyy/mm/dd): measurement date not known (1970-01-01 stands for unknown)",
                text.trim().trim_end_matches('\0')
            );
            warnings.push(note.clone());
            (UNKNOWN_DATE.to_string(), format!("; {note}"))
        }
        None => (
            UNKNOWN_DATE.to_string(),
            "; the source stores no date: measurement date not known (1970-01-01 stands for unknown)"
                .to_string(),
        ),
    };
    // CalibrationDate is required by the schema too, and the time of writing would be a false
    // claim about a calibration: 1970-01-01 stands for unknown, said in Comment.
    const UNKNOWN_CALIBRATION: &str = "1970-01-01T00:00:00Z";
    let (calibration, calibration_note) = match m
        .extra
        .get("calibration_date")
        .and_then(|d| iso8601_date(d))
    {
        Some(d) => (d, String::new()),
        None => (
            UNKNOWN_CALIBRATION.to_string(),
            "; CalibrationDate not known (1970-01-01 stands for unknown)".to_string(),
        ),
    };
    // Every Record2 element the schema requires holds text: an empty <Model/> breaks readers
    // (SurfaceTopography 1.27 fails on it); "not available" as Digital Surf's writer says it.
    // An X3P source's Manufacturer, Model and Version are kept apart; any other source's
    // instrument name (one string) is the Manufacturer.
    let [manufacturer, model, version] = instrument_elements(m);
    let text = |v: Option<&String>| esc(v.map_or(NOT_AVAILABLE, |v| v.as_str()));
    let serial = esc(m.serial.as_deref().unwrap_or(NOT_AVAILABLE));
    let (manufacturer, model, version) = (
        text(manufacturer.as_ref()),
        text(model.as_ref()),
        text(version.as_ref()),
    );
    // The schema's three types; an optical profiler's is NonContacting.
    let probing_type = m
        .extra
        .get("probing_system")
        .map(String::as_str)
        .filter(|t| matches!(*t, "Contacting" | "NonContacting" | "Software"))
        .unwrap_or("NonContacting");
    let probing_id = text(m.extra.get("probing_identification"));
    let creator = esc(&match m.extra.get("creator") {
        Some(c) if !c.trim().is_empty() => c.trim().to_string(),
        _ => format!("surfstream {}", env!("CARGO_PKG_VERSION")),
    });
    let source = if m.format.is_empty() || m.format == "x3p" {
        String::new()
    } else {
        format!(" from a .{} file", m.format)
    };
    let comment = esc(&format!(
        "written by surfstream {}{source}{date_note}{calibration_note}",
        env!("CARGO_PKG_VERSION")
    ));
    let [ox, oy] = m.stage_position_um.unwrap_or([0.0, 0.0]);
    let xml = format!(
        r#"<?xml version="1.0" encoding="UTF-8" standalone="no" ?>
<p:ISO5436_2 xmlns:p="{NAMESPACE}" xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance" xsi:schemaLocation="{NAMESPACE} {NAMESPACE}/ISO5436_2.xsd">
  <Record1>
    <Revision>ISO5436 - 2000</Revision>
    <FeatureType>SUR</FeatureType>
    <Axes>
      <CX>
        <AxisType>I</AxisType>
        <DataType>D</DataType>
        <Increment>{px:e}</Increment>
        <Offset>{ox:e}</Offset>
      </CX>
      <CY>
        <AxisType>I</AxisType>
        <DataType>D</DataType>
        <Increment>{py:e}</Increment>
        <Offset>{oy:e}</Offset>
      </CY>
      <CZ>
        <AxisType>A</AxisType>
        <DataType>D</DataType>
        <Increment>1</Increment>
        <Offset>0</Offset>
      </CZ>
    </Axes>
  </Record1>
  <Record2>
    <Date>{date}</Date>
    <Creator>{creator}</Creator>
    <Instrument>
      <Manufacturer>{manufacturer}</Manufacturer>
      <Model>{model}</Model>
      <Serial>{serial}</Serial>
      <Version>{version}</Version>
    </Instrument>
    <CalibrationDate>{calibration}</CalibrationDate>
    <ProbingSystem>
      <Type>{probing_type}</Type>
      <Identification>{probing_id}</Identification>
    </ProbingSystem>
    <Comment>{comment}</Comment>
  </Record2>
  <Record3>
    <MatrixDimension>
      <SizeX>{w}</SizeX>
      <SizeY>{h}</SizeY>
      <SizeZ>1</SizeZ>
    </MatrixDimension>
    <DataLink>
      <PointDataLink>bindata/data.bin</PointDataLink>
      <MD5ChecksumPointData>{md5}</MD5ChecksumPointData>{valid_link}
    </DataLink>{mask}
  </Record3>
  <Record4>
    <ChecksumFile>md5checksum.hex</ChecksumFile>
  </Record4>
</p:ISO5436_2>
"#,
        px = s.pitch_x_um * 1e-6,
        py = s.pitch_y_um * 1e-6,
        ox = ox * 1e-6,
        oy = oy * 1e-6,
        date = esc(&date),
        calibration = esc(&calibration),
        w = s.width,
        h = s.height,
        md5 = data_md5,
    );
    (xml, warnings)
}

/// Keys under which the X3P reader keeps `Record2/Instrument`'s Manufacturer, Model, Version.
const INSTRUMENT_KEYS: [&str; 3] = [
    "instrument_manufacturer",
    "instrument_model",
    "instrument_version",
];

/// Manufacturer, Model, Version for Record2: the X3P reader's separate elements while they
/// still make up `instrument` (the name was not changed since), else `instrument` as the
/// Manufacturer.
fn instrument_elements(m: &Metadata) -> [Option<String>; 3] {
    let parts = INSTRUMENT_KEYS.map(|k| m.extra.get(k).cloned());
    let joined: Vec<&str> = parts.iter().flatten().map(String::as_str).collect();
    match &m.instrument {
        Some(name) if !joined.is_empty() && *name == joined.join(" ") => parts,
        Some(name) => [Some(name.clone()), None, None],
        None => [None, None, None],
    }
}

/// What the writer puts in a required Record2 element it has nothing for.
const NOT_AVAILABLE: &str = "not available";

pub use super::date::iso8601_date;

/// Where the writer puts a colour mask's image (x3ptools' and FiX3P's default name).
const MASK_IMAGE: &str = "bindata/mask.png";

/// `Record3/Mask` of `s`'s colour mask (the background, one `Annotation` per annotated
/// colour), as x3ptools writes it; empty without a mask.
fn mask_xml(s: &Surface) -> String {
    let Some(mask) = &s.metadata.mask else {
        return String::new();
    };
    let background = mask
        .regions
        .iter()
        .find(|r| r.background)
        .map_or("#cd7f32", |r| r.colour.as_str());
    let annotations: String = mask
        .regions
        .iter()
        .filter_map(|r| {
            r.annotation.as_ref().map(|a| {
                format!(
                    "\n        <Annotation color=\"{}\">{}</Annotation>",
                    r.colour,
                    esc(a)
                )
            })
        })
        .collect();
    format!(
        "\n    <Mask>\n      <Background>{background}</Background>\n      <Annotations>{annotations}\n      </Annotations>\n    </Mask>"
    )
}

/// The colour mask of `s` as an 8-bit RGB PNG (one pixel per point), if it has one.
fn mask_png(s: &Surface) -> Result<Option<Vec<u8>>> {
    let Some(mask) = &s.metadata.mask else {
        return Ok(None);
    };
    if mask.labels.len() != s.width * s.height {
        bail!(
            "the colour mask labels {} points, the surface has {} x {}",
            mask.labels.len(),
            s.width,
            s.height
        );
    }
    let colours: Vec<[u8; 3]> = mask
        .regions
        .iter()
        .map(|r| {
            parse_colour(&r.colour)
                .with_context(|| format!("mask region colour '{}' is not #rrggbb", r.colour))
        })
        .collect::<Result<_>>()?;
    let mut rgb = Vec::with_capacity(mask.labels.len() * 3);
    for &l in &mask.labels {
        let c = colours
            .get(l as usize)
            .with_context(|| format!("mask label {l} names no region"))?;
        rgb.extend_from_slice(c);
    }
    let (w, h) = (
        u32::try_from(s.width).context("mask width")?,
        u32::try_from(s.height).context("mask height")?,
    );
    let mut out = Vec::new();
    let mut enc = png::Encoder::new(&mut out, w, h);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    let mut writer = enc.write_header().context("mask PNG header")?;
    writer.write_image_data(&rgb).context("mask PNG data")?;
    writer.finish().context("mask PNG")?;
    Ok(Some(out))
}

/// Writes `s` as an X3P file, atomically.
/// What the user should be told about it (see [`encode_noting`]) goes to stderr,
/// "PATH: warning: ...", as the verbs print a reader's warnings.
pub fn write(path: &Path, s: &Surface) -> Result<()> {
    let (bytes, warnings) = encode_noting(s).with_context(|| format!("{}", path.display()))?;
    surfstream_core::fsutil::write_atomic(path, |w| {
        w.write_all(&bytes)
            .with_context(|| format!("{}: write failed", path.display()))
    })?;
    tell(path, &warnings);
    Ok(())
}

fn tell(path: &Path, warnings: &[String]) {
    for w in warnings {
        eprintln!("{}: warning: {w}", path.display());
    }
}

/// Writes an X3P of `s`'s size, pitch and metadata (`s.heights_um` is ignored and may be
/// empty) whose heights come from `rows(row0, n, out)`, a band of whole rows at a time, so the
/// map is never held whole: two passes over the rows (main.xml precedes the data in the zip
/// and carries data.bin's MD5), then data.bin straight into the file, deflated (level 1)
/// or stored as [`write`] decides, atomically. The valid-point mask (one bit per point) is
/// the one thing held. The content equals [`write`]'s (same main.xml, data.bin, valid.bin).
pub fn write_by_rows(
    path: &Path,
    s: &Surface,
    mut rows: impl FnMut(usize, usize, &mut Vec<f64>) -> Result<()>,
) -> Result<()> {
    use md5::Digest as _;
    let ctx = || format!("{}", path.display());
    let n = checked_size(&[s.width, s.height], "width * height").with_context(ctx)?;
    if n == 0 {
        bail!(
            "{}: surface is {} x {}, expected > 0",
            path.display(),
            s.width,
            s.height
        );
    }
    // Rows per band: about 8 MB of f64.
    let band = (1 << 20) / s.width.max(1) + 1;
    let mut buf = Vec::new();
    let mut bytes = Vec::new();
    let mut valid = vec![0u8; n.div_ceil(8)];
    let mut any_invalid = false;
    let mut data_md5 = Md5::new();
    // data.bin is stored when deflating saves less than 10 %, as `put_entry` decides: the
    // deflated size is measured in the first pass (the zip crate deflates with this flate2).
    let mut deflated_size =
        flate2::write::DeflateEncoder::new(ByteCount(0), flate2::Compression::new(1));
    let mut row0 = 0;
    while row0 < s.height {
        let k = band.min(s.height - row0);
        rows(row0, k, &mut buf).with_context(ctx)?;
        if buf.len() != k * s.width {
            bail!(
                "{}: rows {row0}..{} gave {} heights, expected {}",
                path.display(),
                row0 + k,
                buf.len(),
                k * s.width
            );
        }
        bytes.clear();
        bytes.extend(buf.iter().flat_map(|z| (z * 1e-6).to_le_bytes()));
        data_md5.update(&bytes);
        deflated_size.write_all(&bytes).with_context(ctx)?;
        for (j, z) in buf.iter().enumerate() {
            let i = row0 * s.width + j;
            if z.is_nan() {
                any_invalid = true;
            } else {
                valid[i / 8] |= 1 << (i % 8);
            }
        }
        row0 += k;
    }
    let deflate = (deflated_size.finish().with_context(ctx)?.0 as f64) < 0.9 * (n * 8) as f64;
    let (xml, warnings) = main_xml(
        s,
        &hex(&data_md5.finalize()),
        any_invalid.then(|| md5_hex(&valid)).as_deref(),
    );
    surfstream_core::fsutil::write_atomic(path, |w| {
        let mut zw = zip::ZipWriter::new(w);
        put_entry(&mut zw, "main.xml", xml.as_bytes()).with_context(ctx)?;
        put_entry(
            &mut zw,
            "md5checksum.hex",
            format!("{} *main.xml\n", md5_hex(xml.as_bytes())).as_bytes(),
        )
        .with_context(ctx)?;
        let options = if deflate {
            zip::write::SimpleFileOptions::default()
                .compression_method(zip::CompressionMethod::Deflated)
                .compression_level(Some(1))
        } else {
            zip::write::SimpleFileOptions::default()
                .compression_method(zip::CompressionMethod::Stored)
        };
        let options = options.large_file(n as u64 * 8 >= u32::MAX as u64);
        zw.start_file("bindata/data.bin", options)
            .with_context(|| format!("{}: zip entry bindata/data.bin", path.display()))?;
        let mut row0 = 0;
        while row0 < s.height {
            let k = band.min(s.height - row0);
            rows(row0, k, &mut buf).with_context(ctx)?;
            bytes.clear();
            bytes.extend(buf.iter().flat_map(|z| (z * 1e-6).to_le_bytes()));
            zw.write_all(&bytes)
                .with_context(|| format!("{}: write failed", path.display()))?;
            row0 += k;
        }
        if any_invalid {
            put_entry(&mut zw, "bindata/valid.bin", &valid).with_context(ctx)?;
        }
        if let Some(png) = mask_png(s).with_context(ctx)? {
            put_entry(&mut zw, MASK_IMAGE, &png).with_context(ctx)?;
        }
        zw.finish()
            .with_context(|| format!("{}: finishing the zip", path.display()))?;
        Ok(())
    })?;
    tell(path, &warnings);
    Ok(())
}

/// A writer that only counts the bytes.
struct ByteCount(u64);

impl Write for ByteCount {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.0 += buf.len() as u64;
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

#[cfg(test)]
mod by_rows_tests {
    use super::*;

    fn entry(bytes: &[u8], name: &str) -> Vec<u8> {
        let mut zip = zip::ZipArchive::new(Cursor::new(bytes)).unwrap();
        let mut out = Vec::new();
        zip.by_name(name).unwrap().read_to_end(&mut out).unwrap();
        out
    }

    #[test]
    fn written_by_rows_has_the_content_of_the_whole_write() {
        let dir = std::env::temp_dir().join(format!("x3p-rows-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        // 300 columns: a band is 3496 rows, so 7000 rows take three bands.
        let (w, h) = (300, 7000);
        let heights: Vec<f64> = (0..w * h)
            .map(|i| {
                if i % 977 == 5 {
                    f64::NAN
                } else {
                    ((i * 31 % 113) as f64).sin() * 2.5
                }
            })
            .collect();
        let s = Surface {
            width: w,
            height: h,
            pitch_x_um: 0.8148,
            pitch_y_um: 0.9,
            heights_um: heights.clone(),
            metadata: Metadata {
                format: "npy".into(),
                pitch_known: true,
                date: Some("2023-03-10 16:35:59".into()),
                ..Metadata::default()
            },
        };
        let whole = dir.join("whole.x3p");
        let rows = dir.join("rows.x3p");
        write(&whole, &s).unwrap();
        let shell = Surface {
            heights_um: Vec::new(),
            ..s.clone()
        };
        let mut reads = 0;
        write_by_rows(&rows, &shell, |r0, n, out| {
            reads += 1;
            out.clear();
            out.extend_from_slice(&heights[r0 * w..(r0 + n) * w]);
            Ok(())
        })
        .unwrap();
        assert_eq!(reads, 6, "two passes of three bands");
        let (a, b) = (
            std::fs::read(&whole).unwrap(),
            std::fs::read(&rows).unwrap(),
        );
        for name in [
            "main.xml",
            "md5checksum.hex",
            "bindata/data.bin",
            "bindata/valid.bin",
        ] {
            assert!(entry(&a, name) == entry(&b, name), "{name} differs");
        }
        // This map deflates well: data.bin is deflated in both (the streams may differ).
        let method = |bytes: &[u8]| {
            let mut zip = zip::ZipArchive::new(Cursor::new(bytes.to_vec())).unwrap();
            let m = zip.by_name("bindata/data.bin").unwrap().compression();
            m
        };
        assert_eq!(method(&b), zip::CompressionMethod::Deflated);
        assert_eq!(method(&a), method(&b));
        // Heights that do not deflate: data.bin stored, the file the same byte for byte.
        let noisy: Vec<f64> = (0..w * 50)
            .map(|i| (i as f64 * 0.7123).sin() * 2.5)
            .collect();
        let small = Surface {
            height: 50,
            heights_um: noisy.clone(),
            ..s.clone()
        };
        write(&whole, &small).unwrap();
        write_by_rows(
            &rows,
            &Surface {
                heights_um: Vec::new(),
                ..small.clone()
            },
            |r0, n, out| {
                out.clear();
                out.extend_from_slice(&noisy[r0 * w..(r0 + n) * w]);
                Ok(())
            },
        )
        .unwrap();
        let (a2, b2) = (
            std::fs::read(&whole).unwrap(),
            std::fs::read(&rows).unwrap(),
        );
        assert_eq!(method(&b2), zip::CompressionMethod::Stored);
        assert!(a2 == b2, "zip bytes differ");
        // The reader checks both MD5s and gives the heights back.
        let back = parse(&b).unwrap();
        assert_eq!((back.width, back.height), (w, h));
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&back.heights_um), bits(&parse(&a).unwrap().heights_um));
        assert_eq!(
            back.heights_um.iter().filter(|v| v.is_nan()).count(),
            7000 * 300 / 977 + 1
        );
        // A source that fails names the file and leaves nothing behind.
        let bad = dir.join("bad.x3p");
        let e = write_by_rows(&bad, &shell, |_, _, _| Err(anyhow!("disk gone"))).unwrap_err();
        assert!(format!("{e:#}").contains("bad.x3p"), "{e:#}");
        assert!(!bad.exists());
        std::fs::remove_dir_all(&dir).ok();
    }
}
