//! Pairwise registration on synthetic, seeded tiles: accuracy at 10, 20 and 30 % overlap for
//! horizontal and vertical neighbours (256 and 1024 px), heavy dropouts, other surfaces and
//! planes, refusals on featureless, unrelated and periodic pairs, and bad input.
//!
//! The synthetic surface (tests/support) is a band-limited self-affine roughness of rms 1 um
//! sampled at exact sub-pixel offsets; tiles get random piston (+-5 um) and tilt
//! (+-0.005 um/px), white noise and dropouts; the stage error is 3 px (sigma).

mod support;

use support::{make_pair, rough_pair, Pair, PairSpec};
use surfstream_core::raster::{RasterView, Shape, ShapeError};
use surfstream_matcher::{
    register_pair, InputError, PairRegistration, PhaseCorrelator, PhaseParams, Rejection,
};

/// The view of `rows x cols` heights (well-formed in every test that uses it).
fn raster(heights: &[f32], rows: usize, cols: usize) -> RasterView<'_, f32> {
    RasterView::new(heights, Shape::new(rows, cols)).expect("raster shape")
}

fn register(corr: &mut PhaseCorrelator, pair: &Pair) -> PairRegistration {
    corr.register(
        raster(&pair.a, pair.h, pair.w),
        raster(&pair.b, pair.h, pair.w),
        pair.nominal_offset_px,
        &PhaseParams::default(),
    )
}

/// [x, y] error of the measured offset, px; panics with the reason when the pair was refused.
fn error_px(r: &PairRegistration, pair: &Pair, what: &str) -> [f64; 2] {
    let o = r
        .offset_px
        .unwrap_or_else(|| panic!("{what}: pair refused: {:?}", r.rejection));
    [o[0] - pair.true_offset_px[0], o[1] - pair.true_offset_px[1]]
}

/// Registers every pair, prints the errors, and asserts the worst |error| over x and y.
fn check_accuracy(specs: &[PairSpec], tolerance_px: f64, make: impl Fn(&PairSpec) -> Pair) {
    let mut corr = PhaseCorrelator::new();
    let mut worst = 0.0f64;
    for spec in specs {
        let pair = make(spec);
        let r = register(&mut corr, &pair);
        let what = format!(
            "{} px, overlap {:.0} %, {}, seed {}",
            spec.tile_px,
            spec.overlap * 100.0,
            if spec.horizontal {
                "horizontal"
            } else {
                "vertical"
            },
            spec.seed
        );
        let e = error_px(&r, &pair, &what);
        eprintln!(
            "{what}: error ({:+.3}, {:+.3}) px, ncc {:.3}, peak ratio {:.1}, roundness {:.2}",
            e[0], e[1], r.ncc, r.peak_ratio, r.peak_roundness
        );
        worst = worst.max(e[0].abs()).max(e[1].abs());
        assert!(
            e[0].abs() <= tolerance_px && e[1].abs() <= tolerance_px,
            "{what}: error ({:.3}, {:.3}) px exceeds {tolerance_px} px",
            e[0],
            e[1]
        );
        assert!(r.rejection.is_none());
        assert!(r.ncc > 0.8, "{what}: ncc {}", r.ncc);
    }
    eprintln!("worst error {worst:.3} px over {} pairs", specs.len());
}

fn all_layouts(tile_px: usize, seeds: u64, tweak: impl Fn(&mut PairSpec)) -> Vec<PairSpec> {
    let mut specs = Vec::new();
    for overlap in [0.1, 0.2, 0.3] {
        for horizontal in [true, false] {
            for seed in 0..seeds {
                let mut s = PairSpec::new(tile_px, overlap, horizontal, 100 * seed + 7);
                tweak(&mut s);
                specs.push(s);
            }
        }
    }
    specs
}

#[test]
fn offsets_of_256_px_tiles_at_10_20_30_percent_overlap() {
    check_accuracy(&all_layouts(256, 3, |_| {}), 0.15, rough_pair);
}

#[test]
fn offsets_of_1024_px_tiles_at_10_20_30_percent_overlap() {
    check_accuracy(&all_layouts(1024, 1, |_| {}), 0.05, rough_pair);
}

#[test]
fn thirty_percent_dropouts_still_register() {
    let heavy = |s: &mut PairSpec| {
        s.nan_fraction = 0.3;
        s.noise_um = 0.1;
    };
    check_accuracy(&all_layouts(256, 2, heavy), 0.15, rough_pair);
    let mut big = PairSpec::new(1024, 0.2, false, 11);
    heavy(&mut big);
    check_accuracy(&[big], 0.05, rough_pair);
}

#[test]
fn sub_pixel_sweep_has_no_pixel_locking() {
    // The same geometry with the fractional offset swept across a pixel, on each axis.
    let mut specs = Vec::new();
    for i in 0..10 {
        let f = i as f64 / 10.0;
        for horizontal in [true, false] {
            let mut s = PairSpec::new(256, 0.2, horizontal, 5);
            s.fixed_error_px = Some(if horizontal { [f, 2.0] } else { [2.0, f] });
            specs.push(s);
        }
    }
    check_accuracy(&specs, 0.1, rough_pair);
}

#[test]
fn rougher_surfaces_register_more_precisely() {
    // Short correlation length and content up to near Nyquist (the easy case for whitening
    // and for the NCC peak fit alike).
    let specs = all_layouts(256, 1, |_| {});
    check_accuracy(&specs, 0.05, |s| make_pair(&s.surface(5.0, 0.8, 0.35), s));
}

#[test]
fn large_piston_and_tilt_do_not_matter() {
    let mut corr = PhaseCorrelator::new();
    let spec = PairSpec::new(256, 0.2, true, 21);
    let mut pair = rough_pair(&spec);
    // 500 um piston and 0.05 um/px tilt on b (13 um across the tile), -300 um on a.
    for (i, v) in pair.b.iter_mut().enumerate() {
        let (r, c) = ((i / 256) as f32, (i % 256) as f32);
        *v += 500.0 + 0.05 * c - 0.03 * r;
    }
    for v in pair.a.iter_mut() {
        *v -= 300.0;
    }
    let r = register(&mut corr, &pair);
    let e = error_px(&r, &pair, "large planes");
    assert!(e[0].abs() < 0.15 && e[1].abs() < 0.15, "{e:?}");
}

#[test]
fn tiles_of_different_sizes_register() {
    let spec = PairSpec::new(256, 0.3, true, 31);
    let pair = rough_pair(&spec);
    // Keep a 256 x 256, crop b to its top-left 200 x 240 (origin unchanged).
    let (bw, bh) = (200, 240);
    let b: Vec<f32> = (0..bh)
        .flat_map(|r| pair.b[r * 256..r * 256 + bw].iter().copied())
        .collect();
    let r = register_pair(
        raster(&pair.a, 256, 256),
        raster(&b, bh, bw),
        pair.nominal_offset_px,
        &PhaseParams::default(),
    );
    let e = error_px(&r, &pair, "different sizes");
    assert!(e[0].abs() < 0.15 && e[1].abs() < 0.15, "{e:?}");
    assert_eq!(r.overlap_px, [256 - spec.step_px() as usize, 240]);
}

#[test]
fn reused_correlator_matches_one_shot() {
    let small = rough_pair(&PairSpec::new(256, 0.1, false, 41));
    let other = rough_pair(&PairSpec::new(256, 0.3, true, 42));
    let mut corr = PhaseCorrelator::new();
    let first = register(&mut corr, &small);
    let _ = register(&mut corr, &other);
    let again = register(&mut corr, &small);
    let fresh = register_pair(
        raster(&small.a, small.h, small.w),
        raster(&small.b, small.h, small.w),
        small.nominal_offset_px,
        &PhaseParams::default(),
    );
    assert_eq!(first, again);
    assert_eq!(first, fresh);
}

#[test]
fn shift_beyond_the_limit_is_refused_with_the_measured_shift() {
    // Vertical neighbours, 40 px off along x (the long axis of the overlap): found, refused.
    let mut spec = PairSpec::new(256, 0.3, false, 51);
    spec.fixed_error_px = Some([40.3, 1.2]);
    let pair = rough_pair(&spec);
    let r = register(&mut PhaseCorrelator::new(), &pair);
    assert!(r.offset_px.is_none());
    match r.rejection {
        Some(Rejection::ShiftTooLarge { shift_px, limit_px }) => {
            assert!((shift_px[0] - 40.3).abs() < 0.15, "{shift_px:?}");
            assert_eq!(limit_px[0], 30.0);
        }
        ref other => panic!("expected ShiftTooLarge, got {other:?}"),
    }
    // The same pair registers when the limit allows it.
    let params = PhaseParams {
        max_shift_px: 45.0,
        ..PhaseParams::default()
    };
    let r = register_pair(
        raster(&pair.a, pair.h, pair.w),
        raster(&pair.b, pair.h, pair.w),
        pair.nominal_offset_px,
        &params,
    );
    let e = error_px(&r, &pair, "wider limit");
    assert!(e[0].abs() < 0.15 && e[1].abs() < 0.15, "{e:?}");
}

/// The refusal of a pair that has no right answer, printing it.
fn refusal(a: &[f32], b: &[f32], w: usize, nominal: [f64; 2], what: &str) -> Rejection {
    let r = register_pair(
        raster(a, w, w),
        raster(b, w, w),
        nominal,
        &PhaseParams::default(),
    );
    eprintln!(
        "{what}: {:?} (ncc {:.3}, peak ratio {:.2}, roundness {:.2})",
        r.rejection, r.ncc, r.peak_ratio, r.peak_roundness
    );
    assert!(
        r.offset_px.is_none(),
        "{what}: got an offset {:?}",
        r.offset_px
    );
    r.rejection.unwrap_or_else(|| panic!("{what}: no reason"))
}

#[test]
fn featureless_pairs_are_refused() {
    let w = 256;
    let flat = vec![3.25f32; w * w];
    let rej = refusal(&flat, &flat, w, [205.0, 0.0], "constant");
    assert!(matches!(rej, Rejection::Featureless { .. }), "{rej:?}");

    let plane: Vec<f32> = (0..w * w)
        .map(|i| 700.0 + 0.01 * (i % w) as f32 - 0.02 * (i / w) as f32)
        .collect();
    let rej = refusal(&plane, &plane, w, [0.0, 205.0], "tilted plane");
    assert!(matches!(rej, Rejection::Featureless { .. }), "{rej:?}");
}

#[test]
fn unrelated_pairs_are_refused() {
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};
    let w = 256;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(61);
    let normal = Normal::new(0.0, 1.0).expect("unit normal");
    for trial in 0..3 {
        let a: Vec<f32> = (0..w * w).map(|_| normal.sample(&mut rng) as f32).collect();
        let b: Vec<f32> = (0..w * w).map(|_| normal.sample(&mut rng) as f32).collect();
        let rej = refusal(&a, &b, w, [205.0, 1.0], &format!("white noise {trial}"));
        assert!(
            matches!(rej, Rejection::LowNcc { .. } | Rejection::Ambiguous { .. }),
            "{rej:?}"
        );
    }
    // Two different rough surfaces.
    for (trial, horizontal) in [true, false].into_iter().enumerate() {
        let p = rough_pair(&PairSpec::new(256, 0.2, horizontal, 70 + trial as u64));
        let q = rough_pair(&PairSpec::new(256, 0.2, horizontal, 80 + trial as u64));
        let rej = refusal(&p.a, &q.b, w, p.nominal_offset_px, "unrelated surfaces");
        assert!(
            matches!(rej, Rejection::LowNcc { .. } | Rejection::Ambiguous { .. }),
            "{rej:?}"
        );
    }
}

/// A tile of the grating `amplitude * sin(2 pi (x cos(angle) + y sin(angle)) / period)` with
/// its origin at (x0, y0), plus white noise.
fn grating_tile(
    w: usize,
    origin: [f64; 2],
    period_px: f64,
    angle_deg: f64,
    rng: &mut rand_chacha::ChaCha8Rng,
) -> Vec<f32> {
    use rand_distr::{Distribution, Normal};
    let noise = Normal::new(0.0, 0.03).expect("normal");
    let (s, c) = angle_deg.to_radians().sin_cos();
    (0..w * w)
        .map(|i| {
            let x = origin[0] + (i % w) as f64;
            let y = origin[1] + (i / w) as f64;
            let phase = std::f64::consts::TAU * (x * c + y * s) / period_px;
            (phase.sin() + noise.sample(rng)) as f32
        })
        .collect()
}

#[test]
fn periodic_gratings_are_refused_not_misplaced() {
    use rand::SeedableRng;
    let w = 256;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(91);
    for (angle_deg, horizontal) in [
        (0.0, true),
        (0.0, false),
        (90.0, true),
        (45.0, true),
        (30.0, false),
    ] {
        let nominal = if horizontal {
            [205.0, 0.0]
        } else {
            [0.0, 205.0]
        };
        let truth = [nominal[0] + 2.4, nominal[1] - 1.7];
        let a = grating_tile(w, [0.0, 0.0], 20.0, angle_deg, &mut rng);
        let b = grating_tile(w, truth, 20.0, angle_deg, &mut rng);
        let rej = refusal(
            &a,
            &b,
            w,
            nominal,
            &format!("grating at {angle_deg} deg, horizontal {horizontal}"),
        );
        assert!(
            matches!(
                rej,
                Rejection::Ambiguous { .. } | Rejection::NotLocalized { .. }
            ),
            "{rej:?}"
        );
    }
}

#[test]
fn bad_input_is_refused_with_a_reason() {
    let w = 64;
    let good = vec![0.0f32; w * w];
    let params = PhaseParams::default();
    let reason =
        |a: RasterView<'_, f32>, b: RasterView<'_, f32>, off: [f64; 2], p: &PhaseParams| {
            let r = register_pair(a, b, off, p);
            assert!(r.offset_px.is_none());
            r.rejection.expect("a reason")
        };

    // Wrong slice length and zero size: the view refuses to exist, and the matcher's
    // InputError, converted from that refusal, still says which.
    let short = vec![0.0f32; w * w - 1];
    let refused = RasterView::new(&short, Shape::new(w, w)).expect_err("short slice");
    let e = InputError::from(refused);
    assert!(
        matches!(
            e,
            InputError::Shape(ShapeError::Length {
                expected: 4096,
                found: 4095,
                ..
            })
        ),
        "{e:?}"
    );
    let refused = RasterView::<f32>::new(&[], Shape::new(10, 0)).expect_err("zero size");
    let e = InputError::from(refused);
    assert!(
        matches!(e, InputError::Shape(ShapeError::Empty(_))),
        "{e:?}"
    );
    // Non-finite nominal offset.
    let rej = reason(
        raster(&good, w, w),
        raster(&good, w, w),
        [f64::NAN, 0.0],
        &params,
    );
    assert!(
        matches!(
            rej,
            Rejection::InvalidInput(InputError::NonFiniteOffset { .. })
        ),
        "{rej:?}"
    );
    let rej = reason(
        raster(&good, w, w),
        raster(&good, w, w),
        [1e300, 0.0],
        &params,
    );
    assert!(
        matches!(
            rej,
            Rejection::InvalidInput(InputError::OffsetOutOfRange { .. })
        ),
        "{rej:?}"
    );
    // Invalid parameters.
    let bad = PhaseParams {
        candidates: 0,
        ..PhaseParams::default()
    };
    let rej = reason(raster(&good, w, w), raster(&good, w, w), [50.0, 0.0], &bad);
    match rej {
        Rejection::InvalidInput(InputError::InvalidParameter { name, .. }) => {
            assert_eq!(name, "candidates")
        }
        other => panic!("{other:?}"),
    }
    // No overlap at all, and an overlap too thin to register.
    let rej = reason(
        raster(&good, w, w),
        raster(&good, w, w),
        [64.0, 0.0],
        &params,
    );
    assert!(
        matches!(
            rej,
            Rejection::NoOverlap {
                overlap_px: [0, 64],
                ..
            }
        ),
        "{rej:?}"
    );
    let rej = reason(
        raster(&good, w, w),
        raster(&good, w, w),
        [-60.0, 3.0],
        &params,
    );
    assert!(
        matches!(
            rej,
            Rejection::NoOverlap {
                overlap_px: [4, 61],
                ..
            }
        ),
        "{rej:?}"
    );
    // An overlap that is (almost) all dropouts.
    let spec = PairSpec::new(256, 0.2, true, 3);
    let mut pair = rough_pair(&spec);
    for (i, v) in pair.b.iter_mut().enumerate() {
        if i % 256 < 60 {
            *v = f32::NAN;
        }
    }
    let rej = reason(
        raster(&pair.a, 256, 256),
        raster(&pair.b, 256, 256),
        pair.nominal_offset_px,
        &params,
    );
    assert!(
        matches!(rej, Rejection::TooFewValidPixels { .. }),
        "{rej:?}"
    );
    // Messages name the problem.
    assert!(rej.to_string().contains("valid pixels"), "{rej}");
}
