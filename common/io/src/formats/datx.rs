//! Zygo `.datx` (Mx): HDF5, read in pure Rust with `hdf5-reader`.
//!
//! The height dataset is found through the `/MetaData` link table (Source, Link, Destination):
//! Root -Measurement-> {M} -Surface-> {S} -Path-> the dataset path; never "the first dataset
//! under /Data/Surface", which is wrong on files holding several surfaces. Strings may be
//! fixed-length or variable-length. Heights: `Unit` a length unit -> values in that unit;
//! `Unit` = Fringes -> height_m = value * S * O * lambda with `Z Converter.Parameters` =
//! [?, lambda_m, S, O]. Pitch = `X Converter.Parameters[1]` metres (Y likewise). Invalid:
//! a value at or above `No Data`, or NaN. Rows keep the stored order (first stored row = row
//! 0).
//!
//! Metadata: wavelength = `Z Converter.Parameters[1]`; instrument, serial and date from the
//! measurement's attribute group ("Data Context.Data Attributes.System Type" / "System Serial
//! Number" / "Time Stamp"), where present.

use anyhow::{anyhow, bail, Context, Result};
use hdf5_reader::{
    messages::datatype::{StringSize, VarLenKind},
    ByteOrder, Dataset, Datatype, Hdf5File,
};
use rayon::prelude::*;

use super::bytes::{checked_size, length_unit_um};
use super::{Metadata, Surface};

fn h5<T>(r: hdf5_reader::error::Result<T>, what: &str) -> Result<T> {
    r.map_err(|e| anyhow!("{what}: {e}"))
}

/// Decodes one string member at `bytes` (fixed-length: NUL/space padded; variable-length: a
/// global-heap reference resolved through `ds`).
fn decode_string(ds: &Dataset, dtype: &Datatype, bytes: &[u8], what: &str) -> Result<String> {
    let raw = match dtype {
        Datatype::String {
            size: StringSize::Fixed(_),
            ..
        } => bytes.to_vec(),
        Datatype::String {
            size: StringSize::Variable,
            ..
        } => h5(ds.resolve_vlen_reference_bytes(bytes, 1), what)?,
        Datatype::VarLen {
            kind: VarLenKind::String,
            ..
        } => h5(ds.resolve_vlen_reference_bytes(bytes, 1), what)?,
        other => bail!("{what}: expected a string, found {other:?}"),
    };
    let end = raw.iter().position(|&b| b == 0).unwrap_or(raw.len());
    Ok(String::from_utf8_lossy(&raw[..end]).trim().to_string())
}

/// Element size in bytes of a compound member type, as stored in raw data.
fn stored_size(ds: &Dataset, dtype: &Datatype) -> Result<usize> {
    Ok(match dtype {
        Datatype::String {
            size: StringSize::Fixed(n),
            ..
        } => *n as usize,
        Datatype::String {
            size: StringSize::Variable,
            ..
        }
        | Datatype::VarLen { .. } => ds.vlen_reference_size(),
        Datatype::FloatingPoint { size, .. } | Datatype::FixedPoint { size, .. } => *size as usize,
        other => bail!("unsupported member type {other:?}"),
    })
}

/// A dataset cannot hold more than its file's bytes expanded by deflate's best ratio (1032:1):
/// a larger declared size is a lying header, refused before anything is allocated for it.
fn plausible_size(declared_bytes: usize, file_len: usize, what: &str) -> Result<()> {
    const DEFLATE_MAX_RATIO: usize = 1032;
    if declared_bytes > file_len.saturating_mul(DEFLATE_MAX_RATIO) {
        bail!(
            "{what}: declares {declared_bytes} bytes of data, more than a {file_len}-byte file can hold even deflated (x{DEFLATE_MAX_RATIO})"
        );
    }
    Ok(())
}

fn field_slice<'a>(raw: &'a [u8], offset: usize, len: usize, what: &str) -> Result<&'a [u8]> {
    raw.get(offset..offset.saturating_add(len))
        .with_context(|| {
            format!(
                "{what}: member at byte {offset} (+{len}) lies outside the {}-byte record",
                raw.len()
            )
        })
}

/// The `/MetaData` link table as (source, link, destination) triples.
fn link_table(file: &Hdf5File, file_len: usize) -> Result<Vec<(String, String, String)>> {
    let ds = h5(
        file.dataset("/MetaData"),
        "dataset /MetaData (the link table)",
    )?;
    let Datatype::Compound { size, fields } = ds.dtype().clone() else {
        bail!("/MetaData: expected a compound (Source, Link, Destination) dataset");
    };
    let field = |name: &str| {
        fields
            .iter()
            .find(|f| f.name == name)
            .with_context(|| format!("/MetaData: member '{name}' missing"))
    };
    let (src, link, dst) = (field("Source")?, field("Link")?, field("Destination")?);
    let shape: Vec<usize> = ds.shape().iter().map(|&d| d as usize).collect();
    let records = checked_size(&shape, "/MetaData shape")?;
    let declared = checked_size(&[records, size as usize], "/MetaData size")?;
    plausible_size(declared, file_len, "/MetaData")?;
    let raw = h5(ds.read_raw_bytes(), "/MetaData")?;
    let rec = size as usize;
    if rec == 0 {
        bail!("/MetaData: record size 0");
    }
    let mut out = Vec::new();
    for r in raw.chunks_exact(rec) {
        let get = |f: &hdf5_reader::messages::datatype::CompoundField| -> Result<String> {
            let len = stored_size(&ds, &f.datatype)?;
            let b = field_slice(r, f.byte_offset as usize, len, "/MetaData")?;
            decode_string(
                &ds,
                &f.datatype,
                b,
                &format!("/MetaData member '{}'", f.name),
            )
        };
        out.push((get(src)?, get(link)?, get(dst)?));
    }
    Ok(out)
}

fn follow(table: &[(String, String, String)], from: &str, link: &str) -> Result<String> {
    table
        .iter()
        .find(|(s, l, _)| s == from && l == link)
        .map(|(_, _, d)| d.clone())
        .with_context(|| format!("/MetaData: no link '{link}' from '{from}'"))
}

/// `Parameters` (vlen f64[]) and `Category` of a converter attribute.
fn converter(ds: &Dataset, name: &str) -> Result<(String, Vec<f64>)> {
    let attr = h5(ds.attribute(name), &format!("attribute '{name}'"))?;
    let Datatype::Compound { size, fields } = &attr.datatype else {
        bail!("attribute '{name}': expected a compound (Category, BaseUnit, Parameters)");
    };
    let rec = field_slice(
        &attr.raw_data,
        0,
        *size as usize,
        &format!("attribute '{name}'"),
    )?;
    let params = fields
        .iter()
        .find(|f| f.name == "Parameters")
        .with_context(|| format!("attribute '{name}': member 'Parameters' missing"))?;
    let Datatype::VarLen { base, .. } = &params.datatype else {
        bail!("attribute '{name}': 'Parameters' is not a variable-length array");
    };
    let Datatype::FloatingPoint {
        size: 8,
        byte_order,
    } = base.as_ref()
    else {
        bail!("attribute '{name}': 'Parameters' elements are not float64");
    };
    let reference = field_slice(
        rec,
        params.byte_offset as usize,
        ds.vlen_reference_size(),
        name,
    )?;
    let bytes = h5(
        ds.resolve_vlen_reference_bytes(reference, 8),
        &format!("attribute '{name}' Parameters"),
    )?;
    let values = bytes
        .chunks_exact(8)
        .map(|c| {
            let mut a = [0u8; 8];
            a.copy_from_slice(c);
            match byte_order {
                ByteOrder::BigEndian => f64::from_be_bytes(a),
                _ => f64::from_le_bytes(a),
            }
        })
        .collect();
    let category = match fields.iter().find(|f| f.name == "Category") {
        Some(f) => {
            let len = stored_size(ds, &f.datatype)?;
            decode_string(
                ds,
                &f.datatype,
                field_slice(rec, f.byte_offset as usize, len, name)?,
                name,
            )?
        }
        None => String::new(),
    };
    Ok((category, values))
}

/// A string attribute (fixed or variable length, scalar or 1-element array).
fn string_attr(ds: &Dataset, name: &str) -> Result<String> {
    let attr = h5(ds.attribute(name), &format!("attribute '{name}'"))?;
    if let Some(s) = attr.decoded_strings.as_ref().and_then(|v| v.first()) {
        return Ok(s.trim_end_matches('\0').trim().to_string());
    }
    let len = stored_size(ds, &attr.datatype)?;
    let b = field_slice(&attr.raw_data, 0, len, &format!("attribute '{name}'"))?;
    decode_string(ds, &attr.datatype, b, &format!("attribute '{name}'"))
}

fn pitch_m(ds: &Dataset, name: &str) -> Result<Option<f64>> {
    match converter(ds, name) {
        Ok((_, p)) => {
            let v = *p.get(1).with_context(|| {
                format!(
                    "attribute '{name}': Parameters has {} values, expected >= 2",
                    p.len()
                )
            })?;
            Ok((v.is_finite() && v > 0.0).then_some(v))
        }
        Err(_) if h5(ds.attribute(name), name).is_err() => Ok(None),
        Err(e) => Err(e),
    }
}

/// Prefix of Mx's measurement attributes ("Data Context.Data Attributes.System Type", ...).
const ATTRIBUTE_PREFIX: &str = "Data Context.Data Attributes.";

/// A text attribute's value (fixed or variable-length string, scalar or 1-element array),
/// NULs and spaces trimmed; None for other types or an empty text.
fn attr_text(a: &hdf5_reader::Attribute) -> Option<String> {
    let s = match a.decoded_strings.as_ref().and_then(|v| v.first()) {
        Some(s) => s.clone(),
        None => a.read_string().ok()?,
    };
    let s = s.trim_end_matches('\0').trim();
    (!s.is_empty()).then(|| s.to_string())
}

/// Instrument, serial number and date from the measurement's attribute group, where Mx keeps
/// them as "Data Context.Data Attributes.System Type" / "System Serial Number" / "Time Stamp"
/// (plus acquisition details, kept in `extra`). The group is the one the link table names
/// (measurement -Attributes-> node -Path-> group), else `/Measurement/Attributes` (older
/// files), else the first group under `/Attributes` that has them. Metadata only: a file
/// without the group, or with unreadable attributes, reads with these fields absent.
fn instrument_attributes(
    file: &Hdf5File,
    table: &[(String, String, String)],
    measurement: &str,
    metadata: &mut Metadata,
) {
    let mut groups = Vec::new();
    if let Ok(node) = follow(table, measurement, "Attributes") {
        match follow(table, &node, "Path") {
            Ok(path) => groups.push(path),
            Err(_) if node.starts_with('/') => groups.push(node),
            Err(_) => {}
        }
    }
    groups.push("/Measurement/Attributes".to_string());
    if let Ok((names, _)) = file.group("/Attributes").and_then(|g| g.member_names()) {
        groups.extend(names.into_iter().map(|n| format!("/Attributes/{n}")));
    }
    for path in groups {
        let Ok(attrs) = file.group(&path).and_then(|g| g.attributes()) else {
            continue;
        };
        let mut found = false;
        for a in &attrs {
            let Some(key) = a.name.strip_prefix(ATTRIBUTE_PREFIX) else {
                continue;
            };
            let Some(text) = attr_text(a) else {
                continue;
            };
            let slot = match key {
                "System Type" => &mut metadata.instrument,
                "System Serial Number" => &mut metadata.serial,
                "Time Stamp" => &mut metadata.date,
                "Acquisition Mode" | "Camera Name" | "Camera Mode" => {
                    metadata
                        .extra
                        .insert(key.to_ascii_lowercase().replace(' ', "_"), text);
                    continue;
                }
                _ => continue,
            };
            *slot = Some(text);
            found = true;
        }
        if found {
            metadata.extra.insert("attributes_path".into(), path);
            return;
        }
    }
}

/// The decoded element count must be the shape's.
fn check_len(len: usize, n: usize, elem: usize, what: &str) -> Result<()> {
    if len != n {
        bail!("{what}: {} bytes, expected {n} x {elem}", len * elem);
    }
    Ok(())
}

pub fn parse(data: &[u8]) -> Result<Surface> {
    let file = h5(Hdf5File::from_bytes(data), "not a readable HDF5 file")?;
    let table = link_table(&file, data.len())?;
    let measurement = follow(&table, "Root", "Measurement")?;
    let surface_node = follow(&table, &measurement, "Surface")?;
    let path = follow(&table, &surface_node, "Path")?;
    let ds = h5(file.dataset(&path), &format!("surface dataset '{path}'"))?;
    let shape = ds.shape().to_vec();
    let (height, width) = match shape.as_slice() {
        [h, w] if *h > 0 && *w > 0 => (*h as usize, *w as usize),
        other => bail!("surface dataset '{path}': shape {other:?}, expected 2-D rows x columns"),
    };
    let n = checked_size(&[width, height], "surface shape")?;
    let elem = match ds.dtype() {
        Datatype::FloatingPoint { size, .. } if *size == 4 || *size == 8 => *size as usize,
        other => bail!("surface dataset '{path}': type {other:?}, expected float32 or float64"),
    };
    plausible_size(
        checked_size(&[n, elem], "surface size")?,
        data.len(),
        &format!("surface dataset '{path}'"),
    )?;
    let unit = string_attr(&ds, "Unit").with_context(|| format!("surface dataset '{path}'"))?;
    let no_data = match ds.attribute("No Data") {
        Ok(a) => Some(h5(a.read_as_f64(), "attribute 'No Data'").or_else(|_| {
            h5(a.read_1d::<f64>(), "attribute 'No Data'")?
                .first()
                .copied()
                .context("attribute 'No Data' is empty")
        })?),
        Err(_) => None,
    };
    let mut metadata = Metadata {
        format: "datx".into(),
        ..Metadata::default()
    };
    instrument_attributes(&file, &table, &measurement, &mut metadata);
    let scale_um = if unit == "Fringes" {
        let (_, p) = converter(&ds, "Z Converter").context("Unit is Fringes")?;
        let [_, lambda_m, s, o, ..] = p[..] else {
            bail!(
                "attribute 'Z Converter': Parameters has {} values, expected [?, lambda, S, O]",
                p.len()
            );
        };
        metadata.wavelength_um = Some(lambda_m * 1e6);
        lambda_m * s * o * 1e6
    } else {
        if let Ok((_, p)) = converter(&ds, "Z Converter") {
            if let Some(&l) = p.get(1).filter(|l| l.is_finite() && **l > 0.0) {
                metadata.wavelength_um = Some(l * 1e6);
            }
        }
        length_unit_um(&unit).with_context(|| {
            format!("attribute 'Unit' is '{unit}', expected a length unit or Fringes")
        })?
    };
    let to_um = |v: f64| -> f64 {
        if v.is_nan() || no_data.is_some_and(|nd| v >= nd) {
            f64::NAN
        } else {
            v * scale_um
        }
    };
    // Chunks (gzip-compressed in Mx files) are inflated in parallel by the HDF5 reader, which
    // also converts the byte order; the unit conversion runs in parallel over rows.
    let what = format!("surface dataset '{path}'");
    let heights_um: Vec<f64> = if elem == 8 {
        let a = h5(ds.read_array_parallel::<f64>(), &what)?;
        check_len(a.len(), n, elem, &what)?;
        match a.as_slice() {
            Some(s) => s.par_iter().map(|&v| to_um(v)).collect(),
            None => a.iter().map(|&v| to_um(v)).collect(),
        }
    } else {
        let a = h5(ds.read_array_parallel::<f32>(), &what)?;
        check_len(a.len(), n, elem, &what)?;
        // The marker is compared in the stored precision: an f32 'No Data' widened.
        match a.as_slice() {
            Some(s) => s.par_iter().map(|&v| to_um(v as f64)).collect(),
            None => a.iter().map(|&v| to_um(v as f64)).collect(),
        }
    };
    let px = pitch_m(&ds, "X Converter")?;
    let py = pitch_m(&ds, "Y Converter")?.or(px);
    metadata.pitch_known = px.is_some();
    metadata.extra.insert("surface_path".into(), path.clone());
    metadata.extra.insert("unit".into(), unit);
    Ok(Surface {
        width,
        height,
        pitch_x_um: px.map_or(1.0, |v| v * 1e6),
        pitch_y_um: py.map_or(1.0, |v| v * 1e6),
        heights_um,
        metadata,
    })
}
