//! Zygo MetroPro `.dat`: a big-endian header (834 or 4096 bytes), the intensity block, then
//! the phase block (i32 big-endian, top row first).
//!
//! height = phase * S * O * lambda / R with R = 4096 / 32768 / 131072 for phase_res 0 / 1 / 2
//! (the MetroPro reference guide, Gwyddion and SurfaceTopography agree; surfalize 0.19.2 keys
//! the table 1 / 2 / 3 and reads heights 8x too tall). Negated when `sign` != 0. Phase values
//! >= 2147483640 are invalid (NaN).

use anyhow::{bail, Result};

use super::bytes::{checked_size, Bytes};
use super::{Metadata, Surface};

const MAGIC: [u8; 3] = [0x88, 0x1B, 0x03];
const PHASE_INVALID: i32 = 2_147_483_640;

pub fn parse(data: &[u8]) -> Result<Surface> {
    let b = Bytes::new(data);
    let magic = b.slice(0, 4, "magic")?;
    if magic[..3] != MAGIC || !(0x6F..=0x71).contains(&magic[3]) {
        bail!(
            "not a MetroPro .dat file: magic {:02x?}, expected 88 1b 03 6f/70/71",
            magic
        );
    }
    let format_from_magic = (magic[3] - 0x6F + 1) as u16;
    let header_format = b.u16_be(4, "header_format")?;
    let header_size = b.u32_be(6, "header_size")? as usize;
    let expected_size = if header_format == 3 { 4096 } else { 834 };
    if header_format != format_from_magic || header_size != expected_size {
        bail!(
            "inconsistent header: magic says format {format_from_magic}, header_format is \
             {header_format}, header_size is {header_size} (expected {expected_size} for format {header_format})"
        );
    }
    let ac_n_bytes = b.u32_be(60, "ac_n_bytes")? as usize;
    let width = b.u16_be(68, "cn_width")? as usize;
    let height = b.u16_be(70, "cn_height")? as usize;
    let cn_n_bytes = b.u32_be(72, "cn_n_bytes")? as usize;
    let scale = b.f32_be(164, "intf_scale_factor")? as f64;
    let wavelength_m = b.f32_be(168, "wavelength_in")? as f64;
    let obliquity = b.f32_be(176, "obliquity_factor")? as f64;
    let lateral_res_m = b.f32_be(184, "lateral_res")? as f64;
    let phase_res = b.i16_be(218, "phase_res")?;
    let sign = b.i16_be(232, "phase_sign")?;
    let r = match phase_res {
        0 => 4096.0,
        1 => 32768.0,
        2 => 131072.0,
        other => bail!("field 'phase_res' is {other}, expected 0, 1 or 2"),
    };
    if width == 0 || height == 0 {
        bail!("no phase data (cn_width {width}, cn_height {height})");
    }
    let n = checked_size(&[width, height], "cn_width * cn_height")?;
    if cn_n_bytes != 4 * n {
        bail!(
            "field 'cn_n_bytes' is {cn_n_bytes}, expected 4 * {width} * {height} = {}",
            4 * n
        );
    }
    for (name, v) in [
        ("intf_scale_factor", scale),
        ("wavelength_in", wavelength_m),
        ("obliquity_factor", obliquity),
    ] {
        if !v.is_finite() || v == 0.0 {
            bail!("field '{name}' is {v}, expected a finite non-zero number");
        }
    }
    // A negative wavelength would flip every height's sign (issue 36).
    if wavelength_m < 0.0 {
        bail!("field 'wavelength_in' is {wavelength_m} m, expected a positive wavelength");
    }
    let start = header_size
        .checked_add(ac_n_bytes)
        .ok_or_else(|| anyhow::anyhow!("header_size + ac_n_bytes overflows"))?;
    let phase = b.slice(start, cn_n_bytes, "phase data")?;
    // Same operation order as the references (phase * S * O * lambda / R, then to um).
    let factor_sign = if sign != 0 { -1.0 } else { 1.0 };
    let heights_um = phase
        .chunks_exact(4)
        .map(|c| {
            let p = i32::from_be_bytes([c[0], c[1], c[2], c[3]]);
            if p >= PHASE_INVALID {
                f64::NAN
            } else {
                factor_sign * (p as f64 * scale * obliquity * wavelength_m / r) * 1e6
            }
        })
        .collect();
    let pitch_known = lateral_res_m.is_finite() && lateral_res_m > 0.0;
    let pitch_um = if pitch_known {
        lateral_res_m * 1e6
    } else {
        1.0
    };
    let mut metadata = Metadata {
        format: "metropro".into(),
        pitch_known,
        wavelength_um: Some(wavelength_m * 1e6),
        ..Metadata::default()
    };
    metadata
        .extra
        .insert("header_format".into(), header_format.to_string());
    metadata
        .extra
        .insert("phase_res".into(), phase_res.to_string());
    metadata
        .extra
        .insert("intf_scale_factor".into(), scale.to_string());
    metadata
        .extra
        .insert("obliquity_factor".into(), obliquity.to_string());
    Ok(Surface {
        width,
        height,
        pitch_x_um: pitch_um,
        pitch_y_um: pitch_um,
        heights_um,
        metadata,
    })
}
