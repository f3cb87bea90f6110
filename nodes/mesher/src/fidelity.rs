//! ISO 25178 areal height parameters (Sa, Sq, Sz) and the developed interfacial area ratio
//! (Sdr) of a height map, so that a mesh resampled on the grid can be judged against the
//! height field it was made from.
//!
//! Both surfaces are levelled by the same least-squares plane (fitted to the height field), so
//! the comparison sees only what the mesh changed. Missing samples (NaN) are left out; Sdr
//! counts only grid cells with four measured corners.

use serde::Serialize;

/// Areal parameters of one surface, um (Sdr in %).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct AreaParams {
    /// Arithmetic mean height about the levelling plane, um.
    pub sa_um: f64,
    /// Root mean square height about the levelling plane, um.
    pub sq_um: f64,
    /// Maximum height (highest peak to deepest valley), um.
    pub sz_um: f64,
    /// Developed interfacial area ratio, %.
    pub sdr_percent: f64,
}

/// Least-squares plane z = c0 + cx * col + cy * row over the finite samples; `None` when fewer
/// than three samples or they are collinear.
pub fn fit_plane(heights_um: &[f32], width: usize) -> Option<[f64; 3]> {
    // Normal equations in centred coordinates keep the 3 x 3 system well conditioned.
    let (mut n, mut sx, mut sy, mut sz) = (0.0f64, 0.0, 0.0, 0.0);
    for (k, &h) in heights_um.iter().enumerate() {
        if h.is_finite() {
            n += 1.0;
            sx += (k % width) as f64;
            sy += (k / width) as f64;
            sz += f64::from(h);
        }
    }
    if n < 3.0 {
        return None;
    }
    let (mx, my, mz) = (sx / n, sy / n, sz / n);
    let (mut xx, mut xy, mut yy, mut xz, mut yz) = (0.0f64, 0.0, 0.0, 0.0, 0.0);
    for (k, &h) in heights_um.iter().enumerate() {
        if h.is_finite() {
            let (x, y, z) = (
                (k % width) as f64 - mx,
                (k / width) as f64 - my,
                f64::from(h) - mz,
            );
            xx += x * x;
            xy += x * y;
            yy += y * y;
            xz += x * z;
            yz += y * z;
        }
    }
    let det = xx * yy - xy * xy;
    if det.abs() <= 1e-12 * (xx * yy).max(1e-300) {
        return None;
    }
    let cx = (xz * yy - yz * xy) / det;
    let cy = (yz * xx - xz * xy) / det;
    Some([mz - cx * mx - cy * my, cx, cy])
}

/// Sa, Sq, Sz and Sdr of `heights_um` after subtracting `plane` (from [`fit_plane`]).
/// `None` when no sample is finite.
pub fn area_params(
    heights_um: &[f32],
    width: usize,
    pitch_x_um: f64,
    pitch_y_um: f64,
    plane: [f64; 3],
) -> Option<AreaParams> {
    let level = |k: usize| {
        f64::from(heights_um[k])
            - plane[0]
            - plane[1] * (k % width) as f64
            - plane[2] * (k / width) as f64
    };
    let (mut n, mut sum_abs, mut sum2) = (0usize, 0.0f64, 0.0f64);
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    // The mean of the residuals is zero for the height field's own plane; for a mesh it is the
    // mesh's bias, which Sa and Sq should show, so they are taken about the plane, not the mean.
    for (k, h) in heights_um.iter().enumerate() {
        if h.is_finite() {
            let z = level(k);
            n += 1;
            sum_abs += z.abs();
            sum2 += z * z;
            lo = lo.min(z);
            hi = hi.max(z);
        }
    }
    if n == 0 {
        return None;
    }
    // Sdr: each cell as two triangles (the grid's own split), area over projected area.
    let height = heights_um.len() / width;
    let (mut developed, mut projected) = (0.0f64, 0.0f64);
    for i in 0..height.saturating_sub(1) {
        for j in 0..width - 1 {
            let k = i * width + j;
            let z = [k, k + 1, k + width, k + width + 1].map(|k| f64::from(heights_um[k]));
            if !z.iter().all(|z| z.is_finite()) {
                continue;
            }
            let tri = |a: [f64; 3], b: [f64; 3], c: [f64; 3]| {
                let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
                let v = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
                let n = [
                    u[1] * v[2] - u[2] * v[1],
                    u[2] * v[0] - u[0] * v[2],
                    u[0] * v[1] - u[1] * v[0],
                ];
                0.5 * (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt()
            };
            let (px, py) = (pitch_x_um, pitch_y_um);
            let p00 = [0.0, 0.0, z[0]];
            let p01 = [px, 0.0, z[1]];
            let p10 = [0.0, py, z[2]];
            let p11 = [px, py, z[3]];
            developed += tri(p00, p01, p11) + tri(p00, p11, p10);
            projected += px * py;
        }
    }
    Some(AreaParams {
        sa_um: sum_abs / n as f64,
        sq_um: (sum2 / n as f64).sqrt(),
        sz_um: hi - lo,
        sdr_percent: if projected > 0.0 {
            100.0 * (developed / projected - 1.0)
        } else {
            0.0
        },
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tilted_plane_levels_to_zero_and_sine_matches_theory() {
        let (w, h) = (64, 48);
        let tilted: Vec<f32> = (0..w * h)
            .map(|k| (3.0 + 0.01 * (k % w) as f64 - 0.02 * (k / w) as f64) as f32)
            .collect();
        let plane = fit_plane(&tilted, w).unwrap();
        let p = area_params(&tilted, w, 1.0, 1.0, plane).unwrap();
        assert!(p.sq_um < 1e-5 && p.sz_um < 1e-5, "{p:?}");
        // A sine of amplitude A along x over whole periods: Sq = A / sqrt 2, Sa = 2 A / pi.
        let a = 2.0f64;
        let sine: Vec<f32> = (0..w * h)
            .map(|k| (a * (2.0 * std::f64::consts::PI * (k % w) as f64 / 16.0).sin()) as f32)
            .collect();
        let plane = fit_plane(&sine, w).unwrap();
        // The plane of a few whole periods sampled on a grid is not exactly flat; level by the
        // exact zero plane to compare with theory.
        let p = area_params(&sine, w, 1.0, 1.0, [0.0, 0.0, 0.0]).unwrap();
        assert!((p.sq_um - a / 2f64.sqrt()).abs() < 1e-3, "{p:?}");
        assert!(
            (p.sa_um - 2.0 * a / std::f64::consts::PI).abs() < 0.02,
            "{p:?}"
        );
        assert!((p.sz_um - 2.0 * a).abs() < 1e-3);
        assert!(p.sdr_percent > 0.0);
        assert!(plane[1].abs() < 0.1);
    }
}
