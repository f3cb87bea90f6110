//! Resampling one tile onto the canvas grid and folding it into the per-pixel accumulators.
//!
//! The canvas grid and a tile share the pitch but not the origin: a tile sits at a sub-pixel
//! offset `o = (x_um - anchor_x_um) / pitch_x_um` (likewise y). Canvas grid column `g` then
//! lies at tile column `u = g - o`. Along each axis the covered canvas pixels are those whose
//! centre falls inside the hull of the tile's pixel centres, `0 <= u <= w - 1`: the panorama
//! never extrapolates a tile beyond its outermost measured pixel centre, so at an offset with
//! a fractional part a tile covers `w - 1` canvas columns instead of `w`.

/// Offsets within this distance (px) of an integer are snapped onto it. A position computed in
/// um and divided by the pitch carries rounding noise of ~1e-12 px; without the snap, a tile
/// that sits exactly on the grid would be needlessly interpolated and lose its last column.
/// 1e-6 px is below a picometre at the reference pitch.
pub(crate) const SNAP_PX: f64 = 1e-6;

/// Largest accepted distance (px) of a tile from the first tile: far beyond any real scan,
/// small enough that grid indices stay exact in f64 and i64.
pub(crate) const MAX_OFFSET_PX: f64 = (1u64 << 40) as f64;

/// Largest accepted blend ramp (px): beyond it the smallest weight, `(0.5 / ramp)^2`, would
/// lose all precision in the f32 weight accumulator.
pub(crate) const MAX_RAMP_PX: f64 = 1.0e6;

/// Where a tile lands along one axis.
#[derive(Debug, Clone)]
pub(crate) struct AxisPlan {
    /// Canvas grid index of the first covered pixel.
    pub start: i64,
    /// Number of covered canvas pixels (0 only for a 1-px tile at a fractional offset).
    pub len: usize,
    /// Covered canvas pixel `i` lies at tile coordinate `i + frac`; `frac` in `[0, 1)`.
    pub frac: f64,
    /// Blend weight of covered canvas pixel `i` (the ramp evaluated at `i + frac`).
    pub weights: Vec<f64>,
}

impl AxisPlan {
    /// `offset_px`: tile origin minus canvas anchor, in pixels (caller checked its range);
    /// `n`: tile pixels along the axis (>= 1); `ramp_px`: blend ramp length.
    pub fn new(offset_px: f64, n: usize, ramp_px: f64) -> Self {
        let nearest = offset_px.round();
        let (start, frac, len) = if (offset_px - nearest).abs() < SNAP_PX {
            (nearest as i64, 0.0, n)
        } else {
            // First grid index strictly right of the origin; it sits `frac` px into the tile.
            let floor = offset_px.floor();
            (floor as i64 + 1, 1.0 - (offset_px - floor), n - 1)
        };
        let last = (n - 1) as f64;
        let weights = (0..len)
            .map(|i| {
                let u = i as f64 + frac;
                ramp_weight(u.min(last - u).max(0.0), ramp_px)
            })
            .collect();
        Self {
            start,
            len,
            frac,
            weights,
        }
    }
}

/// The gradual in-and-out weight of a pixel `distance_px` from the nearer border of its tile:
/// `(d + 0.5) / ramp`, clamped to 1. Never 0 inside the tile, so no measured pixel is lost.
pub(crate) fn ramp_weight(distance_px: f64, ramp_px: f64) -> f64 {
    if ramp_px <= 0.5 {
        // (d + 0.5) / ramp >= 1 everywhere: the plain average, without dividing by ~0.
        1.0
    } else {
        ((distance_px + 0.5) / ramp_px).min(1.0)
    }
}

/// Everything needed to resample one tile, shared read-only by the row workers.
pub(crate) struct Resampler<'a> {
    pub heights: &'a [f32],
    pub width: usize,
    pub height: usize,
    pub x: AxisPlan,
    pub y: AxisPlan,
    /// `-tilt_x * (col - (w-1)/2)` per tile column: the column part of the plane correction.
    pub col_term_um: Vec<f64>,
    /// Piston of the plane correction, um.
    pub piston_um: f64,
    /// Row slope of the plane correction, um/px.
    pub tilt_y_um_per_px: f64,
    /// Tile z offset minus canvas z offset, um: moves the tile's heights into the canvas's z.
    pub dz_um: f64,
}

/// Minimum share of the bilinear weight that must come from measured (non-NaN) tile pixels
/// for a canvas pixel to get a value from the tile. 0.5 keeps the measured area the same size
/// on average: a hole neither grows nor shrinks under resampling, and on the grid (no
/// fractional offset) the rule is an exact copy, NaN for NaN.
pub(crate) const MIN_VALID_SHARE: f64 = 0.5;

impl Resampler<'_> {
    /// `row_term(r) = dz - (piston + tilt_y * (r - (h-1)/2))`: the row part of the correction.
    fn row_term_um(&self, row: usize) -> f64 {
        let centre = (self.height - 1) as f64 / 2.0;
        self.dz_um - (self.piston_um + self.tilt_y_um_per_px * (row as f64 - centre))
    }

    /// Resample covered canvas row `j` (`0..y.len`) and fold it into the accumulators, which
    /// are the `x.len` covered pixels of that canvas row.
    ///
    /// Accumulators: `mean` is the running weighted mean `sum(w z) / sum(w)` and `weight` is
    /// `sum(w)`; `weight == 0` means no tile has data there.
    pub fn blend_row(&self, j: usize, mean: &mut [f32], weight: &mut [f32]) {
        debug_assert_eq!(mean.len(), self.x.len);
        self.blend_span(j, 0, mean, weight)
    }

    /// [`Resampler::blend_row`] for the covered pixels `i0 .. i0 + mean.len()` of row `j`
    /// only: a chunk's part of the row. Every pixel is computed on its own, so blending a row
    /// in spans gives the same bits as blending it whole.
    pub fn blend_span(&self, j: usize, i0: usize, mean: &mut [f32], weight: &mut [f32]) {
        debug_assert!(i0 + mean.len() <= self.x.len);
        debug_assert_eq!(weight.len(), mean.len());
        let w = self.width;
        // With a fractional offset the covered pixels stop one short of the tile's last
        // row/column, so `+ 1` stays inside; on the grid the second corner has weight 0 and
        // is simply the first one again. No clamping in the inner loop.
        let r0 = j;
        let r1 = j + usize::from(self.y.frac > 0.0);
        let row0 = &self.heights[r0 * w..(r0 + 1) * w];
        let row1 = &self.heights[r1 * w..(r1 + 1) * w];
        let (t0, t1) = (self.row_term_um(r0), self.row_term_um(r1));

        // Bilinear corner weights are the same for every pixel of the tile: the offset is.
        let (a0, a1) = (1.0 - self.x.frac, self.x.frac);
        let (b0, b1) = (1.0 - self.y.frac, self.y.frac);
        let (w00, w01, w10, w11) = (b0 * a0, b0 * a1, b1 * a0, b1 * a1);
        // The sum of the weights of four measured corners, accumulated in the same order as
        // `valid` below, so the common all-measured case multiplies instead of dividing.
        let all_valid = ((w00 + w01) + w10) + w11;
        let inv_all_valid = 1.0 / all_valid;
        let wy = self.y.weights[j];
        let ct = &self.col_term_um;
        let dc = usize::from(self.x.frac > 0.0);

        for (k, ((m, acc_w), &wx)) in mean
            .iter_mut()
            .zip(weight.iter_mut())
            .zip(&self.x.weights[i0..])
            .enumerate()
        {
            let c0 = i0 + k;
            let c1 = c0 + dc;
            let mut sum = 0.0f64;
            let mut valid = 0.0f64;
            // NaN corners are skipped, never multiplied: 0 * NaN would poison the sum.
            let z = row0[c0];
            if !z.is_nan() {
                sum += w00 * (z as f64 + ct[c0] + t0);
                valid += w00;
            }
            let z = row0[c1];
            if !z.is_nan() {
                sum += w01 * (z as f64 + ct[c1] + t0);
                valid += w01;
            }
            let z = row1[c0];
            if !z.is_nan() {
                sum += w10 * (z as f64 + ct[c0] + t1);
                valid += w10;
            }
            let z = row1[c1];
            if !z.is_nan() {
                sum += w11 * (z as f64 + ct[c1] + t1);
                valid += w11;
            }
            if valid < MIN_VALID_SHARE {
                continue;
            }
            // Renormalise over the measured corners only.
            let z = if valid == all_valid {
                sum * inv_all_valid
            } else {
                sum / valid
            };
            let w_pix = wx * wy;
            let w_old = *acc_w;
            if w_old > 0.0 {
                // Running weighted mean: algebraically sum(w z) / sum(w), but a constant
                // surface stays exactly constant (z - m == 0) and nothing cancels.
                let w_new = w_old as f64 + w_pix;
                let m_old = *m as f64;
                *m = (m_old + (w_pix / w_new) * (z - m_old)) as f32;
                *acc_w = w_new as f32;
            } else {
                *m = z as f32;
                *acc_w = w_pix as f32;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn on_grid_offset_covers_every_pixel() {
        let p = AxisPlan::new(-3.0, 5, 2.0);
        assert_eq!((p.start, p.len, p.frac), (-3, 5, 0.0));
        // d = 0, 1, 2, 1, 0 -> (d + 0.5) / 2 clamped.
        assert_eq!(p.weights, vec![0.25, 0.75, 1.0, 0.75, 0.25]);
    }

    #[test]
    fn fractional_offset_covers_the_hull_of_centres() {
        let p = AxisPlan::new(2.25, 4, 0.0);
        assert_eq!((p.start, p.len), (3, 3));
        assert!((p.frac - 0.75).abs() < 1e-12);
        assert_eq!(p.weights, vec![1.0; 3]);
        let q = AxisPlan::new(-2.25, 4, 0.0);
        assert_eq!((q.start, q.len), (-2, 3));
        assert!((q.frac - 0.25).abs() < 1e-12);
    }

    #[test]
    fn near_integer_offsets_snap() {
        let p = AxisPlan::new(7.0 - 1e-9, 4, 1.0);
        assert_eq!((p.start, p.len, p.frac), (7, 4, 0.0));
        let q = AxisPlan::new(-7.0 + 1e-9, 4, 1.0);
        assert_eq!((q.start, q.len, q.frac), (-7, 4, 0.0));
    }

    #[test]
    fn ramp_weight_is_positive_and_clamped() {
        assert_eq!(ramp_weight(0.0, 10.0), 0.05);
        assert_eq!(ramp_weight(9.5, 10.0), 1.0);
        assert_eq!(ramp_weight(100.0, 10.0), 1.0);
        assert_eq!(ramp_weight(0.0, 0.0), 1.0);
    }
}
