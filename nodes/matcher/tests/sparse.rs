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
    let noise = Normal::new(0.0, 0.002).unwrap();
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
fn pair_errors() -> Vec<Option<f64>> {
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
        // solve can live with; a wrong offset is not.
        errors.push(
            r.offset_px
                .map(|o| (o[0] - truth[0]).hypot(o[1] - truth[1])),
        );
    }
    errors
}

/// Measured: with the cross term 15 of 16 pairs within 0.1 px (median 0.03 px); fitting x and
/// y apart, 5 of 16 (median 0.14 px). The one pair beyond (0.67 px either way, NCC peak
/// roundness 0.13) is a scratch crossing that leaves the peak nearly a ridge: see
/// docs/registration.md, "what is left".
#[test]
fn slanted_scratches_on_a_polished_field_register_within_a_tenth_of_a_pixel() {
    let all = pair_errors();
    let e: Vec<f64> = all.iter().flatten().copied().collect();
    eprintln!("errors px: {e:.3?}");
    assert_eq!(e.len(), all.len(), "every pair answered");
    let within = e.iter().filter(|&&v| v <= 0.1).count();
    assert!(within >= 14, "{within} of {} pairs within 0.1 px", e.len());
    assert!(
        e.iter().all(|&v| v < 1.0),
        "no pair wrong by a pixel or more"
    );
}
