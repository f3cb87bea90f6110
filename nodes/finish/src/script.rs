//! The LIGGGHTS input script of one DEM segment: the patch as a `mesh/surface/stress` wall with
//! Finnie wear, and media spheres sent over it one pass at a time.
//!
//! A pass: one sphere is created above the patch, given the machine's relative velocity (at
//! the impact angle, in a random direction) and pressed toward the part by the bed's load plus
//! the centrifugal body force; it strikes, slides and leaves; it is deleted before the next.
//! One sphere at a time, because a 3 mm medium covers the whole sub-millimetre patch: two
//! would overlap. The script is self-contained (the STL beside it) so anyone can rerun it:
//! `liggghts -in in.liggghts`.
//!
//! Pitfalls of LIGGGHTS 3.8 handled here: moduli above 1e9 Pa need `hard_particles yes`; a
//! millimetre sphere over 10^4 micrometre triangles overflows the default neighbour pages
//! (LIGGGHTS aborts without a message), hence `neigh_modify one/page`; atom sorting with one
//! particle of a huge cutoff aborts ("bin size = 0"), hence `atom_modify sort 0 0`; atom ids
//! restart at 1 after a deletion, hence `set group all` rather than `set atom N`.

use std::fmt::Write;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use crate::setting::{Action, Media, MediaPhysics, Workpiece};

/// File names inside a segment's folder.
pub const INPUT: &str = "in.liggghts";
pub const LOG: &str = "log.liggghts";
pub const STL: &str = "patch.stl";
pub const WEAR_VTK: &str = "wear.vtk";
pub const CONTACTS: &str = "contacts.txt";

/// One medium's pass over the patch.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Pass {
    /// Centre of the sphere when it is created, m.
    pub start_m: [f64; 3],
    pub velocity_m_s: [f64; 3],
}

/// Everything a segment's script says.
#[derive(Debug, Clone, Serialize)]
pub struct Segment {
    /// Bounding box of the wall mesh, m: [[x0, x1], [y0, y1], [z0, z1]].
    pub mesh_bounds_m: [[f64; 2]; 3],
    pub triangles: usize,
    pub media: Media,
    pub workpiece: Workpiece,
    /// Finnie's constant, 1/Pa (LIGGGHTS' `k_finnie`).
    pub k_finnie_per_pa: f64,
    pub timestep_s: f64,
    pub steps_per_pass: usize,
    pub passes: Vec<Pass>,
    /// The force pressing each sphere toward the part, N.
    pub press_force_n: f64,
    /// Contacts are dumped every this many steps (the Archard sampling).
    pub contact_every: usize,
    /// Thermo output every this many steps (progress and ETA).
    pub thermo_every: usize,
}

impl Segment {
    pub fn total_steps(&self) -> usize {
        self.steps_per_pass * self.passes.len()
    }

    pub fn simulated_time_s(&self) -> f64 {
        self.total_steps() as f64 * self.timestep_s
    }
}

/// Where the passes aim: the patch inside the guard band, m.
#[derive(Debug, Clone, Copy)]
pub struct AimArea {
    pub x_m: [f64; 2],
    pub y_m: [f64; 2],
    /// Highest point of the mesh, m.
    pub top_m: f64,
}

/// The passes of a segment: directions uniform, aim points uniform over `aim`; each sphere
/// starts `gap` above the highest point, upstream of its aim point by the distance it flies
/// before landing there. Returns the passes and the steps each needs (landing and sliding
/// over a quarter of the patch's diagonal).
pub fn plan_passes(
    count: usize,
    seed: u64,
    aim: AimArea,
    media: &Media,
    action: &Action,
    timestep_s: f64,
    guard_m: f64,
) -> (Vec<Pass>, usize) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let r = media.radius_m();
    let angle = action.impact_angle_deg.to_radians();
    let v = action.media_velocity_m_s;
    let (v_t, v_n) = (v * angle.cos(), v * angle.sin());
    // A gap of a micrometre: the flight is short, the landing point well defined.
    let gap = 1e-6;
    let flight_s = if v_n > 0.0 { gap / v_n } else { 0.0 };
    let mut passes = Vec::with_capacity(count);
    for _ in 0..count {
        let phi: f64 = rng.gen_range(0.0..std::f64::consts::TAU);
        let ax = rng.gen_range(aim.x_m[0]..=aim.x_m[1]);
        let ay = rng.gen_range(aim.y_m[0]..=aim.y_m[1]);
        let (dx, dy) = (phi.cos(), phi.sin());
        passes.push(Pass {
            start_m: [
                ax - dx * v_t * flight_s,
                ay - dy * v_t * flight_s,
                aim.top_m + gap + r,
            ],
            velocity_m_s: [v_t * dx, v_t * dy, -v_n],
        });
    }
    // A pass is the impact and a slide over a quarter of the patch's diagonal (at least
    // 20 um): the wear of a medium is in its impacts and the bounces that follow; short passes
    // spread more impacts over the patch for the same engine time.
    let w = aim.x_m[1] - aim.x_m[0];
    let h = aim.y_m[1] - aim.y_m[0];
    let _ = guard_m;
    let cross_m = (0.25 * (w * w + h * h).sqrt()).max(2e-5);
    let pass_s = flight_s + if v_t > 0.0 { cross_m / v_t } else { 1e-5 };
    let steps = ((pass_s / timestep_s).ceil() as usize).max(10);
    (passes, steps)
}

/// The input script of `seg`, reading [`STL`] and writing [`WEAR_VTK`], [`CONTACTS`].
pub fn input_script(seg: &Segment) -> String {
    let [[x0, x1], [y0, y1], [z0, z1]] = seg.mesh_bounds_m;
    let r = seg.media.radius_m();
    // The box holds the sphere wherever it is over the patch: a radius and a margin around
    // the mesh sideways, two diameters above. A sphere that leaves is lost (ignored).
    let margin = r + 1e-4;
    let skin = 2e-5;
    let one = seg.triangles + 1000;
    let m = &seg.media;
    let w = &seg.workpiece;
    let e = m.restitution;
    let mu = m.friction;
    let k = seg.k_finnie_per_pa;
    let mut s = String::new();
    let _ = writeln!(
        s,
        "# surfstream finish: one DEM segment of the finishing simulation (LIGGGHTS 3.8).\n\
         # Rerun: liggghts -in {INPUT}   (or mpirun -np N liggghts -in {INPUT})\n\
         # Patch: {STL} ({} triangles, m); media: {} mm spheres, {} passes of {} steps at dt = {:e} s.\n\
         atom_style granular\n\
         atom_modify map array sort 0 0.0\n\
         boundary f f f\n\
         newton off\n\
         communicate single vel yes\n\
         units si\n\
         region domain block {:e} {:e} {:e} {:e} {:e} {:e} units box\n\
         create_box 2 domain\n\
         neighbor {skin:e} bin\n\
         neigh_modify delay 0 one {one} page {}\n\
         hard_particles yes\n\
         # type 1: media, type 2: the part\n\
         fix m1 all property/global youngsModulus peratomtype {:e} {:e}\n\
         fix m2 all property/global poissonsRatio peratomtype {} {}\n\
         fix m3 all property/global coefficientRestitution peratomtypepair 2 {e} {e} {e} {e}\n\
         fix m4 all property/global coefficientFriction peratomtypepair 2 {mu} {mu} {mu} {mu}\n\
         fix m5 all property/global k_finnie peratomtypepair 2 {k:e} {k:e} {k:e} {k:e}\n\
         pair_style gran model hertz tangential history\n\
         pair_coeff * *\n\
         timestep {:e}\n\
         fix wall all mesh/surface/stress file {STL} type 2 wear finnie\n\
         fix walls all wall/gran model hertz tangential history mesh n_meshes 1 meshes wall\n\
         fix integrate all nve/sphere\n\
         # bed load + centrifugal body force, pressing each medium on the part\n\
         fix press all addforce 0 0 {:e}\n\
         compute wc all wall/gran/local pos vel id force\n\
         dump dc all local {} {CONTACTS} {}\n\
         thermo_style custom step atoms ke cpu\n\
         thermo {}\n\
         thermo_modify lost ignore norm no",
        seg.triangles,
        m.diameter_mm,
        seg.passes.len(),
        seg.steps_per_pass,
        seg.timestep_s,
        x0 - margin,
        x1 + margin,
        y0 - margin,
        y1 + margin,
        z0 - 1e-5,
        z1 + 4.0 * r + 1e-4,
        one * 10,
        m.youngs_modulus_pa,
        w.youngs_modulus_pa,
        m.poisson_ratio,
        w.poisson_ratio,
        seg.timestep_s,
        -seg.press_force_n,
        seg.contact_every,
        (1..=crate::contacts::CONTACT_COLUMNS)
            .map(|i| format!("c_wc[{i}]"))
            .collect::<Vec<_>>()
            .join(" "),
        seg.thermo_every,
    );
    let n = seg.passes.len();
    for (i, p) in seg.passes.iter().enumerate() {
        let [x, y, z] = p.start_m;
        let [vx, vy, vz] = p.velocity_m_s;
        let _ = writeln!(
            s,
            "print \"surfstream pass {} of {n}\"\n\
             create_atoms 1 single {x:e} {y:e} {z:e} units box\n\
             set group all diameter {:e} density {} vx {vx:e} vy {vy:e} vz {vz:e}\n\
             run {} post no",
            i + 1,
            2.0 * r,
            m.density_kg_m3,
            seg.steps_per_pass,
        );
        if i + 1 < n {
            let _ = writeln!(s, "delete_atoms group all");
        }
    }
    let _ = writeln!(
        s,
        "dump dm all mesh/vtk 1 {WEAR_VTK} output face area wear wall\n\
         run 0\n\
         print \"surfstream segment done\""
    );
    s
}

/// How a micro pass loads the patch.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum MicroLoad {
    /// A free impact: the sphere flies at its velocity, strikes, rebounds; Finnie wear.
    Impact,
    /// An enduring sliding contact: the sphere is pressed by `press_force_n` (`fix addforce`,
    /// its normal motion integrated under that load and the contact) while its velocity along
    /// the part is prescribed (`fix move linear vx vy NULL`: no spin, so the slip is the
    /// prescribed speed); Archard wear from the contact dump. It is first pressed in place for
    /// `settle_steps` (`fix move linear 0 0 NULL`: no slip, so no Archard wear) so that it
    /// slides at its load, not ringing about it.
    Sliding {
        press_force_n: f64,
        settle_steps: usize,
    },
}

/// One pass of a micro segment.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct MicroPass {
    /// Centre of the sphere when it is created, m.
    pub start_m: [f64; 3],
    pub velocity_m_s: [f64; 3],
    pub steps: usize,
    pub load: MicroLoad,
}

/// A micro segment's script: the patch (the tolerance mesh) and passes of either kind. The
/// passes of one engine process are all of one kind (their wear is read from one output).
#[derive(Debug, Clone, Serialize)]
pub struct MicroSegment {
    /// Bounding box of the wall mesh, m: [[x0, x1], [y0, y1], [z0, z1]].
    pub mesh_bounds_m: [[f64; 2]; 3],
    pub triangles: usize,
    pub media: Media,
    pub workpiece: Workpiece,
    /// Finnie's constant, 1/Pa (LIGGGHTS' `k_finnie`).
    pub k_finnie_per_pa: f64,
    pub timestep_s: f64,
    /// The mesh's `curvature`, degrees: neighbouring triangles within this angle are one
    /// surface to LIGGGHTS (one contact per medium on them, edges and corners between them
    /// not contacts); `curvature_tolerant yes` lets it exceed the mesh's smallest angle.
    pub curvature_deg: f64,
    pub passes: Vec<MicroPass>,
    /// Contacts are dumped every this many steps (the Archard sampling and the contact
    /// statistics).
    pub contact_every: usize,
    pub thermo_every: usize,
}

impl MicroPass {
    /// The engine steps the pass takes: its own and a sliding pass's settling in place.
    pub fn engine_steps(&self) -> usize {
        match self.load {
            MicroLoad::Sliding { settle_steps, .. } => self.steps + settle_steps,
            MicroLoad::Impact => self.steps,
        }
    }
}

impl MicroSegment {
    pub fn total_steps(&self) -> usize {
        self.passes.iter().map(MicroPass::engine_steps).sum()
    }

    pub fn simulated_time_s(&self) -> f64 {
        self.total_steps() as f64 * self.timestep_s
    }
}

/// The input script of a micro segment, reading [`STL`] and writing [`WEAR_VTK`] (Finnie, per
/// triangle) and [`CONTACTS`] (every contact every `contact_every` steps).
pub fn micro_script(seg: &MicroSegment) -> String {
    let [[x0, x1], [y0, y1], [z0, z1]] = seg.mesh_bounds_m;
    let r = seg.media.radius_m();
    let margin = r + 1e-4;
    let skin = 2e-5;
    let one = seg.triangles + 1000;
    let (m, w) = (&seg.media, &seg.workpiece);
    let (e, mu, k) = (m.restitution, m.friction, seg.k_finnie_per_pa);
    let mut s = String::new();
    let _ = writeln!(
        s,
        "# surfstream finish: micro passes on the patch's tolerance mesh (LIGGGHTS 3.8).\n\
         # Rerun: liggghts -in {INPUT}\n\
         # Patch: {STL} ({} triangles, m); media: {} mm spheres, {} passes, dt = {:e} s.\n\
         atom_style granular\n\
         atom_modify map array sort 0 0.0\n\
         boundary f f f\n\
         newton off\n\
         communicate single vel yes\n\
         units si\n\
         region domain block {:e} {:e} {:e} {:e} {:e} {:e} units box\n\
         create_box 2 domain\n\
         neighbor {skin:e} bin\n\
         neigh_modify delay 0 one {one} page {}\n\
         hard_particles yes\n\
         # type 1: media, type 2: the part (its real stiffness)\n\
         fix m1 all property/global youngsModulus peratomtype {:e} {:e}\n\
         fix m2 all property/global poissonsRatio peratomtype {} {}\n\
         fix m3 all property/global coefficientRestitution peratomtypepair 2 {e} {e} {e} {e}\n\
         fix m4 all property/global coefficientFriction peratomtypepair 2 {mu} {mu} {mu} {mu}\n\
         fix m5 all property/global k_finnie peratomtypepair 2 {k:e} {k:e} {k:e} {k:e}\n\
         pair_style gran model hertz tangential history\n\
         pair_coeff * *\n\
         timestep {:e}\n\
         # curvature: the patch's triangles within {} deg of each other are one surface (one\n\
         # contact per medium, not one per triangle)\n\
         fix wall all mesh/surface/stress file {STL} type 2 curvature {} curvature_tolerant yes wear finnie\n\
         fix walls all wall/gran model hertz tangential history mesh n_meshes 1 meshes wall\n\
         compute wc all wall/gran/local pos vel id force\n\
         dump dc all local {} {CONTACTS} {}\n\
         thermo_style custom step atoms ke cpu\n\
         thermo {}\n\
         thermo_modify lost ignore norm no",
        seg.triangles,
        m.diameter_mm,
        seg.passes.len(),
        seg.timestep_s,
        x0 - margin,
        x1 + margin,
        y0 - margin,
        y1 + margin,
        z0 - 1e-5,
        z1 + 4.0 * r + 1e-4,
        one * 10,
        m.youngs_modulus_pa,
        w.youngs_modulus_pa,
        m.poisson_ratio,
        w.poisson_ratio,
        seg.timestep_s,
        seg.curvature_deg,
        seg.curvature_deg,
        seg.contact_every,
        (1..=crate::contacts::CONTACT_COLUMNS)
            .map(|i| format!("c_wc[{i}]"))
            .collect::<Vec<_>>()
            .join(" "),
        seg.thermo_every,
    );
    let n = seg.passes.len();
    for (i, p) in seg.passes.iter().enumerate() {
        let [x, y, z] = p.start_m;
        let [vx, vy, vz] = p.velocity_m_s;
        let _ = writeln!(
            s,
            "print \"surfstream pass {} of {n}\"\n\
             create_atoms 1 single {x:e} {y:e} {z:e} units box\n\
             set group all diameter {:e} density {} vx {vx:e} vy {vy:e} vz {vz:e}",
            i + 1,
            2.0 * r,
            m.density_kg_m3,
        );
        match p.load {
            MicroLoad::Impact => {
                let _ = writeln!(
                    s,
                    "fix integrate all nve/sphere\nrun {} post no\nunfix integrate",
                    p.steps
                );
            }
            MicroLoad::Sliding {
                press_force_n,
                settle_steps,
            } => {
                let _ = writeln!(s, "fix press all addforce 0 0 {:e}", -press_force_n);
                if settle_steps > 0 {
                    let _ = writeln!(
                        s,
                        "fix settle all move linear 0 0 NULL\n\
                         run {settle_steps} post no\n\
                         unfix settle"
                    );
                }
                let _ = writeln!(
                    s,
                    "fix slide all move linear {vx:e} {vy:e} NULL\n\
                     run {} post no\n\
                     unfix slide\n\
                     unfix press",
                    p.steps
                );
            }
        }
        if i + 1 < n {
            let _ = writeln!(s, "delete_atoms group all");
        }
    }
    let _ = writeln!(
        s,
        "dump dm all mesh/vtk 1 {WEAR_VTK} output face area wear wall\n\
         run 0\n\
         print \"surfstream segment done\""
    );
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::setting::{BarrelKinematics, BarrelMachine};

    #[test]
    fn passes_land_on_the_patch_and_the_script_names_every_pass() {
        let media = Media::default();
        let action = BarrelMachine::default().action(&media, 20.0).unwrap();
        let aim = AimArea {
            x_m: [1e-5, 2e-4],
            y_m: [1e-5, 2e-4],
            top_m: 5e-6,
        };
        let (passes, steps) = plan_passes(7, 3, aim, &media, &action, 1e-7, 2e-5);
        assert_eq!(passes.len(), 7);
        assert!(steps > 100, "{steps}");
        for p in &passes {
            // Starts one radius plus 1 um above the top, moves down, speed as the action says.
            assert!((p.start_m[2] - (5e-6 + 1e-6 + 1.5e-3)).abs() < 1e-12);
            let v = p.velocity_m_s;
            let speed = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            assert!((speed - action.media_velocity_m_s).abs() < 1e-9);
            assert!(v[2] < 0.0);
        }
        // Same seed, same passes.
        assert_eq!(
            plan_passes(7, 3, aim, &media, &action, 1e-7, 2e-5).0,
            passes
        );
        let seg = Segment {
            mesh_bounds_m: [[0.0, 2.1e-4], [0.0, 2.1e-4], [0.0, 5e-6]],
            triangles: 800,
            media,
            workpiece: Workpiece::default(),
            k_finnie_per_pa: 1e-10,
            timestep_s: 1e-7,
            steps_per_pass: steps,
            passes,
            press_force_n: 0.03,
            contact_every: 5,
            thermo_every: 100,
        };
        let text = input_script(&seg);
        assert_eq!(text.matches("create_atoms 1 single").count(), 7);
        assert_eq!(text.matches("delete_atoms group all").count(), 6);
        assert!(text.contains("print \"surfstream pass 7 of 7\""));
        assert!(text.contains("hard_particles yes"));
        assert!(text.contains("k_finnie peratomtypepair 2 1e-10 1e-10 1e-10 1e-10"));
        assert!(text.contains("c_wc[18]"));
    }
}
