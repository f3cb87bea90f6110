//! Scan planning: serpentine order, geometry, determinism, validation.

use surfstream_core::raster::Shape;
use surfstream_replay::{plan_scan, serpentine_order, ReplayError, StageParams};

fn params(rows: usize, cols: usize) -> StageParams {
    StageParams {
        rows,
        cols,
        tile_px: 100,
        ..StageParams::default()
    }
}

#[test]
fn serpentine_order_alternates_direction() {
    assert_eq!(
        serpentine_order(3, 3),
        vec![
            (0, 0),
            (0, 1),
            (0, 2),
            (1, 2),
            (1, 1),
            (1, 0),
            (2, 0),
            (2, 1),
            (2, 2)
        ]
    );
    assert_eq!(serpentine_order(1, 3), vec![(0, 0), (0, 1), (0, 2)]);
    assert_eq!(serpentine_order(2, 1), vec![(0, 0), (1, 0)]);
    assert!(serpentine_order(0, 4).is_empty());
}

#[test]
fn plan_tiles_follow_the_serpentine_with_indices() {
    let plan = plan_scan(&params(3, 4)).expect("valid");
    assert_eq!(plan.tiles.len(), 12);
    let order: Vec<(usize, usize)> = plan.tiles.iter().map(|t| (t.row, t.col)).collect();
    assert_eq!(order, serpentine_order(3, 4));
    for (k, t) in plan.tiles.iter().enumerate() {
        assert_eq!(t.index, k);
        assert_eq!(plan.index_of(t.row, t.col), Some(k));
    }
    assert_eq!(plan.index_of(1, 0), Some(7));
    assert_eq!(plan.index_of(3, 0), None);
    assert_eq!(plan.index_of(0, 4), None);
}

#[test]
fn nominal_grid_has_the_overlap_and_fits_the_specimen_with_margin() {
    let p = StageParams {
        overlap_y: Some(0.3),
        tile_width_px: Some(120),
        ..params(3, 4)
    };
    let plan = plan_scan(&p).expect("valid");
    assert_eq!((plan.tile_width_px, plan.tile_height_px), (120, 100));
    assert!((plan.step_x_px - 108.0).abs() < 1e-9);
    assert!((plan.step_y_px - 70.0).abs() < 1e-9);
    let t = |r, c| &plan.tiles[plan.index_of(r, c).expect("inside")];
    for r in 0..3 {
        for c in 0..4 {
            let n = t(r, c).nominal_origin_px;
            let n0 = t(0, 0).nominal_origin_px;
            assert!((n[0] - n0[0] - c as f64 * 108.0).abs() < 1e-9);
            assert!((n[1] - n0[1] - r as f64 * 70.0).abs() < 1e-9);
        }
    }
    // margin max(8, 5 * 3) = 15 px, plus 2 px of bicubic support, on every side
    assert_eq!(plan.margin_px, 15.0);
    let ext_x = 3.0 * 108.0 + 120.0;
    let ext_y = 2.0 * 70.0 + 100.0;
    assert_eq!(plan.specimen_width_px, (ext_x + 34.0_f64).ceil() as usize);
    assert_eq!(plan.specimen_height_px, (ext_y + 34.0_f64).ceil() as usize);
    for tile in &plan.tiles {
        let [x, y] = tile.true_origin_px;
        assert!(x - 1.0 >= 0.0 && y - 1.0 >= 0.0, "{x}, {y}");
        assert!(
            x + 120.0 + 1.0 <= plan.specimen_width_px as f64 - 1.0,
            "{x}"
        );
        assert!(
            y + 100.0 + 1.0 <= plan.specimen_height_px as f64 - 1.0,
            "{y}"
        );
        let e = [
            tile.true_origin_px[0] - tile.nominal_origin_px[0],
            tile.true_origin_px[1] - tile.nominal_origin_px[1],
        ];
        assert!(e[0].abs() <= 15.0 && e[1].abs() <= 15.0);
    }
}

#[test]
fn micrometres_are_pixels_times_pitch() {
    let plan = plan_scan(&params(2, 3)).expect("valid");
    for t in &plan.tiles {
        for k in 0..2 {
            assert!((t.stage_position_um[k] - t.nominal_origin_px[k] * 0.8148).abs() < 1e-9);
            assert!((t.true_origin_um[k] - t.true_origin_px[k] * 0.8148).abs() < 1e-9);
        }
    }
}

#[test]
fn stage_errors_piston_and_tilt_have_the_requested_spread() {
    let p = StageParams {
        stage_sigma_px: 2.0,
        piston_sigma_um: 0.5,
        tilt_sigma_um: 0.25,
        ..params(20, 20)
    };
    let plan = plan_scan(&p).expect("valid");
    let rms = |v: Vec<f64>| (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt();
    let ex = rms(plan
        .tiles
        .iter()
        .map(|t| t.true_origin_px[0] - t.nominal_origin_px[0])
        .collect());
    let ey = rms(plan
        .tiles
        .iter()
        .map(|t| t.true_origin_px[1] - t.nominal_origin_px[1])
        .collect());
    let piston = rms(plan.tiles.iter().map(|t| t.piston_um).collect());
    let tilt = rms(plan.tiles.iter().map(|t| t.tilt_x_um).collect());
    // 400 samples: the RMS is within ~ 7 % (2 sigma) of sigma
    assert!((ex / 2.0 - 1.0).abs() < 0.12, "{ex}");
    assert!((ey / 2.0 - 1.0).abs() < 0.12, "{ey}");
    assert!((piston / 0.5 - 1.0).abs() < 0.12, "{piston}");
    assert!((tilt / 0.25 - 1.0).abs() < 0.12, "{tilt}");
}

#[test]
fn zero_sigmas_give_the_nominal_pose() {
    let p = StageParams {
        stage_sigma_px: 0.0,
        piston_sigma_um: 0.0,
        tilt_sigma_um: 0.0,
        ..params(2, 2)
    };
    for t in plan_scan(&p).expect("valid").tiles {
        assert_eq!(t.true_origin_px, t.nominal_origin_px);
        assert_eq!((t.piston_um, t.tilt_x_um, t.tilt_y_um), (0.0, 0.0, 0.0));
    }
}

#[test]
fn backlash_shifts_reversed_rows() {
    let p = StageParams {
        stage_sigma_px: 0.0,
        backlash_px: 1.5,
        ..params(2, 2)
    };
    let plan = plan_scan(&p).expect("valid");
    for t in &plan.tiles {
        let dx = t.true_origin_px[0] - t.nominal_origin_px[0];
        assert_eq!(dx, if t.row % 2 == 1 { 1.5 } else { 0.0 });
    }
}

#[test]
fn plan_is_deterministic_and_seeded_per_tile() {
    let a = plan_scan(&params(3, 3)).expect("valid");
    let b = plan_scan(&params(3, 3)).expect("valid");
    assert_eq!(a, b);
    let c = plan_scan(&StageParams {
        seed: 2,
        ..params(3, 3)
    })
    .expect("valid");
    assert_ne!(a.tiles[0].true_origin_px, c.tiles[0].true_origin_px);
    // Tile k's pose depends on (seed, k) only, not on the grid size.
    let d = plan_scan(&params(1, 3)).expect("valid");
    for k in 0..3 {
        let e = |p: &surfstream_replay::TilePlan| {
            [
                p.true_origin_px[0] - p.nominal_origin_px[0],
                p.piston_um,
                p.tilt_y_um,
            ]
        };
        let (x, y) = (e(&a.tiles[k]), e(&d.tiles[k]));
        for i in 0..3 {
            assert!((x[i] - y[i]).abs() < 1e-12);
        }
    }
}

#[test]
fn specimen_params_and_check_specimen() {
    let plan = plan_scan(&params(1, 2)).expect("valid");
    let sp = plan.specimen_params(&surfstream_replay::SpecimenParams::default());
    assert_eq!(
        (sp.width_px, sp.height_px),
        (plan.specimen_width_px, plan.specimen_height_px)
    );
    let ok = surfstream_replay::Specimen::from_heights(
        vec![0.0; sp.width_px * sp.height_px],
        Shape::new(sp.height_px, sp.width_px),
        0.8148,
    )
    .expect("shape");
    assert!(plan.check_specimen(&ok).is_ok());
    let small =
        surfstream_replay::Specimen::from_heights(vec![0.0; 100], Shape::new(10, 10), 0.8148)
            .expect("shape");
    let err = plan.check_specimen(&small).expect_err("too small");
    assert!(err.to_string().contains("10 x 10 px"), "{err}");
    let other_pitch = surfstream_replay::Specimen {
        pitch_um: 0.5,
        ..ok
    };
    let err = plan.check_specimen(&other_pitch).expect_err("pitch");
    assert!(err.to_string().contains("pitch"), "{err}");
}

#[test]
fn large_scan_plan_sizes() {
    // A 5 x 10 serpentine of 1024 px tiles at 10 % overlap.
    let plan = plan_scan(&StageParams {
        rows: 5,
        cols: 10,
        ..StageParams::default()
    })
    .expect("valid");
    assert_eq!(plan.tiles.len(), 50);
    assert_eq!(plan.specimen_width_px, 9353); // 9 * 921.6 + 1024 + 2 * 17
    assert_eq!(plan.specimen_height_px, 4745); // 4 * 921.6 + 1024 + 2 * 17
}

fn expect_invalid(p: StageParams, field: &str, expected_fragment: &str) {
    let err = plan_scan(&p).expect_err(field);
    let msg = err.to_string();
    match &err {
        ReplayError::InvalidParam { field: f, .. } => assert_eq!(*f, field, "{msg}"),
        other => panic!("{field}: expected InvalidParam, got {other:?}"),
    }
    assert!(msg.contains(&format!("`{field}`")), "{msg}");
    assert!(msg.contains(expected_fragment), "{msg}");
}

#[test]
fn invalid_parameters_are_clear_errors() {
    let b = StageParams::default();
    expect_invalid(
        StageParams {
            overlap: 0.95,
            ..b.clone()
        },
        "overlap",
        "[0, 0.95)",
    );
    expect_invalid(
        StageParams {
            overlap: 1.2,
            ..b.clone()
        },
        "overlap",
        "[0, 0.95)",
    );
    expect_invalid(
        StageParams {
            overlap: -0.1,
            ..b.clone()
        },
        "overlap",
        "[0, 0.95)",
    );
    expect_invalid(
        StageParams {
            overlap: f64::NAN,
            ..b.clone()
        },
        "overlap",
        "[0, 0.95)",
    );
    expect_invalid(
        StageParams {
            overlap_x: Some(0.97),
            ..b.clone()
        },
        "overlap_x",
        "0.95",
    );
    expect_invalid(
        StageParams {
            overlap_y: Some(-0.01),
            ..b.clone()
        },
        "overlap_y",
        "0.95",
    );
    expect_invalid(
        StageParams {
            rows: 0,
            ..b.clone()
        },
        "rows",
        ">= 1",
    );
    expect_invalid(
        StageParams {
            cols: 0,
            ..b.clone()
        },
        "cols",
        ">= 1",
    );
    expect_invalid(
        StageParams {
            rows: 1000,
            cols: 1000,
            ..b.clone()
        },
        "rows",
        "rows * cols",
    );
    expect_invalid(
        StageParams {
            tile_px: 0,
            ..b.clone()
        },
        "tile_px",
        "1 ..=",
    );
    expect_invalid(
        StageParams {
            tile_width_px: Some(0),
            ..b.clone()
        },
        "tile_width_px",
        "1 ..=",
    );
    expect_invalid(
        StageParams {
            tile_height_px: Some(0),
            ..b.clone()
        },
        "tile_height_px",
        "1 ..=",
    );
    expect_invalid(
        StageParams {
            pitch_um: 0.0,
            ..b.clone()
        },
        "pitch_um",
        "> 0",
    );
    expect_invalid(
        StageParams {
            stage_sigma_px: -1.0,
            ..b.clone()
        },
        "stage_sigma_px",
        ">= 0",
    );
    expect_invalid(
        StageParams {
            stage_sigma_px: 1e9,
            ..b.clone()
        },
        "stage_sigma_px",
        "1000",
    );
    expect_invalid(
        StageParams {
            backlash_px: f64::INFINITY,
            ..b.clone()
        },
        "backlash_px",
        "finite",
    );
    expect_invalid(
        StageParams {
            piston_sigma_um: -0.5,
            ..b.clone()
        },
        "piston_sigma_um",
        ">= 0",
    );
    expect_invalid(
        StageParams {
            tilt_sigma_um: f64::NAN,
            ..b.clone()
        },
        "tilt_sigma_um",
        ">= 0",
    );
    expect_invalid(
        StageParams {
            noise_um: -0.02,
            ..b.clone()
        },
        "noise_um",
        ">= 0",
    );
    expect_invalid(
        StageParams {
            dropout_fraction: 1.5,
            ..b.clone()
        },
        "dropout_fraction",
        "[0, 1]",
    );
    expect_invalid(
        StageParams {
            dropout_blobs_mean: -1.0,
            ..b.clone()
        },
        "dropout_blobs_mean",
        ">= 0",
    );
    expect_invalid(
        StageParams {
            blob_radius_px: [5.0, 2.0],
            ..b.clone()
        },
        "blob_radius_px",
        "min <= max",
    );
    expect_invalid(
        StageParams {
            blob_radius_px: [0.0, 2.0],
            ..b.clone()
        },
        "blob_radius_px",
        "0 < min",
    );
}

#[test]
fn overlap_message_reads_well() {
    let err = plan_scan(&StageParams {
        overlap: 0.95,
        ..StageParams::default()
    })
    .expect_err("invalid");
    assert_eq!(
        err.to_string(),
        "invalid stage parameter `overlap` = 0.95: expected a fraction of the tile in [0, 0.95)"
    );
}

#[test]
fn huge_grids_are_refused_as_too_large() {
    let err = plan_scan(&StageParams {
        rows: 300,
        cols: 300,
        ..StageParams::default()
    })
    .expect_err("too large");
    assert!(matches!(err, ReplayError::TooLarge { .. }), "{err}");
}

#[test]
fn params_deserialize_with_defaults_and_reject_unknown_fields() {
    let p: StageParams = serde_json::from_str("{}").expect("defaults");
    assert_eq!(p, StageParams::default());
    assert_eq!((p.rows, p.cols, p.tile_px, p.seed), (2, 2, 1024, 1));
    assert_eq!(p.overlap, 0.10);
    assert_eq!(p.stage_sigma_px, 3.0);
    let p: StageParams = serde_json::from_str(
        r#"{"rows": 3, "cols": 5, "overlap": 0.2, "overlap_x": 0.15, "tile_height_px": 512}"#,
    )
    .expect("partial");
    assert_eq!(p.overlap_xy(), (0.15, 0.2));
    assert_eq!(p.tile_shape_px(), (1024, 512));
    let err =
        serde_json::from_str::<StageParams>(r#"{"rows": 3, "colums": 2}"#).expect_err("unknown");
    assert!(err.to_string().contains("unknown field `colums`"), "{err}");
    // Round trip (the truth file embeds the parameters).
    let text = serde_json::to_string(&p).expect("serialize");
    let back: StageParams = serde_json::from_str(&text).expect("round trip");
    assert_eq!(back, p);
}
