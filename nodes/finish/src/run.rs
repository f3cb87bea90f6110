//! The finishing simulation, cycle by cycle: DEM segment in LIGGGHTS -> Finnie and Archard
//! wear on the grid -> wear scaled to the process time (or fitted to a target) -> worn surface
//! -> re-mesh -> next segment. Writes the outputs listed in [`outputs`].

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use anyhow::{anyhow, bail, Context, Result};
use serde::Serialize;
use serde_json::Value;
use surfstream_core::metrology::{functional_params, level_plane, params, sim, AbbottCurve, Grid};
use surfstream_core::record;
use surfstream_core::{Sampling, Shape};

use crate::contacts::{archard_from_dump, ContactSummary};
use crate::engine::{run_engine, EngineCommand, EngineProgress};
use crate::field::{self, impact_rate_per_m2_s, ApproachDistribution, FieldGrid, WearTable};
use crate::grid::{crop, mesh_patch, volume_um3, Patch};
use crate::script::{self, input_script, plan_passes, AimArea, Segment};
use crate::setting::{
    hertz_contact_time_s, rayleigh_time_s, Action, BarrelMachine, Media, Workpiece,
    DEFAULT_IMPACT_ANGLE_DEG,
};
use crate::summary::{
    AbbottSummary, CalibrationSummary, CheckMean, ContactFieldSummary, CycleField, CycleRecord,
    CycleVolumeCheck, FinalFit, FinishSetting, FinishSummary, IdealModelRun, PaperValues,
    PatchRecord, ProbeRecord, SimValues, Timings, VolumeCheck, WearVolumes,
};
use crate::vtk::read_vtk;

/// The files a finish writes into its output folder.
pub mod outputs {
    pub const WEAR: &str = "wear.npy";
    pub const WEAR_FINNIE: &str = "wear_finnie.npy";
    pub const WEAR_ARCHARD: &str = "wear_archard.npy";
    pub const WORN: &str = "worn.npy";
    pub const WORN_X3P: &str = "worn.x3p";
    pub const ORIGINAL: &str = "original.npy";
    pub const SUMMARY: &str = "finish.json";
    pub const HTML: &str = "finish.html";
}

/// A height map: the model to finish.
#[derive(Debug, Clone)]
pub struct Model {
    pub heights_um: Vec<f64>,
    pub rows: usize,
    pub cols: usize,
    pub pitch_x_um: f64,
    pub pitch_y_um: f64,
    /// Where it came from (recorded).
    pub source: String,
}

impl Model {
    pub fn from_surface(s: surfstream_io::formats::Surface, source: String) -> Self {
        Model {
            heights_um: s.heights_um,
            rows: s.height,
            cols: s.width,
            pitch_x_um: s.pitch_x_um,
            pitch_y_um: s.pitch_y_um,
            source,
        }
    }
}

/// What to fit the wear coefficient to.
#[derive(Debug, Clone)]
pub enum Calibration {
    /// Sa after the process time (before: the model's own Sa, or this value when given, which
    /// is then reached as the same relative reduction).
    Sa {
        before_um: Option<f64>,
        after_um: f64,
    },
    /// A measured after-finish scan of the same area on the model's grid (same shape): its Sa
    /// is the target, and SIM compares the prediction with it.
    Measured(Model),
}

/// The settings of a finishing run; [`FinishOptions::default`] is the paper's setting.
#[derive(Debug, Clone)]
pub struct FinishOptions {
    /// Patch (width, height), um; None: a centred square as large as the triangle budget
    /// meshes at full resolution.
    pub patch_um: Option<(f64, f64)>,
    /// Guard band around the patch, um; None: 15 % of the patch's larger side.
    pub guard_um: Option<f64>,
    /// Engine wall time for the whole job (all cycles and the ideal run), s.
    pub time_budget_s: f64,
    pub cycles: usize,
    /// Passes per segment; None: as many as the budget allows.
    pub passes: Option<usize>,
    pub media: Media,
    pub workpiece: Workpiece,
    pub machine: BarrelMachine,
    pub impact_angle_deg: f64,
    /// Given directly instead of from the machine.
    pub media_velocity_m_s: Option<f64>,
    pub pressure_pa: Option<f64>,
    /// Finnie's constant in the DEM, 1/Pa; None: the wear model's default
    /// ([`DEFAULT_K_FINNIE_PER_PA`], [`DEFAULT_K_FINNIE_SAMPLED_MAP_PER_PA`]).
    pub k_finnie_per_pa: Option<f64>,
    /// Archard's K / H, 1/Pa.
    pub archard_k_over_h_per_pa: f64,
    /// Real process time the run stands for, s (the paper: 5 min).
    pub process_time_s: f64,
    pub calibrate: Option<Calibration>,
    /// Most triangles of the patch's mesh.
    pub max_triangles: usize,
    pub ranks: usize,
    pub hostfile: Option<PathBuf>,
    pub seed: u64,
    /// Engine cost per triangle and step, s, for planning passes within the budget.
    pub cost_per_triangle_step_s: f64,
    /// Run the ideal model too (the paper's comparison).
    pub ideal: Option<Model>,
    /// How the DEM's wear becomes the process's (default: the contact field).
    pub wear_model: WearModel,
}

/// How a cycle's DEM wear is turned into the wear of its share of the process time.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum WearModel {
    /// The default: the DEM measures the wear per contact as a function of the gap below
    /// the ball's envelope, and the contact field of the current surface, re-closed step by
    /// step, extrapolates it over the process's impacts (crate::field).
    #[default]
    ContactField,
    /// The first method: each cycle's sampled DEM wear map scaled by the acceleration factor
    /// (or fitted per cycle to the target under a depth cap of the crop's Sq).
    SampledMap,
}

impl WearModel {
    pub fn name(self) -> &'static str {
        match self {
            WearModel::ContactField => "contact-field",
            WearModel::SampledMap => "sampled-map",
        }
    }

    pub fn parse(s: &str) -> Result<Self> {
        match s {
            "contact-field" => Ok(WearModel::ContactField),
            "sampled-map" => Ok(WearModel::SampledMap),
            _ => bail!("wear model {s:?}: expected contact-field or sampled-map"),
        }
    }
}

/// The calibration counts as reached when the predicted Sa is within this of the target.
pub const CALIBRATION_TOLERANCE_PERCENT: f64 = 5.0;

impl Default for FinishOptions {
    fn default() -> Self {
        FinishOptions {
            patch_um: None,
            guard_um: None,
            time_budget_s: 300.0,
            cycles: 4,
            passes: None,
            media: Media::default(),
            workpiece: Workpiece::default(),
            machine: BarrelMachine::default(),
            impact_angle_deg: DEFAULT_IMPACT_ANGLE_DEG,
            media_velocity_m_s: None,
            pressure_pa: None,
            k_finnie_per_pa: None,
            archard_k_over_h_per_pa: DEFAULT_ARCHARD_K_OVER_H_PER_PA,
            process_time_s: 300.0,
            calibrate: None,
            max_triangles: 20_000,
            ranks: 1,
            hostfile: None,
            seed: 1,
            cost_per_triangle_step_s: DEFAULT_COST_PER_TRIANGLE_STEP_S,
            ideal: None,
            wear_model: WearModel::ContactField,
        }
    }
}

/// Finnie's constant used when none is given (contact-field model), 1/Pa: the value fitted
/// once by `--calibrate 1.272,0.565` on the demo specimen (5.84e-12, docs/finish.md),
/// rounded. It belongs to this setting (the impact rate, the approach distribution, the DEM
/// passes that measured the wear per contact), not to a material.
pub const DEFAULT_K_FINNIE_PER_PA: f64 = 6e-12;
/// The same for `--wear-model sampled-map`: the mean of its per-cycle fits on the demo,
/// short of the target (its per-cycle depth cap; docs/finish.md).
pub const DEFAULT_K_FINNIE_SAMPLED_MAP_PER_PA: f64 = 9e-17;
/// Largest wear scale the contact field's fit tries (x the process's impacts).
pub const MAX_FIELD_SCALE: f64 = 1e8;
/// Archard K / H when none is given, 1/Pa: K = 1e-4 (a mild abrasive regime) over H = 2 GPa
/// (hardened steel), a textbook order of magnitude, not fitted.
pub const DEFAULT_ARCHARD_K_OVER_H_PER_PA: f64 = 5e-14;
/// Planning estimate of LIGGGHTS' cost per triangle and step with one medium over the patch,
/// s (measured here, docs/finish.md); the real time is measured and reported.
pub const DEFAULT_COST_PER_TRIANGLE_STEP_S: f64 = 4e-8;

/// One progress report of [`finish`].
#[derive(Debug, Clone)]
pub struct Progress {
    pub label: String,
    pub cycle: usize,
    pub cycles: usize,
    pub engine: EngineProgress,
    /// Simulated time of this segment so far, s.
    pub simulated_s: f64,
    pub segment_simulated_s: f64,
}

impl Progress {
    pub fn line(&self) -> String {
        let e = &self.engine;
        format!(
            "finish: {} {}/{}: pass {}/{}, simulated {:.3} of {:.3} ms, engine {:.0} s, ETA {}",
            self.label,
            self.cycle,
            self.cycles,
            e.pass,
            e.passes,
            self.simulated_s * 1e3,
            self.segment_simulated_s * 1e3,
            e.elapsed_s,
            e.eta_s.map_or("?".to_string(), |s| format!("{s:.0} s")),
        )
    }
}

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

/// The levelled heights and parameters of `z` (rows x cols).
pub fn surface_params(z: &[f64], at: Sampling) -> Result<(Vec<f64>, SurfaceParams)> {
    let g = Grid::of(z, at)?;
    let l = level_plane(&g)?;
    let g = Grid::of(&l, at)?;
    let p = params(&g)?;
    let f = functional_params(&g)?;
    let out = SurfaceParams {
        sa: p.sa,
        sq: p.sq,
        sp: p.sp,
        sv: p.sv,
        sz: p.sz,
        ssk: p.ssk,
        sku: p.sku,
        sdq: p.sdq,
        sk: f.sk,
        spk: f.spk,
        svk: f.svk,
        smr1: f.smr1,
        smr2: f.smr2,
    };
    Ok((l, out))
}

/// What one DEM segment gave.
#[derive(Debug, Clone)]
pub struct SegmentResult {
    /// Finnie depth along z on the meshed area, um (in the DEM's own time, unscaled).
    pub finnie_um: Vec<f64>,
    pub archard_um: Vec<f64>,
    /// Sum of wear x area over LIGGGHTS' triangles, um^3.
    pub liggghts_volume_um3: f64,
    /// The same volume after mapping to the grid, um^3.
    pub grid_volume_um3: f64,
    pub unmapped_volume_um3: f64,
    pub contacts: ContactSummary,
    pub segment: Segment,
    pub engine_s: f64,
    pub engine_cpu_s: f64,
    pub stopped: bool,
    pub command: String,
    pub triangles: usize,
    pub mesh_stride: usize,
}

impl SegmentResult {
    pub fn volume_relative_error(&self) -> f64 {
        if self.liggghts_volume_um3 > 0.0 {
            self.grid_volume_um3 / self.liggghts_volume_um3 - 1.0
        } else {
            0.0
        }
    }
}

/// Inputs of one segment that do not change between cycles.
pub struct SegmentPlan<'a> {
    pub engine: &'a EngineCommand,
    pub media: Media,
    pub workpiece: Workpiece,
    pub action: Action,
    pub k_finnie_per_pa: f64,
    pub archard_k_over_h_per_pa: f64,
    pub max_triangles: usize,
    pub timestep_s: f64,
    pub passes: Option<usize>,
    pub engine_budget_s: f64,
    pub cost_per_triangle_step_s: f64,
    pub seed: u64,
    pub contact_every: usize,
}

/// Meshes `heights_um` (the patch + guard, sampled as `at` says), writes the segment's STL and script
/// into `dir`, runs LIGGGHTS and maps its wear back to the grid.
#[allow(clippy::too_many_arguments)]
pub fn run_segment(
    plan: &SegmentPlan<'_>,
    heights_um: &[f64],
    at: Sampling,
    aim_window: crate::grid::Window,
    dir: &Path,
    stop: &AtomicBool,
    progress: &mut dyn FnMut(EngineProgress, &Segment),
) -> Result<SegmentResult> {
    std::fs::create_dir_all(dir).with_context(|| format!("{}: cannot create", dir.display()))?;
    let pm = mesh_patch(heights_um, at, plan.max_triangles)?;
    let (pitch_x_um, pitch_y_um) = (at.pitch_x_um(), at.pitch_y_um());
    let mesh = &pm.target.mesh;
    let stl = dir.join(script::STL);
    surfstream_core::fsutil::write_atomic(&stl, |w| {
        surfstream_mesher::write_stl_ascii(w, mesh, "surfstream finish patch")?;
        Ok(())
    })?;
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for v in &mesh.vertices {
        for k in 0..3 {
            lo[k] = lo[k].min(v[k]);
            hi[k] = hi[k].max(v[k]);
        }
    }
    // The aim window in mesh coordinates (m).
    let to_m = |um: f64, axis: usize| (um - mesh.offset_um[axis]) * 1e-6;
    let aim = AimArea {
        x_m: [
            to_m(aim_window.col0 as f64 * pitch_x_um, 0),
            to_m(
                (aim_window.col0 + aim_window.cols - 1) as f64 * pitch_x_um,
                0,
            ),
        ],
        y_m: [
            to_m(aim_window.row0 as f64 * pitch_y_um, 1),
            to_m(
                (aim_window.row0 + aim_window.rows - 1) as f64 * pitch_y_um,
                1,
            ),
        ],
        top_m: hi[2],
    };
    let guard_m = (aim_window.col0.max(aim_window.row0) as f64) * pitch_x_um * 1e-6;
    let (_, steps_per_pass) = plan_passes(
        1,
        plan.seed,
        aim,
        &plan.media,
        &plan.action,
        plan.timestep_s,
        guard_m,
    );
    let triangles = mesh.triangles.len();
    let passes = plan.passes.unwrap_or_else(|| {
        let steps =
            plan.engine_budget_s / (plan.cost_per_triangle_step_s * triangles.max(1) as f64);
        ((steps / steps_per_pass as f64).floor() as usize).max(1)
    });
    let (passes, steps_per_pass) = plan_passes(
        passes,
        plan.seed,
        aim,
        &plan.media,
        &plan.action,
        plan.timestep_s,
        guard_m,
    );
    let press_force_n = plan.media.load_n(plan.action.pressure_pa)
        + plan.media.mass_kg() * plan.action.acceleration_m_s2;
    let seg = Segment {
        mesh_bounds_m: [[lo[0], hi[0]], [lo[1], hi[1]], [lo[2], hi[2]]],
        triangles,
        media: plan.media,
        workpiece: plan.workpiece,
        k_finnie_per_pa: plan.k_finnie_per_pa,
        timestep_s: plan.timestep_s,
        steps_per_pass,
        passes,
        press_force_n,
        contact_every: plan.contact_every,
        thermo_every: (steps_per_pass / 4).max(1),
    };
    let input = dir.join(script::INPUT);
    std::fs::write(&input, input_script(&seg))
        .with_context(|| format!("{}: cannot write", input.display()))?;
    let run = run_engine(
        plan.engine,
        dir,
        script::INPUT,
        script::LOG,
        seg.steps_per_pass,
        seg.passes.len(),
        stop,
        &mut |p| progress(p, &seg),
    )?;
    if run.stopped {
        return Ok(SegmentResult {
            finnie_um: vec![],
            archard_um: vec![],
            liggghts_volume_um3: 0.0,
            grid_volume_um3: 0.0,
            unmapped_volume_um3: 0.0,
            contacts: ContactSummary::default(),
            segment: seg,
            engine_s: run.wall_s,
            engine_cpu_s: run.cpu_s,
            stopped: true,
            command: run.command,
            triangles,
            mesh_stride: pm.map.stride,
        });
    }
    let vtk = read_vtk(&dir.join(script::WEAR_VTK))?;
    let wear = vtk.field("wear")?;
    let area = vtk.field("area")?;
    let volume_m3: Vec<f64> = wear.iter().zip(area).map(|(w, a)| w * a).collect();
    let liggghts_volume_um3 = volume_m3.iter().sum::<f64>() * 1e18;
    let (finnie_um, unmapped) = pm.map.triangle_volumes_to_depth(&vtk.triangles, &volume_m3);
    let grid_volume_um3 = volume_um3(&finnie_um, at.pitch());
    let (contacts, contact_summary) = archard_from_dump(
        &dir.join(script::CONTACTS),
        plan.archard_k_over_h_per_pa,
        plan.contact_every as f64 * plan.timestep_s,
    )?;
    let points: Vec<(f64, f64, f64)> = contacts
        .iter()
        .map(|c| (c.x_m, c.y_m, c.volume_m3))
        .collect();
    let archard_um = pm.map.point_volumes_to_depth(&points);
    // The contact dump is the bulk of a segment's files; its content is summarised in
    // finish.json (rerunning the script writes it again).
    let _ = std::fs::remove_file(dir.join(script::CONTACTS));
    Ok(SegmentResult {
        finnie_um,
        archard_um,
        liggghts_volume_um3,
        grid_volume_um3,
        unmapped_volume_um3: unmapped * 1e18,
        contacts: contact_summary,
        segment: seg,
        engine_s: run.wall_s,
        engine_cpu_s: run.cpu_s,
        stopped: false,
        command: run.command,
        triangles,
        mesh_stride: pm.map.stride,
    })
}

/// The time step: a fifth of the media's Rayleigh time, and at least 50 steps per Hertz
/// impact at the normal speed.
pub fn timestep_s(media: &Media, workpiece: &Workpiece, action: &Action) -> f64 {
    let v_n = action.media_velocity_m_s * action.impact_angle_deg.to_radians().sin();
    (0.2 * rayleigh_time_s(media)).min(hertz_contact_time_s(media, workpiece, v_n.max(0.05)) / 50.0)
}

/// Sa of the crop of `h - s * wear` (levelled).
fn sa_after(patch: &Patch, h: &[f64], wear: &[f64], s: f64) -> Result<f64> {
    let z: Vec<f64> = h.iter().zip(wear).map(|(a, w)| a - s * w).collect();
    let c = patch.cropped(&z);
    let (_, p) = surface_params(&c, patch.crop_sampling())?;
    Ok(p.sa)
}

/// The scale `s` such that the crop of `h - s * wear` has Sa = `target`: the first crossing
/// on a scan of s up to the scale that wears the deepest point by the crop's Sq, then
/// bisection. Returns the scale and whether the target was reached (else the scale of the
/// smallest Sa within that cap).
fn fit_scale(patch: &Patch, h: &[f64], wear: &[f64], target: f64) -> Result<(f64, bool)> {
    let crop_wear = patch.cropped(wear);
    let max_w = crop_wear.iter().cloned().fold(0.0, f64::max);
    if max_w <= 0.0 {
        return Ok((0.0, false));
    }
    let c = patch.cropped(h);
    let (_, p0) = surface_params(&c, patch.crop_sampling())?;
    if p0.sa <= target {
        return Ok((0.0, true));
    }
    // No point is worn by more than the crop's Sq in one cycle: deeper would cut a touched
    // peak below untouched neighbours, which only the next DEM segment can tell.
    let s_max = p0.sq / max_w;
    let n = 64;
    let mut prev = 0.0;
    let mut best = (0.0, p0.sa);
    for i in 1..=n {
        let s = s_max * i as f64 / n as f64;
        let sa = sa_after(patch, h, wear, s)?;
        if sa < best.1 {
            best = (s, sa);
        }
        if sa <= target {
            let (mut a, mut b) = (prev, s);
            for _ in 0..40 {
                let m = 0.5 * (a + b);
                if sa_after(patch, h, wear, m)? > target {
                    a = m;
                } else {
                    b = m;
                }
            }
            return Ok((0.5 * (a + b), true));
        }
        prev = s;
    }
    Ok((best.0, false))
}

/// A fit of the contact field's scale: the worn surface it ends on and what it took.
struct FieldFit {
    cycle: usize,
    heights_um: Vec<f64>,
    wear_um: Vec<f64>,
    impacts: f64,
    extrapolation: field::Extrapolation,
    reached: bool,
}

impl FieldFit {
    /// Wears a copy of the original surface along the contact field until the crop's Sa
    /// reaches `target_sa_um` (or `max_impacts`): the fit of the tables so far.
    #[allow(clippy::too_many_arguments)]
    fn from_original(
        cycle: usize,
        original_um: &[f64],
        g: field::FieldGrid,
        dist: &field::ApproachDistribution,
        table: &field::WearTable,
        max_impacts: f64,
        target_sa_um: f64,
        stop: &std::sync::atomic::AtomicBool,
        sa_of_crop: impl FnMut(&[f64]) -> Result<f64>,
    ) -> Result<Self> {
        let mut heights_um = original_um.to_vec();
        let mut wear_um = vec![0.0; original_um.len()];
        let (impacts, extrapolation, reached) = field::wear_to_target(
            &mut heights_um,
            &mut wear_um,
            g,
            dist,
            table,
            max_impacts,
            target_sa_um,
            stop,
            sa_of_crop,
        )?;
        Ok(Self {
            cycle,
            heights_um,
            wear_um,
            impacts,
            extrapolation,
            reached,
        })
    }
}

fn add_scaled(acc: &mut [f64], x: &[f64], s: f64) {
    for (a, v) in acc.iter_mut().zip(x) {
        *a += s * v;
    }
}

/// Runs the finishing simulation of `model` into `out_dir`; see the crate doc. `say` gets
/// progress lines (stderr for the CLI). A set `stop` ends the engine; completed cycles are
/// kept and finish.json says `partial`.
pub fn finish(
    model: &Model,
    opts: &FinishOptions,
    out_dir: &Path,
    stop: &AtomicBool,
    say: &mut dyn FnMut(&str),
) -> Result<Value> {
    let t_start = Instant::now();
    if opts.cycles == 0 {
        bail!("--cycles 0: expected at least one cycle");
    }
    if !(opts.time_budget_s.is_finite() && opts.time_budget_s > 0.0) {
        bail!(
            "--time-budget-s {}: expected seconds > 0",
            opts.time_budget_s
        );
    }
    let k_finnie = opts.k_finnie_per_pa.unwrap_or(match opts.wear_model {
        WearModel::ContactField => DEFAULT_K_FINNIE_PER_PA,
        WearModel::SampledMap => DEFAULT_K_FINNIE_SAMPLED_MAP_PER_PA,
    });
    if !(k_finnie.is_finite() && k_finnie > 0.0) {
        bail!("--k-finnie {}: expected a number > 0 (1/Pa)", k_finnie);
    }
    if !(opts.process_time_s.is_finite() && opts.process_time_s > 0.0) {
        bail!(
            "--process-time-s {}: expected seconds > 0",
            opts.process_time_s
        );
    }
    opts.media.validate()?;
    let engine = EngineCommand::locate(opts.ranks, opts.hostfile.clone())?;
    let mut action = opts.machine.action(&opts.media, opts.impact_angle_deg)?;
    if opts.media_velocity_m_s.is_some() || opts.pressure_pa.is_some() {
        if let Some(v) = opts.media_velocity_m_s {
            if !(v.is_finite() && v > 0.0) {
                bail!("--media-velocity-m-s {v}: expected > 0");
            }
            action.media_velocity_m_s = v;
        }
        if let Some(p) = opts.pressure_pa {
            if !(p.is_finite() && p >= 0.0) {
                bail!("--pressure-pa {p}: expected >= 0");
            }
            action.pressure_pa = p;
        }
        action.source = format!("given directly (the rest from {})", action.source);
    }
    std::fs::create_dir_all(out_dir)
        .with_context(|| format!("{}: cannot create", out_dir.display()))?;

    // The patch: default a square meshed at full resolution within the triangle budget.
    let side_samples = ((opts.max_triangles as f64 / 2.0).sqrt()).floor().max(4.0);
    let (pw, ph) = opts.patch_um.unwrap_or((
        (side_samples * model.pitch_x_um).min(model.cols as f64 * model.pitch_x_um * 0.7),
        (side_samples * model.pitch_y_um).min(model.rows as f64 * model.pitch_y_um * 0.7),
    ));
    let guard = opts.guard_um.unwrap_or(0.15 * pw.max(ph));
    let model_at = Sampling::new(
        Shape::new(model.rows, model.cols),
        model.pitch_x_um,
        model.pitch_y_um,
    )
    .with_context(|| model.source.clone())?;
    let patch = Patch::cut(&model.heights_um, model_at, pw, ph, guard)
        .with_context(|| model.source.clone())?;
    let dt = timestep_s(&opts.media, &opts.workpiece, &action);
    let segments = opts.cycles + usize::from(opts.ideal.is_some());
    let plan = SegmentPlan {
        engine: &engine,
        media: opts.media,
        workpiece: opts.workpiece,
        action: action.clone(),
        k_finnie_per_pa: k_finnie,
        archard_k_over_h_per_pa: opts.archard_k_over_h_per_pa,
        max_triangles: opts.max_triangles,
        timestep_s: dt,
        passes: opts.passes,
        engine_budget_s: opts.time_budget_s / segments as f64,
        cost_per_triangle_step_s: opts.cost_per_triangle_step_s,
        seed: opts.seed,
        contact_every: 5,
    };
    say(&format!(
        "finish: patch {} x {} samples ({:.0} x {:.0} um) in a {} x {} area with its guard band, \
         media {} mm at {:.2} m/s, {:.0} Pa, dt {:.2e} s, engine {}",
        patch.crop.rows,
        patch.crop.cols,
        patch.crop.cols as f64 * patch.sampling.pitch_x_um(),
        patch.crop.rows as f64 * patch.sampling.pitch_y_um(),
        patch.sampling.rows(),
        patch.sampling.cols(),
        opts.media.diameter_mm,
        action.media_velocity_m_s,
        action.pressure_pa,
        dt,
        engine.argv(script::INPUT, script::LOG).join(" ")
    ));

    let (original_crop, before) =
        surface_params(&patch.cropped(&patch.heights_um), patch.crop_sampling())?;
    // The calibration target: Sa after the whole process.
    let measured_after = match &opts.calibrate {
        Some(Calibration::Measured(m)) => {
            if (m.rows, m.cols) != (model.rows, model.cols) {
                bail!(
                    "{}: the measured after-finish scan is {} x {} (rows x cols); the model is {} x {}",
                    m.source, m.rows, m.cols, model.rows, model.cols
                );
            }
            let w = patch.in_model;
            let area = crop(&m.heights_um, m.cols, w);
            let inner = crop(&area, w.cols, patch.crop);
            Some(surface_params(&inner, patch.crop_sampling())?)
        }
        _ => None,
    };
    let target_sa = match &opts.calibrate {
        None => None,
        Some(Calibration::Sa {
            before_um,
            after_um,
        }) => {
            if !(after_um.is_finite() && *after_um > 0.0) {
                bail!("--calibrate: Sa after {after_um}: expected um > 0");
            }
            Some(match before_um {
                Some(b) if *b > 0.0 => before.sa * after_um / b,
                _ => *after_um,
            })
        }
        Some(Calibration::Measured(_)) => measured_after.as_ref().map(|(_, p)| p.sa),
    };

    let mut h = patch.heights_um.clone();
    let n = h.len();
    let mut finnie_total = vec![0.0; n];
    let mut archard_total = vec![0.0; n];
    let mut cycles_json = Vec::new();
    let mut engine_s = 0.0;
    let mut engine_cpu_s = 0.0;
    let mut cost = opts.cost_per_triangle_step_s;
    let mut partial = false;
    let mut first_finnie_map: Option<Vec<f64>> = None;
    let mut worst_volume_error: f64 = 0.0;
    let mut sim_time_total = 0.0;
    // The contact-field model (crate::field): the approach distribution, the process's
    // impacts on the evaluated patch, and the wear-per-contact table pooled over the cycles.
    let press_force_n =
        opts.media.load_n(action.pressure_pa) + opts.media.mass_kg() * action.acceleration_m_s2;
    let dist = ApproachDistribution::of(&opts.media, &opts.workpiece, &action, press_force_n);
    let field_grid = FieldGrid {
        sampling: patch.sampling,
        radius_um: opts.media.radius_m() * 1e6,
    };
    let cell_area_um2 = patch.sampling.pitch().cell_area_um2();
    let aim_area_um2 = cell_area_um2 * (patch.crop.rows * patch.crop.cols) as f64;
    let impact_rate = impact_rate_per_m2_s(&opts.media, &action);
    let impacts_process = impact_rate * aim_area_um2 * 1e-12 * opts.process_time_s;
    let mut table = WearTable::empty(dist.max_um());
    let mut provisional_scale: Option<f64> = None;
    let mut last_fit: Option<FieldFit> = None;
    let mut archard_sampled: Vec<(Vec<f64>, f64)> = Vec::new();
    let mut checks: Vec<field::FieldCheck> = Vec::new();
    let mut sa_of_crop = |z: &[f64]| -> Result<f64> {
        let c = patch.cropped(z);
        let g = Grid::of(&c, patch.crop_sampling())?;
        let l = level_plane(&g)?;
        let g = Grid::of(&l, patch.crop_sampling())?;
        Ok(params(&g)?.sa)
    };
    // Planning passes within the budget needs the engine's cost on this machine now (a busy
    // machine makes it several times the quiet estimate): a probe of two passes measures it.
    let mut probe: Option<ProbeRecord> = None;
    if opts.passes.is_none() {
        let r = run_segment(
            &SegmentPlan {
                passes: Some(2),
                ..plan.clone_with_engine(&engine)
            },
            &h,
            patch.sampling,
            patch.crop,
            &out_dir.join("probe"),
            stop,
            &mut |_, _| {},
        )?;
        engine_s += r.engine_s;
        engine_cpu_s += r.engine_cpu_s;
        let steps = r.triangles as f64 * r.segment.total_steps() as f64;
        if !r.stopped && steps > 0.0 {
            cost = r.engine_s / steps;
        }
        say(&format!(
            "finish: probe: {} triangles x {} steps in {:.1} s ({:.2e} s per triangle-step, start-up included)",
            r.triangles,
            r.segment.total_steps(),
            r.engine_s,
            cost
        ));
        probe = Some(ProbeRecord {
            dir: "probe".into(),
            engine_s: r.engine_s,
            engine_cpu_s: r.engine_cpu_s,
            triangles: r.triangles,
            steps: r.segment.total_steps(),
            cost_per_triangle_step_s: cost,
        });
        partial |= r.stopped;
    }
    for c in 1..=opts.cycles {
        if partial {
            break;
        }
        let dir = out_dir.join(format!("cycle_{c:02}"));
        // The budget left, shared by the segments left, at the cost measured so far (the
        // machine may be busier than the planning estimate assumes).
        let left = segments - (c - 1);
        let seg_plan = SegmentPlan {
            seed: opts.seed.wrapping_add(c as u64 - 1),
            engine_budget_s: ((opts.time_budget_s - engine_s) / left as f64)
                .max(0.02 * opts.time_budget_s),
            cost_per_triangle_step_s: cost,
            ..plan.clone_with_engine(&engine)
        };
        let cycles = opts.cycles;
        let mut last_say = Instant::now();
        let r = run_segment(
            &seg_plan,
            &h,
            patch.sampling,
            patch.crop,
            &dir,
            stop,
            &mut |p, seg| {
                if last_say.elapsed().as_secs_f64() >= 2.0 || p.steps_done == p.steps_total {
                    last_say = Instant::now();
                    say(&Progress {
                        label: "cycle".into(),
                        cycle: c,
                        cycles,
                        engine: p,
                        simulated_s: p.steps_done as f64 * seg.timestep_s,
                        segment_simulated_s: seg.simulated_time_s(),
                    }
                    .line());
                }
            },
        )?;
        engine_s += r.engine_s;
        engine_cpu_s += r.engine_cpu_s;
        let steps = r.triangles as f64 * r.segment.total_steps() as f64;
        if !r.stopped && steps > 0.0 {
            cost = r.engine_s / steps;
        }
        if r.stopped {
            partial = true;
            say(&format!(
                "finish: stopped during cycle {c}; keeping {} completed cycle(s)",
                c - 1
            ));
            break;
        }
        let sim_s = r.segment.simulated_time_s();
        sim_time_total += sim_s;
        if first_finnie_map.is_none() {
            first_finnie_map = Some(r.finnie_um.clone());
        }
        let dem_passes = r.segment.passes.len();
        let (scale, reached, acceleration, fitted_k, cycle_field) = match opts.wear_model {
            WearModel::SampledMap => {
                // The acceleration factor: each cycle stands for its share of the process time.
                let acceleration = opts.process_time_s / opts.cycles as f64 / sim_s;
                let (scale, reached) = match target_sa {
                    Some(t) => {
                        let sa0 = before.sa;
                        let goal = sa0 * (t / sa0).powf(c as f64 / opts.cycles as f64);
                        fit_scale(&patch, &h, &r.finnie_um, goal)?
                    }
                    None => (acceleration, true),
                };
                let fitted_k = k_finnie * scale / acceleration;
                // A wear deeper than the whole roughness in one cycle is not a finishing step:
                // the constant does not fit the process time (and the re-mesh would be slivers).
                let deepest = patch
                    .cropped(&r.finnie_um)
                    .iter()
                    .fold(0.0f64, |m, w| m.max(w * scale));
                let (_, now) = surface_params(&patch.cropped(&h), patch.crop_sampling())?;
                if deepest > (2.0 * now.sz).max(0.5) {
                    bail!(
                        "cycle {c}: the wear is {deepest:.3e} um deep at its deepest, more than twice the \
                         patch's Sz ({:.3} um) and 0.5 um: k_finnie {:.3e} 1/Pa is far too large for a process \
                         time of {} s; fit it with --calibrate SA_BEFORE,SA_AFTER or give a smaller --k-finnie",
                        now.sz,
                        k_finnie,
                        opts.process_time_s
                    );
                }
                add_scaled(&mut finnie_total, &r.finnie_um, scale);
                add_scaled(&mut archard_total, &r.archard_um, scale);
                add_scaled(&mut h, &r.finnie_um, -scale);
                (scale, reached, acceleration, fitted_k, None)
            }
            WearModel::ContactField => {
                // The contact field of the surface this segment ran on, checked against
                // where the DEM wore, and the wear per contact it measured.
                let gap = field::ball_gap_um(&h, patch.sampling, field_grid.radius_um);
                let gap_crop = patch.cropped(&gap);
                let dem_crop = patch.cropped(&r.finnie_um);
                let check = field::check_field(&dist, &gap_crop, &dem_crop);
                let mut own = WearTable::empty(dist.max_um());
                own.add_segment(&dist, &gap_crop, &dem_crop, dem_passes, cell_area_um2)?;
                table.add_segment(&dist, &gap_crop, &dem_crop, dem_passes, cell_area_um2)?;
                let impacts_cycle = impacts_process / opts.cycles as f64;
                // The scale that steers the next segments' surfaces: refitted on the tables
                // so far over the whole process (the final fit, once, uses every table).
                if let Some(t) = target_sa {
                    let fit = FieldFit::from_original(
                        c,
                        &patch.heights_um,
                        field_grid,
                        &dist,
                        &table,
                        impacts_process * MAX_FIELD_SCALE,
                        t,
                        stop,
                        &mut sa_of_crop,
                    )?;
                    provisional_scale = Some(fit.impacts / impacts_process);
                    // After the last cycle this is the final fit (same tables): kept.
                    last_fit = Some(fit);
                }
                let scale = provisional_scale.unwrap_or(1.0);
                // The next segment's surface: the model's estimate at the end of this cycle's
                // share of the process, from the original with the tables so far.
                let mut h_next = patch.heights_um.clone();
                let mut w_next = vec![0.0; n];
                let e = field::extrapolate(
                    &mut h_next,
                    &mut w_next,
                    field_grid,
                    &dist,
                    &table,
                    impacts_cycle * c as f64,
                    scale,
                );
                h = h_next;
                finnie_total = w_next;
                archard_sampled.push((r.archard_um.clone(), impacts_cycle / dem_passes as f64));
                say(&format!(
                    "finish: cycle {c}: contact field: AUC {:.3} (gap ranks the DEM's worn cells), {:.1} % of the DEM wear within reach; {} extrapolation steps",
                    check.auc_gap_predicts_worn,
                    check.dem_volume_within_reach * 100.0,
                    e.steps
                ));
                checks.push(check.clone());
                let acceleration = impacts_cycle / dem_passes as f64;
                (
                    scale,
                    true,
                    acceleration,
                    k_finnie * scale,
                    Some(CycleField {
                        check,
                        table: own,
                        impacts: impacts_cycle,
                        dem_impacts: dem_passes,
                        extrapolation: e,
                        scale_is: if target_sa.is_some() { "provisional (fitted on the tables so far); the final fit uses every table" } else { "1: k_finnie as given" }.into(),
                    }),
                )
            }
        };
        let (_, after_c) = surface_params(&patch.cropped(&h), patch.crop_sampling())?;
        worst_volume_error = worst_volume_error.max(r.volume_relative_error().abs());
        say(&format!(
            "finish: cycle {c}/{} ({}): {} passes, {:.3} ms simulated in {:.1} s; wear x {:.3e}{}; Sa {:.3} um (volume check {:+.2e})",
            opts.cycles,
            opts.wear_model.name(),
            r.segment.passes.len(),
            sim_s * 1e3,
            r.engine_s,
            scale,
            if target_sa.is_some() { format!(" (fitted k_finnie {fitted_k:.3e} 1/Pa{})", if reached { "" } else { ", target NOT reached" }) } else { String::new() },
            after_c.sa,
            r.volume_relative_error()
        ));
        cycles_json.push(CycleRecord {
            cycle: c,
            dir: format!("cycle_{c:02}"),
            command: r.command.clone(),
            triangles: r.triangles,
            mesh_block_stride: r.mesh_stride,
            passes: r.segment.passes.len(),
            steps_per_pass: r.segment.steps_per_pass,
            timestep_s: r.segment.timestep_s,
            simulated_s: sim_s,
            engine_s: r.engine_s,
            engine_cpu_s: r.engine_cpu_s,
            cost_per_triangle_step_s: r.engine_s
                / (r.triangles as f64 * r.segment.total_steps() as f64),
            cpu_per_triangle_step_s: r.engine_cpu_s
                / (r.triangles as f64 * r.segment.total_steps() as f64),
            acceleration_factor: acceleration,
            wear_scale: scale,
            target_reached: reached,
            k_finnie_equivalent_per_pa: fitted_k,
            volume_check: CycleVolumeCheck {
                liggghts_um3: r.liggghts_volume_um3,
                grid_um3: r.grid_volume_um3,
                unmapped_um3: r.unmapped_volume_um3,
                relative_error: r.volume_relative_error(),
            },
            archard_volume_um3: volume_um3(&r.archard_um, patch.sampling.pitch()),
            contacts: record::to_value(&r.contacts),
            contact_field: cycle_field,
            after: after_c,
        });
    }
    let completed = cycles_json.len();
    // A stop during the contact field's fit (no engine running) ends the run the same way.
    if stop.load(std::sync::atomic::Ordering::Relaxed) {
        partial = true;
    }

    // The contact field's final fit, once, with every cycle's table, from the original
    // surface over the whole process time; without a target the cycles' wear stands (k as
    // given).
    let mut final_fit: Option<FinalFit> = None;
    if opts.wear_model == WearModel::ContactField && completed > 0 {
        let mut scale = provisional_scale.unwrap_or(1.0);
        if let (Some(t), false) = (target_sa, partial) {
            let fit = match last_fit.take().filter(|f| f.cycle == completed) {
                Some(f) => f,
                None => FieldFit::from_original(
                    completed,
                    &patch.heights_um,
                    field_grid,
                    &dist,
                    &table,
                    impacts_process * MAX_FIELD_SCALE,
                    t,
                    stop,
                    &mut sa_of_crop,
                )?,
            };
            let FieldFit {
                heights_um: h0,
                wear_um: w0,
                impacts: used,
                extrapolation: e,
                reached,
                ..
            } = fit;
            scale = used / impacts_process;
            h = h0;
            finnie_total = w0;
            let sa = sa_of_crop(&h)?;
            let err = sa / t - 1.0;
            say(&format!(
                "finish: contact field fitted once over {} impacts on the patch: scale {scale:.4e} (k_finnie {:.3e} 1/Pa), Sa {sa:.4} um for the target {t:.4} ({:+.2} %){}",
                impacts_process,
                k_finnie * scale,
                err * 100.0,
                if reached { "" } else { ": target NOT reached" }
            ));
            final_fit = Some(FinalFit {
                scale,
                k_finnie_fitted_per_pa: k_finnie * scale,
                sa_after_um: sa,
                relative_error: err,
                reached: reached && err.abs() * 100.0 <= CALIBRATION_TOLERANCE_PERCENT,
                extrapolation: e,
            });
        }
        archard_total = vec![0.0; n];
        for (map, factor) in &archard_sampled {
            add_scaled(&mut archard_total, map, factor * scale);
        }
    }

    // The paper's comparison: the ideal model (form only) under the same first segment.
    let mut ideal_run: Option<IdealModelRun> = None;
    if let (Some(ideal), false, Some(hifi_map)) = (&opts.ideal, partial, &first_finnie_map) {
        if (ideal.rows, ideal.cols) != (model.rows, model.cols) {
            bail!(
                "{}: the ideal model is {} x {}; the model is {} x {}",
                ideal.source,
                ideal.rows,
                ideal.cols,
                model.rows,
                model.cols
            );
        }
        let w = patch.in_model;
        let area = crop(&ideal.heights_um, ideal.cols, w);
        let g = Grid::of(&area, patch.sampling.with_shape(Shape::new(w.rows, w.cols)))?;
        let levelled = level_plane(&g)?;
        let dir = out_dir.join("ideal");
        let mut last_say = Instant::now();
        let r = run_segment(
            &SegmentPlan {
                seed: opts.seed,
                engine_budget_s: (opts.time_budget_s - engine_s).max(0.02 * opts.time_budget_s),
                cost_per_triangle_step_s: cost,
                ..plan.clone_with_engine(&engine)
            },
            &levelled,
            patch.sampling.with_shape(Shape::new(w.rows, w.cols)),
            patch.crop,
            &dir,
            stop,
            &mut |p, seg| {
                if last_say.elapsed().as_secs_f64() >= 2.0 {
                    last_say = Instant::now();
                    say(&Progress {
                        label: "ideal model".into(),
                        cycle: 1,
                        cycles: 1,
                        engine: p,
                        simulated_s: p.steps_done as f64 * seg.timestep_s,
                        segment_simulated_s: seg.simulated_time_s(),
                    }
                    .line());
                }
            },
        )?;
        engine_s += r.engine_s;
        engine_cpu_s += r.engine_cpu_s;
        if r.stopped {
            partial = true;
        } else {
            let a = patch.cropped(hifi_map);
            let b = patch.cropped(&r.finnie_um);
            let s = sim(&a, &b).unwrap_or(f64::NAN);
            say(&format!(
                "finish: SIM(wear map of the model, wear map of the ideal model) = {s:.3}"
            ));
            ideal_run = Some(IdealModelRun {
                source: ideal.source.clone(),
                dir: "ideal".into(),
                engine_s: r.engine_s,
                volume_um3: r.grid_volume_um3,
                sim_wear_maps: s.is_finite().then_some(s),
                note: "SIM (eq. 12) between the first cycle's Finnie map on the model and on the ideal model, same passes".into(),
            });
        }
    }

    // Outputs on the crop.
    let (rows, cols) = (patch.crop.rows, patch.crop.cols);
    let finnie_crop = patch.cropped(&finnie_total);
    let archard_crop = patch.cropped(&archard_total);
    let worn_raw = patch.cropped(&h);
    let (worn_crop, after) = surface_params(&worn_raw, patch.crop_sampling())?;
    // Every .npy keeps its pitch in its sidecar, as every other writer of the project does.
    let geometry = surfstream_io::sidecar::NpyGeometry {
        pitch_x_um: patch.sampling.pitch_x_um(),
        pitch_y_um: patch.sampling.pitch_y_um(),
        origin_um: None,
    };
    let write = |name: &str, z: &[f64]| -> Result<()> {
        let path = out_dir.join(name);
        surfstream_io::npy::write_npy_f64(&path, z, rows, cols)
            .map_err(|e| anyhow!("{}: {e}", path.display()))?;
        surfstream_io::sidecar::write_sidecar(&path, &geometry)
    };
    write(outputs::WEAR, &finnie_crop)?;
    write(outputs::WEAR_FINNIE, &finnie_crop)?;
    write(outputs::WEAR_ARCHARD, &archard_crop)?;
    write(outputs::WORN, &worn_crop)?;
    write(outputs::ORIGINAL, &original_crop)?;
    let x3p = surfstream_io::formats::Surface {
        width: cols,
        height: rows,
        pitch_x_um: patch.sampling.pitch_x_um(),
        pitch_y_um: patch.sampling.pitch_y_um(),
        heights_um: worn_crop.clone(),
        metadata: surfstream_io::formats::Metadata {
            format: "x3p".into(),
            pitch_known: true,
            ..Default::default()
        },
    };
    surfstream_io::formats::write_surface(&out_dir.join(outputs::WORN_X3P), &x3p)?;

    let sim_finnie_archard = sim(&finnie_crop, &archard_crop)
        .ok()
        .filter(|s| s.is_finite());
    let sim_measured = measured_after
        .as_ref()
        .and_then(|(m, _)| sim(&worn_crop, m).ok())
        .filter(|s| s.is_finite());
    let total_s = t_start.elapsed().as_secs_f64();
    let abbott = |z: &[f64]| -> Result<AbbottSummary> {
        let g = Grid::of(z, patch.crop_sampling())?;
        let a = AbbottCurve::of(&g)?;
        Ok(AbbottSummary {
            material_ratio_pct: a.material_ratio_pct,
            height_um: a.height_um,
        })
    };
    let check_mean = |f: &dyn Fn(&field::FieldCheck) -> f64| -> Option<f64> {
        let v: Vec<f64> = checks.iter().map(f).filter(|x| x.is_finite()).collect();
        (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
    };
    let summary = FinishSummary {
        model: model.source.clone(),
        partial,
        cycles_completed: completed,
        cycles_requested: opts.cycles,
        setting: Some(FinishSetting {
            patch: PatchRecord {
                rows_cols: [rows, cols],
                size_um: [cols as f64 * patch.sampling.pitch_x_um(), rows as f64 * patch.sampling.pitch_y_um()],
                pitch_um: [patch.sampling.pitch_x_um(), patch.sampling.pitch_y_um()],
                in_model_rows_cols_origin: [patch.in_model.row0 + patch.crop.row0, patch.in_model.col0 + patch.crop.col0],
                guard_band_um: guard,
                meshed_area_rows_cols: [patch.sampling.rows(), patch.sampling.cols()],
                boundary: "guard band of real neighbouring surface, meshed and worn, then cropped (not periodic: a mirrored seam is an artificial ridge, and a 3 mm medium spans the whole patch)".into(),
                levelled: "least-squares plane of the meshed area removed".into(),
                filled_samples: patch.filled_samples,
            },
            media: opts.media,
            workpiece: opts.workpiece,
            machine: opts.machine,
            action: action.clone(),
            press_force_n: opts.media.load_n(action.pressure_pa) + opts.media.mass_kg() * action.acceleration_m_s2,
            k_finnie_per_pa: k_finnie,
            archard_k_over_h_per_pa: opts.archard_k_over_h_per_pa,
            process_time_s: opts.process_time_s,
            timestep_s: dt,
            ranks: opts.ranks,
            max_triangles: opts.max_triangles,
            time_budget_s: opts.time_budget_s,
            seed: opts.seed,
            wear_depth: "volume (LIGGGHTS' normal wear x triangle area) spread to the grid: depth along z = normal wear / cos(slope)".into(),
            acceleration: "each cycle's wear x (process time / cycles) / simulated time, or x the scale fitted to the calibration target".into(),
        }),
        calibration: opts.calibrate.as_ref().map(|c| CalibrationSummary {
            kind: match c { Calibration::Sa{..} => "Sa before/after", Calibration::Measured(_) => "measured after-finish scan" }.into(),
            target_sa_um: target_sa,
            wear_model: Some(opts.wear_model.name().into()),
            tolerance_percent: Some(CALIBRATION_TOLERANCE_PERCENT),
            k_finnie_fitted_per_pa: if opts.wear_model == WearModel::ContactField {
                final_fit.as_ref().map(|f| f.k_finnie_fitted_per_pa)
            } else if completed > 0 {
                // Cycles whose constant is not finite were written as null and left out.
                Some(cycles_json.iter().map(|c| c.k_finnie_equivalent_per_pa).filter(|k| k.is_finite()).sum::<f64>() / completed as f64)
            } else { None },
            sa_after_um: Some(after.sa),
            relative_error: target_sa.map(|t| after.sa / t - 1.0),
            reached: target_sa.map(|t| !partial && (after.sa / t - 1.0).abs() * 100.0 <= CALIBRATION_TOLERANCE_PERCENT),
            fit: final_fit.clone(),
            provisional_scale,
            measured_after: measured_after.as_ref().map(|(_, p)| p.clone()),
        }),
        wear_model: Some(opts.wear_model.name().into()),
        contact_field: (opts.wear_model == WearModel::ContactField).then(|| ContactFieldSummary {
            ball_radius_um: field_grid.radius_um,
            closing: "the surface closed with the paraboloid r^2/2R of the media's radius (separable lower envelope of parabolas, exact, at the model's full resolution, over the patch and its guard band); the sphere differs from it by r^4/8R^3 (0.06 um at 200 um for R = 1.5 mm)".into(),
            approach: Some(dist),
            approach_model: "Hertz approach (15 m v_n^2 / (16 E* sqrt R))^(2/5), impact angle uniform on [0, max_impact_angle_deg] at the media speed; the press load's static approach a floor; p(gap) = P(approach > gap)".into(),
            impact_rate_per_m2_s: impact_rate,
            impact_rate_model: "the bed's contact layer holds one medium per 2 sqrt(3) r^2 and each strikes afresh once per diameter travelled at the media speed (an assumption)".into(),
            patch_area_um2: aim_area_um2,
            impacts_over_process: impacts_process,
            step_depth_um: field::STEP_DEPTH_UM,
            table: table.clone(),
            check_mean: CheckMean {
                auc_gap_predicts_worn: check_mean(&|c| c.auc_gap_predicts_worn),
                dem_volume_within_reach: check_mean(&|c| c.dem_volume_within_reach),
                cells_within_reach: check_mean(&|c| c.cells_within_reach),
                dem_worn_cells: check_mean(&|c| c.dem_worn_cells),
            },
            worn_cells_after: Some(finnie_crop.iter().filter(|w| **w > 0.0).count() as f64 / finnie_crop.len().max(1) as f64),
        }),
        paper: Some(PaperValues {
            before: [("Sa", 1.272), ("Sq", 1.624), ("Sz", 15.262)].map(|(k, v)| (k.to_string(), v)).into(),
            after: [("Sa", 0.565), ("Sq", 0.708), ("Sz", 6.162)].map(|(k, v)| (k.to_string(), v)).into(),
            process_time_s: 300,
        }),
        before,
        after,
        abbott_before: abbott(&original_crop)?,
        abbott_after: abbott(&worn_crop)?,
        volume_check: Some(VolumeCheck {
            relative_error: worst_volume_error,
            what: "largest |grid volume / LIGGGHTS' sum of wear x area - 1| over the cycles".into(),
        }),
        wear: Some(WearVolumes {
            finnie_volume_um3: volume_um3(&finnie_crop, patch.sampling.pitch()),
            archard_volume_um3: volume_um3(&archard_crop, patch.sampling.pitch()),
            max_depth_um: finnie_crop.iter().cloned().fold(0.0, f64::max),
            mean_depth_um: finnie_crop.iter().sum::<f64>() / finnie_crop.len() as f64,
        }),
        sim: Some(SimValues {
            finnie_vs_archard: sim_finnie_archard,
            worn_vs_measured_after: sim_measured,
        }),
        ideal_model: ideal_run,
        cycles: cycles_json,
        probe,
        timings: Timings {
            engine_s,
            engine_cpu_s,
            total_s,
            surfstream_overhead_s: total_s - engine_s,
            overhead_share_of_engine: (engine_s > 0.0).then(|| (total_s - engine_s) / engine_s),
            simulated_s: sim_time_total,
        },
        outputs: [outputs::WEAR, outputs::WEAR_FINNIE, outputs::WEAR_ARCHARD, outputs::WORN, outputs::WORN_X3P, outputs::ORIGINAL, outputs::SUMMARY, outputs::HTML].map(String::from).into(),
    };
    // Written as a JSON value: its keys sorted, as finish.json has always had them.
    let summary = record::to_value(&summary);
    let path = out_dir.join(outputs::SUMMARY);
    surfstream_core::fsutil::write_atomic(&path, |w| {
        serde_json::to_writer_pretty(w, &summary).map_err(|e| anyhow!("{}: {e}", path.display()))
    })?;
    crate::html::write_report(
        &out_dir.join(outputs::HTML),
        &summary,
        &original_crop,
        &worn_crop,
        &finnie_crop,
        rows,
        cols,
    )?;
    Ok(summary)
}

impl SegmentPlan<'_> {
    fn clone_with_engine<'b>(&self, engine: &'b EngineCommand) -> SegmentPlan<'b> {
        SegmentPlan {
            engine,
            media: self.media,
            workpiece: self.workpiece,
            action: self.action.clone(),
            k_finnie_per_pa: self.k_finnie_per_pa,
            archard_k_over_h_per_pa: self.archard_k_over_h_per_pa,
            max_triangles: self.max_triangles,
            timestep_s: self.timestep_s,
            passes: self.passes,
            engine_budget_s: self.engine_budget_s,
            cost_per_triangle_step_s: self.cost_per_triangle_step_s,
            seed: self.seed,
            contact_every: self.contact_every,
        }
    }
}
