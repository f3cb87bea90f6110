//! A height field as an error-bounded mesh ([`crate::tin`]) made into an STL-ready solid or
//! sheet, with its fidelity: the achieved vertical error and the areal parameters of the mesh
//! resampled on the grid beside those of the height field.

use serde::{Deserialize, Serialize};

use crate::error::{MeshError, Result};
use crate::fidelity::{compare, field_params, AreaParams};
use surfstream_core::raster::RasterView;
use surfstream_core::record::{self, AdaptiveMeshRecord};

use crate::field::{validate, ScanPlacement};
use crate::solid::{close_top_surface, default_base_depth_um, SolidMesh, SolidParams};
use crate::tin::{resample_with_error, triangulate, ErrorStats, MissingSamples, Tin, TinParams};

/// The error bound: absolute, or a fraction of the height field's Sq.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Epsilon {
    /// Largest vertical error, um.
    Um(f64),
    /// Largest vertical error as a fraction of Sq (about the least-squares plane).
    SqFraction(f64),
}

/// A closed solid (top, side walls, flat base) or the open top surface alone.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MeshKind {
    #[default]
    Solid,
    Sheet,
}

/// Everything [`mesh_height_field`] needs besides the field.
#[derive(Debug, Clone, PartialEq)]
pub struct MeshParams {
    pub epsilon: Epsilon,
    pub max_triangles: Option<usize>,
    pub kind: MeshKind,
    pub missing: MissingSamples,
    /// Units, base depth (solids) and recentring, as for the grid solid.
    pub solid: SolidParams,
    /// Side of the blocks meshed independently and in parallel, samples (None: the default,
    /// [`crate::tin::DEFAULT_BLOCK_SAMPLES`]); see [`crate::tin::triangulate`].
    pub block_samples: Option<usize>,
}

impl MeshParams {
    /// The vertical bound in um: absolute, or the fraction of the field's Sq (`sq_um`, asked
    /// only then). Errors: a fraction that is not finite and positive, or an Sq of zero.
    pub(crate) fn epsilon_um(&self, sq_um: impl FnOnce() -> f64) -> Result<f64> {
        match self.epsilon {
            Epsilon::Um(e) => Ok(e),
            Epsilon::SqFraction(f) => {
                crate::field::positive_finite("epsilon_sq_fraction", f)?;
                let sq = sq_um();
                if sq <= 0.0 {
                    return Err(MeshError::Incompatible(format!(
                        "epsilon relative to Sq: the height field's Sq is {sq} um, so the bound \
                         would be zero; give an absolute epsilon in um"
                    )));
                }
                Ok(f * sq)
            }
        }
    }

    /// The insertion's parameters at the bound `epsilon_um`.
    pub(crate) fn tin_params(&self, epsilon_um: f64, keep_extremes: bool) -> TinParams {
        TinParams {
            epsilon_um,
            max_triangles: self.max_triangles,
            missing: self.missing,
            block_samples: self.block_samples,
            keep_extremes,
        }
    }
}

/// The fidelity report (issue item 5), in um.
#[derive(Debug, Clone, Serialize)]
pub struct Fidelity {
    /// The bound that was asked for, um.
    pub epsilon_um: f64,
    /// Achieved vertical error over the measured samples.
    pub error: ErrorStats,
    /// The bound holds at every measured sample the mesh covers.
    pub bound_met: bool,
    /// Sa, Sq, Sz, Sdr of the height field (missing samples left out).
    pub field: Option<AreaParams>,
    /// The same of the mesh resampled on the grid at the measured samples.
    pub mesh: Option<AreaParams>,
}

/// An adaptive mesh of a height field and how well it represents it.
#[derive(Debug, Clone)]
pub struct AdaptiveMesh {
    pub mesh: SolidMesh,
    pub kind: MeshKind,
    pub fidelity: Fidelity,
    /// The surface's triangles (the first `mesh.top_triangles`).
    pub surface_triangles: usize,
    /// Missing samples in the input, and how they were treated.
    pub missing_samples: usize,
    pub missing: MissingSamples,
    pub budget_reached: bool,
    /// The mesh resampled on the grid, um relative to the field's z offset (NaN: not covered).
    pub resampled_um: Vec<f32>,
}

/// Meshes `heights` (placed in scan coordinates by `at`) with the greedy error-bounded triangulation and closes it into a solid or keeps
/// it as a sheet. Errors: bad geometry or parameters, a solid asked with missing samples left as
/// holes (a solid needs a closed top), or a solid whose top no longer reaches the grid's rim.
/// In memory: the product is `stream::mesh_streaming` (the same mesh and STL bytes in bounded
/// memory); this twin is the tests' oracle.
pub fn mesh_height_field(
    heights: RasterView<'_, f32>,
    at: &ScanPlacement,
    params: &MeshParams,
) -> Result<AdaptiveMesh> {
    mesh_height_field_with(heights, at, params, false)
}

/// [`mesh_height_field`], optionally with every block's peak and valley kept as vertices
/// ([`TinParams::keep_extremes`]).
pub(crate) fn mesh_height_field_with(
    heights: RasterView<'_, f32>,
    at: &ScanPlacement,
    params: &MeshParams,
    keep_extremes: bool,
) -> Result<AdaptiveMesh> {
    check_adaptive(heights, at, params)?;
    let epsilon_um =
        params.epsilon_um(|| field_params(heights, at.pitch).map_or(0.0, |p| p.sq_um))?;
    let tin = triangulate(heights, &params.tin_params(epsilon_um, keep_extremes))?;
    finish_adaptive(heights, at, params, &tin, epsilon_um)
}

/// Checks what [`mesh_height_field`] checks before meshing.
pub(crate) fn check_adaptive(
    heights: RasterView<'_, f32>,
    at: &ScanPlacement,
    params: &MeshParams,
) -> Result<()> {
    validate(heights, at)?;
    params.solid.validate()?;
    if params.kind == MeshKind::Solid && params.missing == MissingSamples::Holes {
        return Err(MeshError::Incompatible(
            "a solid needs a closed top surface: missing samples must be filled (use a sheet \
             to keep them as holes)"
                .into(),
        ));
    }
    Ok(())
}

/// The adaptive mesh of a triangulation `tin` of `heights` made at `epsilon_um`: resampled,
/// compared, placed and closed as [`mesh_height_field`] does.
pub(crate) fn finish_adaptive(
    heights: RasterView<'_, f32>,
    at: &ScanPlacement,
    params: &MeshParams,
    tin: &Tin,
    epsilon_um: f64,
) -> Result<AdaptiveMesh> {
    let heights_um = heights.values();
    let (resampled_um, error) = resample_with_error(tin, heights_um);
    // Compare at the measured samples only.
    let mesh_at_measured: Vec<f32> = resampled_um
        .iter()
        .zip(heights_um)
        .map(|(&m, h)| if h.is_nan() { f32::NAN } else { m })
        .collect();
    let (field_params, mesh_params) = compare(heights, &mesh_at_measured, at.pitch);

    // Place the vertices as the grid solid does: x, y from the sample's index, z from its
    // height; re-centred from small numbers so that no precision is lost.
    let mut used = vec![u32::MAX; tin.vertex_samples.len()];
    let mut samples = Vec::new();
    let mut top = Vec::with_capacity(tin.triangles.len());
    for t in &tin.triangles {
        top.push(t.map(|v| {
            if used[v as usize] == u32::MAX {
                used[v as usize] = samples.len() as u32;
                samples.push(tin.vertex_samples[v as usize] as usize);
            }
            used[v as usize]
        }));
    }
    if top.is_empty() {
        return Err(MeshError::Incompatible(
            "no triangle has three measured corners: nothing to mesh".into(),
        ));
    }
    let (min_um, max_um) =
        samples
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &s| {
                let h = f64::from(tin.filled_um[s]);
                (lo.min(h), hi.max(h))
            });
    let place = VertexPlacement::new(params, at, heights.shape(), min_um, max_um);
    let mut vertices: Vec<[f64; 3]> = samples
        .iter()
        .map(|&s| place.vertex(s, tin.filled_um[s]))
        .collect();
    let (offset_um, base_depth_um) = (place.offset_um(), place.base_depth_um);
    let surface_triangles = top.len();
    let mut triangles = top;
    if params.kind == MeshKind::Solid {
        let rim = tin.rim.as_ref().ok_or_else(|| {
            MeshError::Incompatible(
                "the mesh's top does not reach the whole rim of the grid; cannot close it".into(),
            )
        })?;
        let rim: Vec<u32> = rim.iter().map(|&v| used[v as usize]).collect();
        close_top_surface(&mut vertices, &mut triangles, &rim, place.base_z())?;
    }
    let bound_met = error.max_um <= epsilon_um;
    Ok(AdaptiveMesh {
        mesh: SolidMesh {
            vertices,
            triangles,
            offset_um,
            units: params.solid.units,
            filled_samples: if params.missing == MissingSamples::Fill {
                tin.missing_samples
            } else {
                0
            },
            top_triangles: surface_triangles,
            base_depth_um,
        },
        kind: params.kind,
        fidelity: Fidelity {
            epsilon_um,
            error,
            bound_met,
            field: field_params,
            mesh: mesh_params,
        },
        surface_triangles,
        missing_samples: tin.missing_samples,
        missing: params.missing,
        budget_reached: tin.budget_reached,
        resampled_um,
    })
}

/// Where the vertices of an adaptive mesh go: x, y from the sample's index, z from its height,
/// re-centred from small numbers so that no precision is lost (the grid's centre at x = y = 0,
/// the base at z = 0; see [`SolidMesh`]). One copy for the in-memory and the streaming mesher,
/// so both place every vertex on the same f64.
#[derive(Debug, Clone, Copy)]
pub(crate) struct VertexPlacement {
    at: ScanPlacement,
    cols: usize,
    centre_col: f64,
    centre_row: f64,
    /// Lowest and highest height of the used vertices, um (relative to the z offset).
    min_um: f64,
    pub(crate) base_depth_um: f64,
    um_per_unit: f64,
    recentre: bool,
}

impl VertexPlacement {
    /// The placement for a mesh of `params.kind` whose vertices' heights span
    /// `min_um..=max_um` on a grid of `shape`.
    pub(crate) fn new(
        params: &MeshParams,
        at: &ScanPlacement,
        shape: surfstream_core::raster::Shape,
        min_um: f64,
        max_um: f64,
    ) -> Self {
        let base_depth_um = match params.kind {
            MeshKind::Solid => params
                .solid
                .base_depth_um
                .unwrap_or_else(|| default_base_depth_um(max_um - min_um)),
            MeshKind::Sheet => 0.0,
        };
        let (centre_col, centre_row) = shape.centre_px();
        Self {
            at: *at,
            cols: shape.cols,
            centre_col,
            centre_row,
            min_um,
            base_depth_um,
            um_per_unit: params.solid.units.um_per_unit(),
            recentre: params.solid.recentre,
        }
    }

    /// Scan position (um) of the output origin (zero without recentring).
    pub(crate) fn offset_um(&self) -> [f64; 3] {
        let at = &self.at;
        if self.recentre {
            [
                at.origin_x_um + self.centre_col * at.pitch.x_um(),
                at.origin_y_um + self.centre_row * at.pitch.y_um(),
                at.z_offset_um + self.min_um - self.base_depth_um,
            ]
        } else {
            [0.0; 3]
        }
    }

    /// The base plane's z, output units.
    pub(crate) fn base_z(&self) -> f64 {
        let base_z_um = if self.recentre {
            0.0
        } else {
            self.at.z_offset_um + self.min_um - self.base_depth_um
        };
        base_z_um / self.um_per_unit
    }

    /// The vertex of grid sample `s` at height `h_um` (filled), output units.
    pub(crate) fn vertex(&self, s: usize, h_um: f32) -> [f64; 3] {
        let at = &self.at;
        let (i, j) = ((s / self.cols) as f64, (s % self.cols) as f64);
        let h = f64::from(h_um);
        let p = if self.recentre {
            [
                (j - self.centre_col) * at.pitch.x_um(),
                (i - self.centre_row) * at.pitch.y_um(),
                (h - self.min_um) + self.base_depth_um,
            ]
        } else {
            [
                at.origin_x_um + j * at.pitch.x_um(),
                at.origin_y_um + i * at.pitch.y_um(),
                at.z_offset_um + h,
            ]
        };
        p.map(|c| c / self.um_per_unit)
    }
}

impl AdaptiveMesh {
    /// The statistics written to run.json (everything but the file names).
    pub fn record(&self) -> Result<AdaptiveSummary, record::RecordError> {
        adaptive_summary(
            self.kind,
            &MeshCounts::of(&self.mesh),
            self.missing_samples,
            self.missing,
            self.budget_reached,
            &self.fidelity,
        )
    }

    /// [`AdaptiveMesh::record`] as a JSON object (the mesh verb's OUT.json starts from it).
    pub fn summary(&self) -> Result<serde_json::Value, record::RecordError> {
        self.record()?.to_value()
    }
}

/// The sizes of a finished mesh, as run.json reports them (whether the mesh is in memory or
/// was streamed to its file).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MeshCounts {
    pub units: crate::LengthUnit,
    pub offset_um: [f64; 3],
    pub triangles: usize,
    /// The surface's triangles (the first ones); the rest are walls and base.
    pub top_triangles: usize,
    pub vertices: usize,
    pub filled_samples: usize,
    pub base_depth_um: f64,
}

impl MeshCounts {
    pub fn of(mesh: &SolidMesh) -> Self {
        Self {
            units: mesh.units,
            offset_um: mesh.offset_um,
            triangles: mesh.triangles.len(),
            top_triangles: mesh.top_triangles,
            vertices: mesh.vertices.len(),
            filled_samples: mesh.filled_samples,
            base_depth_um: mesh.base_depth_um,
        }
    }
}

/// The statistics written to run.json and OUT.json for an adaptive mesh.
pub(crate) fn adaptive_summary(
    kind: MeshKind,
    mesh: &MeshCounts,
    missing_samples: usize,
    missing: MissingSamples,
    budget_reached: bool,
    fidelity: &Fidelity,
) -> Result<AdaptiveSummary, record::RecordError> {
    Ok(AdaptiveSummary {
        counts: *mesh,
        record: AdaptiveMeshRecord {
            kind: serde_name(&kind)?,
            offset_rule: OFFSET_RULE.into(),
            surface_triangles: mesh.top_triangles as u64,
            missing_samples: missing_samples as u64,
            missing: serde_name(&missing)?,
            budget_reached,
            fidelity: fidelity.into(),
            element_quality: None,
        },
    })
}

/// How `offset_um` maps the STL's vertices to scan coordinates (the report's `offset_rule`).
pub const OFFSET_RULE: &str = "scan_um = vertex * um_per_unit + offset_um";

/// The name serde gives a unit-like enum value ("solid", "fill", "keep"), the one the report
/// has always carried.
pub(crate) fn serde_name<T: Serialize>(v: &T) -> Result<String, record::RecordError> {
    Ok(match record::to_value(v)? {
        serde_json::Value::String(s) => s,
        other => other.to_string(),
    })
}

/// An adaptive mesh's statistics: the sizes (they stand among the report's common fields) and
/// the adaptive mesh's own part.
#[derive(Debug, Clone, PartialEq)]
pub struct AdaptiveSummary {
    pub counts: MeshCounts,
    pub record: AdaptiveMeshRecord,
}

impl AdaptiveSummary {
    /// As a JSON object: the record and the sizes it is written with (the mesh verb's
    /// report starts from it).
    pub fn to_value(&self) -> Result<serde_json::Value, record::RecordError> {
        let mut v = record::to_value(&self.record)?;
        if let Some(o) = v.as_object_mut() {
            let c = &self.counts;
            o.insert("units".into(), c.units.symbol().into());
            o.insert("offset_um".into(), record::to_value(&c.offset_um)?);
            o.insert("triangles".into(), c.triangles.into());
            o.insert("vertices".into(), c.vertices.into());
            o.insert("base_depth_um".into(), record::to_value(&c.base_depth_um)?);
        }
        Ok(v)
    }
}
