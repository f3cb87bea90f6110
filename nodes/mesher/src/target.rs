//! What each discrete-element engine imports, and the checks that say an STL will load.
//!
//! The engines disagree (checked against the real programs where Debian ships them):
//!
//! | engine | reads | wall as | units | limits |
//! |---|---|---|---|---|
//! | LIGGGHTS-PUBLIC 3.8 | ASCII STL only | open sheet (`mesh/surface`); a closed solid aborts the run | SI (m) | smallest angle: below 0.5 deg a "high aspect ratio" warning, below the `curvature` angle (default acos(1 - 1e-5) = 0.256 deg) an abort at setup, below acos(0.9999995) = 0.057 deg always an abort (`src/surface_mesh_I.h`); no duplicate elements. The tolerance mesh is refined to 1 deg ([`crate::tin::AngleBound`]) |
//! | MercuryDPM | binary STL only (`readTriangleWall`) | sheet | SI (m) | none documented |
//! | EDEM | binary or ASCII STL | closed solid (geometry import) | mm (the import dialog's default) | none documented |
//! | Yade | ASCII STL (`ymport.stl`) | sheet | SI (m) | vertices are welded in O(V^2): keep the mesh small |
//!
//! A target therefore fixes the format, the kind, the units, the meshing method and a
//! triangle budget; [`EngineProfile::for_engine`] is the table above as data. Regular grids are
//! made to fit the budget by block means over `stride x stride` samples ([`block_mean`]).
//! LIGGGHTS gets the model from the tolerance ([`crate::tolerance`]) with its smallest angle
//! bounded (each checkpoint's mesh refined, then judged); its regular grid stays available
//! (`method = "grid"`, `surfstream mesh --target liggghts --grid`).

use std::str::FromStr;

use serde::{Deserialize, Serialize};
use surfstream_core::raster::{Raster, RasterView, Shape};
use surfstream_core::record::{self, EngineTargetRecord, GridSheetFidelity, GridSheetRecord};
use surfstream_core::Pitch;

use crate::error::{MeshError, Result};
use crate::fidelity::{field_params, AreaParams};
use crate::field::ScanPlacement;
use crate::solid::{grid_solid, LengthUnit, SolidMesh, SolidParams};
use crate::tolerance::{Tolerance, ToleranceSettings, ANGLE_BOUNDED_TOLERANCE, DEFAULT_TOLERANCE};

/// A discrete-element engine an STL is made for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DemEngine {
    Liggghts,
    MercuryDpm,
    Edem,
    Yade,
}

impl FromStr for DemEngine {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.to_ascii_lowercase().as_str() {
            "liggghts" => Ok(Self::Liggghts),
            "mercurydpm" => Ok(Self::MercuryDpm),
            "edem" => Ok(Self::Edem),
            "yade" => Ok(Self::Yade),
            other => Err(format!(
                "unknown DEM target '{other}', expected liggghts, mercurydpm, edem or yade"
            )),
        }
    }
}

impl DemEngine {
    pub fn name(self) -> &'static str {
        match self {
            Self::Liggghts => "liggghts",
            Self::MercuryDpm => "mercurydpm",
            Self::Edem => "edem",
            Self::Yade => "yade",
        }
    }
}

/// How the mesh is made for an engine.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum TargetMethod {
    /// Two triangles per (block-averaged) grid cell: no slivers, at most 6 triangles per vertex.
    Grid,
    /// The model from the tolerance (fewest triangles within it), with its smallest angle
    /// bounded by `min_angle_deg` when that is above 0.
    Adaptive,
}

/// What one engine imports.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct EngineProfile {
    pub engine: DemEngine,
    /// ASCII (true) or binary STL.
    pub ascii: bool,
    /// A closed solid (true) or the open surface.
    pub solid: bool,
    pub units: LengthUnit,
    pub method: TargetMethod,
    /// Most surface triangles the engine is given.
    pub max_triangles: usize,
    /// Smallest interior angle every triangle must have, degrees.
    pub min_angle_deg: f64,
}

impl EngineProfile {
    /// The engine's profile with its triangle budget lowered (or raised) to `max_triangles`
    /// when the user gives one.
    pub fn with_budget(engine: DemEngine, max_triangles: Option<usize>) -> Self {
        let mut p = Self::for_engine(engine);
        if let Some(budget) = max_triangles {
            p.max_triangles = budget;
        }
        p
    }

    /// The tolerance the engine's model is made to when the caller states none: an
    /// angle-bounded adaptive mesh (LIGGGHTS) gets [`ANGLE_BOUNDED_TOLERANCE`] (no bound on
    /// the largest pointwise error: it does not fit the angle bound and the budget), every
    /// other target [`DEFAULT_TOLERANCE`].
    pub fn default_tolerance(&self) -> Tolerance {
        if self.method == TargetMethod::Adaptive && self.min_angle_deg > 0.0 {
            ANGLE_BOUNDED_TOLERANCE
        } else {
            DEFAULT_TOLERANCE
        }
    }

    pub fn for_engine(engine: DemEngine) -> Self {
        match engine {
            DemEngine::Liggghts => Self {
                engine,
                ascii: true,
                solid: false,
                units: LengthUnit::M,
                method: TargetMethod::Adaptive,
                max_triangles: 400_000,
                // LIGGGHTS aborts below 0.256 deg (its default `curvature`) and warns below
                // 0.5 deg; 1 deg keeps clear of both.
                min_angle_deg: 1.0,
            },
            DemEngine::MercuryDpm => Self {
                engine,
                ascii: false,
                solid: false,
                units: LengthUnit::M,
                method: TargetMethod::Grid,
                max_triangles: 1_000_000,
                min_angle_deg: 1.0,
            },
            DemEngine::Edem => Self {
                engine,
                ascii: false,
                solid: true,
                units: LengthUnit::Mm,
                method: TargetMethod::Adaptive,
                max_triangles: 2_000_000,
                min_angle_deg: 0.0,
            },
            DemEngine::Yade => Self {
                engine,
                ascii: true,
                solid: false,
                units: LengthUnit::M,
                method: TargetMethod::Grid,
                // Welding is O(V^2): 20k triangles is ~10k vertices, ~1e8 comparisons.
                max_triangles: 20_000,
                min_angle_deg: 1.0,
            },
        }
    }
}

impl ToleranceSettings {
    /// The default settings for a mesh made for `profile` (its default tolerance,
    /// [`EngineProfile::default_tolerance`]; [`DEFAULT_TOLERANCE`] without one).
    pub fn for_target(profile: Option<&EngineProfile>) -> Self {
        Self {
            tolerance: profile.map_or(DEFAULT_TOLERANCE, |p| p.default_tolerance()),
            ..Self::default()
        }
    }
}

/// The smallest block side `stride` such that a grid of `shape` averaged over
/// `stride x stride` blocks meshes into at most `max_triangles` triangles (two per cell).
pub fn grid_stride_for_budget(shape: Shape, max_triangles: usize) -> usize {
    let triangles = |s: usize| {
        let (r, c) = (shape.rows.div_ceil(s), shape.cols.div_ceil(s));
        2 * r.saturating_sub(1) * c.saturating_sub(1)
    };
    let mut stride = 1;
    while triangles(stride) > max_triangles && stride < shape.rows.max(shape.cols) {
        stride += 1;
    }
    stride
}

/// The NaN-aware mean of every `stride x stride` block (edge blocks may be smaller); a block
/// with no valid sample stays NaN. The block's centre moves by `(stride - 1) / 2` samples, which
/// the caller adds to the origin.
pub fn block_mean(heights: RasterView<'_, f32>, stride: usize) -> Raster<f32> {
    let stride = stride.max(1);
    let out_shape = Shape::new(
        heights.rows().div_ceil(stride),
        heights.cols().div_ceil(stride),
    );
    let mut out = Raster::filled(out_shape, f32::NAN);
    for r in 0..out_shape.rows {
        for c in 0..out_shape.cols {
            let (mut n, mut sum) = (0usize, 0.0f64);
            for rr in r * stride..((r + 1) * stride).min(heights.rows()) {
                for &z in &heights.row(rr)[c * stride..((c + 1) * stride).min(heights.cols())] {
                    if !z.is_nan() {
                        n += 1;
                        sum += z as f64;
                    }
                }
            }
            if n > 0 {
                out.values_mut()[out_shape.index(r, c)] = (sum / n as f64) as f32;
            }
        }
    }
    out
}

/// The block means back on the measured grid (each sample takes its block's value): the
/// surface the engine is given, sampled where the measurement was, for Table 6.
pub fn block_values_on_grid(
    reduced: RasterView<'_, f32>,
    stride: usize,
    shape: Shape,
) -> Raster<f32> {
    let stride = stride.max(1);
    let mut out = Raster::filled(shape, f32::NAN);
    for r in 0..shape.rows {
        let src = reduced.row((r / stride).min(reduced.rows() - 1));
        for (c, z) in out.row_mut(r).iter_mut().enumerate() {
            *z = src[(c / stride).min(src.len() - 1)];
        }
    }
    out
}

/// Element quality of a mesh: the one record the report carries ([`record::ElementQuality`]).
pub use surfstream_core::record::ElementQuality;

/// Measures the quality of the first `count` triangles of `mesh`.
pub fn element_quality(mesh: &SolidMesh, count: usize) -> ElementQuality {
    let mut min_angle = f64::INFINITY;
    let mut per_vertex = vec![0usize; mesh.vertices.len()];
    let mut keys: Vec<[u32; 3]> = Vec::with_capacity(count);
    for t in mesh.triangles.iter().take(count) {
        let p = t.map(|i| mesh.vertices[i as usize]);
        for k in 0..3 {
            let (a, b, c) = (p[k], p[(k + 1) % 3], p[(k + 2) % 3]);
            let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
            let v = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
            let dot = u[0] * v[0] + u[1] * v[1] + u[2] * v[2];
            let cross = [
                u[1] * v[2] - u[2] * v[1],
                u[2] * v[0] - u[0] * v[2],
                u[0] * v[1] - u[1] * v[0],
            ];
            let sin = (cross[0] * cross[0] + cross[1] * cross[1] + cross[2] * cross[2]).sqrt();
            min_angle = min_angle.min(sin.atan2(dot).to_degrees());
        }
        for &i in t {
            per_vertex[i as usize] += 1;
        }
        let mut key = *t;
        key.sort_unstable();
        keys.push(key);
    }
    keys.sort_unstable();
    let duplicate_triangles = keys.windows(2).filter(|w| w[0] == w[1]).count();
    ElementQuality {
        min_angle_deg: if min_angle.is_finite() {
            min_angle
        } else {
            0.0
        },
        max_triangles_per_vertex: per_vertex.into_iter().max().unwrap_or(0) as u64,
        duplicate_triangles: duplicate_triangles as u64,
    }
}

/// A regular-grid sheet made for an engine, and what was done to fit it.
#[derive(Debug, Clone)]
pub struct TargetMesh {
    /// The open surface (every triangle is surface).
    pub mesh: SolidMesh,
    pub profile: EngineProfile,
    /// Side of the blocks averaged into one grid sample (1: the measured grid itself).
    pub stride: usize,
    /// The meshed grid, rows x cols.
    pub grid: Shape,
    /// The block means that were meshed, um relative to the input's z offset.
    pub block_means: Raster<f32>,
    /// Sample spacing of the meshed grid.
    pub pitch: Pitch,
    pub quality: ElementQuality,
    /// Sa, Sq, Sz, Sdr of the measured field and of the meshed grid (what averaging cost).
    pub measured: Option<AreaParams>,
    pub meshed: Option<AreaParams>,
}

impl TargetMesh {
    /// What run.json and the mesh JSON record of a grid target beside the common fields
    /// (`target` and `method` are the report's own).
    pub fn record(&self) -> GridSheetRecord {
        GridSheetRecord {
            kind: "sheet".into(),
            block_stride: self.stride as u64,
            grid_rows_cols: [self.grid.rows as u64, self.grid.cols as u64],
            meshed_pitch_um: self.pitch.um(),
            element_quality: self.quality,
            fidelity: GridSheetFidelity {
                measured: self.measured,
                meshed_grid: self.meshed,
            },
        }
    }

    /// [`TargetMesh::record`] with the engine and the method, as a JSON object (the mesh
    /// verb's and the Python binding's report start from it).
    pub fn summary(&self) -> Result<serde_json::Value, record::RecordError> {
        let mut v = record::to_value(&self.record())?;
        if let Some(o) = v.as_object_mut() {
            o.insert(
                "target".into(),
                record::to_value(&EngineTargetRecord::try_from(&self.profile)?)?,
            );
            o.insert("method".into(), "grid".into());
        }
        Ok(v)
    }
}

/// Meshes `heights` as a regular-grid sheet within the engine's triangle budget and checks
/// the elements against its limits. Missing samples are filled (see [`crate::fill_missing`]).
/// Errors: a geometry the grid mesher refuses, or an element the engine would reject.
pub fn grid_sheet_for(
    heights: RasterView<'_, f32>,
    at: &ScanPlacement,
    profile: &EngineProfile,
) -> Result<TargetMesh> {
    let stride = grid_stride_for_budget(heights.shape(), profile.max_triangles);
    let reduced = block_mean(heights, stride);
    // A block's mean stands at the block's centre.
    let half = (stride as f64 - 1.0) * 0.5;
    let reduced_at = ScanPlacement {
        pitch: at.pitch.times(stride)?,
        origin_x_um: at.origin_x_um + half * at.pitch.x_um(),
        origin_y_um: at.origin_y_um + half * at.pitch.y_um(),
        z_offset_um: at.z_offset_um,
    };
    let params = SolidParams {
        units: profile.units,
        base_depth_um: None,
        recentre: true,
    };
    let mut mesh = grid_solid(reduced.view(), &reduced_at, &params)?;
    // The engines that take a sheet want the measured surface alone: drop walls and base.
    // grid_solid lays the top out first (vertex row * cols + col, then the surface triangles):
    // what follows is walls and base.
    mesh.triangles.truncate(mesh.top_triangles);
    mesh.vertices.truncate(reduced.shape().len());
    // Without its base the sheet's lowest point, not the base, sits at z = 0.
    let lowest = mesh
        .vertices
        .iter()
        .map(|v| v[2])
        .fold(f64::INFINITY, f64::min);
    if lowest.is_finite() {
        for v in &mut mesh.vertices {
            v[2] -= lowest;
        }
        mesh.offset_um[2] += lowest * profile.units.um_per_unit();
        mesh.base_depth_um = 0.0;
    }
    let quality = element_quality(&mesh, mesh.triangles.len());
    if quality.min_angle_deg < profile.min_angle_deg || quality.duplicate_triangles > 0 {
        return Err(MeshError::Incompatible(format!(
            "{}: the mesh has a smallest angle of {:.3} deg and {} duplicate triangles; the \
             engine needs angles above {} deg and no duplicates (pitch {} x {} um is too \
             anisotropic)",
            profile.engine.name(),
            quality.min_angle_deg,
            quality.duplicate_triangles,
            profile.min_angle_deg,
            reduced_at.pitch.x_um(),
            reduced_at.pitch.y_um()
        )));
    }
    Ok(TargetMesh {
        mesh,
        measured: field_params(heights, at.pitch),
        meshed: field_params(reduced.view(), reduced_at.pitch),
        // Recorded as what was made: the regular grid, whatever the engine's default.
        profile: EngineProfile {
            method: TargetMethod::Grid,
            ..*profile
        },
        stride,
        grid: reduced.shape(),
        block_means: reduced,
        pitch: reduced_at.pitch,
        quality,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use surfstream_core::Pitch;

    #[test]
    fn engines_parse_and_liggghts_gets_an_ascii_sheet_in_metres() {
        assert_eq!("LIGGGHTS".parse::<DemEngine>(), Ok(DemEngine::Liggghts));
        assert!("rocky"
            .parse::<DemEngine>()
            .unwrap_err()
            .contains("expected liggghts"));
        let p = EngineProfile::for_engine(DemEngine::Liggghts);
        assert!(p.ascii && !p.solid);
        assert_eq!(p.units, LengthUnit::M);
        assert_eq!(p.method, TargetMethod::Adaptive);
        assert!(p.min_angle_deg > 0.256, "LIGGGHTS aborts below 0.256 deg");
        let m = EngineProfile::for_engine(DemEngine::MercuryDpm);
        assert!(!m.ascii, "MercuryDPM reads binary STL only");
    }

    #[test]
    fn the_angle_bounded_target_states_its_own_default_tolerance() {
        // LIGGGHTS: the angle bound and the budget leave no room for the pointwise maximum.
        let l = EngineProfile::for_engine(DemEngine::Liggghts).default_tolerance();
        assert_eq!(l, ANGLE_BOUNDED_TOLERANCE);
        assert_eq!((l.max_error_pct, l.residual_pct), (None, Some(50.0)));
        assert_eq!((l.sa_pct, l.sq_pct, l.sz_pct), (1.0, 1.0, 3.0));
        // Every other target (and LIGGGHTS' regular grid) keeps the default's pointwise bound.
        let edem = EngineProfile::for_engine(DemEngine::Edem).default_tolerance();
        assert_eq!(edem, DEFAULT_TOLERANCE);
        assert_eq!(edem.max_error_pct, Some(50.0));
        let mut grid = EngineProfile::for_engine(DemEngine::Liggghts);
        grid.method = TargetMethod::Grid;
        assert_eq!(grid.default_tolerance(), DEFAULT_TOLERANCE);
        let s = ToleranceSettings::for_target(None);
        assert_eq!(s.tolerance, DEFAULT_TOLERANCE);
    }

    #[test]
    fn stride_fits_the_budget_and_block_means_skip_nan() {
        let shape = Shape::new(1000, 600);
        assert_eq!(grid_stride_for_budget(shape, 2 * 999 * 599), 1);
        let s = grid_stride_for_budget(shape, 20_000);
        let (r, c) = (1000usize.div_ceil(s), 600usize.div_ceil(s));
        assert!(2 * (r - 1) * (c - 1) <= 20_000);
        let (r1, c1) = (1000usize.div_ceil(s - 1), 600usize.div_ceil(s - 1));
        assert!(
            2 * (r1 - 1) * (c1 - 1) > 20_000,
            "stride {s} is not the smallest"
        );

        // 3 rows x 4 cols, one NaN: 2 x 2 blocks.
        let z = [
            1.0,
            3.0,
            5.0,
            7.0,
            f32::NAN,
            5.0,
            9.0,
            11.0,
            2.0,
            4.0,
            6.0,
            8.0,
        ];
        let m = block_mean(RasterView::new(&z, Shape::new(3, 4)).unwrap(), 2);
        assert_eq!(m.shape(), Shape::new(2, 2));
        assert_eq!(m.values(), &[3.0, 8.0, 3.0, 7.0]);
    }

    #[test]
    fn a_liggghts_sheet_fits_the_budget_with_good_elements() {
        let shape = Shape::new(60, 90);
        let z: Vec<f32> = (0..shape.len())
            .map(|i| ((i % 90) as f32 * 0.3).sin() + ((i / 90) as f32 * 0.2).cos())
            .collect();
        let mut profile = EngineProfile::for_engine(DemEngine::Liggghts);
        profile.max_triangles = 2000;
        let t = grid_sheet_for(
            RasterView::new(&z, shape).unwrap(),
            &ScanPlacement::new(Pitch::new(0.5, 1.0).expect("a positive pitch")),
            &profile,
        )
        .unwrap();
        assert!(
            t.mesh.triangles.len() <= 2000 && t.stride > 1,
            "{}",
            t.stride
        );
        assert_eq!(
            t.mesh.triangles.len(),
            2 * (t.grid.rows - 1) * (t.grid.cols - 1)
        );
        assert!(t.quality.min_angle_deg > 20.0, "{:?}", t.quality);
        assert!(t.quality.max_triangles_per_vertex <= 6);
        assert_eq!(t.quality.duplicate_triangles, 0);
        // Metres, and the sheet spans the measured area (less half a block at each end).
        let xs: Vec<f64> = t.mesh.vertices.iter().map(|v| v[0]).collect();
        let span = xs.iter().cloned().fold(f64::MIN, f64::max)
            - xs.iter().cloned().fold(f64::MAX, f64::min);
        assert!(span > 40e-6 && span <= 45e-6, "{span}");
        let zmin = t
            .mesh
            .vertices
            .iter()
            .map(|v| v[2])
            .fold(f64::MAX, f64::min);
        assert!(
            zmin.abs() < 1e-12,
            "the sheet's lowest point is at z = 0: {zmin}"
        );
    }
}
