//! The stage: scan parameters, the serpentine plan, and each tile's true pose.

use rand::Rng;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};
use surfstream_core::raster::Shape;

use crate::error::{invalid, ReplayError, Result};
use crate::rng::{domain, stream};
use crate::specimen::{SpecimenParams, SpecimenSurface, MAX_SIDE_PX};

/// Pixels of interpolation support kept inside the specimen on every side (bicubic: the
/// sample at x needs columns floor(x) - 1 ..= floor(x) + 2).
pub const INTERPOLATION_SUPPORT_PX: usize = 2;

/// Largest tile side in pixels (a 16384^2 tile is 1 GiB of f32).
pub const MAX_TILE_SIDE_PX: usize = 16_384;

/// Largest number of tiles in one scan.
pub const MAX_TILES: usize = 100_000;

/// Parameters of a simulated scan. Every field has a default (a 2 x 2 scan of 1024 px ZeGage
/// fields at 10 % overlap); unknown fields are rejected.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StageParams {
    /// Rows of the tile grid (along y).
    pub rows: usize,
    /// Columns of the tile grid (along x).
    pub cols: usize,
    /// Overlap of neighbouring tiles as a fraction of the tile, in [0, 0.95).
    pub overlap: f64,
    /// Overlap along x (between horizontal neighbours); `overlap` if absent.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub overlap_x: Option<f64>,
    /// Overlap along y (between vertical neighbours); `overlap` if absent.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub overlap_y: Option<f64>,
    /// Tile side in pixels (square tiles).
    pub tile_px: usize,
    /// Tile width in pixels; `tile_px` if absent.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tile_width_px: Option<usize>,
    /// Tile height in pixels; `tile_px` if absent.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tile_height_px: Option<usize>,
    /// Pixel pitch in micrometres (x and y); the specimen must have the same.
    pub pitch_um: f64,
    /// Standard deviation of the stage positioning error per axis, in pixels. Errors are
    /// truncated at the scan margin, `max(8, 5 * stage_sigma_px)`.
    pub stage_sigma_px: f64,
    /// Extra x error in pixels on reversed (odd) serpentine rows.
    pub backlash_px: f64,
    /// Standard deviation of the per-tile piston (constant height offset), in micrometres.
    pub piston_sigma_um: f64,
    /// Standard deviation of the per-tile tilt, as the height change across the tile in x and
    /// in y, in micrometres.
    pub tilt_sigma_um: f64,
    /// Standard deviation of white measurement noise, in micrometres.
    pub noise_um: f64,
    /// Fraction of isolated random pixels that are not measured (NaN), in [0, 1].
    pub dropout_fraction: f64,
    /// Mean number (Poisson) of elliptical NaN blobs per tile.
    pub dropout_blobs_mean: f64,
    /// Range of the blobs' semi-axes in pixels, `[min, max]`.
    pub blob_radius_px: [f64; 2],
    /// Seed of every random quantity of the scan (stage errors, piston, tilt, noise, dropouts).
    pub seed: u64,
}

impl Default for StageParams {
    fn default() -> Self {
        Self {
            rows: 2,
            cols: 2,
            overlap: 0.10,
            overlap_x: None,
            overlap_y: None,
            tile_px: 1024,
            tile_width_px: None,
            tile_height_px: None,
            pitch_um: 0.8148,
            stage_sigma_px: 3.0,
            backlash_px: 0.0,
            piston_sigma_um: 0.5,
            tilt_sigma_um: 0.5,
            noise_um: 0.02,
            dropout_fraction: 0.002,
            dropout_blobs_mean: 2.0,
            blob_radius_px: [2.0, 8.0],
            seed: 1,
        }
    }
}

const SECTION: &str = "stage";

fn check_non_negative(field: &'static str, v: f64) -> Result<()> {
    if v.is_finite() && v >= 0.0 {
        Ok(())
    } else {
        Err(invalid(SECTION, field, v, "a finite number >= 0"))
    }
}

fn check_overlap(field: &'static str, v: f64) -> Result<()> {
    if v.is_finite() && (0.0..0.95).contains(&v) {
        Ok(())
    } else {
        Err(invalid(
            SECTION,
            field,
            v,
            "a fraction of the tile in [0, 0.95)",
        ))
    }
}

fn check_tile_side(field: &'static str, v: usize) -> Result<()> {
    if (1..=MAX_TILE_SIDE_PX).contains(&v) {
        Ok(())
    } else {
        Err(invalid(
            SECTION,
            field,
            v,
            format!("an integer in 1 ..= {MAX_TILE_SIDE_PX}"),
        ))
    }
}

impl StageParams {
    /// Tile (width, height) in pixels, after the optional per-axis overrides.
    pub fn tile_shape_px(&self) -> (usize, usize) {
        (
            self.tile_width_px.unwrap_or(self.tile_px),
            self.tile_height_px.unwrap_or(self.tile_px),
        )
    }

    /// Overlap (x, y) as fractions, after the optional per-axis overrides.
    pub fn overlap_xy(&self) -> (f64, f64) {
        (
            self.overlap_x.unwrap_or(self.overlap),
            self.overlap_y.unwrap_or(self.overlap),
        )
    }

    /// The scan margin: the largest stage error (truncation bound) plus backlash, in pixels.
    pub fn margin_px(&self) -> f64 {
        self.error_bound_px() + self.backlash_px.abs()
    }

    fn error_bound_px(&self) -> f64 {
        (5.0 * self.stage_sigma_px).max(8.0)
    }

    /// Checks every field; the error names the first field out of range.
    pub fn validate(&self) -> Result<()> {
        for (field, v) in [("rows", self.rows), ("cols", self.cols)] {
            if v == 0 {
                return Err(invalid(SECTION, field, v, "an integer >= 1"));
            }
        }
        if self.rows.saturating_mul(self.cols) > MAX_TILES {
            return Err(invalid(
                SECTION,
                "rows",
                format!("{} (x cols = {})", self.rows, self.cols),
                format!("rows * cols <= {MAX_TILES}"),
            ));
        }
        check_overlap("overlap", self.overlap)?;
        if let Some(v) = self.overlap_x {
            check_overlap("overlap_x", v)?;
        }
        if let Some(v) = self.overlap_y {
            check_overlap("overlap_y", v)?;
        }
        check_tile_side("tile_px", self.tile_px)?;
        if let Some(v) = self.tile_width_px {
            check_tile_side("tile_width_px", v)?;
        }
        if let Some(v) = self.tile_height_px {
            check_tile_side("tile_height_px", v)?;
        }
        if !(self.pitch_um.is_finite() && self.pitch_um > 0.0) {
            return Err(invalid(
                SECTION,
                "pitch_um",
                self.pitch_um,
                "a finite number > 0",
            ));
        }
        check_non_negative("stage_sigma_px", self.stage_sigma_px)?;
        if self.stage_sigma_px > 1000.0 {
            return Err(invalid(
                SECTION,
                "stage_sigma_px",
                self.stage_sigma_px,
                "at most 1000 px",
            ));
        }
        if !(self.backlash_px.is_finite() && self.backlash_px.abs() <= 1000.0) {
            return Err(invalid(
                SECTION,
                "backlash_px",
                self.backlash_px,
                "a finite number of pixels in -1000 ..= 1000",
            ));
        }
        check_non_negative("piston_sigma_um", self.piston_sigma_um)?;
        check_non_negative("tilt_sigma_um", self.tilt_sigma_um)?;
        check_non_negative("noise_um", self.noise_um)?;
        for (field, v) in [
            ("piston_sigma_um", self.piston_sigma_um),
            ("tilt_sigma_um", self.tilt_sigma_um),
            ("noise_um", self.noise_um),
        ] {
            if v > crate::specimen::MAX_HEIGHT_PARAM_UM {
                return Err(invalid(
                    SECTION,
                    field,
                    v,
                    format!(
                        "at most {:e} um (heights beyond +-1 m are refused)",
                        crate::specimen::MAX_HEIGHT_PARAM_UM
                    ),
                ));
            }
        }
        if !(self.dropout_fraction.is_finite() && (0.0..=1.0).contains(&self.dropout_fraction)) {
            return Err(invalid(
                SECTION,
                "dropout_fraction",
                self.dropout_fraction,
                "a fraction in [0, 1]",
            ));
        }
        check_non_negative("dropout_blobs_mean", self.dropout_blobs_mean)?;
        if self.dropout_blobs_mean > 1000.0 {
            return Err(invalid(
                SECTION,
                "dropout_blobs_mean",
                self.dropout_blobs_mean,
                "at most 1000 blobs per tile",
            ));
        }
        let [rmin, rmax] = self.blob_radius_px;
        if !(rmin.is_finite() && rmax.is_finite() && rmin > 0.0 && rmin <= rmax && rmax <= 1e4) {
            return Err(invalid(
                SECTION,
                "blob_radius_px",
                format!("[{rmin}, {rmax}]"),
                "[min, max] with 0 < min <= max <= 10000",
            ));
        }
        let (w, h) = self.specimen_shape_px();
        if w > MAX_SIDE_PX || h > MAX_SIDE_PX {
            return Err(ReplayError::TooLarge {
                what: format!("specimen for a {} x {} scan", self.rows, self.cols),
                width_px: w,
                height_px: h,
                limit: format!("at most {MAX_SIDE_PX} px per side"),
            });
        }
        Ok(())
    }

    /// Nominal step between neighbouring tiles (x, y) in pixels.
    fn step_px(&self) -> (f64, f64) {
        let (tw, th) = self.tile_shape_px();
        let (ox, oy) = self.overlap_xy();
        (tw as f64 * (1.0 - ox), th as f64 * (1.0 - oy))
    }

    /// Extent of the nominal grid (x, y) in pixels.
    fn extent_px(&self) -> (f64, f64) {
        let (tw, th) = self.tile_shape_px();
        let (sx, sy) = self.step_px();
        (
            self.cols.saturating_sub(1) as f64 * sx + tw as f64,
            self.rows.saturating_sub(1) as f64 * sy + th as f64,
        )
    }

    /// Specimen (width, height) in pixels: the grid extent plus, on every side, the margin and
    /// the interpolation support.
    fn specimen_shape_px(&self) -> (usize, usize) {
        let (ex, ey) = self.extent_px();
        let border = 2.0 * (self.margin_px() + INTERPOLATION_SUPPORT_PX as f64);
        // f64 -> usize saturates; validation rejects the absurd sizes afterwards.
        ((ex + border).ceil() as usize, (ey + border).ceil() as usize)
    }
}

/// One tile of the plan: where the stage was commanded and where it really went.
///
/// Pixel coordinates are (x, y) = (column, row) of the specimen; micrometres are scan
/// coordinates, `um = px * pitch_um`, with the specimen's pixel (0, 0) at (0, 0) um.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TilePlan {
    /// Acquisition index (0-based, serpentine order).
    pub index: usize,
    /// Grid row (y).
    pub row: usize,
    /// Grid column (x).
    pub col: usize,
    /// Commanded (stage-reported) position of the tile's pixel (0, 0), in specimen pixels.
    pub nominal_origin_px: [f64; 2],
    /// The same in micrometres: what the stage reports.
    pub stage_position_um: [f64; 2],
    /// Where the tile's pixel (0, 0) really is, in specimen pixels (sub-pixel).
    pub true_origin_px: [f64; 2],
    /// The same in micrometres.
    pub true_origin_um: [f64; 2],
    /// Constant height offset added to the tile, in micrometres.
    pub piston_um: f64,
    /// Height change across the tile along x, in micrometres.
    pub tilt_x_um: f64,
    /// Height change across the tile along y, in micrometres.
    pub tilt_y_um: f64,
}

/// A whole scan: geometry, the specimen it needs, and every tile in acquisition order.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ScanPlan {
    /// The (validated) parameters the plan was made from.
    pub params: StageParams,
    /// Tile width in pixels.
    pub tile_width_px: usize,
    /// Tile height in pixels.
    pub tile_height_px: usize,
    /// Nominal step between horizontal neighbours, in pixels.
    pub step_x_px: f64,
    /// Nominal step between vertical neighbours, in pixels.
    pub step_y_px: f64,
    /// Largest stage error plus backlash, in pixels.
    pub margin_px: f64,
    /// Width of the specimen the scan needs, in pixels.
    pub specimen_width_px: usize,
    /// Height of the specimen the scan needs, in pixels.
    pub specimen_height_px: usize,
    /// Tiles in acquisition order (`tiles[k].index == k`).
    pub tiles: Vec<TilePlan>,
}

impl ScanPlan {
    /// `base` with the size and pitch this scan needs.
    pub fn specimen_params(&self, base: &SpecimenParams) -> SpecimenParams {
        SpecimenParams {
            width_px: self.specimen_width_px,
            height_px: self.specimen_height_px,
            pitch_um: self.params.pitch_um,
            ..base.clone()
        }
    }

    /// Checks that `specimen` is large enough for the plan and has its pixel pitch.
    pub fn check_specimen<S: SpecimenSurface + ?Sized>(&self, specimen: &S) -> Result<()> {
        let Shape { rows, cols } = specimen.shape();
        if cols < self.specimen_width_px || rows < self.specimen_height_px {
            return Err(ReplayError::SpecimenMismatch(format!(
                "specimen is {} x {} px, the scan needs at least {} x {} px (rows x cols)",
                rows, cols, self.specimen_height_px, self.specimen_width_px
            )));
        }
        let rel = (specimen.pitch_um() - self.params.pitch_um).abs() / self.params.pitch_um;
        if rel.is_nan() || rel > 1e-9 {
            return Err(ReplayError::SpecimenMismatch(format!(
                "specimen pitch is {} um, the stage's pitch_um is {} um",
                specimen.pitch_um(),
                self.params.pitch_um
            )));
        }
        Ok(())
    }

    /// Index of the tile at (row, col), if inside the grid.
    pub fn index_of(&self, row: usize, col: usize) -> Option<usize> {
        let (rows, cols) = (self.params.rows, self.params.cols);
        if row >= rows || col >= cols {
            return None;
        }
        let c = if row % 2 == 1 { cols - 1 - col } else { col };
        Some(row * cols + c)
    }
}

/// (row, col) of every tile in serpentine acquisition order: row 0 left to right, row 1 right
/// to left, and so on.
pub fn serpentine_order(rows: usize, cols: usize) -> Vec<(usize, usize)> {
    let mut order = Vec::with_capacity(rows.saturating_mul(cols));
    for r in 0..rows {
        if r % 2 == 0 {
            order.extend((0..cols).map(|c| (r, c)));
        } else {
            order.extend((0..cols).rev().map(|c| (r, c)));
        }
    }
    order
}

/// Plans a scan: validates `params`, sizes the specimen (grid extent plus margin and
/// interpolation support on every side, the nominal grid centred) and draws every tile's true
/// pose from a per-tile random stream keyed by (seed, tile index).
pub fn plan_scan(params: &StageParams) -> Result<ScanPlan> {
    params.validate()?;
    let (tw, th) = params.tile_shape_px();
    let (step_x, step_y) = params.step_px();
    let (ext_x, ext_y) = params.extent_px();
    let (sw, sh) = params.specimen_shape_px();
    let gx0 = (sw as f64 - ext_x) / 2.0;
    let gy0 = (sh as f64 - ext_y) / 2.0;
    let bound = params.error_bound_px();
    let pitch = params.pitch_um;
    let tiles = serpentine_order(params.rows, params.cols)
        .into_iter()
        .enumerate()
        .map(|(index, (row, col))| {
            let mut rng = stream(params.seed, domain::TILE_POSE, index as u64);
            let mut normal = || rng.sample::<f64, _>(StandardNormal);
            let ex = (normal() * params.stage_sigma_px).clamp(-bound, bound);
            let ey = (normal() * params.stage_sigma_px).clamp(-bound, bound);
            let piston_um = normal() * params.piston_sigma_um;
            let tilt_x_um = normal() * params.tilt_sigma_um;
            let tilt_y_um = normal() * params.tilt_sigma_um;
            let backlash = if row % 2 == 1 {
                params.backlash_px
            } else {
                0.0
            };
            let nominal = [gx0 + col as f64 * step_x, gy0 + row as f64 * step_y];
            let truth = [nominal[0] + ex + backlash, nominal[1] + ey];
            TilePlan {
                index,
                row,
                col,
                nominal_origin_px: nominal,
                stage_position_um: [nominal[0] * pitch, nominal[1] * pitch],
                true_origin_px: truth,
                true_origin_um: [truth[0] * pitch, truth[1] * pitch],
                piston_um,
                tilt_x_um,
                tilt_y_um,
            }
        })
        .collect();
    Ok(ScanPlan {
        params: params.clone(),
        tile_width_px: tw,
        tile_height_px: th,
        step_x_px: step_x,
        step_y_px: step_y,
        margin_px: params.margin_px(),
        specimen_width_px: sw,
        specimen_height_px: sh,
        tiles,
    })
}
