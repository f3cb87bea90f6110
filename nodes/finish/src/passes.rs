//! A cycle's passes on the high-fidelity model (the micro scale, issue 38).
//!
//! - **The model.** The patch is meshed by the project's tolerance mesher
//!   ([`surfstream_mesher::mesh_surface`], LIGGGHTS' profile: ASCII sheet in m, 1 deg angle bound),
//!   the model the rest of the pipeline builds and judges, not a block-averaged grid. Its
//!   fidelity on the evaluated patch is [`PatchModel`] (finish.json `patch.model`).
//! - **One contact per medium.** LIGGGHTS takes every triangle a sphere overlaps as a full
//!   Hertz contact unless the triangles are one surface to it: the mesh's `curvature` angle
//!   (`fix mesh/surface ... curvature C curvature_tolerant yes`) makes neighbours within C
//!   degrees coplanar, so that a face contact on one suppresses the others
//!   (`FixContactHistoryMesh::coplanarContactAlready`) and the edges and corners between them
//!   are no contacts (`SurfaceMesh::handleSharedEdge`). On a flat meshed with slightly
//!   non-coplanar small triangles, the default (0.256 deg) gives 104 contacts and 80 x the
//!   Hertz force at 2 um overlap; 1 deg gives one contact, 0.998 x Hertz (tests/micro.rs).
//! - **Contacts from the macro statistics.** Each pass is one [`ContactSample`] of the
//!   machine's run drawn at random: an impact at its normal and tangential speed (Finnie wear,
//!   LIGGGHTS' per-triangle output), or an enduring sliding contact pressed by its normal
//!   force and slid at its tangential speed (`fix addforce` + `fix move linear vx vy NULL`;
//!   Archard wear from the per-contact dump). The part has its real stiffness.
//! - **Parallel passes.** The passes go into engine processes of at most
//!   `passes_per_engine` passes of one kind, in a fixed order; `jobs` processes run at once,
//!   each in its own folder; the wear maps are summed in the groups' order, so the result is
//!   the same for any `jobs`.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::Instant;

use anyhow::{anyhow, bail, Context, Result};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use surfstream_core::metrology::{height_params, level_plane, Grid};
use surfstream_core::raster::Shape;
use surfstream_core::Sampling;
use surfstream_mesher::tolerance::{Tolerance, ANGLE_BOUNDED_TOLERANCE};
use surfstream_mesher::{
    mesh_surface, prepare_heights, DemEngine, LengthUnit, MeshKind, MeshMade, MeshOutputs,
    MesherConfig, StlFormat,
};

use crate::contacts::{archard_from_dump, ContactSummary};
use crate::engine::{run_engine, EngineCommand, EngineProgress};
use crate::grid::{triangle_volumes_to_samples, volume_um3, NodeMap, Window, MESH_SHIFT_M};
use crate::script::{self, micro_script, MicroLoad, MicroPass, MicroSegment};
use crate::setting::{
    effective_modulus_pa, hertz_contact_time_s, rayleigh_time_s, Media, MediaPhysics, PartMaterial,
    PartMaterialPhysics, Workpiece,
};
use crate::vtk::read_vtk;

/// finish.json `patch.model` is core's record.
pub use surfstream_core::record::finish::PatchModel;

/// The `curvature` given to the patch's mesh, degrees (see the module doc).
pub const DEFAULT_CURVATURE_DEG: f64 = 1.0;
/// Engine processes a cycle's passes are split into ([`passes_per_engine`]): fixed, so the
/// wear does not depend on `--jobs`; each process pays LIGGGHTS' set-up (reading the STL and
/// building the mesh's topology; docs/finish.md measures it).
pub const DEFAULT_ENGINE_PROCESSES: usize = 4;

/// The contacts the passes draw: [`crate::machine::MacroContacts::samples`].
pub use crate::machine::ContactSample;

/// How a patch the micro passes strike is meshed (always LIGGGHTS' profile: ASCII sheet in
/// m, 1 deg angle bound). One pointwise bound in um for every surface of a run, set by the
/// measured model: half its Sq on the patch (the model's default, the paper's "within
/// 1 um"); what else is judged depends on what the surface is.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum PatchFidelity {
    /// The measured model (cycle 1): LIGGGHTS' statistical tolerance (Sa/Sq/Sz 1/1/3 %,
    /// residual 50 % of Sq) and no point farther than `max_error_um` from the measurement.
    Measured { max_error_um: f64 },
    /// A worn surface the laws predicted (cycles 2..): the same statistical tolerance,
    /// relative to its own Sq, and the measured model's pointwise bound in um.
    Worn { max_error_um: f64 },
    /// A form (the ideal model): the pointwise bound alone; its Sa/Sq/Sz are the form's, and
    /// 1 % of a form's small Sq cost the demo's datum 69 011 triangles for nothing the DEM
    /// sees.
    Form { max_error_um: f64 },
    /// LIGGGHTS' statistical tolerance alone, no pointwise bound (the profile's default:
    /// synthetic surfaces of the engine's checks).
    Statistical,
}

impl PatchFidelity {
    /// The pointwise bound of a run whose measured patch has `sq_um`.
    pub fn bound_for(sq_um: f64) -> f64 {
        surfstream_mesher::tolerance::DEFAULT_MAX_ERROR_PCT / 100.0 * sq_um
    }

    pub fn max_error_um(self) -> Option<f64> {
        match self {
            PatchFidelity::Measured { max_error_um }
            | PatchFidelity::Worn { max_error_um }
            | PatchFidelity::Form { max_error_um } => Some(max_error_um),
            PatchFidelity::Statistical => None,
        }
    }

    /// The mesher's tolerance for a surface of `sq_um` (about its mean, the meshed area). The
    /// mesher bounds the error as a share of each region's Sq: the bound in um is that share
    /// of the whole area's Sq, exact on the whole area and in proportion to a window's Sq in
    /// the window (on a homogeneous surface within a few percent; `patch.model.max_error_um`
    /// is measured on the evaluated patch either way).
    fn tolerance(self, sq_um: f64) -> Tolerance {
        let max_error_pct = self.max_error_um().map(|b| 100.0 * b / sq_um.max(1e-12));
        match self {
            PatchFidelity::Measured { .. }
            | PatchFidelity::Worn { .. }
            | PatchFidelity::Statistical => Tolerance {
                max_error_pct,
                ..ANGLE_BOUNDED_TOLERANCE
            },
            // Statistics not judged (100 %: any mesh within the pointwise bound keeps a
            // form's Sa and Sq far closer than that).
            PatchFidelity::Form { .. } => Tolerance {
                sa_pct: 100.0,
                sq_pct: 100.0,
                sz_pct: 100.0,
                residual_pct: None,
                max_error_pct,
                roughness_pct: None,
            },
        }
    }

    fn describe(self) -> String {
        let b = self.max_error_um().unwrap_or(f64::NAN);
        // The statistical part read from the tolerance the mesher is given, not restated.
        let t = ANGLE_BOUNDED_TOLERANCE;
        let stats = format!(
            "Sa/Sq/Sz {}/{}/{} %, residual {} %",
            t.sa_pct,
            t.sq_pct,
            t.sz_pct,
            t.residual_pct.unwrap_or(f64::NAN)
        );
        match self {
            PatchFidelity::Statistical => format!("LIGGGHTS' statistical tolerance: {stats} of Sq per region, no pointwise bound"),
            PatchFidelity::Measured { .. } => format!("measured model: {stats} of Sq per region, no point farther than {b:.3} um (half the patch's Sq)"),
            PatchFidelity::Worn { .. } => format!("worn surface: {stats} of its own Sq per region, no point farther than {b:.3} um (the measured model's bound)"),
            PatchFidelity::Form { .. } => format!("form (ideal model): no point farther than {b:.3} um (the measured model's bound); a form's Sa/Sq/Sz not judged"),
        }
    }
}

/// The patch's tolerance mesh, as LIGGGHTS reads it.
#[derive(Debug, Clone)]
pub struct ModelMesh {
    /// Triangles in m (the STL's coordinates).
    pub triangles_m: Vec<[[f64; 3]; 3]>,
    /// STL (m) to patch coordinates (um): um = m * 1e6 + offset.
    pub offset_um: [f64; 3],
    pub sampling: Sampling,
    pub bounds_m: [[f64; 2]; 3],
    pub model: PatchModel,
}

impl MicroPlan {
    pub fn workpiece(&self) -> Workpiece {
        self.part.workpiece()
    }

    /// Archard's K / H, 1/Pa.
    pub fn archard_k_over_h_per_pa(&self) -> f64 {
        self.archard_k / self.part.hardness_pa
    }
}

impl ModelMesh {
    /// The sample grid as nodes (stride 1), for point volumes.
    pub fn node_map(&self) -> NodeMap {
        NodeMap {
            stride: 1,
            node_rows: self.sampling.rows(),
            node_cols: self.sampling.cols(),
            sampling: self.sampling,
            offset_um: self.offset_um,
        }
    }

    /// Height (m) of a sphere's centre of `radius_m` at (x, y) (m) when it first touches the
    /// mesh's vertices from above.
    pub fn touch_height_m(&self, x: f64, y: f64, radius_m: f64) -> f64 {
        let r2 = radius_m * radius_m;
        let mut top = f64::NEG_INFINITY;
        for t in &self.triangles_m {
            for v in t {
                let d2 = (v[0] - x).powi(2) + (v[1] - y).powi(2);
                if d2 < r2 {
                    top = top.max(v[2] + (r2 - d2).sqrt());
                }
            }
        }
        top
    }
}

/// Meshes `heights_um` (patch + guard band, sampled as `at` says) with the tolerance mesher
/// for LIGGGHTS within `max_triangles`, writes `dir/patch.stl` (shifted by
/// [`MESH_SHIFT_M`] in x and y: LIGGGHTS refuses a mesh spanning less than 1e-4 m) and judges
/// the mesh on `region` (the evaluated patch).
pub fn mesh_model(
    heights_um: &[f64],
    at: Sampling,
    region: Window,
    max_triangles: usize,
    judged_as: PatchFidelity,
    curvature_deg: f64,
    dir: &Path,
) -> Result<ModelMesh> {
    std::fs::create_dir_all(dir).with_context(|| format!("{}: cannot create", dir.display()))?;
    let shape = Shape::new(at.rows(), at.cols());
    let prepared = prepare_heights(heights_um, shape)?;
    let measured_um = prepared.heights_um.clone();
    // A plane (the ideal model of a flat part) has no roughness to judge a tolerance by:
    // it is meshed to a fixed bound of 1 nm instead, which a plane meets with two triangles.
    let g = Grid::of(heights_um, at)?;
    let sq_um = height_params(&g)?[1];
    let flat = height_params(&Grid::of(&level_plane(&g)?, at)?)?[1] < 1e-6;
    let config = if flat {
        // (A plane needs no angle bound: its greedy mesh is two right triangles.)
        MesherConfig {
            epsilon_um: Some(1e-3),
            max_triangles: Some(max_triangles),
            kind: MeshKind::Sheet,
            units: LengthUnit::M,
            format: StlFormat::Ascii,
            ..MesherConfig::default()
        }
    } else {
        // LIGGGHTS' angle-bounded mesh, judged as the surface's kind asks (PatchFidelity).
        MesherConfig {
            target: Some(DemEngine::Liggghts),
            max_triangles: Some(max_triangles),
            tolerance: Some(judged_as.tolerance(sq_um)),
            ..MesherConfig::default()
        }
    };
    let settings = config
        .settings()
        .map_err(|e| anyhow!("the patch's mesher: {e}"))?;
    let raw_stl = dir.join("patch.model.stl");
    let outputs = MeshOutputs {
        stl: &raw_stl,
        resampled_npy: None,
        stl_label: "surfstream mesh",
    };
    let outcome = mesh_surface(&settings, prepared.into_input(at.pitch()), &outputs)
        .context("meshing the patch with the tolerance mesher")?;
    let MeshMade::Model(mesh) = &outcome.made else {
        bail!("the tolerance mesher returned a grid for LIGGGHTS' adaptive profile");
    };
    let mut offset_um = mesh.counts.offset_um;
    let text = std::fs::read_to_string(&raw_stl)
        .with_context(|| format!("{}: cannot read the patch's mesh", raw_stl.display()))?;
    let mut triangles_m =
        read_ascii_stl(&text).with_context(|| format!("{}", raw_stl.display()))?;
    let _ = std::fs::remove_file(&raw_stl);
    for t in &mut triangles_m {
        for v in t.iter_mut() {
            v[0] += MESH_SHIFT_M;
            v[1] += MESH_SHIFT_M;
        }
    }
    offset_um[0] -= MESH_SHIFT_M * 1e6;
    offset_um[1] -= MESH_SHIFT_M * 1e6;
    let stl = dir.join(script::STL);
    surfstream_core::fsutil::write_atomic(&stl, |w| {
        write_ascii_stl(w, &triangles_m).map_err(|e| anyhow!("{}: {e}", stl.display()))
    })?;
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for v in triangles_m.iter().flatten() {
        for k in 0..3 {
            lo[k] = lo[k].min(v[k]);
            hi[k] = hi[k].max(v[k]);
        }
    }
    let tolerance_met = outcome.report.tolerance.as_ref().map(|t| t.met);
    let min_angle_deg = outcome
        .report
        .adaptive()
        .and_then(|a| a.element_quality.as_ref())
        .map(|q| q.min_angle_deg);
    let fit = fidelity(&measured_um, &mesh.resampled_um, at.cols(), region)?;
    Ok(ModelMesh {
        offset_um,
        sampling: at,
        bounds_m: [[lo[0], hi[0]], [lo[1], hi[1]], [lo[2], hi[2]]],
        model: PatchModel {
            mesher: if flat {
                "surfstream mesher (mesh_surface) at a fixed bound of 1 nm: a plane has no roughness to judge a tolerance by (sheet in m, no angle bound: two right triangles)".into()
            } else {
                "surfstream tolerance mesher (mesh_surface, LIGGGHTS profile: sheet in m, 1 deg angle bound)".into()
            },
            fidelity: if flat {
                String::new()
            } else {
                judged_as.describe()
            },
            max_error_bound_um: judged_as.max_error_um().filter(|_| !flat),
            budget_triangles: max_triangles,
            surface_triangles: triangles_m.len(),
            max_error_over_sq: fit.0,
            max_error_um: fit.1,
            rms_error_um: fit.2,
            sq_um: fit.3,
            tolerance_met,
            min_angle_deg,
            curvature_deg,
        },
        triangles_m,
    })
}

/// (max |e| / Sq, max |e|, rms e, Sq) of mesh vs heights on `region`, each about its mean.
fn fidelity(
    heights: &[f32],
    mesh: &[f32],
    cols: usize,
    region: Window,
) -> Result<(f64, f64, f64, f64)> {
    let mut h = Vec::with_capacity(region.rows * region.cols);
    let mut m = Vec::with_capacity(h.capacity());
    for r in region.row0..region.row0 + region.rows {
        for c in region.col0..region.col0 + region.cols {
            let k = r * cols + c;
            let (a, b) = (f64::from(heights[k]), f64::from(mesh[k]));
            if a.is_finite() && b.is_finite() {
                h.push(a);
                m.push(b);
            }
        }
    }
    if h.is_empty() {
        bail!("the patch's mesh covers no measured sample of the evaluated patch");
    }
    let n = h.len() as f64;
    let (mh, mm) = (h.iter().sum::<f64>() / n, m.iter().sum::<f64>() / n);
    let sq = (h.iter().map(|x| (x - mh).powi(2)).sum::<f64>() / n).sqrt();
    let e: Vec<f64> = h.iter().zip(&m).map(|(a, b)| (b - mm) - (a - mh)).collect();
    let max = e.iter().fold(0.0f64, |a, x| a.max(x.abs()));
    let rms = (e.iter().map(|x| x * x).sum::<f64>() / n).sqrt();
    Ok((if sq > 0.0 { max / sq } else { 0.0 }, max, rms, sq))
}

/// The triangles of an ASCII STL (its `vertex` lines, three per facet).
pub fn read_ascii_stl(text: &str) -> Result<Vec<[[f64; 3]; 3]>> {
    let mut out = Vec::new();
    let mut cur = Vec::with_capacity(3);
    for (i, line) in text.lines().enumerate() {
        let l = line.trim_start();
        if let Some(rest) = l.strip_prefix("vertex") {
            let v: Vec<f64> = rest
                .split_whitespace()
                .map(str::parse)
                .collect::<Result<_, _>>()
                .map_err(|_| anyhow!("line {}: expected three numbers after 'vertex'", i + 1))?;
            if v.len() != 3 {
                bail!(
                    "line {}: {} numbers after 'vertex', expected 3",
                    i + 1,
                    v.len()
                );
            }
            cur.push([v[0], v[1], v[2]]);
            if cur.len() == 3 {
                out.push([cur[0], cur[1], cur[2]]);
                cur.clear();
            }
        }
    }
    if !cur.is_empty() {
        bail!("a facet with {} vertices at the end", cur.len());
    }
    if out.is_empty() {
        bail!("no triangle (no 'vertex' lines)");
    }
    Ok(out)
}

fn write_ascii_stl(w: &mut dyn std::io::Write, triangles: &[[[f64; 3]; 3]]) -> std::io::Result<()> {
    writeln!(w, "solid surfstream_finish_patch")?;
    for t in triangles {
        let (a, b, c) = (t[0], t[1], t[2]);
        let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
        let v = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
        let n = [
            u[1] * v[2] - u[2] * v[1],
            u[2] * v[0] - u[0] * v[2],
            u[0] * v[1] - u[1] * v[0],
        ];
        let l = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt().max(1e-300);
        writeln!(
            w,
            "facet normal {:e} {:e} {:e}",
            n[0] / l,
            n[1] / l,
            n[2] / l
        )?;
        writeln!(w, "outer loop")?;
        for p in t {
            writeln!(w, "vertex {:e} {:e} {:e}", p[0], p[1], p[2])?;
        }
        writeln!(w, "endloop\nendfacet")?;
    }
    writeln!(w, "endsolid surfstream_finish_patch")?;
    w.flush()
}

/// What a cycle's micro passes are made of.
#[derive(Debug, Clone)]
pub struct MicroPlan {
    /// The media at their real stiffness (the macro run's are softened).
    pub media: Media,
    /// The part: its elasticity is the wall's, its hardness Archard's H.
    pub part: PartMaterial,
    pub k_finnie_per_pa: f64,
    /// Archard's dimensionless wear coefficient K (V = K / H F s).
    pub archard_k: f64,
    pub curvature_deg: f64,
    pub passes: usize,
    pub seed: u64,
    /// Engine processes at once.
    pub jobs: usize,
    pub passes_per_engine: usize,
    pub contact_every: usize,
    /// The track an enduring contact slides, m (the macro run's softened media do not keep
    /// contact durations; the Archard wear per length of track is what the passes sample).
    pub max_slide_m: f64,
}

/// Periods of the normal oscillation a sliding pass is pressed in place before it slides.
pub const SETTLE_PERIODS: f64 = 3.0;

/// Period of the normal oscillation of a medium pressed by `force_n` on a flat of Hertz
/// constant `k_hertz` (4/3 E* sqrt(R)), s: 2 pi sqrt(m / (dF/d delta)) at the static overlap.
pub fn normal_period_s(media: &Media, k_hertz: f64, force_n: f64) -> f64 {
    let f = force_n.max(1e-9);
    // dF/d(delta) at the static overlap (F / K)^(2/3).
    let stiffness = 1.5 * k_hertz.powf(2.0 / 3.0) * f.powf(1.0 / 3.0);
    std::f64::consts::TAU * (media.mass_kg() / stiffness).sqrt()
}

/// The time step of `samples` at the real stiffness: a fifth of the media's Rayleigh time,
/// at least 50 steps per Hertz impact at the fastest sampled normal speed and 50 per period
/// of the normal oscillation under the largest sampled load.
pub fn micro_timestep_s(media: &Media, part: &Workpiece, samples: &[ContactSample]) -> f64 {
    let mut dt = 0.2 * rayleigh_time_s(media);
    let k_hertz = 4.0 / 3.0 * effective_modulus_pa(media, part) * media.radius_m().sqrt();
    for s in samples {
        if s.enduring {
            dt = dt.min(normal_period_s(media, k_hertz, s.normal_force_n) / 50.0);
        } else {
            dt = dt.min(hertz_contact_time_s(media, part, s.normal_speed_m_s) / 50.0);
        }
    }
    dt
}

/// The passes: `plan.passes` samples drawn uniformly from `samples` (seeded), each aimed at a
/// uniform point of `aim` (patch coordinates, m) in a uniform direction along the part.
/// Impacts start 0.1 um above their first touch and run for the flight and 1.5 Hertz contact
/// times; enduring contacts start at the static Hertz overlap of their load below it, moving
/// at their normal speed, pressed and slid over `max_slide_m` (the softened
/// macro run's durations are not kept), centred on the aim point.
pub fn plan_micro_passes(
    samples: &[ContactSample],
    plan: &MicroPlan,
    mesh: &ModelMesh,
    aim: ([f64; 2], [f64; 2]),
    timestep_s: f64,
) -> Result<Vec<MicroPass>> {
    if samples.is_empty() {
        bail!("no contact samples from the machine's run: nothing to send at the patch");
    }
    for (i, s) in samples.iter().enumerate() {
        for (name, v) in [
            ("normal_speed_m_s", s.normal_speed_m_s),
            ("tangential_speed_m_s", s.tangential_speed_m_s),
            ("normal_force_n", s.normal_force_n),
            ("duration_s", s.duration_s),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                bail!("contact sample {i}: {name} = {v}: expected a finite number >= 0");
            }
        }
    }
    let r = plan.media.radius_m();
    let k_hertz = 4.0 / 3.0 * effective_modulus_pa(&plan.media, &plan.workpiece()) * r.sqrt();
    let mut rng = ChaCha8Rng::seed_from_u64(plan.seed);
    let (impacts, enduring): (Vec<ContactSample>, Vec<ContactSample>) =
        samples.iter().partition(|s| !s.enduring);
    let (n_impacts, n_sliding) = pass_kinds(plan.passes, impacts.len(), enduring.len());
    let mut out = Vec::with_capacity(plan.passes);
    // Impacts first, then sliding passes; each kind drawn uniformly from its own samples.
    let draws = (0..n_impacts)
        .map(|_| &impacts)
        .chain((0..n_sliding).map(|_| &enduring));
    for from in draws {
        let s = from[rng.gen_range(0..from.len())];
        let phi: f64 = rng.gen_range(0.0..std::f64::consts::TAU);
        let ax = rng.gen_range(aim.0[0]..=aim.0[1]);
        let ay = rng.gen_range(aim.1[0]..=aim.1[1]);
        let (dx, dy) = (phi.cos(), phi.sin());
        let (vt, vn) = (s.tangential_speed_m_s, s.normal_speed_m_s);
        if s.enduring {
            // The macro run's softened media keep the load and the speed of an enduring
            // contact, not its duration: each slides a track of the plan's length.
            let slide = plan.max_slide_m;
            let (x0, y0) = (ax - 0.5 * slide * dx, ay - 0.5 * slide * dy);
            // At the static Hertz overlap of its load: pressed from the first step (its
            // normal speed then makes the normal motion about it).
            let z0 = mesh.touch_height_m(x0, y0, r) - (s.normal_force_n / k_hertz).powf(2.0 / 3.0);
            // A contact that does not slide wears nothing by Archard: a few steps.
            let t = if vt > 0.0 { slide / vt } else { 0.0 };
            // The start is the static overlap on a flat; on the rough patch the sphere then
            // rings about its equilibrium, and a slide of about one period (30 um at the
            // default machine's speeds) would average the ringing, not the load (Archard 1.37
            // x K/H F s on the wavy test patch). Pressed in place for SETTLE_PERIODS periods
            // of the normal oscillation first (the restitution damps it to ~5 %).
            let period = normal_period_s(&plan.media, k_hertz, s.normal_force_n);
            out.push(MicroPass {
                start_m: [x0, y0, z0],
                velocity_m_s: [vt * dx, vt * dy, -vn],
                steps: ((t / timestep_s).ceil() as usize).max(10),
                load: MicroLoad::Sliding {
                    press_force_n: s.normal_force_n,
                    settle_steps: (SETTLE_PERIODS * period / timestep_s).ceil() as usize,
                },
            });
        } else {
            let gap = 1e-7;
            let vn = vn.max(1e-3);
            let flight_s = gap / vn;
            // Upstream of the aim point by the flight.
            let (x0, y0) = (ax - dx * vt * flight_s, ay - dy * vt * flight_s);
            let z0 = mesh.touch_height_m(ax, ay, r) + gap;
            let t = flight_s + 1.5 * hertz_contact_time_s(&plan.media, &plan.workpiece(), vn);
            out.push(MicroPass {
                start_m: [x0, y0, z0],
                velocity_m_s: [vt * dx, vt * dy, -vn],
                steps: ((t / timestep_s).ceil() as usize).max(10),
                load: MicroLoad::Impact,
            });
        }
    }
    Ok(out)
}

/// Of `passes` per cycle, how many are impacts and how many sliding passes, given the
/// macro run's impact and enduring samples: a fixed share, not the machine's mix. Only the
/// impacts make the prediction's DEM table (the Finnie wear per impact pass, times the
/// machine's impact rate); the sliding law's volume is the macro run's sliding work, and its
/// passes check that volume and show where it goes. An impact costs about a tenth of a
/// sliding pass's steps (the default machine: ~200 against ~2 000), so the budget buys
/// impacts: one pass in [`SLIDING_PASS_EVERY`] slides (at least one when there are both).
pub fn pass_kinds(passes: usize, impact_samples: usize, enduring_samples: usize) -> (usize, usize) {
    match (impact_samples, enduring_samples) {
        (0, _) => (0, passes),
        (_, 0) => (passes, 0),
        _ if passes < 2 => (passes, 0),
        _ => {
            let sliding = (passes / SLIDING_PASS_EVERY).max(1);
            (passes - sliding, sliding)
        }
    }
}

/// Archard's volume on a flat for the sliding passes among `passes`: K/H x F_n x the slide
/// each is commanded (its speed along the part x its steps x `timestep_s`), m^3.
pub fn archard_flat_m3(passes: &[MicroPass], k_over_h_per_pa: f64, timestep_s: f64) -> f64 {
    passes
        .iter()
        .map(|p| match p.load {
            MicroLoad::Sliding { press_force_n, .. } => {
                let [vx, vy, _] = p.velocity_m_s;
                k_over_h_per_pa * press_force_n * vx.hypot(vy) * p.steps as f64 * timestep_s
            }
            MicroLoad::Impact => 0.0,
        })
        .sum()
}

/// One pass in this many is a sliding pass ([`pass_kinds`]).
pub const SLIDING_PASS_EVERY: usize = 8;

/// One engine process of a cycle: passes of one kind.
#[derive(Debug, Clone, Serialize)]
pub struct GroupRecord {
    pub dir: String,
    pub kind: &'static str,
    pub passes: usize,
    pub steps: usize,
    pub engine_s: f64,
    /// LIGGGHTS' own loop time (the sum of its "Loop time of" lines), s: the stepping,
    /// without the set-up (reading the STL, the mesh's topology, the neighbour lists).
    pub loop_s: f64,
    pub command: String,
}

/// What a cycle's micro passes gave (wear in the DEM's own time, unscaled).
#[derive(Debug, Clone)]
pub struct MicroRun {
    /// Finnie depth along z on the meshed area (impacts), um.
    pub finnie_um: Vec<f64>,
    /// Archard depth along z on the meshed area (enduring contacts), um.
    pub archard_um: Vec<f64>,
    /// LIGGGHTS' sum of wear x area over the impact groups, um^3.
    pub finnie_liggghts_volume_um3: f64,
    pub finnie_grid_volume_um3: f64,
    pub unmapped_volume_um3: f64,
    /// Volume of triangles between samples given to the nearest sample, um^3.
    pub to_nearest_sample_um3: f64,
    /// Archard volume from the dumps, um^3 (the grid keeps it exactly).
    pub archard_volume_um3: f64,
    /// K/H x F_n x the commanded slide of the completed sliding passes, um^3: Archard on a
    /// flat, for the DEM's volume on the rough patch to be compared with.
    pub archard_flat_um3: f64,
    pub sliding_contacts: ContactSummary,
    pub impact_contacts: ContactSummary,
    pub model: PatchModel,
    pub passes: Vec<MicroPass>,
    pub timestep_s: f64,
    pub groups: Vec<GroupRecord>,
    /// Wall time of the parallel section and CPU of all its engine processes, s.
    pub engine_s: f64,
    pub engine_cpu_s: f64,
    pub triangles: usize,
    pub stopped: bool,
}

/// What finish.json records of a cycle's micro passes ([`MicroRun::record`]): the maps
/// left out.
#[derive(Debug, Clone, Serialize)]
pub struct MicroRecord {
    pub model: PatchModel,
    pub impacts: usize,
    pub sliding: usize,
    pub timestep_s: f64,
    pub simulated_s: f64,
    pub triangles: usize,
    pub triangle_steps: f64,
    pub engine_s: f64,
    pub engine_cpu_s: f64,
    pub loop_s: f64,
    pub cpu_per_triangle_step_s: f64,
    pub finnie_volume_um3: f64,
    pub archard_volume_um3: f64,
    /// K/H x F_n x the commanded slide of the sliding passes, um^3 (Archard on a flat).
    pub archard_flat_um3: f64,
    /// The DEM's Archard volume on the rough patch over the flat one: below 1 where the
    /// sliding medium hops from peak to peak instead of staying in contact (None: no
    /// sliding pass).
    pub archard_over_flat: Option<f64>,
    pub volume_relative_error: f64,
    pub impact_contacts: ContactSummary,
    pub sliding_contacts: ContactSummary,
    pub processes: Vec<GroupRecord>,
    pub stopped: bool,
}

impl MicroRun {
    pub fn record(&self) -> MicroRecord {
        let impacts = self
            .passes
            .iter()
            .filter(|p| matches!(p.load, MicroLoad::Impact))
            .count();
        let steps: usize = self.passes.iter().map(MicroPass::engine_steps).sum();
        let ts = self.triangle_steps();
        MicroRecord {
            model: self.model.clone(),
            impacts,
            sliding: self.passes.len() - impacts,
            timestep_s: self.timestep_s,
            simulated_s: steps as f64 * self.timestep_s,
            triangles: self.triangles,
            triangle_steps: ts,
            engine_s: self.engine_s,
            engine_cpu_s: self.engine_cpu_s,
            loop_s: self.loop_s(),
            cpu_per_triangle_step_s: if ts > 0.0 {
                self.engine_cpu_s / ts
            } else {
                0.0
            },
            finnie_volume_um3: self.finnie_liggghts_volume_um3,
            archard_volume_um3: self.archard_volume_um3,
            archard_flat_um3: self.archard_flat_um3,
            archard_over_flat: (self.archard_flat_um3 > 0.0)
                .then(|| self.archard_volume_um3 / self.archard_flat_um3),
            volume_relative_error: self.volume_relative_error(),
            impact_contacts: self.impact_contacts.clone(),
            sliding_contacts: self.sliding_contacts.clone(),
            processes: self.groups.clone(),
            stopped: self.stopped,
        }
    }

    /// LIGGGHTS' loop time over all the processes, s.
    pub fn loop_s(&self) -> f64 {
        self.groups.iter().map(|g| g.loop_s).sum()
    }

    pub fn triangle_steps(&self) -> f64 {
        self.triangles as f64
            * self
                .passes
                .iter()
                .map(MicroPass::engine_steps)
                .sum::<usize>() as f64
    }

    pub fn volume_relative_error(&self) -> f64 {
        if self.finnie_liggghts_volume_um3 > 0.0 {
            self.finnie_grid_volume_um3 / self.finnie_liggghts_volume_um3 - 1.0
        } else {
            0.0
        }
    }
}

/// Progress of one engine process of the cycle.
#[derive(Debug, Clone, Copy)]
pub struct GroupProgress {
    /// Which engine process, counted from 1 (of `groups`).
    pub group: usize,
    pub groups: usize,
    pub engine: EngineProgress,
}

/// The passes in engine processes: at most `per` consecutive passes of one kind each,
/// impacts first; the order depends on the passes alone.
pub fn group_passes(passes: &[MicroPass], per: usize) -> Vec<Vec<MicroPass>> {
    let per = per.max(1);
    let mut out = Vec::new();
    for impact in [true, false] {
        let kind: Vec<MicroPass> = passes
            .iter()
            .filter(|p| matches!(p.load, MicroLoad::Impact) == impact)
            .copied()
            .collect();
        out.extend(kind.chunks(per).map(<[MicroPass]>::to_vec));
    }
    out
}

/// The micro passes of one cycle: meshes `heights_um` with the tolerance mesher into `dir`,
/// plans `plan.passes` passes from `samples`, runs them in engine processes `plan.jobs` at a
/// time (`dir/group_NN/`) and maps their wear to the grid keeping the volume. A set `stop`
/// ends the engines; the result says `stopped`.
#[allow(clippy::too_many_arguments)]
pub fn run_micro_passes(
    engine: &EngineCommand,
    plan: &MicroPlan,
    samples: &[ContactSample],
    heights_um: &[f64],
    at: Sampling,
    aim_window: Window,
    max_triangles: usize,
    fidelity: PatchFidelity,
    dir: &Path,
    stop: &AtomicBool,
    progress: &mut dyn FnMut(GroupProgress),
) -> Result<MicroRun> {
    if plan.jobs == 0 {
        bail!("--jobs 0: expected at least one engine process");
    }
    plan.part.check()?;
    plan.media.validate()?;
    let mesh_within = |budget: usize| {
        mesh_model(
            heights_um,
            at,
            aim_window,
            budget,
            fidelity,
            plan.curvature_deg,
            dir,
        )
    };
    // The tolerance is relative to the surface's own Sq: a smooth one (a form model, a
    // surface worn to plateaus) may need more triangles than the budget even at the coarsest
    // mesh; it then gets four times the budget once (`patch.model.budget_triangles`).
    let mesh = match mesh_within(max_triangles) {
        Err(e)
            if matches!(
                e.downcast_ref::<surfstream_mesher::MeshError>(),
                Some(surfstream_mesher::MeshError::CoarsestOverBudget { .. })
            ) =>
        {
            mesh_within(4 * max_triangles)
                .with_context(|| format!("{e:#}; and within 4 x the budget"))?
        }
        r => r?,
    };
    let to_m = |um: f64, axis: usize| (um - mesh.offset_um[axis]) * 1e-6;
    let (px, py) = (at.pitch_x_um(), at.pitch_y_um());
    let aim = (
        [
            to_m(aim_window.col0 as f64 * px, 0),
            to_m((aim_window.col0 + aim_window.cols - 1) as f64 * px, 0),
        ],
        [
            to_m(aim_window.row0 as f64 * py, 1),
            to_m((aim_window.row0 + aim_window.rows - 1) as f64 * py, 1),
        ],
    );
    let dt = micro_timestep_s(&plan.media, &plan.workpiece(), samples);
    let passes = plan_micro_passes(samples, plan, &mesh, aim, dt)?;
    let groups = group_passes(&passes, plan.passes_per_engine);
    let segments: Vec<(PathBuf, MicroSegment)> = groups
        .iter()
        .enumerate()
        .map(|(i, g)| {
            let steps: usize = g.iter().map(MicroPass::engine_steps).sum();
            (
                dir.join(format!("group_{:02}", i + 1)),
                MicroSegment {
                    mesh_bounds_m: mesh.bounds_m,
                    triangles: mesh.triangles_m.len(),
                    media: plan.media,
                    workpiece: plan.workpiece(),
                    k_finnie_per_pa: plan.k_finnie_per_pa,
                    timestep_s: dt,
                    curvature_deg: plan.curvature_deg,
                    passes: g.clone(),
                    contact_every: plan.contact_every,
                    thermo_every: (steps / 8).max(1),
                },
            )
        })
        .collect();
    for (gdir, seg) in &segments {
        std::fs::create_dir_all(gdir)
            .with_context(|| format!("{}: cannot create", gdir.display()))?;
        let stl = gdir.join(script::STL);
        let _ = std::fs::remove_file(&stl);
        std::fs::hard_link(dir.join(script::STL), &stl)
            .or_else(|_| std::fs::copy(dir.join(script::STL), &stl).map(|_| ()))
            .with_context(|| format!("{}: cannot place the patch's mesh", stl.display()))?;
        let input = gdir.join(script::INPUT);
        std::fs::write(&input, micro_script(seg))
            .with_context(|| format!("{}: cannot write", input.display()))?;
    }
    let (runs, engine_s, engine_cpu_s) = run_groups(engine, &segments, plan.jobs, stop, progress);
    let mut run = MicroRun {
        finnie_um: vec![0.0; at.rows() * at.cols()],
        archard_um: vec![0.0; at.rows() * at.cols()],
        finnie_liggghts_volume_um3: 0.0,
        finnie_grid_volume_um3: 0.0,
        unmapped_volume_um3: 0.0,
        to_nearest_sample_um3: 0.0,
        archard_volume_um3: 0.0,
        archard_flat_um3: 0.0,
        sliding_contacts: ContactSummary::default(),
        impact_contacts: ContactSummary::default(),
        model: mesh.model.clone(),
        passes,
        timestep_s: dt,
        groups: Vec::new(),
        engine_s,
        engine_cpu_s,
        triangles: mesh.triangles_m.len(),
        stopped: false,
    };
    let nodes = mesh.node_map();
    // In the groups' order: the sums are the same for any number of jobs.
    for ((gdir, seg), r) in segments.iter().zip(runs) {
        let r = r?;
        let impact = matches!(seg.passes[0].load, MicroLoad::Impact);
        run.groups.push(GroupRecord {
            dir: gdir
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default(),
            kind: if impact { "impact" } else { "sliding" },
            passes: seg.passes.len(),
            steps: seg.total_steps(),
            engine_s: r.wall_s,
            loop_s: loop_time_s(&gdir.join(script::LOG)),
            command: r.command.clone(),
        });
        if r.stopped {
            run.stopped = true;
            continue;
        }
        let (points, summary) = archard_from_dump(
            &gdir.join(script::CONTACTS),
            plan.archard_k_over_h_per_pa(),
            plan.contact_every as f64 * dt,
        )?;
        let _ = std::fs::remove_file(gdir.join(script::CONTACTS));
        if impact {
            let vtk = read_vtk(&gdir.join(script::WEAR_VTK))?;
            let (wear, area) = (vtk.field("wear")?, vtk.field("area")?);
            let volume_m3: Vec<f64> = wear.iter().zip(area).map(|(w, a)| w * a).collect();
            run.finnie_liggghts_volume_um3 += volume_m3.iter().sum::<f64>() * 1e18;
            let mapped =
                triangle_volumes_to_samples(at, mesh.offset_um, &vtk.triangles, &volume_m3);
            run.unmapped_volume_um3 += mapped.unmapped_m3 * 1e18;
            run.to_nearest_sample_um3 += mapped.to_nearest_sample_m3 * 1e18;
            add(&mut run.finnie_um, &mapped.depth_um);
            merge(&mut run.impact_contacts, &summary);
        } else {
            let pts: Vec<(f64, f64, f64)> =
                points.iter().map(|c| (c.x_m, c.y_m, c.volume_m3)).collect();
            add(&mut run.archard_um, &nodes.point_volumes_to_depth(&pts));
            run.archard_volume_um3 += summary.total_volume_m3 * 1e18;
            run.archard_flat_um3 +=
                archard_flat_m3(&seg.passes, plan.archard_k_over_h_per_pa(), dt) * 1e18;
            merge(&mut run.sliding_contacts, &summary);
        }
    }
    run.finnie_grid_volume_um3 = volume_um3(&run.finnie_um, at.pitch());
    Ok(run)
}

/// The sum of the "Loop time of T on N procs" lines of a LIGGGHTS log, s (0 without a log).
pub fn loop_time_s(log: &Path) -> f64 {
    std::fs::read_to_string(log)
        .map(|t| {
            t.lines()
                .filter_map(|l| l.strip_prefix("Loop time of "))
                .filter_map(|l| l.split_whitespace().next()?.parse::<f64>().ok())
                .sum()
        })
        .unwrap_or(0.0)
}

/// Passes per engine process so that `passes` make `processes` processes (at least one
/// pass each): fixed by the plan, not by `--jobs`, so the wear is the same for any jobs.
pub fn passes_per_engine(passes: usize, processes: usize) -> usize {
    passes.div_ceil(processes.max(1)).max(1)
}

fn add(acc: &mut [f64], x: &[f64]) {
    for (a, v) in acc.iter_mut().zip(x) {
        *a += v;
    }
}

fn merge(acc: &mut ContactSummary, s: &ContactSummary) {
    acc.samples += s.samples;
    acc.snapshots += s.snapshots;
    acc.clipped_negative_normal_forces += s.clipped_negative_normal_forces;
    acc.max_normal_force_n = acc.max_normal_force_n.max(s.max_normal_force_n);
    acc.total_volume_m3 += s.total_volume_m3;
    acc.max_contacts_per_snapshot = acc
        .max_contacts_per_snapshot
        .max(s.max_contacts_per_snapshot);
    acc.max_snapshot_normal_force_n = acc
        .max_snapshot_normal_force_n
        .max(s.max_snapshot_normal_force_n);
}

/// Runs the segments' engines, `jobs` at a time, each in its folder; returns their runs in
/// the segments' order, the wall time of the whole and the CPU time of all the engines.
fn run_groups(
    engine: &EngineCommand,
    segments: &[(PathBuf, MicroSegment)],
    jobs: usize,
    stop: &AtomicBool,
    progress: &mut dyn FnMut(GroupProgress),
) -> (Vec<Result<crate::engine::EngineRun>>, f64, f64) {
    let cpu0 = children_cpu_s();
    let t0 = Instant::now();
    let next = AtomicUsize::new(0);
    let results: Mutex<Vec<Option<Result<crate::engine::EngineRun>>>> =
        Mutex::new((0..segments.len()).map(|_| None).collect());
    let groups = segments.len();
    std::thread::scope(|scope| {
        let (tx, rx) = std::sync::mpsc::channel::<GroupProgress>();
        for _ in 0..jobs.min(groups.max(1)) {
            let tx = tx.clone();
            let (next, results) = (&next, &results);
            scope.spawn(move || loop {
                let i = next.fetch_add(1, Ordering::SeqCst);
                if i >= groups {
                    break;
                }
                let (gdir, seg) = &segments[i];
                let r = run_engine(
                    engine,
                    gdir,
                    script::INPUT,
                    script::LOG,
                    seg.total_steps().max(1),
                    1,
                    stop,
                    &mut |e| {
                        let _ = tx.send(GroupProgress {
                            group: i + 1,
                            groups,
                            engine: e,
                        });
                    },
                );
                if let Ok(mut v) = results.lock() {
                    v[i] = Some(r);
                }
            });
        }
        drop(tx);
        for p in rx {
            progress(p);
        }
    });
    let engine_s = t0.elapsed().as_secs_f64();
    let cpu_s = children_cpu_s() - cpu0;
    let runs = results
        .into_inner()
        .unwrap_or_default()
        .into_iter()
        .map(|r| r.unwrap_or_else(|| Err(anyhow!("an engine process did not report"))))
        .collect();
    (runs, engine_s, cpu_s)
}

/// User + system CPU time of the waited-for children of this process, s.
fn children_cpu_s() -> f64 {
    // SAFETY: getrusage fills the struct it is given.
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    if unsafe { libc::getrusage(libc::RUSAGE_CHILDREN, &mut u) } != 0 {
        return 0.0;
    }
    let t = |v: libc::timeval| v.tv_sec as f64 + v.tv_usec as f64 * 1e-6;
    t(u.ru_utime) + t(u.ru_stime)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pass(impact: bool) -> MicroPass {
        MicroPass {
            start_m: [0.0; 3],
            velocity_m_s: [0.0; 3],
            steps: 10,
            load: if impact {
                MicroLoad::Impact
            } else {
                MicroLoad::Sliding {
                    press_force_n: 1.0,
                    settle_steps: 0,
                }
            },
        }
    }

    #[test]
    fn the_budget_buys_impacts_and_keeps_one_sliding_pass_in_eight() {
        assert_eq!(pass_kinds(32, 900, 1200), (28, 4));
        assert_eq!(pass_kinds(6, 2, 1), (5, 1));
        // Only one kind in the machine's run: every pass is of that kind.
        assert_eq!(pass_kinds(6, 0, 3), (0, 6));
        assert_eq!(pass_kinds(6, 3, 0), (6, 0));
        assert_eq!(pass_kinds(1, 3, 3), (1, 0));
    }

    #[test]
    fn passes_are_grouped_by_kind_in_a_fixed_order() {
        let p: Vec<MicroPass> = [true, false, true, true, false, true, true]
            .iter()
            .map(|&i| pass(i))
            .collect();
        let g = group_passes(&p, 2);
        let kinds: Vec<(bool, usize)> = g
            .iter()
            .map(|g| (matches!(g[0].load, MicroLoad::Impact), g.len()))
            .collect();
        assert_eq!(kinds, [(true, 2), (true, 2), (true, 1), (false, 2)]);
        for grp in &g {
            assert!(grp.iter().all(|q| q.load == grp[0].load));
        }
    }

    #[test]
    fn a_form_is_meshed_to_the_bound_in_um_not_to_its_own_small_sq() {
        // A smooth form (the ideal model): its own Sq is small, and 1 % of it in Sa/Sq/Sz
        // costs triangles the DEM does not need; the form is held to the measured model's
        // bound in um instead.
        let (rows, cols) = (64, 64);
        let z: Vec<f64> = (0..rows * cols)
            .map(|k| {
                let (x, y) = ((k % cols) as f64, (k / cols) as f64);
                2e-4 * ((x - 30.0).powi(2) + 0.5 * (y - 20.0).powi(2)) + 0.3 * (x / 25.0).sin()
            })
            .collect();
        let at = Sampling::square(Shape::new(rows, cols), 1.0).unwrap();
        let region = Window {
            row0: 8,
            col0: 8,
            rows: 48,
            cols: 48,
        };
        let bound_um = 0.05;
        let dir = tempfile::tempdir().unwrap();
        let form = PatchFidelity::Form {
            max_error_um: bound_um,
        };
        let f = mesh_model(&z, at, region, 20_000, form, 1.0, dir.path()).unwrap();
        let s = mesh_model(
            &z,
            at,
            region,
            20_000,
            PatchFidelity::Statistical,
            1.0,
            dir.path(),
        )
        .unwrap();
        assert!(f.model.max_error_um <= 1.1 * bound_um, "{:?}", f.model);
        assert_eq!(f.model.max_error_bound_um, Some(bound_um));
        assert!(f.model.fidelity.starts_with("form"), "{}", f.model.fidelity);
        assert!(
            4 * f.triangles_m.len() < s.triangles_m.len(),
            "form {} vs statistical {} triangles",
            f.triangles_m.len(),
            s.triangles_m.len()
        );
    }

    #[test]
    fn the_model_mesh_is_judged_at_the_measured_points() {
        let (rows, cols) = (48, 48);
        let z: Vec<f64> = (0..rows * cols)
            .map(|k| {
                let (x, y) = ((k % cols) as f64, (k / cols) as f64);
                0.8 * (x / 5.0).sin() * (y / 7.0).cos() + 0.1 * (x / 1.7 + y / 2.3).sin()
            })
            .collect();
        let at = Sampling::square(Shape::new(rows, cols), 1.0).unwrap();
        let region = Window {
            row0: 8,
            col0: 8,
            rows: 32,
            cols: 32,
        };
        let dir = tempfile::tempdir().unwrap();
        let bound_um = PatchFidelity::bound_for(0.5);
        let fidelity = PatchFidelity::Measured {
            max_error_um: bound_um,
        };
        let m = mesh_model(&z, at, region, 4000, fidelity, 1.0, dir.path()).unwrap();
        assert!(dir.path().join(script::STL).is_file());
        // The pointwise bound holds at the measured points of the evaluated patch.
        assert_eq!(m.model.max_error_bound_um, Some(bound_um));
        assert!(m.model.max_error_um <= 1.1 * bound_um, "{:?}", m.model);
        assert_eq!(m.model.tolerance_met, Some(true), "{:?}", m.model);
        assert_eq!(m.model.surface_triangles, m.triangles_m.len());
        assert!(m.triangles_m.len() < 2 * 47 * 47, "{}", m.triangles_m.len());
        assert!(
            m.model.max_error_over_sq > 0.0 && m.model.max_error_over_sq < 1.0,
            "{:?}",
            m.model
        );
        // Every vertex is a sample: in patch coordinates it sits on the grid at its height
        // (the mesher's z offset aside: the same for all).
        let mut dz = None;
        for v in m.triangles_m.iter().flatten() {
            let (x, y) = (v[0] * 1e6 + m.offset_um[0], v[1] * 1e6 + m.offset_um[1]);
            let (c, r) = (x.round(), y.round());
            assert!((x - c).abs() < 1e-6 && (y - r).abs() < 1e-6, "{x} {y}");
            let h = z[r as usize * cols + c as usize];
            let d = v[2] * 1e6 + m.offset_um[2] - h;
            let d0 = *dz.get_or_insert(d);
            assert!((d - d0).abs() < 1e-4, "{d} vs {d0}");
        }
        // The touch height of a sphere over a vertex is at least the vertex + radius.
        let v = m.triangles_m[0][0];
        assert!(m.touch_height_m(v[0], v[1], 1.5e-3) >= v[2] + 1.5e-3 - 1e-15);
    }
}
