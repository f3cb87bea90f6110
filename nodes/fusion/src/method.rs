//! The three fusion methods of the paper and the wavelet fusion rule (eq. 6).
//!
//! * [`FusionMethod::Average`] (eq. 4): every covering tile has weight 1.
//! * [`FusionMethod::Gradual`] (eq. 5, generalised to 2-D): weights by distance to each
//!   tile's border, see [`crate::BlendParams`].
//! * [`FusionMethod::Wavelet`] (eq. 6): where a new tile overlaps what the panorama already
//!   holds, both are decomposed with a 2-D DWT ([`WaveletFusion`]: sym5, level 2, mode
//!   symmetric by default), the approximations are averaged, and each detail coefficient is
//!   taken from the input whose coefficient is larger in magnitude (the "max-abs" rule of the
//!   image-fusion literature: it keeps the sharper of the two textures instead of blurring
//!   them together); the inverse DWT gives the fused overlap, feathered into the lone sides
//!   over [`feather_px`] from the overlap's edge so no step remains. Pixels only one side measured
//!   keep that side's value, so a pixel valid in any tile is valid in the panorama. With more
//!   than two tiles over a pixel (corners), tiles are fused one at a time in index order.

use std::fmt;

use serde::{Deserialize, Serialize};
use surfstream_core::raster::{Shape, ShapeError};
use surfstream_wavelet::{
    dwt_max_level, fill_invalid, wavedec2, waverec2, Coeffs2, Mode, Wavelet, WaveletError,
};

/// How overlapping tiles are fused.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FusionMethod {
    Average,
    Gradual,
    Wavelet,
}

impl FusionMethod {
    pub const ALL: [FusionMethod; 3] = [
        FusionMethod::Average,
        FusionMethod::Gradual,
        FusionMethod::Wavelet,
    ];

    /// The graph-file name: "average", "gradual" or "wavelet".
    pub fn name(self) -> &'static str {
        match self {
            FusionMethod::Average => "average",
            FusionMethod::Gradual => "gradual",
            FusionMethod::Wavelet => "wavelet",
        }
    }

    /// Parse a graph-file name (ASCII case ignored).
    pub fn by_name(name: &str) -> Option<FusionMethod> {
        Self::ALL
            .into_iter()
            .find(|m| m.name().eq_ignore_ascii_case(name.trim()))
    }
}

impl std::str::FromStr for FusionMethod {
    type Err = String;
    /// A graph-file name (ASCII case and surrounding blanks ignored).
    fn from_str(s: &str) -> Result<Self, String> {
        Self::by_name(s)
            .ok_or_else(|| format!("{s:?}: expected \"gradual\", \"average\" or \"wavelet\""))
    }
}

impl fmt::Display for FusionMethod {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Parameters of wavelet fusion (eq. 6).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WaveletFusion {
    pub wavelet: Wavelet,
    /// Decomposition levels; clamped to the overlap's `dwt_max_level` (at least 1).
    pub level: usize,
    pub mode: Mode,
}

impl Default for WaveletFusion {
    fn default() -> Self {
        Self {
            // sym5 is what the separation uses; two levels fit a 10 % overlap of a 1024 px
            // tile (102 px: dwt_max_level(102, 10) = 3).
            wavelet: Wavelet::by_name("sym5").unwrap_or_else(|| unreachable!("sym5 is built in")),
            level: 2,
            mode: Mode::Symmetric,
        }
    }
}

/// Fuse two co-registered rasters (row-major `rows x cols`, NaN = not measured) by eq. 6.
///
/// Returns the fused raster: NaN where both are NaN, the measured one where only one is, and
/// the wavelet fusion where both are. Before the transform each side's holes are filled with
/// the other side's values, and pixels neither measured by
/// [`surfstream_wavelet::fill_invalid`]'s interpolation, so no NaN reaches the DWT. An
/// overlap too small for one level (side < `2 * (filter_len - 1)`) falls back to the average.
pub fn fuse_wavelet(
    a: &[f32],
    b: &[f32],
    rows: usize,
    cols: usize,
    p: &WaveletFusion,
) -> Result<Vec<f32>, WaveletError> {
    fuse_wavelet_in(a, b, rows, cols, p, |_, _| false)
}

/// [`fuse_wavelet`] for a raster that sits inside a larger one where only `a` continues:
/// `a_beyond(row, col)` (indices may be -1 or `rows` / `cols`) says whether `a` is measured
/// just outside, so the feathering also meets `a` there without a step.
pub fn fuse_wavelet_in(
    a: &[f32],
    b: &[f32],
    rows: usize,
    cols: usize,
    p: &WaveletFusion,
    a_beyond: impl Fn(isize, isize) -> bool,
) -> Result<Vec<f32>, WaveletError> {
    let n = rows * cols;
    for found in [a.len(), b.len()] {
        if found != n {
            let shape = Shape::new(rows, cols);
            return Err(ShapeError::Length {
                shape,
                expected: n,
                found,
            }
            .into());
        }
    }
    let mut out: Vec<f32> = a
        .iter()
        .zip(b)
        .map(|(&x, &y)| match (x.is_finite(), y.is_finite()) {
            (true, true) => 0.5 * (x + y),
            (true, false) => x,
            (false, true) => y,
            (false, false) => f32::NAN,
        })
        .collect();
    // Bounding box of the pixels both measured: only there is anything to fuse.
    let (mut r0, mut r1, mut c0, mut c1) = (usize::MAX, 0, usize::MAX, 0);
    for r in 0..rows {
        for c in 0..cols {
            let i = r * cols + c;
            if a[i].is_finite() && b[i].is_finite() {
                r0 = r0.min(r);
                r1 = r1.max(r + 1);
                c0 = c0.min(c);
                c1 = c1.max(c + 1);
            }
        }
    }
    if r0 == usize::MAX {
        return Ok(out);
    }
    let (h, w) = (r1 - r0, c1 - c0);
    let max_level = dwt_max_level(h.min(w), p.wavelet.filter_len());
    if max_level == 0 {
        return Ok(out); // too small for a DWT: the average computed above stands
    }
    let level = p.level.clamp(1, max_level);
    let mut fa = Vec::with_capacity(h * w);
    let mut fb = Vec::with_capacity(h * w);
    for r in r0..r1 {
        for c in c0..c1 {
            let i = r * cols + c;
            let (x, y) = (a[i], b[i]);
            fa.push(if x.is_finite() { x } else { y });
            fb.push(if y.is_finite() { y } else { x });
        }
    }
    let fa = fill_invalid(&fa, h, w)?;
    let fb = fill_invalid(&fb, h, w)?;
    let ca = wavedec2(&fa, h, w, &p.wavelet, p.mode, level)?;
    let cb = wavedec2(&fb, h, w, &p.wavelet, p.mode, level)?;
    let fused = waverec2(&fuse_coeffs(ca, &cb), &p.wavelet, p.mode)?;
    // Feathering: the fused overlap differs from the single tile just outside it (its
    // approximation is the two sides' mean), which leaves a step where an overlap ends. Over
    // `feather_px` from the edge of the both-measured region the result slides from the
    // distance-weighted blend of the two sides (equal to the lone side at the edge, as in
    // the gradual method) to the wavelet fusion.
    // Distances to where only one side shows: near a lone-`a` pixel the blend is `a`, near a
    // lone-`b` pixel it is `b`. Pixels neither side measured show nothing and do not count.
    let lone_b = distance_to(
        rows,
        cols,
        |i| !a[i].is_finite() && b[i].is_finite(),
        |_, _| false,
    );
    let lone_a = distance_to(
        rows,
        cols,
        |i| a[i].is_finite() && !b[i].is_finite(),
        &a_beyond,
    );
    let feather_px = feather_px(level);
    for r in 0..h {
        for c in 0..w {
            let i = (r + r0) * cols + c + c0;
            if a[i].is_finite() && b[i].is_finite() {
                // waverec2 gives one extra row / column on odd sizes: index, never reshape.
                let f = fused.values()[r * fused.cols() + c];
                // `a` weighs with the distance to lone `b`, `b` with the distance to lone `a`.
                let (da, db) = (f64::from(lone_b[i]), f64::from(lone_a[i]));
                let edge = (da.min(db) / feather_px).min(1.0);
                let blend = (da * f64::from(a[i]) + db * f64::from(b[i])) / (da + db);
                out[i] = (edge * f + (1.0 - edge) * blend) as f32;
            }
        }
    }
    Ok(out)
}

/// Width of the seam feathering of wavelet fusion, px: four times the coarsest fused
/// approximation's sample spacing, so the step of the averaged approximation is spread over
/// a few of its own samples.
pub fn feather_px(level: usize) -> f64 {
    4.0 * f64::from(1u32 << level.min(16))
}

/// Chamfer (3-4) distance, px, from every pixel to the nearest pixel `i` with `target(i)`,
/// or just outside the raster at (row, col) with `outside(row, col)`. Large (1e9 / 3) when
/// there is none.
fn distance_to(
    rows: usize,
    cols: usize,
    target: impl Fn(usize) -> bool,
    outside: impl Fn(isize, isize) -> bool,
) -> Vec<f32> {
    const FAR: f32 = 1.0e9;
    let mut d: Vec<f32> = (0..rows * cols)
        .map(|i| if target(i) { 0.0 } else { FAR })
        .collect();
    let at = |d: &[f32], r: isize, c: isize| -> f32 {
        if r < 0 || c < 0 || r >= rows as isize || c >= cols as isize {
            if outside(r, c) {
                0.0
            } else {
                FAR
            }
        } else {
            d[r as usize * cols + c as usize]
        }
    };
    for r in 0..rows as isize {
        for c in 0..cols as isize {
            let i = r as usize * cols + c as usize;
            let v = d[i]
                .min(at(&d, r, c - 1) + 3.0)
                .min(at(&d, r - 1, c) + 3.0)
                .min(at(&d, r - 1, c - 1) + 4.0)
                .min(at(&d, r - 1, c + 1) + 4.0);
            d[i] = v;
        }
    }
    for r in (0..rows as isize).rev() {
        for c in (0..cols as isize).rev() {
            let i = r as usize * cols + c as usize;
            let v = d[i]
                .min(at(&d, r, c + 1) + 3.0)
                .min(at(&d, r + 1, c) + 3.0)
                .min(at(&d, r + 1, c + 1) + 4.0)
                .min(at(&d, r + 1, c - 1) + 4.0);
            d[i] = v;
        }
    }
    // The 3-4 chamfer counts 3 per pixel step.
    d.iter().map(|v| v / 3.0).collect()
}

/// Approximations averaged, details by the max-abs rule (ties keep `a`'s).
fn fuse_coeffs(mut a: Coeffs2, b: &Coeffs2) -> Coeffs2 {
    for (x, y) in a.approx.values_mut().iter_mut().zip(b.approx.values()) {
        *x = 0.5 * (*x + y);
    }
    for (da, db) in a.details.iter_mut().zip(&b.details) {
        for (ba, bb) in [(&mut da.h, &db.h), (&mut da.v, &db.v), (&mut da.d, &db.d)] {
            for (x, &y) in ba.values_mut().iter_mut().zip(bb.values()) {
                if y.abs() > x.abs() {
                    *x = y;
                }
            }
        }
    }
    a
}

#[cfg(test)]
mod tests {
    use super::*;

    fn surface(rows: usize, cols: usize, phase: f32) -> Vec<f32> {
        (0..rows * cols)
            .map(|i| {
                let (r, c) = ((i / cols) as f32, (i % cols) as f32);
                (0.3 * r + phase).sin() + 0.5 * (0.7 * c).cos()
            })
            .collect()
    }

    #[test]
    fn identical_inputs_fuse_to_themselves() {
        let a = surface(40, 50, 0.0);
        let f = fuse_wavelet(&a, &a, 40, 50, &WaveletFusion::default()).unwrap();
        for (x, y) in f.iter().zip(&a) {
            assert!((x - y).abs() < 1e-5, "{x} vs {y}");
        }
    }

    #[test]
    fn nan_never_contaminates_and_coverage_is_the_union() {
        let (rows, cols) = (40, 50);
        let mut a = surface(rows, cols, 0.0);
        let mut b = surface(rows, cols, 0.1);
        for c in 0..cols {
            a[5 * cols + c] = f32::NAN; // a row a lacks
        }
        for r in 0..rows {
            b[r * cols + 7] = f32::NAN; // a column b lacks
        }
        a[3] = f32::NAN;
        b[3] = f32::NAN; // a pixel neither has
        let f = fuse_wavelet(&a, &b, rows, cols, &WaveletFusion::default()).unwrap();
        for i in 0..rows * cols {
            let any = a[i].is_finite() || b[i].is_finite();
            assert_eq!(f[i].is_finite(), any, "pixel {i}");
            if a[i].is_finite() && !b[i].is_finite() {
                assert_eq!(f[i], a[i]);
            }
            if b[i].is_finite() && !a[i].is_finite() {
                assert_eq!(f[i], b[i]);
            }
        }
    }

    #[test]
    fn approximation_is_averaged_and_sharper_detail_kept() {
        // a: smooth offset 0; b: smooth offset 2 plus a fine checkerboard. The fused low
        // frequencies sit half-way (offset 1); the checkerboard, b's larger detail, survives.
        let (rows, cols) = (64, 64);
        let a: Vec<f32> = vec![0.0; rows * cols];
        let b: Vec<f32> = (0..rows * cols)
            .map(|i| {
                2.0 + if (i / cols + i % cols) % 2 == 0 {
                    0.1
                } else {
                    -0.1
                }
            })
            .collect();
        let f = fuse_wavelet(&a, &b, rows, cols, &WaveletFusion::default()).unwrap();
        let interior = |r: usize, c: usize| f[r * cols + c];
        let mean: f32 = (20..44)
            .flat_map(|r| (20..44).map(move |c| (r, c)))
            .map(|(r, c)| interior(r, c))
            .sum::<f32>()
            / (24.0 * 24.0);
        assert!((mean - 1.0).abs() < 1e-3, "mean {mean}");
        let swing = (interior(30, 30) - interior(30, 31)).abs();
        assert!((swing - 0.2).abs() < 1e-3, "checkerboard swing {swing}");
    }

    #[test]
    fn tiny_overlap_falls_back_to_the_average() {
        let a = vec![1.0f32; 5 * 6];
        let b = vec![3.0f32; 5 * 6];
        let f = fuse_wavelet(&a, &b, 5, 6, &WaveletFusion::default()).unwrap();
        assert!(f.iter().all(|&v| v == 2.0));
        assert!(fuse_wavelet(&a, &b[..4], 5, 6, &WaveletFusion::default()).is_err());
    }

    #[test]
    fn no_step_where_an_overlap_ends() {
        // Two tiles of one smooth surface, the second 0.5 um higher (a piston nobody removed):
        // without feathering the fused overlap (mean approximation) meets the lone tiles with
        // a 0.25 um step on each side.
        let (rows, cols) = (40, 112);
        let f = |r: usize, c: usize| (0.05 * c as f32).sin() + 0.01 * r as f32;
        let mut a = vec![f32::NAN; rows * cols];
        let mut b = vec![f32::NAN; rows * cols];
        for r in 0..rows {
            for c in 0..cols {
                if c < 80 {
                    a[r * cols + c] = f(r, c);
                }
                if c >= 32 {
                    b[r * cols + c] = f(r, c) + 0.5;
                }
            }
        }
        let out = fuse_wavelet(&a, &b, rows, cols, &WaveletFusion::default()).unwrap();
        let mut worst = 0.0f32;
        for r in 0..rows {
            for c in 0..cols - 1 {
                let jump = out[r * cols + c + 1] - out[r * cols + c] - (f(r, c + 1) - f(r, c));
                worst = worst.max(jump.abs());
            }
        }
        // 0.5 um spread over the 48 px overlap is ~0.01 um per px; a step would be 0.25.
        assert!(
            worst < 0.05,
            "largest jump beyond the surface's own slope: {worst}"
        );
    }

    #[test]
    fn names_round_trip() {
        for m in FusionMethod::ALL {
            assert_eq!(FusionMethod::by_name(m.name()), Some(m));
        }
        assert_eq!(FusionMethod::by_name("median"), None);
    }
}
