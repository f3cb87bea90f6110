//! The finishing simulation, cycle by cycle: DEM segment in LIGGGHTS -> Finnie and Archard
//! wear on the grid -> wear scaled to the process time (or fitted to a target) -> worn surface
//! -> re-mesh -> next segment. Writes the outputs listed in [`outputs`].

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;

use anyhow::{bail, Context, Result};
use surfstream_core::metrology::{functional_params, level_plane, params, Grid};
use surfstream_core::Sampling;

use crate::contacts::{archard_from_dump, ContactSummary};
use crate::engine::{run_engine, EngineCommand, EngineProgress};
use crate::grid::{mesh_patch, volume_um3};
use crate::script::{self, input_script, plan_passes, AimArea, Segment};
use crate::setting::{
    hertz_contact_time_s, rayleigh_time_s, Action, BarrelMachine, Media, MediaPhysics,
    PartMaterialPhysics, Workpiece, DEFAULT_IMPACT_ANGLE_DEG,
};
use crate::vtk::read_vtk;

/// finish.json's surface parameters (`before`, `after`, ...) are core's record.
pub use surfstream_core::record::finish::SurfaceParams;

/// The files a finish writes into its output folder.
pub mod outputs {
    pub const WEAR: &str = "wear.npy";
    pub const WEAR_FINNIE: &str = "wear_finnie.npy";
    pub const WEAR_ARCHARD: &str = "wear_archard.npy";
    /// The ideal model's predicted wear (with an ideal model and a prediction).
    pub const WEAR_IDEAL: &str = "wear_ideal.npy";
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

/// The patch mesh's triangle budget: the demo's 300 um patch (with its guard band) at the
/// measured model's pointwise bound needs 42 609 (docs/finish.md); LIGGGHTS' cost is about
/// linear in it.
pub const DEFAULT_MAX_TRIANGLES: usize = 60_000;

/// The default patch's side, samples (81 um at the Zygo's 0.8148 um pitch).
pub const DEFAULT_PATCH_SIDE_SAMPLES: usize = 100;

/// The settings of a finishing run; [`FinishOptions::default`] is the paper's setting.
#[derive(Debug, Clone)]
pub struct FinishOptions {
    /// Patch (width, height), um; None: a centred square of [`DEFAULT_PATCH_SIDE_SAMPLES`]
    /// samples a side.
    pub patch_um: Option<(f64, f64)>,
    /// Guard band around the patch, um; None: 15 % of the patch's larger side.
    pub guard_um: Option<f64>,
    /// Engine wall time for the whole job (all cycles and the ideal run), s.
    pub time_budget_s: f64,
    pub cycles: usize,
    /// Passes per segment; None: as many as the budget allows.
    pub passes: Option<usize>,
    pub media: Media,
    pub machine: BarrelMachine,
    pub impact_angle_deg: f64,
    /// Given directly instead of from the machine.
    pub media_velocity_m_s: Option<f64>,
    pub pressure_pa: Option<f64>,
    /// Finnie's constant in the DEM, 1/Pa; None: the wear model's default
    /// ([`DEFAULT_K_FINNIE_PER_PA`], [`DEFAULT_K_FINNIE_SAMPLED_MAP_PER_PA`]).
    pub k_finnie_per_pa: Option<f64>,
    /// Archard's K / H, 1/Pa, when given (a sweep's setting takes the base's fitted one);
    /// None: [`ARCHARD_K`] over the part's hardness ([`FinishOptions::archard_k_over_h_per_pa`]).
    pub archard_k_over_h_per_pa: Option<f64>,
    /// Real process time the run stands for, s (the paper: 5 min).
    pub process_time_s: f64,
    pub calibrate: Option<Calibration>,
    /// When the calibration's Sa holds, s (None: the process time).
    pub calibrate_at_s: Option<f64>,
    /// Times of the prediction's series, s (None: [`crate::predict::series_times_s`]).
    pub series_s: Option<Vec<f64>>,
    /// Interval of the wear maps written over the process, s (None: a tenth of the process
    /// time).
    pub wear_map_every_s: Option<f64>,
    /// A measured after-finish scan on the model's grid (registered to it by
    /// [`crate::after::register_after`]): SIM between it and the predicted worn surface (not a
    /// calibration target).
    pub after: Option<Model>,
    /// How the measured scans (`after`, a measured calibration target) were registered to the
    /// model (finish.json `after_registrations`).
    pub after_registrations: Vec<surfstream_core::record::finish::AfterRegistration>,
    /// The macro run (the machine at the media scale, [`crate::machine`]) first, by default
    /// the paper's machine; its contact statistics give the prediction's impact and sliding
    /// rates and its contact samples the cycles' micro passes. None: the rates from the barrel
    /// kinematics' assumptions and the one-medium segment (or `macro_contacts` when given,
    /// which replaces the run).
    pub machine_run: Option<crate::machine::MachineSetting>,
    /// A macro run's record given (e.g. read from a previous finish.json's `macro`).
    pub macro_contacts: Option<crate::machine::MacroContacts>,
    /// The part's material: the one source of the DEM wall's E and nu
    /// ([`FinishOptions::workpiece`]), Archard's hardness, and the macro run's part (a
    /// `machine_run` with another material is refused).
    pub part_material: crate::setting::PartMaterial,
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
    /// Engine processes at once for a cycle's micro passes (`--jobs`; with contact samples).
    pub jobs: usize,
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
            machine: BarrelMachine::default(),
            impact_angle_deg: DEFAULT_IMPACT_ANGLE_DEG,
            media_velocity_m_s: None,
            pressure_pa: None,
            k_finnie_per_pa: None,
            archard_k_over_h_per_pa: None,
            process_time_s: 300.0,
            calibrate: None,
            calibrate_at_s: None,
            series_s: None,
            wear_map_every_s: None,
            after: None,
            after_registrations: Vec::new(),
            machine_run: Some(crate::machine::MachineSetting::default()),
            macro_contacts: None,
            // The paper's part, aluminium, for the DEM wall and Archard's hardness alike.
            part_material: crate::setting::PartMaterial::default(),
            max_triangles: DEFAULT_MAX_TRIANGLES,
            ranks: 1,
            hostfile: None,
            seed: 1,
            cost_per_triangle_step_s: DEFAULT_COST_PER_TRIANGLE_STEP_S,
            ideal: None,
            wear_model: WearModel::ContactField,
            jobs: 1,
        }
    }
}

impl FinishOptions {
    /// The part as the DEM's wall sees it (E, nu of [`FinishOptions::part_material`]).
    pub fn workpiece(&self) -> Workpiece {
        self.part_material.workpiece()
    }

    /// Archard's K / H, 1/Pa: the given one, or [`ARCHARD_K`] over the part's hardness.
    pub fn archard_k_over_h_per_pa(&self) -> f64 {
        self.archard_k_over_h_per_pa
            .unwrap_or(ARCHARD_K / self.part_material.hardness_pa)
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
/// Archard's dimensionless K (K / H with the part material's hardness H: 1e-13 1/Pa for the
/// default aluminium): a mild abrasive regime, a textbook order, not fitted.
pub const ARCHARD_K: f64 = 1e-4;
/// Planning estimate of LIGGGHTS' cost per triangle and step with one medium over the patch,
/// s (measured here, docs/finish.md); the real time is measured and reported.
pub const DEFAULT_COST_PER_TRIANGLE_STEP_S: f64 = 4e-8;

/// One progress report of [`crate::finish_record`].
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
