//! Large specimens: a periodic roughness texture of bounded size, sampled per tile, with the
//! waviness and form of the whole specimen evaluated where they are read.

use surfstream_core::raster::Shape;
use surfstream_replay::specimen::{ROUGHNESS_PERIOD_PX, WHOLE_SYNTHESIS_MAX_POINTS};
use surfstream_replay::{
    acquire_tile, generate_specimen, generate_virtual_specimen, plan_scan, truth_for,
    PeriodicSpecimen, ReplayError, SpecimenParams, SpecimenSurface, StageParams, VirtualSpecimen,
};

fn roughness_only(period: usize) -> SpecimenParams {
    SpecimenParams {
        width_px: 300,
        height_px: 170,
        waviness_components: 0,
        form_sag_um: 0.0,
        seed: 5,
        roughness_period_px: Some(period),
        ..SpecimenParams::default()
    }
}

fn block(s: &impl SpecimenSurface, x0: usize, y0: usize, w: usize, h: usize) -> Vec<f32> {
    let mut out = vec![0f32; w * h];
    s.read_block(x0, y0, w, &mut out);
    out
}

#[test]
fn the_roughness_repeats_with_the_stated_period() {
    let s = PeriodicSpecimen::generate(&roughness_only(64)).expect("valid");
    assert_eq!(s.period_px(), 64);
    let a = block(&s, 3, 5, 100, 40);
    for (dx, dy) in [(64, 0), (0, 64), (128, 64), (192, 64)] {
        let b = block(&s, 3 + dx, 5 + dy, 100, 40);
        assert!(
            a.iter().zip(&b).all(|(p, q)| p.to_bits() == q.to_bits()),
            "shift ({dx}, {dy})"
        );
    }
    // Not periodic at any smaller shift: one period holds no repeat.
    let c = block(&s, 3 + 32, 5, 100, 40);
    assert!(a.iter().zip(&c).filter(|(p, q)| p != q).count() > a.len() * 9 / 10);
}

#[test]
fn one_period_has_the_specified_sa_and_zero_mean() {
    for sa_um in [0.4, 1.3] {
        let p = SpecimenParams {
            sa_um,
            ..roughness_only(128)
        };
        let s = PeriodicSpecimen::generate(&p).expect("valid");
        let v = block(&s, 7, 11, 128, 128); // any one whole period
        let n = v.len() as f64;
        let mean = v.iter().map(|&x| f64::from(x)).sum::<f64>() / n;
        let sa = v.iter().map(|&x| (f64::from(x) - mean).abs()).sum::<f64>() / n;
        assert!((sa - sa_um).abs() < 1e-5 * sa_um, "Sa {sa} for {sa_um}");
        assert!(mean.abs() < 1e-5, "mean {mean}");
    }
}

#[test]
fn waviness_and_form_are_those_of_the_whole_specimen() {
    // Without roughness the periodic specimen is the analytic waviness + form alone: the
    // same bits as the specimen synthesised whole.
    let p = SpecimenParams {
        width_px: 250,
        height_px: 190,
        sa_um: 0.0,
        waviness_amplitude_um: 2.0,
        waviness_wavelength_um: 60.0,
        form_sag_um: 3.0,
        seed: 9,
        ..SpecimenParams::default()
    };
    let whole = generate_specimen(&p).expect("valid");
    let periodic = PeriodicSpecimen::generate(&SpecimenParams {
        roughness_period_px: Some(64),
        ..p.clone()
    })
    .expect("valid");
    assert_eq!(periodic.allocated_points(), 0);
    let got = block(&periodic, 0, 0, 250, 190);
    assert!(got
        .iter()
        .zip(&whole.heights)
        .all(|(a, b)| a.to_bits() == b.to_bits()));
    assert!(whole.heights.iter().any(|&v| v.abs() > 1.0), "not flat");
}

#[test]
fn tile_acquisition_equals_sampling_the_rendered_specimen() {
    // Every degradation on: the tiles measured from the periodic specimen (read where needed)
    // are bit-identical to those measured from the same specimen rendered whole.
    let stage = StageParams {
        rows: 3,
        cols: 3,
        tile_px: 48,
        ..StageParams::default()
    };
    let plan = plan_scan(&stage).expect("plan");
    let params = plan.specimen_params(&SpecimenParams {
        roughness_period_px: Some(40),
        ..SpecimenParams::default()
    });
    let periodic = generate_virtual_specimen(&params).expect("valid");
    assert_eq!(periodic.period_px(), Some(40));
    assert_eq!(periodic.allocated_points(), 40 * 40);
    let raster = periodic.to_specimen().expect("small");
    assert_eq!(raster.shape, periodic.shape());
    plan.check_specimen(&periodic).expect("fits");
    for t in &plan.tiles {
        assert!(t.true_origin_px[0].fract() != 0.0, "sub-pixel origin");
        let a = acquire_tile(&periodic, t, &stage);
        let b = acquire_tile(raster.as_ref(), t, &stage);
        assert!(
            a.iter().zip(&b).all(|(p, q)| p.to_bits() == q.to_bits()),
            "tile {}",
            t.index
        );
        assert!(a.iter().filter(|v| v.is_finite()).count() > a.len() / 2);
    }
    // generate_specimen renders the same specimen.
    let direct = generate_specimen(&params).expect("valid");
    assert_eq!(direct.heights.len(), raster.heights.len());
    assert!(direct
        .heights
        .iter()
        .zip(&raster.heights)
        .all(|(a, b)| a.to_bits() == b.to_bits()));
}

#[test]
fn small_scans_are_synthesised_whole_as_before() {
    // The demo (2 x 2) and the test scans up to 3 x 3 of 1024 px keep the whole synthesis.
    for (rows, cols) in [(2, 2), (3, 3), (4, 4)] {
        let plan = plan_scan(&StageParams {
            rows,
            cols,
            ..StageParams::default()
        })
        .expect("plan");
        let p = plan.specimen_params(&SpecimenParams::default());
        assert_eq!(p.roughness_period(), None, "{rows} x {cols}");
        assert_eq!(
            truth_for(&plan)
                .with_specimen(&p)
                .specimen
                .roughness_period_px,
            None
        );
    }
    // The smallest square scan past the threshold is periodic.
    let plan = plan_scan(&StageParams {
        rows: 5,
        cols: 5,
        ..StageParams::default()
    })
    .expect("plan");
    let p = plan.specimen_params(&SpecimenParams::default());
    assert!(p.width_px * p.height_px > WHOLE_SYNTHESIS_MAX_POINTS);
    assert_eq!(p.roughness_period(), Some(ROUGHNESS_PERIOD_PX));
}

#[test]
fn a_20_by_20_scan_holds_one_period_not_its_area() {
    let stage = StageParams {
        rows: 20,
        cols: 20,
        ..StageParams::default()
    };
    let plan = plan_scan(&stage).expect("plan");
    let params = plan.specimen_params(&SpecimenParams::default());
    let area = params.width_px * params.height_px;
    assert!(area > 300_000_000, "{area} px");
    // Rendering it whole is refused before allocating; measuring it is not.
    let err = generate_specimen(&params).expect_err("too large for a raster");
    assert!(matches!(err, ReplayError::TooLarge { .. }), "{err}");
    let s = generate_virtual_specimen(&params).expect("valid");
    assert!(matches!(s, VirtualSpecimen::Periodic(_)));
    assert_eq!(s.shape(), Shape::new(params.height_px, params.width_px));
    assert_eq!(
        s.allocated_points(),
        ROUGHNESS_PERIOD_PX * ROUGHNESS_PERIOD_PX
    );
    plan.check_specimen(&s).expect("fits");
    let truth = truth_for(&plan).with_specimen(&params);
    assert_eq!(
        truth.specimen.roughness_period_px,
        Some(ROUGHNESS_PERIOD_PX)
    );
    // The last tile (far corner) is measured like any other.
    let last = plan.tiles.last().expect("tiles");
    let tile = acquire_tile(&s, last, &stage);
    assert_eq!(tile.len(), 1024 * 1024);
    assert!(tile.iter().filter(|v| v.is_finite()).count() > tile.len() * 9 / 10);
    // Its true origin says where it was read: the same tile measured from a raster of the
    // block around it (origin shifted by the block's corner) is bit-identical.
    let clean = StageParams {
        piston_sigma_um: 0.0,
        tilt_sigma_um: 0.0,
        noise_um: 0.0,
        dropout_fraction: 0.0,
        dropout_blobs_mean: 0.0,
        ..stage.clone()
    };
    let [x0, y0] = last.true_origin_px;
    let (bx, by) = (x0.floor() as usize - 2, y0.floor() as usize - 2);
    let side = 1024 + 6;
    let local = surfstream_replay::Specimen::from_heights(
        block(&s, bx, by, side, side),
        Shape::new(side, side),
        s.pitch_um(),
    )
    .expect("block");
    let mut shifted = last.clone();
    shifted.true_origin_px = [x0 - bx as f64, y0 - by as f64];
    assert_eq!(shifted.true_origin_px[0].fract(), x0.fract());
    let got = acquire_tile(&s, last, &clean);
    let want = acquire_tile(&local, &shifted, &clean);
    assert!(got.iter().all(|v| v.is_finite()));
    assert!(got
        .iter()
        .zip(&want)
        .all(|(a, b)| a.to_bits() == b.to_bits()));
}

#[test]
fn a_bad_period_names_the_field() {
    for p in [0, 3, 100_000] {
        let err = PeriodicSpecimen::generate(&roughness_only(p))
            .err()
            .expect("invalid");
        assert!(err.to_string().contains("roughness_period_px"), "{err}");
    }
}
