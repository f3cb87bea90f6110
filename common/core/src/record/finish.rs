//! finish.json's typed records (the finishing node, `surfstream-finish`): written by
//! `surfstream_finish::process::finish_record` and read by finish.html
//! (`surfstream_finish::html`), the run's report.html (`launch/src/report/finish.rs`) and the
//! node's run.json report ([`FinishReport`]) through the same structs, so the compiler ties a
//! field's writer to its readers. Here, in core's record module, beside every other record
//! the project writes (issue 39); with them the plain data types they carry: the setting (the
//! media, the workpiece, the barrel and its action, the part's material), the macro run's
//! contacts ([`MacroContacts`]), the contact field's distribution and table, the surface
//! parameters, the patch model and the after-finish registration. The finish crate re-exports
//! each from the module it was defined in (`surfstream_finish::setting::Media`, ...) and keeps
//! their physics (Hertz approaches, the wear table's measurement, the barrel's kinematics) as
//! extension traits there; only what is about the record itself (reading finish.json, the
//! material presets the default is one of, which source an approach came from) is here.
//!
//! Key order: the file is written from [`super::to_value`] (serde_json without
//! `preserve_order`: keys sorted), so a field's place in a struct does not matter. Fields a
//! partial or older run may lack are read with a default; the writer always writes them.
//! The engine's own diagnostics (a cycle's contact statistics) stay a JSON value.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};
use serde_json::Value;

// ---------------------------------------------------------------------------------------
// finish.json

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
    pub after_registrations: Vec<AfterRegistration>,
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
    pub model: PatchModel,
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

impl super::NodeRecord for FinishReport {
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

// ---------------------------------------------------------------------------------------
// The setting (`surfstream_finish::setting`)

/// The grinding media: spheres.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Media {
    pub diameter_mm: f64,
    pub density_kg_m3: f64,
    pub youngs_modulus_pa: f64,
    pub poisson_ratio: f64,
    /// Media-part coefficient of restitution (LIGGGHTS' Hertz damping).
    pub restitution: f64,
    /// Media-part Coulomb friction coefficient.
    pub friction: f64,
}

impl Default for Media {
    /// Ceramic (alumina-silica) media of the paper's 3 mm size. The paper states the size
    /// only; density, modulus, Poisson ratio, restitution and friction are typical catalogue
    /// values for fused ceramic media, not measured here.
    fn default() -> Self {
        Media {
            diameter_mm: 3.0,
            density_kg_m3: 2500.0,
            youngs_modulus_pa: 1.0e11,
            poisson_ratio: 0.25,
            restitution: 0.6,
            friction: 0.3,
        }
    }
}

/// The finished part's material (the wall in LIGGGHTS).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Workpiece {
    pub youngs_modulus_pa: f64,
    pub poisson_ratio: f64,
}

impl Default for Workpiece {
    /// Steel.
    fn default() -> Self {
        Workpiece {
            youngs_modulus_pa: 2.1e11,
            poisson_ratio: 0.3,
        }
    }
}

/// The part's material: the wall's elasticity in LIGGGHTS and the hardness of Archard's law.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PartMaterial {
    /// The preset's name, or "custom".
    pub name: String,
    pub youngs_modulus_pa: f64,
    pub poisson_ratio: f64,
    /// Indentation hardness H of Archard's law V = K / H F s, Pa.
    pub hardness_pa: f64,
}

impl Default for PartMaterial {
    fn default() -> Self {
        PartMaterial::aluminium()
    }
}

impl PartMaterial {
    /// The paper's part, an aluminium alloy sheet: E 70 GPa, nu 0.33, H 1.0 GPa (about
    /// 100 HV, a 6061-T6-like alloy; textbook values, the paper gives no grade).
    pub fn aluminium() -> Self {
        PartMaterial {
            name: "aluminium".into(),
            youngs_modulus_pa: 7.0e10,
            poisson_ratio: 0.33,
            hardness_pa: 1.0e9,
        }
    }

    /// Steel: E 210 GPa, nu 0.3, H 2 GPa (about 200 HV; the first sessions' hard-coded part).
    pub fn steel() -> Self {
        PartMaterial {
            name: "steel".into(),
            youngs_modulus_pa: 2.1e11,
            poisson_ratio: 0.3,
            hardness_pa: 2.0e9,
        }
    }

    /// The presets by name: `aluminium` (also `aluminum`) or `steel`.
    pub fn preset(name: &str) -> Result<Self> {
        match name {
            "aluminium" | "aluminum" => Ok(Self::aluminium()),
            "steel" => Ok(Self::steel()),
            _ => bail!("part material {name:?}: expected aluminium or steel (or give its modulus, Poisson ratio and hardness)"),
        }
    }
}

/// A centrifugal barrel machine: barrels on a turret.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct BarrelMachine {
    /// Turret revolution, r/min.
    pub revolution_rpm: f64,
    /// Distance of the barrel's axis from the turret's axis, mm.
    pub revolution_radius_mm: f64,
    /// Barrel rotation relative to the turret, r/min, opposite to the revolution.
    pub counter_rotation_rpm: f64,
    /// Inner radius of the barrel, mm (not given by the paper: an assumption).
    pub barrel_radius_mm: f64,
    /// Depth of media above the part, mm (an assumption).
    pub bed_depth_mm: f64,
    /// Volume fraction of media in the bed (random packing of spheres).
    pub packing_fraction: f64,
}

impl Default for BarrelMachine {
    /// The paper's machine: 300 r/min revolution at 135 mm, 300 r/min counter-rotation; the
    /// barrel radius (50 mm), bed depth (20 mm) and packing (0.6) are assumptions.
    fn default() -> Self {
        BarrelMachine {
            revolution_rpm: 300.0,
            revolution_radius_mm: 135.0,
            counter_rotation_rpm: 300.0,
            barrel_radius_mm: 50.0,
            bed_depth_mm: 20.0,
            packing_fraction: 0.6,
        }
    }
}

/// What the machine does to the part, as the DEM patch sees it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Action {
    /// Speed of the media relative to the part, m/s.
    pub media_velocity_m_s: f64,
    /// Angle of the media's velocity to the part's plane, degrees (glancing impacts).
    pub impact_angle_deg: f64,
    /// Contact pressure of the media bed on the part, Pa.
    pub pressure_pa: f64,
    /// Body acceleration of the media toward the part, m/s^2 (the centrifugal field).
    pub acceleration_m_s2: f64,
    /// How the numbers were obtained.
    pub source: String,
}

// ---------------------------------------------------------------------------------------
// The macro run (`surfstream_finish::machine`)

/// The media of the macro run: spheres, softened (see `surfstream_finish::machine`'s
/// documentation).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MediaSpec {
    pub diameter_mm: f64,
    pub density_kg_m3: f64,
    /// Young's modulus used in the macro run, Pa (softened).
    pub youngs_modulus_pa: f64,
    pub poisson_ratio: f64,
    /// Coefficient of restitution (media-media and media-wall).
    pub restitution: f64,
    /// Coulomb friction (media-media and media-wall).
    pub friction: f64,
}

impl Default for MediaSpec {
    /// The paper's 3 mm media, softened to its EDEM time step: E = 3e7 Pa gives a Rayleigh
    /// time of 7.4e-5 s, of which 20 % is 1.48e-5 s (the paper: 1.5e-5 s). Density 2500 kg/m^3,
    /// nu 0.25, restitution 0.6, friction 0.3: catalogue values for ceramic media, not
    /// measured.
    fn default() -> Self {
        MediaSpec {
            diameter_mm: 3.0,
            density_kg_m3: 2500.0,
            youngs_modulus_pa: 3.0e7,
            poisson_ratio: 0.25,
            restitution: 0.6,
            friction: 0.3,
        }
    }
}

impl MediaSpec {
    /// The same media at another stiffness: the micro passes' media (the real modulus, where
    /// the macro run's is softened). One media, two stiffnesses: every other property is the
    /// macro run's.
    pub fn at_modulus(&self, youngs_modulus_pa: f64) -> Media {
        Media {
            diameter_mm: self.diameter_mm,
            density_kg_m3: self.density_kg_m3,
            youngs_modulus_pa,
            poisson_ratio: self.poisson_ratio,
            restitution: self.restitution,
            friction: self.friction,
        }
    }

    /// The first property (not the modulus) in which `m` is not these media, as
    /// "name: macro run's vs micro passes'".
    pub fn differs_from(&self, m: &Media) -> Option<String> {
        [
            ("diameter_mm", self.diameter_mm, m.diameter_mm),
            ("density_kg_m3", self.density_kg_m3, m.density_kg_m3),
            ("poisson_ratio", self.poisson_ratio, m.poisson_ratio),
            ("restitution", self.restitution, m.restitution),
            ("friction", self.friction, m.friction),
        ]
        .into_iter()
        .find(|(_, a, b)| a != b)
        .map(|(name, a, b)| format!("{name} {a} in the macro run vs {b} in the micro passes"))
    }
}

/// p10, p50 and p90 of a sample.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Percentiles {
    pub p10: f64,
    pub p50: f64,
    pub p90: f64,
}

/// One contact of a medium on the part, as the micro run draws it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ContactSample {
    /// Approach speed along the part's normal at the contact's first sample, m/s.
    pub normal_speed_m_s: f64,
    /// Mean sliding speed of the medium's centre relative to the part over the contact, m/s.
    pub tangential_speed_m_s: f64,
    /// Mean normal force over the contact, N (the quasi-static load of an enduring contact).
    pub normal_force_n: f64,
    /// Samples x dump interval, s (softened media: not the real duration).
    pub duration_s: f64,
    /// Longer than twice the Hertz impact time at its approach speed: pressed and sliding,
    /// not a bounce.
    pub enduring: bool,
}

/// The contact statistics on the part's central region.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct ContactStatistics {
    /// Contacts begun during the recording.
    pub count: usize,
    pub impacts: usize,
    pub enduring: usize,
    /// New contacts per mm^2 of the region and s.
    pub rate_per_mm2_s: f64,
    /// The next three over the contact samples in the region (time-weighted: each dump of a
    /// contact is one sample): |normal speed|, m/s.
    pub normal_speed_m_s: Percentiles,
    /// Sliding speed of the medium's centre relative to the part, m/s.
    pub tangential_speed_m_s: Percentiles,
    /// Normal force, N (clipped at 0).
    pub normal_force_n: Percentiles,
    /// Approach speed of the impacts (contacts that are not enduring) at their first sample,
    /// m/s.
    pub impact_normal_speed_m_s: Percentiles,
    /// Mean normal force of each enduring contact (what softening keeps), N.
    pub enduring_normal_force_n: Percentiles,
    /// Duration of each contact, s (softened media: not the real one).
    pub duration_s: Percentiles,
    /// Sum over samples of F_n |v_t| dt per mm^2 and s, J/(mm^2 s).
    pub sliding_work_j_per_mm2_s: f64,
    /// Sum over contacts of m v_n^2 / 2 at their first sample per mm^2 and s, J/(mm^2 s).
    pub impact_energy_j_per_mm2_s: f64,
    /// Share of samples whose tangential force is within 5 % of the Coulomb limit (sliding,
    /// not rolling or sticking).
    pub coulomb_limit_share: f64,
    /// Contact samples read in the region.
    pub samples: usize,
}

/// What the softened media keep, stated in the record.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Softening {
    /// The media's Young's modulus in the macro run, Pa.
    pub media_youngs_modulus_pa: f64,
    /// Real ceramic media, Pa (the micro run's stiffness).
    pub real_youngs_modulus_pa: f64,
    pub timestep_s: f64,
    pub rayleigh_time_s: f64,
    /// Taken from the macro run.
    pub trusted: Vec<String>,
    /// Not taken: they depend on the stiffness; the micro run makes them at the real one.
    pub not_trusted: Vec<String>,
}

/// The macro run's record (finish.json `macro`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MacroContacts {
    /// "liggghts".
    pub engine: String,
    pub machine: String,
    pub media_count: usize,
    /// Recorded simulated time (after settling), s.
    pub simulated_s: f64,
    pub settle_s: f64,
    pub timestep_s: f64,
    /// The region the statistics are per area of, mm^2.
    pub region_area_mm2: f64,
    pub contacts: ContactStatistics,
    /// A uniform reservoir of the contacts (at most `samples_kept`).
    pub samples: Vec<ContactSample>,
    pub softening: Softening,
    /// Media that left the drum (lost by LIGGGHTS: a leak in the walls).
    pub media_lost: usize,
    /// Stopped before the end: the statistics cover `simulated_s` only.
    pub partial: bool,
    pub cost: MacroCost,
    pub seed: u64,
    /// The media the run used (softened): a record given back (`--macro-record`) is checked
    /// against the micro passes' media. Absent in records written before it was kept.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub media: Option<MediaSpec>,
}

/// What the macro run cost.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct MacroCost {
    pub ranks: usize,
    pub engine_s: f64,
    pub engine_cpu_s: f64,
    /// LIGGGHTS' own "Loop time" summed over its runs, s.
    pub loop_s: f64,
    pub steps: usize,
    /// Loop time / (media x steps), s.
    pub per_particle_step_s: f64,
    /// Loop time / simulated time (settling and recording), s per s.
    pub per_simulated_s: f64,
    pub command: String,
}

// ---------------------------------------------------------------------------------------
// The contact field (`surfstream_finish::field`)

/// The distribution of the contacts' approach into the part (Hertz), um: p(gap) =
/// P(approach > gap). finish.json `contact_field.approach` names its `source` and holds only
/// that source's numbers.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "source", rename_all = "kebab-case", try_from = "ApproachRecord")]
pub enum ApproachDistribution {
    /// From the barrel kinematics' assumptions (no macro run): impacts at the media speed,
    /// angles uniform on [0, max], the press load's static approach a floor.
    Kinematics(KinematicApproach),
    /// From the macro run's contact samples: the share of the very contacts the micro passes
    /// are drawn from whose approach exceeds the gap.
    MacroSamples(SampledApproach),
}

/// The approach of the barrel kinematics' impacts ([`ApproachDistribution::Kinematics`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct KinematicApproach {
    /// Approach of an impact at the full media speed, normal to the part, um.
    pub full_speed_approach_um: f64,
    /// Largest impact angle: angles are uniform on [0, this], degrees.
    pub max_impact_angle_deg: f64,
    /// The static approach under the press load: every reachable cell within it is touched.
    pub static_approach_um: f64,
    /// Approach at the setting's (mean) impact angle, um (reported).
    pub mean_angle_approach_um: f64,
}

/// The approaches of the macro run's contacts at the part's real stiffness: an impact's
/// Hertz approach at its normal speed; an enduring contact's static approach under its
/// normal force (or its impact approach, if larger).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct SampledApproach {
    pub contacts: usize,
    pub impacts: usize,
    pub p10_um: f64,
    pub p50_um: f64,
    pub p90_um: f64,
    pub max_um: f64,
    /// Sorted ascending, um (not written: finish.json has the percentiles).
    #[serde(skip)]
    pub approaches_um: Vec<f64>,
}

/// `contact_field.approach` as read: tagged by `source`, or (records written before the
/// source was named) the kinematic fields beside an optional `sampled`.
#[derive(Deserialize)]
struct ApproachRecord {
    source: Option<String>,
    #[serde(flatten)]
    kinematics: Option<KinematicApproach>,
    sampled: Option<SampledApproach>,
    #[serde(flatten)]
    macro_samples: Option<SampledApproach>,
}

impl ApproachDistribution {
    /// The macro run's samples, when p(gap) comes from them.
    pub fn sampled(&self) -> Option<&SampledApproach> {
        match self {
            ApproachDistribution::MacroSamples(sa) => Some(sa),
            ApproachDistribution::Kinematics(_) => None,
        }
    }
}

impl TryFrom<ApproachRecord> for ApproachDistribution {
    type Error = String;

    fn try_from(r: ApproachRecord) -> std::result::Result<Self, String> {
        match r.source.as_deref() {
            Some("kinematics") => r
                .kinematics
                .map(ApproachDistribution::Kinematics)
                .ok_or_else(|| "approach: source kinematics without its four approaches".into()),
            Some("macro-samples") => r
                .macro_samples
                .map(ApproachDistribution::MacroSamples)
                .ok_or_else(|| "approach: source macro-samples without its percentiles".into()),
            Some(other) => Err(format!(
                "approach: source {other:?}, expected kinematics or macro-samples"
            )),
            None => match (r.sampled, r.kinematics) {
                (Some(s), _) => Ok(ApproachDistribution::MacroSamples(s)),
                (None, Some(k)) => Ok(ApproachDistribution::Kinematics(k)),
                (None, None) => {
                    Err("approach: expected a source (kinematics or macro-samples)".into())
                }
            },
        }
    }
}

/// One gap bin of the wear-per-contact table.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct WearBin {
    pub gap_from_um: f64,
    pub gap_to_um: f64,
    /// Cells of the evaluated patch in the bin (summed over the segments pooled).
    pub cells: usize,
    /// Summed contact probability of those cells x impacts: the expected contacts.
    pub expected_contacts: f64,
    /// DEM wear depth summed over the bin's cells, um (at the DEM's k).
    pub dem_depth_sum_um: f64,
    /// Cells the DEM wore (depth > 0).
    pub dem_worn_cells: usize,
    /// Wear depth per expected contact, um (at the DEM's k): the table's value, after the
    /// monotone pooling ([`WearTable::pooled_bins`]).
    pub wear_per_contact_um: f64,
    /// The same as measured in this bin alone, before pooling, um.
    #[serde(default)]
    pub measured_wear_per_contact_um: f64,
    /// The bin's value is its pooled block's: its own measurement made a deeper cell wear more
    /// per impact than a shallower one.
    #[serde(default)]
    pub pooled: bool,
}

/// The wear per contact as a function of the gap, measured from DEM segments.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct WearTable {
    pub bins: Vec<WearBin>,
    /// DEM impacts (passes) the table was measured from.
    pub impacts: usize,
    /// DEM wear volume on cells the contact field says no impact reaches (gap beyond the
    /// largest approach), um^3: spread over the reachable bins in proportion to their wear
    /// so the table reproduces the DEM's volume.
    pub dem_volume_beyond_reach_um3: f64,
    pub dem_volume_um3: f64,
    /// Bins whose value comes from pooling with a neighbour: the depth worn per impact,
    /// p(gap) x wear per contact, is made non-increasing in the gap (every contact that reaches
    /// a cell reaches a shallower cell deeper, so within the contact field's own model a deeper
    /// cell never wears faster). Measured violations are the DEM's sampling noise in the few
    /// contacts deep bins hold; left in, they wear valleys as fast as crests and stall the
    /// smoothing. The pooling keeps the table's volume exactly.
    #[serde(default)]
    pub pooled_bins: usize,
}

/// How well the contact field predicts where the DEM wore (one segment).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct FieldCheck {
    /// P(gap of a DEM-worn cell < gap of an unworn cell), ties half: 1 = the gap ranks every
    /// worn cell first, 0.5 = no better than chance.
    pub auc_gap_predicts_worn: f64,
    /// Share of the DEM's wear volume on cells the contact field reaches (p > 0).
    pub dem_volume_within_reach: f64,
    /// Share of the cells the contact field reaches (p > 0).
    pub cells_within_reach: f64,
    /// Share of the cells the DEM wore.
    pub dem_worn_cells: f64,
    /// Median gap of the DEM-worn cells and of all cells, um.
    pub median_gap_worn_um: f64,
    pub median_gap_all_um: f64,
}

/// What an extrapolation did.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Extrapolation {
    pub steps: usize,
    /// Volume removed, um^3 (= the sum of the applied depths x cell area).
    pub volume_um3: f64,
    /// Share of the cells worn at all.
    pub worn_cells: f64,
    /// Stopped at `surfstream_finish::field::MAX_STEPS` with process time (or impacts) left:
    /// the surface is worn less than the laws say (said on stderr; never silent).
    #[serde(default)]
    pub truncated_at_max_steps: bool,
}

// ---------------------------------------------------------------------------------------
// Surface parameters (`surfstream_finish::run`), the patch model (`surfstream_finish::passes`),
// the after-finish registration (`surfstream_finish::after`)

/// ISO 25178 parameters of a (cropped) surface, levelled by its plane.
#[derive(Debug, Clone, Serialize, serde::Deserialize)]
pub struct SurfaceParams {
    #[serde(rename = "Sa")]
    pub sa: f64,
    #[serde(rename = "Sq")]
    pub sq: f64,
    #[serde(rename = "Sp")]
    pub sp: f64,
    #[serde(rename = "Sv")]
    pub sv: f64,
    #[serde(rename = "Sz")]
    pub sz: f64,
    #[serde(rename = "Ssk")]
    pub ssk: f64,
    #[serde(rename = "Sku")]
    pub sku: f64,
    #[serde(rename = "Sdq")]
    pub sdq: f64,
    #[serde(rename = "Sk")]
    pub sk: f64,
    #[serde(rename = "Spk")]
    pub spk: f64,
    #[serde(rename = "Svk")]
    pub svk: f64,
    #[serde(rename = "Smr1")]
    pub smr1: f64,
    #[serde(rename = "Smr2")]
    pub smr2: f64,
}

/// The patch model's fidelity: the tolerance mesh judged at the measured points of the
/// evaluated patch (finish.json `patch.model`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PatchModel {
    pub mesher: String,
    /// The triangle budget it was meshed within (the run's, or four times it for a smooth
    /// surface whose tolerance mesh did not fit).
    #[serde(default)]
    pub budget_triangles: usize,
    /// Triangles of the patch's surface (patch and guard band).
    pub surface_triangles: usize,
    /// max |mesh - measured| over the evaluated patch's samples, each with its mean over the
    /// patch removed, divided by the patch's Sq.
    pub max_error_over_sq: f64,
    pub max_error_um: f64,
    pub rms_error_um: f64,
    pub sq_um: f64,
    /// The mesher's tolerance verdict (Sa, Sq, Sz per region) and its smallest angle.
    pub tolerance_met: Option<bool>,
    pub min_angle_deg: Option<f64>,
    /// The mesh's `curvature` in LIGGGHTS, degrees.
    pub curvature_deg: f64,
    /// What the mesh was judged by (`surfstream_finish::passes::PatchFidelity`): the surface's
    /// kind and its bounds.
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub fidelity: String,
    /// The pointwise bound the mesher was given, um (absent: none, records before it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_error_bound_um: Option<f64>,
}

/// How the after-finish scan was placed on the model (finish.json `after_registration`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AfterRegistration {
    /// The scan's file.
    pub source: String,
    /// What it is for: "after" (`--after`, SIM against the prediction) or "calibration"
    /// (`--calibrate FILE`, the target's Sa).
    pub role: String,
    /// The scan's pixel (0, 0) minus the model's, px (x, y) of the model's grid.
    pub offset_px: [f64; 2],
    /// The same in um.
    pub offset_um: [f64; 2],
    /// NCC of the levelled heights at the offset (the worn surface against the unworn: the
    /// valleys the finishing keeps correlate, the peaks it cuts do not).
    pub ncc: f64,
    /// The scan's shape (rows, cols) before resampling.
    pub scan_shape: [usize; 2],
    /// Share of the model's samples the registered scan covers.
    pub covered_fraction: f64,
    pub method: String,
}
