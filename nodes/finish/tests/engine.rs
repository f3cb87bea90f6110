//! The finishing simulation against the real engine (LIGGGHTS 3.8, Debian package `liggghts`;
//! scripts/test.sh installs it). Small meshes and few passes: the whole file runs in well under
//! a minute.
//!
//! - one frictionless sphere on a flat mesh: LIGGGHTS' Finnie volume equals the analytic
//!   integral of Finnie's law over the loading half of a Hertz impact within 1 %, at 20, 45
//!   and 70 degrees;
//! - the wear mapped to the grid sums to LIGGGHTS' own total within 0.5 %;
//! - the wear is linear in Finnie's k;
//! - a flat surface wears without a pattern tied to the mesh or the position;
//! - a sinusoidal surface loses its peaks first (Spk falls by a larger share than Svk).

use std::path::Path;
use std::sync::atomic::AtomicBool;

use surfstream_core::record::finish::FinishReport;
use surfstream_core::{Pitch, Sampling, Shape};
use surfstream_finish::engine::{run_engine, EngineCommand};
use surfstream_finish::grid::{mesh_patch, volume_um3, Window};
use surfstream_finish::run::WearModel;
use surfstream_finish::run::{
    run_segment, surface_params, timestep_s, SegmentPlan, CALIBRATION_TOLERANCE_PERCENT,
};
use surfstream_finish::script::{self, input_script, Pass, Segment};
use surfstream_finish::setting::{BarrelKinematics, BarrelMachine, Media, MediaPhysics, Workpiece};
use surfstream_finish::vtk::read_vtk;
use surfstream_finish::{finish_record, Calibration, FinishOptions, Model};

mod support;
use support::{analytic_finnie_m3, engine};

fn flat_segment(dir: &Path, media: Media, k: f64, vt: f64, vn: f64) -> Segment {
    let (rows, cols) = (21, 21);
    let at = Sampling::square(Shape::new(rows, cols), 10.0).unwrap();
    let pm = mesh_patch(&vec![0.0; rows * cols], at, 10_000).unwrap();
    std::fs::create_dir_all(dir).unwrap();
    let f = std::fs::File::create(dir.join(script::STL)).unwrap();
    surfstream_mesher::write_stl_ascii(f, &pm.target.mesh, "flat").unwrap();
    let contact =
        surfstream_finish::setting::hertz_contact_time_s(&media, &Workpiece::default(), vn);
    let dt = contact / 2000.0;
    let gap = 1e-8;
    let steps = ((gap / vn + contact) / dt) as usize + 200;
    let v = &pm.target.mesh.vertices;
    let lo = |k: usize| v.iter().map(|p| p[k]).fold(f64::INFINITY, f64::min);
    let hi = |k: usize| v.iter().map(|p| p[k]).fold(f64::NEG_INFINITY, f64::max);
    let (cx, cy) = (0.5 * (lo(0) + hi(0)), 0.5 * (lo(1) + hi(1)));
    assert!(hi(2) - lo(2) == 0.0 && hi(0) - lo(0) > 1.9e-4);
    Segment {
        mesh_bounds_m: [[lo(0), hi(0)], [lo(1), hi(1)], [lo(2), hi(2)]],
        triangles: pm.target.mesh.triangles.len(),
        media,
        workpiece: Workpiece::default(),
        k_finnie_per_pa: k,
        timestep_s: dt,
        steps_per_pass: steps,
        passes: vec![Pass {
            start_m: [cx - 3e-5, cy + 1e-6, hi(2) + media.radius_m() + gap],
            velocity_m_s: [vt, 0.0, -vn],
        }],
        press_force_n: 0.0,
        contact_every: 5,
        thermo_every: steps,
    }
}

fn liggghts_volume_m3(dir: &Path) -> f64 {
    let m = read_vtk(&dir.join(script::WEAR_VTK)).unwrap();
    let w = m.field("wear").unwrap();
    let a = m.field("area").unwrap();
    w.iter().zip(a).map(|(w, a)| w * a).sum()
}

fn run_in(dir: &Path, seg: &Segment) {
    std::fs::write(dir.join(script::INPUT), input_script(seg)).unwrap();
    let stop = AtomicBool::new(false);
    let r = run_engine(
        &engine(),
        dir,
        script::INPUT,
        script::LOG,
        seg.steps_per_pass,
        seg.passes.len(),
        &stop,
        &mut |_| {},
    )
    .unwrap();
    assert!(!r.stopped);
}

#[test]
fn a_single_impact_matches_the_analytic_finnie_integral_within_one_percent() {
    let media = Media {
        friction: 0.0,
        restitution: 1.0,
        ..Media::default()
    };
    let k = 1e-10;
    let tmp = tempfile::tempdir().unwrap();
    for angle_deg in [20.0f64, 45.0, 70.0] {
        let (vt, vn) = (angle_deg.to_radians().cos(), angle_deg.to_radians().sin());
        let dir = tmp.path().join(format!("a{angle_deg}"));
        let seg = flat_segment(&dir, media, k, vt, vn);
        run_in(&dir, &seg);
        let sim = liggghts_volume_m3(&dir);
        let exact = analytic_finnie_m3(&media, &Workpiece::default(), k, vt, vn);
        let ratio = sim / exact;
        eprintln!("impact at {angle_deg} deg: LIGGGHTS {sim:.4e} m^3, analytic {exact:.4e}, ratio {ratio:.5}");
        assert!(exact > 0.0);
        assert!((ratio - 1.0).abs() < 0.01, "{angle_deg} deg: ratio {ratio}");
    }
}

/// A rough test surface: two crossed sines and a finer ripple, um.
fn rough(rows: usize, cols: usize, pitch: f64) -> Vec<f64> {
    (0..rows * cols)
        .map(|k| {
            let (x, y) = ((k % cols) as f64 * pitch, (k / cols) as f64 * pitch);
            1.5 * (x / 23.0).sin() * (y / 31.0).cos() + 0.4 * (x / 7.0 + y / 11.0).sin()
        })
        .collect()
}

fn plan<'a>(engine: &'a EngineCommand, k: f64, passes: usize) -> SegmentPlan<'a> {
    let media = Media::default();
    let action = BarrelMachine::default().action(&media, 30.0).unwrap();
    SegmentPlan {
        engine,
        media,
        workpiece: Workpiece::default(),
        timestep_s: timestep_s(&media, &Workpiece::default(), &action),
        action,
        k_finnie_per_pa: k,
        archard_k_over_h_per_pa: 5e-14,
        max_triangles: 6_000,
        passes: Some(passes),
        engine_budget_s: 10.0,
        cost_per_triangle_step_s: 4e-8,
        seed: 7,
        contact_every: 5,
    }
}

#[test]
fn grid_wear_sums_to_liggghts_total_and_is_linear_in_k() {
    let (rows, cols, pitch) = (50, 50, 3.0);
    let z = rough(rows, cols, pitch);
    let aim = Window {
        row0: 8,
        col0: 8,
        rows: 34,
        cols: 34,
    };
    let e = engine();
    let tmp = tempfile::tempdir().unwrap();
    let stop = AtomicBool::new(false);
    let mut maps = Vec::new();
    for (i, k) in [1e-10, 3e-10].into_iter().enumerate() {
        let r = run_segment(
            &plan(&e, k, 6),
            &z,
            Sampling::square(Shape::new(rows, cols), pitch).unwrap(),
            aim,
            &tmp.path().join(format!("k{i}")),
            &stop,
            &mut |_, _| {},
        )
        .unwrap();
        assert!(r.liggghts_volume_um3 > 0.0, "no wear at all");
        let err = r.volume_relative_error();
        eprintln!(
            "k = {k:e}: LIGGGHTS {:.6e} um^3, grid {:.6e} um^3 (error {err:.2e}), Archard {:.3e} um^3, {} contact samples",
            r.liggghts_volume_um3,
            r.grid_volume_um3,
            volume_um3(&r.archard_um, Pitch::square(pitch).unwrap()),
            r.contacts.samples
        );
        assert!(err.abs() < 0.005, "grid vs LIGGGHTS: {err}");
        assert_eq!(r.unmapped_volume_um3, 0.0);
        assert!(
            r.contacts.samples > 0
                && volume_um3(&r.archard_um, Pitch::square(pitch).unwrap()) > 0.0
        );
        maps.push(r.finnie_um);
    }
    // Same passes, three times k: three times the wear, sample by sample.
    let (a, b) = (&maps[0], &maps[1]);
    let total_a: f64 = a.iter().sum();
    let total_b: f64 = b.iter().sum();
    assert!(
        (total_b / total_a - 3.0).abs() < 3e-3,
        "{}",
        total_b / total_a
    );
    let max_a = a.iter().cloned().fold(0.0, f64::max);
    for (x, y) in a.iter().zip(b) {
        assert!((y - 3.0 * x).abs() <= 3e-3 * 3.0 * max_a, "{x} {y}");
    }
}

#[test]
fn a_flat_surface_wears_without_pattern() {
    let (rows, cols, pitch) = (40, 40, 5.0);
    let model = Model {
        heights_um: vec![0.0; rows * cols],
        rows,
        cols,
        pitch_x_um: pitch,
        pitch_y_um: pitch,
        source: "flat".into(),
    };
    let tmp = tempfile::tempdir().unwrap();
    let opts = FinishOptions {
        patch_um: Some((150.0, 150.0)),
        guard_um: Some(25.0),
        cycles: 1,
        // The one-medium segment on the kinematics' rates (no macro run).
        machine_run: None,
        passes: Some(60),
        max_triangles: 6_000,
        impact_angle_deg: 30.0,
        // A constant that wears the flat by a fraction of a micrometre in the process time.
        k_finnie_per_pa: Some(1e-18),
        // The DEM's own map is what this test looks at (the contact field of a flat is
        // uniform by construction: field::tests).
        wear_model: WearModel::SampledMap,
        ..Default::default()
    };
    let stop = AtomicBool::new(false);
    let s = finish_record(&model, &opts, tmp.path(), &stop, &mut |l| eprintln!("{l}")).unwrap();
    let wear = surfstream_io::npy::read_npy_f64(tmp.path().join("wear.npy")).unwrap();
    let (r, c) = (wear.rows, wear.cols);
    let total: f64 = wear.data.iter().sum();
    assert!(total > 0.0);
    // No position pattern: each quadrant holds a fair share (random tracks: within 2x).
    let mut q = [0.0; 4];
    for (k, w) in wear.data.iter().enumerate() {
        let (i, j) = (k / c, k % c);
        q[(2 * i / r) * 2 + 2 * j / c] += w;
    }
    eprintln!("quadrant shares {:?}", q.map(|x| x / total));
    for x in q {
        assert!(x / total > 0.125 && x / total < 0.5, "{q:?}");
    }
    // No mesh pattern: even and odd rows and columns wear alike (a triangle-diagonal artefact
    // would alternate).
    let par = |f: &dyn Fn(usize) -> bool| -> f64 {
        wear.data
            .iter()
            .enumerate()
            .filter(|(k, _)| f(*k))
            .map(|(_, w)| w)
            .sum::<f64>()
            / total
    };
    let even_cols = par(&|k| (k % c) % 2 == 0);
    let even_rows = par(&|k| (k / c) % 2 == 0);
    eprintln!("even columns {even_cols:.3}, even rows {even_rows:.3}");
    assert!((even_cols - 0.5).abs() < 0.05 && (even_rows - 0.5).abs() < 0.05);
    // The worn flat stays flat at the scale of the wear: its roughness is a fraction of the
    // mean depth removed plus what the media's tracks leave.
    assert!(s.volume_check.as_ref().unwrap().relative_error < 0.005);
    for f in [
        "wear.npy",
        "wear_finnie.npy",
        "wear_archard.npy",
        "worn.npy",
        "worn.x3p",
        "finish.json",
        "finish.html",
        "cycle_01/in.liggghts",
        "cycle_01/log.liggghts",
        "cycle_01/patch.stl",
    ] {
        assert!(tmp.path().join(f).is_file(), "{f} missing");
    }
}

#[test]
fn a_sinusoidal_surface_loses_its_peaks_first() {
    let (rows, cols, pitch) = (60, 60, 4.0);
    let heights_um: Vec<f64> = (0..rows * cols)
        .map(|k| {
            let (x, y) = ((k % cols) as f64 * pitch, (k / cols) as f64 * pitch);
            2.0 * (std::f64::consts::TAU * x / 60.0).sin()
                * (std::f64::consts::TAU * y / 60.0).sin()
        })
        .collect();
    let model = Model {
        heights_um,
        rows,
        cols,
        pitch_x_um: pitch,
        pitch_y_um: pitch,
        source: "sine".into(),
    };
    let tmp = tempfile::tempdir().unwrap();
    let opts = FinishOptions {
        patch_um: Some((180.0, 180.0)),
        guard_um: Some(20.0),
        cycles: 2,
        // The one-medium segment on the kinematics' rates (no macro run).
        machine_run: None,
        passes: Some(12),
        max_triangles: 6_000,
        calibrate: Some(Calibration::Sa {
            before_um: Some(1.0),
            after_um: 0.75,
        }),
        ..Default::default()
    };
    let stop = AtomicBool::new(false);
    let rec = finish_record(&model, &opts, tmp.path(), &stop, &mut |l| eprintln!("{l}")).unwrap();
    // The node's report (run.json) is finish.json without the curves, cycles and macro run,
    // plus `dir`:
    // the typed record against the same value edited by key.
    let mut by_key = surfstream_core::record::to_value(&rec).unwrap();
    for k in ["abbott_before", "abbott_after", "cycles", "macro"] {
        by_key.as_object_mut().unwrap().remove(k).unwrap();
    }
    by_key["dir"] = "finish".into();
    let report =
        surfstream_core::record::to_value(&FinishReport::of(rec.clone(), "finish")).unwrap();
    assert_eq!(
        serde_json::to_string_pretty(&report).unwrap(),
        serde_json::to_string_pretty(&by_key).unwrap()
    );
    assert!(!report["contact_field"].is_null() && !report["calibration"].is_null());
    let (b, a) = (&rec.before, &rec.after);
    let share = |after: f64, before: f64| 1.0 - after / before;
    let (sa, spk, svk) = (share(a.sa, b.sa), share(a.spk, b.spk), share(a.svk, b.svk));
    eprintln!(
        "Sa {} -> {}, Spk {} -> {} ({spk:.2}), Svk {} -> {} ({svk:.2})",
        b.sa, a.sa, b.spk, a.spk, b.svk, a.svk
    );
    assert!(sa > 0.01, "the calibration did not wear the surface");
    assert!(spk > svk + 0.05, "peaks did not go first");
    // The contact field (the default) reaches the target within the tolerance, fitted once.
    assert_eq!(rec.wear_model.as_deref(), Some("contact-field"));
    let c = rec.calibration.as_ref().unwrap();
    assert_eq!(c.reached, Some(true), "{c:?}");
    assert!(c.relative_error.unwrap().abs() * 100.0 <= CALIBRATION_TOLERANCE_PERCENT);
    let auc = rec
        .contact_field
        .as_ref()
        .unwrap()
        .check_mean
        .auc_gap_predicts_worn
        .unwrap();
    assert!(
        auc > 0.5,
        "the contact field does not predict where the DEM wore: AUC {auc}"
    );
    let (_, p) = surface_params(
        &surfstream_io::npy::read_npy_f64(tmp.path().join("worn.npy"))
            .unwrap()
            .data,
        Sampling::square(Shape::new(45, 45), pitch).unwrap(),
    )
    .unwrap();
    assert!((p.sa - a.sa).abs() < 1e-9);
}

#[test]
fn with_a_macro_record_the_cycles_run_micro_passes_on_the_tolerance_mesh() {
    use surfstream_finish::machine::{
        ContactSample, ContactStatistics, MacroContacts, Percentiles, Softening,
    };
    let (rows, cols, pitch) = (40, 40, 4.0);
    let heights_um: Vec<f64> = (0..rows * cols)
        .map(|k| {
            let (x, y) = ((k % cols) as f64 * pitch, (k / cols) as f64 * pitch);
            2.0 * (std::f64::consts::TAU * x / 60.0).sin()
                * (std::f64::consts::TAU * y / 60.0).sin()
        })
        .collect();
    let model = Model {
        heights_um,
        rows,
        cols,
        pitch_x_um: pitch,
        pitch_y_um: pitch,
        source: "sine".into(),
    };
    let sample = |vn: f64, vt: f64, f: f64, enduring: bool| ContactSample {
        normal_speed_m_s: vn,
        tangential_speed_m_s: vt,
        normal_force_n: f,
        duration_s: if enduring { 1e-4 } else { 0.0 },
        enduring,
    };
    let p = |v: f64| Percentiles {
        p10: v,
        p50: v,
        p90: v,
    };
    // A small macro record written here: the contact rate and sliding work the laws run at,
    // the samples the micro passes draw.
    let macro_record = MacroContacts {
        engine: "liggghts".into(),
        machine: "test".into(),
        media_count: 100,
        simulated_s: 0.1,
        settle_s: 0.05,
        timestep_s: 1e-6,
        region_area_mm2: 1.0,
        contacts: ContactStatistics {
            count: 3,
            impacts: 2,
            enduring: 1,
            rate_per_mm2_s: 50.0,
            enduring_normal_force_n: p(0.02),
            sliding_work_j_per_mm2_s: 1e-3,
            ..Default::default()
        },
        samples: vec![
            sample(0.1, 0.3, 0.0, false),
            sample(0.2, 0.5, 0.0, false),
            sample(0.01, 0.3, 0.02, true),
        ],
        softening: Softening {
            media_youngs_modulus_pa: 1e8,
            real_youngs_modulus_pa: 3e11,
            timestep_s: 1e-6,
            rayleigh_time_s: 1e-5,
            trusted: Vec::new(),
            not_trusted: Vec::new(),
        },
        media_lost: 0,
        partial: false,
        cost: Default::default(),
        seed: 1,
        media: None,
    };
    let tmp = tempfile::tempdir().unwrap();
    let opts = FinishOptions {
        patch_um: Some((100.0, 100.0)),
        guard_um: Some(20.0),
        cycles: 2,
        passes: Some(6),
        jobs: 2,
        max_triangles: 3_000,
        macro_contacts: Some(macro_record),
        ..Default::default()
    };
    let stop = AtomicBool::new(false);
    let rec = finish_record(&model, &opts, tmp.path(), &stop, &mut |l| eprintln!("{l}")).unwrap();
    assert!(!rec.partial);
    let text = std::fs::read_to_string(tmp.path().join("finish.json")).unwrap();
    let json: serde_json::Value = serde_json::from_str(&text).unwrap();
    let triangles = json["patch"]["model"]["surface_triangles"]
        .as_u64()
        .unwrap();
    assert!(triangles > 0, "{}", json["patch"]);
    assert!(json["patch"]["model"]["max_error_over_sq"]
        .as_f64()
        .unwrap()
        .is_finite());
    assert!(json["cycle_path"]
        .as_str()
        .unwrap()
        .starts_with("micro passes"));
    let cycles = json["cycles"].as_array().unwrap();
    assert_eq!(cycles.len(), 2);
    for c in cycles {
        let m = &c["micro"];
        assert_eq!(
            m["impacts"].as_u64().unwrap() + m["sliding"].as_u64().unwrap(),
            6,
            "{m}"
        );
        assert!(m["processes"].as_array().is_some_and(|p| !p.is_empty()));
        assert_eq!(c["mesh_block_stride"], 1);
    }
    // The micro passes' Finnie map fed the contact field's table: it holds their impacts.
    let table = &rec.contact_field.as_ref().unwrap().table;
    let impacts: u64 = cycles
        .iter()
        .map(|c| c["micro"]["impacts"].as_u64().unwrap())
        .sum();
    assert!(impacts > 0);
    assert_eq!(table.impacts as u64, impacts);
    assert!(rec.after.sa < rec.before.sa, "the surface did not wear");
    // The Finnie law's rate counts the impacts (2 of the 3 contacts): the enduring one wears
    // through the sliding work, not as an impact too.
    let rate = json["wear_laws"]["impact_rate_per_m2_s"].as_f64().unwrap();
    assert!(
        (rate / (50.0 * 2.0 / 3.0 * 1e6) - 1.0).abs() < 1e-12,
        "{rate}"
    );
    assert_eq!(json["setting"]["action_used"], false);
}
