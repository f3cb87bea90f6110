//! The machine at the media scale (issue 38, macro scale): a centrifugal barrel simulated in
//! LIGGGHTS, and the contacts its media make on the part, as statistics ([`MacroContacts`]) the
//! roughness-scale (micro) run samples from.
//!
//! Frame: the drum's. The turret axis and the drum's axis are parallel to z (up); the drum's
//! axis is the z axis of the simulation, the drum a LIGGGHTS primitive wall (`zcylinder` and
//! two `zplane` caps), the part a plate on its wall (its own mesh, the only mesh wall: LIGGGHTS
//! 3.8 allows one `fix wall/gran` of meshes, and `compute wall/gran/local` reports mesh walls
//! only, so the dump holds the part's contacts alone). The frame turns with the drum's
//! absolute angular velocity w (about z) and its origin revolves at the turret's W at radius
//! R_t, so every medium carries the body forces of that frame (`fix addforce` with atom-style
//! variables), exactly:
//!
//! - the revolution's centrifugal field, m W^2 R_t, pointing away from the turret's axis,
//!   which turns in the drum's frame at -(w - W) (minus the rotation relative to the turret);
//! - the drum's own centrifugal force, m w^2 r (radial from the drum's axis);
//! - Coriolis, -2 m w x v.
//!
//! Gravity (9.81 m/s^2) acts along -z. Left out: the frame's gyroscopic torque on a spinning
//! sphere (-I w x omega); it is zero in the default setting (w = 0: the drum keeps its
//! orientation in the lab). Velocities relative to the part are the media's velocities in
//! this frame (the walls are at rest in it). The drum's frame rather than moving meshes (`fix
//! move/mesh`, which LIGGGHTS can superpose): the simulation box is the drum, not the turret's
//! 300 mm circle; a split along the axis balances any number of ranks; the drum's walls are
//! exact cylinders; and the one mesh wall LIGGGHTS allows is the part. The media start at rest
//! in the drum and settle for [`MachineSetting::settle_s`] before the contacts on the part are
//! recorded.
//!
//! Contacts on the part: `compute wall/gran/local pos vel id force`, dumped every [`MachineSetting::contact_every_steps`]
//! steps. A contact is followed across dumps by the medium's id: its first sample gives the
//! approach (normal) speed, its samples the sliding speed, the normal force and the sliding
//! work (F_n |v_t| dt). Only contacts whose first point lies in the plate's central region (the
//! plate less one media radius on every side) count, so that edge contacts do not bias the
//! rates per area.
//!
//! Softening: the media are soft (the paper's EDEM run: dt 1.5e-5 s at 20 % of the Rayleigh
//! time, which for 3 mm media of 2500 kg/m^3 means E of about 3e7 Pa). Checked against four
//! times the stiffness (tests/machine.rs), softened media keep the sliding speeds and the
//! sliding work and impact energy per area and time; not the count of contacts (stiffer media
//! chatter into more, shorter ones), the impacts' approach speeds, their forces or durations,
//! nor the enduring contacts' loads: [`Softening`] says so in the record.
//!
//! Other machine kinds would enter as other [`MachineKind`]s with their own wall motion and
//! the same contact recording: a vibratory bowl as a torus-shaped mesh under `fix move/mesh
//! vibrot` / `viblin` (the bowl's gyratory vibration; frequency, amplitudes, phase lag), a drag
//! finisher as a static tub with the part (on its holder) driven along a circle by `fix
//! move/mesh rotate` (and its own spin superposed). Neither is implemented.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::io::BufRead;
use std::path::Path;
use std::sync::atomic::AtomicBool;

use anyhow::{anyhow, bail, Context, Result};
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::engine::{run_engine_watched, EngineCommand, EngineRun, EngineWatch};
use crate::setting::{PartMaterial, PartMaterialPhysics};

/// The macro run's records (finish.json `macro`) are core's; their physics is here
/// ([`MediaSpecPhysics`], [`PercentilesOf`]).
pub use surfstream_core::record::finish::{
    ContactSample, ContactStatistics, MacroContacts, MacroCost, MediaSpec, Percentiles, Softening,
};

/// File names inside the macro run's folder.
pub mod files {
    pub const INPUT: &str = "in.machine";
    pub const LOG: &str = "log.machine";
    pub const PART_STL: &str = "part.stl";
    pub const CONTACTS: &str = "part_contacts.txt";
}

/// Which machine.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MachineKind {
    /// Drums on a turret in planetary motion (the paper's BJL-LL05). Vibratory bowls and drag
    /// finishers are described in the module's documentation, not implemented.
    #[default]
    CentrifugalBarrel,
}

impl MachineKind {
    pub fn name(self) -> &'static str {
        match self {
            MachineKind::CentrifugalBarrel => "centrifugal-barrel",
        }
    }

    pub fn parse(s: &str) -> Result<Self> {
        match s {
            "centrifugal-barrel" => Ok(MachineKind::CentrifugalBarrel),
            "vibratory" | "drag" => bail!(
                "machine kind {s:?} is not implemented (docs/finish.md, \"The machine\", says how it would enter); expected centrifugal-barrel"
            ),
            _ => bail!("machine kind {s:?}: expected centrifugal-barrel"),
        }
    }
}

/// The frame the drum's rotation speed is given in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SpeedFrame {
    /// Relative to the ground: the drum's absolute angular velocity.
    Lab,
    /// Relative to the turret (the drum's bearings): absolute = revolution + rotation.
    #[default]
    Turret,
}

impl SpeedFrame {
    pub fn parse(s: &str) -> Result<Self> {
        match s {
            "lab" => Ok(SpeedFrame::Lab),
            "turret" => Ok(SpeedFrame::Turret),
            _ => bail!("rotation frame {s:?}: expected lab or turret"),
        }
    }
}

/// The stiffness of real ceramic media, Pa, recorded beside the softened one.
pub const REAL_MEDIA_YOUNGS_MODULUS_PA: f64 = 1.0e11;

/// Share of the Rayleigh time taken as the time step (the paper's 20 %).
pub const RAYLEIGH_SHARE: f64 = 0.2;

/// The macro run's media as spheres (the record, [`MediaSpec`], is core's).
pub trait MediaSpecPhysics {
    fn radius_m(&self) -> f64;
    fn volume_m3(&self) -> f64;
    fn mass_kg(&self) -> f64;
    /// Rayleigh time, s.
    fn rayleigh_time_s(&self) -> f64;
}

impl MediaSpecPhysics for MediaSpec {
    fn radius_m(&self) -> f64 {
        self.diameter_mm * 0.5e-3
    }

    fn volume_m3(&self) -> f64 {
        4.0 / 3.0 * std::f64::consts::PI * self.radius_m().powi(3)
    }

    fn mass_kg(&self) -> f64 {
        self.density_kg_m3 * self.volume_m3()
    }

    fn rayleigh_time_s(&self) -> f64 {
        let g = self.youngs_modulus_pa / (2.0 * (1.0 + self.poisson_ratio));
        std::f64::consts::PI * self.radius_m() * (self.density_kg_m3 / g).sqrt()
            / (0.1631 * self.poisson_ratio + 0.8766)
    }
}

/// Refuses media that cannot run, naming the field.
fn check_media(media: &MediaSpec) -> Result<()> {
    positive("media.diameter_mm", media.diameter_mm)?;
    positive("media.density_kg_m3", media.density_kg_m3)?;
    positive("media.youngs_modulus_pa", media.youngs_modulus_pa)?;
    within("media.poisson_ratio", media.poisson_ratio, 0.0, 0.4999)?;
    within("media.restitution", media.restitution, 1e-3, 1.0)?;
    within("media.friction", media.friction, 0.0, 10.0)
}

/// The part in the drum.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "shape", rename_all = "kebab-case", deny_unknown_fields)]
pub enum PartSpec {
    /// A flat plate on the drum's wall at mid-height, facing the drum's axis, width along the
    /// wall's circumference and length along the axis, mm.
    Plate { width_mm: f64, length_mm: f64 },
}

impl Default for PartSpec {
    /// 20 x 20 mm (a central region of 17 x 17 mm: 2 176 and 2 133 contacts in the default
    /// 2 s for seeds 1 and 2, rates 2.0 % apart; docs/finish.md): larger than a medium (the 300 um patch is a sample of this surface; a plate
    /// of the patch's size would be smaller than one contact's footprint on a 3 mm medium).
    fn default() -> Self {
        PartSpec::Plate {
            width_mm: 20.0,
            length_mm: 20.0,
        }
    }
}

/// Everything the macro run does.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MachineSetting {
    pub kind: MachineKind,
    /// Distance of the drum's axis from the turret's axis, mm.
    pub turret_radius_mm: f64,
    /// Inner radius of the drum, mm.
    pub drum_radius_mm: f64,
    /// Inner height (length along its axis) of the drum, mm.
    pub drum_height_mm: f64,
    /// Turret revolution, r/min, signed about +z (the axes point up): negative is clockwise
    /// seen from above.
    pub revolution_rpm: f64,
    /// Drum rotation, r/min, signed about +z, in `rotation_frame`.
    pub rotation_rpm: f64,
    pub rotation_frame: SpeedFrame,
    /// Bulk volume of the media over the drum's volume.
    pub fill_fraction: f64,
    /// Solid fraction of the media's bulk (random packing of spheres).
    pub bulk_packing: f64,
    pub media: MediaSpec,
    pub part: PartSpec,
    pub part_material: PartMaterial,
    /// Time step, s; None: [`RAYLEIGH_SHARE`] of the media's Rayleigh time.
    pub timestep_s: Option<f64>,
    /// Simulated time before recording, s.
    pub settle_s: f64,
    /// Simulated time recorded after settling, s.
    pub record_s: f64,
    /// Contacts on the part are dumped every this many steps.
    pub contact_every_steps: usize,
    /// Most joint contact samples kept in the record (a uniform reservoir of all contacts).
    pub samples_kept: usize,
    pub gravity_m_s2: f64,
    pub seed: u64,
}

impl Default for MachineSetting {
    /// The paper's machine: revolution 300 r/min clockwise at 135 mm, drum 300 r/min
    /// counter-clockwise relative to the turret (so the drum keeps its orientation in the
    /// lab: the paper does not say the frame; this is the reading stated in docs/finish.md),
    /// 70 % fill. The drum's size is not in the paper: 30 mm radius, 30 mm long (an
    /// assumption). Settling 0.5 s, recording 2 s.
    fn default() -> Self {
        MachineSetting {
            kind: MachineKind::CentrifugalBarrel,
            turret_radius_mm: 135.0,
            drum_radius_mm: 30.0,
            drum_height_mm: 30.0,
            revolution_rpm: -300.0,
            rotation_rpm: 300.0,
            rotation_frame: SpeedFrame::Turret,
            fill_fraction: 0.7,
            bulk_packing: 0.6,
            media: MediaSpec::default(),
            part: PartSpec::default(),
            part_material: PartMaterial::aluminium(),
            timestep_s: None,
            settle_s: 0.5,
            record_s: 2.0,
            contact_every_steps: 2,
            samples_kept: 4000,
            gravity_m_s2: 9.81,
            seed: 1,
        }
    }
}

fn positive(name: &str, v: f64) -> Result<()> {
    if !(v.is_finite() && v > 0.0) {
        bail!("machine.{name} = {v}: expected a finite number > 0");
    }
    Ok(())
}

fn within(name: &str, v: f64, lo: f64, hi: f64) -> Result<()> {
    if !(v.is_finite() && (lo..=hi).contains(&v)) {
        bail!("machine.{name} = {v}: expected {lo} <= value <= {hi}");
    }
    Ok(())
}

impl MachineSetting {
    /// Refuses a setting that cannot run, naming the field.
    pub fn check(&self) -> Result<()> {
        positive("turret_radius_mm", self.turret_radius_mm)?;
        positive("drum_radius_mm", self.drum_radius_mm)?;
        positive("drum_height_mm", self.drum_height_mm)?;
        if !self.revolution_rpm.is_finite() || !self.rotation_rpm.is_finite() {
            bail!(
                "machine.revolution_rpm = {}, rotation_rpm = {}: expected finite numbers",
                self.revolution_rpm,
                self.rotation_rpm
            );
        }
        if self.turret_radius_mm <= self.drum_radius_mm {
            bail!(
                "machine.turret_radius_mm = {} <= drum_radius_mm = {}: expected the drum's axis outside the drum of the turret's axis",
                self.turret_radius_mm,
                self.drum_radius_mm
            );
        }
        within("fill_fraction", self.fill_fraction, 1e-3, 1.0)?;
        within("bulk_packing", self.bulk_packing, 0.05, 0.64)?;
        check_media(&self.media)?;
        self.part_material.check()?;
        let PartSpec::Plate {
            width_mm,
            length_mm,
        } = self.part;
        positive("part.width_mm", width_mm)?;
        positive("part.length_mm", length_mm)?;
        let d = self.media.diameter_mm;
        if width_mm <= 2.0 * d || length_mm <= 2.0 * d {
            bail!(
                "machine.part = {width_mm} x {length_mm} mm: expected each side > two media diameters ({} mm), so that the plate has a central region",
                2.0 * d
            );
        }
        if width_mm >= self.drum_radius_mm || length_mm >= self.drum_height_mm - 2.0 * d {
            bail!(
                "machine.part = {width_mm} x {length_mm} mm: expected width < drum_radius_mm ({}) and length < drum_height_mm less two diameters ({})",
                self.drum_radius_mm,
                self.drum_height_mm - 2.0 * d
            );
        }
        if 4.0 * d >= self.drum_radius_mm.min(self.drum_height_mm) {
            bail!(
                "machine.media.diameter_mm = {d}: expected a drum (radius {}, height {} mm) larger than four media diameters",
                self.drum_radius_mm,
                self.drum_height_mm
            );
        }
        if let Some(dt) = self.timestep_s {
            positive("timestep_s", dt)?;
        }
        if !(self.settle_s.is_finite() && self.settle_s >= 0.0) {
            bail!(
                "machine.settle_s = {}: expected a finite number >= 0",
                self.settle_s
            );
        }
        positive("record_s", self.record_s)?;
        if self.contact_every_steps == 0 || self.samples_kept == 0 {
            bail!("machine.contact_every_steps and samples_kept: expected at least 1");
        }
        if !(self.gravity_m_s2.is_finite() && self.gravity_m_s2 >= 0.0) {
            bail!(
                "machine.gravity_m_s2 = {}: expected >= 0",
                self.gravity_m_s2
            );
        }
        Ok(())
    }

    pub fn timestep(&self) -> f64 {
        self.timestep_s
            .unwrap_or(RAYLEIGH_SHARE * self.media.rayleigh_time_s())
    }

    /// Media in the drum: fill x drum volume x packing / one medium's volume.
    pub fn media_count(&self) -> usize {
        let v_drum = std::f64::consts::PI
            * (self.drum_radius_mm * 1e-3).powi(2)
            * self.drum_height_mm
            * 1e-3;
        (self.fill_fraction * v_drum * self.bulk_packing / self.media.volume_m3()).round() as usize
    }

    /// Turret revolution, rad/s about +z.
    pub fn revolution_rad_s(&self) -> f64 {
        self.revolution_rpm * std::f64::consts::TAU / 60.0
    }

    /// The drum's angular velocity relative to the turret, rad/s about +z.
    pub fn rotation_in_turret_rad_s(&self) -> f64 {
        let w = self.rotation_rpm * std::f64::consts::TAU / 60.0;
        match self.rotation_frame {
            SpeedFrame::Turret => w,
            SpeedFrame::Lab => w - self.revolution_rad_s(),
        }
    }

    /// The drum's angular velocity in the lab, rad/s about +z.
    pub fn rotation_in_lab_rad_s(&self) -> f64 {
        self.revolution_rad_s() + self.rotation_in_turret_rad_s()
    }

    fn steps(&self) -> (usize, usize) {
        let dt = self.timestep();
        (
            (self.settle_s / dt).round() as usize,
            ((self.record_s / dt).round() as usize).max(1),
        )
    }
}

/// The percentiles of a sample (the record, [`Percentiles`], is core's).
pub trait PercentilesOf {
    /// Linear interpolation between order statistics; NaN for an empty sample.
    fn of(values: &[f64]) -> Self;
}

impl PercentilesOf for Percentiles {
    fn of(values: &[f64]) -> Self {
        let mut v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
        v.sort_by(f64::total_cmp);
        let q = |p: f64| -> f64 {
            if v.is_empty() {
                return f64::NAN;
            }
            let x = p * (v.len() - 1) as f64;
            let (i, f) = (x.floor() as usize, x - x.floor());
            let j = (i + 1).min(v.len() - 1);
            v[i] + f * (v[j] - v[i])
        };
        Percentiles {
            p10: q(0.1),
            p50: q(0.5),
            p90: q(0.9),
        }
    }
}

/// What softened media keep, for a setting (the record, [`Softening`], is core's).
pub(crate) trait SofteningOf {
    fn of(setting: &MachineSetting) -> Self;
}

impl SofteningOf for Softening {
    fn of(setting: &MachineSetting) -> Self {
        Softening {
            media_youngs_modulus_pa: setting.media.youngs_modulus_pa,
            real_youngs_modulus_pa: REAL_MEDIA_YOUNGS_MODULUS_PA,
            timestep_s: setting.timestep(),
            rayleigh_time_s: setting.media.rayleigh_time_s(),
            trusted: [
                "tangential_speed_m_s",
                "sliding_work_j_per_mm2_s",
                "impact_energy_j_per_mm2_s",
            ]
            .map(String::from)
            .to_vec(),
            not_trusted: [
                "rate_per_mm2_s (stiffer media chatter: more, shorter contacts)",
                "impact_normal_speed_m_s",
                "enduring_normal_force_n (which contacts endure depends on E)",
                "normal_force_n of impacts and impact peak forces",
                "duration_s",
            ]
            .map(String::from)
            .to_vec(),
        }
    }
}

/// Progress of the macro run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MachineProgress {
    pub simulated_s: f64,
    pub total_s: f64,
    pub settling: bool,
    pub elapsed_s: f64,
    pub eta_s: Option<f64>,
}

impl MachineProgress {
    /// The progress line: "machine: 0.84 of 2.5 s simulated (recording), 41 s, ETA 81 s".
    pub fn line(&self) -> String {
        let eta = self
            .eta_s
            .map(|e| format!(", ETA {e:.0} s"))
            .unwrap_or_default();
        format!(
            "machine: {:.3} of {:.3} s simulated ({}), {:.0} s{eta}",
            self.simulated_s,
            self.total_s,
            if self.settling {
                "settling"
            } else {
                "recording"
            },
            self.elapsed_s
        )
    }
}

/// Runs the machine in `dir` (created; the script, meshes, log and contact dump stay there)
/// and returns the contacts on the part. A set `stop` ends the engine and returns the
/// statistics of what was recorded, `partial`.
pub fn run_machine(
    setting: &MachineSetting,
    dir: &Path,
    engine: &EngineCommand,
    stop: &AtomicBool,
    progress: &mut dyn FnMut(MachineProgress),
) -> Result<MacroContacts> {
    setting.check()?;
    std::fs::create_dir_all(dir).with_context(|| format!("{}: cannot create", dir.display()))?;
    let geometry = Geometry::of(setting);
    write_file(&dir.join(files::PART_STL), &geometry.part_stl())?;
    let media = place_media(setting, &geometry)?;
    write_file(
        &dir.join(files::INPUT),
        &input_script(setting, &geometry, &media, engine.ranks),
    )?;
    let dt = setting.timestep();
    let (settle_steps, record_steps) = setting.steps();
    let total = settle_steps + record_steps;
    let watch = EngineWatch {
        name: format!("the machine run in {}", dir.display()),
        ..EngineWatch::default()
    };
    let run = run_engine_watched(
        engine,
        dir,
        files::INPUT,
        files::LOG,
        total,
        1,
        stop,
        &mut |p| {
            progress(MachineProgress {
                simulated_s: p.steps_done as f64 * dt,
                total_s: total as f64 * dt,
                settling: p.steps_done < settle_steps,
                elapsed_s: p.elapsed_s,
                eta_s: p.eta_s,
            })
        },
        &watch,
    )?;
    let log = dir.join(files::LOG);
    if !run.stopped && !read_log(&log).done {
        bail!(
            "LIGGGHTS ended without finishing {}: no \"surfstream machine done\" in {} (command: {})",
            watch.name,
            log.display(),
            run.command
        );
    }
    let record = summarise(setting, &geometry, dir, &run, media.len())?;
    // The dump is the bulk of the folder (tens of MB per simulated second); its content is
    // in the record, and rerunning the script writes it again.
    let _ = std::fs::remove_file(dir.join(files::CONTACTS));
    Ok(record)
}

fn write_file(path: &Path, text: &str) -> Result<()> {
    std::fs::write(path, text).with_context(|| format!("{}: cannot write", path.display()))
}

/// Where the walls are, m (the drum's frame).
#[derive(Debug, Clone, Copy)]
struct Geometry {
    /// Drum axis at (centre_x, 0): the z axis.
    centre_x_m: f64,
    radius_m: f64,
    height_m: f64,
    /// The plate's plane x = plate_x_m, facing -x; its extent in y and z.
    plate_x_m: f64,
    plate_y_m: [f64; 2],
    plate_z_m: [f64; 2],
    /// The central region (the plate less one media radius on every side).
    region_y_m: [f64; 2],
    region_z_m: [f64; 2],
}

impl Geometry {
    fn of(s: &MachineSetting) -> Self {
        let PartSpec::Plate {
            width_mm,
            length_mm,
        } = s.part;
        let (w, l) = (width_mm * 1e-3, length_mm * 1e-3);
        let rd = s.drum_radius_m();
        let h = s.drum_height_mm * 1e-3;
        // A flat plate on a curved wall: its middle stands off the wall by the sagitta of its
        // width, plus 0.2 mm so that its edges are inside the drum.
        let inset = w * w / (8.0 * rd) + 2e-4;
        let r = s.media.radius_m();
        let centre_x_m = 0.0;
        Geometry {
            centre_x_m,
            radius_m: rd,
            height_m: h,
            plate_x_m: centre_x_m + rd - inset,
            plate_y_m: [-0.5 * w, 0.5 * w],
            plate_z_m: [0.5 * (h - l), 0.5 * (h + l)],
            region_y_m: [-0.5 * w + r, 0.5 * w - r],
            region_z_m: [0.5 * (h - l) + r, 0.5 * (h + l) - r],
        }
    }

    fn region_area_mm2(&self) -> f64 {
        (self.region_y_m[1] - self.region_y_m[0]) * (self.region_z_m[1] - self.region_z_m[0]) * 1e6
    }

    fn part_stl(&self) -> String {
        let x = self.plate_x_m;
        let [y0, y1] = self.plate_y_m;
        let [z0, z1] = self.plate_z_m;
        let quad = [[x, y0, z0], [x, y1, z0], [x, y1, z1], [x, y0, z1]];
        stl(
            "part",
            &[[quad[0], quad[1], quad[2]], [quad[0], quad[2], quad[3]]],
        )
    }
}

impl MachineSetting {
    fn drum_radius_m(&self) -> f64 {
        self.drum_radius_mm * 1e-3
    }
}

fn stl(name: &str, tris: &[[[f64; 3]; 3]]) -> String {
    let mut s = format!("solid {name}\n");
    for t in tris {
        let u = sub(t[1], t[0]);
        let v = sub(t[2], t[0]);
        let n = cross(u, v);
        let len = dot(n, n).sqrt().max(1e-300);
        let _ = writeln!(
            s,
            "facet normal {:e} {:e} {:e}\nouter loop",
            n[0] / len,
            n[1] / len,
            n[2] / len
        );
        for p in t {
            let _ = writeln!(s, "vertex {:e} {:e} {:e}", p[0], p[1], p[2]);
        }
        let _ = writeln!(s, "endloop\nendfacet");
    }
    let _ = writeln!(s, "endsolid {name}");
    s
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// The media's starting centres: sites of a face-centred cubic lattice (spacing 3 % over
/// touching) inside the drum, clear of the walls and the plate, drawn at random (the seed)
/// and shifted by a random fraction of the clearance.
fn place_media(s: &MachineSetting, g: &Geometry) -> Result<Vec<[f64; 3]>> {
    let n = s.media_count();
    if n == 0 {
        bail!(
            "machine.fill_fraction = {}: no media fit (drum {} x {} mm, media {} mm)",
            s.fill_fraction,
            s.drum_radius_mm,
            s.drum_height_mm,
            s.media.diameter_mm
        );
    }
    let r = s.media.radius_m();
    let d = 2.0 * r * 1.03;
    let a = d * std::f64::consts::SQRT_2;
    let clear = 0.2 * r;
    let reach = g.radius_m - r - clear;
    let x_max = g.plate_x_m - r - clear;
    let basis = [
        [0.0, 0.0, 0.0],
        [0.5, 0.5, 0.0],
        [0.5, 0.0, 0.5],
        [0.0, 0.5, 0.5],
    ];
    let cells_xy = (2.0 * g.radius_m / a).ceil() as i64 + 1;
    let cells_z = (g.height_m / a).ceil() as i64 + 1;
    let mut sites = Vec::new();
    for i in -cells_xy..=cells_xy {
        for j in -cells_xy..=cells_xy {
            for k in 0..=cells_z {
                for b in &basis {
                    let x = g.centre_x_m + (i as f64 + b[0]) * a;
                    let y = (j as f64 + b[1]) * a;
                    let z = r + clear + (k as f64 + b[2]) * a;
                    let rho = (x - g.centre_x_m).hypot(y);
                    if rho <= reach && z <= g.height_m - r - clear && x <= x_max {
                        sites.push([x, y, z]);
                    }
                }
            }
        }
    }
    if sites.len() < n {
        bail!(
            "machine.fill_fraction = {}: {n} media do not fit at the start ({} lattice sites in the drum); lower the fill or the bulk_packing",
            s.fill_fraction,
            sites.len()
        );
    }
    let mut rng = ChaCha8Rng::seed_from_u64(s.seed);
    sites.shuffle(&mut rng);
    sites.truncate(n);
    // Each centre moves by less than half the gap between neighbours (|shift| <= sqrt(3) j).
    let jitter = 0.49 * (d - 2.0 * r) / 3f64.sqrt();
    for p in &mut sites {
        for c in p.iter_mut() {
            *c += rng.gen_range(-jitter..=jitter);
        }
    }
    Ok(sites)
}

/// Columns of the part's contact dump: `compute wall/gran/local pos vel id force`.
const DUMP_COLUMNS: usize = 18;

fn input_script(s: &MachineSetting, g: &Geometry, media: &[[f64; 3]], ranks: usize) -> String {
    let m = &s.media;
    let p = &s.part_material;
    let dt = s.timestep();
    let (settle_steps, record_steps) = s.steps();
    let r = m.radius_m();
    let reach = g.radius_m + 2.0 * r;
    let (e, mu) = (m.restitution, m.friction);
    let thermo = ((settle_steps + record_steps) / 200).clamp(20, 2000);
    let mut t = String::new();
    let _ = writeln!(
        t,
        "# surfstream finish: the machine at the media scale (LIGGGHTS 3.8), in the drum's frame.\n\
         # {} drum {} x {} mm at {} mm, revolution {} r/min, rotation {} r/min ({:?} frame);\n\
         # {} media of {} mm (E {:e} Pa, softened), dt {:e} s; settle {} steps, record {} steps.\n\
         # Rerun: liggghts -in {}   (or mpirun -np N liggghts -in {})\n\
         atom_style granular\n\
         atom_modify map array\n\
         boundary f f f\n\
         newton off\n\
         communicate single vel yes\n\
         units si",
        s.kind.name(),
        s.drum_radius_mm,
        s.drum_height_mm,
        s.turret_radius_mm,
        s.revolution_rpm,
        s.rotation_rpm,
        s.rotation_frame,
        media.len(),
        m.diameter_mm,
        m.youngs_modulus_pa,
        dt,
        settle_steps,
        record_steps,
        files::INPUT,
        files::INPUT,
    );
    if ranks > 1 {
        // Along the axis: the bed lies against the wall at an angle that turns, so a split
        // across the axis would give one rank most of it; every slice along z holds its share.
        let _ = writeln!(t, "processors 1 1 {ranks}");
    }
    let _ = writeln!(
        t,
        "region domain block {:e} {:e} {:e} {:e} {:e} {:e} units box\n\
         create_box 2 domain\n\
         neighbor {:e} bin\n\
         neigh_modify delay 0\n\
         hard_particles yes\n\
         # type 1: media, type 2: drum and part\n\
         fix m1 all property/global youngsModulus peratomtype {:e} {:e}\n\
         fix m2 all property/global poissonsRatio peratomtype {} {}\n\
         fix m3 all property/global coefficientRestitution peratomtypepair 2 {e} {e} {e} {e}\n\
         fix m4 all property/global coefficientFriction peratomtypepair 2 {mu} {mu} {mu} {mu}\n\
         pair_style gran model hertz tangential history\n\
         pair_coeff * *\n\
         timestep {dt:e}\n\
         fix drum_side all wall/gran model hertz tangential history primitive type 2 zcylinder {:e} 0 0\n\
         fix drum_base all wall/gran model hertz tangential history primitive type 2 zplane 0\n\
         fix drum_lid all wall/gran model hertz tangential history primitive type 2 zplane {:e}\n\
         fix part all mesh/surface file {} type 2\n\
         fix wall_part all wall/gran model hertz tangential history mesh n_meshes 1 meshes part",
        -reach,
        reach,
        -reach,
        reach,
        -2.0 * r,
        g.height_m + 2.0 * r,
        0.25 * r,
        m.youngs_modulus_pa,
        p.youngs_modulus_pa,
        m.poisson_ratio,
        p.poisson_ratio,
        g.radius_m,
        g.height_m,
        files::PART_STL,
    );
    if s.gravity_m_s2 > 0.0 {
        let _ = writeln!(t, "fix gravi all gravity {} vector 0 0 -1", s.gravity_m_s2);
    }
    frame_forces(&mut t, s);
    for c in media {
        let _ = writeln!(
            t,
            "create_atoms 1 single {:e} {:e} {:e} units box",
            c[0], c[1], c[2]
        );
    }
    let _ = writeln!(
        t,
        "set group all diameter {:e} density {}\n\
         fix integrate all nve/sphere\n\
         compute wc all wall/gran/local pos vel id force\n\
         thermo_style custom step atoms ke cpu\n\
         thermo {thermo}\n\
         thermo_modify lost ignore norm no flush yes\n\
         print \"surfstream machine settling\"\n\
         run {settle_steps}\n\
         print \"surfstream machine recording\"\n\
         dump dc all local {} {} {}\n\
         run {record_steps}\n\
         print \"surfstream machine done\"",
        2.0 * r,
        m.density_kg_m3,
        s.contact_every_steps,
        files::CONTACTS,
        (1..=DUMP_COLUMNS)
            .map(|i| format!("c_wc[{i}]"))
            .collect::<Vec<_>>()
            .join(" "),
    );
    t
}

/// The drum frame's body forces (the module's documentation): the revolution's centrifugal
/// field turning at minus the rotation relative to the turret, the drum's centrifugal force
/// and Coriolis.
fn frame_forces(t: &mut String, s: &MachineSetting) {
    let big_w = s.revolution_rad_s();
    let w = s.rotation_in_lab_rad_s();
    let w_rel = s.rotation_in_turret_rad_s();
    let field = big_w * big_w * s.turret_radius_mm * 1e-3;
    let dt = s.timestep();
    let _ = writeln!(
        t,
        "# frame: revolution field {field:e} m/s^2 turning at {:e} rad/s; drum {w:e} rad/s\n\
         variable field_angle equal ({:e})*step*{dt:e}\n\
         variable frame_fx atom mass*({field:e}*cos(v_field_angle)+({:e})*x+({:e})*vy)\n\
         variable frame_fy atom mass*({field:e}*sin(v_field_angle)+({:e})*y-({:e})*vx)\n\
         fix frame all addforce v_frame_fx v_frame_fy 0",
        -w_rel,
        -w_rel,
        w * w,
        2.0 * w,
        w * w,
        2.0 * w,
    );
}

/// One row of the part's contact dump.
#[derive(Debug, Clone, Copy)]
struct Row {
    contact: [f64; 3],
    centre: [f64; 3],
    v_wall: [f64; 3],
    v_medium: [f64; 3],
    medium: u64,
    force: [f64; 3],
}

impl Row {
    fn of(v: &[f64]) -> Row {
        let a = |i: usize| [v[i], v[i + 1], v[i + 2]];
        Row {
            contact: a(0),
            centre: a(3),
            v_wall: a(6),
            v_medium: a(9),
            medium: v[14] as u64,
            force: a(15),
        }
    }

    /// (normal speed, positive approaching; tangential speed; normal force, clipped at 0;
    /// tangential force).
    fn kinematics(&self) -> (f64, f64, f64, f64) {
        let n = sub(self.centre, self.contact);
        let len = dot(n, n).sqrt();
        let n = if len > 0.0 {
            [n[0] / len, n[1] / len, n[2] / len]
        } else {
            [-1.0, 0.0, 0.0]
        };
        let v = sub(self.v_medium, self.v_wall);
        let vn = dot(v, n);
        let vt = sub(v, [vn * n[0], vn * n[1], vn * n[2]]);
        let fn_ = dot(self.force, n);
        let ft = sub(self.force, [fn_ * n[0], fn_ * n[1], fn_ * n[2]]);
        (-vn, dot(vt, vt).sqrt(), fn_.max(0.0), dot(ft, ft).sqrt())
    }
}

/// A contact followed across dumps.
#[derive(Debug, Clone, Copy)]
struct Open {
    first_step: u64,
    last_step: u64,
    /// Begun before the recording's first dump: not counted as a new contact.
    inherited: bool,
    in_region: bool,
    normal_speed_m_s: f64,
    sum_vt: f64,
    sum_fn: f64,
    samples: usize,
}

/// A medium back on the part within this many dumps continues its contact.
const MERGE_DUMPS: usize = 3;

/// Everything read from the dump.
#[derive(Debug, Default)]
struct Tally {
    closed: Vec<(Open, usize)>,
    sliding_work_j: f64,
    region_samples: usize,
    coulomb_samples: usize,
    /// Normal speed, tangential speed and normal force of every sample in the region.
    region_vn: Vec<f64>,
    region_vt: Vec<f64>,
    region_fn: Vec<f64>,
    last_step: Option<u64>,
    first_step: Option<u64>,
}

fn read_dump(path: &Path, s: &MachineSetting, g: &Geometry) -> Result<Tally> {
    let mut tally = Tally::default();
    let file = match std::fs::File::open(path) {
        Ok(f) => f,
        // Stopped before the recording began.
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(tally),
        Err(e) => return Err(e).with_context(|| format!("{}: cannot read", path.display())),
    };
    let dt_sample = s.contact_every_steps as f64 * s.timestep();
    // Ordered by the medium's id: contacts that end in the same snapshot close in one order on
    // every run (a HashMap's order is per process: the samples' order, and so the micro
    // passes drawn from them, differed between two runs of the same command).
    let mut open: BTreeMap<u64, Open> = BTreeMap::new();
    let mut lines = std::io::BufReader::new(file).lines();
    let mut line_no = 0usize;
    let mut next = |what: &str| -> Result<Option<String>> {
        line_no += 1;
        match lines.next() {
            None => Ok(None),
            Some(l) => l.map(Some).with_context(|| {
                format!("{}: line {line_no} ({what}): read failed", path.display())
            }),
        }
    };
    let bad = |what: &str, l: &str| anyhow!("{}: expected {what}, found {l:?}", path.display());
    'snapshots: while let Some(l) = next("ITEM: TIMESTEP")? {
        if !l.starts_with("ITEM: TIMESTEP") {
            continue;
        }
        let Some(step_line) = next("timestep")? else {
            break;
        };
        let step: u64 = step_line
            .trim()
            .parse()
            .map_err(|_| bad("a timestep", &step_line))?;
        let mut count = None;
        loop {
            let Some(l) = next("header")? else {
                break 'snapshots;
            };
            if l.starts_with("ITEM: NUMBER OF ENTRIES") {
                let Some(c) = next("entry count")? else {
                    break 'snapshots;
                };
                count = Some(
                    c.trim()
                        .parse::<usize>()
                        .map_err(|_| bad("an entry count", &c))?,
                );
            } else if l.starts_with("ITEM: ENTRIES") {
                break;
            }
        }
        let count = count.ok_or_else(|| bad("ITEM: NUMBER OF ENTRIES", "ITEM: ENTRIES"))?;
        let mut rows = Vec::with_capacity(count);
        for _ in 0..count {
            // A snapshot cut short (the engine stopped while writing) is not counted.
            let Some(l) = next("entry")? else {
                break 'snapshots;
            };
            let v: Vec<f64> = l
                .split_whitespace()
                .map(str::parse)
                .collect::<Result<_, _>>()
                .map_err(|_| bad("numbers", &l))?;
            if v.len() != DUMP_COLUMNS {
                return Err(bad(
                    &format!("{DUMP_COLUMNS} columns (pos vel id force)"),
                    &l,
                ));
            }
            rows.push(Row::of(&v));
        }
        tally.snapshot(step, &rows, &mut open, s, g, dt_sample);
    }
    let ids: Vec<u64> = open.keys().copied().collect();
    for id in ids {
        if let Some(o) = open.remove(&id) {
            tally.closed.push((o, o.samples));
        }
    }
    Ok(tally)
}

impl Tally {
    fn snapshot(
        &mut self,
        step: u64,
        rows: &[Row],
        open: &mut BTreeMap<u64, Open>,
        s: &MachineSetting,
        g: &Geometry,
        dt_sample: f64,
    ) {
        let first = *self.first_step.get_or_insert(step);
        let mu = s.media.friction;
        for row in rows {
            let (vn, vt, fn_, ft) = row.kinematics();
            let in_region = (g.region_y_m[0]..=g.region_y_m[1]).contains(&row.contact[1])
                && (g.region_z_m[0]..=g.region_z_m[1]).contains(&row.contact[2]);
            // Several triangles of the plate may report one medium: one sample per medium.
            let o = open.entry(row.medium).or_insert(Open {
                first_step: step,
                last_step: step,
                inherited: step == first,
                in_region,
                normal_speed_m_s: vn.max(0.0),
                sum_vt: 0.0,
                sum_fn: 0.0,
                samples: 0,
            });
            if o.samples > 0 && o.last_step == step {
                continue;
            }
            o.last_step = step;
            o.samples += 1;
            o.sum_vt += vt;
            o.sum_fn += fn_;
            if in_region {
                self.region_samples += 1;
                self.region_vn.push(vn.abs());
                self.region_vt.push(vt);
                self.region_fn.push(fn_);
                self.sliding_work_j += fn_ * vt * dt_sample;
                if fn_ > 0.0 && ft >= 0.95 * mu * fn_ {
                    self.coulomb_samples += 1;
                }
            }
        }
        // A contact that chatters (apart for a few dumps, then back) stays one contact.
        let gap = (MERGE_DUMPS * s.contact_every_steps) as u64;
        let ended: Vec<u64> = open
            .iter()
            .filter(|(_, o)| o.last_step + gap < step)
            .map(|(id, _)| *id)
            .collect();
        for id in ended {
            if let Some(o) = open.remove(&id) {
                self.closed.push((o, o.samples));
            }
        }
        self.last_step = Some(step);
    }
}

/// Hertz impact time of a medium on the part at normal speed `v_n`, s.
fn hertz_time_s(s: &MachineSetting, v_n: f64) -> f64 {
    let m = &s.media;
    let p = &s.part_material;
    let e = 1.0
        / ((1.0 - m.poisson_ratio.powi(2)) / m.youngs_modulus_pa
            + (1.0 - p.poisson_ratio.powi(2)) / p.youngs_modulus_pa);
    let mass = m.mass_kg();
    2.87 * (mass * mass / (m.radius_m() * e * e * v_n.max(1e-3))).powf(0.2)
}

fn summarise(
    s: &MachineSetting,
    g: &Geometry,
    dir: &Path,
    run: &EngineRun,
    media_count: usize,
) -> Result<MacroContacts> {
    let tally = read_dump(&dir.join(files::CONTACTS), s, g)?;
    let dt = s.timestep();
    let dt_sample = s.contact_every_steps as f64 * dt;
    let (settle_steps, record_steps) = s.steps();
    let recorded_steps = match (tally.first_step, tally.last_step) {
        (Some(a), Some(b)) if run.stopped => b - a + s.contact_every_steps as u64,
        (Some(_), Some(_)) | (None, None) if !run.stopped => record_steps as u64,
        _ => 0,
    };
    let simulated_s = recorded_steps as f64 * dt;
    let area = g.region_area_mm2();
    let mut rng = ChaCha8Rng::seed_from_u64(s.seed ^ 0x5eed);
    let mut samples: Vec<ContactSample> = Vec::new();
    let mut all: Vec<ContactSample> = Vec::new();
    let mut impact_energy_j = 0.0;
    let mass = s.media.mass_kg();
    for (o, n) in tally
        .closed
        .iter()
        .filter(|(o, _)| o.in_region && !o.inherited)
    {
        let duration_s = *n as f64 * dt_sample;
        let c = ContactSample {
            normal_speed_m_s: o.normal_speed_m_s,
            tangential_speed_m_s: o.sum_vt / *n as f64,
            normal_force_n: o.sum_fn / *n as f64,
            duration_s,
            enduring: duration_s > 2.0 * hertz_time_s(s, o.normal_speed_m_s),
        };
        impact_energy_j += 0.5 * mass * o.normal_speed_m_s.powi(2);
        // Reservoir sampling (Algorithm R).
        if samples.len() < s.samples_kept {
            samples.push(c);
        } else {
            let j = rng.gen_range(0..=all.len());
            if j < s.samples_kept {
                samples[j] = c;
            }
        }
        all.push(c);
        let _ = (o.first_step, o.last_step);
    }
    let per = |x: f64| {
        if simulated_s > 0.0 {
            x / (area * simulated_s)
        } else {
            f64::NAN
        }
    };
    let pick = |f: &dyn Fn(&ContactSample) -> f64, only: &dyn Fn(&ContactSample) -> bool| {
        Percentiles::of(&all.iter().filter(|c| only(c)).map(f).collect::<Vec<_>>())
    };
    let any = |_: &ContactSample| true;
    let enduring = all.iter().filter(|c| c.enduring).count();
    let contacts = ContactStatistics {
        count: all.len(),
        impacts: all.len() - enduring,
        enduring,
        rate_per_mm2_s: per(all.len() as f64),
        normal_speed_m_s: Percentiles::of(&tally.region_vn),
        tangential_speed_m_s: Percentiles::of(&tally.region_vt),
        normal_force_n: Percentiles::of(&tally.region_fn),
        impact_normal_speed_m_s: pick(&|c| c.normal_speed_m_s, &|c| !c.enduring),
        enduring_normal_force_n: pick(&|c| c.normal_force_n, &|c| c.enduring),
        duration_s: pick(&|c| c.duration_s, &any),
        sliding_work_j_per_mm2_s: per(tally.sliding_work_j),
        impact_energy_j_per_mm2_s: per(impact_energy_j),
        coulomb_limit_share: if tally.region_samples > 0 {
            tally.coulomb_samples as f64 / tally.region_samples as f64
        } else {
            f64::NAN
        },
        samples: tally.region_samples,
    };
    let log = read_log(&dir.join(files::LOG));
    let steps = if run.stopped {
        settle_steps.min(log.steps) + recorded_steps as usize
    } else {
        settle_steps + record_steps
    };
    let particle_steps = (media_count * steps.max(1)) as f64;
    let loop_s = if log.loop_s > 0.0 {
        log.loop_s
    } else {
        run.wall_s
    };
    Ok(MacroContacts {
        engine: "liggghts".into(),
        machine: s.kind.name().into(),
        media_count,
        simulated_s,
        settle_s: settle_steps as f64 * dt,
        timestep_s: dt,
        region_area_mm2: area,
        contacts,
        samples,
        softening: Softening::of(s),
        media_lost: media_count.saturating_sub(log.atoms.unwrap_or(media_count)),
        partial: run.stopped,
        cost: MacroCost {
            ranks: run_ranks(&run.command),
            engine_s: run.wall_s,
            engine_cpu_s: run.cpu_s,
            loop_s,
            steps,
            per_particle_step_s: loop_s / particle_steps,
            per_simulated_s: loop_s / (steps.max(1) as f64 * dt),
            command: run.command.clone(),
        },
        seed: s.seed,
        media: Some(s.media),
    })
}

fn run_ranks(command: &str) -> usize {
    let w: Vec<&str> = command.split_whitespace().collect();
    w.iter()
        .position(|x| *x == "-np")
        .and_then(|i| w.get(i + 1))
        .and_then(|n| n.parse().ok())
        .unwrap_or(1)
}

/// What the engine's log says: loop times, the steps run, the last atom count.
#[derive(Debug, Default)]
struct LogFacts {
    loop_s: f64,
    steps: usize,
    atoms: Option<usize>,
    /// The script's last line was printed.
    done: bool,
}

fn read_log(path: &Path) -> LogFacts {
    let mut f = LogFacts::default();
    let Ok(text) = std::fs::read_to_string(path) else {
        return f;
    };
    for l in text.lines() {
        f.done |= l.starts_with("surfstream machine done");
        // "Loop time of 12.3 on 2 procs for 3000 steps with 1200 atoms"
        if let Some(rest) = l.strip_prefix("Loop time of ") {
            let w: Vec<&str> = rest.split_whitespace().collect();
            if let (Some(t), Some(st), Some(a)) = (
                w.first().and_then(|x| x.parse::<f64>().ok()),
                w.get(5).and_then(|x| x.parse::<usize>().ok()),
                w.get(8).and_then(|x| x.parse::<usize>().ok()),
            ) {
                f.loop_s += t;
                f.steps += st;
                f.atoms = Some(a);
            }
        }
    }
    f
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_papers_setting_has_its_time_step_and_a_stated_frame() {
        let s = MachineSetting::default();
        s.check().unwrap();
        // 20 % of the Rayleigh time of 3 mm media at E = 3e7 Pa: the paper's 1.5e-5 s.
        assert!((s.timestep() - 1.5e-5).abs() < 0.05e-5, "{}", s.timestep());
        // Turret frame, 300 against -300: the drum keeps its orientation in the lab.
        assert!(s.rotation_in_lab_rad_s().abs() < 1e-12);
        let lab = MachineSetting {
            rotation_frame: SpeedFrame::Lab,
            ..s.clone()
        };
        assert!((lab.rotation_in_turret_rad_s() - 20.0 * std::f64::consts::PI).abs() < 1e-9);
        // 70 % of a 30 x 30 mm drum at packing 0.6, 3 mm media: 2520.
        assert_eq!(s.media_count(), 2520);
        let bad = MachineSetting {
            fill_fraction: 1.5,
            ..s.clone()
        };
        assert!(bad
            .check()
            .unwrap_err()
            .to_string()
            .contains("machine.fill_fraction = 1.5"));
        let toml_text =
            "drum_radius_mm = 20.0\nrotation_frame = \"lab\"\n[media]\ndiameter_mm = 2.0\n";
        let t: MachineSetting = toml::from_str(toml_text).unwrap();
        assert_eq!(t.rotation_frame, SpeedFrame::Lab);
        assert_eq!(t.media.density_kg_m3, 2500.0);
        assert!(toml::from_str::<MachineSetting>("drum_radius = 3.0").is_err());
    }

    #[test]
    fn the_media_fit_the_drum_apart_and_start_with_its_motion() {
        let s = MachineSetting {
            drum_radius_mm: 20.0,
            drum_height_mm: 30.0,
            part: PartSpec::Plate {
                width_mm: 10.0,
                length_mm: 10.0,
            },
            ..MachineSetting::default()
        };
        s.check().unwrap();
        let g = Geometry::of(&s);
        let media = place_media(&s, &g).unwrap();
        assert_eq!(media.len(), s.media_count());
        let r = s.media.radius_m();
        for (i, a) in media.iter().enumerate() {
            let rho = (a[0] - g.centre_x_m).hypot(a[1]);
            assert!(rho + r < g.radius_m && a[2] > r && a[2] + r < g.height_m);
            assert!(a[0] + r < g.plate_x_m);
            for b in &media[i + 1..] {
                let d = dot(sub(*a, *b), sub(*a, *b)).sqrt();
                assert!(d > 2.0 * r, "overlap {d}");
            }
        }
        let text = input_script(&s, &g, &media, 2);
        assert!(text.contains("processors 1 1 2"));
        // Turret frame, 300 against -300 r/min: the drum does not turn in the lab, the
        // field (W^2 R_t = 133.2 m/s^2) turns with the turret in it, clockwise at 10 pi rad/s,
        // and there is no Coriolis force.
        assert!(
            text.contains("variable field_angle equal (-3.14159"),
            "{text}"
        );
        assert!(text.contains("mass*(1.332396"), "{text}");
        assert!(text.contains("+(0e0)*x+(0e0)*vy"), "{text}");
        let other = place_media(
            &MachineSetting {
                seed: 2,
                ..s.clone()
            },
            &g,
        )
        .unwrap();
        assert_ne!(other, media);
    }

    #[test]
    fn contacts_that_end_together_close_in_the_mediums_order_on_every_read() {
        // The samples' order picks the micro passes (a seeded draw by index): two reads of
        // one dump must give one order.
        let s = MachineSetting::default();
        let g = Geometry::of(&s);
        let y = 0.5 * (g.region_y_m[0] + g.region_y_m[1]);
        let z = 0.5 * (g.region_z_m[0] + g.region_z_m[1]);
        let (x, cx) = (g.plate_x_m, g.plate_x_m - s.media.radius_m());
        let ids = [9u64, 3, 7, 1, 5, 8, 2, 6, 4];
        let mut dump = String::new();
        // Every medium on the plate in one snapshot, none in the next, long after: all end
        // together.
        for (step, on) in [(100u64, true), (1_000_000, false)] {
            let rows: Vec<String> = ids
                .iter()
                .filter(|_| on)
                .map(|&id| {
                    let f = id as f64 * 0.01;
                    format!(
                        "{x} {y} {z} {cx} {y} {z} 0 0 0 0.1 0.2 0 0 0 {id} {} 0 0",
                        -f
                    )
                })
                .collect();
            let _ = write!(
                dump,
                "ITEM: TIMESTEP\n{step}\nITEM: NUMBER OF ENTRIES\n{}\nITEM: ENTRIES\n",
                rows.len()
            );
            for r in rows {
                dump.push_str(&r);
                dump.push('\n');
            }
        }
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("contacts.dump");
        std::fs::write(&path, dump).unwrap();
        let forces = |t: Tally| -> Vec<f64> { t.closed.iter().map(|(o, _)| o.sum_fn).collect() };
        let mut sorted = ids;
        sorted.sort_unstable();
        let expected: Vec<f64> = sorted.iter().map(|&id| id as f64 * 0.01).collect();
        for _ in 0..3 {
            let got = forces(read_dump(&path, &s, &g).unwrap());
            assert_eq!(got.len(), ids.len());
            for (a, b) in got.iter().zip(&expected) {
                assert!((a - b).abs() < 1e-12, "{got:?} vs {expected:?}");
            }
        }
    }

    #[test]
    fn percentiles_interpolate_order_statistics() {
        let p = Percentiles::of(&[5.0, 1.0, 3.0, 2.0, 4.0, f64::NAN]);
        assert_eq!((p.p10, p.p50, p.p90), (1.4, 3.0, 4.6));
        assert!(Percentiles::of(&[]).p50.is_nan());
    }
}
