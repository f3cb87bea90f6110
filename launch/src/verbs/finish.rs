//! `surfstream finish FILE|OUTDIR -o OUT`: the finishing simulation on LIGGGHTS (the
//! surfstream-finish crate does the work; this is its command line).

use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Result};
use clap::Args;
use surfstream_finish::engine::EngineCommand;
use surfstream_finish::machine::{run_machine, MachineKind, MachineSetting, PartSpec, SpeedFrame};
use surfstream_finish::setting::{PartMaterial, PartMaterialPhysics};
use surfstream_finish::{Calibration, FinishOptions, Model};

#[derive(Args)]
pub struct FinishArgs {
    /// A height map (any format the readers know), or a run's out dir (its panorama is the
    /// model and its datum the ideal model).
    pub input: PathBuf,
    /// Output folder (created): wear.npy, worn.npy/.x3p, finish.json, finish.html, and per
    /// cycle the LIGGGHTS input script, STL and log.
    #[arg(short = 'o', long, value_name = "OUT")]
    pub out: PathBuf,
    /// Write into an existing OUT that no surfstream command made (files of the same name
    /// are replaced). The input's own folder is never accepted as OUT.
    #[arg(long)]
    pub force: bool,
    /// Patch size, um: W or W,H (default: a centred square of 100 x 100 samples).
    #[arg(long, value_name = "W[,H]")]
    pub patch_um: Option<String>,
    /// Guard band around the patch, meshed and cropped, um (default 15 % of the patch).
    #[arg(long)]
    pub guard_um: Option<f64>,
    /// Engine wall-time budget of the whole job, s (sets the number of media passes).
    #[arg(long, default_value_t = 300.0)]
    pub time_budget_s: f64,
    /// DEM segments; the surface is worn and re-meshed between them.
    #[arg(long, default_value_t = 4)]
    pub cycles: usize,
    /// Media passes per segment (default: as many as the budget allows).
    #[arg(long)]
    pub passes: Option<usize>,
    /// Engine processes at once for a cycle's micro passes (with a macro run's contact
    /// samples); the wear does not depend on it.
    #[arg(long, default_value_t = 1)]
    pub jobs: usize,
    /// Diameter of the spherical media, mm (default 3, the paper's ceramic media).
    #[arg(long)]
    pub media_diameter_mm: Option<f64>,
    /// Density of the media, kg/m^3 (default 2500, ceramic).
    #[arg(long)]
    pub media_density_kg_m3: Option<f64>,
    /// Young's modulus of the media in the micro passes, Pa (default 1e11: real ceramic media;
    /// the macro run's softened one is --macro-media-modulus-pa).
    #[arg(long)]
    pub media_modulus_pa: Option<f64>,
    /// Relative media velocity, m/s (default: from the barrel kinematics).
    #[arg(long)]
    pub media_velocity_m_s: Option<f64>,
    /// Media pressure on the part, Pa (default: from the barrel kinematics).
    #[arg(long)]
    pub pressure_pa: Option<f64>,
    /// Angle of the media's velocity to the part's plane, degrees.
    #[arg(long)]
    pub impact_angle_deg: Option<f64>,
    /// Turret revolution, r/min (the paper: 300).
    #[arg(long)]
    pub revolution_rpm: Option<f64>,
    /// Barrel counter-rotation, r/min (the paper: 300).
    #[arg(long)]
    pub rotation_rpm: Option<f64>,
    /// Finnie's constant in the DEM, 1/Pa.
    #[arg(long)]
    pub k_finnie: Option<f64>,
    /// Process time the run stands for, s (the paper: 300).
    #[arg(long)]
    pub process_time_s: Option<f64>,
    /// Fit the wear coefficient: BEFORE,AFTER Sa in um (the paper: 1.272,0.565; the model's
    /// Sa is reduced by the same ratio), or a measured after-finish scan of the same area.
    #[arg(long, value_name = "SA_BEFORE,SA_AFTER | FILE")]
    pub calibrate: Option<String>,
    /// When the calibration's Sa holds, s (default: the process time; e.g. 300 with
    /// --process-time-s 600 to predict 10 min from the paper's 5-min Sa).
    #[arg(long)]
    pub calibrate_at_s: Option<f64>,
    /// Times of the predicted series, s (default: the paper's 1, 2, 3, 5, 10 min up to the
    /// process time and its fifths).
    #[arg(long, value_name = "T1,T2,...")]
    pub series_s: Option<String>,
    /// Interval of the wear maps over the process, s (default: a tenth of the process time).
    #[arg(long)]
    pub wear_map_every_s: Option<f64>,
    /// A measured after-finish scan of the same area (any mounting: it is registered to the
    /// model by phase correlation and resampled on its grid): SIM between it and the
    /// predicted worn surface (the paper's SIM against the real part).
    #[arg(long, value_name = "FILE")]
    pub after: Option<PathBuf>,
    /// Settings to compare with one calibration: NAME=V1,V2,... (revolution-rpm,
    /// rotation-rpm or media-diameter-mm); each runs in full into OUT/sweep_NAME_V.
    #[arg(long, value_name = "NAME=V1,V2,...")]
    pub sweep: Option<String>,
    /// Do not run the machine (the macro run: the centrifugal barrel in LIGGGHTS, run by
    /// default before the cycles): the rates come from the barrel kinematics' assumptions and
    /// the cycles run the one-medium segment instead of the micro passes.
    #[arg(long = "no-macro", conflicts_with = "macro_record")]
    pub no_macro: bool,
    /// A macro run's record instead of running it: a finish.json with `macro`, or the
    /// record itself.
    #[arg(long, value_name = "FILE")]
    pub macro_record: Option<PathBuf>,
    /// Skip the ideal model's run (the paper's comparison) for an out dir with a datum.
    #[arg(long)]
    pub no_ideal: bool,
    /// The ideal model for a height-map input (a file on the same grid).
    #[arg(long)]
    pub ideal: Option<PathBuf>,
    /// The most triangles the patch's mesh may use (default 60 000); the tolerance mesher
    /// uses the fewest that meet the patch's bounds (finish.json patch.model).
    #[arg(long)]
    pub max_triangles: Option<usize>,
    /// MPI ranks (mpirun -np N liggghts).
    #[arg(long, default_value_t = 1)]
    pub ranks: usize,
    /// mpirun hostfile for a cluster.
    #[arg(long)]
    pub hostfile: Option<PathBuf>,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// How the DEM's wear becomes the process's: contact-field (default: the wear per
    /// contact measured by the DEM, extrapolated over every peak the media reach, re-closing
    /// the ball envelope step by step) or sampled-map (the DEM's sampled wear map scaled).
    #[arg(
        long,
        default_value = "contact-field",
        value_name = "contact-field|sampled-map"
    )]
    pub wear_model: String,
    /// Sample spacing, um, for files without a lateral calibration (.npy).
    #[arg(long)]
    pub pitch_um: Option<f64>,
    #[command(flatten)]
    pub machine: Box<MachineArgs>,
}

/// The machine at the media scale (docs/finish.md, "The machine (macro scale)"): these build a
/// `MachineSetting`; --revolution-rpm and --rotation-rpm above set its speeds too (revolution
/// clockwise, rotation counter-clockwise in --rotation-frame, as the paper states them).
#[derive(Args, Default)]
pub struct MachineArgs {
    /// The machine as a TOML file of MachineSetting's fields (the flags below override it).
    #[arg(long, value_name = "FILE.toml")]
    pub machine: Option<PathBuf>,
    /// Machine kind: centrifugal-barrel (vibratory and drag: not implemented).
    #[arg(long, value_name = "KIND")]
    pub machine_kind: Option<String>,
    /// Distance of the drum's axis from the turret's, mm (the paper: 135).
    #[arg(long)]
    pub turret_radius_mm: Option<f64>,
    /// Inner radius of the drum, mm (default 30: an assumption).
    #[arg(long)]
    pub drum_radius_mm: Option<f64>,
    /// Inner length of the drum along its axis, mm (default 30: an assumption).
    #[arg(long)]
    pub drum_height_mm: Option<f64>,
    /// The frame of --rotation-rpm: turret (default: relative to the turret) or lab.
    #[arg(long, value_name = "turret|lab")]
    pub rotation_frame: Option<String>,
    /// Bulk volume of the media over the drum's volume (the paper: 0.7).
    #[arg(long)]
    pub fill: Option<f64>,
    /// Young's modulus of the media in the macro run, Pa (default 3e7: softened to the
    /// paper's time step, 1.5e-5 s).
    #[arg(long)]
    pub macro_media_modulus_pa: Option<f64>,
    /// Media Poisson ratio (0.25).
    #[arg(long)]
    pub media_poisson: Option<f64>,
    /// Media coefficient of restitution (0.6).
    #[arg(long)]
    pub media_restitution: Option<f64>,
    /// Media friction coefficient (0.3).
    #[arg(long)]
    pub media_friction: Option<f64>,
    /// The part's material: aluminium (default, the paper's part) or steel.
    #[arg(long, value_name = "aluminium|steel")]
    pub part_material: Option<String>,
    /// The part's Young's modulus, Pa (overrides the preset's).
    #[arg(long)]
    pub part_modulus_pa: Option<f64>,
    /// The part's Poisson ratio (overrides the preset's).
    #[arg(long)]
    pub part_poisson: Option<f64>,
    /// The part's hardness, Pa (Archard's H; overrides the preset's).
    #[arg(long)]
    pub part_hardness_pa: Option<f64>,
    /// The part in the drum: a plate W,L mm (along the wall, along the axis; default 20,20).
    #[arg(long, value_name = "W,L")]
    pub part_plate_mm: Option<String>,
    /// Simulated settling time of the macro run, s (0.5).
    #[arg(long)]
    pub settle_s: Option<f64>,
    /// Simulated time recorded after settling, s (2).
    #[arg(long)]
    pub record_s: Option<f64>,
    /// Run the machine only: OUT/macro/ (script, log, contact dump) and OUT/macro.json.
    #[arg(long)]
    pub macro_only: bool,
}

/// The machine setting of the command line: `--machine FILE` or the defaults, then each flag.
pub fn machine_setting(a: &FinishArgs) -> Result<MachineSetting> {
    let m = &a.machine;
    let mut s = match &m.machine {
        Some(p) => {
            let text = std::fs::read_to_string(p)
                .map_err(|e| anyhow!("--machine {}: cannot read: {e}", p.display()))?;
            toml::from_str::<MachineSetting>(&text)
                .map_err(|e| anyhow!("--machine {}: {e}", p.display()))?
        }
        None => MachineSetting::default(),
    };
    if let Some(k) = &m.machine_kind {
        s.kind = MachineKind::parse(k).map_err(|e| anyhow!("--machine-kind: {e}"))?;
    }
    if let Some(f) = &m.rotation_frame {
        s.rotation_frame = SpeedFrame::parse(f).map_err(|e| anyhow!("--rotation-frame: {e}"))?;
    }
    if let Some(x) = a.revolution_rpm {
        s.revolution_rpm = -x;
    }
    if let Some(x) = a.rotation_rpm {
        s.rotation_rpm = x;
    }
    let set = |dst: &mut f64, v: Option<f64>| {
        if let Some(v) = v {
            *dst = v;
        }
    };
    set(&mut s.turret_radius_mm, m.turret_radius_mm);
    set(&mut s.drum_radius_mm, m.drum_radius_mm);
    set(&mut s.drum_height_mm, m.drum_height_mm);
    set(&mut s.fill_fraction, m.fill);
    set(&mut s.media.diameter_mm, a.media_diameter_mm);
    set(&mut s.media.density_kg_m3, a.media_density_kg_m3);
    set(&mut s.media.youngs_modulus_pa, m.macro_media_modulus_pa);
    set(&mut s.media.poisson_ratio, m.media_poisson);
    set(&mut s.media.restitution, m.media_restitution);
    set(&mut s.media.friction, m.media_friction);
    s.part_material = part_material(m, s.part_material)?;
    if let Some(p) = &m.part_plate_mm {
        match parse_pair(p, "--part-plate-mm")?.as_slice() {
            [w, l] => {
                s.part = PartSpec::Plate {
                    width_mm: *w,
                    length_mm: *l,
                }
            }
            _ => bail!("--part-plate-mm {p:?}: expected W,L in mm"),
        }
    }
    set(&mut s.settle_s, m.settle_s);
    set(&mut s.record_s, m.record_s);
    s.seed = a.seed;
    s.check()?;
    Ok(s)
}

/// The part's material: `start` (the --machine file's or the default, aluminium), the preset
/// of --part-material, then --part-modulus-pa, --part-poisson, --part-hardness-pa.
pub fn part_material(m: &MachineArgs, start: PartMaterial) -> Result<PartMaterial> {
    let mut p = match &m.part_material {
        Some(name) => PartMaterial::preset(name).map_err(|e| anyhow!("--part-material: {e}"))?,
        None => start,
    };
    let custom =
        m.part_modulus_pa.is_some() || m.part_poisson.is_some() || m.part_hardness_pa.is_some();
    for (dst, v) in [
        (&mut p.youngs_modulus_pa, m.part_modulus_pa),
        (&mut p.poisson_ratio, m.part_poisson),
        (&mut p.hardness_pa, m.part_hardness_pa),
    ] {
        if let Some(v) = v {
            *dst = v;
        }
    }
    if custom {
        p.name = format!("{} (modified)", p.name);
    }
    p.check()?;
    Ok(p)
}

/// OUT/macro.json of `--macro-only`: the machine's setting and its run's contacts.
#[derive(serde::Serialize)]
struct MacroOnlyJson<'a> {
    setting: &'a MachineSetting,
    #[serde(rename = "macro")]
    macro_run: &'a surfstream_finish::machine::MacroContacts,
}

/// `--macro-only`: the machine run alone, into OUT/macro and OUT/macro.json.
fn run_macro_only(a: &FinishArgs, claim: &crate::outdir::Claim) -> Result<()> {
    let setting = machine_setting(a)?;
    let engine = EngineCommand::locate(a.ranks, a.hostfile.clone())?;
    let staged = crate::outdir::stage(&a.out, claim)?;
    surfstream_runtime::stop::install()?;
    let mut last = std::time::Instant::now() - std::time::Duration::from_secs(10);
    let work = staged.staging.clone();
    let made = run_machine(
        &setting,
        &work.join("macro"),
        &engine,
        &surfstream_runtime::ipc::STOP_REQUESTED,
        &mut |p| {
            if last.elapsed().as_secs_f64() >= 5.0 {
                last = std::time::Instant::now();
                eprintln!("{}", p.line());
            }
        },
    )
    .and_then(|m| {
        let json = work.join("macro.json");
        // Through a JSON value: every level's keys sorted, as the file has always had them.
        let record = serde_json::to_value(MacroOnlyJson {
            setting: &setting,
            macro_run: &m,
        })?;
        let text = serde_json::to_string_pretty(&record)?;
        std::fs::write(&json, text + "\n")
            .map_err(|e| anyhow!("{}: cannot write: {e}", json.display()))?;
        Ok(m)
    });
    let m = match made {
        Ok(m) => m,
        Err(e) => return Err(failed(staged, e)),
    };
    let json = staged.commit()?.join("macro.json");
    let c = &m.contacts;
    println!(
        "finish --macro-only: {} media, {:.3} s recorded{}; {} contacts on {:.1} mm^2 ({:.3} /mm^2/s), \
         normal speed p50 {:.4} m/s, tangential p50 {:.4} m/s, normal force p50 {:.4} N, \
         sliding work {:.3e} J/mm^2/s; engine {:.1} s ({:.2e} s per particle-step); {}",
        m.media_count,
        m.simulated_s,
        if m.partial { " (partial: stopped)" } else { "" },
        c.count,
        m.region_area_mm2,
        c.rate_per_mm2_s,
        c.normal_speed_m_s.p50,
        c.tangential_speed_m_s.p50,
        c.normal_force_n.p50,
        c.sliding_work_j_per_mm2_s,
        m.cost.engine_s,
        m.cost.per_particle_step_s,
        json.display()
    );
    if m.partial {
        let sig = surfstream_runtime::stop::signal().unwrap_or(libc::SIGINT);
        eprintln!(
            "surfstream: finish --macro-only {}: {:.3} s of recording kept, macro.json marked partial",
            surfstream_runtime::stop::interrupted(sig),
            m.simulated_s
        );
        std::process::exit(128 + sig);
    }
    Ok(())
}

fn read_model(path: &Path, pitch_um: Option<f64>, pitch_like: Option<(f64, f64)>) -> Result<Model> {
    let s = surfstream_io::formats::read_surface(path)?;
    for w in &s.metadata.warnings {
        eprintln!("{}: warning: {w}", path.display());
    }
    let mut m = Model::from_surface(s.clone(), path.display().to_string());
    match (pitch_um, pitch_like) {
        (Some(p), _) => {
            if !(p.is_finite() && p > 0.0) {
                bail!("--pitch-um {p}: expected a finite number > 0");
            }
            m.pitch_x_um = p;
            m.pitch_y_um = p;
        }
        (None, Some((x, y))) if !s.metadata.pitch_known => {
            m.pitch_x_um = x;
            m.pitch_y_um = y;
        }
        (None, _) if !s.metadata.pitch_known => eprintln!(
            "finish: warning: {} carries no lateral calibration; assuming a pitch of {} um (give --pitch-um)",
            path.display(),
            m.pitch_x_um
        ),
        _ => {}
    }
    Ok(m)
}

/// The model and the ideal model of the input: a file, or a run's out dir.
fn inputs(a: &FinishArgs) -> Result<(Model, Option<Model>)> {
    if a.input.is_dir() {
        let dir = &a.input;
        let pano = ["panorama.x3p", "panorama.npy", "pooled.npy"]
            .iter()
            .map(|f| dir.join(f))
            .find(|p| p.is_file())
            .ok_or_else(|| {
                anyhow!(
                    "{}: no panorama.x3p, panorama.npy or pooled.npy: give a run's out dir or a height-map file (a run with --outputs model keeps none: run it with --outputs full)",
                    dir.display()
                )
            })?;
        let model = read_model(&pano, a.pitch_um, None)?;
        let datum = dir.join("datum.npy");
        let ideal = if a.no_ideal || !datum.is_file() {
            None
        } else {
            let d = read_model(&datum, None, Some((model.pitch_x_um, model.pitch_y_um)))?;
            if (d.rows, d.cols) == (model.rows, model.cols) {
                Some(d)
            } else {
                eprintln!(
                    "finish: warning: {} is {} x {}, the panorama {} x {}: no ideal-model run",
                    datum.display(),
                    d.rows,
                    d.cols,
                    model.rows,
                    model.cols
                );
                None
            }
        };
        return Ok((model, ideal));
    }
    super::one_file(&a.input, "finish")?;
    let model = read_model(&a.input, a.pitch_um, None)?;
    let ideal = match &a.ideal {
        Some(p) if !a.no_ideal => Some(read_model(
            p,
            None,
            Some((model.pitch_x_um, model.pitch_y_um)),
        )?),
        _ => None,
    };
    Ok((model, ideal))
}

/// A run that failed: before any engine ran (nothing but the staging folder's own files), OUT
/// stays as it was; after, OUT becomes the failed run, its FAILED record naming the cause and
/// `logs/` holding every engine's input script and log (`cycle_01_group_01_log.liggghts`).
fn failed(staged: crate::outdir::StagedOut, e: anyhow::Error) -> anyhow::Error {
    let produced = std::fs::read_dir(&staged.staging)
        .map(|d| d.flatten().any(|x| x.path().is_dir()))
        .unwrap_or(false);
    if !produced {
        staged.discard();
        return e;
    }
    let logs = staged.staging.join("logs");
    if std::fs::create_dir_all(&logs).is_ok() {
        keep_engine_files(&staged.staging, &staged.staging, &logs, 0);
    }
    match staged.fail(&e) {
        Ok(dir) => anyhow!(
            "{e:#}\nsurfstream: finish FAILED: {} holds the failure record (FAILED) and the engines' scripts and logs (logs/)",
            dir.display()
        ),
        Err(f) => anyhow!("{e:#} (and the failure record could not be written: {f:#})"),
    }
}

/// Copies the engines' input scripts and logs under `dir` into `logs`, named by their path.
fn keep_engine_files(root: &Path, dir: &Path, logs: &Path, depth: usize) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for e in entries.flatten() {
        let p = e.path();
        let Ok(t) = e.file_type() else { continue };
        if t.is_dir() && depth < 3 && p != logs {
            keep_engine_files(root, &p, logs, depth + 1);
        } else if t.is_file() && depth > 0 {
            let name = e.file_name().to_string_lossy().to_string();
            if name.starts_with("log.") || name.starts_with("in.") {
                if let Ok(rel) = p.strip_prefix(root) {
                    let flat = rel.to_string_lossy().replace('/', "_");
                    let _ = std::fs::copy(&p, logs.join(flat));
                }
            }
        }
    }
}

/// A macro run's record: a finish.json's `macro`, or the record itself.
fn read_macro(path: &Path) -> Result<surfstream_finish::machine::MacroContacts> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| anyhow!("--macro-record {}: cannot read: {e}", path.display()))?;
    let v: serde_json::Value = serde_json::from_str(&text)
        .map_err(|e| anyhow!("--macro-record {}: not JSON: {e}", path.display()))?;
    let record = match v.get("macro") {
        Some(m) if !m.is_null() => m.clone(),
        _ => v,
    };
    surfstream_core::record::from_value(&record, &format!("--macro-record {}", path.display()))
        .map_err(|e| anyhow!(e))
}

/// A measured scan of the finished part registered to the model and resampled on its grid;
/// the registration is said and recorded.
fn registered(model: &Model, scan: &Model, role: &str, o: &mut FinishOptions) -> Result<Model> {
    let (on_model, reg) = surfstream_finish::after::register_after(model, scan, role)?;
    eprintln!(
        "finish: {} registered to the model: offset ({:.2}, {:.2}) px = ({:.2}, {:.2}) um, NCC {:.3}, covers {:.1} % of it",
        scan.source,
        reg.offset_px[0],
        reg.offset_px[1],
        reg.offset_um[0],
        reg.offset_um[1],
        reg.ncc,
        reg.covered_fraction * 100.0
    );
    o.after_registrations.push(reg);
    Ok(on_model)
}

fn parse_pair(s: &str, what: &str) -> Result<Vec<f64>> {
    s.split(',')
        .map(|v| {
            v.trim()
                .parse::<f64>()
                .map_err(|_| anyhow!("{what} {s:?}: expected numbers separated by a comma"))
        })
        .collect()
}

pub fn run(a: FinishArgs) -> Result<()> {
    // OUT is ours only if we made it (the rule of every verb that writes a folder).
    let claim = crate::outdir::Claim {
        inputs: vec![a.input.clone()],
        force: a.force,
    };
    crate::outdir::check_ours(&a.out, &claim)?;
    if a.machine.macro_only {
        return run_macro_only(&a, &claim);
    }
    // One part material (--part-material and its overrides, aluminium by default) for the
    // macro run, the patch's DEM wall and Archard's K/H.
    let part = part_material(&a.machine, PartMaterial::default())?;
    let (model, ideal) = inputs(&a)?;
    let mut o = FinishOptions {
        time_budget_s: a.time_budget_s,
        cycles: a.cycles,
        passes: a.passes,
        jobs: a.jobs,
        guard_um: a.guard_um,
        ranks: a.ranks,
        hostfile: a.hostfile.clone(),
        seed: a.seed,
        media_velocity_m_s: a.media_velocity_m_s,
        pressure_pa: a.pressure_pa,
        ideal,
        part_material: part,
        ..Default::default()
    };
    if let Some(p) = &a.patch_um {
        let v = parse_pair(p, "--patch-um")?;
        o.patch_um = Some(match v.as_slice() {
            [s] => (*s, *s),
            [w, h] => (*w, *h),
            _ => bail!("--patch-um {p:?}: expected W or W,H in um"),
        });
    }
    // One media for the macro run and the micro passes (the flags and --machine FILE set
    // both); only the stiffness differs: the macro run's softened, the passes' real.
    let machine = machine_setting(&a)?;
    o.media = machine
        .media
        .at_modulus(a.media_modulus_pa.unwrap_or(o.media.youngs_modulus_pa));
    if let Some(x) = a.impact_angle_deg {
        o.impact_angle_deg = x;
    }
    if let Some(x) = a.revolution_rpm {
        o.machine.revolution_rpm = x;
    }
    if let Some(x) = a.rotation_rpm {
        o.machine.counter_rotation_rpm = x;
    }
    if let Some(k) = a.k_finnie {
        o.k_finnie_per_pa = Some(k);
    }
    if let Some(t) = a.process_time_s {
        o.process_time_s = t;
    }
    o.calibrate_at_s = a.calibrate_at_s;
    o.wear_map_every_s = a.wear_map_every_s;
    if let Some(t) = &a.series_s {
        o.series_s = Some(parse_pair(t, "--series-s")?);
    }
    if let Some(f) = &a.after {
        let scan = read_model(f, None, Some((model.pitch_x_um, model.pitch_y_um)))?;
        o.after = Some(registered(&model, &scan, "after", &mut o)?);
    }
    // The macro run by default, with the machine flags (--machine FILE, --record-s, ...) as
    // `--macro-only` reads them; a given record replaces it for the base setting (a sweep's
    // other settings run their own machine).
    o.machine_run = (!a.no_macro).then_some(machine);
    if let Some(f) = &a.macro_record {
        o.macro_contacts = Some(read_macro(f)?);
    }
    let sweep = a
        .sweep
        .as_deref()
        .map(surfstream_finish::sweep::SweepSpec::parse)
        .transpose()?;
    o.wear_model = surfstream_finish::run::WearModel::parse(&a.wear_model)
        .map_err(|e| anyhow!("--wear-model: {e}"))?;
    if let Some(t) = a.max_triangles {
        o.max_triangles = t;
    }
    if let Some(c) = &a.calibrate {
        let as_file = PathBuf::from(c);
        o.calibrate = Some(if as_file.is_file() {
            let scan = read_model(&as_file, None, Some((model.pitch_x_um, model.pitch_y_um)))?;
            Calibration::Measured(registered(&model, &scan, "calibration", &mut o)?)
        } else {
            match parse_pair(c, "--calibrate")?.as_slice() {
                [b, af] => Calibration::Sa {
                    before_um: Some(*b),
                    after_um: *af,
                },
                [af] => Calibration::Sa {
                    before_um: None,
                    after_um: *af,
                },
                _ => bail!("--calibrate {c:?}: expected SA_BEFORE,SA_AFTER (um) or a file"),
            }
        });
    }
    // The project's one signal story (surfstream_runtime::stop, as launch/run/stitch):
    // Ctrl-C, SIGTERM or SIGHUP sets the runtime's stop flag, which stops the engine; the
    // completed cycles are kept (finish.json says partial); a second signal forces.
    // Written into a staging folder beside OUT and moved into place when done (complete, or
    // partial after a stop): a failed run leaves OUT as its FAILED record and the engine's
    // logs, never half-written outputs beside an earlier run's (crate::outdir).
    let staged = crate::outdir::stage(&a.out, &claim)?;
    surfstream_runtime::stop::install()?;
    let stop = &surfstream_runtime::ipc::STOP_REQUESTED;
    let say = &mut |l: &str| eprintln!("{l}");
    let work = staged.staging.clone();
    let made = match &sweep {
        Some(spec) => surfstream_finish::sweep::finish_sweep(&model, &o, spec, &work, stop, say),
        None => surfstream_finish::finish_record(&model, &o, &work, stop, say),
    };
    let summary = match made {
        Ok(s) => s,
        Err(e) => return Err(failed(staged, e)),
    };
    let out = staged.commit()?;
    let (b, af) = (&summary.before, &summary.after);
    // "after" is the series' last point (the process time): fitted when the calibration holds there.
    let sa_fitted = summary.series.last().is_some_and(|p| !p.fitted.is_empty());
    for p in &summary.series {
        println!(
            "finish: predicted at {:.0} s: Sa {:.3}{} um, Sq {:.3}, Sz {:.3}, Spk {:.3}, Svk {:.3}, Sk {:.3} ({})",
            p.time_s,
            p.sa,
            if p.fitted.is_empty() { "" } else { " (fitted)" },
            p.sq,
            p.sz,
            p.spk,
            p.svk,
            p.sk,
            if p.fitted.is_empty() { "prediction" } else { "prediction; Sa fitted" }
        );
    }
    if let Some(bl) = &summary.baselines {
        for (name, base) in [
            ("constant wear", &bl.constant_wear),
            ("plateau cut", &bl.plateau),
        ] {
            println!(
                "finish: baseline {name} (no DEM, {}) after the process: Sa {:.3}, Sq {:.3}, Sz {:.3}, Spk {:.3}, Svk {:.3} um; prediction within noise of it in: {}",
                if base.reached { "same Sa at the calibration time" } else { "did NOT reach the prediction's Sa at the calibration time: not comparable" },
                base.after.sa,
                base.after.sq,
                base.after.sz,
                base.after.spk,
                base.after.svk,
                if bl.noise.is_none() { "no noise estimate (one cycle)".to_string() } else if base.within_noise.is_empty() { "none".to_string() } else { base.within_noise.join(", ") }
            );
        }
    }
    if let Some(sw) = &summary.sweep {
        for st in &sw.settings {
            println!(
                "finish: sweep {} = {}{}: Sa {}{} at {:.0} s; Sa {:.3}, Sq {:.3}, Sz {:.3} um after the process ({})",
                sw.parameter,
                st.value,
                if st.calibrated_here {
                    " (calibrated)"
                } else {
                    ""
                },
                st.sa_compared_um
                    .map_or("?".to_string(), |sa| format!("{sa:.3}")),
                match (st.sa_noise_um, st.sa_macro_noise_um) {
                    (Some(n), Some(m)) => format!(" (noise {n:.3} tables, {m:.3} macro counting)"),
                    (Some(n), None) => format!(" (noise {n:.3})"),
                    (None, Some(m)) => format!(" (macro counting noise {m:.3})"),
                    (None, None) => String::new(),
                },
                sw.compared_at_s,
                st.after.sa,
                st.after.sq,
                st.after.sz,
                st.dir
            );
        }
        println!("finish: sweep: {}", sw.verdict);
    }
    if !summary.fitted.is_empty() {
        println!("finish: fitted: {}", summary.fitted.join(", "));
    }
    println!(
        "finish: {} cycle(s){}; Sa {:.3} -> {:.3}{} um, Sq {:.3} -> {:.3}, Sz {:.3} -> {:.3}, Spk {:.3} -> {:.3}, Svk {:.3} -> {:.3}; \
         engine {:.1} s, surfstream {:.1} s; {}",
        summary.cycles_completed,
        if summary.partial { " (partial: stopped)" } else { "" },
        b.sa,
        af.sa,
        if sa_fitted { " (fitted)" } else { "" },
        b.sq,
        af.sq,
        b.sz,
        af.sz,
        b.spk,
        af.spk,
        b.svk,
        af.svk,
        summary.timings.engine_s,
        summary.timings.surfstream_overhead_s,
        out.join("finish.json").display()
    );
    if summary.partial {
        let sig = surfstream_runtime::stop::signal().unwrap_or(libc::SIGINT);
        eprintln!(
            "surfstream: finish {}: {} completed cycle(s) kept, outputs marked partial",
            surfstream_runtime::stop::interrupted(sig),
            summary.cycles_completed
        );
        std::process::exit(128 + sig);
    }
    Ok(())
}
