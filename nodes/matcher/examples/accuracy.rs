//! Accuracy survey of the registration on synthetic pairs: the default parameters against the
//! alternatives (sub-pixel estimators, window, spectral Gaussian, dropout fill), all on the
//! same pairs (10, 20 and 30 % overlap, horizontal and vertical neighbours). This is how the
//! defaults were chosen.
//!
//! `cargo run --release -p surfstream-matcher --example accuracy -- [TILE_PX] [PAIRS_PER_CASE]
//! [NOISE_UM] [NAN_FRACTION] [NAN_BLOBS]
//! [CORR_LEN_PX] [CUTOFF_CYCLES_PER_PX]`

#[path = "../tests/support/mod.rs"]
mod support;

use support::{make_pair, PairSpec, Surface};
use surfstream_core::raster::{RasterView, Shape};
use surfstream_matcher::{PhaseCorrelator, PhaseParams, SubPixel, Window};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let arg = |i: usize, d: f64| -> f64 { args.get(i).and_then(|s| s.parse().ok()).unwrap_or(d) };
    let tile = arg(1, 256.0) as usize;
    let per_case = arg(2, 6.0) as usize;
    let noise = arg(3, 0.05);
    let nan = arg(4, 0.05);
    let blobs = arg(5, 3.0) as usize;
    let corr_len = arg(6, 40.0);
    let cutoff = arg(7, 0.25);

    let d = PhaseParams::default();
    let configs: Vec<(&str, PhaseParams)> = vec![
        ("default (NCC Gaussian)", d.clone()),
        (
            "NCC parabola",
            PhaseParams {
                subpixel: SubPixel::NccParabolic,
                ..d.clone()
            },
        ),
        (
            "phase pass 2, Gaussian",
            PhaseParams {
                subpixel: SubPixel::PhaseGaussian,
                ..d.clone()
            },
        ),
        (
            "phase pass 2, parabola",
            PhaseParams {
                subpixel: SubPixel::PhaseParabolic,
                ..d.clone()
            },
        ),
        (
            "phase pass 2, Foroosh",
            PhaseParams {
                subpixel: SubPixel::PhaseForoosh,
                ..d.clone()
            },
        ),
        (
            "phase pass 2, Foroosh, sigma 0",
            PhaseParams {
                subpixel: SubPixel::PhaseForoosh,
                peak_sigma_px: 0.0,
                ..d.clone()
            },
        ),
        (
            "phase pass 2, Gaussian, no fill",
            PhaseParams {
                subpixel: SubPixel::PhaseGaussian,
                fill_dropouts: false,
                ..d.clone()
            },
        ),
        (
            "NCC Gaussian, sigma 0",
            PhaseParams {
                peak_sigma_px: 0.0,
                ..d.clone()
            },
        ),
        (
            "NCC Gaussian, Hann window",
            PhaseParams {
                window: Window::Hann,
                ..d.clone()
            },
        ),
    ];
    // errs[config][overlap index]
    let mut errs: Vec<[Vec<f64>; 3]> = vec![Default::default(); configs.len()];
    let mut rejected = vec![0usize; configs.len()];
    let mut corr = PhaseCorrelator::new();
    let mut seed = 1u64;
    for (oi, overlap) in [0.1, 0.2, 0.3].into_iter().enumerate() {
        for k in 0..per_case {
            for horizontal in [true, false] {
                let spec = PairSpec {
                    noise_um: noise,
                    nan_fraction: nan,
                    nan_blobs: blobs,
                    ..PairSpec::new(tile, overlap, horizontal, seed * 7 + k as u64)
                };
                let (nx, ny) = spec.surface_dims();
                let surface = Surface::rough(nx, ny, 1000 + seed, corr_len, 0.8, cutoff);
                seed += 1;
                let pair = make_pair(&surface, &spec);
                let a =
                    RasterView::new(&pair.a, Shape::new(pair.h, pair.w)).expect("synthetic tile");
                let b =
                    RasterView::new(&pair.b, Shape::new(pair.h, pair.w)).expect("synthetic tile");
                for (i, (_, p)) in configs.iter().enumerate() {
                    let r = corr.register(a, b, pair.nominal_offset_px, p);
                    match r.offset_px {
                        Some(o) => errs[i][oi].push(
                            (o[0] - pair.true_offset_px[0])
                                .abs()
                                .max((o[1] - pair.true_offset_px[1]).abs()),
                        ),
                        None => rejected[i] += 1,
                    }
                }
            }
        }
    }
    println!(
        "tile {tile} px, surface corr. length {corr_len} px cutoff {cutoff}/px, noise {noise} um, NaN {nan} + {blobs} blobs, {} pairs; error = max over x, y of |measured - true| (px)",
        6 * per_case
    );
    println!(
        "{:32} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8}",
        "configuration", "rms", "max 10%", "max 20%", "max 30%", "max all", "rejected"
    );
    for (i, (name, _)) in configs.iter().enumerate() {
        let all: Vec<f64> = errs[i].iter().flatten().copied().collect();
        let rms = (all.iter().map(|v| v * v).sum::<f64>() / all.len().max(1) as f64).sqrt();
        let max = |v: &[f64]| v.iter().copied().fold(0.0f64, f64::max);
        println!(
            "{name:32} {rms:8.4} {:8.4} {:8.4} {:8.4} {:8.4} {:>8}",
            max(&errs[i][0]),
            max(&errs[i][1]),
            max(&errs[i][2]),
            max(&all),
            rejected[i]
        );
    }
}
