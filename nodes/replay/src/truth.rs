//! The ground truth of a simulated scan, in the layout of `bench/make_tiles.py`'s
//! `ground_truth.json` so that `bench/score_registration.py` scores a surfstream run against it.
//! This is the writer. Its tiles and pitch are `surfstream_core::record`'s [`TileTruth`] and
//! [`Xy`], which every reader (the matcher's scoring, [`surfstream_io::truth::ScanTruth`]; the
//! fusion comparison; the manifest's pitch check) reads back through
//! `surfstream_core::record::TruthRecord`; a test below reads what this writes with it.
//!
//! The scorer reads `pixel_pitch_um.{x,y}`, `tiles[].index`, `tiles[].true_origin_px` and
//! `pairs[].{a,b,true_offset_px}`; everything else is for people and other tools. Field names
//! follow make_tiles.py where the concept is the same (`piston`, `tilt_x`, `tilt_y` are in
//! micrometres, as the conventions block says).

use serde::Serialize;
pub use surfstream_core::record::{TileTruth, Xy};

use crate::specimen::SpecimenParams;
use crate::stage::{ScanPlan, StageParams};

/// The conventions block: how to read the numbers.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Conventions {
    /// Pixel coordinates.
    pub coords: String,
    /// Scan coordinates in micrometres.
    pub scan_coords: String,
    /// Unit of heights, piston and tilt.
    pub height_unit: String,
    /// Meaning of NaN.
    pub nan: String,
    /// Definition of a pair's offset.
    pub pair_offset: String,
    /// Definition of piston and tilt.
    pub pose: String,
}

/// Grid geometry.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct GridTruth {
    /// Rows (y).
    pub rows: usize,
    /// Columns (x).
    pub cols: usize,
    /// Acquisition order: always `"serpentine"`.
    pub order: String,
    /// Where the order starts.
    pub start: String,
    /// Tile shape `[height, width]` in pixels (numpy order, as make_tiles.py).
    pub tile_shape_px: [usize; 2],
    /// Overlap fractions.
    pub overlap: Xy,
    /// Nominal step between neighbours in pixels.
    pub nominal_step_px: Xy,
    /// Nominal overlap in pixels.
    pub nominal_overlap_px: Xy,
}

/// Degradation parameters, with make_tiles.py's keys (heights in micrometres).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DegradationTruth {
    /// Stage error sigma per axis, px.
    pub stage_sigma_px: f64,
    /// Stage error truncation bound per axis, px.
    pub stage_error_bound_px: f64,
    /// Extra x error on reversed rows, px.
    pub backlash_px: f64,
    /// White noise sigma, um.
    pub noise_sigma: f64,
    /// Piston sigma, um.
    pub piston_sigma: f64,
    /// Tilt sigma (height change across the tile), um.
    pub tilt_sigma: f64,
    /// Fraction of isolated NaN pixels.
    pub dropout_fraction: f64,
    /// Mean number of NaN blobs per tile.
    pub dropout_blobs_mean: f64,
    /// Blob semi-axes range, px.
    pub blob_radius_px: [f64; 2],
}

/// The specimen the scan needs (and, once known, how it was made).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SpecimenTruth {
    /// Width in pixels.
    pub width_px: usize,
    /// Height in pixels.
    pub height_px: usize,
    /// Generation parameters, if the specimen was generated.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub generated: Option<SpecimenParams>,
    /// The roughness repeats with this period in pixels (x and y), if it is a periodic
    /// texture (a large generated specimen): the true heights at (x, y) and (x + period, y)
    /// differ only by waviness and form.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub roughness_period_px: Option<usize>,
}

/// A pair of grid neighbours, `b` right of or below `a`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PairTruth {
    /// Acquisition index of the first tile.
    pub a: usize,
    /// Acquisition index of the second tile.
    pub b: usize,
    /// `"horizontal"` or `"vertical"`.
    pub direction: String,
    /// `nominal_origin_px[b] - nominal_origin_px[a]`.
    pub nominal_offset_px: [f64; 2],
    /// `true_origin_px[b] - true_origin_px[a]`.
    pub true_offset_px: [f64; 2],
}

/// Everything a scorer needs about a simulated scan; serialise it as `ground_truth.json`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct GroundTruth {
    /// Who wrote it.
    pub generator: String,
    /// How to read it.
    pub conventions: Conventions,
    /// The specimen.
    pub specimen: SpecimenTruth,
    /// Pixel pitch in micrometres.
    pub pixel_pitch_um: Xy,
    /// Grid geometry.
    pub grid: GridTruth,
    /// Degradations.
    pub degradation: DegradationTruth,
    /// The stage parameters as given.
    pub params: StageParams,
    /// Tiles in acquisition order.
    pub tiles: Vec<TileTruth>,
    /// Horizontal and vertical neighbour pairs.
    pub pairs: Vec<PairTruth>,
}

impl GroundTruth {
    /// Records how the specimen was generated.
    pub fn with_specimen(mut self, specimen: &SpecimenParams) -> Self {
        self.specimen = SpecimenTruth {
            width_px: specimen.width_px,
            height_px: specimen.height_px,
            generated: Some(specimen.clone()),
            roughness_period_px: specimen.roughness_period(),
        };
        self
    }
}

fn diff(b: [f64; 2], a: [f64; 2]) -> [f64; 2] {
    [b[0] - a[0], b[1] - a[1]]
}

/// The truth of a plan.
pub fn truth_for(plan: &ScanPlan) -> GroundTruth {
    let p = &plan.params;
    let (ox, oy) = p.overlap_xy();
    let (tw, th) = (plan.tile_width_px, plan.tile_height_px);
    let tiles: Vec<TileTruth> = plan
        .tiles
        .iter()
        .map(|t| TileTruth {
            index: t.index,
            row: t.row,
            col: t.col,
            nominal_origin_px: t.nominal_origin_px,
            stage_position_um: t.stage_position_um,
            true_origin_px: t.true_origin_px,
            true_origin_um: t.true_origin_um,
            stage_error_px: diff(t.true_origin_px, t.nominal_origin_px),
            piston: t.piston_um,
            tilt_x: t.tilt_x_um,
            tilt_y: t.tilt_y_um,
        })
        .collect();
    let mut pairs = Vec::new();
    for r in 0..p.rows {
        for c in 0..p.cols {
            let Some(a) = plan.index_of(r, c) else {
                continue;
            };
            let right = plan.index_of(r, c + 1).map(|b| (b, "horizontal"));
            let below = plan.index_of(r + 1, c).map(|b| (b, "vertical"));
            for (b, direction) in [right, below].into_iter().flatten() {
                let (Some(ta), Some(tb)) = (plan.tiles.get(a), plan.tiles.get(b)) else {
                    continue;
                };
                pairs.push(PairTruth {
                    a,
                    b,
                    direction: direction.to_string(),
                    nominal_offset_px: diff(tb.nominal_origin_px, ta.nominal_origin_px),
                    true_offset_px: diff(tb.true_origin_px, ta.true_origin_px),
                });
            }
        }
    }
    GroundTruth {
        generator: format!("surfstream-replay {}", env!("CARGO_PKG_VERSION")),
        conventions: Conventions {
            coords: "(x, y) = (column, row) in pixels of the specimen; tile pixel (i, j) = \
                     specimen(x0 + j, y0 + i) with (x0, y0) = true_origin_px, resampled bicubically \
                     (Keys, a = -0.5)"
                .into(),
            scan_coords: "micrometres, x along columns, y along rows; specimen pixel (0, 0) at \
                          (0, 0) um; um = px * pixel_pitch_um"
                .into(),
            height_unit: "um".into(),
            nan: "not measured".into(),
            pair_offset: "true_offset_px = true_origin_px[b] - true_origin_px[a]".into(),
            pose: "tile += piston + tilt_x * xn + tilt_y * yn, xn = (j - (w - 1) / 2) / w, \
                   yn = (i - (h - 1) / 2) / h"
                .into(),
        },
        specimen: SpecimenTruth {
            width_px: plan.specimen_width_px,
            height_px: plan.specimen_height_px,
            generated: None,
            roughness_period_px: None,
        },
        pixel_pitch_um: Xy {
            x: p.pitch_um,
            y: p.pitch_um,
        },
        grid: GridTruth {
            rows: p.rows,
            cols: p.cols,
            order: "serpentine".into(),
            start: "upper-left, first row left-to-right".into(),
            tile_shape_px: [th, tw],
            overlap: Xy { x: ox, y: oy },
            nominal_step_px: Xy {
                x: plan.step_x_px,
                y: plan.step_y_px,
            },
            nominal_overlap_px: Xy {
                x: tw as f64 - plan.step_x_px,
                y: th as f64 - plan.step_y_px,
            },
        },
        degradation: DegradationTruth {
            stage_sigma_px: p.stage_sigma_px,
            stage_error_bound_px: plan.margin_px - p.backlash_px.abs(),
            backlash_px: p.backlash_px,
            noise_sigma: p.noise_um,
            piston_sigma: p.piston_sigma_um,
            tilt_sigma: p.tilt_sigma_um,
            dropout_fraction: p.dropout_fraction,
            dropout_blobs_mean: p.dropout_blobs_mean,
            blob_radius_px: p.blob_radius_px,
        },
        params: p.clone(),
        tiles,
        pairs,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stage::plan_scan;

    #[test]
    fn the_truth_reader_reads_what_the_stage_writes() {
        let params = StageParams {
            rows: 2,
            cols: 3,
            tile_px: 64,
            ..StageParams::default()
        };
        let plan = plan_scan(&params).expect("plan");
        let truth = truth_for(&plan);
        let text = serde_json::to_string_pretty(&truth).expect("json");
        let read =
            surfstream_io::truth::ScanTruth::parse(&text, std::path::Path::new("truth.json"))
                .expect("readable");
        assert_eq!(read.tiles(), 6);
        for p in &truth.pairs {
            // serde_json's default float parsing may be one ulp off.
            let got = read.true_offset_px(p.a as u64, p.b as u64).expect("listed");
            assert!((got[0] - p.true_offset_px[0]).abs() < 1e-9, "{got:?}");
            assert!((got[1] - p.true_offset_px[1]).abs() < 1e-9, "{got:?}");
        }
    }
}
