//! Tile acquisition: exact sampling, sub-pixel accuracy, degradations, determinism.

use rayon::prelude::*;
use surfstream_core::raster::Shape;
use surfstream_replay::{
    acquire_tile, generate_specimen, plan_scan, sample_bicubic, Specimen, SpecimenParams,
    StageParams, TilePlan,
};

/// A stage with every degradation off.
fn clean(tile_px: usize) -> StageParams {
    StageParams {
        tile_px,
        stage_sigma_px: 0.0,
        piston_sigma_um: 0.0,
        tilt_sigma_um: 0.0,
        noise_um: 0.0,
        dropout_fraction: 0.0,
        dropout_blobs_mean: 0.0,
        ..StageParams::default()
    }
}

fn tile_at(index: usize, x: f64, y: f64) -> TilePlan {
    TilePlan {
        index,
        row: 0,
        col: 0,
        nominal_origin_px: [x.round(), y.round()],
        stage_position_um: [x.round() * 0.8148, y.round() * 0.8148],
        true_origin_px: [x, y],
        true_origin_um: [x * 0.8148, y * 0.8148],
        piston_um: 0.0,
        tilt_x_um: 0.0,
        tilt_y_um: 0.0,
    }
}

fn analytic(w: usize, h: usize, f: impl Fn(f64, f64) -> f64) -> Specimen {
    let heights = (0..h)
        .flat_map(|y| (0..w).map(move |x| (x, y)))
        .map(|(x, y)| f(x as f64, y as f64) as f32)
        .collect();
    Specimen::from_heights(heights, Shape::new(h, w), 0.8148).expect("shape")
}

fn rough_specimen() -> Specimen {
    generate_specimen(&SpecimenParams {
        width_px: 200,
        height_px: 150,
        seed: 4,
        ..SpecimenParams::default()
    })
    .expect("valid")
}

#[test]
fn integer_origin_without_degradations_is_an_exact_crop() {
    let s = rough_specimen();
    let stage = StageParams {
        tile_width_px: Some(64),
        tile_height_px: Some(48),
        ..clean(0)
    };
    for (x0, y0) in [(0usize, 0usize), (17, 31), (136, 102)] {
        let tile = acquire_tile(&s, &tile_at(0, x0 as f64, y0 as f64), &stage);
        assert_eq!(tile.len(), 64 * 48);
        for i in 0..48 {
            for j in 0..64 {
                let expected = s.get(x0 + j, y0 + i).expect("inside");
                assert_eq!(
                    tile[i * 64 + j].to_bits(),
                    expected.to_bits(),
                    "({x0},{y0}) ({j},{i})"
                );
            }
        }
    }
}

#[test]
fn planned_tiles_without_degradations_are_exact_crops() {
    // tile 64, overlap 0.25: step 48, extent 112, margin 8 + 2: integer nominal origins
    let stage = StageParams {
        rows: 2,
        cols: 2,
        overlap: 0.25,
        ..clean(64)
    };
    let plan = plan_scan(&stage).expect("valid");
    let specimen =
        generate_specimen(&plan.specimen_params(&SpecimenParams::default())).expect("valid");
    plan.check_specimen(&specimen).expect("fits");
    for t in &plan.tiles {
        let [x0, y0] = t.true_origin_px;
        assert_eq!((x0.fract(), y0.fract()), (0.0, 0.0));
        let tile = acquire_tile(&specimen, t, &stage);
        for i in 0..64 {
            for j in 0..64 {
                let v = specimen
                    .get(x0 as usize + j, y0 as usize + i)
                    .expect("inside");
                assert_eq!(tile[i * 64 + j], v);
            }
        }
    }
}

#[test]
fn subpixel_sampling_reproduces_quadratics() {
    // Keys' cubic convolution (a = -0.5) reproduces polynomials up to degree 2.
    let f = |x: f64, y: f64| 0.01 * x * x - 0.02 * x * y + 0.015 * y * y + 0.3 * x - 0.2 * y + 1.0;
    let s = analytic(60, 50, f);
    let stage = clean(20);
    for (x0, y0) in [(5.25, 7.5), (10.9, 3.1), (2.001, 20.75)] {
        let tile = acquire_tile(&s, &tile_at(0, x0, y0), &stage);
        for i in 0..20 {
            for j in 0..20 {
                let exact = f(x0 + j as f64, y0 + i as f64);
                let got = f64::from(tile[i * 20 + j]);
                assert!(
                    (got - exact).abs() < 2e-5 * exact.abs().max(1.0),
                    "({j},{i}): {got} vs {exact}"
                );
            }
        }
    }
}

#[test]
fn subpixel_sampling_of_a_smooth_wave_is_accurate() {
    // A 2-D wave of 24 px wavelength, amplitude 1: bicubic error well under 1 %.
    let k = std::f64::consts::TAU / 24.0;
    let f = move |x: f64, y: f64| (k * (0.8 * x + 0.6 * y)).sin();
    let s = analytic(120, 120, f);
    let stage = clean(64);
    let mut max_err: f64 = 0.0;
    for (x0, y0) in [(10.5, 20.5), (30.25, 11.8), (7.1, 40.37)] {
        let tile = acquire_tile(&s, &tile_at(0, x0, y0), &stage);
        for i in 0..64 {
            for j in 0..64 {
                let e = (f64::from(tile[i * 64 + j]) - f(x0 + j as f64, y0 + i as f64)).abs();
                max_err = max_err.max(e);
            }
        }
    }
    assert!(max_err < 0.01, "max error {max_err}");
}

#[test]
fn tile_matches_pointwise_bicubic_samples() {
    let s = rough_specimen();
    let stage = clean(32);
    let (x0, y0) = (41.37, 12.81);
    let tile = acquire_tile(&s, &tile_at(0, x0, y0), &stage);
    for i in (0..32).step_by(5) {
        for j in (0..32).step_by(3) {
            let p = sample_bicubic(&s, x0 + j as f64, y0 + i as f64);
            assert!((tile[i * 32 + j] - p).abs() < 1e-5, "({j},{i})");
        }
    }
    // Shifting the origin by one pixel shifts the tile by one pixel.
    let shifted = acquire_tile(&s, &tile_at(0, x0 + 1.0, y0 + 1.0), &stage);
    for i in 0..31 {
        for j in 0..31 {
            assert!((shifted[i * 32 + j] - tile[(i + 1) * 32 + j + 1]).abs() < 1e-5);
        }
    }
}

#[test]
fn outside_the_specimen_is_nan_not_a_panic() {
    let s = rough_specimen(); // 200 x 150
    let stage = clean(32);
    let tile = acquire_tile(&s, &tile_at(0, -10.5, 3.0), &stage);
    assert!(tile[0].is_nan()); // x = -10.5
    assert!(tile[3 * 32 + 20].is_finite()); // x = 9.5, y = 6
    let tile = acquire_tile(&s, &tile_at(0, 190.0, 140.0), &stage);
    assert!(tile[0].is_finite());
    assert!(tile[31 * 32 + 31].is_nan());
    for (x, y) in [
        (f64::NAN, 0.0),
        (0.0, f64::INFINITY),
        (1e300, -1e300),
        (-5000.0, 10.0),
    ] {
        let tile = acquire_tile(&s, &tile_at(0, x, y), &stage);
        assert_eq!(tile.len(), 32 * 32);
        assert!(tile.iter().all(|v| v.is_nan()));
    }
    assert!(sample_bicubic(&s, 0.5, 0.5).is_nan()); // support reaches x = -1
    assert!(sample_bicubic(&s, 1.5, 1.5).is_finite());
    assert_eq!(sample_bicubic(&s, 0.0, 0.0), s.get(0, 0).expect("inside"));
}

#[test]
fn piston_and_tilt_add_the_documented_plane() {
    let s = rough_specimen();
    let stage = clean(40);
    let base = tile_at(3, 20.0, 30.0);
    let posed = TilePlan {
        piston_um: 0.7,
        tilt_x_um: 0.4,
        tilt_y_um: -0.2,
        ..base.clone()
    };
    let a = acquire_tile(&s, &base, &stage);
    let b = acquire_tile(&s, &posed, &stage);
    for i in 0..40 {
        for j in 0..40 {
            let xn = (j as f64 - 19.5) / 40.0;
            let yn = (i as f64 - 19.5) / 40.0;
            let plane = 0.7 + 0.4 * xn - 0.2 * yn;
            let d = f64::from(b[i * 40 + j] - a[i * 40 + j]);
            assert!((d - plane).abs() < 1e-5, "({j},{i}): {d} vs {plane}");
        }
    }
}

#[test]
fn noise_has_the_requested_sigma() {
    let s = rough_specimen();
    let noisy = StageParams {
        noise_um: 0.1,
        ..clean(100)
    };
    let t = tile_at(0, 50.0, 25.0);
    let a = acquire_tile(&s, &t, &clean(100));
    let b = acquire_tile(&s, &t, &noisy);
    let d: Vec<f64> = a.iter().zip(&b).map(|(x, y)| f64::from(y - x)).collect();
    let mean = d.iter().sum::<f64>() / d.len() as f64;
    let sd = (d.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / d.len() as f64).sqrt();
    assert!(mean.abs() < 0.005, "{mean}");
    assert!((sd / 0.1 - 1.0).abs() < 0.03, "{sd}");
}

#[test]
fn dropout_pixels_have_the_requested_fraction() {
    let s = analytic(300, 300, |_, _| 0.0);
    let stage = StageParams {
        dropout_fraction: 0.01,
        ..clean(256)
    };
    let tile = acquire_tile(&s, &tile_at(0, 10.0, 10.0), &stage);
    let nan = tile.iter().filter(|v| v.is_nan()).count() as f64 / tile.len() as f64;
    // 65536 pixels: binomial sigma ~ 0.0004
    assert!((nan - 0.01).abs() < 0.0015, "{nan}");
    let all = StageParams {
        dropout_fraction: 1.0,
        ..clean(16)
    };
    assert!(acquire_tile(&s, &tile_at(0, 10.0, 10.0), &all)
        .iter()
        .all(|v| v.is_nan()));
}

#[test]
fn dropout_blobs_are_clusters() {
    let s = analytic(300, 300, |_, _| 0.0);
    let stage = StageParams {
        dropout_blobs_mean: 4.0,
        blob_radius_px: [3.0, 5.0],
        ..clean(256)
    };
    let mut total = 0;
    for index in 0..8 {
        let tile = acquire_tile(&s, &tile_at(index, 10.0, 10.0), &stage);
        let nan: Vec<usize> = (0..tile.len()).filter(|&k| tile[k].is_nan()).collect();
        total += nan.len();
        // every NaN pixel of a blob of semi-axes >= 3 px has a NaN 4-neighbour
        for &k in &nan {
            let (i, j) = (k / 256, k % 256);
            let neighbours = [
                (i > 0).then(|| k - 256),
                (i < 255).then(|| k + 256),
                (j > 0).then(|| k - 1),
                (j < 255).then(|| k + 1),
            ];
            assert!(
                neighbours.iter().flatten().any(|&n| tile[n].is_nan()),
                "isolated {k}"
            );
        }
    }
    // 8 tiles x 4 blobs x ~ pi * 4^2 px
    assert!(total > 400, "{total}");
}

#[test]
fn default_degradations_are_present_and_tile_is_mostly_valid() {
    let s = rough_specimen();
    let stage = StageParams {
        tile_px: 128,
        ..StageParams::default()
    };
    let tile = acquire_tile(&s, &tile_at(0, 30.0, 10.0), &stage);
    let nan = tile.iter().filter(|v| v.is_nan()).count();
    assert!(nan > 0 && nan < tile.len() / 10, "{nan}");
}

#[test]
fn tiles_are_deterministic_per_seed_and_index_in_any_order() {
    let stage = StageParams {
        rows: 2,
        cols: 3,
        ..StageParams::default()
    };
    let stage = StageParams {
        tile_px: 48,
        ..stage
    };
    let plan = plan_scan(&stage).expect("valid");
    let specimen =
        generate_specimen(&plan.specimen_params(&SpecimenParams::default())).expect("valid");
    let forward: Vec<Vec<u32>> = plan
        .tiles
        .iter()
        .map(|t| {
            acquire_tile(&specimen, t, &stage)
                .iter()
                .map(|v| v.to_bits())
                .collect()
        })
        .collect();
    let mut backward: Vec<Vec<u32>> = plan
        .tiles
        .iter()
        .rev()
        .map(|t| {
            acquire_tile(&specimen, t, &stage)
                .iter()
                .map(|v| v.to_bits())
                .collect()
        })
        .collect();
    backward.reverse();
    let parallel: Vec<Vec<u32>> = plan
        .tiles
        .par_iter()
        .map(|t| {
            acquire_tile(&specimen, t, &stage)
                .iter()
                .map(|v| v.to_bits())
                .collect()
        })
        .collect();
    assert_eq!(forward, backward);
    assert_eq!(forward, parallel);
    // Another seed changes the noise.
    let other = StageParams {
        seed: 99,
        ..stage.clone()
    };
    let t0 = acquire_tile(&specimen, &plan.tiles[0], &other);
    let diff = t0
        .iter()
        .zip(&forward[0])
        .filter(|(a, b)| a.to_bits() != **b)
        .count();
    assert!(diff > t0.len() / 2, "{diff}");
}

#[test]
fn tile_shape_follows_width_and_height_overrides() {
    let s = rough_specimen();
    let stage = StageParams {
        tile_width_px: Some(30),
        tile_height_px: Some(10),
        ..clean(5)
    };
    let tile = acquire_tile(&s, &tile_at(0, 3.0, 4.0), &stage);
    assert_eq!(tile.len(), 300);
    assert_eq!(tile[29], s.get(32, 4).expect("inside"));
    assert_eq!(tile[30 * 9], s.get(3, 13).expect("inside"));
}
