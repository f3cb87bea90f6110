//! The mesher's report as the records its readers read ([`surfstream_core::record`]): the
//! search's and the mesh's own types turned into [`MeshReport`]'s parts, field by field, so a
//! field added to a record must be written here before the mesher compiles.
//!
//! The computation keeps its own types where they carry more than the report (`usize` counts,
//! the search's state); the ones that are the report's layout and nothing else are the records
//! themselves (`AreaParams` = [`LevelledParams`], `AngleStats` = [`AngleRecord`],
//! `ElementQuality`, `Spike`).

use surfstream_core::record::{
    AngleQuality, CurvePointRecord, EngineTargetRecord, MeshFidelity, ModelTolerance,
    OutliersRecord, RegionFitRecord, ToleranceRecord, VerticalError,
};

use std::collections::BTreeMap;

use surfstream_core::raster::Shape;
use surfstream_core::record::{
    FormPlane, GridSheetRecord, MeshMethodRecord, MeshReport, RecordError,
};

use crate::adaptive::{serde_name, AdaptiveSummary, Fidelity, MeshCounts};
use crate::check::MeshCheck;
use crate::config::MeshSettings;
use crate::field::ScanPlacement;
use crate::outliers::OutlierReport;
use crate::target::EngineProfile;
use crate::tin::ErrorStats;
use crate::tolerance::{CurvePoint, RegionFit, Tolerance, ToleranceReport};

impl From<&ErrorStats> for VerticalError {
    fn from(e: &ErrorStats) -> Self {
        Self {
            max_um: e.max_um,
            rms_um: e.rms_um,
            samples: e.samples as u64,
            uncovered: e.uncovered as u64,
        }
    }
}

impl From<&Fidelity> for MeshFidelity {
    fn from(f: &Fidelity) -> Self {
        Self {
            epsilon_um: f.epsilon_um,
            error: (&f.error).into(),
            bound_met: f.bound_met,
            field: f.field,
            mesh: f.mesh,
        }
    }
}

impl From<&Tolerance> for ModelTolerance {
    fn from(t: &Tolerance) -> Self {
        Self {
            sa_pct: t.sa_pct,
            sq_pct: t.sq_pct,
            sz_pct: t.sz_pct,
            residual_pct: t.residual_pct,
            max_error_pct: t.max_error_pct,
            roughness_pct: t.roughness_pct,
        }
    }
}

impl From<&RegionFit> for RegionFitRecord {
    fn from(f: &RegionFit) -> Self {
        Self {
            region: f.region.clone(),
            samples: f.samples as u64,
            measured_um: f.measured_um,
            deviation_pct: f.deviation_pct,
            residual_pct_of_sq: f.residual_pct_of_sq,
            max_error_um: Some(f.max_error_um),
            max_error_pct_of_sq: Some(f.max_error_pct_of_sq),
            roughness_deviation_pct: f.roughness_deviation_pct,
        }
    }
}

impl From<&CurvePoint> for CurvePointRecord {
    fn from(p: &CurvePoint) -> Self {
        Self {
            epsilon_um: p.epsilon_um,
            epsilon_sq_fraction: p.epsilon_sq_fraction,
            surface_triangles: p.surface_triangles as u64,
            triangles_per_measured_px: p.triangles_per_measured_px,
            worst_sa_pct: p.worst_sa_pct,
            worst_sq_pct: p.worst_sq_pct,
            worst_sz_pct: p.worst_sz_pct,
            worst_residual_pct_of_sq: p.worst_residual_pct_of_sq,
            worst_max_error_pct_of_sq: Some(p.worst_max_error_pct_of_sq),
            worst_roughness_pct: p.worst_roughness_pct,
            worst_region: p.worst_region.clone(),
            pass: p.pass,
            over_budget: p.over_budget,
            chosen: p.chosen,
        }
    }
}

impl From<&ToleranceReport> for ToleranceRecord {
    fn from(r: &ToleranceReport) -> Self {
        Self {
            tolerance: (&r.tolerance).into(),
            target_share: r.target_share,
            region_px: r.region_px as u64,
            regions: r.regions as u64,
            footprints: r.footprints as u64,
            measured_px: r.measured_px as u64,
            met: r.met,
            surface_triangles: r.surface_triangles as u64,
            triangles_per_measured_px: r.triangles_per_measured_px,
            epsilon_um: r.epsilon_um,
            reason: r.reason.clone(),
            region_fits: r.region_fits.iter().map(Into::into).collect(),
            curve: r.curve.iter().map(Into::into).collect(),
            angles: r.angles,
            judged_plane: r.judged_plane,
        }
    }
}

impl TryFrom<&OutlierReport> for OutliersRecord {
    type Error = RecordError;
    fn try_from(r: &OutlierReport) -> Result<Self, RecordError> {
        Ok(Self {
            rule: r.rule.clone(),
            threshold_um: r.threshold_um,
            count: r.count as u64,
            largest: r.largest.clone(),
            sz_um: r.sz_um,
            sz_without_spikes_um: r.sz_without_spikes_um,
            sz_effect_pct: r.sz_effect_pct,
            policy: serde_name(&r.policy)?,
            removed: r.removed as u64,
        })
    }
}

impl TryFrom<&EngineProfile> for EngineTargetRecord {
    type Error = RecordError;
    fn try_from(p: &EngineProfile) -> Result<Self, RecordError> {
        Ok(Self {
            engine: serde_name(&p.engine)?,
            ascii: p.ascii,
            solid: p.solid,
            units: serde_name(&p.units)?,
            method: serde_name(&p.method)?,
            max_triangles: p.max_triangles as u64,
            min_angle_deg: p.min_angle_deg,
        })
    }
}

/// The tolerance search's record, and with an angle bound the element quality of the mesh
/// written (as the engines' grid sheets report theirs).
pub(crate) fn tolerance_parts(r: &ToleranceReport) -> (ToleranceRecord, Option<AngleQuality>) {
    let record = ToleranceRecord::from(r);
    let quality = record.angles.as_ref().map(AngleQuality::from);
    (record, quality)
}

/// What a method adds to the mesher's report.
// One value per mesh made: the variants' sizes do not matter.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone, PartialEq)]
pub enum MethodSummary {
    /// An adaptive mesh: its statistics and the tolerance search's record.
    Adaptive {
        summary: AdaptiveSummary,
        tolerance: Option<ToleranceRecord>,
    },
    /// An engine's regular-grid sheet.
    GridSheet(GridSheetRecord),
}

/// An adaptive mesh's statistics with the tolerance search's report ("tolerance") and, with
/// an angle bound (an engine's target), the element quality of the mesh written
/// ("element_quality", as the grid targets report it).
pub(crate) fn adaptive_method(
    mut summary: AdaptiveSummary,
    report: Option<&ToleranceReport>,
) -> MethodSummary {
    let tolerance = report.map(|r| {
        let (record, quality) = tolerance_parts(r);
        summary.record.element_quality = quality;
        record
    });
    MethodSummary::Adaptive { summary, tolerance }
}

/// What the report says beside the mesh itself: the settings, the grid meshed and where it
/// came from, the spikes found.
pub(crate) struct ReportContext<'a> {
    pub settings: &'a MeshSettings,
    pub shape: Shape,
    pub at: &'a ScanPlacement,
    pub t_acquired_ns: u64,
    /// "panorama", ... (empty: a map from a file).
    pub surface: &'a str,
    pub outliers: &'a OutlierReport,
    /// The plane removed before meshing (with `settings.level`).
    pub form_plane: Option<FormPlane>,
}

/// The mesher's one record, of a mesh in memory or streamed to its file. The caller fills in
/// what only it knows: the node its files, wiring and times (`file`, `resampled`, `sources`,
/// `t_written_ns`, `live_frames_skipped`), the verb its input file.
pub(crate) fn mesh_report(
    counts: &MeshCounts,
    check: &MeshCheck,
    method: Option<&MethodSummary>,
    c: &ReportContext<'_>,
) -> Result<MeshReport, RecordError> {
    let settings = c.settings;
    // An adaptive mesh's own sizes stand for the mesh's (they are the same mesh's).
    let (counts, units) = match method {
        Some(MethodSummary::Adaptive { summary, .. }) => {
            (&summary.counts, summary.counts.units.symbol())
        }
        _ => (counts, settings.solid.units.symbol()),
    };
    let (method_name, method_record, tolerance) = match method {
        Some(MethodSummary::Adaptive { summary, tolerance }) => (
            "adaptive",
            Some(MeshMethodRecord::Adaptive(summary.record.clone())),
            tolerance.clone(),
        ),
        Some(MethodSummary::GridSheet(g)) => {
            ("grid", Some(MeshMethodRecord::GridSheet(g.clone())), None)
        }
        None => ("grid", None, None),
    };
    Ok(MeshReport {
        file: String::new(),
        resampled: String::new(),
        sources: BTreeMap::new(),
        t_acquired_ns: c.t_acquired_ns,
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
        degenerate_triangles: check.degenerate_triangles as u64,
        duplicate_triangles: check.duplicate_triangles as u64,
        grid_px: [c.shape.cols as u64, c.shape.rows as u64],
        pitch_um: [c.at.pitch.x_um(), c.at.pitch.y_um()],
        surface: c.surface.into(),
        form_removed: settings.form_removed().map(Into::into),
        form_plane: c.form_plane,
        input: None,
        input_format: None,
        mesh_s: None,
        target: settings
            .target
            .as_ref()
            .map(TryInto::try_into)
            .transpose()?,
        method: method_name.into(),
        method_record,
        tolerance,
        outliers: Some(c.outliers.try_into()?),
    })
}
