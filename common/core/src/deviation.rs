//! The model-vs-measurement deviation of the reference study's Table 6, over in-memory
//! surfaces: no files, no JSON.
//!
//! A measured surface (the fused panorama) is compared with model stages on its grid (datum +
//! roughness, the pooled map spread back with [`unpool`], the mesh re-sampled), in regions of
//! the panorama (each tile's footprint, [`Region::tile_footprint`], and the whole map).
//! Per region and stage: the nine ISO 25178 parameters ([`metrology::params`], mean removed,
//! no levelling) of both, each over the points valid in both maps (holes are not deviation);
//! relative deviation = (model - measured) / measured in %; the stage passes a region when
//! |deviation| <= the threshold for Sa, Sq and Sz ([`JUDGED`]). Slope parameters of a
//! re-sampled model (Sdq, Sdr of the pooled map) differ by construction: reported, not judged.

use crate::metrology::{self, Grid, Params};
use crate::raster::{Raster, RasterView, Shape};

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
        pitch_um: (f64, f64),
        tile: Shape,
        panorama: Shape,
    ) -> Option<Self> {
        let col0 = ((tile_origin_um.0 - panorama_origin_um.0) / pitch_um.0)
            .round()
            .max(0.0) as usize;
        let row0 = ((tile_origin_um.1 - panorama_origin_um.1) / pitch_um.1)
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

    /// The heights of this region of `z` where `mask` (same shape) is valid, NaN elsewhere.
    fn crop(&self, z: RasterView<f64>, mask: RasterView<f64>) -> Vec<f64> {
        let mut out = Vec::with_capacity(self.rows * self.cols);
        for row in self.row0..self.row0 + self.rows {
            let span = self.col0..self.col0 + self.cols;
            out.extend(
                z.row(row)[span.clone()]
                    .iter()
                    .zip(&mask.row(row)[span])
                    .map(|(&v, &m)| if m.is_nan() { f64::NAN } else { v }),
            );
        }
        out
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
    /// Judges each `(stage name, model surface)` against `measured` in `regions` at
    /// `threshold_pct`. Models must have the measured surface's shape and regions must lie
    /// inside it.
    pub fn judge(
        measured: Measured,
        stages: &[(&str, RasterView<f64>)],
        regions: &[Region],
        threshold_pct: f64,
    ) -> Result<Self, DeviationError> {
        let shape = measured.heights_um.shape();
        if let Some(r) = regions.iter().find(|r| !r.fits(shape)) {
            return Err(DeviationError::RegionOutside {
                region: r.name.clone(),
                row0: r.row0,
                col0: r.col0,
                rows: r.rows,
                cols: r.cols,
                measured: shape,
            });
        }
        let stages = stages
            .iter()
            .map(|(name, model)| judge_stage(&measured, name, *model, regions, threshold_pct))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Self {
            threshold_pct,
            pass: stages.iter().all(|s| s.pass),
            stages,
        })
    }
}

fn judge_stage(
    m: &Measured,
    stage: &str,
    model: RasterView<f64>,
    regions: &[Region],
    threshold_pct: f64,
) -> Result<StageVerdict, DeviationError> {
    if model.shape() != m.heights_um.shape() {
        return Err(DeviationError::StageShape {
            stage: stage.to_string(),
            model: model.shape(),
            measured: m.heights_um.shape(),
        });
    }
    let regions: Vec<RegionVerdict> = regions
        .iter()
        .map(|r| judge_region(m, model, r, threshold_pct))
        .collect();
    Ok(StageVerdict {
        stage: stage.to_string(),
        pass: regions.iter().all(|r| r.pass),
        regions,
    })
}

fn judge_region(
    m: &Measured,
    model: RasterView<f64>,
    r: &Region,
    threshold_pct: f64,
) -> RegionVerdict {
    let params_of = |z: &[f64]| -> Option<Params> {
        metrology::params(&Grid::new(z, r.rows, r.cols, m.pitch_x_um, m.pitch_y_um).ok()?).ok()
    };
    // Both over the points valid in both maps, so holes do not count as deviation.
    let measured = params_of(&r.crop(m.heights_um, model));
    let modelled = params_of(&r.crop(model, m.heights_um));
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
        region: r.name.clone(),
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
            (0.5, 0.5),
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
            (0.5, 0.5),
            tile,
            pano,
        );
        assert_eq!(outside, None);
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
            &[("same", z.view()), ("scaled", scaled.view())],
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
        let t = Table6::judge(measured, &[("scaled", scaled.view())], &regions, 7.0).unwrap();
        assert!(t.pass);
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
            &[("holed", model.view())],
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
            &[("small", small.view())],
            &[Region::whole(z.shape())],
            5.0,
        );
        assert!(matches!(e, Err(DeviationError::StageShape { .. })));
        let big = Region::whole(shape(11, 10));
        let e = Table6::judge(measured, &[], &[big], 5.0);
        assert!(matches!(e, Err(DeviationError::RegionOutside { .. })));
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
}
