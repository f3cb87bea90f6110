//! The mesher's input: a height field is a [`RasterView`] of `f32` heights (the payload of a
//! frame, DESIGN §2) placed in scan coordinates by a [`ScanPlacement`]; and the filling of
//! missing samples.

use std::borrow::Cow;

use surfstream_core::frame::FrameHeader;
use surfstream_core::raster::RasterView;
use surfstream_core::{ParamError, Pitch, Sampling};

use crate::error::{MeshError, Result};

/// Where the samples of a height field sit in scan coordinates; the samples themselves and the
/// grid's size are a [`RasterView`] (`rows x cols`, row-major `f32` heights in micrometres
/// relative to `z_offset_um`, NaN = not measured).
///
/// Scan coordinates (DESIGN §2): sample (row `i`, column `j`) sits at
/// `x = origin_x_um + j * pitch_x_um`, `y = origin_y_um + i * pitch_y_um`,
/// `z = z_offset_um + heights[(i, j)]`. Row index grows with y, column index with x.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScanPlacement {
    /// Sample spacing along x (columns) and y (rows), checked when made; the shape is the
    /// [`RasterView`]'s.
    pub pitch: Pitch,
    /// Scan x of sample (0, 0), um.
    pub origin_x_um: f64,
    /// Scan y of sample (0, 0), um.
    pub origin_y_um: f64,
    /// Height that the raster's heights are relative to, um.
    pub z_offset_um: f64,
}

impl ScanPlacement {
    /// Sample (0, 0) at the scan origin and heights relative to z = 0.
    pub fn new(pitch: Pitch) -> Self {
        Self {
            pitch,
            origin_x_um: 0.0,
            origin_y_um: 0.0,
            z_offset_um: 0.0,
        }
    }

    /// The placement a frame header carries; its pitch checked by [`FrameHeader::pitch`].
    pub fn of_frame(h: &FrameHeader) -> std::result::Result<Self, ParamError> {
        Ok(Self {
            pitch: h.pitch()?,
            origin_x_um: h.origin_x_um,
            origin_y_um: h.origin_y_um,
            z_offset_um: h.z_offset_um,
        })
    }

    /// The same placement with sample (0, 0) at (`origin_x_um`, `origin_y_um`).
    pub fn with_origin(mut self, origin_x_um: f64, origin_y_um: f64) -> Self {
        self.origin_x_um = origin_x_um;
        self.origin_y_um = origin_y_um;
        self
    }

    /// The same placement with heights relative to `z_offset_um`.
    pub fn with_z_offset(mut self, z_offset_um: f64) -> Self {
        self.z_offset_um = z_offset_um;
        self
    }
}

/// Checks the geometry of a field to mesh: at least 2 x 2 samples, finite positive pitches,
/// finite origin and z offset. The heights themselves are checked by [`fill_missing`].
pub(crate) fn validate(heights: RasterView<'_, f32>, at: &ScanPlacement) -> Result<()> {
    let (rows, cols) = (heights.rows(), heights.cols());
    if rows < 2 || cols < 2 {
        return Err(MeshError::TooSmall { rows, cols });
    }
    // The pitch is a checked Pitch (a non-positive one would mirror the grid and invert every
    // triangle's winding); the origin is checked here.
    Sampling::of(heights.shape(), at.pitch).with_origin(at.origin_x_um, at.origin_y_um)?;
    finite("z_offset_um", at.z_offset_um)?;
    Ok(())
}

pub(crate) fn positive_finite(name: &'static str, value: f64) -> Result<()> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        Err(MeshError::from(ParamError::new(
            name,
            value,
            "a finite number > 0",
        )))
    }
}

pub(crate) fn finite(name: &'static str, value: f64) -> Result<()> {
    if value.is_finite() {
        Ok(())
    } else {
        Err(MeshError::from(ParamError::new(
            name,
            value,
            "a finite number",
        )))
    }
}

/// Replaces every NaN (missing) sample, returning the complete heights and how many samples were
/// filled. Borrows the input when nothing is missing.
///
/// Rule ("onion peel"): in rounds, every missing sample that has at least one valid sample
/// among its 8 neighbours takes the mean of those valid neighbours; samples filled in a round
/// count as valid only from the next round on, so the result does not depend on scan order.
/// A hole therefore closes from its rim inwards with a smooth, bounded fill (never outside the
/// range of the measured heights), without the streaks that copying along rows would leave.
///
/// Errors: a sample that is +/-infinity (corrupt input, not "missing"), or no valid sample at
/// all.
pub fn fill_missing(heights: RasterView<'_, f32>) -> Result<(Cow<'_, [f32]>, usize)> {
    let (rows, cols) = (heights.rows(), heights.cols());
    let heights_um = heights.values();
    let mut missing = 0usize;
    for (k, &h) in heights_um.iter().enumerate() {
        if h.is_nan() {
            missing += 1;
        } else if h.is_infinite() {
            return Err(MeshError::InfiniteSample {
                row: k / cols,
                col: k % cols,
                value: h,
            });
        }
    }
    if missing == 0 {
        return Ok((Cow::Borrowed(heights_um), 0));
    }
    if missing == heights_um.len() {
        return Err(MeshError::NoValidSample {
            samples: heights_um.len(),
        });
    }

    const MISSING: u8 = 0;
    const VALID: u8 = 1;
    const QUEUED: u8 = 2;
    let mut out = heights_um.to_vec();
    let mut state: Vec<u8> = heights_um
        .iter()
        .map(|h| if h.is_nan() { MISSING } else { VALID })
        .collect();

    // Calls `f` with the index of every in-bounds 8-neighbour of sample k.
    let neighbours = |k: usize, f: &mut dyn FnMut(usize)| {
        let (i, j) = (k / cols, k % cols);
        for ni in i.saturating_sub(1)..=(i + 1).min(rows - 1) {
            for nj in j.saturating_sub(1)..=(j + 1).min(cols - 1) {
                if ni != i || nj != j {
                    f(ni * cols + nj);
                }
            }
        }
    };

    let mut frontier: Vec<usize> = Vec::new();
    for k in 0..out.len() {
        if state[k] == MISSING {
            let mut touches_valid = false;
            neighbours(k, &mut |n| touches_valid |= state[n] == VALID);
            if touches_valid {
                state[k] = QUEUED;
                frontier.push(k);
            }
        }
    }
    let mut values: Vec<f32> = Vec::new();
    let mut filled = 0usize;
    while !frontier.is_empty() {
        values.clear();
        for &k in &frontier {
            let (mut sum, mut count) = (0.0f64, 0u32);
            neighbours(k, &mut |n| {
                if state[n] == VALID {
                    sum += f64::from(out[n]);
                    count += 1;
                }
            });
            // Every queued sample touches a valid one: it was queued next to one that is valid
            // now (either from the start or filled in the previous round).
            values.push((sum / f64::from(count.max(1))) as f32);
        }
        for (&k, &v) in frontier.iter().zip(&values) {
            out[k] = v;
            state[k] = VALID;
        }
        filled += frontier.len();
        let mut next = Vec::new();
        for &k in &frontier {
            neighbours(k, &mut |n| {
                if state[n] == MISSING {
                    state[n] = QUEUED;
                    next.push(n);
                }
            });
        }
        frontier = next;
    }
    // The grid is connected and holds a valid sample, so the rounds reach every missing one.
    debug_assert_eq!(filled, missing);
    Ok((Cow::Owned(out), filled))
}

#[cfg(test)]
mod tests {
    use super::*;
    use surfstream_core::raster::Shape;

    fn view(h: &[f32], rows: usize, cols: usize) -> RasterView<'_, f32> {
        RasterView::new(h, Shape::new(rows, cols)).unwrap()
    }

    #[test]
    fn fills_a_hole_from_its_rim() {
        #[rustfmt::skip]
        let h = [
            1.0, 1.0, 1.0, 1.0,
            1.0, f32::NAN, f32::NAN, 3.0,
            1.0, 1.0, 1.0, 3.0,
        ];
        let (out, filled) = fill_missing(view(&h, 3, 4)).unwrap();
        assert_eq!(filled, 2);
        // Both holes see only measured neighbours in round one.
        assert!((out[5] - 1.0).abs() < 1e-6);
        assert!((out[6] - (1.0 + 1.0 + 1.0 + 3.0 + 1.0 + 1.0 + 3.0) / 7.0).abs() < 1e-6);
    }

    #[test]
    fn fills_far_from_the_only_sample() {
        let mut h = vec![f32::NAN; 25];
        h[0] = 4.5;
        let (out, filled) = fill_missing(view(&h, 5, 5)).unwrap();
        assert_eq!(filled, 24);
        assert!(out.iter().all(|&v| v == 4.5));
    }

    #[test]
    fn borrows_when_complete_and_refuses_infinity() {
        let h = [0.0f32; 4];
        let (out, filled) = fill_missing(view(&h, 2, 2)).unwrap();
        assert!(matches!(out, Cow::Borrowed(_)));
        assert_eq!(filled, 0);
        let h = [0.0, 0.0, f32::INFINITY, 0.0];
        assert!(matches!(
            fill_missing(view(&h, 2, 2)),
            Err(MeshError::InfiniteSample { row: 1, col: 0, .. })
        ));
    }
}
