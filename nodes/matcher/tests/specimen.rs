//! Known shifts on tiles cut from real measured surfaces (tests/data/specimens, or
//! SURFSTREAM_SPECIMENS): the periodic x3p-2.x3p grating at its anisotropic pitch (0.128 x
//! 0.315 um) and the smooth metropro-1.dat, 10 % and 15 % overlaps of 220 px tiles, stage
//! errors up to 3 px, per-tile piston and tilt. Every pair must be answered within 0.5 px or
//! refused: never a wrong offset. The narrow strips of the grating are where a levelling plane
//! fitted at the wrong offset moved the answer by 1-2 px.

use std::path::{Path, PathBuf};

use surfstream_core::raster::{RasterView, Shape};
use surfstream_io::formats::read_surface;
use surfstream_matcher::{PhaseCorrelator, PhaseParams};

const TILE: usize = 220;

fn specimen(name: &str) -> PathBuf {
    std::env::var_os("SURFSTREAM_SPECIMENS")
        .map(|d| PathBuf::from(d).join(name))
        .into_iter()
        .chain([Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../tests/data/specimens")
            .join(name)])
        .find(|p| p.is_file())
        .unwrap_or_else(|| {
            panic!("specimen {name} missing: neither in tests/data/specimens nor in $SURFSTREAM_SPECIMENS")
        })
}

/// The tile whose pixel (0, 0) is the specimen's (x0, y0), plus a piston and a height change
/// `tilt_um` across the tile in x and in y.
fn cut(
    z: &[f64],
    width: usize,
    x0: usize,
    y0: usize,
    piston_um: f64,
    tilt_um: [f64; 2],
) -> Vec<f32> {
    let c = (TILE as f64 - 1.0) * 0.5;
    let mut t = Vec::with_capacity(TILE * TILE);
    for r in 0..TILE {
        for col in 0..TILE {
            let plane = piston_um
                + tilt_um[0] * (col as f64 - c) / TILE as f64
                + tilt_um[1] * (r as f64 - c) / TILE as f64;
            t.push((z[(y0 + r) * width + x0 + col] + plane) as f32);
        }
    }
    t
}

/// Stage errors (true minus nominal offset, px) up to 3 px.
const STAGE_ERRORS: [[i64; 2]; 6] = [[3, -2], [-3, 1], [2, 3], [-1, -3], [0, 2], [3, 3]];

/// Registers horizontal and vertical neighbours cut at known offsets, the stage off by
/// `errors` (along x, y; cycled); returns (answered, tried) and fails on any answer more than
/// 0.5 px off.
fn known_shifts(name: &str, overlap_px: usize, errors: &[[i64; 2]]) -> (usize, usize) {
    let s = read_surface(&specimen(name)).expect("readable specimen");
    let step = TILE - overlap_px;
    let sq = {
        let v: Vec<f64> = s
            .heights_um
            .iter()
            .copied()
            .filter(|v| v.is_finite())
            .collect();
        let m = v.iter().sum::<f64>() / v.len() as f64;
        (v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / v.len() as f64).sqrt()
    };
    let params = PhaseParams::default();
    let mut corr = PhaseCorrelator::new();
    let (mut answered, mut tried) = (0, 0);
    let mut k = 0;
    for vertical in [false, true] {
        for &(x0, y0) in &[(5usize, 5usize), (60, 20), (150, 40), (200, 50)] {
            let e = errors[k % errors.len()];
            k += 1;
            // The error's second component is along the pair's direction.
            let e = if vertical { e } else { [e[1], e[0]] };
            let truth = if vertical {
                [e[0], step as i64 + e[1]]
            } else {
                [step as i64 + e[0], e[1]]
            };
            let (bx, by) = (x0 as i64 + truth[0], y0 as i64 + truth[1]);
            let fits = |x: i64, y: i64| {
                x >= 0 && y >= 0 && x as usize + TILE <= s.width && y as usize + TILE <= s.height
            };
            if !(fits(x0 as i64, y0 as i64) && fits(bx, by)) {
                continue;
            }
            let a = cut(
                &s.heights_um,
                s.width,
                x0,
                y0,
                0.3 * sq,
                [0.5 * sq, -0.4 * sq],
            );
            let b = cut(
                &s.heights_um,
                s.width,
                bx as usize,
                by as usize,
                -0.7 * sq,
                [-0.3 * sq, 0.6 * sq],
            );
            let nominal = [truth[0] as f64 - e[0] as f64, truth[1] as f64 - e[1] as f64];
            let r = corr.register(
                RasterView::new(&a, Shape::new(TILE, TILE)).expect("tile"),
                RasterView::new(&b, Shape::new(TILE, TILE)).expect("tile"),
                nominal,
                &params,
            );
            tried += 1;
            if let Some(o) = r.offset_px {
                let err = (o[0] - truth[0] as f64).hypot(o[1] - truth[1] as f64);
                assert!(
                    err <= 0.5,
                    "{name}, overlap {overlap_px} px, {} pair at ({x0}, {y0}): offset {o:?}, \
                     truth {truth:?}, error {err:.3} px",
                    if vertical { "vertical" } else { "horizontal" }
                );
                answered += 1;
            }
        }
    }
    (answered, tried)
}

#[test]
fn periodic_x3p_grating_narrow_overlaps_are_right_or_refused() {
    for overlap_px in [22, 33] {
        let (answered, tried) = known_shifts("x3p-2.x3p", overlap_px, &STAGE_ERRORS);
        assert!(tried >= 6, "only {tried} pairs fit in the specimen");
        // Most pairs are answered: refusing everything is not the point either.
        assert!(
            answered * 4 >= tried * 3,
            "overlap {overlap_px} px: only {answered} of {tried} pairs answered"
        );
    }
}

#[test]
fn smooth_metropro_known_shifts_are_recovered() {
    for overlap_px in [22, 33] {
        let (answered, tried) = known_shifts("metropro-1.dat", overlap_px, &STAGE_ERRORS);
        assert!(tried >= 6, "only {tried} pairs fit in the specimen");
        assert_eq!(
            answered, tried,
            "overlap {overlap_px} px: all pairs answered"
        );
    }
}

/// A stage error along the pair beyond the shift limit (0.45 x the 22 px overlap = 9.9 px) but
/// within `max_shift_px`: the nominal strips then hardly share any surface, and on the grating
/// they show an alias well inside the limit (8.9 px wrong in the anchor benchmark). Such a
/// pair must never be answered at the alias: `known_shifts` asserts every answer within
/// 0.5 px. These errors widen the overlap (the tiles sit 12-18 px closer than nominal): there
/// the limit is `max_shift_px` alone, and the pairs answered are answered at the true offset
/// (before, every one was refused).
#[test]
fn periodic_x3p_grating_true_offset_beyond_the_limit_is_never_answered_at_an_alias() {
    let errors = [[-8, -16], [5, -14], [-2, -18], [7, -12]];
    let (answered, tried) = known_shifts("x3p-2.x3p", 22, &errors);
    assert!(tried >= 6, "only {tried} pairs fit in the specimen");
    eprintln!("{answered} of {tried} answered, each within 0.5 px");
}
