//! One height map meshed to an STL file with its statistics: the steps the `surfstream mesh`
//! verb and the Python binding's `mesh` share, so that the two cannot drift (issue 24).
//!
//! [`prepare_heights`] turns the map's f64 heights into the frame's f32 about their mean
//! (refusing a map with no measured sample or an infinite one) and finds spikes;
//! [`mesh_map`] places them, chooses the method (an engine's regular grid, a fixed vertical
//! bound, or the fewest triangles that meet a tolerance), meshes streamed
//! ([`crate::mesh_streaming`], [`crate::mesh_streaming_to_tolerance`]: the triangles wait in a
//! spill file in the STL's folder), writes the STL and returns the statistics as one typed
//! value ([`MapStats`], what the verb writes to `OUT.json` and Python returns).

use std::path::Path;
use std::time::Instant;

use anyhow::{anyhow, bail, Context, Result};
use serde::Serialize;
use serde_json::{Map, Value};
use surfstream_core::frame::to_frame_heights;
use surfstream_core::raster::{RasterView, Shape};

use crate::job::DEFAULT_EPSILON_SQ_FRACTION;
use crate::outliers::{find_spikes, OutlierPolicy, OutlierReport};
use crate::{
    grid_sheet_for, mesh_streaming, mesh_streaming_to_tolerance, EngineProfile, Epsilon,
    LengthUnit, MeshError, MeshKind, MeshParams, MissingSamples, ScanPlacement, SolidParams,
    StreamedMesh, TargetMesh, TargetMethod, ToleranceReport, ToleranceSettings,
};

/// The heights to mesh: f32 about their mean (so that f32 keeps nanometres however far up
/// the z axis the part sits; the mean comes back in the offset), spikes found.
pub struct PreparedHeights {
    pub heights_um: Vec<f32>,
    pub z_offset_um: f64,
    pub shape: Shape,
    pub spikes: OutlierReport,
}

/// `heights_um` (row-major, `shape`, NaN = not measured) as [`PreparedHeights`]; with
/// [`OutlierPolicy::Remove`] the spikes become NaN. Errors: no measured sample, or an infinite
/// sample ([`MeshError::InfiniteSample`]: only NaN marks a missing sample).
pub fn prepare_heights(
    heights_um: &[f64],
    shape: Shape,
    policy: OutlierPolicy,
) -> Result<PreparedHeights> {
    if heights_um.len() != shape.rows * shape.cols {
        bail!(
            "the map holds {} heights, its shape says {shape}",
            heights_um.len()
        );
    }
    if !heights_um.iter().any(|h| h.is_finite()) {
        bail!("no measured sample (all NaN)");
    }
    // Refused before it enters the mean.
    if let Some(k) = heights_um.iter().position(|h| h.is_infinite()) {
        let cols = shape.cols.max(1);
        return Err(MeshError::InfiniteSample {
            row: k / cols,
            col: k % cols,
            value: heights_um[k] as f32,
        }
        .into());
    }
    let (z_offset_um, mut heights) = to_frame_heights(heights_um);
    let (spikes, spike_at) = find_spikes(RasterView::new(&heights, shape)?, policy);
    if policy == OutlierPolicy::Remove {
        for &k in &spike_at {
            heights[k] = f32::NAN;
        }
    }
    Ok(PreparedHeights {
        heights_um: heights,
        z_offset_um,
        shape,
        spikes,
    })
}

/// The mesh's shape as a caller states it (the verb's flags, Python's arguments).
#[derive(Debug, Clone, Copy)]
pub struct MeshOptions {
    /// A fixed vertical bound (`None`: 0.05 x Sq when a fixed bound is used).
    pub fixed: Option<Epsilon>,
    pub max_triangles: Option<usize>,
    /// The open surface instead of a closed solid.
    pub sheet: bool,
    /// Missing samples left as holes (a sheet only).
    pub holes: bool,
    pub units: LengthUnit,
    pub base_depth_um: Option<f64>,
}

impl MeshOptions {
    /// The mesher's parameters; an engine's profile sets kind and units.
    pub fn params(&self, profile: Option<EngineProfile>) -> MeshParams {
        MeshParams {
            epsilon: self
                .fixed
                .unwrap_or(Epsilon::SqFraction(DEFAULT_EPSILON_SQ_FRACTION)),
            max_triangles: self.max_triangles,
            kind: if self.sheet || profile.is_some_and(|p| !p.solid) {
                MeshKind::Sheet
            } else {
                MeshKind::Solid
            },
            missing: if self.holes {
                MissingSamples::Holes
            } else {
                MissingSamples::Fill
            },
            solid: SolidParams {
                units: profile.map_or(self.units, |p| p.units),
                base_depth_um: self.base_depth_um,
                recentre: true,
            },
            block_samples: None,
        }
    }
}

/// How the surface is meshed (an engine's grid profile overrides both).
#[derive(Debug, Clone, Copy)]
pub enum MapBound {
    /// At most `params.epsilon` between any measured sample and the mesh.
    Fixed,
    /// The fewest triangles that meet the tolerance (the smallest angle from the engine's
    /// profile when it bounds one).
    Tolerance(ToleranceSettings),
}

/// What [`mesh_map`] meshes and where it writes.
pub struct MapRequest<'a> {
    pub heights: &'a PreparedHeights,
    pub pitch: surfstream_core::Pitch,
    pub params: MeshParams,
    pub profile: Option<EngineProfile>,
    pub bound: MapBound,
    /// The measured roughness on the same grid (relative to its mean), judged by the
    /// tolerance.
    pub roughness_um: Option<&'a [f32]>,
    /// ASCII STL (an engine's profile decides instead when given).
    pub ascii: bool,
    /// The STL; its folder is created and holds the spill file while the mesh is made.
    pub stl: &'a Path,
    /// The input file and its format, for the statistics (None: not from a file).
    pub input: Option<(String, String)>,
}

/// The statistics of one meshed map: the mesher's own summary (a JSON object, flattened) and
/// what the file, the checks and the search add. [`MapStats::to_json`] sorts the keys.
#[derive(Debug, Clone, Serialize)]
pub struct MapStats {
    #[serde(flatten)]
    pub summary: Map<String, Value>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub input: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub input_format: Option<String>,
    /// The form removed from the heights before meshing, when the caller levelled them
    /// (the verb's `--level`: "least-squares plane", as `params --level`); absent: the mean
    /// only. The mesh and its tolerance are then of the levelled surface.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub form_removed: Option<&'static str>,
    /// The STL's file name.
    pub stl: String,
    /// "ascii" or "binary".
    pub format: &'static str,
    pub pitch_um: [f64; 2],
    /// Seconds spent meshing (not writing).
    pub mesh_s: f64,
    #[serde(flatten)]
    pub method: MethodStats,
}

/// What the method adds to [`MapStats`].
#[derive(Debug, Clone, Serialize)]
#[serde(untagged)]
// One value per map meshed: the variants' sizes do not matter.
#[allow(clippy::large_enum_variant)]
pub enum MethodStats {
    Model(ModelStats),
    Grid(GridStats),
}

/// The model (fixed bound or tolerance): the closed-solid checks, the search, the spikes.
#[derive(Debug, Clone, Serialize)]
pub struct ModelStats {
    pub grid_rows_cols: [usize; 2],
    #[serde(skip_serializing_if = "Option::is_none")]
    pub target: Option<EngineProfile>,
    pub watertight: bool,
    pub consistently_oriented: bool,
    pub degenerate_triangles: usize,
    pub duplicate_triangles: usize,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tolerance: Option<ToleranceReport>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub element_quality: Option<ElementQualityStats>,
    pub outliers: OutlierReport,
}

/// The smallest angle against the engine's bound (tolerance with an angle bound only).
#[derive(Debug, Clone, Serialize)]
pub struct ElementQualityStats {
    pub min_angle_deg: f64,
    pub min_angle_bound_deg: f64,
    pub below_bound: u64,
}

/// An engine's regular grid.
#[derive(Debug, Clone, Serialize)]
pub struct GridStats {
    pub units: crate::LengthUnit,
    pub triangles: usize,
    pub surface_triangles: usize,
    pub measured_grid_rows_cols: [usize; 2],
    pub offset_um: [f64; 3],
    pub offset_rule: &'static str,
    pub filled_samples: usize,
}

impl MapStats {
    /// As a JSON object with its keys sorted (`OUT.json`, Python's `mesh`).
    pub fn to_json(&self) -> Result<Value> {
        serde_json::to_value(self).map_err(|e| anyhow!("mesh statistics: {e}"))
    }
}

/// The mesh made, for the caller's own lines.
#[allow(clippy::large_enum_variant)]
pub enum MapMesh {
    Model(StreamedMesh),
    Grid(TargetMesh),
}

/// What [`mesh_map`] made.
pub struct MapOutcome {
    pub mesh: MapMesh,
    pub stats: MapStats,
}

/// Meshes `r.heights` as `r` says, writes the STL at `r.stl` and returns the mesh and its
/// statistics.
pub fn mesh_map(r: &MapRequest) -> Result<MapOutcome> {
    // The statistics name the STL by its file name: a path without one is refused first.
    if r.stl.file_name().is_none() {
        bail!(
            "{}: expected a path ending in the STL's file name",
            r.stl.display()
        );
    }
    // Every caller (the verb, Python, the finishing patch) refuses what the verb refuses: an
    // STL named otherwise (`x.obj`) is not written.
    if !(r.stl.extension()).is_some_and(|e| e.eq_ignore_ascii_case("stl")) {
        return Err(MeshError::Incompatible(format!(
            "{}: mesh writes STL; name the output OUT.stl (the statistics go to OUT.json)",
            r.stl.display()
        ))
        .into());
    }
    let p = r.heights;
    let heights = RasterView::new(&p.heights_um, p.shape)?;
    let at = ScanPlacement::new(r.pitch).with_z_offset(p.z_offset_um);
    if let Some(profile) = r.profile.filter(|p| p.method == TargetMethod::Grid) {
        return grid_target(r, heights, &at, &profile);
    }
    let t0 = Instant::now();
    let (mut m, tolerance) = model(r, heights, &at)?;
    let mesh_s = t0.elapsed().as_secs_f64();
    let ascii = r.profile.map_or(r.ascii, |p| p.ascii);
    // The writer adds units and offset to the label (stl::stl_header); the closed-solid check
    // is made as the triangles pass.
    let mut check = None;
    surfstream_core::fsutil::write_atomic(r.stl, |w| {
        check = Some(m.write_stl(w, ascii, "surfstream mesh", heights)?);
        Ok(())
    })?;
    let check = check.ok_or_else(|| anyhow!("{}: nothing written", r.stl.display()))?;
    let mut summary = object(m.summary.to_value())?;
    summary.remove("grid_px");
    let element_quality =
        tolerance
            .as_ref()
            .and_then(|t| t.angles.as_ref())
            .map(|q| ElementQualityStats {
                min_angle_deg: q.min_angle_deg,
                min_angle_bound_deg: q.bound_deg,
                below_bound: q.below_bound,
            });
    let method = MethodStats::Model(ModelStats {
        grid_rows_cols: [p.shape.rows, p.shape.cols],
        target: r.profile,
        watertight: check.watertight,
        consistently_oriented: check.consistently_oriented,
        degenerate_triangles: check.degenerate_triangles,
        duplicate_triangles: check.duplicate_triangles,
        tolerance,
        element_quality,
        outliers: p.spikes.clone(),
    });
    let stats = stats(r, summary, ascii, mesh_s, method);
    Ok(MapOutcome {
        mesh: MapMesh::Model(m),
        stats,
    })
}

/// The common part of the statistics; the method's keys replace the summary's.
fn stats(
    r: &MapRequest,
    mut summary: Map<String, Value>,
    ascii: bool,
    mesh_s: f64,
    method: MethodStats,
) -> MapStats {
    if let Ok(Value::Object(o)) = serde_json::to_value(&method) {
        for key in o.keys() {
            summary.remove(key);
        }
    }
    for key in [
        "input",
        "input_format",
        "stl",
        "format",
        "pitch_um",
        "mesh_s",
    ] {
        summary.remove(key);
    }
    MapStats {
        summary,
        input: r.input.as_ref().map(|i| i.0.clone()),
        input_format: r.input.as_ref().map(|i| i.1.clone()),
        form_removed: None,
        // Present: mesh_map checked it.
        stl: r
            .stl
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default(),
        format: if ascii { "ascii" } else { "binary" },
        pitch_um: [r.pitch.x_um(), r.pitch.y_um()],
        mesh_s,
        method,
    }
}

fn object(v: Value) -> Result<Map<String, Value>> {
    match v {
        Value::Object(o) => Ok(o),
        _ => bail!("mesh summary is not an object"),
    }
}

/// At a fixed vertical bound, or the fewest triangles that meet the tolerance; streamed, the
/// triangles spilled into the STL's folder (created here).
fn model(
    r: &MapRequest,
    heights: RasterView<'_, f32>,
    at: &ScanPlacement,
) -> Result<(StreamedMesh, Option<ToleranceReport>)> {
    // An engine that refuses slivers gets the tolerance mesh with its angles bounded.
    let min_angle_deg = r.profile.map(|p| p.min_angle_deg).filter(|&deg| deg > 0.0);
    let spill_dir = match r.stl.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let settings = match (r.bound, r.profile, min_angle_deg) {
        (MapBound::Fixed, Some(p), Some(_)) => bail!(
            "target {} needs the model from a tolerance (its smallest angle is bounded \
             there) or its regular grid, not a fixed vertical bound (the verb's --epsilon-um / \
             --epsilon-sq, Python's tolerance_um / tolerance_sq)",
            p.engine.name()
        ),
        (MapBound::Fixed, _, _) => None,
        (MapBound::Tolerance(s), _, _) => Some(ToleranceSettings { min_angle_deg, ..s }),
    };
    std::fs::create_dir_all(spill_dir)
        .with_context(|| format!("{}: cannot create the folder", spill_dir.display()))?;
    Ok(match settings {
        None => (mesh_streaming(heights, at, &r.params, spill_dir)?, None),
        Some(s) => {
            let (m, t) =
                mesh_streaming_to_tolerance(heights, r.roughness_um, at, &r.params, &s, spill_dir)?;
            (m, Some(t))
        }
    })
}

/// An engine's regular-grid sheet: block-averaged to its triangle budget, elements checked
/// against its limits, written in its format and units.
fn grid_target(
    r: &MapRequest,
    heights: RasterView<'_, f32>,
    at: &ScanPlacement,
    profile: &EngineProfile,
) -> Result<MapOutcome> {
    let t0 = Instant::now();
    let t = grid_sheet_for(heights, at, profile)?;
    let mesh_s = t0.elapsed().as_secs_f64();
    let label = format!("surfstream mesh for {}", profile.engine.name());
    surfstream_core::fsutil::write_atomic(r.stl, |w| {
        if profile.ascii {
            crate::write_stl_ascii(w, &t.mesh, &label)?;
        } else {
            crate::write_stl_binary(w, &t.mesh, &label)?;
        }
        Ok(())
    })?;
    let method = MethodStats::Grid(GridStats {
        units: profile.units,
        triangles: t.mesh.triangles.len(),
        surface_triangles: t.mesh.triangles.len(),
        measured_grid_rows_cols: [heights.rows(), heights.cols()],
        offset_um: t.mesh.offset_um,
        offset_rule: "scan_um = vertex * um_per_unit + offset_um",
        filled_samples: t.mesh.filled_samples,
    });
    let stats = stats(r, object(t.summary())?, profile.ascii, mesh_s, method);
    Ok(MapOutcome {
        mesh: MapMesh::Grid(t),
        stats,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{check_closed, mesh_height_field, write_stl_binary, DemEngine};
    use surfstream_core::Pitch;

    /// A tilted wavy 40 x 50 map about 30 um up, one sample not measured, one spike.
    fn map() -> (Vec<f64>, Shape) {
        let shape = Shape::new(40, 50);
        let mut h: Vec<f64> = (0..shape.rows * shape.cols)
            .map(|k| {
                let (y, x) = ((k / shape.cols) as f64, (k % shape.cols) as f64);
                30.0 + 0.01 * x + (x / 5.0).sin() + 0.3 * (y / 7.0).cos()
            })
            .collect();
        h[7 * shape.cols + 9] = f64::NAN;
        h[20 * shape.cols + 25] += 40.0;
        (h, shape)
    }

    fn options() -> MeshOptions {
        MeshOptions {
            fixed: Some(Epsilon::Um(0.02)),
            max_triangles: None,
            sheet: false,
            holes: false,
            units: LengthUnit::Mm,
            base_depth_um: None,
        }
    }

    /// The streamed model written by `mesh_map` is the in-memory mesher's (the oracle) byte
    /// for byte, its statistics carry the oracle's counts and checks, and the spill leaves
    /// nothing beside the STL.
    #[test]
    fn the_model_is_the_in_memory_meshers() {
        let d = tempfile::tempdir().unwrap();
        let (h, shape) = map();
        let p = prepare_heights(&h, shape, OutlierPolicy::Keep).unwrap();
        assert_eq!(p.spikes.count, 1);
        let pitch = Pitch::new(0.5, 0.7).unwrap();
        let stl = d.path().join("m/w.stl");
        let params = options().params(None);
        let out = mesh_map(&MapRequest {
            heights: &p,
            pitch,
            params: params.clone(),
            profile: None,
            bound: MapBound::Fixed,
            roughness_um: None,
            ascii: false,
            stl: &stl,
            input: None,
        })
        .unwrap();
        let at = ScanPlacement::new(pitch).with_z_offset(p.z_offset_um);
        let view = RasterView::new(&p.heights_um, shape).unwrap();
        let m = mesh_height_field(view, &at, &params).unwrap();
        let mut want = Vec::new();
        write_stl_binary(&mut want, &m.mesh, "surfstream mesh").unwrap();
        assert!(std::fs::read(&stl).unwrap() == want, "STL bytes differ");
        let json = out.stats.to_json().unwrap();
        let oracle = m.summary();
        for key in ["triangles", "vertices", "fidelity", "offset_um"] {
            assert_eq!(json[key], oracle[key], "{key}");
        }
        assert_eq!(json["watertight"], check_closed(&m.mesh).watertight);
        assert_eq!(json["outliers"]["count"], 1);
        assert_eq!(json["stl"], "w.stl");
        assert!(json.get("input").is_none() && json.get("grid_px").is_none());
        let files: Vec<_> = std::fs::read_dir(stl.parent().unwrap()).unwrap().collect();
        assert_eq!(files.len(), 1);
    }

    /// An engine's grid: the STL `grid_sheet_for` makes, its counts in the statistics; a
    /// fixed bound with an engine that bounds angles is refused; so is an infinite sample.
    #[test]
    fn grid_targets_and_refusals() {
        let d = tempfile::tempdir().unwrap();
        let (h, shape) = map();
        let p = prepare_heights(&h, shape, OutlierPolicy::Remove).unwrap();
        assert!(p.heights_um[20 * shape.cols + 25].is_nan());
        let pitch = Pitch::square(1.0).unwrap();
        let mut profile = EngineProfile::with_budget(DemEngine::Yade, None);
        profile.method = TargetMethod::Grid;
        let stl = d.path().join("y.stl");
        let request = |profile, bound| MapRequest {
            heights: &p,
            pitch,
            params: options().params(Some(profile)),
            profile: Some(profile),
            bound,
            roughness_um: None,
            ascii: false,
            stl: &stl,
            input: Some(("in.npy".into(), "npy".into())),
        };
        let out = mesh_map(&request(profile, MapBound::Fixed)).unwrap();
        let at = ScanPlacement::new(pitch).with_z_offset(p.z_offset_um);
        let t = grid_sheet_for(
            RasterView::new(&p.heights_um, shape).unwrap(),
            &at,
            &profile,
        )
        .unwrap();
        let json = out.stats.to_json().unwrap();
        assert_eq!(json["triangles"], t.mesh.triangles.len());
        assert_eq!(json["measured_grid_rows_cols"][1], shape.cols);
        assert_eq!(json["input"], "in.npy");
        assert!(std::fs::metadata(&stl).unwrap().len() > 0);

        // An STL under another name is refused, as the verb refuses it, and nothing written.
        let obj = d.path().join("x.obj");
        let e = mesh_map(&MapRequest {
            stl: &obj,
            ..request(profile, MapBound::Fixed)
        })
        .err()
        .unwrap();
        assert!(e.to_string().contains("mesh writes STL"), "{e}");
        assert!(e.downcast_ref::<MeshError>().is_some(), "{e}");
        assert!(!obj.exists());

        let liggghts = EngineProfile::with_budget(DemEngine::Liggghts, None);
        let e = mesh_map(&request(liggghts, MapBound::Fixed)).err().unwrap();
        assert!(
            e.to_string().contains("needs the model from a tolerance"),
            "{e}"
        );

        let mut inf = h.clone();
        inf[3] = f64::INFINITY;
        let e = prepare_heights(&inf, shape, OutlierPolicy::Keep)
            .err()
            .unwrap();
        assert!(e.downcast_ref::<MeshError>().is_some(), "{e}");
        let nan = vec![f64::NAN; 6];
        assert!(prepare_heights(&nan, Shape::new(2, 3), OutlierPolicy::Keep).is_err());
    }
}
