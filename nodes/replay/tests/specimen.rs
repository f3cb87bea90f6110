//! Specimen synthesis: determinism, exact Sa, components, validation.

use surfstream_core::raster::Shape;
use surfstream_replay::{generate_specimen, ReplayError, Specimen, SpecimenParams};

fn small(seed: u64) -> SpecimenParams {
    SpecimenParams {
        width_px: 300,
        height_px: 211, // odd and not FFT-friendly on purpose
        seed,
        ..SpecimenParams::default()
    }
}

fn roughness_only(seed: u64) -> SpecimenParams {
    SpecimenParams {
        waviness_amplitude_um: 0.0,
        form_sag_um: 0.0,
        ..small(seed)
    }
}

fn bytes(s: &Specimen) -> Vec<u8> {
    s.heights.iter().flat_map(|v| v.to_le_bytes()).collect()
}

fn mean_and_sa(v: &[f32]) -> (f64, f64) {
    let n = v.len() as f64;
    let mean = v.iter().map(|&x| f64::from(x)).sum::<f64>() / n;
    let sa = v.iter().map(|&x| (f64::from(x) - mean).abs()).sum::<f64>() / n;
    (mean, sa)
}

#[test]
fn same_seed_gives_identical_bytes() {
    let a = generate_specimen(&small(7)).expect("valid");
    let b = generate_specimen(&small(7)).expect("valid");
    assert_eq!(a.shape, Shape::new(211, 300));
    assert_eq!(a.heights.len(), 300 * 211);
    assert_eq!(bytes(&a), bytes(&b));
    assert!(a.heights.iter().all(|v| v.is_finite()));
}

#[test]
fn different_seed_gives_different_specimen() {
    let a = generate_specimen(&small(7)).expect("valid");
    let b = generate_specimen(&small(8)).expect("valid");
    let differing = a
        .heights
        .iter()
        .zip(&b.heights)
        .filter(|(x, y)| x != y)
        .count();
    assert!(
        differing > a.heights.len() * 9 / 10,
        "only {differing} differ"
    );
}

#[test]
fn result_does_not_depend_on_thread_count() {
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("thread pool")
            .install(|| generate_specimen(&small(3)).expect("valid"))
    };
    assert_eq!(bytes(&run(1)), bytes(&run(3)));
}

#[test]
fn roughness_sa_matches_target() {
    for (seed, sa_um) in [(1, 1.3), (2, 0.4), (3, 2.5)] {
        let p = SpecimenParams {
            sa_um,
            ..roughness_only(seed)
        };
        let s = generate_specimen(&p).expect("valid");
        let (mean, sa) = mean_and_sa(&s.heights);
        assert!(
            (sa - sa_um).abs() <= 0.02 * sa_um,
            "seed {seed}: Sa {sa} vs target {sa_um}"
        );
        assert!(mean.abs() < 1e-3 * sa_um, "mean {mean}");
    }
}

#[test]
fn roughness_sa_holds_for_a_large_flat_spectrum_specimen() {
    // Short correlation length, Hurst 1, a large non-square specimen.
    let p = SpecimenParams {
        width_px: 1000,
        height_px: 700,
        hurst: 1.0,
        correlation_length_um: 5.0,
        ..roughness_only(11)
    };
    let s = generate_specimen(&p).expect("valid");
    let (_, sa) = mean_and_sa(&s.heights);
    assert!((sa - 1.3).abs() <= 0.02 * 1.3, "Sa {sa}");
}

#[test]
fn longer_correlation_length_is_smoother_at_equal_sa() {
    let slope = |corr: f64| {
        let p = SpecimenParams {
            correlation_length_um: corr,
            ..roughness_only(5)
        };
        let s = generate_specimen(&p).expect("valid");
        // mean |dz/dx| per pixel
        let mut sum = 0.0;
        for row in s.heights.chunks_exact(s.shape.cols) {
            for w in row.windows(2) {
                sum += f64::from((w[1] - w[0]).abs());
            }
        }
        sum / ((s.shape.cols - 1) * s.shape.rows) as f64
    };
    let rough = slope(5.0);
    let smooth = slope(80.0);
    assert!(smooth < 0.5 * rough, "slopes: 5 um {rough}, 80 um {smooth}");
}

#[test]
fn form_alone_is_a_dome_of_the_given_sag() {
    let p = SpecimenParams {
        width_px: 101,
        height_px: 61,
        sa_um: 0.0,
        waviness_amplitude_um: 0.0,
        form_sag_um: 3.0,
        ..SpecimenParams::default()
    };
    let s = generate_specimen(&p).expect("valid");
    let centre = f64::from(s.get(50, 30).expect("inside"));
    for (x, y) in [(0, 0), (100, 0), (0, 60), (100, 60)] {
        let corner = f64::from(s.get(x, y).expect("inside"));
        assert!((centre - corner - 3.0).abs() < 1e-5, "corner ({x},{y})");
    }
    assert!((centre - 1.5).abs() < 1e-5);
}

#[test]
fn waviness_alone_is_bounded_by_its_amplitude_and_present() {
    let p = SpecimenParams {
        width_px: 800,
        height_px: 600,
        sa_um: 0.0,
        form_sag_um: 0.0,
        waviness_amplitude_um: 2.0,
        waviness_components: 2,
        ..SpecimenParams::default()
    };
    let s = generate_specimen(&p).expect("valid");
    let max = s.heights.iter().fold(0f32, |m, v| m.max(v.abs()));
    assert!(max <= 2.0 + 1e-5, "max {max}");
    assert!(max > 0.5, "max {max}");
}

#[test]
fn zero_sa_and_no_components_is_flat() {
    let p = SpecimenParams {
        width_px: 16,
        height_px: 9,
        sa_um: 0.0,
        waviness_amplitude_um: 0.0,
        form_sag_um: 0.0,
        ..SpecimenParams::default()
    };
    let s = generate_specimen(&p).expect("valid");
    assert!(s.heights.iter().all(|&v| v == 0.0));
}

fn field_of(err: ReplayError) -> String {
    match err {
        ReplayError::InvalidParam { field, .. } => field.to_string(),
        other => panic!("expected InvalidParam, got {other:?}"),
    }
}

#[test]
fn invalid_parameters_name_the_field() {
    let base = SpecimenParams::default();
    let cases: Vec<(SpecimenParams, &str)> = vec![
        (
            SpecimenParams {
                width_px: 0,
                ..base.clone()
            },
            "width_px",
        ),
        (
            SpecimenParams {
                height_px: 1,
                ..base.clone()
            },
            "height_px",
        ),
        (
            SpecimenParams {
                pitch_um: 0.0,
                ..base.clone()
            },
            "pitch_um",
        ),
        (
            SpecimenParams {
                pitch_um: f64::NAN,
                ..base.clone()
            },
            "pitch_um",
        ),
        (
            SpecimenParams {
                sa_um: -1.0,
                ..base.clone()
            },
            "sa_um",
        ),
        (
            SpecimenParams {
                hurst: 0.0,
                ..base.clone()
            },
            "hurst",
        ),
        (
            SpecimenParams {
                hurst: 1.5,
                ..base.clone()
            },
            "hurst",
        ),
        (
            SpecimenParams {
                correlation_length_um: 0.0,
                ..base.clone()
            },
            "correlation_length_um",
        ),
        (
            SpecimenParams {
                waviness_amplitude_um: f64::INFINITY,
                ..base.clone()
            },
            "waviness_amplitude_um",
        ),
        (
            SpecimenParams {
                waviness_wavelength_um: -4.0,
                ..base.clone()
            },
            "waviness_wavelength_um",
        ),
        (
            SpecimenParams {
                waviness_components: 1000,
                ..base.clone()
            },
            "waviness_components",
        ),
        (
            SpecimenParams {
                form_sag_um: f64::NAN,
                ..base.clone()
            },
            "form_sag_um",
        ),
    ];
    for (p, field) in cases {
        let err = generate_specimen(&p).expect_err(field);
        let msg = err.to_string();
        assert!(msg.contains(&format!("`{field}`")), "{msg}");
        assert!(msg.contains("expected"), "{msg}");
        assert_eq!(field_of(err), field);
    }
}

#[test]
fn hurst_message_says_what_is_expected() {
    let err = generate_specimen(&SpecimenParams {
        hurst: 1.5,
        ..SpecimenParams::default()
    })
    .expect_err("invalid");
    assert_eq!(
        err.to_string(),
        "invalid specimen parameter `hurst` = 1.5: expected a number in (0, 1]"
    );
}

#[test]
fn oversized_specimen_is_refused_before_allocating() {
    let err = generate_specimen(&SpecimenParams {
        width_px: 100_000,
        height_px: 100_000,
        ..SpecimenParams::default()
    })
    .expect_err("too large");
    assert!(matches!(err, ReplayError::TooLarge { .. }), "{err}");
    assert!(err.to_string().contains("too large"));
}

#[test]
fn params_deserialize_with_defaults_and_reject_unknown_fields() {
    let p: SpecimenParams = serde_json::from_str("{}").expect("defaults");
    assert_eq!(p, SpecimenParams::default());
    assert_eq!(p.pitch_um, 0.8148);
    assert_eq!(p.sa_um, 1.3);
    assert_eq!(p.hurst, 0.8);
    let p: SpecimenParams = serde_json::from_str(r#"{"sa_um": 0.5, "seed": 9}"#).expect("partial");
    assert_eq!(p.sa_um, 0.5);
    assert_eq!(p.seed, 9);
    assert_eq!(p.hurst, 0.8);
    let err = serde_json::from_str::<SpecimenParams>(r#"{"sa": 0.5}"#).expect_err("unknown");
    assert!(err.to_string().contains("unknown field `sa`"), "{err}");
}

#[test]
fn from_heights_checks_the_shape() {
    // 2 rows of 3.
    assert!(Specimen::from_heights(vec![0.0; 6], Shape::new(2, 3), 0.5).is_ok());
    let err = Specimen::from_heights(vec![0.0; 5], Shape::new(2, 3), 0.5).expect_err("short");
    assert!(matches!(err, ReplayError::Shape(_)), "{err}");
    assert!(Specimen::from_heights(vec![], Shape::new(0, 0), 0.5).is_err());
    assert!(Specimen::from_heights(vec![0.0; 6], Shape::new(2, 3), -1.0).is_err());
}
