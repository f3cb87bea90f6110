//! finish.json as typed records: written by [`crate::process::finish`] and read by the run's
//! report.html (`launch/src/report/finish.rs`) through the same structs, so the compiler ties
//! a field's writer to its readers. Only this crate and the launcher's report use them, so they
//! live here, not in `surfstream_core::record`.
//!
//! Key order: the file is written from [`surfstream_core::record::to_value`] (serde_json without
//! `preserve_order`: keys sorted), so a field's place in a struct does not matter. Fields a
//! partial or older run may lack are read with a default; the writer always writes them.
//! The engine's own diagnostics (a cycle's contact statistics) stay a JSON value.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};
use serde_json::Value;

use crate::field::{ApproachDistribution, Extrapolation, FieldCheck, WearTable};
use crate::run::SurfaceParams;
use crate::setting::{Action, BarrelMachine, Media, Workpiece};

/// finish.json.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FinishSummary {
    /// The model's source (file or out dir).
    pub model: String,
    #[serde(default)]
    pub partial: bool,
    pub cycles_completed: usize,
    pub cycles_requested: usize,
    #[serde(default)]
    pub setting: Option<FinishSetting>,
    /// Null without a calibration target.
    #[serde(default)]
    pub calibration: Option<CalibrationSummary>,
    /// "contact-field" or "sampled-map" (absent before the contact field: sampled).
    #[serde(default)]
    pub wear_model: Option<String>,
    /// Null with the sampled map.
    #[serde(default)]
    pub contact_field: Option<ContactFieldSummary>,
    #[serde(default)]
    pub paper: Option<PaperValues>,
    pub before: SurfaceParams,
    pub after: SurfaceParams,
    pub abbott_before: AbbottSummary,
    pub abbott_after: AbbottSummary,
    #[serde(default)]
    pub volume_check: Option<VolumeCheck>,
    #[serde(default)]
    pub wear: Option<WearVolumes>,
    #[serde(default)]
    pub sim: Option<SimValues>,
    /// The ideal model's run (null without one, or when the run stopped early).
    #[serde(default)]
    pub ideal_model: Option<IdealModelRun>,
    #[serde(default)]
    pub cycles: Vec<CycleRecord>,
    /// The probe segment that measured the engine's cost (null when the passes were given).
    #[serde(default)]
    pub probe: Option<ProbeRecord>,
    pub timings: Timings,
    #[serde(default)]
    pub outputs: Vec<String>,
}

/// The patch meshed and worn (`setting.patch`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PatchRecord {
    pub rows_cols: [usize; 2],
    pub size_um: [f64; 2],
    pub pitch_um: [f64; 2],
    pub in_model_rows_cols_origin: [usize; 2],
    pub guard_band_um: f64,
    pub meshed_area_rows_cols: [usize; 2],
    pub boundary: String,
    pub levelled: String,
    pub filled_samples: usize,
}

/// Everything the run was set up with (`setting`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FinishSetting {
    pub patch: PatchRecord,
    pub media: Media,
    pub workpiece: Workpiece,
    pub machine: BarrelMachine,
    pub action: Action,
    pub press_force_n: f64,
    pub k_finnie_per_pa: f64,
    pub archard_k_over_h_per_pa: f64,
    pub process_time_s: f64,
    pub timestep_s: f64,
    pub ranks: usize,
    pub max_triangles: usize,
    pub time_budget_s: f64,
    pub seed: u64,
    pub wear_depth: String,
    pub acceleration: String,
}

/// The contact field's final fit over every cycle's table (`calibration.fit`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FinalFit {
    pub scale: f64,
    pub k_finnie_fitted_per_pa: f64,
    pub sa_after_um: f64,
    pub relative_error: f64,
    pub reached: bool,
    pub extrapolation: Extrapolation,
}

/// The calibration to a target Sa (`calibration`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CalibrationSummary {
    pub kind: String,
    #[serde(default)]
    pub target_sa_um: Option<f64>,
    #[serde(default)]
    pub wear_model: Option<String>,
    #[serde(default)]
    pub k_finnie_fitted_per_pa: Option<f64>,
    #[serde(default)]
    pub sa_after_um: Option<f64>,
    #[serde(default)]
    pub relative_error: Option<f64>,
    #[serde(default)]
    pub reached: Option<bool>,
    #[serde(default)]
    pub tolerance_percent: Option<f64>,
    /// The contact field's final fit (null: none).
    #[serde(default)]
    pub fit: Option<FinalFit>,
    #[serde(default)]
    pub provisional_scale: Option<f64>,
    /// The measured after-finish scan's parameters (null: a target Sa).
    #[serde(default)]
    pub measured_after: Option<SurfaceParams>,
}

/// The contact field's checks, averaged over the cycles (null where no cycle gave one).
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct CheckMean {
    pub auc_gap_predicts_worn: Option<f64>,
    pub dem_volume_within_reach: Option<f64>,
    pub cells_within_reach: Option<f64>,
    pub dem_worn_cells: Option<f64>,
}

/// The contact-field wear model (`contact_field`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ContactFieldSummary {
    pub ball_radius_um: f64,
    #[serde(default)]
    pub closing: String,
    #[serde(default)]
    pub approach: Option<ApproachDistribution>,
    #[serde(default)]
    pub approach_model: String,
    #[serde(default)]
    pub impact_rate_per_m2_s: f64,
    #[serde(default)]
    pub impact_rate_model: String,
    #[serde(default)]
    pub patch_area_um2: f64,
    pub impacts_over_process: f64,
    #[serde(default)]
    pub step_depth_um: f64,
    pub table: WearTable,
    #[serde(default)]
    pub check_mean: CheckMean,
    #[serde(default)]
    pub worn_cells_after: Option<f64>,
}

/// The reference study's measured part (`paper`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PaperValues {
    pub before: BTreeMap<String, f64>,
    pub after: BTreeMap<String, f64>,
    #[serde(default)]
    pub process_time_s: u64,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct AbbottSummary {
    pub material_ratio_pct: Vec<f64>,
    pub height_um: Vec<f64>,
}

/// The worst volume check over the cycles (`volume_check`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct VolumeCheck {
    pub relative_error: f64,
    pub what: String,
}

/// The wear on the evaluated patch (`wear`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct WearVolumes {
    pub finnie_volume_um3: f64,
    pub archard_volume_um3: f64,
    pub max_depth_um: f64,
    pub mean_depth_um: f64,
}

/// SIM (eq. 12) comparisons (`sim`; null where not computed).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SimValues {
    pub finnie_vs_archard: Option<f64>,
    pub worn_vs_measured_after: Option<f64>,
}

/// The ideal model's segment (`ideal_model`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct IdealModelRun {
    pub source: String,
    pub dir: String,
    pub engine_s: f64,
    pub volume_um3: f64,
    pub sim_wear_maps: Option<f64>,
    pub note: String,
}

/// A cycle's volume check: LIGGGHTS' sum of wear x area against the grid's.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CycleVolumeCheck {
    pub liggghts_um3: f64,
    pub grid_um3: f64,
    pub unmapped_um3: f64,
    pub relative_error: f64,
}

/// A cycle's contact field: its check against the DEM's wear and its own table.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CycleField {
    pub check: FieldCheck,
    pub table: WearTable,
    pub impacts: f64,
    pub dem_impacts: usize,
    pub extrapolation: Extrapolation,
    pub scale_is: String,
}

/// One DEM segment (`cycles[]`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CycleRecord {
    pub cycle: usize,
    pub dir: String,
    pub command: String,
    pub triangles: usize,
    pub mesh_block_stride: usize,
    pub passes: usize,
    pub steps_per_pass: usize,
    pub timestep_s: f64,
    pub simulated_s: f64,
    pub engine_s: f64,
    pub engine_cpu_s: f64,
    pub cost_per_triangle_step_s: f64,
    pub cpu_per_triangle_step_s: f64,
    pub acceleration_factor: f64,
    pub wear_scale: f64,
    pub target_reached: bool,
    pub k_finnie_equivalent_per_pa: f64,
    pub volume_check: CycleVolumeCheck,
    pub archard_volume_um3: f64,
    /// The engine's contact statistics (its own layout).
    pub contacts: Value,
    /// Null with the sampled map.
    pub contact_field: Option<CycleField>,
    pub after: SurfaceParams,
}

/// The probe segment (`probe`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ProbeRecord {
    pub dir: String,
    pub engine_s: f64,
    pub engine_cpu_s: f64,
    pub triangles: usize,
    pub steps: usize,
    pub cost_per_triangle_step_s: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Timings {
    pub engine_s: f64,
    #[serde(default)]
    pub engine_cpu_s: f64,
    pub total_s: f64,
    #[serde(default)]
    pub surfstream_overhead_s: f64,
    #[serde(default)]
    pub overhead_share_of_engine: Option<f64>,
    #[serde(default)]
    pub simulated_s: f64,
}

impl FinishSummary {
    /// Reads `path` (a finish.json); an error names the file and the field.
    pub fn read(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("{}: cannot read", path.display()))?;
        serde_json::from_str(&text).with_context(|| {
            format!(
                "{}: not a finish.json this surfstream reads (fields model, before, after, abbott_before, abbott_after, timings, ...)",
                path.display()
            )
        })
    }
}
