//! The paper's feature matchers: Harris, SIFT, NCC eq. 1, the two-way check, RANSAC, r and
//! MAP, a real specimen, NaN handling and malformed input.

use std::path::Path;

use surfstream_core::raster::{RasterView, Shape};
use surfstream_matcher::detector::{DetectorImage, DetectorParams, Rect};
use surfstream_matcher::efficiency::{aggregate, match_quality, RankedMatch};
use surfstream_matcher::feature_match::{mutual_best, ncc_eq1, ransac_translation, similarity_fit};
use surfstream_matcher::{
    harris_corners, register_pair_features, sift_keypoints, FeatureMethod, FeatureParams,
    HarrisParams, Rejection, ScanTruth, SiftParams,
};

fn image(heights: &[f32], w: usize, h: usize) -> DetectorImage {
    let r = RasterView::new(heights, Shape::new(h, w)).expect("raster");
    let params = DetectorParams {
        highpass_sigma_px: 0.0,
        smoothing_sigma_px: 0.0,
        ..Default::default()
    };
    DetectorImage::from_region(r, Rect::full(w, h), &params).expect("image")
}

#[test]
fn harris_fires_at_a_corner_not_on_an_edge_or_flat() {
    let (w, h) = (64, 64);
    // A bright quadrant: one corner at (32, 32), edges along x = 32 and y = 32 beyond it.
    let mut z = vec![0f32; w * h];
    for y in 32..h {
        for x in 32..w {
            z[y * w + x] = 1.0;
        }
    }
    let corners = harris_corners(&image(&z, w, h), &HarrisParams::default()).expect("harris");
    assert!(!corners.is_empty(), "no corner found");
    let best = corners[0];
    assert!(
        (best.x - 31.5).abs() <= 1.0 && (best.y - 31.5).abs() <= 1.0,
        "strongest corner at ({}, {}), expected near (31.5, 31.5)",
        best.x,
        best.y
    );
    // Every corner is at the quadrant's corner: none along the edges (x = 32 with y > 40, or
    // y = 32 with x > 40) or on the flat parts.
    for c in &corners {
        assert!(
            (c.x - 31.5).abs() <= 3.0 && (c.y - 31.5).abs() <= 3.0,
            "corner at ({}, {}) away from the only corner",
            c.x,
            c.y
        );
    }
    // An edge alone gives no corner.
    let mut edge = vec![0f32; w * h];
    for y in 0..h {
        for x in 32..w {
            edge[y * w + x] = 1.0;
        }
    }
    let corners = harris_corners(&image(&edge, w, h), &HarrisParams::default()).expect("harris");
    assert!(corners.is_empty(), "an edge gave corners: {corners:?}");
    let flat = vec![0.3f32; w * h];
    let corners = harris_corners(&image(&flat, w, h), &HarrisParams::default()).expect("harris");
    assert!(corners.is_empty(), "flat ground gave corners");
}

/// A smooth random surface sampled at a sub-pixel offset, from a sum of cosines (exact at any
/// position).
fn cosine_surface(w: usize, h: usize, dx: f64, dy: f64, seed: u64) -> Vec<f32> {
    let mut s = seed;
    let mut rnd = || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((s >> 11) as f64) / ((1u64 << 53) as f64)
    };
    let waves: Vec<(f64, f64, f64, f64)> = (0..60)
        .map(|_| {
            let k = 0.25 + 0.9 * rnd();
            let a = std::f64::consts::TAU * rnd();
            (
                k * a.cos(),
                k * a.sin(),
                std::f64::consts::TAU * rnd(),
                1.0 / (k * 10.0),
            )
        })
        .collect();
    let mut z = vec![0f32; w * h];
    for y in 0..h {
        for x in 0..w {
            let (px, py) = (x as f64 + dx, y as f64 + dy);
            z[y * w + x] = waves
                .iter()
                .map(|(kx, ky, ph, amp)| amp * (kx * px + ky * py + ph).cos())
                .sum::<f64>() as f32;
        }
    }
    z
}

#[test]
fn sift_keypoints_repeat_under_a_subpixel_shift_and_descriptors_match() {
    let (w, h) = (128, 128);
    let (sx, sy) = (0.4, -0.3);
    let a = cosine_surface(w, h, 0.0, 0.0, 7);
    // b(x, y) = a(x + sx, y + sy): a feature at p in a appears at p - s in b.
    let b = cosine_surface(w, h, sx, sy, 7);
    let params = DetectorParams::default();
    let ia = DetectorImage::from_region(
        RasterView::new(&a, Shape::new(h, w)).unwrap(),
        Rect::full(w, h),
        &params,
    )
    .unwrap();
    let ib = DetectorImage::from_region(
        RasterView::new(&b, Shape::new(h, w)).unwrap(),
        Rect::full(w, h),
        &params,
    )
    .unwrap();
    let ka = sift_keypoints(&ia, &SiftParams::default()).unwrap();
    let kb = sift_keypoints(&ib, &SiftParams::default()).unwrap();
    assert!(ka.len() >= 10, "only {} key points", ka.len());
    // Key points whose descriptor footprint (circumscribed radius 3 sigma x sqrt 2 x 5 / 2)
    // leaves the image are kept when half of it is inside (narrow overlap strips need them),
    // but the part outside is missing from their descriptor, so they repeat less well.
    let inside = |p: &surfstream_matcher::sift::Keypoint| {
        let r = 3.0 * p.sigma_px * std::f64::consts::SQRT_2 * 2.5 + 1.0;
        p.x >= r && p.y >= r && p.x + r < w as f64 && p.y + r < h as f64
    };
    let (mut repeated, mut matched) = ([0; 2], [0; 2]);
    for p in &ka {
        let Some(q) = kb.iter().min_by(|u, v| {
            let du = (u.x - (p.x - sx)).hypot(u.y - (p.y - sy));
            let dv = (v.x - (p.x - sx)).hypot(v.y - (p.y - sy));
            du.total_cmp(&dv)
        }) else {
            continue;
        };
        if (q.x - (p.x - sx)).hypot(q.y - (p.y - sy)) < 0.3 {
            let k = usize::from(inside(p));
            repeated[k] += 1;
            let d: f32 = p
                .descriptor
                .iter()
                .zip(&q.descriptor)
                .map(|(x, y)| (x - y) * (x - y))
                .sum::<f32>()
                .sqrt();
            if d < 0.25 {
                matched[k] += 1;
            }
        }
    }
    let all = repeated[0] + repeated[1];
    assert!(
        all * 10 >= ka.len() * 7,
        "{all} of {} key points repeated within 0.3 px",
        ka.len()
    );
    assert!(
        repeated[1] >= 10,
        "only {} interior key points",
        repeated[1]
    );
    assert!(
        matched[1] * 10 >= repeated[1] * 8,
        "{} of {} repeated interior key points have close descriptors",
        matched[1],
        repeated[1]
    );
    assert!(
        (matched[0] + matched[1]) * 4 >= all * 3,
        "{} of {all} repeated key points have close descriptors",
        matched[0] + matched[1]
    );
}

#[test]
fn ncc_eq1_equals_a_direct_computation() {
    let a = [1.0f32, 2.0, 4.0, 3.0, 0.5, 7.0];
    let b = [2.0f32, 1.0, 5.0, 3.5, 1.0, 6.0];
    // Direct: means 2.916666.. and 3.083333..
    let (ma, mb) = (17.5 / 6.0, 18.5 / 6.0);
    let num: f64 = a
        .iter()
        .zip(&b)
        .map(|(x, y)| (*x as f64 - ma) * (*y as f64 - mb))
        .sum();
    let da: f64 = a.iter().map(|x| (*x as f64 - ma).powi(2)).sum();
    let db: f64 = b.iter().map(|y| (*y as f64 - mb).powi(2)).sum();
    let direct = num / (da * db).sqrt();
    let got = ncc_eq1(&a, &b).unwrap();
    assert!((got - direct).abs() < 1e-12, "{got} vs {direct}");
    // Invariant to gain and offset; -1 for an inverted copy.
    let c: Vec<f32> = a.iter().map(|x| 3.0 * x + 2.0).collect();
    assert!((ncc_eq1(&a, &c).unwrap() - 1.0).abs() < 1e-6);
    let d: Vec<f32> = a.iter().map(|x| -x).collect();
    assert!((ncc_eq1(&a, &d).unwrap() + 1.0).abs() < 1e-6);
    // NaN pairs are left out: the same as the direct value over the other pairs.
    let mut an = a;
    an[5] = f32::NAN;
    assert!((ncc_eq1(&an, &b).unwrap() - ncc_eq1(&a[..5], &b[..5]).unwrap()).abs() < 1e-12);
    assert_eq!(ncc_eq1(&a, &b[..3]), None);
    assert_eq!(ncc_eq1(&[1.0, 1.0, 1.0], &[1.0, 2.0, 3.0]), None);
}

#[test]
fn two_way_check_drops_a_one_way_match() {
    // a0's best is b0, and b0's best is a0: kept. a1's best is b0 too, but b0 prefers a0: a1
    // is a one-way match and is dropped. a2 -> b1 mutual but below the threshold.
    let scores = vec![
        vec![(0, 0.95), (1, 0.2)],
        vec![(0, 0.9), (2, 0.5)],
        vec![(1, 0.6)],
    ];
    let m = mutual_best(&scores, 0.7);
    assert_eq!(m, vec![(0, 0, 0.95)]);
    // Without the threshold a2 -> b1 survives (b1's best is a2: 0.6 > 0.2); a1 still does
    // not (its best, b0, prefers a0).
    let m = mutual_best(&scores, -1.0);
    assert_eq!(m, vec![(0, 0, 0.95), (2, 1, 0.6)]);
}

#[test]
fn ransac_recovers_a_translation_with_40_percent_outliers() {
    let truth = [123.4, -5.6];
    let mut d = Vec::new();
    let mut s = 99u64;
    let mut rnd = || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((s >> 11) as f64) / ((1u64 << 53) as f64) - 0.5
    };
    for _ in 0..30 {
        d.push([truth[0] + 0.3 * rnd(), truth[1] + 0.3 * rnd()]);
    }
    for _ in 0..20 {
        d.push([truth[0] + 30.0 * rnd(), truth[1] + 30.0 * rnd()]);
    }
    let scores = vec![1.0; d.len()];
    let fit = ransac_translation(&d, &scores, 1.5).unwrap();
    let t = fit.translation_px;
    assert!(
        (t[0] - truth[0]).abs() < 0.1 && (t[1] - truth[1]).abs() < 0.1,
        "{t:?} vs {truth:?}"
    );
    assert!(fit.inliers[..30].iter().all(|i| *i), "an inlier was lost");
    let wrong = fit.inliers[30..].iter().filter(|i| **i).count();
    assert!(wrong <= 1, "{wrong} outliers taken as inliers");
    // The residual rotation of a pure translation is zero; a rotated set is measured.
    let a: Vec<[f64; 2]> = (0..10).map(|k| [k as f64 * 7.0, (k * k) as f64]).collect();
    let b: Vec<[f64; 2]> = a.iter().map(|p| [p[0] - 3.0, p[1] + 1.0]).collect();
    let (theta, scale) = similarity_fit(&a, &b).unwrap();
    assert!(theta.abs() < 1e-12 && (scale - 1.0).abs() < 1e-12);
    let ang = 0.01f64;
    let rot: Vec<[f64; 2]> = b
        .iter()
        .map(|p| {
            [
                ang.cos() * p[0] - ang.sin() * p[1],
                ang.sin() * p[0] + ang.cos() * p[1],
            ]
        })
        .collect();
    let (theta, _) = similarity_fit(&a, &rot).unwrap();
    assert!(
        (theta + ang).abs() < 1e-9,
        "rotation {theta}, expected {}",
        -ang
    );
}

#[test]
fn r_and_map_on_a_hand_made_example() {
    let truth = [100.0, 0.0];
    let m = |dx: f64, score: f64| RankedMatch {
        displacement_px: [100.0 + dx, 0.0],
        score,
    };
    // Ranked by score: correct, wrong, correct, wrong, correct (0.6 px off: still within 1).
    let matches = [
        m(0.0, 0.9),
        m(5.0, 0.8),
        m(0.2, 0.7),
        m(-3.0, 0.6),
        m(0.6, 0.5),
    ];
    let q = match_quality(&matches, truth, 1.0);
    assert_eq!((q.matches, q.correct), (5, 3));
    assert!((q.r.unwrap() - 0.6).abs() < 1e-12);
    // Precision at the correct ranks 1, 3, 5: 1/1, 2/3, 3/5; AP = their mean.
    let ap = (1.0 + 2.0 / 3.0 + 3.0 / 5.0) / 3.0;
    assert!((q.average_precision.unwrap() - ap).abs() < 1e-12);
    // Order given does not matter; ranking is by score.
    let mut rev = matches;
    rev.reverse();
    assert_eq!(match_quality(&rev, truth, 1.0), q);
    // A second pair with all matches wrong: r = 0, AP = 0; no matches: left out of the mean.
    let q2 = match_quality(&[m(4.0, 0.9)], truth, 1.0);
    assert_eq!((q2.r, q2.average_precision), (Some(0.0), Some(0.0)));
    let q3 = match_quality(&[], truth, 1.0);
    assert_eq!((q3.r, q3.average_precision), (None, None));
    let (r, map, n) = aggregate(&[q, q2, q3]);
    assert_eq!(n, 2);
    assert!((r.unwrap() - 0.3).abs() < 1e-12);
    assert!((map.unwrap() - ap / 2.0).abs() < 1e-12);
}

/// Two 200 x 160 px tiles cut from a real measured surface, horizontal neighbours `step` px
/// apart, at a known sub-pixel offset (bilinear resampling of the specimen for b).
fn specimen_pair(step: f64, shift: [f64; 2]) -> (Vec<f32>, Vec<f32>, usize, usize, [f64; 2]) {
    let path =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/specimens/metropro-1.dat");
    let s = surfstream_io::formats::read_surface(&path).unwrap_or_else(|e| {
        panic!(
            "{}: {e:#} (the test reads tests/data/specimens)",
            path.display()
        )
    });
    let (tw, th) = (200usize, 160usize);
    // a at (x0, y0); b at (x0 + step + shift.x, y0 + shift.y): true offset = (step + sx, sy).
    let (x0, y0) = (20.0, 20.0);
    assert!(s.width as f64 > x0 + step + tw as f64 + 5.0 && s.height as f64 > y0 + th as f64 + 5.0);
    let sample = |x: f64, y: f64| -> f32 {
        let (xi, yi) = (x.floor() as usize, y.floor() as usize);
        let (fx, fy) = (x - xi as f64, y - yi as f64);
        let z = |c: usize, r: usize| s.heights_um[r * s.width + c];
        ((1.0 - fx) * (1.0 - fy) * z(xi, yi)
            + fx * (1.0 - fy) * z(xi + 1, yi)
            + (1.0 - fx) * fy * z(xi, yi + 1)
            + fx * fy * z(xi + 1, yi + 1)) as f32
    };
    let mut a = vec![0f32; tw * th];
    let mut b = vec![0f32; tw * th];
    for y in 0..th {
        for x in 0..tw {
            a[y * tw + x] = sample(x0 + x as f64, y0 + y as f64);
            b[y * tw + x] = sample(x0 + step + shift[0] + x as f64, y0 + shift[1] + y as f64);
        }
    }
    (a, b, tw, th, [step + shift[0], shift[1]])
}

#[test]
fn known_shift_on_a_real_specimen_by_harris_and_by_sift() {
    let (a, b, w, h, truth) = specimen_pair(150.0, [2.3, -1.6]);
    let ra = RasterView::new(&a, Shape::new(h, w)).unwrap();
    let rb = RasterView::new(&b, Shape::new(h, w)).unwrap();
    // The stage's nominal offset is 3 px off the truth.
    let nominal = [150.0, 0.0];
    for method in [FeatureMethod::Harris, FeatureMethod::Sift] {
        let f = register_pair_features(ra, rb, nominal, &FeatureParams::for_method(method));
        let o = f
            .registration
            .offset_px
            .unwrap_or_else(|| panic!("{}: no answer: {:?}", method.name(), f.reason()));
        let err = (o[0] - truth[0]).abs().max((o[1] - truth[1]).abs());
        assert!(
            err <= 0.5,
            "{}: offset {o:?}, truth {truth:?}: error {err} px",
            method.name()
        );
        assert!(f.inliers >= 4, "{}: {} inliers", method.name(), f.inliers);
        let rot = f.rotation_deg.expect("rotation");
        assert!(
            rot.abs() < 0.5,
            "{}: residual rotation {rot} deg",
            method.name()
        );
        // r and AP against the truth: most two-way matches are correct.
        let q = f.quality(truth, 1.0);
        assert!(q.r.unwrap() > 0.5, "{}: r = {:?}", method.name(), q.r);
    }
}

/// SIFT on a 22 px overlap strip (10 % of a 220 px tile, as in the anchor benchmark): its
/// footprint spans most of the strip, so key points whose footprint leaves the strip must
/// still be kept (half of it measured suffices) for the pair to get enough matches.
#[test]
fn sift_registers_a_narrow_overlap_strip() {
    let mut answered = 0;
    let shifts = [[2.3, -1.6], [-1.4, 2.7], [0.6, 0.9], [-2.8, -2.2]];
    for shift in shifts {
        let (a, b, w, h, truth) = specimen_pair(178.0, shift);
        let ra = RasterView::new(&a, Shape::new(h, w)).unwrap();
        let rb = RasterView::new(&b, Shape::new(h, w)).unwrap();
        let params = FeatureParams::for_method(FeatureMethod::Sift);
        let f = register_pair_features(ra, rb, [178.0, 0.0], &params);
        if let Some(o) = f.registration.offset_px {
            let err = (o[0] - truth[0]).abs().max((o[1] - truth[1]).abs());
            assert!(err <= 0.5, "shift {shift:?}: offset {o:?}, truth {truth:?}");
            answered += 1;
        }
    }
    assert!(
        answered >= 3,
        "only {answered} of {} strips answered",
        shifts.len()
    );
}

#[test]
fn nan_blobs_never_produce_features() {
    let (w, h) = (128, 128);
    let mut z = cosine_surface(w, h, 0.0, 0.0, 3);
    // Two round dropouts.
    let blobs = [(40.0, 40.0, 12.0), (90.0, 80.0, 9.0)];
    let inside = |x: f64, y: f64, grow: f64| {
        blobs
            .iter()
            .any(|(cx, cy, r)| (x - cx).hypot(y - cy) <= r + grow)
    };
    for y in 0..h {
        for x in 0..w {
            if inside(x as f64, y as f64, 0.0) {
                z[y * w + x] = f32::NAN;
            }
        }
    }
    let params = DetectorParams::default();
    let img = DetectorImage::from_region(
        RasterView::new(&z, Shape::new(h, w)).unwrap(),
        Rect::full(w, h),
        &params,
    )
    .unwrap();
    let corners = harris_corners(&img, &HarrisParams::default()).unwrap();
    let keys = sift_keypoints(&img, &SiftParams::default()).unwrap();
    assert!(
        !corners.is_empty() && !keys.is_empty(),
        "the valid part has features"
    );
    // No feature on a blob, and none whose support is mostly a blob: the support-valid rule
    // (90 %) keeps every feature at least a few px off the blob's rim.
    for c in &corners {
        assert!(
            !inside(c.x, c.y, 1.0),
            "Harris corner at ({}, {}) on a blob",
            c.x,
            c.y
        );
        assert!(c.response.is_finite());
    }
    for k in &keys {
        assert!(
            !inside(k.x, k.y, 1.0),
            "SIFT key point at ({}, {}) on a blob",
            k.x,
            k.y
        );
        assert!(k.descriptor.iter().all(|v| v.is_finite()));
    }
    // An all-NaN region has none and no error.
    let nan = vec![f32::NAN; w * h];
    let img = DetectorImage::from_region(
        RasterView::new(&nan, Shape::new(h, w)).unwrap(),
        Rect::full(w, h),
        &params,
    )
    .unwrap();
    assert!(harris_corners(&img, &HarrisParams::default())
        .unwrap()
        .is_empty());
    assert!(sift_keypoints(&img, &SiftParams::default())
        .unwrap()
        .is_empty());
}

#[test]
fn scattered_dropouts_still_register_by_harris() {
    let (a, mut b, w, h, truth) = specimen_pair(150.0, [1.2, 0.7]);
    // Scattered dropouts on both tiles: about 2 % single pixels plus holes.
    let mut s = 5u64;
    let mut rnd = || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((s >> 11) as f64) / ((1u64 << 53) as f64)
    };
    let mut a = a;
    for t in [&mut a, &mut b] {
        for v in t.iter_mut() {
            if rnd() < 0.02 {
                *v = f32::NAN;
            }
        }
    }
    let f = register_pair_features(
        RasterView::new(&a, Shape::new(h, w)).unwrap(),
        RasterView::new(&b, Shape::new(h, w)).unwrap(),
        [149.0, 1.0],
        &FeatureParams::for_method(FeatureMethod::Harris),
    );
    let o = f
        .registration
        .offset_px
        .unwrap_or_else(|| panic!("{:?}", f.reason()));
    assert!(
        (o[0] - truth[0]).abs() <= 0.5 && (o[1] - truth[1]).abs() <= 0.5,
        "{o:?} vs {truth:?}"
    );
}

#[test]
fn malformed_input_is_a_clear_error() {
    let z = vec![0f32; 100];
    let good = RasterView::new(&z, Shape::new(10, 10)).expect("10 x 10");
    // 100 heights are not 11 x 10: the view refuses to exist.
    assert!(RasterView::new(&z, Shape::new(11, 10)).is_err());
    let p = FeatureParams::default();
    let f = register_pair_features(good, good, [f64::NAN, 0.0], &p);
    assert!(matches!(
        f.registration.rejection,
        Some(Rejection::InvalidInput(_))
    ));
    // A bad parameter names itself.
    let mut q = FeatureParams::default();
    q.harris.k = 0.2;
    let f = register_pair_features(good, good, [5.0, 0.0], &q);
    let why = f
        .registration
        .rejection
        .map(|r| r.to_string())
        .unwrap_or_default();
    assert!(why.contains("harris.k"), "{why}");
    // No overlap at all.
    let f = register_pair_features(good, good, [50.0, 0.0], &p);
    assert!(matches!(
        f.registration.rejection,
        Some(Rejection::NoOverlap { .. })
    ));
    // Truth files: errors name the file and the field.
    let path = Path::new("gt.json");
    let e = ScanTruth::parse("{\"tiles\": [{\"index\": 0}]}", path)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("gt.json") && e.contains("at tiles[0]: missing field"),
        "{e}"
    );
    // A tile whose origin is not two numbers is named by its place in the file.
    let tile = "\"index\": 0, \"row\": 0, \"col\": 0, \"nominal_origin_px\": [0, 0], \"stage_position_um\": [0, 0], \"stage_error_px\": [0, 0], \"piston\": 0, \"tilt_x\": 0, \"tilt_y\": 0";
    let e = ScanTruth::parse(
        &format!("{{\"tiles\": [{{{tile}, \"true_origin_px\": [1, 2]}}, {{{tile}, \"true_origin_px\": [\"a\", 2]}}]}}"),
        path,
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("gt.json") && e.contains("tiles[1].true_origin_px[0]"),
        "{e}"
    );
    let e = ScanTruth::parse("not json", path).unwrap_err().to_string();
    assert!(e.contains("gt.json") && e.contains("not JSON"), "{e}");
    let e = ScanTruth::parse("{}", path).unwrap_err().to_string();
    assert!(e.contains("tiles"), "{e}");
    let t = ScanTruth::parse(
        &format!("{{\"tiles\": [{{{tile}, \"true_origin_px\": [1, 2]}}, {{{}, \"true_origin_px\": [11.5, 1]}}]}}", tile.replace("\"index\": 0", "\"index\": 1")),
        path,
    )
    .unwrap();
    assert_eq!(t.true_offset_px(0, 1), Some([10.5, -1.0]));
    assert_eq!(t.true_offset_px(0, 7), None);
    let e = ScanTruth::read(Path::new("/nonexistent/ground_truth.json"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("/nonexistent/ground_truth.json"), "{e}");
}
