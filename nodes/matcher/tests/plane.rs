//! Piston and tilt: plane fits, the correction helpers, and the z alignment of a tile against
//! already-levelled neighbours (bilinear sampling at sub-pixel offsets, dropouts, thin strips,
//! bad input).

mod support;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use support::{cut, Surface};
use surfstream_core::raster::{Raster, RasterView, Shape};
use surfstream_matcher::{
    estimate_plane, estimate_plane_report, fit_plane, PlaneCorrection, PlaneError, PlaneModel,
};

/// The view of `rows x cols` heights (well-formed in every test that uses it).
fn raster(heights: &[f32], rows: usize, cols: usize) -> RasterView<'_, f32> {
    RasterView::new(heights, Shape::new(rows, cols)).expect("raster shape")
}

/// `z + correction(row, col)` for every pixel of a `w x h` tile (the raw tile whose
/// corrected version is `z`).
fn add_plane(z: &[f32], w: usize, h: usize, p: &PlaneCorrection) -> Vec<f32> {
    z.iter()
        .enumerate()
        .map(|(i, &v)| (v as f64 + p.at((i / w) as f64, (i % w) as f64, Shape::new(h, w))) as f32)
        .collect()
}

fn drop_random(z: &mut [f32], fraction: f64, rng: &mut ChaCha8Rng) {
    for v in z.iter_mut() {
        if rng.gen::<f64>() < fraction {
            *v = f32::NAN;
        }
    }
}

fn add_noise(z: &mut [f32], sigma_um: f64, rng: &mut ChaCha8Rng) {
    use rand_distr::{Distribution, Normal};
    let n = Normal::new(0.0, sigma_um).expect("normal");
    for v in z.iter_mut() {
        *v += n.sample(rng) as f32;
    }
}

fn assert_close(got: &PlaneCorrection, want: &PlaneCorrection, tol_um: f64, tol_tilt: f64) {
    assert!(
        (got.piston_um - want.piston_um).abs() <= tol_um
            && (got.tilt_x_um_per_px - want.tilt_x_um_per_px).abs() <= tol_tilt
            && (got.tilt_y_um_per_px - want.tilt_y_um_per_px).abs() <= tol_tilt,
        "got {got:?}, want {want:?}"
    );
}

#[test]
fn correction_helpers_follow_the_convention() {
    let p = PlaneCorrection {
        piston_um: 2.0,
        tilt_x_um_per_px: 0.1,
        tilt_y_um_per_px: -0.05,
    };
    // Centre of a 5 x 3 tile is (row 1, col 2).
    let shape = Shape::new(3, 5);
    assert_eq!(p.at(1.0, 2.0, shape), 2.0);
    assert!((p.at(0.0, 4.0, shape) - (2.0 + 0.2 + 0.05)).abs() < 1e-12);
    let raw = add_plane(&[0.0; 15], 5, 3, &p);
    let mut z = Raster::new(raw.clone(), shape).expect("valid raster");
    z.values_mut()[7] = f32::NAN;
    p.apply(&mut z);
    for (i, v) in z.values().iter().enumerate() {
        if i == 7 {
            assert!(v.is_nan());
        } else {
            assert!(v.abs() < 1e-6, "{i}: {v}");
        }
    }
    let c = p.corrected(RasterView::new(&raw, shape).expect("valid raster"));
    assert!(c.values().iter().all(|v| v.abs() < 1e-6));
    let sum = p.then(&p);
    assert_eq!(sum.piston_um, 4.0);
}

#[test]
fn fit_plane_recovers_a_plane_through_dropouts() {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let want = PlaneCorrection {
        piston_um: 812.5,
        tilt_x_um_per_px: 0.003,
        tilt_y_um_per_px: -0.007,
    };
    let (w, h) = (300, 200);
    let mut z = add_plane(&vec![0.0; w * h], w, h, &want);
    drop_random(&mut z, 0.3, &mut rng);
    let got = fit_plane(raster(&z, h, w)).expect("a plane");
    assert_close(&got, &want, 1e-3, 1e-6);
    assert!(fit_plane(raster(&[f32::NAN; 4], 2, 2)).is_none());
    // Three heights cannot be a 2 x 2 tile: the view refuses to exist.
    assert!(RasterView::new(&[1.0f32; 3], Shape::new(2, 2)).is_err());
}

/// A b tile with a left and a top neighbour, all cut from one rough surface; b sits at a
/// sub-pixel offset. Returns (b raw, left raw, top raw, offsets of b relative to left and
/// top, true corrections of b, left, top).
struct Scene {
    b: Vec<f32>,
    left: Vec<f32>,
    top: Vec<f32>,
    off_left: [f64; 2],
    off_top: [f64; 2],
    plane_b: PlaneCorrection,
    plane_left: PlaneCorrection,
    plane_top: PlaneCorrection,
}

const T: usize = 256;

fn scene(step: usize, frac: [f64; 2], seed: u64) -> Scene {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let m = 4;
    let n = surfstream_core::fft::fast_len(T + step + 2 * m);
    let surface = Surface::rough(n, n, seed, 40.0, 0.8, 0.25);
    let (f0, f1) = surface.render_pair(frac[0], frac[1]);
    // b at (m + step + fx, m + step + fy); left at (m, m + step); top at (m + step, m).
    let truth_b = cut(&f1, n, m + step, m + step, T, T);
    let truth_left = cut(&f0, n, m, m + step, T, T);
    let truth_top = cut(&f0, n, m + step, m, T, T);
    let mut plane = || PlaneCorrection {
        piston_um: rng.gen_range(-5.0..5.0),
        tilt_x_um_per_px: rng.gen_range(-0.005..0.005),
        tilt_y_um_per_px: rng.gen_range(-0.005..0.005),
    };
    let (plane_b, plane_left, plane_top) = (plane(), plane(), plane());
    let mut b = add_plane(&truth_b, T, T, &plane_b);
    let mut left = add_plane(&truth_left, T, T, &plane_left);
    let mut top = add_plane(&truth_top, T, T, &plane_top);
    for z in [&mut b, &mut left, &mut top] {
        add_noise(z, 0.05, &mut rng);
        drop_random(z, 0.1, &mut rng);
    }
    Scene {
        b,
        left,
        top,
        off_left: [step as f64 + frac[0], frac[1]],
        off_top: [frac[0], step as f64 + frac[1]],
        plane_b,
        plane_left,
        plane_top,
    }
}

#[test]
fn plane_of_a_tile_against_two_levelled_neighbours() {
    for (seed, frac) in [(11, [0.37, 0.81]), (12, [0.0, 0.5]), (13, [0.93, 0.12])] {
        let s = scene(230, frac, seed);
        let neighbours = [
            (raster(&s.left, T, T), s.off_left, s.plane_left),
            (raster(&s.top, T, T), s.off_top, s.plane_top),
        ];
        let est = estimate_plane_report(raster(&s.b, T, T), &neighbours).expect("an estimate");
        eprintln!(
            "seed {seed}: got {:?}, want {:?}, {} samples, rms {:.3} um",
            est.correction, s.plane_b, est.samples, est.rms_residual_um
        );
        assert_eq!(est.model, PlaneModel::Full);
        assert_close(&est.correction, &s.plane_b, 0.01, 5e-5);
        assert!(est.rms_residual_um < 0.1, "{}", est.rms_residual_um);
        // The plain entry point agrees.
        assert_eq!(
            estimate_plane(raster(&s.b, T, T), &neighbours),
            Some(est.correction)
        );
    }
}

#[test]
fn one_neighbour_with_a_normal_overlap_fits_the_full_plane() {
    let s = scene(205, [0.25, 0.6], 21);
    let est = estimate_plane_report(
        raster(&s.b, T, T),
        &[(raster(&s.left, T, T), s.off_left, s.plane_left)],
    )
    .expect("an estimate");
    assert_eq!(est.model, PlaneModel::Full);
    // The tilt across a 51 px strip is less well determined than along it.
    assert_close(&est.correction, &s.plane_b, 0.03, 2e-4);
}

#[test]
fn thin_strip_falls_back_to_the_tilt_along_it() {
    // b overlaps its left neighbour by a single column of pixels.
    let s = scene(255, [0.0, 0.4], 31);
    let b_flat_x = PlaneCorrection {
        tilt_x_um_per_px: 0.0,
        ..s.plane_b
    };
    let truth_b: Vec<f32> = {
        // Re-level b with its true plane, then give it a plane without x tilt.
        let z = s
            .plane_b
            .corrected(RasterView::new(&s.b, Shape::new(T, T)).expect("valid"))
            .into_values();
        add_plane(&z, T, T, &b_flat_x)
    };
    let est = estimate_plane_report(
        raster(&truth_b, T, T),
        &[(raster(&s.left, T, T), s.off_left, s.plane_left)],
    )
    .expect("an estimate");
    eprintln!("{est:?}");
    assert_eq!(est.model, PlaneModel::AlongStrip);
    assert_eq!(est.correction.tilt_x_um_per_px, 0.0);
    assert_close(&est.correction, &b_flat_x, 0.02, 1e-4);
}

#[test]
fn no_overlap_or_bad_input_gives_none() {
    let s = scene(230, [0.5, 0.5], 41);
    let b = raster(&s.b, T, T);
    // Too far away.
    let far = [(raster(&s.left, T, T), [400.0, 0.0], s.plane_left)];
    assert_eq!(estimate_plane(b, &far), None);
    assert_eq!(
        estimate_plane_report(b, &far).map(|e| e.samples),
        Err(PlaneError::NoOverlap)
    );
    assert_eq!(estimate_plane(b, &[]), None);
    // A wrong slice length or a zero size cannot make a neighbour's view; a non-finite offset
    // is the input error left to refuse.
    assert!(RasterView::new(&s.left[1..], Shape::new(T, T)).is_err());
    assert!(RasterView::<f32>::new(&[], Shape::new(0, 0)).is_err());
    let nan = [(raster(&s.left, T, T), [f64::NAN, 0.0], s.plane_left)];
    assert_eq!(estimate_plane(b, &nan), None);
    assert!(matches!(
        estimate_plane_report(b, &nan),
        Err(PlaneError::Input(_))
    ));
    // An overlap that is all dropouts.
    let holes = vec![f32::NAN; T * T];
    let dark = [(raster(&holes, T, T), s.off_left, s.plane_left)];
    assert_eq!(
        estimate_plane_report(b, &dark).map(|e| e.samples),
        Err(PlaneError::NoOverlap)
    );
}
