//! A measured after-finish scan registered to the model (`--after FILE`, `--calibrate FILE`):
//! the part is measured again after finishing, on another mounting, so the scan is shifted
//! against the model by an unknown offset. It is found by the matcher's phase correlation
//! (the same registration that places the tiles: NCC of the levelled heights, sub-pixel
//! refinement), and the scan is resampled bilinearly onto the model's grid; samples it does
//! not cover are missing (NaN), and the patch must lie inside what it covers.

use anyhow::{bail, Result};
use surfstream_core::raster::RasterView;
use surfstream_core::Shape;
use surfstream_matcher::register::{register_pair, PhaseParams};

use crate::run::Model;

/// finish.json `after_registrations[]` is core's record.
pub use surfstream_core::record::finish::AfterRegistration;

/// Pitches further apart than this (relative) are refused: the scan would need resampling in
/// scale, which a measurement of the same area on the same instrument does not.
pub const PITCH_TOLERANCE: f64 = 0.01;

/// Smallest NCC accepted for an after-finish scan: a finishing step lowers the correlation
/// with the original (its peaks are cut), so below the tiles' 0.5; unrelated surfaces
/// measure below 0.1 (the matcher's tests).
pub const MIN_AFTER_NCC: f64 = 0.3;

/// Registers `after` to `model` and returns it resampled on the model's grid (NaN where it
/// does not reach) with the registration. Errors name the file and what was expected.
pub fn register_after(
    model: &Model,
    after: &Model,
    role: &str,
) -> Result<(Model, AfterRegistration)> {
    for (axis, m, a) in [
        ("x", model.pitch_x_um, after.pitch_x_um),
        ("y", model.pitch_y_um, after.pitch_y_um),
    ] {
        // (NaN pitches fail the comparison and are refused too.)
        if (a - m).abs().partial_cmp(&(PITCH_TOLERANCE * m)) != Some(std::cmp::Ordering::Less) {
            bail!(
                "{}: pitch {axis} {a} um; the model's is {m} um: expected the same pitch (within {} %) for an after-finish scan of the same area",
                after.source,
                PITCH_TOLERANCE * 100.0
            );
        }
    }
    let a32: Vec<f32> = model.heights_um.iter().map(|&v| v as f32).collect();
    let b32: Vec<f32> = after.heights_um.iter().map(|&v| v as f32).collect();
    let a = RasterView::new(&a32, Shape::new(model.rows, model.cols))?;
    let b = RasterView::new(&b32, Shape::new(after.rows, after.cols))?;
    // A re-mounted part may be shifted by much more than neighbouring tiles: allow up to the
    // matcher's fraction of the overlap; the threshold is the after-scan's.
    let params = PhaseParams {
        max_shift_px: model.rows.max(model.cols) as f64,
        min_ncc: MIN_AFTER_NCC,
        ..PhaseParams::default()
    };
    let r = register_pair(a, b, [0.0, 0.0], &params);
    let Some(offset_px) = r.offset_px else {
        bail!(
            "{}: the after-finish scan could not be registered to the model ({}; best NCC {:.3}, at least {MIN_AFTER_NCC} expected): is it a scan of the same area?",
            after.source,
            r.rejection
                .map(|x| format!("{x:?}"))
                .unwrap_or_else(|| "no offset".into()),
            r.ncc
        );
    };
    let heights_um = resample(after, offset_px, model.rows, model.cols);
    let covered = heights_um.iter().filter(|v| v.is_finite()).count();
    let reg = AfterRegistration {
        source: after.source.clone(),
        role: role.into(),
        offset_px,
        offset_um: [
            offset_px[0] * model.pitch_x_um,
            offset_px[1] * model.pitch_y_um,
        ],
        ncc: r.ncc,
        scan_shape: [after.rows, after.cols],
        covered_fraction: covered as f64 / heights_um.len().max(1) as f64,
        method: "phase correlation + NCC (surfstream-matcher register_pair), bilinear resampling onto the model's grid".into(),
    };
    Ok((
        Model {
            heights_um,
            rows: model.rows,
            cols: model.cols,
            pitch_x_um: model.pitch_x_um,
            pitch_y_um: model.pitch_y_um,
            source: after.source.clone(),
        },
        reg,
    ))
}

/// `after` sampled at the model's grid points: model (row r, col c) is the scan's
/// (r - dy, c - dx); bilinear between the four samples around it, NaN outside or where one
/// of them is missing.
fn resample(after: &Model, offset_px: [f64; 2], rows: usize, cols: usize) -> Vec<f64> {
    let [dx, dy] = offset_px;
    let at = |r: i64, c: i64| -> f64 {
        if r < 0 || c < 0 || r >= after.rows as i64 || c >= after.cols as i64 {
            f64::NAN
        } else {
            after.heights_um[r as usize * after.cols + c as usize]
        }
    };
    let mut out = vec![f64::NAN; rows * cols];
    for r in 0..rows {
        let y = r as f64 - dy;
        let (y0, fy) = (y.floor(), y - y.floor());
        for c in 0..cols {
            let x = c as f64 - dx;
            let (x0, fx) = (x.floor(), x - x.floor());
            let (y0i, x0i) = (y0 as i64, x0 as i64);
            let v00 = at(y0i, x0i);
            let v01 = at(y0i, x0i + 1);
            let v10 = at(y0i + 1, x0i);
            let v11 = at(y0i + 1, x0i + 1);
            // Exactly on a sample the far neighbours carry no weight (and may be outside).
            let w = [
                (1.0 - fy) * (1.0 - fx),
                (1.0 - fy) * fx,
                fy * (1.0 - fx),
                fy * fx,
            ];
            let mut acc = 0.0;
            let mut ok = true;
            for (v, w) in [v00, v01, v10, v11].into_iter().zip(w) {
                if w > 0.0 {
                    if v.is_finite() {
                        acc += v * w;
                    } else {
                        ok = false;
                    }
                }
            }
            if ok {
                out[r * cols + c] = acc;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn surface(rows: usize, cols: usize, shift: (f64, f64)) -> Model {
        // A rough texture (sum of incommensurate waves), sampled shifted by `shift` px (x, y).
        let mut h = Vec::with_capacity(rows * cols);
        for r in 0..rows {
            for c in 0..cols {
                let (x, y) = (c as f64 + shift.0, r as f64 + shift.1);
                h.push(
                    (0.31 * x).sin() * (0.17 * y).cos()
                        + 0.5 * (0.093 * x + 0.21 * y).sin()
                        + 0.3 * (0.41 * x - 0.07 * y).cos()
                        + 0.2 * (0.05 * x * 0.9 + 0.6 * (0.13 * y).sin()).sin(),
                );
            }
        }
        Model {
            heights_um: h,
            rows,
            cols,
            pitch_x_um: 0.8148,
            pitch_y_um: 0.8148,
            source: "synthetic".into(),
        }
    }

    #[test]
    fn a_shifted_after_scan_is_found_and_resampled_onto_the_model() {
        let model = surface(160, 200, (0.0, 0.0));
        // The after scan starts 12.5 px right and 7 px down of the model's origin: its pixel
        // (0, 0) is the model's (7, 12.5), so the offset is (12.5, 7).
        let mut after = surface(150, 180, (12.5, 7.0));
        // The finishing cut the peaks.
        for v in &mut after.heights_um {
            *v = v.min(0.8);
        }
        after.source = "after.x3p".into();
        let (on_model, reg) = register_after(&model, &after, "after").unwrap();
        assert!((reg.offset_px[0] - 12.5).abs() < 0.1, "{:?}", reg.offset_px);
        assert!((reg.offset_px[1] - 7.0).abs() < 0.1, "{:?}", reg.offset_px);
        assert!(reg.ncc > 0.9, "{}", reg.ncc);
        // Inside the covered area the resampled scan is the cut model.
        let (r, c) = (60, 90);
        let m = model.heights_um[r * model.cols + c].min(0.8);
        let a = on_model.heights_um[r * model.cols + c];
        assert!((a - m).abs() < 0.05, "{a} vs {m}");
        // Outside it (the first rows and columns) it is missing.
        assert!(on_model.heights_um[0].is_nan());
        assert!(reg.covered_fraction > 0.7 && reg.covered_fraction < 1.0);
    }

    #[test]
    fn an_unrelated_scan_or_another_pitch_is_refused_by_name() {
        let model = surface(120, 120, (0.0, 0.0));
        let mut other = model.clone();
        other.source = "other.x3p".into();
        // Deterministic noise: nothing in common with the model.
        let mut s = 12345u64;
        for v in &mut other.heights_um {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            *v = (s >> 33) as f64 / (1u64 << 31) as f64;
        }
        let e = register_after(&model, &other, "after")
            .unwrap_err()
            .to_string();
        assert!(e.contains("other.x3p") && e.contains("same area"), "{e}");
        let mut coarse = model.clone();
        coarse.pitch_x_um = 1.6;
        coarse.source = "coarse.x3p".into();
        let e = register_after(&model, &coarse, "after")
            .unwrap_err()
            .to_string();
        assert!(e.contains("coarse.x3p") && e.contains("pitch x"), "{e}");
    }
}
