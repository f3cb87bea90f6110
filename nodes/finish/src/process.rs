//! The finishing process from start to finish.json, step by step: the set-up (options
//! checked, the patch cut, the targets), an engine probe, the cycles (a DEM segment, then the
//! wear model of the run: the sampled map or the contact field), the contact field's final
//! fit, the ideal model's comparison, the outputs and the summary. [`finish_record`] runs them in
//! that order; each step is a function of the set-up and the state the cycles carry.

use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use anyhow::{anyhow, bail, Context, Result};
use surfstream_core::metrology::{level_plane, sim, AbbottCurve, Grid};
use surfstream_core::record;
use surfstream_core::{Sampling, Shape};

use crate::engine::{EngineCommand, EngineProgress};
use crate::field::{
    self, impact_rate_per_m2_s, ApproachDistribution, ApproachPhysics, FieldGrid, WearTable,
    WearTablePhysics,
};
use crate::grid::{crop, volume_um3, Patch};
use crate::laws::{self, ImpactLaw, SlidingLaw, WearLaw};
use crate::machine::{ContactSample, MacroContacts};
use crate::passes::{
    passes_per_engine, run_micro_passes, MicroPlan, MicroRun, PatchFidelity, PatchModel,
    DEFAULT_CURVATURE_DEG, DEFAULT_ENGINE_PROCESSES,
};
use crate::predict::{self, Prediction, PredictionInput};
use crate::run::{
    outputs, run_segment, surface_params, timestep_s, Calibration, FinishOptions, Model, Progress,
    SegmentPlan, SegmentResult, SurfaceParams, WearModel, CALIBRATION_TOLERANCE_PERCENT,
    DEFAULT_K_FINNIE_PER_PA, DEFAULT_K_FINNIE_SAMPLED_MAP_PER_PA, MAX_FIELD_SCALE,
};
use crate::script::{self, Segment};
use crate::setting::{Action, BarrelKinematics, MediaPhysics, PartMaterialPhysics};
use surfstream_core::record::finish::{
    AbbottSummary, CalibrationSummary, CheckMean, ContactFieldSummary, CycleField, CycleRecord,
    CycleVolumeCheck, EnvelopeShape, FinalFit, FinishFacts, FinishSetting, FinishSummary,
    IdealModelRun, PaperValues, PatchRecord, PatchSummary, ProbeRecord, SimValues, Timings,
    VolumeCheck, WearLawsRecord, WearVolumes,
};

/// Runs the finishing simulation of `model` into `out_dir`; see the crate doc. `say` gets
/// progress lines (stderr for the CLI). A set `stop` ends the engine; completed cycles are
/// kept and finish.json says `partial`. Returns finish.json's record.
pub fn finish_record(
    model: &Model,
    opts: &FinishOptions,
    out_dir: &Path,
    stop: &AtomicBool,
    say: &mut dyn FnMut(&str),
) -> Result<FinishSummary> {
    let t_start = Instant::now();
    let macro_run = macro_contacts(opts, out_dir, stop, say)?;
    let setup = Setup::new(model, opts, out_dir, macro_run.as_ref(), say)?;
    let mut st = State::new(&setup);
    // A macro run made now is engine time of this job (a given record is not).
    if let (Some(m), None) = (&macro_run, &opts.macro_contacts) {
        st.engine_s += m.cost.engine_s;
        st.engine_cpu_s += m.cost.engine_cpu_s;
        st.macro_engine_s = m.cost.engine_s;
    }
    // Planning passes within the budget needs the engine's cost on this machine now (a busy
    // machine makes it several times the quiet estimate): a probe of two passes measures it.
    // (The micro passes are planned by count, not by the budget: no probe.)
    let probe = match (opts.passes, setup.samples.is_empty()) {
        (None, true) => Some(probe(&setup, &mut st, stop, say)?),
        _ => None,
    };
    for c in 1..=opts.cycles {
        if st.partial || !run_cycle(&setup, &mut st, c, stop, say)? {
            break;
        }
    }
    // A stop during the contact field's fit (no engine running) ends the run the same way.
    if stop.load(std::sync::atomic::Ordering::Relaxed) {
        st.partial = true;
    }
    let (final_fit, prediction) = match final_prediction(&setup, &mut st, stop, say)? {
        Some((f, p)) => (f, Some(p)),
        None => (None, None),
    };
    let scale = prediction.as_ref().map(|p| p.scale);
    let ideal_run = ideal_comparison(&setup, &mut st, scale, stop, say)?;
    let crops = write_outputs(&setup, &st)?;
    let total_s = t_start.elapsed().as_secs_f64();
    let mut record = summary(
        &setup,
        st,
        &crops,
        final_fit,
        prediction.as_ref(),
        ideal_run,
        probe,
        total_s,
    )?;
    // Set here: the macro run is made before the set-up, the material is the options'.
    record.macro_run = macro_run;
    record.part_material = Some(opts.part_material.clone());
    record.cycle_path = Some(setup.cycle_path().into());
    record.after_registrations = opts.after_registrations.clone();
    // Written as a JSON value: its keys sorted, as finish.json has always had them.
    let summary = record::to_value(&record)?;
    let path = out_dir.join(outputs::SUMMARY);
    surfstream_core::fsutil::write_atomic(&path, |w| {
        serde_json::to_writer_pretty(w, &summary).map_err(|e| anyhow!("{}: {e}", path.display()))
    })?;
    let (rows, cols) = (setup.patch.crop.rows, setup.patch.crop.cols);
    crate::html::write_report(
        &out_dir.join(outputs::HTML),
        &record,
        &crops.original,
        &crops.worn,
        &crops.finnie,
        crops.ideal_wear.as_deref(),
        rows,
        cols,
    )?;
    Ok(record)
}

/// What a finish is set up with, fixed for the whole process.
struct Setup<'a> {
    model: &'a Model,
    opts: &'a FinishOptions,
    out_dir: &'a Path,
    engine: EngineCommand,
    action: Action,
    /// The micro passes' time step when they draw the macro run's contacts.
    micro_timestep_s: Option<f64>,
    /// `setting.contacts_from`.
    contacts_from: String,
    k_finnie: f64,
    /// The patch (meshed area with its guard band) and the guard's width, um.
    patch: Patch,
    guard_um: f64,
    timestep_s: f64,
    /// Engine segments in all: the cycles and the ideal model's.
    segments: usize,
    /// The evaluated patch before: levelled heights and parameters.
    original_crop: Vec<f64>,
    before: SurfaceParams,
    /// The evaluated patch's envelope under the media's ball (levelled), before.
    envelope: SurfaceParams,
    /// The measured after-finish scan's crop, levelled, and its parameters.
    measured_after: Option<(Vec<f64>, SurfaceParams)>,
    /// The calibration target: Sa after the whole process, um.
    target_sa: Option<f64>,
    /// The contact-field model (crate::field): the approach distribution, the grid, the
    /// impacts the process makes on the evaluated patch.
    dist: ApproachDistribution,
    /// The deepest gap any law reaches (impacts' approach, sliding contacts' depth), um.
    reach_um: f64,
    field_grid: FieldGrid,
    cell_area_um2: f64,
    aim_area_um2: f64,
    impact_rate: f64,
    impacts_process: f64,
    /// The sliding (Archard) law with its rates, and where the rates come from.
    sliding: SlidingLaw,
    sliding_forces_n: Vec<f64>,
    rates_from: String,
    /// When the calibration's Sa holds, and the times of the series, s.
    calibration_time_s: f64,
    series_times_s: Vec<f64>,
    /// The macro run's contact samples (empty: the cycles run the one-medium segment).
    samples: Vec<ContactSample>,
}

/// Micro passes per cycle when `--passes` is not given (they are planned by count): 28
/// impacts and 4 sliding passes ([`crate::passes::pass_kinds`]), about as many engine steps
/// as 16 passes in the machine's mix (7 impacts, 9 sliding) and four times the impacts.
pub const DEFAULT_MICRO_PASSES: usize = 32;

impl<'a> Setup<'a> {
    /// The pointwise bound of every patch the micro passes strike, um: half the measured
    /// patch's Sq ([`PatchFidelity::bound_for`]).
    fn patch_bound_um(&self) -> f64 {
        PatchFidelity::bound_for(self.before.sq)
    }

    /// Checks the options, cuts the patch, says what will run, and reads the targets.
    fn new(
        model: &'a Model,
        opts: &'a FinishOptions,
        out_dir: &'a Path,
        macro_run: Option<&MacroContacts>,
        say: &mut dyn FnMut(&str),
    ) -> Result<Self> {
        let (k_finnie, action) = checked_options(opts)?;
        let engine = EngineCommand::locate(opts.ranks, opts.hostfile.clone())?;
        std::fs::create_dir_all(out_dir)
            .with_context(|| format!("{}: cannot create", out_dir.display()))?;

        // The patch: default a square of DEFAULT_PATCH_SIDE_SAMPLES a side.
        let side_samples = crate::run::DEFAULT_PATCH_SIDE_SAMPLES as f64;
        let (pw, ph) = opts.patch_um.unwrap_or((
            (side_samples * model.pitch_x_um).min(model.cols as f64 * model.pitch_x_um * 0.7),
            (side_samples * model.pitch_y_um).min(model.rows as f64 * model.pitch_y_um * 0.7),
        ));
        let guard_um = opts.guard_um.unwrap_or(0.15 * pw.max(ph));
        let model_at = Sampling::new(
            Shape::new(model.rows, model.cols),
            model.pitch_x_um,
            model.pitch_y_um,
        )
        .with_context(|| model.source.clone())?;
        let patch = Patch::cut(&model.heights_um, model_at, pw, ph, guard_um)
            .with_context(|| model.source.clone())?;
        let dt = timestep_s(&opts.media, &opts.workpiece(), &action);
        // With a macro run the micro passes draw its contacts (and take their own time step
        // from them): the barrel's assumed speed and pressure are then not used, and neither
        // the console nor finish.json may show them as the run's.
        let drawn = macro_run
            .filter(|m| !m.samples.is_empty() && opts.wear_model == WearModel::ContactField);
        let (micro_timestep_s, contacts_from, contacts_line) = match drawn {
            Some(m) => {
                let c = &m.contacts;
                (
                    Some(crate::passes::micro_timestep_s(&opts.media, &opts.workpiece(), &m.samples)),
                    format!(
                        "the macro run's {} contact samples on the part (each micro pass draws one: an impact at its normal and tangential speed, or an enduring contact at its normal force and sliding speed); `action` and `press_force_n` are the barrel kinematics' assumptions and are not used by this run",
                        m.samples.len()
                    ),
                    format!(
                        "contacts drawn from the macro run's {} samples (impact normal speed p50 {:.3} m/s, enduring force p50 {:.4} N)",
                        m.samples.len(),
                        c.impact_normal_speed_m_s.p50,
                        c.enduring_normal_force_n.p50
                    ),
                )
            }
            None => (
                None,
                "the barrel kinematics' assumptions (`action`, `press_force_n`; no macro run's contacts)".into(),
                format!(
                    "media at {:.2} m/s, {:.0} Pa (assumed: no macro run)",
                    action.media_velocity_m_s, action.pressure_pa
                ),
            ),
        };
        say(&format!(
            "finish: patch {} x {} samples ({:.0} x {:.0} um) in a {} x {} area with its guard band, \
             media {} mm, {contacts_line}, dt {:.2e} s, engine {}",
            patch.crop.rows,
            patch.crop.cols,
            patch.crop.cols as f64 * patch.sampling.pitch_x_um(),
            patch.crop.rows as f64 * patch.sampling.pitch_y_um(),
            patch.sampling.rows(),
            patch.sampling.cols(),
            opts.media.diameter_mm,
            micro_timestep_s.unwrap_or(dt),
            engine.argv(script::INPUT, script::LOG).join(" ")
        ));

        let (original_crop, before) =
            surface_params(&patch.cropped(&patch.heights_um), patch.crop_sampling())?;
        // The patch's envelope under the media's ball: the shape that wear confined near the
        // envelope keeps (it lowers the envelope, it does not reach below its long waves).
        let envelope_um: Vec<f64> = field::ball_gap_um(
            &patch.heights_um,
            patch.sampling,
            opts.media.radius_m() * 1e6,
        )
        .iter()
        .zip(&patch.heights_um)
        .map(|(g, h)| h + g)
        .collect();
        let (_, envelope) = surface_params(&patch.cropped(&envelope_um), patch.crop_sampling())?;
        let measured_after = match (&opts.calibrate, &opts.after) {
            (_, Some(m)) | (Some(Calibration::Measured(m)), None) => {
                if (m.rows, m.cols) != (model.rows, model.cols) {
                    bail!(
                        "{}: the measured after-finish scan is {} x {} (rows x cols); the model is {} x {}",
                        m.source, m.rows, m.cols, model.rows, model.cols
                    );
                }
                let w = patch.in_model;
                let area = crop(&m.heights_um, m.cols, w);
                let inner = crop(&area, w.cols, patch.crop);
                covered(m, &inner)?;
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
            Some(Calibration::Measured(m)) => {
                let w = patch.in_model;
                let inner = crop(&crop(&m.heights_um, m.cols, w), w.cols, patch.crop);
                covered(m, &inner)?;
                Some(surface_params(&inner, patch.crop_sampling())?.1.sa)
            }
        };

        let press_force_n = press_force_n(opts, &action);
        // p(gap) from the same contacts the micro passes are drawn from, when there are any:
        // the DEM's wear per contact is then divided by the contacts that reach each gap.
        let dist = match macro_run.filter(|m| !m.samples.is_empty()) {
            Some(m) => {
                ApproachDistribution::from_samples(&opts.media, &opts.workpiece(), &m.samples)
            }
            None => {
                ApproachDistribution::of(&opts.media, &opts.workpiece(), &action, press_force_n)
            }
        };
        let cell_area_um2 = patch.sampling.pitch().cell_area_um2();
        let aim_area_um2 = cell_area_um2 * (patch.crop.rows * patch.crop.cols) as f64;
        let ProcessRates {
            impact_rate,
            sliding_work,
            sliding_forces_n,
            rates_from,
        } = ProcessRates::of(opts, &action, press_force_n, macro_run);
        let impacts_process = impact_rate * aim_area_um2 * 1e-12 * opts.process_time_s;
        let sliding = SlidingLaw::new(
            opts.archard_k_over_h_per_pa(),
            sliding_work,
            &sliding_forces_n,
            &opts.media,
            &opts.workpiece(),
        );
        let reach_um = dist.max_um().max(
            sliding
                .contact_depths_um
                .iter()
                .cloned()
                .fold(0.0, f64::max),
        );
        let field_grid = FieldGrid {
            sampling: patch.sampling,
            radius_um: opts.media.radius_m() * 1e6,
            step_depth_um: field::step_depth_um(reach_um),
        };
        let calibration_time_s = opts.calibrate_at_s.unwrap_or(opts.process_time_s);
        if !(calibration_time_s > 0.0 && calibration_time_s <= opts.process_time_s) {
            bail!(
                "--calibrate-at-s {calibration_time_s}: expected seconds in (0, the process time {}]",
                opts.process_time_s
            );
        }
        let mut series_times_s =
            laws::series_times_s(opts.process_time_s, opts.series_s.as_deref())?;
        series_times_s.extend([calibration_time_s, opts.process_time_s]);
        series_times_s.sort_by(|a, b| a.total_cmp(b));
        series_times_s.dedup_by(|a, b| surfstream_core::record::finish::same_time_s(*a, *b));
        if let Some(e) = opts.wear_map_every_s {
            if !(e.is_finite() && e > 0.0 && e <= opts.process_time_s) {
                bail!(
                    "--wear-map-every-s {e}: expected seconds in (0, the process time {}]",
                    opts.process_time_s
                );
            }
        }
        Ok(Self {
            model,
            opts,
            out_dir,
            engine,
            action,
            k_finnie,
            patch,
            guard_um,
            timestep_s: dt,
            micro_timestep_s,
            contacts_from,
            segments: opts.cycles + usize::from(opts.ideal.is_some()),
            original_crop,
            before,
            envelope,
            measured_after,
            target_sa,
            dist,
            reach_um,
            field_grid,
            cell_area_um2,
            aim_area_um2,
            impact_rate,
            impacts_process,
            sliding,
            sliding_forces_n,
            rates_from,
            calibration_time_s,
            series_times_s,
            samples: macro_run.map(|m| m.samples.clone()).unwrap_or_default(),
        })
    }

    /// finish.json `cycle_path`: which path the cycles ran.
    fn cycle_path(&self) -> &'static str {
        if self.samples.is_empty() {
            "one-medium segment on the block-averaged grid mesh (no contact samples: no macro run or --macro-record)"
        } else {
            "micro passes: the patch meshed by the tolerance mesher, passes drawn from the macro run's contact samples (Finnie impacts, Archard sliding)"
        }
    }

    /// A cycle's micro passes (cycle `c`): the options' media, part, constants and jobs.
    fn micro_plan(&self, c: usize) -> MicroPlan {
        let opts = self.opts;
        let part = opts.part_material.clone();
        let passes = opts.passes.unwrap_or(DEFAULT_MICRO_PASSES);
        let side_um = (self.patch.crop.cols as f64 * self.patch.sampling.pitch_x_um())
            .min(self.patch.crop.rows as f64 * self.patch.sampling.pitch_y_um());
        MicroPlan {
            media: opts.media,
            archard_k: opts.archard_k_over_h_per_pa() * part.hardness_pa,
            part,
            k_finnie_per_pa: self.k_finnie,
            curvature_deg: DEFAULT_CURVATURE_DEG,
            passes,
            seed: opts.seed.wrapping_add(c as u64 - 1),
            jobs: opts.jobs,
            passes_per_engine: passes_per_engine(passes, DEFAULT_ENGINE_PROCESSES),
            contact_every: 5,
            // A tenth of the evaluated patch's smaller side (30 um on a 300 um patch): Archard's
            // volume is linear in the distance, so a short track measures the wear per metre
            // slid as well as a long one; at the macro run's slow sliding (p50 0.017 m/s on the
            // default machine) half the side cost 40 000 steps per pass.
            max_slide_m: 0.1 * side_um * 1e-6,
        }
    }

    /// The prediction's laws with the DEM's wear-per-contact `table`: impacts (Finnie) at
    /// the process's rate on the evaluated patch, sliding (Archard).
    fn laws(&self, table: &WearTable) -> Vec<WearLaw> {
        vec![
            WearLaw::Impacts(ImpactLaw::volume_per_impact(
                self.dist.clone(),
                table.clone(),
                self.impacts_process / self.opts.process_time_s,
                self.aim_area_um2,
            )),
            WearLaw::Sliding(self.sliding.clone()),
        ]
    }

    /// The scale at which the laws with `table` reach `target_sa_um` at the calibration
    /// time, from the original surface.
    fn fit(
        &self,
        table: &WearTable,
        target_sa_um: f64,
        stop: &AtomicBool,
    ) -> Result<(f64, bool, field::Extrapolation)> {
        laws::fit_scale(
            &self.patch.heights_um,
            self.field_grid,
            &self.laws(table),
            self.calibration_time_s,
            MAX_FIELD_SCALE,
            target_sa_um,
            stop,
            |z| self.sa_of_crop(z),
        )
    }

    /// The segments' common inputs; each segment sets its seed, budget and cost.
    fn plan(&self) -> SegmentPlan<'_> {
        let opts = self.opts;
        SegmentPlan {
            engine: &self.engine,
            media: opts.media,
            workpiece: opts.workpiece(),
            action: self.action.clone(),
            k_finnie_per_pa: self.k_finnie,
            archard_k_over_h_per_pa: opts.archard_k_over_h_per_pa(),
            max_triangles: opts.max_triangles,
            timestep_s: self.timestep_s,
            passes: opts.passes,
            engine_budget_s: opts.time_budget_s / self.segments as f64,
            cost_per_triangle_step_s: opts.cost_per_triangle_step_s,
            seed: opts.seed,
            contact_every: 5,
        }
    }

    /// Sa of the evaluated patch of `z`, levelled.
    fn sa_of_crop(&self, z: &[f64]) -> Result<f64> {
        predict::sa_of_crop(&self.patch, z)
    }
}

/// A measured scan's evaluated patch must be measured throughout (a registered scan is
/// missing where it does not reach the model).
fn covered(m: &Model, inner: &[f64]) -> Result<()> {
    let missing = inner.iter().filter(|v| !v.is_finite()).count();
    if missing > 0 {
        bail!(
            "{}: the measured scan, registered to the model, misses {missing} of the evaluated patch's {} samples: expected it to cover the patch (choose --patch-um inside the area both scans hold)",
            m.source,
            inner.len()
        );
    }
    Ok(())
}

/// The rates the prediction's laws run at, and where they come from.
struct ProcessRates {
    /// Contacts (impacts) per m^2 of the part and s.
    impact_rate: f64,
    /// Sliding work per m^2 of the part and s, J/(m^2 s).
    sliding_work: f64,
    /// The sliding contacts' normal forces (equal weights), N.
    sliding_forces_n: Vec<f64>,
    rates_from: String,
}

impl ProcessRates {
    /// From the macro run's contacts on the part when there is one (what softening keeps:
    /// the contact rate, the sliding work, the enduring contacts' forces), else from the
    /// barrel kinematics' assumptions.
    fn of(
        opts: &FinishOptions,
        action: &Action,
        press_force_n: f64,
        macro_run: Option<&MacroContacts>,
    ) -> Self {
        match macro_run {
            Some(m) => {
                let c = &m.contacts;
                let f = c.enduring_normal_force_n;
                let forces: Vec<f64> = [f.p10, f.p50, f.p90]
                    .into_iter()
                    .filter(|x| x.is_finite() && *x > 0.0)
                    .collect();
                // The Finnie table is the DEM's wear per impact pass (a contact that does not
                // endure), so the rate that multiplies it counts those alone: an enduring
                // contact wears through the sliding work, and is not an impact as well.
                let impact_share = if c.count > 0 {
                    c.impacts as f64 / c.count as f64
                } else {
                    1.0
                };
                ProcessRates {
                    impact_rate: c.rate_per_mm2_s * impact_share * 1e6,
                    sliding_work: c.sliding_work_j_per_mm2_s * 1e6,
                    sliding_forces_n: if forces.is_empty() {
                        vec![press_force_n]
                    } else {
                        forces
                    },
                    rates_from: format!(
                        "the macro run (finish.json macro: {} media, {} s simulated on the part's central region): impacts (the {} of {} contacts that do not endure) per area and s, {:.4} of {:.4} contacts per mm^2 and s, for the Finnie law; the sliding work per area and s for the Archard law, placed by the enduring contacts' normal force p10/p50/p90. Under the macro run's softening the sliding work is trusted, the impact rate and the enduring forces are not (macro.softening; docs/finish.md): the one fitted scale absorbs a common factor, not their ratio",
                        m.media_count, m.simulated_s, c.impacts, c.count,
                        c.rate_per_mm2_s * impact_share, c.rate_per_mm2_s
                    ),
                }
            }
            None => ProcessRates {
                impact_rate: impact_rate_per_m2_s(&opts.media, action),
                // Coulomb friction at the limit over the bed's pressure at the media speed.
                sliding_work: opts.media.friction * action.pressure_pa * action.media_velocity_m_s,
                sliding_forces_n: vec![press_force_n],
                rates_from: "the barrel kinematics (assumptions, docs/finish.md; no macro run): impacts once per diameter travelled by the bed's contact layer; sliding work = friction x pressure x media speed, each sliding contact pressed by the press force".into(),
            },
        }
    }
}

/// The macro run's record: run now (`machine_run`, into OUT/macro), given, or none.
fn macro_contacts(
    opts: &FinishOptions,
    out_dir: &Path,
    stop: &AtomicBool,
    say: &mut dyn FnMut(&str),
) -> Result<Option<MacroContacts>> {
    if let Some(m) = &opts.macro_contacts {
        return Ok(Some(m.clone()));
    }
    let Some(setting) = &opts.machine_run else {
        return Ok(None);
    };
    let engine = EngineCommand::locate(opts.ranks, opts.hostfile.clone())?;
    let mut last = Instant::now();
    let m =
        crate::machine::run_machine(setting, &out_dir.join("macro"), &engine, stop, &mut |p| {
            if last.elapsed().as_secs_f64() >= 2.0 {
                last = Instant::now();
                say(&format!("finish: {}", p.line()));
            }
        })?;
    let c = &m.contacts;
    say(&format!(
        "finish: macro run: {} media, {:.2} s recorded: {:.3e} contacts per mm^2 and s ({} of {} impacts), sliding work {:.3e} J/(mm^2 s), enduring normal force p50 {:.4} N, tangential speed p50 {:.3} m/s",
        m.media_count,
        m.simulated_s,
        c.rate_per_mm2_s,
        c.impacts,
        c.count,
        c.sliding_work_j_per_mm2_s,
        c.enduring_normal_force_n.p50,
        c.tangential_speed_m_s.p50
    ));
    Ok(Some(m))
}

/// The Finnie constant and the machine's action, from options that are checked here.
fn checked_options(opts: &FinishOptions) -> Result<(f64, Action)> {
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
    opts.part_material.check()?;
    if let Some(m) = &opts.machine_run {
        if m.part_material != opts.part_material {
            bail!(
                "the macro run's part material ({:?}) is not the finishing run's ({:?}): one part, one material",
                m.part_material.name,
                opts.part_material.name
            );
        }
        // The media strike the part in the macro run and in the micro passes: one media (the
        // micro passes at the real stiffness, the macro run softened), or the contacts the
        // passes draw would be another media's.
        if let Some(d) = m.media.differs_from(&opts.media) {
            bail!("the macro run's media are not the micro passes': {d}: one media, two stiffnesses (set the media once, e.g. --media-friction, for both)");
        }
    }
    if let Some(media) = opts.macro_contacts.as_ref().and_then(|m| m.media.as_ref()) {
        if let Some(d) = media.differs_from(&opts.media) {
            bail!("the given macro record's media are not the micro passes': {d} (record with the same media, or set the passes' media to the record's)");
        }
    }
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
    Ok((k_finnie, action))
}

/// The press load plus the media's inertia under the machine's acceleration, N.
fn press_force_n(opts: &FinishOptions, action: &Action) -> f64 {
    opts.media.load_n(action.pressure_pa) + opts.media.mass_kg() * action.acceleration_m_s2
}

/// What the cycles carry from one to the next.
struct State {
    /// The surface now (patch + guard) and the wear so far.
    h: Vec<f64>,
    finnie_total: Vec<f64>,
    archard_total: Vec<f64>,
    cycles: Vec<CycleRecord>,
    engine_s: f64,
    engine_cpu_s: f64,
    /// The engine's cost per triangle-step, as last measured.
    cost: f64,
    partial: bool,
    first_finnie_map: Option<Vec<f64>>,
    worst_volume_error: f64,
    sim_time_total: f64,
    /// The contact field's wear-per-contact table, pooled over the cycles.
    table: WearTable,
    provisional_scale: Option<f64>,
    /// Each cycle's own wear-per-contact table (the prediction's noise: odd vs even).
    cycle_tables: Vec<WearTable>,
    /// The predicted impact (Finnie) part of `finnie_total` (the contact field).
    impact_total: Option<Vec<f64>>,
    /// The ideal model's predicted wear on the evaluated patch.
    ideal_wear: Option<Vec<f64>>,
    checks: Vec<field::FieldCheck>,
    /// The first micro cycle's patch model (finish.json `patch.model`).
    patch_model: Option<PatchModel>,
    /// The macro run's engine wall time when it ran in this job, s (in `engine_s` too).
    macro_engine_s: f64,
}

impl State {
    fn new(setup: &Setup) -> Self {
        let n = setup.patch.heights_um.len();
        Self {
            h: setup.patch.heights_um.clone(),
            finnie_total: vec![0.0; n],
            archard_total: vec![0.0; n],
            cycles: Vec::new(),
            engine_s: 0.0,
            engine_cpu_s: 0.0,
            cost: setup.opts.cost_per_triangle_step_s,
            partial: false,
            first_finnie_map: None,
            worst_volume_error: 0.0,
            sim_time_total: 0.0,
            table: WearTable::empty(setup.dist.max_um()),
            provisional_scale: None,
            cycle_tables: Vec::new(),
            impact_total: None,
            ideal_wear: None,
            checks: Vec::new(),
            patch_model: None,
            macro_engine_s: 0.0,
        }
    }

    /// Adds a segment's engine time (wall and CPU) and, for [`CostEstimate::Update`] unless it
    /// was stopped, makes its measured cost the estimate later segments are planned with.
    fn count_engine(&mut self, r: &SegmentResult, estimate: CostEstimate) {
        self.engine_s += r.engine_s;
        self.engine_cpu_s += r.engine_cpu_s;
        let steps = r.triangles as f64 * r.segment.total_steps() as f64;
        if estimate == CostEstimate::Update && !r.stopped && steps > 0.0 {
            self.cost = r.engine_s / steps;
        }
    }
}

/// Whether a segment's engine time per triangle-step becomes the cost estimate.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum CostEstimate {
    /// The probe and the cycles: segments of the process, on its surface.
    Update,
    /// The ideal model's segment: counted in the engine time, but it runs on the form-only
    /// surface after the cycles, so its cost stands for nothing planned.
    Keep,
}

/// Two passes on the original surface to measure the engine's cost on this machine now.
fn probe(
    setup: &Setup,
    st: &mut State,
    stop: &AtomicBool,
    say: &mut dyn FnMut(&str),
) -> Result<ProbeRecord> {
    let r = run_segment(
        &SegmentPlan {
            passes: Some(2),
            ..setup.plan()
        },
        &st.h,
        setup.patch.sampling,
        setup.patch.crop,
        &setup.out_dir.join("probe"),
        stop,
        &mut |_, _| {},
    )?;
    st.count_engine(&r, CostEstimate::Update);
    say(&format!(
        "finish: probe: {} triangles x {} steps in {:.1} s ({:.2e} s per triangle-step, start-up included)",
        r.triangles,
        r.segment.total_steps(),
        r.engine_s,
        st.cost
    ));
    st.partial |= r.stopped;
    Ok(ProbeRecord {
        dir: "probe".into(),
        engine_s: r.engine_s,
        engine_cpu_s: r.engine_cpu_s,
        triangles: r.triangles,
        steps: r.segment.total_steps(),
        cost_per_triangle_step_s: st.cost,
    })
}

/// Says when a patch was meshed beyond the run's triangle budget (the micro passes' one
/// fallback for a smooth surface; recorded in `patch.model.budget_triangles`).
fn say_budget(say: &mut dyn FnMut(&str), what: &str, model: &PatchModel, budget: usize) {
    if model.budget_triangles > budget {
        say(&format!(
            "finish: {what}: warning: the patch's tolerance mesh did not fit {budget} triangles; meshed within {} ({} triangles)",
            model.budget_triangles, model.surface_triangles
        ));
    }
    // The DEM then strikes a coarser surface than the bound asks: said, not hidden.
    if model.tolerance_met == Some(false) {
        say(&format!(
            "finish: {what}: warning: the patch's mesh does not meet its bounds within {} triangles ({}; max error {:.3} um on the evaluated patch): raise --max-triangles",
            model.budget_triangles, model.fidelity, model.max_error_um
        ));
    }
}

/// What a cycle's wear model made of its segment.
struct CycleWear {
    scale: f64,
    reached: bool,
    acceleration: f64,
    fitted_k: f64,
    field: Option<CycleField>,
}

/// Cycle `c`: a DEM segment on the surface now, its wear applied by the run's wear model.
/// Returns false when the engine was stopped (the completed cycles stand).
fn run_cycle(
    setup: &Setup,
    st: &mut State,
    c: usize,
    stop: &AtomicBool,
    say: &mut dyn FnMut(&str),
) -> Result<bool> {
    let opts = setup.opts;
    let dir = setup.out_dir.join(format!("cycle_{c:02}"));
    // The budget left, shared by the segments left, at the cost measured so far (the
    // machine may be busier than the planning estimate assumes).
    let left = setup.segments - (c - 1);
    let seg_plan = SegmentPlan {
        seed: opts.seed.wrapping_add(c as u64 - 1),
        engine_budget_s: ((opts.time_budget_s - st.engine_s) / left as f64)
            .max(0.02 * opts.time_budget_s),
        cost_per_triangle_step_s: st.cost,
        ..setup.plan()
    };
    let r = if setup.samples.is_empty() {
        let mut progress = progress_lines(say, "cycle", c, opts.cycles, true);
        let r = run_segment(
            &seg_plan,
            &st.h,
            setup.patch.sampling,
            setup.patch.crop,
            &dir,
            stop,
            &mut progress,
        )?;
        // The progress lines borrow `say`; it speaks again below.
        drop(progress);
        st.count_engine(&r, CostEstimate::Update);
        CycleRun::of_segment(r)?
    } else {
        let mut last = Instant::now();
        let m = run_micro_passes(
            &setup.engine,
            &setup.micro_plan(c),
            &setup.samples,
            &st.h,
            setup.patch.sampling,
            setup.patch.crop,
            opts.max_triangles,
            // Cycle 1 strikes the measured model; later cycles the laws' worn surface, held
            // to the same pointwise bound in um.
            if c == 1 {
                PatchFidelity::Measured {
                    max_error_um: setup.patch_bound_um(),
                }
            } else {
                PatchFidelity::Worn {
                    max_error_um: setup.patch_bound_um(),
                }
            },
            &dir,
            stop,
            &mut |p| {
                if last.elapsed().as_secs_f64() >= 2.0 {
                    last = Instant::now();
                    say(&format!(
                        "finish: cycle {c}/{}: micro passes, engine process {}/{}: step {}/{}",
                        opts.cycles, p.group, p.groups, p.engine.steps_done, p.engine.steps_total
                    ));
                }
            },
        )?;
        st.engine_s += m.engine_s;
        st.engine_cpu_s += m.engine_cpu_s;
        say_budget(say, &format!("cycle {c}"), &m.model, opts.max_triangles);
        CycleRun::of_micro(m)?
    };
    if r.stopped {
        st.partial = true;
        say(&format!(
            "finish: stopped during cycle {c}; keeping {} completed cycle(s)",
            c - 1
        ));
        return Ok(false);
    }
    let sim_s = r.simulated_s;
    st.sim_time_total += sim_s;
    if st.first_finnie_map.is_none() {
        st.first_finnie_map = Some(r.finnie_um.clone());
    }
    let wear = match opts.wear_model {
        WearModel::SampledMap => sampled_map_wear(setup, st, c, &r, sim_s)?,
        WearModel::ContactField => contact_field_wear(setup, st, c, &r, stop, say)?,
    };
    let patch = &setup.patch;
    let (_, after_c) = surface_params(&patch.cropped(&st.h), patch.crop_sampling())?;
    st.worst_volume_error = st.worst_volume_error.max(r.volume_relative_error.abs());
    let CycleWear {
        scale,
        reached,
        acceleration,
        fitted_k,
        field: cycle_field,
    } = wear;
    say(&format!(
        "finish: cycle {c}/{} ({}): {} passes, {:.3} ms simulated in {:.1} s; wear x {:.3e}{}; Sa {:.3} um (volume check {:+.2e})",
        opts.cycles,
        opts.wear_model.name(),
        r.passes,
        sim_s * 1e3,
        r.engine_s,
        scale,
        if setup.target_sa.is_some() { format!(" (fitted k_finnie {fitted_k:.3e} 1/Pa{})", if reached { "" } else { ", target NOT reached" }) } else { String::new() },
        after_c.sa,
        r.volume_relative_error
    ));
    st.cycles.push(CycleRecord {
        cycle: c,
        dir: format!("cycle_{c:02}"),
        command: r.command.clone(),
        triangles: r.triangles,
        mesh_block_stride: r.mesh_stride,
        passes: r.passes,
        steps_per_pass: r.steps_per_pass,
        timestep_s: r.timestep_s,
        simulated_s: sim_s,
        engine_s: r.engine_s,
        engine_cpu_s: r.engine_cpu_s,
        cost_per_triangle_step_s: r.engine_s / r.triangle_steps,
        cpu_per_triangle_step_s: r.engine_cpu_s / r.triangle_steps,
        acceleration_factor: acceleration,
        wear_scale: scale,
        target_reached: reached,
        k_finnie_equivalent_per_pa: fitted_k,
        volume_check: CycleVolumeCheck {
            liggghts_um3: r.liggghts_volume_um3,
            grid_um3: r.grid_volume_um3,
            unmapped_um3: r.unmapped_volume_um3,
            to_nearest_sample_um3: r.to_nearest_sample_um3,
            relative_error: r.volume_relative_error,
        },
        archard_volume_um3: volume_um3(&r.archard_um, patch.sampling.pitch()),
        contacts: r.contacts,
        contact_field: cycle_field,
        after: after_c,
        micro: r.micro,
    });
    if st.patch_model.is_none() {
        st.patch_model = r.model;
    }
    Ok(true)
}

/// What a cycle's engine run gives the wear models and its record, from either path: the
/// one-medium segment or the micro passes.
struct CycleRun {
    finnie_um: Vec<f64>,
    archard_um: Vec<f64>,
    /// Passes in all, and the impacts among them (the contact field's wear per contact).
    passes: usize,
    impacts: usize,
    simulated_s: f64,
    steps_per_pass: usize,
    timestep_s: f64,
    triangle_steps: f64,
    triangles: usize,
    mesh_stride: usize,
    command: String,
    engine_s: f64,
    engine_cpu_s: f64,
    liggghts_volume_um3: f64,
    grid_volume_um3: f64,
    unmapped_volume_um3: f64,
    to_nearest_sample_um3: Option<f64>,
    volume_relative_error: f64,
    contacts: serde_json::Value,
    micro: Option<serde_json::Value>,
    model: Option<PatchModel>,
    stopped: bool,
}

impl CycleRun {
    fn of_segment(r: SegmentResult) -> Result<Self, record::RecordError> {
        let steps = r.segment.total_steps();
        Ok(Self {
            passes: r.segment.passes.len(),
            impacts: r.segment.passes.len(),
            simulated_s: r.segment.simulated_time_s(),
            steps_per_pass: r.segment.steps_per_pass,
            timestep_s: r.segment.timestep_s,
            triangle_steps: r.triangles as f64 * steps as f64,
            triangles: r.triangles,
            mesh_stride: r.mesh_stride,
            command: r.command.clone(),
            engine_s: r.engine_s,
            engine_cpu_s: r.engine_cpu_s,
            liggghts_volume_um3: r.liggghts_volume_um3,
            grid_volume_um3: r.grid_volume_um3,
            unmapped_volume_um3: r.unmapped_volume_um3,
            to_nearest_sample_um3: None,
            volume_relative_error: r.volume_relative_error(),
            contacts: record::to_value(&r.contacts)?,
            micro: None,
            model: None,
            stopped: r.stopped,
            finnie_um: r.finnie_um,
            archard_um: r.archard_um,
        })
    }

    /// The micro passes: `mesh_stride` 1 (the tolerance mesh, not a block average), the
    /// command the first engine process's, the contacts the impacts' summary.
    fn of_micro(m: MicroRun) -> Result<Self, record::RecordError> {
        let rec = m.record();
        let passes = rec.impacts + rec.sliding;
        let steps: usize = m.passes.iter().map(|p| p.steps).sum();
        Ok(Self {
            passes,
            impacts: rec.impacts,
            simulated_s: rec.simulated_s,
            steps_per_pass: steps / passes.max(1),
            timestep_s: rec.timestep_s,
            triangle_steps: rec.triangle_steps,
            triangles: rec.triangles,
            mesh_stride: 1,
            command: m
                .groups
                .first()
                .map(|g| g.command.clone())
                .unwrap_or_default(),
            engine_s: m.engine_s,
            engine_cpu_s: m.engine_cpu_s,
            liggghts_volume_um3: m.finnie_liggghts_volume_um3,
            grid_volume_um3: m.finnie_grid_volume_um3,
            unmapped_volume_um3: m.unmapped_volume_um3,
            to_nearest_sample_um3: Some(m.to_nearest_sample_um3),
            volume_relative_error: m.volume_relative_error(),
            contacts: record::to_value(&m.impact_contacts)?,
            micro: Some(record::to_value(&rec)?),
            model: Some(m.model),
            stopped: m.stopped,
            finnie_um: m.finnie_um,
            archard_um: m.archard_um,
        })
    }
}

/// The sampled map: the segment's Finnie map, scaled to the cycle's share of the process
/// time (or fitted to the target's share), worn into the surface.
fn sampled_map_wear(
    setup: &Setup,
    st: &mut State,
    c: usize,
    r: &CycleRun,
    sim_s: f64,
) -> Result<CycleWear> {
    let (opts, patch, k_finnie) = (setup.opts, &setup.patch, setup.k_finnie);
    // The acceleration factor: each cycle stands for its share of the process time.
    let acceleration = opts.process_time_s / opts.cycles as f64 / sim_s;
    let (scale, reached) = match setup.target_sa {
        Some(t) => {
            let sa0 = setup.before.sa;
            let goal = sa0 * (t / sa0).powf(c as f64 / opts.cycles as f64);
            fit_scale(patch, &st.h, &r.finnie_um, goal)?
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
    let (_, now) = surface_params(&patch.cropped(&st.h), patch.crop_sampling())?;
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
    add_scaled(&mut st.finnie_total, &r.finnie_um, scale);
    add_scaled(&mut st.archard_total, &r.archard_um, scale);
    add_scaled(&mut st.h, &r.finnie_um, -scale);
    Ok(CycleWear {
        scale,
        reached,
        acceleration,
        fitted_k,
        field: None,
    })
}

/// The contact field: the field of the surface this segment ran on, checked against where
/// the DEM wore, its wear per contact pooled into the table, and the next segment's surface
/// extrapolated from the original with the tables so far.
fn contact_field_wear(
    setup: &Setup,
    st: &mut State,
    c: usize,
    r: &CycleRun,
    stop: &AtomicBool,
    say: &mut dyn FnMut(&str),
) -> Result<CycleWear> {
    let (opts, patch, dist) = (setup.opts, &setup.patch, &setup.dist);
    // The Finnie map's contacts: the segment's passes, or the micro passes' impacts.
    let dem_passes = r.impacts;
    let gap = field::ball_gap_um(&st.h, patch.sampling, setup.field_grid.radius_um);
    let gap_crop = patch.cropped(&gap);
    let dem_crop = patch.cropped(&r.finnie_um);
    let check = field::check_field(dist, &gap_crop, &dem_crop);
    let mut own = WearTable::empty(dist.max_um());
    own.add_segment(dist, &gap_crop, &dem_crop, dem_passes, setup.cell_area_um2)?;
    st.table
        .add_segment(dist, &gap_crop, &dem_crop, dem_passes, setup.cell_area_um2)?;
    st.cycle_tables.push(own.clone());
    let impacts_cycle = setup.impacts_process / opts.cycles as f64;
    // The scale that steers the next segments' surfaces: refitted on the tables
    // so far over the whole process (the final fit, once, uses every table).
    if let Some(t) = setup.target_sa {
        st.provisional_scale = Some(setup.fit(&st.table, t, stop)?.0);
    }
    let scale = st.provisional_scale.unwrap_or(1.0);
    // The next segment's surface: the model's estimate at the end of this cycle's
    // share of the process, from the original with the tables so far.
    let mut h_next = patch.heights_um.clone();
    let mut w_next = vec![0.0; h_next.len()];
    let e = laws::advance(
        &mut h_next,
        &mut w_next,
        setup.field_grid,
        &setup.laws(&st.table),
        opts.process_time_s * c as f64 / opts.cycles as f64,
        scale,
    );
    st.h = h_next;
    st.finnie_total = w_next;
    say(&format!(
        "finish: cycle {c}: contact field: AUC {:.3} (gap ranks the DEM's worn cells), {:.1} % of the DEM wear within reach; {} extrapolation steps",
        check.auc_gap_predicts_worn,
        check.dem_volume_within_reach * 100.0,
        e.steps
    ));
    st.checks.push(check.clone());
    Ok(CycleWear {
        scale,
        reached: true,
        acceleration: impacts_cycle / dem_passes as f64,
        fitted_k: setup.k_finnie * scale,
        field: Some(CycleField {
            check,
            table: own,
            impacts: impacts_cycle,
            dem_impacts: dem_passes,
            extrapolation: e,
            scale_is: if setup.target_sa.is_some() {
                "provisional (fitted on the tables so far); the final fit uses every table"
            } else {
                "1: k_finnie as given"
            }
            .into(),
        }),
    })
}

/// The prediction (crate::predict): the laws with every cycle's table, their one scale fitted
/// once to the target at the calibration time (or 1 without a target), the series, the wear
/// maps and the baselines; the surface at the process time becomes the run's worn surface.
/// None with the sampled map, without a completed cycle, or when stopped.
fn final_prediction(
    setup: &Setup,
    st: &mut State,
    stop: &AtomicBool,
    say: &mut dyn FnMut(&str),
) -> Result<Option<(Option<FinalFit>, Prediction)>> {
    let completed = st.cycles.len();
    if setup.opts.wear_model != WearModel::ContactField || completed == 0 || st.partial {
        return Ok(None);
    }
    let halves = (st.cycle_tables.len() >= 2).then(|| {
        let half = |parity: usize| {
            let mut t = WearTable::empty(setup.dist.max_um());
            for ct in st.cycle_tables.iter().skip(parity).step_by(2) {
                t.merge(ct, setup.cell_area_um2);
            }
            setup.laws(&t)
        };
        [half(0), half(1)]
    });
    let input = PredictionInput {
        patch: &setup.patch,
        original_um: &setup.patch.heights_um,
        grid: setup.field_grid,
        laws: setup.laws(&st.table),
        halves,
        calibration_time_s: setup.calibration_time_s,
        process_time_s: setup.opts.process_time_s,
        target_sa_um: setup.target_sa,
        times_s: setup.series_times_s.clone(),
        wear_map_every_s: setup
            .opts
            .wear_map_every_s
            .unwrap_or(setup.opts.process_time_s / 10.0),
        touch_um: setup.field_grid.step_depth_um,
        out_dir: setup.out_dir,
    };
    let p = predict::predict(&input, stop)?;
    if stop.load(std::sync::atomic::Ordering::Relaxed) {
        st.partial = true;
    }
    let k_finnie = setup.k_finnie;
    let final_fit = match (setup.target_sa, p.fit.clone()) {
        (Some(t), Some(e)) => {
            let sa = surfstream_core::record::finish::SeriesPoint::at(
                &p.series,
                setup.calibration_time_s,
            )
            .map_or(f64::NAN, |q| q.sa);
            let err = sa / t - 1.0;
            let reached = p.reached.unwrap_or(false);
            say(&format!(
                "finish: one wear scale fitted on Sa at {} s: {:.4e} (k_finnie {:.3e} 1/Pa, Archard K/H {:.3e} 1/Pa: fitted); Sa {sa:.4} um (fitted) for the target {t:.4} ({:+.2} %){}",
                setup.calibration_time_s,
                p.scale,
                k_finnie * p.scale,
                setup.sliding.k_over_h_per_pa * p.scale,
                err * 100.0,
                if reached { "" } else { ": target NOT reached" }
            ));
            Some(FinalFit {
                scale: p.scale,
                k_finnie_fitted_per_pa: k_finnie * p.scale,
                archard_k_over_h_fitted_per_pa: Some(setup.sliding.k_over_h_per_pa * p.scale),
                calibration_time_s: Some(setup.calibration_time_s),
                sa_after_um: sa,
                relative_error: err,
                reached: reached && err.abs() * 100.0 <= CALIBRATION_TOLERANCE_PERCENT,
                extrapolation: e,
            })
        }
        _ => None,
    };
    for q in &p.series {
        say(&format!(
            "finish: predicted at {:.0} s: Sa {:.3}{} Sq {:.3} Sz {:.3} Spk {:.3} Svk {:.3} um (prediction{})",
            q.time_s,
            q.sa,
            if q.fitted.iter().any(|f| f == "Sa") { " (fitted)" } else { "" },
            q.sq,
            q.sz,
            q.spk,
            q.svk,
            if q.fitted.is_empty() { "" } else { "; Sa fitted" }
        ));
    }
    if p.extrapolation.truncated_at_max_steps {
        say(&format!(
            "finish: warning: the prediction stopped at the extrapolation's limit of {} steps in an interval of the series ({} steps in all): the later times are worn less than the laws say (a wear table with a few deep cells of large wear per contact makes the steps small)",
            field::MAX_STEPS,
            p.extrapolation.steps
        ));
    }
    st.h = p.worn.heights_um.clone();
    st.finnie_total = p.worn.wear_um.clone();
    st.impact_total = Some(p.worn.impact_wear_um.clone());
    // The predicted sliding (Archard) part: the total less the impacts'.
    st.archard_total = p
        .worn
        .wear_um
        .iter()
        .zip(&p.worn.impact_wear_um)
        .map(|(a, b)| a - b)
        .collect();
    Ok(Some((final_fit, p)))
}

/// The engine's progress as `say` lines, at most one every 2 s (and the last step's, with
/// `at_end`): what a segment's run reports, labelled `label` (cycle `cycle` of `cycles`).
fn progress_lines<'a>(
    say: &'a mut dyn FnMut(&str),
    label: &'static str,
    cycle: usize,
    cycles: usize,
    at_end: bool,
) -> impl FnMut(EngineProgress, &Segment) + 'a {
    let mut last_say = Instant::now();
    move |p, seg| {
        if last_say.elapsed().as_secs_f64() >= 2.0 || (at_end && p.steps_done == p.steps_total) {
            last_say = Instant::now();
            say(&Progress {
                label: label.into(),
                cycle,
                cycles,
                engine: p,
                simulated_s: p.steps_done as f64 * seg.timestep_s,
                segment_simulated_s: seg.simulated_time_s(),
            }
            .line());
        }
    }
}

/// The paper's comparison: the ideal model (form only) under the same first segment, its
/// DEM wear map against the model's by SIM; with a prediction, the ideal model's own
/// prediction (its DEM table, the same laws, rates and scale: the same setting) over the
/// process time, its wear map against the high-fidelity prediction's by SIM.
fn ideal_comparison(
    setup: &Setup,
    st: &mut State,
    scale: Option<f64>,
    stop: &AtomicBool,
    say: &mut dyn FnMut(&str),
) -> Result<Option<IdealModelRun>> {
    let (model, opts, patch) = (setup.model, setup.opts, &setup.patch);
    let (Some(ideal), false, Some(hifi_map)) = (&opts.ideal, st.partial, &st.first_finnie_map)
    else {
        return Ok(None);
    };
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
    // Cropped now: the borrow of `st` must end before the segment is counted into it.
    let a = patch.cropped(hifi_map);
    let dir = setup.out_dir.join("ideal");
    let at = patch.sampling.with_shape(Shape::new(w.rows, w.cols));
    let mut ideal_budget = opts.max_triangles;
    // The same engine path as the model's first cycle: its micro passes from the macro
    // run's samples (same plan and seed), else the one-medium segment.
    let r = if setup.samples.is_empty() {
        let mut progress = progress_lines(say, "ideal model", 1, 1, false);
        let r = run_segment(
            &SegmentPlan {
                seed: opts.seed,
                engine_budget_s: (opts.time_budget_s - st.engine_s).max(0.02 * opts.time_budget_s),
                cost_per_triangle_step_s: st.cost,
                ..setup.plan()
            },
            &levelled,
            at,
            patch.crop,
            &dir,
            stop,
            &mut progress,
        )?;
        // The progress lines borrow `say`; it speaks again below.
        drop(progress);
        st.count_engine(&r, CostEstimate::Keep);
        CycleRun::of_segment(r)?
    } else {
        let m = run_micro_passes(
            &setup.engine,
            &setup.micro_plan(1),
            &setup.samples,
            &levelled,
            at,
            patch.crop,
            opts.max_triangles,
            PatchFidelity::Form {
                max_error_um: setup.patch_bound_um(),
            },
            &dir,
            stop,
            &mut |_| {},
        )?;
        ideal_budget = m.model.budget_triangles;
        say_budget(say, "ideal model", &m.model, opts.max_triangles);
        st.engine_s += m.engine_s;
        st.engine_cpu_s += m.engine_cpu_s;
        CycleRun::of_micro(m)?
    };
    if r.stopped {
        st.partial = true;
        return Ok(None);
    }
    let b = patch.cropped(&r.finnie_um);
    let s = sim(&a, &b).unwrap_or(f64::NAN);
    say(&format!(
        "finish: SIM between the first cycle's DEM wear maps of the high-fidelity and the ideal model = {s:.3}"
    ));
    // The ideal model's prediction in the same setting: its own DEM table, the same laws.
    let sim_predictions = match (scale, st.impact_total.is_some()) {
        (Some(scale), true) => {
            let gap = field::ball_gap_um(&levelled, patch.sampling, setup.field_grid.radius_um);
            let mut table = WearTable::empty(setup.dist.max_um());
            table.add_segment(
                &setup.dist,
                &patch.cropped(&gap),
                &b,
                r.impacts,
                setup.cell_area_um2,
            )?;
            let mut h = levelled.clone();
            let mut w = vec![0.0; h.len()];
            laws::advance(
                &mut h,
                &mut w,
                setup.field_grid,
                &setup.laws(&table),
                opts.process_time_s,
                scale,
            );
            let ideal_wear = patch.cropped(&w);
            let hifi_wear = patch.cropped(&st.finnie_total);
            let s2 = sim(&hifi_wear, &ideal_wear).unwrap_or(f64::NAN);
            say(&format!(
                "finish: SIM between the ideal and high-fidelity predictions (wear maps over {} s) = {s2:.3}",
                opts.process_time_s
            ));
            st.ideal_wear = Some(ideal_wear);
            s2.is_finite().then_some(s2)
        }
        _ => None,
    };
    Ok(Some(IdealModelRun {
        mesh_budget_triangles: ideal_budget,
        source: ideal.source.clone(),
        dir: "ideal".into(),
        engine_s: r.engine_s,
        volume_um3: r.grid_volume_um3,
        sim_wear_maps: s.is_finite().then_some(s),
        note: "sim_wear_maps: SIM (eq. 12) between the first cycle's DEM Finnie maps on the high-fidelity model and on the ideal model, same passes; sim_predictions: SIM between the ideal and high-fidelity predictions (their predicted wear maps over the process time, each model's own DEM table, the same laws, rates and fitted scale). Neither is the paper's SIM1/SIM2, which compare with an image of the real finished part: that is sim.worn_vs_measured_after, with --after FILE".into(),
        sim_predictions,
        wear_map: st.ideal_wear.as_ref().map(|_| outputs::WEAR_IDEAL.to_string()),
    }))
}

/// The evaluated patch's maps as written, and the worn surface's parameters.
struct Crops {
    finnie: Vec<f64>,
    archard: Vec<f64>,
    worn: Vec<f64>,
    original: Vec<f64>,
    after: SurfaceParams,
    /// The ideal model's predicted wear (with an ideal model and a prediction).
    ideal_wear: Option<Vec<f64>>,
}

/// Outputs on the crop: the wear maps, the worn and original surfaces (.npy with their
/// sidecars) and worn.x3p.
fn write_outputs(setup: &Setup, st: &State) -> Result<Crops> {
    let (patch, out_dir) = (&setup.patch, setup.out_dir);
    let (rows, cols) = (patch.crop.rows, patch.crop.cols);
    let finnie_crop = patch.cropped(&st.finnie_total);
    let archard_crop = patch.cropped(&st.archard_total);
    let worn_raw = patch.cropped(&st.h);
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
    let impact_crop = st.impact_total.as_ref().map(|w| patch.cropped(w));
    write(
        outputs::WEAR_FINNIE,
        impact_crop.as_deref().unwrap_or(&finnie_crop),
    )?;
    write(outputs::WEAR_ARCHARD, &archard_crop)?;
    write(outputs::WORN, &worn_crop)?;
    if let Some(w) = &st.ideal_wear {
        write(outputs::WEAR_IDEAL, w)?;
    }
    write(outputs::ORIGINAL, &setup.original_crop)?;
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
    Ok(Crops {
        finnie: finnie_crop,
        archard: archard_crop,
        worn: worn_crop,
        original: setup.original_crop.clone(),
        after,
        ideal_wear: st.ideal_wear.clone(),
    })
}

/// finish.json's record of the whole process.
#[allow(clippy::too_many_arguments)]
fn summary(
    setup: &Setup,
    st: State,
    crops: &Crops,
    final_fit: Option<FinalFit>,
    prediction: Option<&Prediction>,
    ideal_run: Option<IdealModelRun>,
    probe: Option<ProbeRecord>,
    total_s: f64,
) -> Result<FinishSummary> {
    let Setup {
        model,
        opts,
        action,
        patch,
        ..
    } = setup;
    let (k_finnie, target_sa, dt, guard) = (
        setup.k_finnie,
        setup.target_sa,
        setup.micro_timestep_s.unwrap_or(setup.timestep_s),
        setup.guard_um,
    );
    let (rows, cols) = (patch.crop.rows, patch.crop.cols);
    let (finnie_crop, archard_crop, worn_crop, after) =
        (&crops.finnie, &crops.archard, &crops.worn, &crops.after);
    let original_crop = &setup.original_crop;
    let (partial, completed, checks) = (st.partial, st.cycles.len(), &st.checks);
    let sim_finnie_archard = sim(finnie_crop, archard_crop)
        .ok()
        .filter(|s| s.is_finite());
    let sim_measured = setup
        .measured_after
        .as_ref()
        .and_then(|(m, _)| sim(worn_crop, m).ok())
        .filter(|s| s.is_finite());
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
    let (engine_s, engine_cpu_s) = (st.engine_s, st.engine_cpu_s);
    let (abbott_before, abbott_after) = (abbott(original_crop)?, abbott(worn_crop)?);
    let facts = FinishFacts {
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
            workpiece: opts.workpiece(),
            machine: opts.machine,
            contacts_from: setup.contacts_from.clone(),
            action_used: setup.micro_timestep_s.is_none(),
            action: action.clone(),
            press_force_n: press_force_n(opts, action),
            k_finnie_per_pa: k_finnie,
            archard_k_over_h_per_pa: opts.archard_k_over_h_per_pa(),
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
                Some(st.cycles.iter().map(|c| c.k_finnie_equivalent_per_pa).filter(|k| k.is_finite()).sum::<f64>() / completed as f64)
            } else { None },
            // The fitted Sa holds at the calibration time (--calibrate-at-s), which may be
            // before the process time: judge the fit there, not at the end.
            sa_after_um: Some(final_fit.as_ref().map_or(after.sa, |f| f.sa_after_um)),
            relative_error: match &final_fit {
                Some(f) => Some(f.relative_error),
                None => target_sa.map(|t| after.sa / t - 1.0),
            },
            reached: match &final_fit {
                Some(f) => Some(!partial && f.reached),
                None => target_sa.map(|t| !partial && (after.sa / t - 1.0).abs() * 100.0 <= CALIBRATION_TOLERANCE_PERCENT),
            },
            fit: final_fit.clone(),
            provisional_scale: st.provisional_scale,
            measured_after: setup.measured_after.as_ref().map(|(_, p)| p.clone()),
        }),
        wear_model: Some(opts.wear_model.name().into()),
        contact_field: (opts.wear_model == WearModel::ContactField).then(|| ContactFieldSummary {
            ball_radius_um: setup.field_grid.radius_um,
            closing: "the surface closed with the paraboloid r^2/2R of the media's radius (separable lower envelope of parabolas, exact, at the model's full resolution, over the patch and its guard band); the sphere differs from it by r^4/8R^3 (0.06 um at 200 um for R = 1.5 mm)".into(),
            approach: Some(setup.dist.clone()),
            approach_model: if setup.dist.sampled().is_some() {
                "p(gap) = the share of the macro run's contact samples (those the micro passes draw) whose approach at the part's real stiffness exceeds the gap: an impact's Hertz approach (15 m v_n^2 / (16 E* sqrt R))^(2/5) at its normal speed, an enduring contact's static Hertz approach under its normal force (or its impact approach, if larger)".into()
            } else {
                "Hertz approach (15 m v_n^2 / (16 E* sqrt R))^(2/5), impact angle uniform on [0, max_impact_angle_deg] at the media speed; the press load's static approach a floor; p(gap) = P(approach > gap) (the barrel kinematics' assumptions: no macro run)".into()
            },
            impact_rate_per_m2_s: setup.impact_rate,
            impact_rate_model: setup.rates_from.clone(),
            patch_area_um2: setup.aim_area_um2,
            impacts_over_process: setup.impacts_process,
            step_depth_um: setup.field_grid.step_depth_um,
            reach_um: Some(setup.reach_um),
            envelope: Some(EnvelopeShape {
                sa_um: setup.envelope.sa,
                sq_um: setup.envelope.sq,
                sz_um: setup.envelope.sz,
                meaning: "the evaluated patch's envelope under the media's ball (the closing, levelled) before finishing: wear confined within reach_um of the envelope lowers it but keeps its long waves, so Sa falls towards this, not to zero".into(),
            }),
            table: st.table.clone(),
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
        before: setup.before.clone(),
        after: after.clone(),
        volume_check: Some(VolumeCheck {
            relative_error: st.worst_volume_error,
            what: "largest |grid volume / LIGGGHTS' sum of wear x area - 1| over the cycles".into(),
        }),
        wear: Some(WearVolumes {
            finnie_volume_um3: volume_um3(finnie_crop, patch.sampling.pitch()),
            archard_volume_um3: volume_um3(archard_crop, patch.sampling.pitch()),
            max_depth_um: finnie_crop.iter().cloned().fold(0.0, f64::max),
            mean_depth_um: finnie_crop.iter().sum::<f64>() / finnie_crop.len() as f64,
        }),
        sim: Some(SimValues {
            finnie_vs_archard: sim_finnie_archard,
            worn_vs_measured_after: sim_measured,
        }),
        ideal_model: ideal_run,
        probe,
        timings: Timings {
            engine_s,
            engine_cpu_s,
            total_s,
            surfstream_overhead_s: total_s - engine_s,
            overhead_share_of_engine: (engine_s > 0.0).then(|| (total_s - engine_s) / engine_s),
            macro_engine_s: st.macro_engine_s,
            simulated_s: st.sim_time_total,
        },
        outputs: [outputs::WEAR, outputs::WEAR_FINNIE, outputs::WEAR_ARCHARD, outputs::WORN, outputs::WORN_X3P, outputs::ORIGINAL, outputs::SUMMARY, outputs::HTML].map(String::from).into(),
        wear_laws: prediction.map(|p| WearLawsRecord {
            impact_rate_per_m2_s: setup.impact_rate,
            sliding_work_j_per_m2_s: setup.sliding.sliding_work_j_per_m2_s,
            sliding_normal_forces_n: setup.sliding_forces_n.clone(),
            sliding_contact_depths_um: setup.sliding.contact_depths_um.clone(),
            archard_k_over_h_per_pa: setup.sliding.k_over_h_per_pa,
            k_finnie_per_pa: k_finnie,
            scale: p.scale,
            scale_is: if target_sa.is_some() {
                format!("fitted once: Sa of the prediction = the target at {} s", setup.calibration_time_s)
            } else {
                "1: the constants as given (no calibration)".into()
            },
            calibration_time_s: setup.calibration_time_s,
            rates_from: setup.rates_from.clone(),
            impact_share_of_volume: p.impact_share,
            extrapolation: Some(p.extrapolation.clone()),
        }),
        series: prediction.map(|p| p.series.clone()).unwrap_or_default(),
        baselines: prediction.map(|p| p.baselines.clone()),
        fitted: fitted_names(target_sa.is_some(), prediction.is_some(), opts.wear_model),
        wear_maps: prediction.map(|p| p.wear_maps.clone()),
        sweep: None,
        after_registrations: Vec::new(),
        part_material: None,
        patch: st.patch_model.map(|model| PatchSummary { model }),
        cycle_path: None,
    };
    Ok(FinishSummary {
        facts,
        abbott_before,
        abbott_after,
        cycles: st.cycles,
        macro_run: None,
    })
}

/// The finish.json paths of every fitted quantity: with a target, the one scale on both
/// laws (and the constants it makes) and Sa at the calibration time; the baselines' own
/// parameter (fitted to the prediction's Sa) whenever there is a prediction.
fn fitted_names(calibrated: bool, predicted: bool, model: WearModel) -> Vec<String> {
    let mut v: Vec<&str> = Vec::new();
    if calibrated && predicted {
        v.extend([
            "calibration.fit.scale",
            "calibration.k_finnie_fitted_per_pa",
            "calibration.fit.archard_k_over_h_fitted_per_pa",
            "wear_laws.scale",
            "series[time_s = calibration time].Sa",
        ]);
    } else if calibrated && model == WearModel::SampledMap {
        v.push("calibration.k_finnie_fitted_per_pa");
    }
    if predicted {
        v.extend([
            "baselines.constant_wear.fitted_value",
            "baselines.plateau.fitted_value",
        ]);
    }
    v.into_iter().map(String::from).collect()
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

fn add_scaled(acc: &mut [f64], x: &[f64], s: f64) {
    for (a, v) in acc.iter_mut().zip(x) {
        *a += s * v;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_part_one_material_for_the_macro_run_and_the_patch() {
        let mut o = FinishOptions::default();
        assert!(checked_options(&o).is_ok());
        assert_eq!(o.workpiece(), o.part_material.workpiece());
        assert_eq!(
            o.archard_k_over_h_per_pa(),
            crate::run::ARCHARD_K / o.part_material.hardness_pa
        );
        // The steel preset reaches the wall and Archard's hardness alike...
        o.part_material = crate::setting::PartMaterial::preset("steel").unwrap();
        assert_eq!(o.workpiece(), o.part_material.workpiece());
        // ...and a macro run left at another material is refused, naming both.
        let e = checked_options(&o).unwrap_err().to_string();
        assert!(e.contains("aluminium") && e.contains("steel"), "{e}");
        if let Some(m) = &mut o.machine_run {
            m.part_material = o.part_material.clone();
        }
        assert!(checked_options(&o).is_ok());
    }

    #[test]
    fn one_media_for_the_macro_run_and_the_micro_passes_at_two_stiffnesses() {
        let mut o = FinishOptions::default();
        // The defaults: the same media, softened in the macro run only.
        let m = o.machine_run.clone().unwrap();
        assert_ne!(m.media.youngs_modulus_pa, o.media.youngs_modulus_pa);
        assert!(checked_options(&o).is_ok());
        // Friction set for one scale only is refused, naming the property and both values.
        o.media.friction = 0.5;
        let e = checked_options(&o).unwrap_err().to_string();
        assert!(e.contains("friction 0.3 in the macro run vs 0.5"), "{e}");
        // The micro passes' media made from the macro run's at the real stiffness agree.
        o.media = m.media.at_modulus(o.media.youngs_modulus_pa);
        assert!(checked_options(&o).is_ok());
        assert_eq!(o.media.friction, 0.3);
        assert_eq!(
            o.media.youngs_modulus_pa,
            crate::setting::Media::default().youngs_modulus_pa
        );
        // A given macro record says its media: another media's record is refused, a record
        // from before the media were kept (none) is taken as it is.
        let mut rec: MacroContacts = serde_json::from_value(serde_json::json!({
            "engine": "liggghts", "machine": "centrifugal-barrel", "media_count": 1,
            "simulated_s": 1.0, "settle_s": 0.1, "timestep_s": 1e-5, "region_area_mm2": 1.0,
            "contacts": crate::machine::ContactStatistics::default(), "samples": [],
            "softening": <crate::machine::Softening as crate::machine::SofteningOf>::of(&m), "media_lost": 0, "partial": false,
            "cost": crate::machine::MacroCost::default(), "seed": 1
        }))
        .unwrap();
        assert!(rec.media.is_none());
        o.machine_run = None;
        o.macro_contacts = Some(rec.clone());
        assert!(checked_options(&o).is_ok());
        let mut other = m.media;
        other.diameter_mm = 5.0;
        rec.media = Some(other);
        o.macro_contacts = Some(rec);
        let e = checked_options(&o).unwrap_err().to_string();
        assert!(
            e.contains("macro record") && e.contains("diameter_mm 5 in the macro run vs 3"),
            "{e}"
        );
    }
}
