//! NanoFocus µsurf `.nms`, binary, little-endian, no magic.
//!
//! No vendor description is published. Two readers were written from real files,
//! SurfaceTopography's `IO/NMS.py` (MIT, followed here) and surfalize's `nms.py` (GPL, read
//! for behaviour only); they agree on the layout:
//!
//! | offset | size | field |
//! |---|---|---|
//! | 16 | 8 + 8 | zmin, zmax (f64) |
//! | 1076 | 16 | date (text; surfalize only) |
//! | 1368 | 4 + 4 | nx, ny (u32) |
//! | 1376 | 8 + 8 | dx, dy (f64) |
//! | 3468 | 2 * nx * ny | heights, u16, ny rows of nx (x fastest); a u8 grey image may follow |
//!
//! Where they disagree, and what is decided here:
//! - Height: both scale raw / 65534 * (zmax - zmin); SurfaceTopography adds zmin, surfalize
//!   zmax. Adding zmin maps the raw range 0..=65534 onto [zmin, zmax], the range the header
//!   states; adding zmax would put every height above zmax. zmin is taken. The two differ by a
//!   constant, so Sa, Sq, Sp, Sv, Sz, Ssk, Sku, Sdq and Sdr are the same either way.
//! - Height unit: neither states one in the file; both return the heights as µm
//!   (SurfaceTopography declares µm, surfalize's surfaces are in µm). Read as µm.
//! - Lateral unit: SurfaceTopography reads dx, dy as mm (× 1000 to µm), surfalize as nm
//!   (× 0.001). The two readings differ by 10^6, so the magnitude decides: a pitch between
//!   1 nm and 100 µm (what an optical profiler's field and pixel count allow) is dx in
//!   [1e-6, 0.1] read as mm or dx in [1, 1e5] read as nm; the ranges do not overlap. Anything
//!   else is refused, naming both readings. The metadata records which one was taken
//!   (`lateral_unit`) and a warning says that it was decided by magnitude.
//! - Invalid points: an early surfalize marked raw 0 as not measured, later releases and
//!   SurfaceTopography mark none; none are marked here (no NaN from this format).
//! - Orientation: both take the first stored row as row 0 (y grows with the row index).

use anyhow::{bail, Result};

use super::bytes::{checked_size, Bytes};
use super::{Metadata, Surface};

const HEADER_LEN: usize = 3468;
/// Raw value of zmax (both readers divide by 2^16 - 2).
const FULL_SCALE: f64 = 65534.0;

/// dx, dy to µm: read as mm when the pitch is plausible that way, else as nm; the name of the
/// unit taken.
fn lateral_um(dx: f64, dy: f64) -> Result<(f64, f64, &'static str)> {
    let as_mm = |v: f64| (1e-6..=0.1).contains(&v);
    let as_nm = |v: f64| (1.0..=1e5).contains(&v);
    if as_mm(dx) && as_mm(dy) {
        Ok((dx * 1e3, dy * 1e3, "mm"))
    } else if as_nm(dx) && as_nm(dy) {
        Ok((dx * 1e-3, dy * 1e-3, "nm"))
    } else {
        bail!(
            "fields 'dx' x 'dy' are {dx} x {dy}: neither a pitch in mm (1e-6..=0.1, \
             SurfaceTopography's reading) nor in nm (1..=1e5, surfalize's) for both"
        )
    }
}

pub fn parse(data: &[u8]) -> Result<Surface> {
    let b = Bytes::new(data);
    if data.len() < HEADER_LEN {
        bail!(
            "the file has {} bytes, shorter than the {HEADER_LEN}-byte header",
            data.len()
        );
    }
    let zmin = b.f64_le(16, "zmin")?;
    let zmax = b.f64_le(24, "zmax")?;
    if !zmin.is_finite() || !zmax.is_finite() || zmax < zmin {
        bail!("fields 'zmin' / 'zmax' are {zmin} / {zmax}, expected finite with zmin <= zmax");
    }
    let nx = b.u32_le(1368, "nx")? as usize;
    let ny = b.u32_le(1372, "ny")? as usize;
    if nx == 0 || ny == 0 {
        bail!("fields 'nx' x 'ny' are {nx} x {ny}, expected positive");
    }
    let dx = b.f64_le(1376, "dx")?;
    let dy = b.f64_le(1384, "dy")?;
    let (pitch_x_um, pitch_y_um, unit) = lateral_um(dx, dy)?;
    let len = checked_size(&[nx, ny, 2], "fields 'nx' x 'ny' x 2 bytes")?;
    if len > data.len() - HEADER_LEN {
        bail!(
            "fields 'nx' x 'ny' ({nx} x {ny}) need {len} bytes of heights from byte {HEADER_LEN}, \
             but the file has only {} bytes",
            data.len()
        );
    }
    let raw = b.slice(HEADER_LEN, len, "height data")?;
    let scale = (zmax - zmin) / FULL_SCALE;
    let heights_um: Vec<f64> = raw
        .chunks_exact(2)
        .map(|c| zmin + u16::from_le_bytes([c[0], c[1]]) as f64 * scale)
        .collect();
    let mut metadata = Metadata {
        format: "nms".into(),
        pitch_known: true,
        instrument: Some("NanoFocus µsurf".into()),
        ..Metadata::default()
    };
    let date = b.text(1076, 16, "date")?;
    if !date.is_empty() {
        metadata.date = Some(date);
    }
    metadata.extra.insert("zmin_um".into(), zmin.to_string());
    metadata.extra.insert("zmax_um".into(), zmax.to_string());
    metadata.extra.insert("lateral_unit".into(), unit.into());
    metadata.warnings.push(format!(
        "NanoFocus .nms: dx, dy ({dx} x {dy}) read as {unit} by their magnitude (the published \
         readers disagree: mm or nm); heights read as µm from zmin (no unit is stored)"
    ));
    Ok(Surface {
        width: nx,
        height: ny,
        pitch_x_um,
        pitch_y_um,
        heights_um,
        metadata,
    })
}
