//! Registration on sparse texture: a polished, nearly flat field whose only features are a few
//! slanted scratches and pits, cut into an overlapping pair at a known sub-pixel offset. The
//! NCC peak of such a pair is elongated along a slant; a sub-pixel fit along x and y apart
//! lands on the ridge's crossing of the sample row, not on its top (0.3-0.5 px errors before
//! the cross term was fitted, docs/registration.md).

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use surfstream_core::raster::{RasterView, Shape};
use surfstream_matcher::{register_pair, PhaseParams};

/// A scratch: a Gaussian groove along a straight line, or a pit (a round Gaussian dip).
struct Feature {
    x: f64,
    y: f64,
    /// Direction of the groove (radians); `None` for a pit.
    angle: Option<f64>,
    width_px: f64,
    depth_um: f64,
}

impl Feature {
    /// The height at a continuous position, so a tile is sampled at any sub-pixel origin.
    fn at(&self, x: f64, y: f64) -> f64 {
        let (dx, dy) = (x - self.x, y - self.y);
        let d2 = match self.angle {
            Some(a) => {
                let across = -dx * a.sin() + dy * a.cos();
                across * across
            }
            None => dx * dx + dy * dy,
        };
        -self.depth_um * (-d2 / (2.0 * self.width_px * self.width_px)).exp()
    }
}

/// Tile of `n x n` px whose pixel (0, 0) sits at (x0, y0) of the field: the features, the
/// tile's own piston and tilt, and white noise.
fn tile(features: &[Feature], x0: f64, y0: f64, n: usize, rng: &mut ChaCha8Rng) -> Vec<f32> {
    noisy_tile(features, x0, y0, n, rng, 0.002)
}

/// [`tile`] with white noise of standard deviation `noise_um`.
fn noisy_tile(
    features: &[Feature],
    x0: f64,
    y0: f64,
    n: usize,
    rng: &mut ChaCha8Rng,
    noise_um: f64,
) -> Vec<f32> {
    let noise = Normal::new(0.0, noise_um).unwrap();
    let piston = rng.gen_range(-2.0..2.0);
    let (tx, ty) = (rng.gen_range(-0.002..0.002), rng.gen_range(-0.002..0.002));
    let mut out = Vec::with_capacity(n * n);
    for r in 0..n {
        for c in 0..n {
            let (x, y) = (x0 + c as f64, y0 + r as f64);
            let z: f64 = features.iter().map(|f| f.at(x, y)).sum();
            out.push((z + piston + tx * c as f64 + ty * r as f64 + noise.sample(rng)) as f32);
        }
    }
    out
}

/// Errors (px) of 16 horizontal and vertical pairs of 128 px tiles at 20 % overlap, each with
/// three slanted scratches and two pits crossing the overlap, and a 0-3 px stage error.
fn pair_errors() -> Vec<(Option<f64>, Option<f64>)> {
    let n = 128;
    let step = 102.0;
    let mut errors = Vec::new();
    for seed in 0..16u64 {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let horizontal = seed % 2 == 0;
        // The overlap strip's centre, in the field (a's origin at (0, 0)).
        let (sx, sy) = if horizontal {
            (step + 13.0, 64.0)
        } else {
            (64.0, step + 13.0)
        };
        // Two scratches slanted one way, one the other: together they fix both axes.
        let mut features: Vec<Feature> = [1.0, 1.0, -1.0]
            .into_iter()
            .map(|sign| Feature {
                x: sx + rng.gen_range(-8.0..8.0) * if horizontal { 1.0 } else { 5.0 },
                y: sy + rng.gen_range(-8.0..8.0) * if horizontal { 5.0 } else { 1.0 },
                angle: Some(rng.gen_range(0.3..1.2) * sign),
                width_px: rng.gen_range(0.8..1.6),
                depth_um: rng.gen_range(0.05..0.3),
            })
            .collect();
        for _ in 0..2 {
            features.push(Feature {
                x: rng.gen_range(0.0..230.0),
                y: rng.gen_range(0.0..230.0),
                angle: None,
                width_px: rng.gen_range(1.0..2.5),
                depth_um: rng.gen_range(0.05..0.2),
            });
        }
        let err = [rng.gen_range(-3.0..3.0), rng.gen_range(-3.0..3.0)];
        let nominal = if horizontal { [step, 0.0] } else { [0.0, step] };
        let truth = [nominal[0] + err[0], nominal[1] + err[1]];
        let a = tile(&features, 0.0, 0.0, n, &mut rng);
        let b = tile(&features, truth[0], truth[1], n, &mut rng);
        let r = register_pair(
            RasterView::new(&a, Shape::new(n, n)).unwrap(),
            RasterView::new(&b, Shape::new(n, n)).unwrap(),
            nominal,
            &PhaseParams::default(),
        );
        // A refusal (a ridge where the scratches run nearly parallel) is an answer the global
        // solve can live with, with its error across the ridge; a wrong offset is not.
        let across = r.directional.map(|d| {
            ((d.offset_px[0] - truth[0]) * d.normal[0] + (d.offset_px[1] - truth[1]) * d.normal[1])
                .abs()
        });
        errors.push((
            r.offset_px
                .map(|o| (o[0] - truth[0]).hypot(o[1] - truth[1])),
            across,
        ));
    }
    errors
}

/// Measured: with the cross term 15 of 16 pairs within 0.1 px (median 0.03 px); fitting x and
/// y apart, 5 of 16 (median 0.14 px). The one pair beyond (0.67 px either way, NCC peak
/// roundness 0.13 on the 3 x 3 stencil, 0.04 measured 2-3 px out along the ridge) is a
/// scratch crossing that leaves the peak nearly a ridge: it is now refused with a
/// one-direction answer (docs/registration.md).
#[test]
fn slanted_scratches_on_a_polished_field_register_within_a_tenth_of_a_pixel() {
    let all = pair_errors();
    let e: Vec<f64> = all.iter().filter_map(|p| p.0).collect();
    eprintln!("errors px: {e:.3?}");
    for (k, p) in all.iter().enumerate() {
        match p {
            (Some(_), _) => {}
            (None, Some(across)) => assert!(*across < 0.1, "pair {k}: {across} px across"),
            (None, None) => panic!("pair {k}: neither an offset nor a one-direction answer"),
        }
    }
    assert!(e.len() >= 14, "{} of {} pairs answered", e.len(), all.len());
    let within = e.iter().filter(|&&v| v <= 0.1).count();
    assert!(within >= 14, "{within} of {} pairs within 0.1 px", e.len());
    assert!(
        e.iter().all(|&v| v < 1.0),
        "no pair wrong by a pixel or more"
    );
}

/// One pair of 128 px tiles at 20 % overlap whose overlap a single long scratch crosses at
/// `angle` (radians from x), with white noise only: the texture fixes the offset across the
/// scratch and not along it. Returns the registration and the true offset.
fn ridge_pair(
    seed: u64,
    horizontal: bool,
    angle: f64,
) -> (surfstream_matcher::PairRegistration, [f64; 2]) {
    let n = 128;
    let step = 102.0;
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (sx, sy) = if horizontal {
        (step + 13.0, 64.0)
    } else {
        (64.0, step + 13.0)
    };
    let features = [Feature {
        x: sx + rng.gen_range(-3.0..3.0),
        y: sy + rng.gen_range(-3.0..3.0),
        angle: Some(angle),
        width_px: rng.gen_range(0.8..1.6),
        depth_um: rng.gen_range(0.1..0.3),
    }];
    let err = [rng.gen_range(-3.0..3.0), rng.gen_range(-3.0..3.0)];
    let nominal = if horizontal { [step, 0.0] } else { [0.0, step] };
    let truth = [nominal[0] + err[0], nominal[1] + err[1]];
    let a = tile(&features, 0.0, 0.0, n, &mut rng);
    let b = tile(&features, truth[0], truth[1], n, &mut rng);
    let r = register_pair(
        RasterView::new(&a, Shape::new(n, n)).unwrap(),
        RasterView::new(&b, Shape::new(n, n)).unwrap(),
        nominal,
        &PhaseParams::default(),
    );
    (r, truth)
}

/// A lone scratch across the overlap: no offset (nothing fixes it along the scratch), but a
/// one-direction answer whose normal is across the scratch and whose component along it is
/// the truth's.
#[test]
fn a_lone_scratch_gives_a_constraint_across_it_and_none_along() {
    let mut answered = 0;
    let cases = [
        (true, 0.0),
        (true, 0.3),
        (true, -0.45),
        (false, std::f64::consts::FRAC_PI_2),
        (false, 1.2),
        (false, 2.0),
    ];
    for (k, &(horizontal, angle)) in cases.iter().enumerate() {
        for seed in 0..3u64 {
            let (r, truth) = ridge_pair(100 + 10 * k as u64 + seed, horizontal, angle);
            assert!(
                r.offset_px.is_none(),
                "{angle}: a ridge gave a 2-D answer {r:?}"
            );
            let Some(d) = r.directional else {
                eprintln!(
                    "{horizontal} {angle} seed {seed}: no directional answer: {:?}",
                    r.rejection
                );
                continue;
            };
            answered += 1;
            let across = [-angle.sin(), angle.cos()];
            let cos = (d.normal[0] * across[0] + d.normal[1] * across[1]).abs();
            assert!(
                cos > 0.97,
                "{angle}: normal {:?} vs across {across:?}",
                d.normal
            );
            let e = [d.offset_px[0] - truth[0], d.offset_px[1] - truth[1]];
            let e_across = e[0] * d.normal[0] + e[1] * d.normal[1];
            eprintln!(
                "{horizontal} {angle:.2} seed {seed}: across error {e_across:.3} px, curvature {:?}",
                d.curvature_per_px2
            );
            assert!(e_across.abs() < 0.2, "{angle}: across error {e_across} px");
            // Nothing along: the curvature across is many times the one along.
            assert!(
                d.curvature_per_px2[1] < 0.3 * d.curvature_per_px2[0],
                "{d:?}"
            );
        }
    }
    assert!(
        answered >= 17,
        "{answered} of 18 ridge pairs gave a one-direction answer"
    );
}

/// The one-direction answers of ridge pairs, given to the global solve with the ordinary
/// links, place a row of tiles across the scratches as the truth does; along them the stage
/// does, and the solve says so.
#[test]
fn a_solve_with_ridge_links_recovers_the_offsets_across() {
    use surfstream_matcher::{solve_positions_anisotropic, AnisotropicLink, SolveParams};
    // Three tiles in a row, each pair crossed by one scratch 0.1 rad off x (no other texture): the
    // pairs fix y only.
    let mut truth = vec![[0.0, 0.0]];
    let mut ridges = Vec::new();
    let mut normals = Vec::new();
    for k in 0..2usize {
        let (r, t) = ridge_pair(300 + k as u64, true, 0.1);
        let d = r
            .directional
            .expect("a ridge pair gives a one-direction answer");
        let prev = truth[k];
        truth.push([prev[0] + t[0], prev[1] + t[1]]);
        ridges.push(AnisotropicLink::across(
            k,
            k + 1,
            d.offset_px,
            d.normal,
            0.05,
        ));
        normals.push(d.normal);
    }
    let stage: Vec<[f64; 2]> = (0..3).map(|i| [102.0 * i as f64, 0.0]).collect();
    let sol = solve_positions_anisotropic(&stage, &[], &ridges, &SolveParams::default()).unwrap();
    for (k, n) in normals.iter().enumerate() {
        let p = &sol.positions_px;
        let got = [p[k + 1][0] - p[k][0], p[k + 1][1] - p[k][1]];
        let want = [truth[k + 1][0] - truth[k][0], truth[k + 1][1] - truth[k][1]];
        let across = (got[0] - want[0]) * n[0] + (got[1] - want[1]) * n[1];
        assert!(across.abs() < 0.2, "pair {k}: across error {across} px");
        // Along the scratch: the stage's offset (102, 0), not the truth's.
        let along = (got[0] - 102.0) * n[1] - got[1] * n[0];
        assert!(along.abs() < 0.05, "pair {k}: along {along} px");
    }
    assert_eq!(sol.registered_directions, vec![1, 1, 1]);
    assert!(sol
        .stage_direction
        .iter()
        .all(|d| d.is_some_and(|d| d[0].abs() > 0.95)));
}

/// A strip holding one isolated pit in strong noise: the true match measures an NCC well below
/// `min_ncc` (0.5) but stands out from every other candidate, and is answered, never by a pit
/// diameter wrong (measured up to 1.19 px at NCC 0.24: much worse than the 0.22 px of
/// bench_sparse's lone features); the same tile against noise alone is refused. Not tested
/// because it fails: a tile holding a *different* lone pit can be matched pit to pit (NCC 0.30
/// in one of 8 pairs), see docs/registration.md, "What is left".
#[test]
fn a_lone_pit_in_noise_is_answered_below_min_ncc_and_noise_alone_is_not() {
    let n = 128;
    let step = 102.0;
    let mut answered = 0;
    for seed in 0..8u64 {
        let mut rng = ChaCha8Rng::seed_from_u64(500 + seed);
        let pit = |rng: &mut ChaCha8Rng| Feature {
            x: step + 13.0 + rng.gen_range(-4.0..4.0),
            y: rng.gen_range(20.0..108.0),
            angle: None,
            width_px: rng.gen_range(1.5..2.5),
            depth_um: rng.gen_range(0.15..0.25),
        };
        let features = [pit(&mut rng)];
        let elsewhere: [Feature; 0] = [];
        let err = [rng.gen_range(-3.0..3.0), rng.gen_range(-3.0..3.0)];
        let truth = [step + err[0], err[1]];
        let a = noisy_tile(&features, 0.0, 0.0, n, &mut rng, 0.02);
        let b = noisy_tile(&features, truth[0], truth[1], n, &mut rng, 0.02);
        let unrelated = noisy_tile(&elsewhere, truth[0], truth[1], n, &mut rng, 0.02);
        fn view(t: &[f32], n: usize) -> RasterView<'_, f32> {
            RasterView::new(t, Shape::new(n, n)).unwrap()
        }
        let p = PhaseParams::default();
        let r = register_pair(view(&a, n), view(&b, n), [step, 0.0], &p);
        eprintln!(
            "seed {seed}: ncc {:.3} offset {:?} truth {truth:?}",
            r.ncc, r.offset_px
        );
        if let Some(o) = r.offset_px {
            answered += 1;
            let e = (o[0] - truth[0]).hypot(o[1] - truth[1]);
            assert!(e < 1.5, "seed {seed}: {e} px wrong");
            assert!(
                r.ncc < p.min_ncc,
                "seed {seed}: the test wants NCC below min_ncc"
            );
        }
        let u = register_pair(view(&a, n), view(&unrelated, n), [step, 0.0], &p);
        assert!(
            u.offset_px.is_none(),
            "seed {seed}: unrelated pair answered {u:?}"
        );
    }
    assert!(answered >= 6, "{answered} of 8 lone-pit pairs answered");
}

/// A periodic texture (pits on a lattice of 70 px along x) seen through a full-width 10 %
/// strip: its aliases at +-70 px along the strip score like the truth, but no stage error
/// within `max_shift_px` (30 px) reaches them. Before the candidates beyond reach were
/// dropped, each alias counted as a rival (the pair refused as ambiguous) or ranked first
/// (refused as a shift beyond the limit): the pills specimen lost two pairs that way
/// (docs/registration.md). Measured: 8 of 8 answered, 7 within 0.02 px, one at 0.65 px (its pits
/// line up along a slant); before (commit e47e0b3), 3 of 8 were refused as ambiguous, the alias
/// ranked first and the truth counted as its rival.
#[test]
fn aliases_of_a_periodic_texture_beyond_the_stage_range_do_not_void_the_answer() {
    let n = 200;
    let step = 180.0;
    let period = 70.0;
    let mut answered = 0;
    for seed in 0..8u64 {
        let mut rng = ChaCha8Rng::seed_from_u64(700 + seed);
        // One cell's pits, repeated along x; most of them in the overlap strip (y 180-200).
        let cell: Vec<(f64, f64, f64, f64)> = (0..6)
            .map(|_| {
                (
                    rng.gen_range(0.0..period),
                    rng.gen_range(165.0..215.0),
                    rng.gen_range(1.5..3.5),
                    rng.gen_range(0.05..0.2),
                )
            })
            .collect();
        let features: Vec<Feature> = (-2..6)
            .flat_map(|k| {
                cell.iter().map(move |&(x, y, w, d)| Feature {
                    x: x + k as f64 * period,
                    y,
                    angle: None,
                    width_px: w,
                    depth_um: d,
                })
            })
            .collect();
        let err = [rng.gen_range(-3.0..3.0), rng.gen_range(-3.0..3.0)];
        let nominal = [0.0, step];
        let truth = [err[0], step + err[1]];
        let a = tile(&features, 0.0, 0.0, n, &mut rng);
        let b = tile(&features, truth[0], truth[1], n, &mut rng);
        let r = register_pair(
            RasterView::new(&a, Shape::new(n, n)).unwrap(),
            RasterView::new(&b, Shape::new(n, n)).unwrap(),
            nominal,
            &PhaseParams::default(),
        );
        eprintln!(
            "seed {seed}: offset {:?} truth {truth:?} ncc {:.3} {:?}",
            r.offset_px, r.ncc, r.rejection
        );
        if let Some(o) = r.offset_px {
            let e = (o[0] - truth[0]).hypot(o[1] - truth[1]);
            // Never an alias; precise where the pits do not line up into a ridge.
            assert!(e < 1.0, "seed {seed}: {e} px wrong");
            answered += (e < 0.2) as usize;
        }
    }
    assert!(
        answered >= 7,
        "{answered} of 8 periodic pairs answered within 0.2 px"
    );
}

/// Pills-like plateaus (sharp-edged flat-topped discs, as on the real specimen
/// sur-uncompressed.sur) on a plane, sampled at a continuous position.
fn plateaus_at(discs: &[(f64, f64, f64, f64)], x: f64, y: f64) -> f64 {
    discs
        .iter()
        .map(|&(cx, cy, radius, height)| {
            let r = (x - cx).hypot(y - cy);
            height * 0.5 * (1.0 - ((r - radius) / 0.7).tanh())
        })
        .sum()
}

/// Errors (x, y) in px of 12 pairs of 128 px tiles at 10 % overlap whose strip holds the edges
/// of two plateaus (0.3-0.6 um high) in white noise of `noise_um`, registered with and without
/// the Lucas-Kanade refinement; with it, the reported standard deviation too.
fn plateau_pair_errors(lucas_kanade: bool, noise_um: f64) -> Vec<Option<([f64; 2], f64)>> {
    let n = 128;
    let step = 115.2;
    let params = PhaseParams {
        lucas_kanade,
        ..PhaseParams::default()
    };
    (0..12u64)
        .map(|seed| {
            let mut rng = ChaCha8Rng::seed_from_u64(1000 + seed);
            let horizontal = seed % 2 == 0;
            let discs: Vec<(f64, f64, f64, f64)> = (0..2)
                .map(|_| {
                    let along = rng.gen_range(10.0..118.0);
                    let across = step + rng.gen_range(-4.0..16.0);
                    let (cx, cy) = if horizontal {
                        (across, along)
                    } else {
                        (along, across)
                    };
                    (cx, cy, rng.gen_range(5.0..12.0), rng.gen_range(0.3..0.6))
                })
                .collect();
            let err = [rng.gen_range(-3.0..3.0), rng.gen_range(-3.0..3.0)];
            let nominal = if horizontal { [step, 0.0] } else { [0.0, step] };
            let truth = [nominal[0] + err[0], nominal[1] + err[1]];
            let noise = Normal::new(0.0, noise_um).unwrap();
            let cut = |x0: f64, y0: f64, rng: &mut ChaCha8Rng| -> Vec<f32> {
                let piston = rng.gen_range(-1.0..1.0);
                let (tx, ty) = (rng.gen_range(-0.002..0.002), rng.gen_range(-0.002..0.002));
                let mut out = Vec::with_capacity(n * n);
                for r in 0..n {
                    for c in 0..n {
                        let z = plateaus_at(&discs, x0 + c as f64, y0 + r as f64);
                        let tilt = tx * c as f64 + ty * r as f64;
                        out.push((z + piston + tilt + noise.sample(rng)) as f32);
                    }
                }
                out
            };
            let a = cut(0.0, 0.0, &mut rng);
            let b = cut(truth[0], truth[1], &mut rng);
            let r = register_pair(
                RasterView::new(&a, Shape::new(n, n)).unwrap(),
                RasterView::new(&b, Shape::new(n, n)).unwrap(),
                nominal,
                &params,
            );
            r.offset_px.map(|o| {
                let sd = r
                    .covariance_px2
                    .map_or(f64::NAN, surfstream_matcher::refine::worst_sd_px);
                ([o[0] - truth[0], o[1] - truth[1]], sd)
            })
        })
        .collect()
}

/// The NCC's 3 x 3 fit alone is thrown off by the noise on the plateaus' edges (the cause of
/// the 0.5-1.1 px errors on the real cut "sur-uncompressed 10 % noisy"); Lucas-Kanade on the
/// smoothed heights much less, and its standard deviation covers its error. Measured: noise
/// 0.06 um: rms 0.228 px (NCC fit) and 0.138 px (LK, sd 0.08-0.28 px); noise 0.03 um: see the
/// message. Disabling the refinement makes both rms equal and fails the test.
#[test]
fn lucas_kanade_refines_noisy_plateau_edges_where_the_ncc_fit_is_off() {
    let rms = |e: &[Option<([f64; 2], f64)>]| {
        let v: Vec<f64> = e.iter().flatten().map(|(d, _)| d[0].hypot(d[1])).collect();
        (
            (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt(),
            v.len(),
        )
    };
    for (noise_um, max_rms_lk) in [(0.03, 0.08), (0.06, 0.2)] {
        let ncc = plateau_pair_errors(false, noise_um);
        let lk = plateau_pair_errors(true, noise_um);
        let (rms_ncc, n_ncc) = rms(&ncc);
        let (rms_lk, n_lk) = rms(&lk);
        eprintln!(
            "noise {noise_um} um\nNCC fit: {ncc:.3?}\nLK: {lk:.3?}\nrms NCC {rms_ncc:.3} ({n_ncc}), \
             LK {rms_lk:.3} ({n_lk})"
        );
        assert!(
            n_lk >= 10 && n_lk == n_ncc,
            "answered: NCC {n_ncc}, LK {n_lk}"
        );
        assert!(rms_lk <= max_rms_lk, "LK rms {rms_lk:.3} px");
        assert!(
            rms_lk <= 0.8 * rms_ncc,
            "NCC rms {rms_ncc:.3} px, LK {rms_lk:.3} px"
        );
        for (d, sd) in lk.iter().flatten() {
            let e = d[0].hypot(d[1]);
            assert!(
                sd.is_finite() && e <= 3.5 * sd,
                "error {e:.3} px, sd {sd:.3} px"
            );
        }
    }
}
