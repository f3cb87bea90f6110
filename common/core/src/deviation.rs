//! The model-vs-measurement deviation of the reference study's Table 6, over in-memory
//! surfaces: no files, no JSON.
//!
//! A measured surface (the fused panorama) is compared with model stages, each on its own grid
//! ([`ModelStage`]): datum + roughness on the panorama grid, the pooled map and the mesh
//! re-sampled on the grid it meshed at their own, coarser pitch (one model cell = `cell_px` x
//! `cell_px` panorama pixels). A pooled map is never blown back up to the panorama grid: that
//! would add steps that are not in the model and bias the slope parameters (Sdq, Sdr).
//! Regions are rectangles of the panorama (each tile's footprint, [`Region::tile_footprint`],
//! and the whole map); on a coarse grid a region covers the cells its pixels fall in.
//! Per region and stage: the nine ISO 25178 parameters ([`metrology::params`], mean removed,
//! no levelling) of both, each over the points valid in both maps (holes are not deviation: a
//! panorama pixel counts when its model cell is valid, a model cell when at least one of its
//! pixels in the region is); relative deviation = (model - measured) / measured in %; the stage
//! passes a region when |deviation| <= the threshold for Sa, Sq and Sz ([`JUDGED`]). Slope
//! parameters of a coarser model differ by construction (the slopes are taken over a longer
//! base): reported, not judged.

use rayon::prelude::*;

use crate::metrology::{self, Grid, Params, ParamsByRows};
use crate::raster::{Raster, RasterView, Shape};
use crate::Pitch;

/// The parameters Table 6 judges.
pub const JUDGED: [&str; 3] = ["Sa", "Sq", "Sz"];

/// Why Table 6 could not be judged.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DeviationError {
    #[error("stage {stage}: model is {model} (rows x cols), the measured surface {measured}")]
    StageShape {
        stage: String,
        model: Shape,
        measured: Shape,
    },
    #[error("region {region} ({rows} x {cols} at row {row0}, col {col0}) leaves the {measured} measured surface")]
    RegionOutside {
        region: String,
        row0: usize,
        col0: usize,
        rows: usize,
        cols: usize,
        measured: Shape,
    },
    #[error("pooled map {pooled} is not a whole-factor pooling of the {target} panorama")]
    NotAPooling { pooled: Shape, target: Shape },
    #[error("stage {stage}: model is {model} (rows x cols) with {cell_px} x {cell_px} px cells, expected {expected} for the {measured} measured surface")]
    StageGrid {
        stage: String,
        model: Shape,
        cell_px: usize,
        expected: Shape,
        measured: Shape,
    },
    #[error("{0}")]
    Read(String),
}

/// A rectangle of the measured grid, pixels, end exclusive.
#[derive(Debug, Clone, PartialEq)]
pub struct Region {
    pub name: String,
    pub row0: usize,
    pub col0: usize,
    pub rows: usize,
    pub cols: usize,
}

/// Table 6's tile regions: the k-th tile (in index order) that has a position is "S<k+1>",
/// its footprint on the panorama ([`Region::tile_footprint`]; tiles without a position keep
/// their number); none without a finite panorama origin. `tiles`: pixel (0, 0) of each tile
/// (um) and its size. The launcher's Table 6 and the mesher's tolerance search both take
/// their tile regions from here, so the two judge the same rectangles under the same names.
pub fn tile_regions(
    tiles: impl IntoIterator<Item = Option<((f64, f64), Shape)>>,
    panorama_origin_um: (f64, f64),
    pitch: Pitch,
    panorama: Shape,
) -> Vec<Region> {
    if !(panorama_origin_um.0.is_finite() && panorama_origin_um.1.is_finite()) {
        return Vec::new();
    }
    tiles
        .into_iter()
        .enumerate()
        .filter_map(|(k, t)| {
            let (origin, tile) = t?;
            Region::tile_footprint(
                format!("S{}", k + 1),
                origin,
                panorama_origin_um,
                pitch,
                tile,
                panorama,
            )
        })
        .collect()
}

impl Region {
    /// The whole surface, named "panorama".
    pub fn whole(shape: Shape) -> Self {
        Self {
            name: "panorama".into(),
            row0: 0,
            col0: 0,
            rows: shape.rows,
            cols: shape.cols,
        }
    }

    /// A tile's footprint on the panorama grid from its final position (um, pixel (0, 0)),
    /// the panorama's origin and pitch (um), clipped to the panorama; `None` when it starts
    /// outside.
    pub fn tile_footprint(
        name: String,
        tile_origin_um: (f64, f64),
        panorama_origin_um: (f64, f64),
        pitch: Pitch,
        tile: Shape,
        panorama: Shape,
    ) -> Option<Self> {
        let col0 = ((tile_origin_um.0 - panorama_origin_um.0) / pitch.x_um())
            .round()
            .max(0.0) as usize;
        let row0 = ((tile_origin_um.1 - panorama_origin_um.1) / pitch.y_um())
            .round()
            .max(0.0) as usize;
        if col0 >= panorama.cols || row0 >= panorama.rows {
            return None;
        }
        Some(Self {
            name,
            row0,
            col0,
            rows: tile.rows.min(panorama.rows - row0),
            cols: tile.cols.min(panorama.cols - col0),
        })
    }

    fn fits(&self, shape: Shape) -> bool {
        self.row0
            .checked_add(self.rows)
            .is_some_and(|end| end <= shape.rows)
            && self
                .col0
                .checked_add(self.cols)
                .is_some_and(|end| end <= shape.cols)
    }

    /// The cells of a grid with `cell_px` x `cell_px` px cells (of `model` shape) that this
    /// region's pixels fall in: (row0, col0, rows, cols).
    fn on_cells(&self, cell_px: usize, model: Shape) -> (usize, usize, usize, usize) {
        let r0 = (self.row0 / cell_px).min(model.rows);
        let c0 = (self.col0 / cell_px).min(model.cols);
        let r1 = (self.row0 + self.rows).div_ceil(cell_px).min(model.rows);
        let c1 = (self.col0 + self.cols).div_ceil(cell_px).min(model.cols);
        (r0, c0, r1 - r0, c1 - c0)
    }

    /// The measured heights of this region where the model cell over them is valid (NaN
    /// elsewhere), and the model cells of the region where at least one of their measured
    /// pixels in the region is valid (NaN elsewhere), with the cells' (rows, cols).
    fn crop_both(
        &self,
        measured: RasterView<f64>,
        model: RasterView<f64>,
        cell_px: usize,
    ) -> (Vec<f64>, Vec<f64>, (usize, usize)) {
        let (r0, c0, rows, cols) = self.on_cells(cell_px, model.shape());
        let mut seen = vec![false; rows * cols];
        let mut m = Vec::with_capacity(self.rows * self.cols);
        for row in self.row0..self.row0 + self.rows {
            let model_row = model.row(row / cell_px);
            for (col, &v) in measured.row(row)[self.col0..self.col0 + self.cols]
                .iter()
                .enumerate()
                .map(|(k, v)| (self.col0 + k, v))
            {
                let cell = model_row[col / cell_px];
                if cell.is_nan() || v.is_nan() {
                    m.push(f64::NAN);
                } else {
                    m.push(v);
                    seen[(row / cell_px - r0) * cols + col / cell_px - c0] = true;
                }
            }
        }
        let mut z = Vec::with_capacity(rows * cols);
        for r in 0..rows {
            let src = &model.row(r0 + r)[c0..c0 + cols];
            z.extend(
                src.iter()
                    .zip(&seen[r * cols..(r + 1) * cols])
                    .map(|(&v, &s)| if s { v } else { f64::NAN }),
            );
        }
        (m, z, (rows, cols))
    }
}

/// One model stage on its own grid: one cell covers `cell_px` x `cell_px` pixels of the
/// measured grid (1 = the measured grid itself), so its shape is the measured shape divided by
/// `cell_px`, rounded up, and its pitch `cell_px` times the measured pitch.
#[derive(Debug, Clone, Copy)]
pub struct ModelStage<'a> {
    pub name: &'a str,
    pub heights_um: RasterView<'a, f64>,
    pub cell_px: usize,
}

impl<'a> ModelStage<'a> {
    /// A stage on the measured grid.
    pub fn on_measured_grid(name: &'a str, heights_um: RasterView<'a, f64>) -> Self {
        Self {
            name,
            heights_um,
            cell_px: 1,
        }
    }

    /// A stage on a coarser grid whose cell size is read from the column counts (what a
    /// whole-factor pooling of `measured` gives); [`Table6::judge`] checks the rows.
    pub fn pooled(name: &'a str, heights_um: RasterView<'a, f64>, measured: Shape) -> Self {
        let cell_px = measured.cols.div_ceil(heights_um.cols().max(1)).max(1);
        Self {
            name,
            heights_um,
            cell_px,
        }
    }

    /// The grid the stage is judged on, for the report.
    pub fn expected_shape(cell_px: usize, measured: Shape) -> Shape {
        Shape {
            rows: measured.rows.div_ceil(cell_px.max(1)),
            cols: measured.cols.div_ceil(cell_px.max(1)),
        }
    }
}

/// The measured surface: heights (um, NaN = not measured) and pitch.
#[derive(Debug, Clone, Copy)]
pub struct Measured<'a> {
    pub heights_um: RasterView<'a, f64>,
    pub pitch_x_um: f64,
    pub pitch_y_um: f64,
}

/// One stage in one region.
#[derive(Debug, Clone, PartialEq)]
pub struct RegionVerdict {
    pub region: String,
    /// `None` when no point is valid in both maps (or the pitch is unusable).
    pub measured: Option<Params>,
    pub model: Option<Params>,
    /// (parameter, (model - measured) / measured * 100), `None` where not finite; empty
    /// when either side has no parameters.
    pub deviation_pct: Vec<(&'static str, Option<f64>)>,
    pub pass: bool,
}

/// One stage over every region.
#[derive(Debug, Clone, PartialEq)]
pub struct StageVerdict {
    pub stage: String,
    /// The grid the stage was judged on: its shape and pixels of the measured grid per cell.
    pub grid: Shape,
    pub cell_px: usize,
    pub regions: Vec<RegionVerdict>,
    pub pass: bool,
}

/// Table 6: every stage judged in every region.
#[derive(Debug, Clone, PartialEq)]
pub struct Table6 {
    pub threshold_pct: f64,
    pub stages: Vec<StageVerdict>,
    /// Every stage passes (true with no stage).
    pub pass: bool,
}

impl Table6 {
    /// Judges each model stage, on its own grid, against `measured` in `regions` at
    /// `threshold_pct`. A model's shape must be the measured shape divided by its `cell_px`
    /// (rounded up) and regions must lie inside the measured surface.
    ///
    /// The in-memory definition, kept as the test oracle: the launcher judges through
    /// [`Table6::judge_streamed`], which the tests hold to this bit for bit.
    pub fn judge(
        measured: Measured,
        stages: &[ModelStage],
        regions: &[Region],
        threshold_pct: f64,
    ) -> Result<Self, DeviationError> {
        let shape = measured.heights_um.shape();
        check_regions(regions, shape)?;
        let stages = stages
            .iter()
            .map(|stage| judge_stage(&measured, stage, regions, threshold_pct))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Self {
            threshold_pct,
            pass: stages.iter().all(|s| s.pass),
            stages,
        })
    }
}

/// Every region lies inside the measured surface.
fn check_regions(regions: &[Region], measured: Shape) -> Result<(), DeviationError> {
    match regions.iter().find(|r| !r.fits(measured)) {
        Some(r) => Err(DeviationError::RegionOutside {
            region: r.name.clone(),
            row0: r.row0,
            col0: r.col0,
            rows: r.rows,
            cols: r.cols,
            measured,
        }),
        None => Ok(()),
    }
}

/// A stage's grid is the measured grid divided by its cell (rounded up); a stage at the
/// measured pitch has the measured shape.
fn check_stage_grid(
    stage: &str,
    cell_px: usize,
    model: Shape,
    measured: Shape,
) -> Result<(), DeviationError> {
    if cell_px <= 1 && model != measured {
        return Err(DeviationError::StageShape {
            stage: stage.to_string(),
            model,
            measured,
        });
    }
    let expected = ModelStage::expected_shape(cell_px, measured);
    if model != expected {
        return Err(DeviationError::StageGrid {
            stage: stage.to_string(),
            model,
            cell_px,
            expected,
            measured,
        });
    }
    Ok(())
}

fn judge_stage(
    m: &Measured,
    stage: &ModelStage,
    regions: &[Region],
    threshold_pct: f64,
) -> Result<StageVerdict, DeviationError> {
    let model = stage.heights_um.shape();
    check_stage_grid(stage.name, stage.cell_px, model, m.heights_um.shape())?;
    let regions: Vec<RegionVerdict> = regions
        .iter()
        .map(|r| judge_region(m, stage, r, threshold_pct))
        .collect();
    Ok(StageVerdict {
        stage: stage.name.to_string(),
        grid: model,
        cell_px: stage.cell_px.max(1),
        pass: regions.iter().all(|r| r.pass),
        regions,
    })
}

fn judge_region(m: &Measured, stage: &ModelStage, r: &Region, threshold_pct: f64) -> RegionVerdict {
    let cell = stage.cell_px.max(1);
    let params_of = |z: &[f64], rows: usize, cols: usize, f: usize| -> Option<Params> {
        let (px, py) = (m.pitch_x_um * f as f64, m.pitch_y_um * f as f64);
        metrology::params(&Grid::new(z, rows, cols, px, py).ok()?).ok()
    };
    // Both over the points valid in both maps, so holes do not count as deviation; each at
    // its own pitch.
    let (zm, zs, (rows, cols)) = r.crop_both(m.heights_um, stage.heights_um, cell);
    let measured = params_of(&zm, r.rows, r.cols, 1);
    let modelled = params_of(&zs, rows, cols, cell);
    region_verdict(r.name.clone(), measured, modelled, threshold_pct)
}

/// The deviations of one region and whether the stage passes it.
fn region_verdict(
    region: String,
    measured: Option<Params>,
    modelled: Option<Params>,
    threshold_pct: f64,
) -> RegionVerdict {
    let mut deviation_pct = Vec::new();
    let mut pass = measured.is_some() && modelled.is_some();
    if let (Some(a), Some(b)) = (&measured, &modelled) {
        for ((name, va), (_, vb)) in a.named().iter().zip(b.named()) {
            let d = (vb - va) / va * 100.0;
            deviation_pct.push((*name, d.is_finite().then_some(d)));
            if JUDGED.contains(name) && !(d.is_finite() && d.abs() <= threshold_pct) {
                pass = false;
            }
        }
    }
    RegionVerdict {
        region,
        measured,
        model: modelled,
        deviation_pct,
        pass,
    }
}

/// Nearest re-sampling of a pooled map (each cell pooled `factor` x `factor` pixels, the
/// factor read from the column counts) back onto the `target` grid.
pub fn unpool(pooled: RasterView<f64>, target: Shape) -> Result<Raster<f64>, DeviationError> {
    let p = pooled.shape();
    let factor = target.cols.div_ceil(p.cols.max(1)).max(1);
    if target.cols.div_ceil(factor) != p.cols || target.rows.div_ceil(factor) != p.rows {
        return Err(DeviationError::NotAPooling { pooled: p, target });
    }
    let mut out = Vec::with_capacity(target.len());
    for r in 0..target.rows {
        let src = pooled.row(r / factor);
        out.extend((0..target.cols).map(|c| src[c / factor]));
    }
    Raster::new(out, target).map_err(|_| DeviationError::NotAPooling { pooled: p, target })
}

// ---------------------------------------------------------------------------------------------
// Table 6 from rasters read by rows (issue 17): nothing larger than a band of rows is held.

/// A raster read by whole rows on demand (a file; or memory, [`RasterRows`]).
pub trait RowSource: Send {
    fn shape(&self) -> Shape;
    /// Rows `row0 .. row0 + rows` into `out` (cleared first), row-major.
    fn read_rows(&mut self, row0: usize, rows: usize, out: &mut Vec<f64>) -> Result<(), String>;
}

/// An in-memory raster as a [`RowSource`].
pub struct RasterRows<'a>(pub RasterView<'a, f64>);

impl RowSource for RasterRows<'_> {
    fn shape(&self) -> Shape {
        self.0.shape()
    }
    fn read_rows(&mut self, row0: usize, rows: usize, out: &mut Vec<f64>) -> Result<(), String> {
        let cols = self.0.cols();
        let v = self
            .0
            .values()
            .get(row0 * cols..(row0 + rows) * cols)
            .ok_or_else(|| format!("rows {row0}..{} outside {}", row0 + rows, self.0.shape()))?;
        out.clear();
        out.extend_from_slice(v);
        Ok(())
    }
}

/// A model stage read by rows ([`ModelStage`]'s streamed counterpart).
pub struct StreamedStage<'a> {
    pub name: &'a str,
    pub heights_um: Box<dyn RowSource + 'a>,
    pub cell_px: usize,
}

impl<'a> StreamedStage<'a> {
    /// A stage on the measured grid.
    pub fn on_measured_grid(name: &'a str, heights_um: Box<dyn RowSource + 'a>) -> Self {
        Self {
            name,
            heights_um,
            cell_px: 1,
        }
    }

    /// A stage on a coarser grid, the cell size read from the column counts as
    /// [`ModelStage::pooled`] does.
    pub fn pooled(name: &'a str, heights_um: Box<dyn RowSource + 'a>, measured: Shape) -> Self {
        let cell_px = measured
            .cols
            .div_ceil(heights_um.shape().cols.max(1))
            .max(1);
        Self {
            name,
            heights_um,
            cell_px,
        }
    }
}

/// Measured rows read per band (both passes read every file twice, band by band).
const BAND_ROWS: usize = 64;

/// One stage in one region while the rows stream by: the masked measured rows and the masked
/// model rows (exactly [`Region::crop_both`]'s) go into two [`ParamsByRows`].
struct RegionStream {
    stage: usize,
    region: usize,
    cell: usize,
    /// The region's cells on the model grid: first row, first column, columns.
    cells: (usize, usize, usize),
    measured: Option<ParamsByRows>,
    model: Option<ParamsByRows>,
    seen: Vec<bool>,
    m_row: Vec<f64>,
    z_row: Vec<f64>,
}

impl RegionStream {
    /// Feeds the rows of `band` (measured rows `b0..`, model rows from `model_row0`) that lie
    /// in `r`; `second` = the second pass.
    fn feed(
        &mut self,
        r: &Region,
        measured: &[f64],
        (b0, cols): (usize, usize),
        model: &[f64],
        (model_row0, model_cols): (usize, usize),
        second: bool,
    ) {
        let band_rows = measured.len() / cols.max(1);
        let (lo, hi) = (b0.max(r.row0), (b0 + band_rows).min(r.row0 + r.rows));
        let (_, c0, n_cells) = self.cells;
        let cell = self.cell;
        for row in lo..hi {
            let src = &measured[(row - b0) * cols..][r.col0..r.col0 + r.cols];
            let cell_row = row / cell;
            let model_row = &model[(cell_row - model_row0) * model_cols..][..model_cols];
            self.m_row.clear();
            for (k, &v) in src.iter().enumerate() {
                let col = r.col0 + k;
                if model_row[col / cell].is_nan() || v.is_nan() {
                    self.m_row.push(f64::NAN);
                } else {
                    self.m_row.push(v);
                    self.seen[col / cell - c0] = true;
                }
            }
            push(&mut self.measured, &self.m_row, second);
            // The model row is complete after the region's last pixel row in this cell row.
            if row + 1 == (cell_row + 1) * cell || row + 1 == r.row0 + r.rows {
                self.z_row.clear();
                self.z_row.extend(
                    model_row[c0..c0 + n_cells]
                        .iter()
                        .zip(&self.seen)
                        .map(|(&v, &s)| if s { v } else { f64::NAN }),
                );
                self.seen.iter_mut().for_each(|s| *s = false);
                push(&mut self.model, &self.z_row, second);
            }
        }
    }
}

/// One row into a parameter stream (`None` = unusable pitch: the parameters are `None`, as
/// [`Grid::new`] failing makes them in [`Table6::judge`]).
fn push(p: &mut Option<ParamsByRows>, row: &[f64], second: bool) {
    if let Some(acc) = p {
        // The width is the stream's own by construction: a shape error cannot happen.
        let ok = if second {
            acc.push_second(row)
        } else {
            acc.push_first(row)
        };
        if ok.is_err() {
            *p = None;
        }
    }
}

impl Table6 {
    /// [`Table6::judge`] over rasters read by rows: the same table, bit for bit, holding one
    /// band of rows of every map at a time (each map is read twice: the parameters take two
    /// passes).
    pub fn judge_streamed(
        measured: &mut dyn RowSource,
        pitch: Pitch,
        stages: &mut [StreamedStage],
        regions: &[Region],
        threshold_pct: f64,
    ) -> Result<Self, DeviationError> {
        let shape = measured.shape();
        check_regions(regions, shape)?;
        // The same checks, in the same order, as judge_stage.
        for stage in stages.iter() {
            check_stage_grid(stage.name, stage.cell_px, stage.heights_um.shape(), shape)?;
        }
        let (px, py) = (pitch.x_um(), pitch.y_um());
        let mut streams: Vec<RegionStream> = Vec::new();
        for (s, stage) in stages.iter().enumerate() {
            let cell = stage.cell_px.max(1);
            for (k, r) in regions.iter().enumerate() {
                let (r0, c0, _, cols) = r.on_cells(cell, stage.heights_um.shape());
                streams.push(RegionStream {
                    stage: s,
                    region: k,
                    cell,
                    cells: (r0, c0, cols),
                    measured: ParamsByRows::new(r.cols, px, py).ok(),
                    model: ParamsByRows::new(cols, px * cell as f64, py * cell as f64).ok(),
                    seen: vec![false; cols],
                    m_row: Vec::with_capacity(r.cols),
                    z_row: Vec::with_capacity(cols),
                });
            }
        }
        let mut band = Vec::new();
        let mut model_bands: Vec<Vec<f64>> = vec![Vec::new(); stages.len()];
        for second in [false, true] {
            let mut b0 = 0;
            while b0 < shape.rows {
                let n = BAND_ROWS.min(shape.rows - b0);
                measured
                    .read_rows(b0, n, &mut band)
                    .map_err(DeviationError::Read)?;
                let mut model_at = Vec::with_capacity(stages.len());
                for (stage, buf) in stages.iter_mut().zip(&mut model_bands) {
                    let cell = stage.cell_px.max(1);
                    let (m0, m1) = (b0 / cell, (b0 + n - 1) / cell + 1);
                    stage
                        .heights_um
                        .read_rows(m0, m1 - m0, buf)
                        .map_err(DeviationError::Read)?;
                    model_at.push((m0, stage.heights_um.shape().cols));
                }
                streams.par_iter_mut().for_each(|t| {
                    t.feed(
                        &regions[t.region],
                        &band,
                        (b0, shape.cols),
                        &model_bands[t.stage],
                        model_at[t.stage],
                        second,
                    )
                });
                b0 += n;
            }
            if !second {
                for t in &mut streams {
                    for p in [&mut t.measured, &mut t.model].into_iter().flatten() {
                        p.end_first();
                    }
                }
            }
        }
        let mut verdicts: Vec<Vec<RegionVerdict>> = vec![Vec::new(); stages.len()];
        for t in streams {
            let measured = t.measured.and_then(|p| p.finish().ok());
            let model = t.model.and_then(|p| p.finish().ok());
            verdicts[t.stage].push(region_verdict(
                regions[t.region].name.clone(),
                measured,
                model,
                threshold_pct,
            ));
        }
        let stages: Vec<StageVerdict> = stages
            .iter()
            .zip(verdicts)
            .map(|(stage, regions)| StageVerdict {
                stage: stage.name.to_string(),
                grid: stage.heights_um.shape(),
                cell_px: stage.cell_px.max(1),
                pass: regions.iter().all(|r| r.pass),
                regions,
            })
            .collect();
        Ok(Self {
            threshold_pct,
            pass: stages.iter().all(|s| s.pass),
            stages,
        })
    }
}

/// The pointwise residual of a model on the measured grid (same shape), per region: the RMS
/// of (model - its mean) - (measured - its mean) over the points valid in both, in percent of
/// the measured Sq there (`None`: no valid point or a flat region). What Sa, Sq and Sz do not
/// show: a model can match them while departing point by point. Reads both sources twice, a
/// band of rows at a time.
pub fn residual_pct_of_sq(
    measured: &mut dyn RowSource,
    model: &mut dyn RowSource,
    regions: &[Region],
) -> Result<Vec<Option<f64>>, DeviationError> {
    let shape = measured.shape();
    if model.shape() != shape {
        return Err(DeviationError::StageShape {
            stage: "residual".into(),
            model: model.shape(),
            measured: shape,
        });
    }
    // Per region: n, sum z, sum m, then sum (dz)^2, sum (dm - dz)^2.
    let mut acc = vec![[0.0f64; 5]; regions.len()];
    let (mut zb, mut mb) = (Vec::new(), Vec::new());
    for second in [false, true] {
        let means: Vec<(f64, f64)> = acc
            .iter()
            .map(|a| (a[1] / a[0].max(1.0), a[2] / a[0].max(1.0)))
            .collect();
        let mut b0 = 0;
        while b0 < shape.rows {
            let n = BAND_ROWS.min(shape.rows - b0);
            measured
                .read_rows(b0, n, &mut zb)
                .map_err(DeviationError::Read)?;
            model
                .read_rows(b0, n, &mut mb)
                .map_err(DeviationError::Read)?;
            for (k, r) in regions.iter().enumerate() {
                let (lo, hi) = (b0.max(r.row0), (b0 + n).min(r.row0 + r.rows));
                for row in lo..hi {
                    let off = (row - b0) * shape.cols + r.col0;
                    let pairs = zb[off..off + r.cols].iter().zip(&mb[off..off + r.cols]);
                    for (&z, &m) in pairs.filter(|(z, m)| !z.is_nan() && !m.is_nan()) {
                        let a = &mut acc[k];
                        if second {
                            let (dz, dm) = (z - means[k].0, m - means[k].1);
                            a[3] += dz * dz;
                            a[4] += (dm - dz) * (dm - dz);
                        } else {
                            a[0] += 1.0;
                            a[1] += z;
                            a[2] += m;
                        }
                    }
                }
            }
            b0 += n;
        }
    }
    Ok(acc
        .iter()
        .map(|a| {
            let share = (a[4] / a[3]).sqrt() * 100.0;
            (a[0] > 0.0 && share.is_finite()).then_some(share)
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn shape(rows: usize, cols: usize) -> Shape {
        Shape { rows, cols }
    }

    fn surface(rows: usize, cols: usize) -> Raster<f64> {
        let z = (0..rows * cols)
            .map(|i| ((i * 31 % 97) as f64).sin())
            .collect();
        Raster::new(z, shape(rows, cols)).unwrap()
    }

    fn deviation(v: &RegionVerdict, name: &str) -> f64 {
        v.deviation_pct
            .iter()
            .find(|(n, _)| *n == name)
            .and_then(|(_, d)| *d)
            .unwrap()
    }

    #[test]
    fn tile_footprints_are_clipped_to_the_panorama() {
        let pano = shape(40, 60);
        let tile = shape(30, 40);
        let r = Region::tile_footprint(
            "S2".into(),
            (25.0, 20.0),
            (10.0, 10.0),
            Pitch::square(0.5).unwrap(),
            tile,
            pano,
        );
        assert_eq!(
            r,
            Some(Region {
                name: "S2".into(),
                row0: 20,
                col0: 30,
                rows: 20,
                cols: 30
            })
        );
        let outside = Region::tile_footprint(
            "S3".into(),
            (50.0, 0.0),
            (10.0, 10.0),
            Pitch::square(0.5).unwrap(),
            tile,
            pano,
        );
        assert_eq!(outside, None);
    }

    /// Table 6's names: the k-th tile is S<k+1> whether or not the tiles before it have a
    /// position; without a finite panorama origin there are none.
    #[test]
    fn tile_regions_are_numbered_by_tile_and_need_an_origin() {
        let (pano, tile, pitch) = (shape(40, 60), shape(30, 40), Pitch::square(0.5).unwrap());
        let tiles = [None, Some(((10.0, 10.0), tile)), Some(((25.0, 20.0), tile))];
        let r = tile_regions(tiles, (10.0, 10.0), pitch, pano);
        let names: Vec<(&str, usize, usize)> = r
            .iter()
            .map(|r| (r.name.as_str(), r.row0, r.col0))
            .collect();
        assert_eq!(names, [("S2", 0, 0), ("S3", 20, 30)]);
        assert!(tile_regions(tiles, (f64::NAN, 10.0), pitch, pano).is_empty());
    }

    #[test]
    fn a_stage_equal_to_the_measurement_passes_a_scaled_one_fails() {
        let z = surface(40, 60);
        let measured = Measured {
            heights_um: z.view(),
            pitch_x_um: 0.5,
            pitch_y_um: 0.5,
        };
        let regions = [
            Region {
                name: "S1".into(),
                row0: 0,
                col0: 0,
                rows: 30,
                cols: 40,
            },
            Region::whole(z.shape()),
        ];
        let scaled = z.map(|v| v * 1.06);
        let t = Table6::judge(
            measured,
            &[
                ModelStage::on_measured_grid("same", z.view()),
                ModelStage::on_measured_grid("scaled", scaled.view()),
            ],
            &regions,
            5.0,
        )
        .unwrap();
        let (same, sc) = (&t.stages[0], &t.stages[1]);
        assert!(same.pass && !sc.pass && !t.pass);
        assert_eq!(deviation(&same.regions[0], "Sq"), 0.0);
        for name in JUDGED {
            let d = deviation(&sc.regions[1], name);
            assert!((d - 6.0).abs() < 1e-9, "{name}: {d}");
        }
        // At a 7 % threshold a 6 % deviation passes.
        let t = Table6::judge(
            measured,
            &[ModelStage::on_measured_grid("scaled", scaled.view())],
            &regions,
            7.0,
        )
        .unwrap();
        assert!(t.pass);
    }

    #[test]
    fn residual_is_zero_for_an_offset_copy_and_half_for_a_halved_one() {
        let z = surface(30, 20);
        let offset = z.map(|v| v + 3.0);
        let halved = z.map(|v| v * 0.5);
        let regions = [Region::whole(z.shape())];
        let r = residual_pct_of_sq(
            &mut RasterRows(z.view()),
            &mut RasterRows(offset.view()),
            &regions,
        )
        .unwrap();
        assert!(r[0].unwrap() < 1e-9, "{r:?}");
        let r = residual_pct_of_sq(
            &mut RasterRows(z.view()),
            &mut RasterRows(halved.view()),
            &regions,
        )
        .unwrap();
        assert!((r[0].unwrap() - 50.0).abs() < 1e-9, "{r:?}");
    }

    #[test]
    fn holes_in_either_map_are_not_deviation() {
        let z = surface(20, 20);
        let mut model = z.clone();
        model.values_mut()[5] = f64::NAN;
        let measured = Measured {
            heights_um: z.view(),
            pitch_x_um: 1.0,
            pitch_y_um: 1.0,
        };
        let t = Table6::judge(
            measured,
            &[ModelStage::on_measured_grid("holed", model.view())],
            &[Region::whole(z.shape())],
            1.0,
        )
        .unwrap();
        assert!(t.pass);
        assert_eq!(deviation(&t.stages[0].regions[0], "Sa"), 0.0);
    }

    #[test]
    fn bad_shapes_are_errors_not_panics() {
        let z = surface(10, 10);
        let measured = Measured {
            heights_um: z.view(),
            pitch_x_um: 1.0,
            pitch_y_um: 1.0,
        };
        let small = surface(5, 10);
        let e = Table6::judge(
            measured,
            &[ModelStage::on_measured_grid("small", small.view())],
            &[Region::whole(z.shape())],
            5.0,
        );
        assert!(matches!(e, Err(DeviationError::StageShape { .. })));
        // A coarse grid whose rows do not match its cell size.
        let coarse = surface(4, 5);
        let e = Table6::judge(
            measured,
            &[ModelStage::pooled("coarse", coarse.view(), z.shape())],
            &[Region::whole(z.shape())],
            5.0,
        );
        assert!(
            matches!(e, Err(DeviationError::StageGrid { cell_px: 2, .. })),
            "{e:?}"
        );
        let big = Region::whole(shape(11, 10));
        let e = Table6::judge(measured, &[], &[big], 5.0);
        assert!(matches!(e, Err(DeviationError::RegionOutside { .. })));
    }

    /// Mean pooling of `z` in `f` x `f` blocks (NaN-aware), the pooled map's own grid.
    fn mean_pool(z: &Raster<f64>, f: usize) -> Raster<f64> {
        let out = ModelStage::expected_shape(f, z.shape());
        let mut v = Vec::with_capacity(out.len());
        for r in 0..out.rows {
            for c in 0..out.cols {
                let cell: Vec<f64> = (r * f..((r + 1) * f).min(z.rows()))
                    .flat_map(|rr| (c * f..((c + 1) * f).min(z.cols())).map(move |cc| (rr, cc)))
                    .map(|(rr, cc)| z.view().row(rr)[cc])
                    .filter(|x| !x.is_nan())
                    .collect();
                v.push(if cell.is_empty() {
                    f64::NAN
                } else {
                    cell.iter().sum::<f64>() / cell.len() as f64
                });
            }
        }
        Raster::new(v, out).unwrap()
    }

    #[test]
    fn a_pooled_stage_is_judged_on_its_own_grid() {
        // A blocky surface (constant in 2 x 2 blocks): its 2 x 2 pooling has exactly the same
        // height distribution, so every height parameter deviates by 0 on the pooled grid, in
        // a tile region and over the whole map, holes on either side included.
        let (rows, cols) = (24, 32);
        let mut z = Raster::new(
            (0..rows * cols)
                .map(|i| (((i / cols) / 2 * 7 + (i % cols) / 2 * 13) % 11) as f64 * 0.3)
                .collect(),
            shape(rows, cols),
        )
        .unwrap();
        // A hole in the measurement (one whole block) and a hole in the model (another cell).
        for (r, c) in [(4, 6), (4, 7), (5, 6), (5, 7)] {
            z.values_mut()[r * cols + c] = f64::NAN;
        }
        let mut pooled = mean_pool(&z, 2);
        assert!(pooled.view().row(2)[3].is_nan());
        pooled.values_mut()[5 * 16 + 9] = f64::NAN;
        let measured = Measured {
            heights_um: z.view(),
            pitch_x_um: 0.5,
            pitch_y_um: 0.5,
        };
        let regions = [
            Region {
                name: "S1".into(),
                row0: 2,
                col0: 4,
                rows: 14,
                cols: 20,
            },
            Region::whole(z.shape()),
        ];
        let stage = ModelStage::pooled("pooled", pooled.view(), z.shape());
        assert_eq!(stage.cell_px, 2);
        let t = Table6::judge(measured, &[stage], &regions, 0.001).unwrap();
        let s = &t.stages[0];
        assert_eq!((s.grid, s.cell_px), (shape(12, 16), 2));
        assert!(t.pass, "{t:?}");
        for region in &s.regions {
            for name in ["Sa", "Sq", "Sp", "Sv", "Sz", "Ssk", "Sku"] {
                assert!(deviation(region, name).abs() < 1e-9, "{name}");
            }
        }
    }

    #[test]
    fn slopes_of_a_pooled_stage_are_taken_at_its_own_pitch() {
        // A long-wave surface pooled 4 x 4: at the pooled pitch Sdq is within a few percent of
        // the measured one (the finite difference over 4 px and the block mean each shorten a
        // 64 px wave's slope by < 1 %); spread back onto the measured grid it would be twice
        // as steep (all slope in one step per block).
        let n = 128;
        let z = Raster::new(
            (0..n * n)
                .map(|i| (2.0 * std::f64::consts::PI * (i % n) as f64 / 64.0).sin())
                .collect(),
            shape(n, n),
        )
        .unwrap();
        let pooled = mean_pool(&z, 4);
        let measured = Measured {
            heights_um: z.view(),
            pitch_x_um: 1.0,
            pitch_y_um: 1.0,
        };
        let up = unpool(pooled.view(), z.shape()).unwrap();
        let t = Table6::judge(
            measured,
            &[
                ModelStage::pooled("own", pooled.view(), z.shape()),
                ModelStage::on_measured_grid("blown up", up.view()),
            ],
            &[Region::whole(z.shape())],
            5.0,
        )
        .unwrap();
        let own = deviation(&t.stages[0].regions[0], "Sdq");
        let blown = deviation(&t.stages[1].regions[0], "Sdq");
        assert!(own.abs() < 3.0, "own grid Sdq deviation {own} %");
        assert!(blown > 80.0, "blown-up Sdq deviation {blown} %");
    }

    #[test]
    fn unpool_spreads_cells() {
        let p = Raster::new(vec![1.0, 2.0, 3.0, 4.0], shape(2, 2)).unwrap();
        let u = unpool(p.view(), shape(3, 4)).unwrap();
        assert_eq!(
            u.values(),
            &[1.0, 1.0, 2.0, 2.0, 1.0, 1.0, 2.0, 2.0, 3.0, 3.0, 4.0, 4.0]
        );
        // Factor 5 from the columns, but 3 rows pool to 1.
        assert!(unpool(p.view(), shape(3, 9)).is_err());
    }

    #[test]
    fn the_streamed_table_equals_the_in_memory_one_bit_for_bit() {
        // 150 rows cross two bands; 77 columns and 3 px cells leave ragged edges; regions
        // start off the cell grid; holes on both sides; a model cell row spans the band edge
        // (row 63/64 lies inside cell row 21).
        let (rows, cols) = (150, 77);
        let mut z = surface(rows, cols);
        for i in (0..rows * cols).step_by(37) {
            z.values_mut()[i] = f64::NAN;
        }
        let datum = z.map(|v| v * 0.97 + 0.01);
        let mut pooled = mean_pool(&z, 3);
        pooled.values_mut()[7] = f64::NAN;
        let measured = Measured {
            heights_um: z.view(),
            pitch_x_um: 0.8,
            pitch_y_um: 0.7,
        };
        let regions = [
            Region {
                name: "S1".into(),
                row0: 5,
                col0: 4,
                rows: 100,
                cols: 50,
            },
            Region {
                name: "S2".into(),
                row0: 61,
                col0: 31,
                rows: 89,
                cols: 46,
            },
            Region::whole(z.shape()),
        ];
        let in_memory = Table6::judge(
            measured,
            &[
                ModelStage::on_measured_grid("datum", datum.view()),
                ModelStage::pooled("pooled", pooled.view(), z.shape()),
            ],
            &regions,
            5.0,
        )
        .unwrap();
        let mut stages = [
            StreamedStage::on_measured_grid("datum", Box::new(RasterRows(datum.view()))),
            StreamedStage::pooled("pooled", Box::new(RasterRows(pooled.view())), z.shape()),
        ];
        let streamed = Table6::judge_streamed(
            &mut RasterRows(z.view()),
            Pitch::new(0.8, 0.7).unwrap(),
            &mut stages,
            &regions,
            5.0,
        )
        .unwrap();
        assert_eq!(streamed.stages[1].cell_px, 3);
        // Bit for bit (PartialEq on f64 would also let -0.0 == 0.0 through).
        let bits = |t: &Table6| {
            format!(
                "{:?}",
                t.stages
                    .iter()
                    .map(|s| s
                        .regions
                        .iter()
                        .map(|r| (
                            r.measured.map(|p| p.named().map(|(_, v)| v.to_bits())),
                            r.model.map(|p| p.named().map(|(_, v)| v.to_bits())),
                            r.pass
                        ))
                        .collect::<Vec<_>>())
                    .collect::<Vec<_>>()
            )
        };
        assert_eq!(bits(&streamed), bits(&in_memory));
        assert_eq!(streamed, in_memory);
        // A wrong model grid is the same error as in memory.
        let small = surface(10, 10);
        let mut bad = [StreamedStage::on_measured_grid(
            "small",
            Box::new(RasterRows(small.view())),
        )];
        let e = Table6::judge_streamed(
            &mut RasterRows(z.view()),
            Pitch::square(1.0).unwrap(),
            &mut bad,
            &regions,
            5.0,
        );
        assert!(matches!(e, Err(DeviationError::StageShape { .. })));
    }
}
