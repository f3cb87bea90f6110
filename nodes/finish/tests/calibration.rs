//! The contact-field calibration on a demo-like specimen, without the engine: the wear per
//! contact is the table recorded by the DEM on the demo run (tests/data/demo_wear_table.json,
//! from `surfstream finish out/demo -o out/finish-demo --patch-um 300 --time-budget-s 300
//! --cycles 6 --calibrate 1.272,0.565`, finish.json `contact_field.table`), the specimen a
//! synthetic rough surface of the demo's size, pitch and Sa. The fit must reach the paper's
//! ratio of Sa within the tolerance, and the peaks must go first.

use surfstream_core::{Sampling, Shape};
use surfstream_finish::field::{
    ball_gap_um, extrapolate, impact_rate_per_m2_s, wear_to_target, ApproachDistribution,
    ApproachPhysics, FieldGrid, WearTable,
};
use surfstream_finish::run::{surface_params, CALIBRATION_TOLERANCE_PERCENT};
use surfstream_finish::setting::{
    BarrelKinematics, BarrelMachine, Media, MediaPhysics, Workpiece, DEFAULT_IMPACT_ANGLE_DEG,
};

/// A rough surface: random-phase waves with amplitudes falling as 1/wavelength^-1 between
/// 6 and 150 um, scaled to Sa = `sa_um` (deterministic).
fn demo_like(rows: usize, cols: usize, pitch: f64, sa_um: f64) -> Vec<f64> {
    let mut seed: u64 = 0x2545_f491_4f6c_dd1d;
    let mut rnd = || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        (seed >> 11) as f64 / (1u64 << 53) as f64
    };
    let waves: Vec<(f64, f64, f64, f64)> = (0..120)
        .map(|_| {
            let wl = 6.0 * (150.0f64 / 6.0).powf(rnd());
            let dir = rnd() * std::f64::consts::PI;
            let k = std::f64::consts::TAU / wl;
            (
                k * dir.cos(),
                k * dir.sin(),
                rnd() * std::f64::consts::TAU,
                wl,
            )
        })
        .collect();
    let mut z: Vec<f64> = (0..rows * cols)
        .map(|i| {
            let (x, y) = ((i % cols) as f64 * pitch, (i / cols) as f64 * pitch);
            waves
                .iter()
                .map(|(kx, ky, ph, wl)| wl.sqrt() * (kx * x + ky * y + ph).sin())
                .sum()
        })
        .collect();
    let m = z.iter().sum::<f64>() / z.len() as f64;
    let sa = z.iter().map(|v| (v - m).abs()).sum::<f64>() / z.len() as f64;
    for v in &mut z {
        *v = (*v - m) * sa_um / sa;
    }
    z
}

#[test]
fn the_recorded_wear_table_calibrates_a_demo_like_patch_to_the_papers_sa() {
    let text = std::fs::read_to_string(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/demo_wear_table.json"),
    )
    .unwrap();
    let table: WearTable = serde_json::from_str(&text).unwrap();
    let media = Media::default();
    let part = Workpiece::default();
    let action = BarrelMachine::default()
        .action(&media, DEFAULT_IMPACT_ANGLE_DEG)
        .unwrap();
    let press = media.load_n(action.pressure_pa) + media.mass_kg() * action.acceleration_m_s2;
    let dist = ApproachDistribution::of(&media, &part, &action, press);
    // The table was binned over the same reach (same setting).
    let last = table.bins.last().unwrap().gap_to_um;
    assert!(
        (last / dist.max_um() - 1.0).abs() < 1e-9,
        "{last} vs {}",
        dist.max_um()
    );

    // The demo's patch: 368 x 368 at 0.8148 um (300 um), with a 45 um guard band each side.
    let (n, guard, pitch) = (368usize, 55usize, 0.8148);
    let side = n + 2 * guard;
    let z = demo_like(side, side, pitch, 1.316);
    let crop = |f: &[f64]| -> Vec<f64> {
        (guard..guard + n)
            .flat_map(|r| f[r * side + guard..r * side + guard + n].to_vec())
            .collect()
    };
    let at = |rows: usize, cols: usize| Sampling::square(Shape::new(rows, cols), pitch).unwrap();
    let params = |f: &[f64]| surface_params(&crop(f), at(n, n)).unwrap().1;
    let before = params(&z);
    let target = before.sa * 0.565 / 1.272;
    let g = FieldGrid {
        sampling: at(side, side),
        radius_um: media.radius_m() * 1e6,
        step_depth_um: surfstream_finish::field::STEP_DEPTH_UM,
    };
    let impacts =
        impact_rate_per_m2_s(&media, &action) * (n as f64 * pitch).powi(2) * 1e-12 * 300.0;
    let mut h = z.clone();
    let mut wear = vec![0.0; h.len()];
    let (used, e, reached) = wear_to_target(
        &mut h,
        &mut wear,
        g,
        &dist,
        &table,
        impacts * 1e8,
        target,
        &std::sync::atomic::AtomicBool::new(false),
        |f| Ok(params(f).sa),
    )
    .unwrap();
    let after = params(&h);
    eprintln!(
        "scale {:.4e}, {} steps; Sa {:.3} -> {:.3} (target {:.3}), Sq {:.3} -> {:.3}, Sz {:.3} -> {:.3}, Spk {:.3} -> {:.3}, Svk {:.3} -> {:.3}",
        used / impacts, e.steps, before.sa, after.sa, target, before.sq, after.sq, before.sz, after.sz, before.spk, after.spk, before.svk, after.svk
    );
    assert!(reached, "the target Sa was not reached");
    assert!(
        (after.sa / target - 1.0).abs() * 100.0 <= CALIBRATION_TOLERANCE_PERCENT,
        "{} vs {target}",
        after.sa
    );
    // Peaks go first; Sq and Sz fall with Sa.
    let share = |b: f64, a: f64| 1.0 - a / b;
    assert!(share(before.spk, after.spk) > share(before.svk, after.svk) + 0.2);
    assert!(after.sq < before.sq && after.sz < before.sz);
    // The plain extrapolation at the fitted scale lands on the same surface.
    let mut h2 = z.clone();
    let mut w2 = vec![0.0; h2.len()];
    extrapolate(&mut h2, &mut w2, g, &dist, &table, impacts, used / impacts);
    assert!((params(&h2).sa / after.sa - 1.0).abs() < 1e-6);
    // The contact field of the worn patch: more of it in reach than before.
    let reach = |f: &[f64]| {
        let gap = crop(&ball_gap_um(f, g.sampling, g.radius_um));
        gap.iter().filter(|v| **v <= dist.max_um()).count() as f64 / gap.len() as f64
    };
    assert!(reach(&h) > reach(&z), "{} vs {}", reach(&h), reach(&z));
}

/// The prediction on a demo-like patch with the DEM's recorded table (impacts) and the
/// sliding law, fitted once on Sa: a different macro run (sliding work, forces of the
/// enduring contacts) gives another prediction at the same Sa, and both differ from the
/// plateau baseline; the series is monotone in time.
#[test]
fn the_prediction_follows_the_macro_statistics_and_not_only_the_calibration() {
    use surfstream_finish::laws::{
        advance, fit_scale, plateau_cut, plateau_level_for_sa, series, series_times_s, ImpactLaw,
        SlidingLaw, WearLaw,
    };
    let text = std::fs::read_to_string(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/demo_wear_table.json"),
    )
    .unwrap();
    let table: WearTable = serde_json::from_str(&text).unwrap();
    let media = Media::default();
    let part = Workpiece::default();
    let action = BarrelMachine::default()
        .action(&media, DEFAULT_IMPACT_ANGLE_DEG)
        .unwrap();
    let press = media.load_n(action.pressure_pa) + media.mass_kg() * action.acceleration_m_s2;
    let dist = ApproachDistribution::of(&media, &part, &action, press);
    let (n, guard, pitch) = (160usize, 30usize, 0.8148);
    let side = n + 2 * guard;
    let z = demo_like(side, side, pitch, 1.316);
    let crop = |f: &[f64]| -> Vec<f64> {
        (guard..guard + n)
            .flat_map(|r| f[r * side + guard..r * side + guard + n].to_vec())
            .collect()
    };
    let at = |rows: usize, cols: usize| Sampling::square(Shape::new(rows, cols), pitch).unwrap();
    let params = |f: &[f64]| surface_params(&crop(f), at(n, n)).unwrap().1;
    let target = params(&z).sa * 0.565 / 1.272;
    let g = FieldGrid {
        sampling: at(side, side),
        radius_um: media.radius_m() * 1e6,
        step_depth_um: surfstream_finish::field::STEP_DEPTH_UM,
    };
    let impacts_per_s = impact_rate_per_m2_s(&media, &action) * (n as f64 * pitch).powi(2) * 1e-12;
    // Two macro runs: (sliding work J/(m^2 s), enduring normal forces N).
    let laws_of = |work: f64, forces: &[f64]| {
        vec![
            WearLaw::Impacts(ImpactLaw {
                dist: dist.clone(),
                table: table.clone(),
                impacts_per_s,
                mean_depth_per_impact_um: None,
            }),
            WearLaw::Sliding(SlidingLaw::new(5e-14, work, forces, &media, &part)),
        ]
    };
    let stop = std::sync::atomic::AtomicBool::new(false);
    let predict = |laws: &[WearLaw]| {
        let (s, ok, _) =
            fit_scale(&z, g, laws, 300.0, 1e8, target, &stop, |f| Ok(params(f).sa)).unwrap();
        assert!(ok, "target not reached");
        let (mut h, mut w) = (z.clone(), vec![0.0; z.len()]);
        advance(&mut h, &mut w, g, laws, 300.0, s);
        (s, params(&h))
    };
    let a = laws_of(1.9e3, &[0.036]);
    let (s_a, p_a) = predict(&a);
    let (s_b, p_b) = predict(&laws_of(5.0e3, &[0.005, 0.017, 0.05]));
    eprintln!(
        "scale {s_a:.3e} vs {s_b:.3e}; Sq {:.4} vs {:.4}, Sz {:.4} vs {:.4}, Spk {:.4} vs {:.4}",
        p_a.sq, p_b.sq, p_a.sz, p_b.sz, p_a.spk, p_b.spk
    );
    assert!((p_a.sa / target - 1.0).abs() < 1e-3 && (p_b.sa / target - 1.0).abs() < 1e-3);
    assert!((s_a / s_b - 1.0).abs() > 0.05, "{s_a} {s_b}");
    assert!(
        (p_a.sq - p_b.sq).abs() > 1e-4 || (p_a.sz - p_b.sz).abs() > 1e-3,
        "the same surface from two macro runs"
    );
    // The plateau baseline at the same Sa: another surface.
    let level = plateau_level_for_sa(&z, target, |f| Ok(params(f).sa))
        .unwrap()
        .unwrap();
    let p_plateau = params(&plateau_cut(&z, level).0);
    assert!((p_plateau.sa / target - 1.0).abs() < 1e-6);
    assert!(
        (p_plateau.sz - p_a.sz).abs() > 0.1,
        "{} vs {}",
        p_plateau.sz,
        p_a.sz
    );
    // The series falls with time and meets the fit at 300 s.
    let times = series_times_s(600.0, None).unwrap();
    let mut sa = vec![];
    series(&z, g, &a, s_a, &times, |_, w| {
        sa.push(params(&w.heights_um).sa);
        Ok(())
    })
    .unwrap();
    assert!(sa.windows(2).all(|p| p[1] < p[0]), "{sa:?}");
    let at_300 = times.iter().position(|t| *t == 300.0).unwrap();
    // The series stops at every time (other step boundaries than the fit): close, not equal.
    assert!(
        (sa[at_300] / target - 1.0).abs() < 1e-2,
        "{} vs {target}",
        sa[at_300]
    );
}
