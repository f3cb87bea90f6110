//! A height field as an error-bounded mesh ([`crate::tin`]) made into an STL-ready solid or
//! sheet, with its fidelity: the achieved vertical error and the areal parameters of the mesh
//! resampled on the grid beside those of the height field.

use serde::{Deserialize, Serialize};

use crate::error::{MeshError, Result};
use crate::fidelity::{compare, field_params, AreaParams};
use surfstream_core::raster::RasterView;

use crate::field::{validate, ScanPlacement};
use crate::solid::{close_top_surface, default_base_depth_um, SolidMesh, SolidParams};
use crate::tin::{resample_with_error, triangulate, ErrorStats, MissingSamples, TinParams};

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
pub fn mesh_height_field(
    heights: RasterView<'_, f32>,
    at: &ScanPlacement,
    params: &MeshParams,
) -> Result<AdaptiveMesh> {
    validate(heights, at)?;
    let heights_um = heights.values();
    params.solid.validate()?;
    if params.kind == MeshKind::Solid && params.missing == MissingSamples::Holes {
        return Err(MeshError::Incompatible(
            "a solid needs a closed top surface: missing samples must be filled (use a sheet \
             to keep them as holes)"
                .into(),
        ));
    }
    let epsilon_um = match params.epsilon {
        Epsilon::Um(e) => e,
        Epsilon::SqFraction(f) => {
            crate::field::positive_finite("epsilon_sq_fraction", f)?;
            let field = field_params(heights, at.pitch_x_um, at.pitch_y_um);
            let sq = field.map_or(0.0, |p| p.sq_um);
            if sq <= 0.0 {
                return Err(MeshError::Incompatible(format!(
                    "epsilon relative to Sq: the height field's Sq is {sq} um, so the bound \
                     would be zero; give an absolute epsilon in um"
                )));
            }
            f * sq
        }
    };
    let tin = triangulate(
        heights,
        &TinParams {
            epsilon_um,
            max_triangles: params.max_triangles,
            missing: params.missing,
            block_samples: params.block_samples,
        },
    )?;
    let (resampled_um, error) = resample_with_error(&tin, heights_um);
    // Compare at the measured samples only.
    let mesh_at_measured: Vec<f32> = resampled_um
        .iter()
        .zip(heights_um)
        .map(|(&m, h)| if h.is_nan() { f32::NAN } else { m })
        .collect();
    let (field_params, mesh_params) =
        compare(heights, &mesh_at_measured, at.pitch_x_um, at.pitch_y_um);

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
    let base_depth_um = match params.kind {
        MeshKind::Solid => params
            .solid
            .base_depth_um
            .unwrap_or_else(|| default_base_depth_um(max_um - min_um)),
        MeshKind::Sheet => 0.0,
    };
    let um_per_unit = params.solid.units.um_per_unit();
    let cols = heights.cols();
    let (centre_col, centre_row) = heights.shape().centre_px();
    let recentre = params.solid.recentre;
    let offset_um = if recentre {
        [
            at.origin_x_um + centre_col * at.pitch_x_um,
            at.origin_y_um + centre_row * at.pitch_y_um,
            at.z_offset_um + min_um - base_depth_um,
        ]
    } else {
        [0.0; 3]
    };
    let mut vertices: Vec<[f64; 3]> = samples
        .iter()
        .map(|&s| {
            let (i, j) = ((s / cols) as f64, (s % cols) as f64);
            let h = f64::from(tin.filled_um[s]);
            let p = if recentre {
                [
                    (j - centre_col) * at.pitch_x_um,
                    (i - centre_row) * at.pitch_y_um,
                    (h - min_um) + base_depth_um,
                ]
            } else {
                [
                    at.origin_x_um + j * at.pitch_x_um,
                    at.origin_y_um + i * at.pitch_y_um,
                    at.z_offset_um + h,
                ]
            };
            p.map(|c| c / um_per_unit)
        })
        .collect();
    let surface_triangles = top.len();
    let mut triangles = top;
    if params.kind == MeshKind::Solid {
        let rim = tin.rim.as_ref().ok_or_else(|| {
            MeshError::Incompatible(
                "the mesh's top does not reach the whole rim of the grid; cannot close it".into(),
            )
        })?;
        let rim: Vec<u32> = rim.iter().map(|&v| used[v as usize]).collect();
        let base_z_um = if recentre {
            0.0
        } else {
            at.z_offset_um + min_um - base_depth_um
        };
        close_top_surface(&mut vertices, &mut triangles, &rim, base_z_um / um_per_unit)?;
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

impl AdaptiveMesh {
    /// The statistics written to run.json and OUT.json (everything but the file names).
    pub fn summary(&self) -> serde_json::Value {
        serde_json::json!({
            "kind": self.kind,
            "units": self.mesh.units.symbol(),
            "offset_um": self.mesh.offset_um,
            "offset_rule": "scan_um = vertex * um_per_unit + offset_um",
            "triangles": self.mesh.triangles.len(),
            "surface_triangles": self.surface_triangles,
            "vertices": self.mesh.vertices.len(),
            "base_depth_um": self.mesh.base_depth_um,
            "missing_samples": self.missing_samples,
            "missing": self.missing,
            "budget_reached": self.budget_reached,
            "fidelity": self.fidelity,
        })
    }
}
