//! The mesher's job in a graph, without IPC: its settings from the graph parameters
//! ([`MesherConfig`] -> [`MeshSettings`]), which surface it meshes and from which inputs
//! ([`SurfaceChoice`]), and [`MeshJob`], which keeps the final frame of every input until each
//! has ended its scan and then meshes the chosen surface once into a [`MeshedSurface`]: the
//! STL-ready solid or sheet, its check, the mesh resampled on the grid and the statistics for
//! run.json (with the fidelity report for the adaptive mesh).
//!
//! Live frames are counted and skipped: a mesh is made once, from the exact final surface.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use anyhow::{anyhow, bail, Result};
use serde::Deserialize;
use surfstream_core::frame::{flags, from_frame_heights, FrameHeader, FrameView, HeightMap};
use surfstream_core::fsutil::write_atomic;
use surfstream_core::raster::{Raster, RasterView, Shape};
use surfstream_core::record::{
    GridSheetRecord, MeshMethodRecord, MeshReport, OutliersRecord, ToleranceRecord,
};
use surfstream_io::npy::{write_npy_abs_f64, write_npy_f64};
use surfstream_io::sidecar::{write_sidecar, NpyGeometry};

use crate::outliers::{find_spikes, OutlierPolicy, OutlierReport};
use crate::report::{tolerance_parts, AdaptiveSummary};
use crate::target::{block_values_on_grid, DemEngine, EngineProfile, TargetMethod};
use crate::tolerance::{mesh_streaming_to_tolerance, mesh_to_tolerance, ToleranceSettings};
use crate::{
    check_closed, grid_sheet_for, grid_solid, grid_streaming, mesh_height_field, mesh_streaming,
    stl, Epsilon, LengthUnit, MeshCheck, MeshCounts, MeshKind, MeshParams, MissingSamples,
    ScanPlacement, SolidMesh, SolidParams,
};

/// The label in the STL header (before the unit and offset).
const STL_LABEL: &str = "surfstream surface";

/// The bound when the graph gives none: 5 % of the surface's Sq.
pub const DEFAULT_EPSILON_SQ_FRACTION: f64 = 0.05;

/// The mesher's graph parameters, as written in a graph file.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MesherConfig {
    /// STL coordinate unit: "mm" (default), "m" or "um".
    #[serde(default)]
    pub units: LengthUnit,
    /// "binary" (EDEM, Rocky, MercuryDPM) or "ascii" (LIGGGHTS).
    #[serde(default = "binary")]
    pub format: String,
    /// Base of the solid below the lowest sample, um (default: from the height range).
    pub base_depth_um: Option<f64>,
    #[serde(default = "stl_name")]
    pub file: String,
    /// "adaptive" (error-bounded, default) or "grid" (two triangles per grid cell).
    #[serde(default = "adaptive")]
    pub method: String,
    /// Largest vertical error, um (adaptive).
    pub epsilon_um: Option<f64>,
    /// Largest vertical error as a fraction of the surface's Sq (adaptive; default 0.05 when
    /// `epsilon_um` is not given).
    pub epsilon_sq_fraction: Option<f64>,
    /// Triangle budget of the surface (adaptive; with a tolerance, the search's limit).
    pub max_triangles: Option<usize>,
    /// The model's tolerance per region, percent: "sa=1,sq=1,sz=3" or { sa = 1, sq = 1, sz = 3 }
    /// (adaptive; the default when neither epsilon is given: Sa 1 %, Sq 1 %, Sz 3 %). The
    /// mesher then finds the fewest triangles that meet it ([`crate::tolerance`]).
    pub tolerance: Option<crate::Tolerance>,
    /// Side of the windows the tolerance is judged in, samples (default: half the map's
    /// shorter side, 64 to 1024).
    pub region_px: Option<usize>,
    /// How the tolerance search's insertion order is made: "balanced" (default) or "greedy"
    /// (the pointwise bound only; for comparison).
    #[serde(default)]
    pub model_method: crate::tolerance::ModelMethod,
    /// Spikes (isolated outliers, [`crate::outliers`]): "keep" (default: mesh what was
    /// measured; they are reported) or "remove" (treated as not measured, and reported).
    #[serde(default)]
    pub outliers: OutlierPolicy,
    /// "solid" (default) or "sheet" (adaptive).
    #[serde(default)]
    pub kind: MeshKind,
    /// "fill" (default) or "holes" (sheet only): missing samples.
    #[serde(default)]
    pub missing: MissingSamples,
    /// Which surface to mesh.
    #[serde(default)]
    pub surface: SurfaceChoice,
    /// "liggghts" | "mercurydpm" | "edem" | "yade": write what that engine imports
    /// ([`crate::target`]); sets the format, units, kind, method and triangle budget
    /// (`max_triangles` still lowers the budget).
    pub target: Option<DemEngine>,
}

fn adaptive() -> String {
    "adaptive".into()
}
fn binary() -> String {
    "binary".into()
}
fn stl_name() -> String {
    "surface.stl".into()
}

/// Which surface the mesher meshes, and the input ports that carry it: "panorama" (default:
/// the full-resolution surface, what the tolerance is judged against) or "pooled" (the
/// reference study's 4 x 4 max-pooled map, an option) arrive on the input `surface`; "datum" and "roughness" on the inputs of those
/// names; "datum+roughness" needs both and meshes their sum (the panorama as the separation
/// rebuilds it).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, serde::Serialize)]
pub enum SurfaceChoice {
    #[serde(rename = "pooled")]
    Pooled,
    #[default]
    #[serde(rename = "panorama")]
    Panorama,
    #[serde(rename = "datum+roughness")]
    DatumPlusRoughness,
    #[serde(rename = "datum")]
    Datum,
    #[serde(rename = "roughness")]
    Roughness,
}

impl SurfaceChoice {
    /// The input ports this choice needs (and the only ones it accepts).
    pub fn ports(self) -> &'static [&'static str] {
        match self {
            Self::Pooled | Self::Panorama => &["surface"],
            Self::DatumPlusRoughness => &["datum", "roughness"],
            Self::Datum => &["datum"],
            Self::Roughness => &["roughness"],
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Self::Pooled => "pooled",
            Self::Panorama => "panorama",
            Self::DatumPlusRoughness => "datum+roughness",
            Self::Datum => "datum",
            Self::Roughness => "roughness",
        }
    }

    /// The inputs this choice may also take: the panorama's measured roughness
    /// (`wavelet/roughness`), the reference that judges the roughness the mesh carries
    /// ([`crate::Tolerance::roughness_pct`]).
    pub fn optional_ports(self) -> &'static [&'static str] {
        match self {
            Self::Panorama => &["roughness"],
            _ => &[],
        }
    }

    /// The wiring must match the choice: a missing or an unused input is an error.
    pub fn check_wiring(self, wired: &[&str]) -> std::result::Result<(), String> {
        let needed = self.ports();
        if let Some(port) = needed.iter().find(|p| !wired.contains(p)) {
            return Err(format!(
                "surface = \"{}\" needs the input '{port}' (wired: {wired:?})",
                self.name()
            ));
        }
        let optional = self.optional_ports();
        if let Some(extra) = wired
            .iter()
            .find(|w| !needed.contains(w) && !optional.contains(w))
        {
            return Err(format!(
                "input '{extra}' is wired but surface = \"{}\" does not use it (it uses \
                 {needed:?}, and may take {optional:?})",
                self.name()
            ));
        }
        Ok(())
    }
}

/// How the STL is written.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StlFormat {
    /// EDEM, Rocky, MercuryDPM.
    Binary,
    /// LIGGGHTS.
    Ascii,
}

impl StlFormat {
    pub fn name(self) -> &'static str {
        match self {
            Self::Binary => "binary",
            Self::Ascii => "ascii",
        }
    }
}

/// The checked settings of a mesher.
#[derive(Debug, Clone, PartialEq)]
pub struct MeshSettings {
    pub solid: SolidParams,
    /// `None`: the full-grid solid.
    pub adaptive: Option<MeshParams>,
    pub format: StlFormat,
    pub surface: SurfaceChoice,
    /// The engine the STL is made for, when one was named.
    pub target: Option<EngineProfile>,
    /// The model from a tolerance (adaptive only; `None`: the fixed bound of `adaptive`).
    pub tolerance: Option<ToleranceSettings>,
    /// Spikes kept (default) or removed before the adaptive mesh.
    pub outliers: OutlierPolicy,
}

impl MesherConfig {
    /// The checked settings; the error says which parameter is wrong and what was expected.
    pub fn settings(&self) -> std::result::Result<MeshSettings, String> {
        let format = match self.format.as_str() {
            "binary" => StlFormat::Binary,
            "ascii" => StlFormat::Ascii,
            other => {
                return Err(format!(
                    "format = {other:?}: expected \"binary\" or \"ascii\""
                ))
            }
        };
        let solid = SolidParams {
            units: self.units,
            base_depth_um: self.base_depth_um,
            recentre: true,
        };
        solid.validate().map_err(|e| e.to_string())?;
        let fixed_bound = self.epsilon_um.is_some() || self.epsilon_sq_fraction.is_some();
        if self.tolerance.is_some() && fixed_bound {
            return Err(
                "give a tolerance or a fixed bound (epsilon_um / epsilon_sq_fraction), not both"
                    .into(),
            );
        }
        if self.tolerance.is_some() && self.method != "adaptive" {
            return Err(format!(
                "tolerance needs method = \"adaptive\" (method = {:?} meshes every sample)",
                self.method
            ));
        }
        if let Some(px) = self.region_px {
            if px < 16 {
                return Err(format!(
                    "region_px = {px}: expected at least 16 (samples per side of a judged window)"
                ));
            }
        }
        let mut tolerance =
            (self.method == "adaptive" && !fixed_bound).then(|| ToleranceSettings {
                // Unless stated, the target's own (an angle-bounded one has no pointwise
                // maximum, [`EngineProfile::default_tolerance`]).
                tolerance: self.tolerance.unwrap_or_else(|| {
                    let profile = self.target.map(EngineProfile::for_engine);
                    ToleranceSettings::for_target(profile.as_ref()).tolerance
                }),
                region_px: self.region_px,
                method: self.model_method,
                min_angle_deg: None,
            });
        let adaptive = match self.method.as_str() {
            "grid" => None,
            "adaptive" => {
                let epsilon = match (self.epsilon_um, self.epsilon_sq_fraction) {
                    (Some(_), Some(_)) => {
                        return Err("give epsilon_um or epsilon_sq_fraction, not both".into())
                    }
                    (Some(e), None) => Epsilon::Um(e),
                    (None, f) => Epsilon::SqFraction(f.unwrap_or(DEFAULT_EPSILON_SQ_FRACTION)),
                };
                Some(MeshParams {
                    epsilon,
                    max_triangles: self.max_triangles,
                    kind: self.kind,
                    missing: self.missing,
                    solid: solid.clone(),
                    block_samples: None,
                })
            }
            other => {
                return Err(format!(
                    "method = {other:?}: expected \"adaptive\" or \"grid\""
                ))
            }
        };
        let mut settings = MeshSettings {
            solid,
            adaptive,
            format,
            surface: self.surface,
            target: None,
            tolerance: None,
            outliers: self.outliers,
        };
        if let Some(engine) = self.target {
            let mut profile = EngineProfile::with_budget(engine, self.max_triangles);
            // method = "grid" asks for the engine's regular grid instead of its adaptive mesh.
            if self.method == "grid" {
                profile.method = TargetMethod::Grid;
            }
            // An engine's regular grid is sized by its budget, not by a tolerance.
            if profile.method == TargetMethod::Grid {
                if self.tolerance.is_some() {
                    return Err(format!(
                        "target = {:?} with method = \"grid\" meshes a regular grid within \
                         its triangle budget; a tolerance applies to the adaptive mesh \
                         (remove one of them)",
                        engine.name()
                    ));
                }
                tolerance = None;
            } else if profile.min_angle_deg > 0.0 {
                // The angle bound refines the tolerance search's meshes; a fixed bound's
                // mesh has none.
                match tolerance.as_mut() {
                    Some(t) => t.min_angle_deg = Some(profile.min_angle_deg),
                    None => {
                        return Err(format!(
                            "target = {:?} needs the model from a tolerance (its smallest \
                             triangle angle is bounded there) or method = \"grid\"; remove \
                             epsilon_um / epsilon_sq_fraction",
                            engine.name()
                        ))
                    }
                }
            }
            settings.format = if profile.ascii {
                StlFormat::Ascii
            } else {
                StlFormat::Binary
            };
            settings.solid.units = profile.units;
            if let Some(a) = settings.adaptive.as_mut() {
                a.solid.units = profile.units;
                a.kind = if profile.solid {
                    MeshKind::Solid
                } else {
                    MeshKind::Sheet
                };
                a.max_triangles = Some(profile.max_triangles);
            }
            settings.target = Some(profile);
        }
        settings.tolerance = tolerance;
        Ok(settings)
    }
}

/// The surface, meshed.
pub struct MeshedSurface {
    pub solid: SolidMesh,
    pub check: MeshCheck,
    /// The adaptive mesh's or the engine grid sheet's own statistics (`None` for the grid
    /// solid).
    pub adaptive: Option<MethodSummary>,
    /// The mesh re-sampled on the meshed grid, absolute heights (um): for the grid mesh the
    /// samples themselves, for the adaptive one its interpolation (NaN where not covered). It
    /// is the "mesh" stage of the model-vs-measurement table (Table 6) in run.json.
    pub resampled_um: Raster<f64>,
    /// The header of the meshed surface's frame (grid, pitch, latency trace).
    pub header: FrameHeader,
}

impl MeshedSurface {
    /// Writes the solid as STL in `format`.
    pub fn write_stl(&self, w: &mut dyn std::io::Write, format: StlFormat) -> crate::Result<()> {
        let label = stl::stl_header(&self.solid, STL_LABEL);
        match format {
            StlFormat::Ascii => crate::write_stl_ascii(w, &self.solid, &label),
            StlFormat::Binary => crate::write_stl_binary(w, &self.solid, &label),
        }
    }

    /// The statistics for run.json (the caller adds files, wiring and times).
    pub fn summary(&self, settings: &MeshSettings) -> MeshReport {
        surface_summary(
            &MeshCounts::of(&self.solid),
            &self.check,
            self.adaptive.as_ref(),
            &self.header,
            settings,
        )
    }
}

/// What a method adds to the mesher's report.
// One value per mesh made: the variants' sizes do not matter.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone, PartialEq)]
pub enum MethodSummary {
    /// An adaptive mesh: its statistics, the tolerance search's record and the spikes found.
    Adaptive {
        summary: AdaptiveSummary,
        tolerance: Option<ToleranceRecord>,
        outliers: Option<OutliersRecord>,
    },
    /// An engine's regular-grid sheet.
    GridSheet(GridSheetRecord),
}

/// The statistics for run.json of a mesh in memory or streamed to its file; the node fills in
/// the files, the wiring and the times (`file`, `resampled`, `sources`, `t_written_ns`,
/// `live_frames_skipped`).
fn surface_summary(
    counts: &MeshCounts,
    check: &MeshCheck,
    method: Option<&MethodSummary>,
    h: &FrameHeader,
    settings: &MeshSettings,
) -> MeshReport {
    // An adaptive mesh's own sizes stand for the mesh's (they are the same mesh's).
    let (counts, units) = match method {
        Some(MethodSummary::Adaptive { summary, .. }) => {
            (&summary.counts, summary.counts.units.symbol())
        }
        _ => (counts, settings.solid.units.symbol()),
    };
    let (method_name, method_record, tolerance, outliers) = match method {
        Some(MethodSummary::Adaptive {
            summary,
            tolerance,
            outliers,
        }) => (
            "adaptive",
            Some(MeshMethodRecord::Adaptive(summary.record.clone())),
            tolerance.clone(),
            outliers.clone(),
        ),
        Some(MethodSummary::GridSheet(g)) => (
            "grid",
            Some(MeshMethodRecord::GridSheet(g.clone())),
            None,
            None,
        ),
        None => ("grid", None, None, None),
    };
    MeshReport {
        file: String::new(),
        resampled: String::new(),
        sources: BTreeMap::new(),
        t_acquired_ns: h.t_acquired_ns,
        t_written_ns: 0,
        live_frames_skipped: 0,
        format: settings.format.name().into(),
        units: units.into(),
        offset_um: counts.offset_um,
        triangles: counts.triangles as u64,
        top_triangles: counts.top_triangles as u64,
        vertices: counts.vertices as u64,
        filled_samples: counts.filled_samples as u64,
        base_depth_um: Some(counts.base_depth_um),
        watertight: check.watertight,
        consistently_oriented: check.consistently_oriented,
        grid_px: [u64::from(h.width), u64::from(h.height)],
        pitch_um: [h.pitch_x_um, h.pitch_y_um],
        surface: settings.surface.name().into(),
        target: settings.target.as_ref().map(Into::into),
        method: method_name.into(),
        method_record,
        tolerance,
        outliers,
    }
}

/// An adaptive mesh's statistics with the tolerance search's report ("tolerance") and, with
/// an angle bound (an engine's target), the element quality of the mesh written
/// ("element_quality", as the grid targets report it).
fn adaptive_method(
    mut summary: AdaptiveSummary,
    report: Option<&crate::ToleranceReport>,
) -> MethodSummary {
    let tolerance = report.map(|r| {
        let (record, quality) = tolerance_parts(r);
        summary.record.element_quality = quality;
        record
    });
    MethodSummary::Adaptive {
        summary,
        tolerance,
        outliers: None,
    }
}

/// Adds the spike report to an adaptive mesh's statistics ("outliers").
fn add_outliers(method: &mut Option<MethodSummary>, report: Option<&OutlierReport>) {
    if let (Some(MethodSummary::Adaptive { outliers, .. }), Some(r)) = (method.as_mut(), report) {
        *outliers = Some(r.into());
    }
}

/// What [`MeshJob::mesh_to_files`] wrote.
pub struct MeshFiles {
    /// The statistics for run.json (as [`MeshedSurface::summary`]).
    pub summary: MeshReport,
    pub check: MeshCheck,
    /// True when the adaptive mesh went through the streaming mesher ([`crate::stream`]).
    pub streamed: bool,
}

/// Collects the final surface from the inputs and meshes it once every input has ended.
pub struct MeshJob {
    settings: MeshSettings,
    /// The final frame per input port, and the ports whose scan has ended.
    finals: BTreeMap<String, HeightMap>,
    ended: BTreeSet<String>,
    live_frames: u64,
    /// The measured roughness is wired: the tolerance judges the roughness the mesh carries.
    roughness_reference: bool,
}

impl MeshJob {
    pub fn new(settings: MeshSettings) -> Self {
        Self {
            settings,
            finals: BTreeMap::new(),
            ended: BTreeSet::new(),
            live_frames: 0,
            roughness_reference: false,
        }
    }

    /// Waits for the measured roughness on the input `roughness` too, and judges the
    /// roughness the mesh carries against it (surface = "panorama", a tolerance).
    pub fn with_roughness_reference(mut self) -> Self {
        self.roughness_reference = self.settings.surface == SurfaceChoice::Panorama;
        self
    }

    /// The tolerance the search meets: without the measured roughness wired there is nothing
    /// to judge the roughness against, and the report does not claim that bound.
    fn tolerance(&self) -> Option<ToleranceSettings> {
        let mut t = self.settings.tolerance?;
        if !self.roughness_reference {
            t.tolerance.roughness_pct = None;
        }
        Some(t)
    }

    /// The input ports whose end of scan the job waits for.
    fn awaited_ports(&self) -> impl Iterator<Item = &'static str> + '_ {
        let reference: &[&str] = if self.roughness_reference {
            &["roughness"]
        } else {
            &[]
        };
        self.settings
            .surface
            .ports()
            .iter()
            .chain(reference)
            .copied()
    }

    pub fn settings(&self) -> &MeshSettings {
        &self.settings
    }

    /// Live (not final) frames seen and skipped.
    pub fn live_frames_skipped(&self) -> u64 {
        self.live_frames
    }

    /// Takes one frame from input `port`; true when it was the last end of scan the job waits
    /// for, so the surface is ready to mesh ([`MeshJob::mesh`]).
    pub fn accept(&mut self, port: &str, frame: FrameView<'_>) -> bool {
        if frame.header.has(flags::END_OF_SCAN) {
            self.ended.insert(port.to_owned());
            return self.awaited_ports().all(|p| self.ended.contains(p));
        }
        if frame.header.has(flags::FINAL) {
            self.finals.insert(port.to_owned(), frame.to_owned());
        } else {
            self.live_frames += 1;
        }
        false
    }

    /// The surface to mesh from the final frames: one input as is, or datum + roughness summed
    /// (the roughness is relative to the same z offset as the datum's frame, so the sum keeps
    /// the datum's offset).
    fn surface_to_mesh(&mut self) -> Result<HeightMap> {
        let mut take = |port: &str| {
            self.finals
                .remove(port)
                .ok_or_else(|| anyhow!("mesher: end of scan without a final '{port}' frame"))
        };
        match self.settings.surface {
            SurfaceChoice::Pooled | SurfaceChoice::Panorama => take("surface"),
            SurfaceChoice::Datum => take("datum"),
            SurfaceChoice::Roughness => take("roughness"),
            SurfaceChoice::DatumPlusRoughness => {
                let mut d = take("datum")?;
                let r = take("roughness")?;
                check_same_grid(("datum", &d), ("roughness", &r))?;
                for (z, &r) in d.heights.iter_mut().zip(&r.heights) {
                    *z += r;
                }
                Ok(d)
            }
        }
    }

    /// The measured roughness wired as the reference, on the surface's grid (takes its final
    /// frame); `None` when it is not wired.
    fn roughness_reference(&mut self, surface: &HeightMap) -> Result<Option<HeightMap>> {
        if !self.roughness_reference {
            return Ok(None);
        }
        let r = self
            .finals
            .remove("roughness")
            .ok_or_else(|| anyhow!("mesher: end of scan without a final 'roughness' frame"))?;
        check_same_grid(("panorama", surface), ("roughness", &r))?;
        Ok(Some(r))
    }

    /// Meshes the chosen surface (takes its final frames) in memory: the twin of
    /// [`MeshJob::mesh_to_files`], which the node runs. Only the tests call it, as the oracle
    /// the streamed files are compared with (the same STL bytes and statistics).
    pub fn mesh(&mut self) -> Result<MeshedSurface> {
        let mut s = self.surface_to_mesh()?;
        let reference = self.roughness_reference(&s)?;
        let spikes = self.spikes(&mut s);
        let mut m = self.mesh_in_memory(&s, reference.as_ref())?;
        add_outliers(&mut m.adaptive, spikes.as_ref());
        Ok(m)
    }

    /// The spikes of the surface an adaptive mesh is made of (reported; removed, i.e. set to
    /// not measured, when the settings ask for it).
    fn spikes(&self, s: &mut HeightMap) -> Option<OutlierReport> {
        if self.settings.adaptive.is_none() || self.grid_target().is_some() {
            return None;
        }
        let h = s.header;
        let shape = Shape::new(h.height as usize, h.width as usize);
        let view = RasterView::new(&s.heights, shape).ok()?;
        let (report, spikes) = find_spikes(view, self.settings.outliers);
        if self.settings.outliers == OutlierPolicy::Remove {
            for k in spikes {
                s.heights[k] = f32::NAN;
            }
        }
        Some(report)
    }

    /// The mesh in memory: the engines' grid sheets (bounded by their budgets) for
    /// [`MeshJob::mesh_to_files`]; every method for [`MeshJob::mesh`], the tests' oracle.
    fn mesh_in_memory(
        &self,
        s: &HeightMap,
        roughness: Option<&HeightMap>,
    ) -> Result<MeshedSurface> {
        let h = s.header;
        // The frame's grid: rows along y (header height), columns along x (header width).
        let shape = Shape::new(h.height as usize, h.width as usize);
        let heights = RasterView::new(&s.heights, shape).map_err(|e| anyhow!("mesher: {e}"))?;
        let at = ScanPlacement::of_frame(&h).map_err(|e| anyhow!("mesher: {e}"))?;
        let (solid, adaptive, resampled) = match (&self.settings.adaptive, self.grid_target()) {
            (_, Some(profile)) => {
                let t = grid_sheet_for(heights, &at, &profile)?;
                let on_grid = block_values_on_grid(t.block_means.view(), t.stride, shape);
                let summary = MethodSummary::GridSheet(t.record());
                (t.mesh, Some(summary), Some(on_grid.into_values()))
            }
            (None, None) => (grid_solid(heights, &at, &self.settings.solid)?, None, None),
            (Some(p), None) => {
                let (m, report) = match &self.tolerance() {
                    Some(t) => {
                        let reference = roughness.map(|r| &r.heights[..]);
                        let (m, r) = mesh_to_tolerance(heights, reference, &at, p, t)?;
                        (m, Some(r))
                    }
                    None => (mesh_height_field(heights, &at, p)?, None),
                };
                let summary = adaptive_method(m.record(), report.as_ref());
                (m.mesh, Some(summary), Some(m.resampled_um))
            }
        };
        let resampled = resampled.as_deref().unwrap_or(&s.heights);
        let resampled_um = Raster::new(from_frame_heights(h.z_offset_um, resampled), shape)
            .map_err(|e| anyhow!("mesher: resampled mesh: {e}"))?;
        let check = check_closed(&solid);
        Ok(MeshedSurface {
            solid,
            check,
            adaptive,
            resampled_um,
            header: h,
        })
    }

    fn grid_target(&self) -> Option<EngineProfile> {
        self.settings
            .target
            .filter(|p| p.method == TargetMethod::Grid)
    }

    /// Meshes the chosen surface (takes its final frames) and writes the STL to `stl` (atomically)
    /// and the mesh re-sampled on the grid (absolute um, f64) to `resampled_npy`: the same files
    /// and statistics as [`MeshJob::mesh`] followed by [`MeshedSurface::write_stl`], but the
    /// adaptive mesh is streamed ([`crate::stream`]): its triangles go through a spill file
    /// beside `stl`, so the memory held is a few bytes per sample whatever the triangle count.
    pub fn mesh_to_files(&mut self, stl: &Path, resampled_npy: &Path) -> Result<MeshFiles> {
        let mut s = self.surface_to_mesh()?;
        let reference = self.roughness_reference(&s)?;
        let spikes = self.spikes(&mut s);
        let (h, format) = (s.header, self.settings.format);
        let shape = Shape::new(h.height as usize, h.width as usize);
        // The re-sampled mesh is on the frame's grid: its pitch travels in the sidecar.
        let geometry = NpyGeometry {
            pitch_x_um: h.pitch_x_um,
            pitch_y_um: h.pitch_y_um,
            origin_um: Some([h.origin_x_um, h.origin_y_um]),
        };
        let params = match (&self.settings.adaptive, self.grid_target()) {
            (Some(p), None) => p.clone(),
            (None, None) => {
                // The full-grid solid, streamed: its mesh on the grid is the samples themselves.
                let heights =
                    RasterView::new(&s.heights, shape).map_err(|e| anyhow!("mesher: {e}"))?;
                let g = grid_streaming(
                    heights,
                    &ScanPlacement::of_frame(&h).map_err(|e| anyhow!("mesher: {e}"))?,
                    &self.settings.solid,
                )?;
                write_npy_abs_f64(
                    resampled_npy,
                    &s.heights,
                    shape.rows,
                    shape.cols,
                    h.z_offset_um,
                )?;
                write_sidecar(resampled_npy, &geometry)?;
                let mut check = None;
                write_atomic(stl, |w| {
                    check = Some(g.write_stl(w, format == StlFormat::Ascii, STL_LABEL, heights)?);
                    Ok(())
                })?;
                let check =
                    check.ok_or_else(|| anyhow!("mesher: {}: nothing written", stl.display()))?;
                return Ok(MeshFiles {
                    summary: surface_summary(&g.counts, &check, None, &h, &self.settings),
                    check,
                    streamed: true,
                });
            }
            _ => {
                // The engines' grid sheets: bounded by their triangle budgets, made in memory.
                let m = self.mesh_in_memory(&s, None)?;
                drop(s);
                let r = &m.resampled_um;
                write_npy_f64(resampled_npy, r.values(), r.rows(), r.cols())?;
                write_sidecar(resampled_npy, &geometry)?;
                write_atomic(stl, |w| Ok(m.write_stl(w, format)?))?;
                return Ok(MeshFiles {
                    summary: m.summary(&self.settings),
                    check: m.check,
                    streamed: false,
                });
            }
        };
        let heights = RasterView::new(&s.heights, shape).map_err(|e| anyhow!("mesher: {e}"))?;
        let at = ScanPlacement::of_frame(&h).map_err(|e| anyhow!("mesher: {e}"))?;
        let spill_dir = match stl.parent() {
            Some(d) if !d.as_os_str().is_empty() => d,
            _ => Path::new("."),
        };
        std::fs::create_dir_all(spill_dir)
            .map_err(|e| anyhow!("{}: cannot create the folder: {e}", spill_dir.display()))?;
        let (mut m, report) = match &self.tolerance() {
            Some(t) => {
                let reference = reference.as_ref().map(|r| &r.heights[..]);
                let (m, r) =
                    mesh_streaming_to_tolerance(heights, reference, &at, &params, t, spill_dir)?;
                (m, Some(r))
            }
            None => (mesh_streaming(heights, &at, &params, spill_dir)?, None),
        };
        let mut method = Some(adaptive_method(m.summary.clone(), report.as_ref()));
        add_outliers(&mut method, spikes.as_ref());
        write_npy_abs_f64(
            resampled_npy,
            &m.resampled_um,
            shape.rows,
            shape.cols,
            h.z_offset_um,
        )?;
        write_sidecar(resampled_npy, &geometry)?;
        let mut check = None;
        write_atomic(stl, |w| {
            check = Some(m.write_stl(w, format == StlFormat::Ascii, STL_LABEL, heights)?);
            Ok(())
        })?;
        let check = check.ok_or_else(|| anyhow!("mesher: {}: nothing written", stl.display()))?;
        Ok(MeshFiles {
            summary: surface_summary(&m.counts, &check, method.as_ref(), &h, &self.settings),
            check,
            streamed: true,
        })
    }
}

/// Two final frames must share one grid (size, pitch, origin) to be combined sample by sample.
fn check_same_grid((a_name, a): (&str, &HeightMap), (b_name, b): (&str, &HeightMap)) -> Result<()> {
    let (x, y) = (&a.header, &b.header);
    if (x.width, x.height) != (y.width, y.height)
        || x.pitch_x_um != y.pitch_x_um
        || x.pitch_y_um != y.pitch_y_um
        || x.origin_x_um != y.origin_x_um
        || x.origin_y_um != y.origin_y_um
        || a.heights.len() != b.heights.len()
    {
        bail!(
            "mesher: {a_name} ({} x {} px (rows x cols), pitch {} x {} um, origin {}, {} um) and \
             {b_name} ({} x {} px, pitch {} x {} um, origin {}, {} um) are not on the same grid",
            x.height,
            x.width,
            x.pitch_x_um,
            x.pitch_y_um,
            x.origin_x_um,
            x.origin_y_um,
            y.height,
            y.width,
            y.pitch_x_um,
            y.pitch_y_um,
            y.origin_x_um,
            y.origin_y_um
        );
    }
    Ok(())
}
