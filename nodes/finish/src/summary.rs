//! finish.json as typed records: written by [`crate::process::finish_record`] and read by the run's
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
use crate::machine::MacroContacts;
use crate::run::SurfaceParams;
use crate::setting::{Action, BarrelMachine, Media, PartMaterial, Workpiece};

/// finish.json: the run's facts (also the node's report, [`FinishReport`]) and its bulky parts.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FinishSummary {
    /// Everything finish.json shares with the node's report (flattened: the same top-level
    /// keys as ever).
    #[serde(flatten)]
    pub facts: FinishFacts,
    pub abbott_before: AbbottSummary,
    pub abbott_after: AbbottSummary,
    #[serde(default)]
    pub cycles: Vec<CycleRecord>,
    /// The macro run's contacts on the part (null: the rates from the kinematics).
    #[serde(rename = "macro", default)]
    pub macro_run: Option<MacroContacts>,
}

/// finish.json without the Abbott curves, the per-cycle records and the macro run with its
/// contact samples: what the node reports (run.json `stages.<id>`, [`FinishReport`]).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FinishFacts {
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
    #[serde(default)]
    pub volume_check: Option<VolumeCheck>,
    #[serde(default)]
    pub wear: Option<WearVolumes>,
    #[serde(default)]
    pub sim: Option<SimValues>,
    /// The ideal model's run (null without one, or when the run stopped early).
    #[serde(default)]
    pub ideal_model: Option<IdealModelRun>,
    /// The probe segment that measured the engine's cost (null when the passes were given).
    #[serde(default)]
    pub probe: Option<ProbeRecord>,
    pub timings: Timings,
    #[serde(default)]
    pub outputs: Vec<String>,
    /// The wear laws of the prediction and where their rates come from.
    #[serde(default)]
    pub wear_laws: Option<WearLawsRecord>,
    /// The prediction versus process time (at least 5 times, the process time last).
    #[serde(default)]
    pub series: Vec<SeriesPoint>,
    /// The no-DEM baselines at the same removal (null when no prediction was made).
    #[serde(default)]
    pub baselines: Option<Baselines>,
    /// The names (finish.json paths) of every fitted quantity; everything else is a
    /// prediction or an input.
    #[serde(default)]
    pub fitted: Vec<String>,
    /// The wear maps written at intervals of the process time.
    #[serde(default)]
    pub wear_maps: Option<WearMaps>,
    /// Settings compared with one calibration (`--sweep`; null without one).
    #[serde(default)]
    pub sweep: Option<Sweep>,
    /// How the measured scans (`--after`, `--calibrate FILE`) were registered to the model.
    #[serde(default)]
    pub after_registrations: Vec<crate::after::AfterRegistration>,
    /// The part's material: the DEM wall's E and nu, Archard's hardness (null only in records
    /// written before the material was an option).
    #[serde(default)]
    pub part_material: Option<PartMaterial>,
    /// The patch as the micro passes meshed it (the first cycle's; null on the one-medium
    /// segment path).
    #[serde(default)]
    pub patch: Option<PatchSummary>,
    /// Which path the cycles ran: the micro passes from the macro run's contact samples, or
    /// the one-medium segment on the block-averaged mesh (no contact samples).
    #[serde(default)]
    pub cycle_path: Option<String>,
}

// finish.json's readers (the page, the report, the sweep) read the facts as the summary's own
// fields: `summary.before` is `summary.facts.before`.
impl std::ops::Deref for FinishSummary {
    type Target = FinishFacts;
    fn deref(&self) -> &FinishFacts {
        &self.facts
    }
}

impl std::ops::DerefMut for FinishSummary {
    fn deref_mut(&mut self) -> &mut FinishFacts {
        &mut self.facts
    }
}

/// finish.json `patch`: the first cycle's patch model (the tolerance mesh and its fidelity).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PatchSummary {
    pub model: crate::passes::PatchModel,
}

/// Two process times the same: the series' times are sums and products of the user's, a
/// relative 1e-9 apart at most.
pub fn same_time_s(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-9 * b.abs().max(1.0)
}

/// One time of the prediction (`series[]`): the worn patch's parameters, um, and its
/// Abbott curve (101 points, material ratio 0..100 %).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SeriesPoint {
    pub time_s: f64,
    #[serde(rename = "Sa")]
    pub sa: f64,
    #[serde(rename = "Sq")]
    pub sq: f64,
    #[serde(rename = "Sz")]
    pub sz: f64,
    #[serde(rename = "Spk")]
    pub spk: f64,
    #[serde(rename = "Svk")]
    pub svk: f64,
    #[serde(rename = "Sk")]
    pub sk: f64,
    pub abbott: AbbottSummary,
    /// Which of this point's values were fitted (["Sa"] at the calibration time); the
    /// others are predictions.
    #[serde(default)]
    pub fitted: Vec<String>,
}

impl SeriesPoint {
    /// The point of `series` at `time_s`, if there is one.
    pub fn at(series: &[SeriesPoint], time_s: f64) -> Option<&SeriesPoint> {
        series.iter().find(|p| same_time_s(p.time_s, time_s))
    }
}

/// The laws of the prediction (`wear_laws`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct WearLawsRecord {
    /// Impacts per m^2 and s on the part (Finnie with the DEM's wear per contact).
    pub impact_rate_per_m2_s: f64,
    /// Sliding work per m^2 and s on the part (Archard), J/(m^2 s).
    pub sliding_work_j_per_m2_s: f64,
    /// Normal forces of the sliding contacts (equal weights), N, and the ball's Hertz
    /// approach under each, um.
    pub sliding_normal_forces_n: Vec<f64>,
    pub sliding_contact_depths_um: Vec<f64>,
    /// Archard's K/H and Finnie's k at scale 1, 1/Pa.
    pub archard_k_over_h_per_pa: f64,
    pub k_finnie_per_pa: f64,
    /// The one scale on both laws (fitted, or 1 for the constants as given).
    pub scale: f64,
    pub scale_is: String,
    /// When the calibration's Sa holds, s.
    pub calibration_time_s: f64,
    /// Where the rates come from (the macro run, or the barrel kinematics as assumed).
    pub rates_from: String,
    /// Share of the predicted volume each law removed over the process.
    pub impact_share_of_volume: f64,
    /// The prediction's extrapolation over the process (steps, volume, whether it stopped
    /// at its step limit).
    #[serde(default)]
    pub extrapolation: Option<Extrapolation>,
}

/// The wear maps over time (`wear_maps`): `dir/<file>` per time.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct WearMaps {
    pub every_s: f64,
    pub dir: String,
    pub files: Vec<String>,
    pub note: String,
}

/// One no-DEM baseline (`baselines.constant_wear`, `baselines.plateau`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Baseline {
    pub what: String,
    /// The parameter fitted to the same Sa as the prediction at the calibration time.
    pub fitted_parameter: String,
    pub fitted_value: f64,
    /// Whether the fit reached the prediction's Sa at the calibration time. A baseline that
    /// did not (a constant rate within a reach that covers almost every cell lowers the
    /// surface without smoothing it: Sa stalls) is not "at the same Sa", and says so.
    #[serde(default = "reached_by_default")]
    pub reached: bool,
    pub after: SurfaceParams,
    pub series: Vec<SeriesPoint>,
    /// Parameters (Sq, Sz, Spk, Svk, Sk) where the prediction lies within the noise of
    /// this baseline after the process time: there the DEM adds nothing measurable.
    pub within_noise: Vec<String>,
}

fn reached_by_default() -> bool {
    true
}

/// The noise of the prediction after the process time: the prediction from the tables of
/// the odd cycles against the even cycles' (different engine seeds), each fitted to the
/// same Sa (`baselines.noise`), um.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PredictionNoise {
    /// |Sa difference| at the calibration time between the two halves' tables at the
    /// prediction's own scale (not refitted): how far this setting's Sa depends on which DEM
    /// segments were drawn (what a sweep's settings are compared by). None in older records.
    #[serde(rename = "Sa", default, skip_serializing_if = "Option::is_none")]
    pub sa: Option<f64>,
    #[serde(rename = "Sq")]
    pub sq: f64,
    #[serde(rename = "Sz")]
    pub sz: f64,
    #[serde(rename = "Spk")]
    pub spk: f64,
    #[serde(rename = "Svk")]
    pub svk: f64,
    #[serde(rename = "Sk")]
    pub sk: f64,
    pub from: String,
}

/// The baselines (`baselines`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Baselines {
    pub constant_wear: Baseline,
    pub plateau: Baseline,
    /// Null with fewer than two cycles (no second sample of the DEM's table).
    #[serde(default)]
    pub noise: Option<PredictionNoise>,
}

/// A sweep (`sweep`): the base run calibrated once, every other setting predicted with its
/// fitted constants.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Sweep {
    pub parameter: String,
    pub settings: Vec<SweepSetting>,
    pub note: String,
    /// The time the settings are compared at (the calibration time), s.
    #[serde(default)]
    pub compared_at_s: f64,
    /// Sa of the ball's envelope of the patch before finishing, um: every setting's Sa falls
    /// towards it, so settings near it are saturated, not told apart.
    #[serde(default)]
    pub envelope_sa_um: Option<f64>,
    /// Every pair of settings compared by Sa at `compared_at_s` against their noise.
    #[serde(default)]
    pub comparisons: Vec<SweepComparison>,
    /// Which settings the DEM tells apart and which not, in one sentence.
    #[serde(default)]
    pub verdict: String,
}

/// Two settings of a sweep compared by their Sa at the calibration time (`sweep.comparisons`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SweepComparison {
    /// The two settings' values, lower first.
    pub values: [f64; 2],
    /// Sa at the second value minus at the first, um (at `sweep.compared_at_s`).
    pub sa_difference_um: f64,
    /// The noise of that difference: the two settings' Sa noises (each the |difference|
    /// between its halves' predictions, about twice its standard deviation) added in
    /// quadrature, um. None when a setting has no noise estimate (one cycle).
    pub noise_um: Option<f64>,
    /// Whether the difference exceeds its noise (None: no noise estimate).
    pub apart: Option<bool>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SweepSetting {
    pub value: f64,
    /// The setting's folder (its own finish.json), "." for the base run.
    pub dir: String,
    /// True for the setting the constants were fitted on.
    pub calibrated_here: bool,
    /// The setting's Sa at the calibration time (`sweep.compared_at_s`), um.
    #[serde(default)]
    pub sa_compared_um: Option<f64>,
    /// The setting's Sa noise there (`baselines.noise.Sa` of its run), um.
    #[serde(default)]
    pub sa_noise_um: Option<f64>,
    /// The Sa its macro run's impact count stands for there, um: the impact rate is counted
    /// from `macro.contacts.impacts` impacts, a relative error of 1/sqrt(N) were they
    /// independent (media contacts cluster: a floor), and a rate off by a share e wears as
    /// the time t (1 + e) does, so Sa moves by |dSa/dt| t e. Null without a macro run.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sa_macro_noise_um: Option<f64>,
    pub after: SurfaceParams,
    pub series: Vec<SeriesPoint>,
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
    /// Where the micro passes' contacts come from, and whether `action` and `press_force_n`
    /// (the barrel kinematics' assumptions) were used at all.
    #[serde(default)]
    pub contacts_from: String,
    /// Whether `action` and `press_force_n` set the passes (false: the macro run's contacts did).
    #[serde(default = "used")]
    pub action_used: bool,
    pub action: Action,
    pub press_force_n: f64,
    pub k_finnie_per_pa: f64,
    pub archard_k_over_h_per_pa: f64,
    pub process_time_s: f64,
    /// The micro passes' time step (from the contacts they draw), s.
    pub timestep_s: f64,
    pub ranks: usize,
    pub max_triangles: usize,
    pub time_budget_s: f64,
    pub seed: u64,
    pub wear_depth: String,
    pub acceleration: String,
}

fn used() -> bool {
    true
}

/// The contact field's final fit over every cycle's table (`calibration.fit`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FinalFit {
    /// The one scale on both wear laws (fitted).
    pub scale: f64,
    pub k_finnie_fitted_per_pa: f64,
    /// Archard's K/H x the scale, 1/Pa (fitted; absent before the sliding law).
    #[serde(default)]
    pub archard_k_over_h_fitted_per_pa: Option<f64>,
    /// When the fitted Sa holds, s (absent before: the process time).
    #[serde(default)]
    pub calibration_time_s: Option<f64>,
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

/// The evaluated patch's envelope under the media's ball (`contact_field.envelope`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EnvelopeShape {
    pub sa_um: f64,
    pub sq_um: f64,
    pub sz_um: f64,
    pub meaning: String,
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
    /// The deepest gap below the envelope any law reaches, um.
    #[serde(default)]
    pub reach_um: Option<f64>,
    #[serde(default)]
    pub envelope: Option<EnvelopeShape>,
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
    /// The triangle budget of the ideal model's patch mesh (the model's, or four times it
    /// when its tolerance mesh did not fit).
    #[serde(default)]
    pub mesh_budget_triangles: usize,
    pub source: String,
    pub dir: String,
    pub engine_s: f64,
    pub volume_um3: f64,
    pub sim_wear_maps: Option<f64>,
    pub note: String,
    /// SIM between the ideal and high-fidelity predictions (null without a prediction).
    #[serde(default)]
    pub sim_predictions: Option<f64>,
    /// The ideal model's predicted wear map in OUT (null without a prediction).
    #[serde(default)]
    pub wear_map: Option<String>,
}

/// A cycle's volume check: LIGGGHTS' sum of wear x area against the grid's.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CycleVolumeCheck {
    pub liggghts_um3: f64,
    pub grid_um3: f64,
    pub unmapped_um3: f64,
    /// Volume of triangles lying between samples, given to the sample nearest their
    /// centroid (kept in `grid_um3`), um^3. None: a block-averaged sheet, or an older record.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub to_nearest_sample_um3: Option<f64>,
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
    /// The cycle's micro passes (`passes::MicroRecord`); null on the one-medium segment path.
    #[serde(default)]
    pub micro: Option<Value>,
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
    /// The macro run's share of `engine_s` (0 without one, or with a given record), s.
    #[serde(default)]
    pub macro_engine_s: f64,
}

/// The finish node's report (run.json `stages.<id>`, `nodes/<id>.json`): finish.json's facts
/// (without the Abbott curves, the per-cycle records and the macro run, which stay in
/// finish.json) plus the node's folder.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FinishReport {
    /// The node's folder under the run's out dir, holding finish.json.
    pub dir: String,
    #[serde(flatten)]
    pub facts: FinishFacts,
}

impl FinishReport {
    /// The report of the run that wrote `summary` into the node's folder `dir`.
    pub fn of(summary: FinishSummary, dir: &str) -> Self {
        FinishReport {
            dir: dir.to_owned(),
            facts: summary.facts,
        }
    }
}

impl surfstream_core::record::NodeRecord for FinishReport {
    const NODE_KIND: &'static str = "finish";
}

impl std::ops::Deref for FinishReport {
    type Target = FinishFacts;
    fn deref(&self) -> &FinishFacts {
        &self.facts
    }
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

/// A finish.json for the tests of its readers (the page, the node's report).
#[cfg(test)]
pub(crate) mod example {
    use super::FinishSummary;
    use crate::setting::{BarrelMachine, Media, Workpiece};
    use serde_json::{json, Value};
    use surfstream_core::record;

    /// Surface parameters: Sa, Sq, Spk as given, the others 1.
    pub(crate) fn params(sa: f64, sq: f64, spk: f64) -> Value {
        json!({"Sa": sa, "Sq": sq, "Spk": spk, "Sp": 1.0, "Sv": 1.0, "Sz": 1.0, "Ssk": 1.0,
               "Sku": 1.0, "Sdq": 1.0, "Sk": 1.0, "Svk": 1.0, "Smr1": 1.0, "Smr2": 1.0})
    }

    pub(crate) fn cycle(n: usize, acceleration_factor: f64, sa: f64) -> Value {
        json!({
            "cycle": n, "dir": format!("cycle_{n:02}"), "command": "liggghts", "triangles": 800,
            "mesh_block_stride": 1, "passes": 3, "steps_per_pass": 200, "timestep_s": 1.8e-7,
            "simulated_s": 1e-4, "engine_s": 2.0, "engine_cpu_s": 1.0,
            "cost_per_triangle_step_s": 1e-8, "cpu_per_triangle_step_s": 5e-9,
            "acceleration_factor": acceleration_factor, "wear_scale": 1.0, "target_reached": false,
            "k_finnie_equivalent_per_pa": 1e-12,
            "volume_check": {"liggghts_um3": 1.0, "grid_um3": 1.0, "unmapped_um3": 0.0,
                             "relative_error": 1e-15},
            "archard_volume_um3": 0.5, "contacts": {}, "contact_field": null,
            "after": params(sa, 1.6, 1.2),
        })
    }

    /// The fields every finish.json has, the curves straight lines.
    pub(crate) fn minimal() -> Value {
        let curve = |scale: f64| {
            json!({
                "material_ratio_pct": (0..=100).map(|k| k as f64).collect::<Vec<_>>(),
                "height_um": (0..=100).map(|k| scale * (50.0 - k as f64) / 25.0).collect::<Vec<_>>(),
            })
        };
        json!({
            "model": "out/demo/panorama.x3p", "cycles_completed": 0, "cycles_requested": 1,
            "before": params(1.3157, 1.64, 1.51), "after": params(1.2692, 1.57, 1.10),
            "abbott_before": curve(1.0), "abbott_after": curve(0.9),
            "timings": {"engine_s": 0.0, "total_s": 1.0},
        })
    }

    /// A series point at `t` s with Sa `sa` (Sq = 1.25 Sa, Sz = 10 Sa, ...).
    pub(crate) fn point(t: f64, sa: f64, fitted: bool) -> Value {
        json!({"time_s": t, "Sa": sa, "Sq": 1.25 * sa, "Sz": 10.0 * sa, "Spk": 0.8 * sa,
               "Svk": 1.1 * sa, "Sk": 3.0 * sa,
               "abbott": {"material_ratio_pct": [0.0, 50.0, 100.0], "height_um": [sa, 0.0, -sa]},
               "fitted": if fitted { vec!["Sa"] } else { vec![] }})
    }

    /// A prediction: the series, the laws, both baselines with a noise, the fitted list.
    pub(crate) fn predicted() -> FinishSummary {
        let mut s = record::to_value(&summary()).unwrap();
        let series = |k: f64| -> Vec<Value> {
            [60.0, 120.0, 180.0, 240.0, 300.0]
                .iter()
                .enumerate()
                .map(|(i, t)| point(*t, k * (1.3 - 0.14 * i as f64), false))
                .collect()
        };
        let mut dem = series(1.0);
        dem[4] = point(300.0, 0.74, true);
        let baseline = |what: &str, sq: f64, within: Vec<&str>| {
            json!({"what": what, "fitted_parameter": "p", "fitted_value": 0.5,
                   "after": params(0.74, sq, 0.4), "series": series(1.0), "within_noise": within})
        };
        let extra = json!({
            "series": dem,
            "after": params(0.74, 0.93, 0.4),
            "fitted": ["calibration.fit.scale", "series[time_s = calibration time].Sa"],
            "wear_laws": {"impact_rate_per_m2_s": 6.72e7, "sliding_work_j_per_m2_s": 1884.0,
                          "sliding_normal_forces_n": [0.0358], "sliding_contact_depths_um": [0.05],
                          "archard_k_over_h_per_pa": 5e-14, "k_finnie_per_pa": 6e-12, "scale": 2.5,
                          "scale_is": "fitted once", "calibration_time_s": 300.0,
                          "rates_from": "the barrel kinematics", "impact_share_of_volume": 0.25},
            "baselines": {"constant_wear": baseline("constant", 1.6, vec!["Sq"]),
                          "plateau": baseline("plateau", 1.9, vec![]),
                          "noise": {"Sq": 0.05, "Sz": 0.3, "Spk": 0.1, "Svk": 0.1, "Sk": 0.2,
                                    "from": "odd vs even cycles"}},
            "sweep": {"parameter": "revolution-rpm", "note": "one calibration",
                      "settings": [
                          {"value": 200.0, "dir": "sweep_revolution-rpm_200", "calibrated_here": false,
                           "after": params(0.9, 1.1, 0.5), "series": series(1.2)},
                          {"value": 300.0, "dir": ".", "calibrated_here": true,
                           "after": params(0.74, 0.93, 0.4), "series": series(1.0)}]},
        });
        for (k, v) in extra.as_object().unwrap() {
            s[k] = v.clone();
        }
        typed(s)
    }

    pub(crate) fn typed(v: Value) -> FinishSummary {
        serde_json::from_value(v).expect("a finish.json")
    }

    pub(crate) fn summary() -> FinishSummary {
        let mut s = minimal();
        let extra = json!({
            "cycles_completed": 2, "cycles_requested": 3, "partial": true,
            "setting": {
                "patch": {"pitch_um": [0.5, 0.5], "size_um": [20.0, 15.0], "rows_cols": [30, 40],
                          "in_model_rows_cols_origin": [0, 0], "meshed_area_rows_cols": [48, 58],
                          "guard_band_um": 45.0, "boundary": "guard band", "levelled": "plane",
                          "filled_samples": 0},
                "media": Media::default(),
                "workpiece": Workpiece::default(),
                "machine": BarrelMachine::default(),
                "action": {"media_velocity_m_s": 1.618, "pressure_pa": 3997.19,
                           "impact_angle_deg": 20.0, "acceleration_m_s2": 133.2, "source": "barrel"},
                "press_force_n": 0.0358, "k_finnie_per_pa": 1e-10, "archard_k_over_h_per_pa": 5e-14,
                "process_time_s": 300.0, "timestep_s": 1.8e-7, "ranks": 1, "max_triangles": 20000,
                "time_budget_s": 60.0, "seed": 1, "wear_depth": "along z",
                "acceleration": "process time / cycles / simulated time",
            },
            "cycles": [cycle(1, 97095.8, 1.3), cycle(2, 37759.5, 1.2)],
            "timings": {"engine_s": 314.4, "engine_cpu_s": 42.5, "surfstream_overhead_s": 9.6,
                        "overhead_share_of_engine": 0.0306, "total_s": 324.0, "simulated_s": 0.006},
            "volume_check": {"relative_error": 2.7e-14, "what": "largest error"},
            "calibration": {"kind": "Sa before/after", "target_sa_um": 0.5844,
                            "k_finnie_fitted_per_pa": 9.01e-17},
            "probe": {"dir": "probe", "engine_s": 1.5, "engine_cpu_s": 0.7, "triangles": 800,
                      "steps": 400, "cost_per_triangle_step_s": 4.7e-9},
            "sim": {"finnie_vs_archard": 0.221, "worn_vs_measured_after": null},
            "wear": {"finnie_volume_um3": 120.0, "archard_volume_um3": 60.0,
                     "max_depth_um": 0.8, "mean_depth_um": 0.1},
            "ideal_model": {"source": "graph input 'datum'", "dir": "ideal", "engine_s": 2.0,
                            "volume_um3": 100.0, "sim_wear_maps": 0.025, "note": "same passes",
                            "sim_predictions": 0.031, "wear_map": "wear_ideal.npy"},
            "paper": {"before": {"Sa": 1.272}, "after": {"Sa": 0.565}, "process_time_s": 300},
            "outputs": ["wear.npy", "finish.json"],
        });
        for (k, v) in extra.as_object().unwrap() {
            s[k] = v.clone();
        }
        typed(s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use surfstream_core::record;

    /// The report as the node built it before it was typed: finish.json's value with the
    /// curves and cycles removed by key, `dir` inserted.
    fn report_by_key(s: &FinishSummary, dir: &str) -> Value {
        let mut v = record::to_value(s).unwrap();
        let o = v.as_object_mut().expect("finish.json is an object");
        for k in ["abbott_before", "abbott_after", "cycles", "macro"] {
            assert!(o.remove(k).is_some(), "finish.json has {k}");
        }
        o.insert("dir".into(), Value::from(dir));
        v
    }

    #[test]
    fn the_report_is_finish_json_without_curves_and_cycles_plus_the_folder() {
        for s in [
            example::summary(),
            example::typed(example::minimal()),
            example::predicted(),
        ] {
            let typed = record::to_value(&FinishReport::of(s.clone(), "fin")).unwrap();
            assert_eq!(typed, report_by_key(&s, "fin"));
            assert_eq!(
                serde_json::to_string_pretty(&typed).unwrap(),
                serde_json::to_string_pretty(&report_by_key(&s, "fin")).unwrap()
            );
            // The launcher reads it back as the same record.
            let back: FinishReport = record::from_value(&typed, "report").unwrap();
            assert_eq!(back.dir, "fin");
            assert_eq!(back.before.sa, s.before.sa);
        }
    }
}
