//! Sensofar `.plu` (PLu / PLu neox / S neox, SensoSCAN), binary, little-endian, no magic.
//!
//! Layout as SurfaceTopography's `IO/PLU.py` (MIT) describes it, checked against Gwyddion's
//! `sensofar.c` (GPL: read for behaviour only), which agree on every offset used here:
//!
//! | offset | size | field |
//! |---|---|---|
//! | 0 | 128 | acquisition date, ASCII |
//! | 128 | 4 | acquisition time (u32) |
//! | 132 | 256 | user comment, ASCII |
//! | 388 | 40 | calibration: yres, xres, N_tall (u32); dy_multip, mppx, mppy, x_0, y_0, mpp_tall, z_0 (f32) |
//! | 428 | 20 | measurement configuration: type, algorithm, method, objective, area_type (u32) |
//! | 448 | 40 | scan settings (field-of-view or point-scan variant, 40 bytes either way) |
//! | 488 | 12 | restore, num_layers, version, config_hardware, num_images, reserved (u8), 2 padding, factor_delmacio (u32) |
//! | 500 | 8 | data block: yres, xres (u32) |
//! | 508 | 4 * xres * yres | heights, f32, micrometres, row after row (x fastest) |
//! | ... | 8 | min, max (f32) |
//!
//! Pixel size: `mppx`, `mppy` (micrometres per pixel, offsets 404 and 408). Only topography
//! measurements (type 3) are read; images, profiles and coordinate maps are refused by name.
//! Only the first layer is read. Invalid points are stored as 1000001.0 (NaN here).
//!
//! Orientation: both readers take the first stored row as row 0 and the row index as y; so
//! do we (no flip).

use anyhow::{bail, Result};

use super::bytes::{checked_size, Bytes};
use super::{Metadata, Surface};

const HEADER_LEN: usize = 500;
/// The value Sensofar writes for a point it could not measure ("LOST_PIXELS").
const LOST_PIXEL: f32 = 1_000_001.0;
const TYPE_TOPOGRAPHY: u32 = 3;

pub fn parse(data: &[u8]) -> Result<Surface> {
    let b = Bytes::new(data);
    if data.len() < HEADER_LEN + 8 {
        bail!(
            "file has {} bytes, expected at least {} (the 500-byte header and the data block's size)",
            data.len(),
            HEADER_LEN + 8
        );
    }
    let meas_type = b.u32_le(428, "measurement type")?;
    if meas_type != TYPE_TOPOGRAPHY {
        bail!(
            "field 'measurement type' is {meas_type} ({}), expected 3 (topography); only topographies are read",
            type_name(meas_type)
        );
    }
    let num_layers = b.slice(489, 1, "num_layers")?[0];
    if num_layers == 0 {
        bail!("field 'num_layers' is 0: the file holds no data");
    }
    let version = b.slice(490, 1, "version")?[0];
    let mppx = b.f32_le(404, "mppx (micrometres per pixel x)")? as f64;
    let mppy = b.f32_le(408, "mppy (micrometres per pixel y)")? as f64;
    for (name, v) in [("mppx", mppx), ("mppy", mppy)] {
        if !v.is_finite() || v <= 0.0 {
            bail!("field '{name}' is {v}, expected a finite positive pixel size in micrometres");
        }
    }
    let yres = b.u32_le(HEADER_LEN, "data yres")? as usize;
    let xres = b.u32_le(HEADER_LEN + 4, "data xres")? as usize;
    if xres == 0 || yres == 0 {
        bail!("fields 'data xres' x 'data yres' are {xres} x {yres}, expected positive");
    }
    let len = checked_size(
        &[xres, yres, 4],
        "fields 'data xres' x 'data yres' x 4 bytes",
    )?;
    let start = HEADER_LEN + 8;
    if len > data.len() - start {
        bail!(
            "fields 'data xres' x 'data yres' ({xres} x {yres}) need {len} bytes of heights from byte {start}, but the file has only {} bytes",
            data.len()
        );
    }
    let raw = b.slice(start, len, "height data")?;
    let heights_um: Vec<f64> = raw
        .chunks_exact(4)
        .map(|c| {
            let v = f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
            if v == LOST_PIXEL {
                f64::NAN
            } else {
                v as f64
            }
        })
        .collect();
    let mut metadata = Metadata {
        format: "plu".into(),
        pitch_known: true,
        ..Metadata::default()
    };
    let date = b.text(0, 128, "date")?;
    if !date.is_empty() {
        metadata.date = Some(date);
    }
    let comment = b.text(132, 256, "comment")?;
    if !comment.is_empty() {
        metadata.extra.insert("comment".into(), comment);
    }
    metadata
        .extra
        .insert("version".into(), format!("{version:#04x}"));
    metadata
        .extra
        .insert("num_layers".into(), num_layers.to_string());
    if num_layers > 1 {
        metadata.warnings.push(format!(
            "the file has {num_layers} layers; only the first is read"
        ));
    }
    Ok(Surface {
        width: xres,
        height: yres,
        pitch_x_um: mppx,
        pitch_y_um: mppy,
        heights_um,
        metadata,
    })
}

fn type_name(t: u32) -> &'static str {
    match t {
        0 => "confocal image",
        1 => "profile",
        2 => "multiple profile",
        3 => "topography",
        4 => "coordinates multiple profile",
        5 => "single point thickness",
        6 => "custom application",
        7 => "coordinates topography map",
        8 => "coordinates thickness map",
        _ => "unknown",
    }
}
