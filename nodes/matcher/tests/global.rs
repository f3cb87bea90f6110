//! The global solve on a whole synthetic scan: tiles cut at known sub-pixel origins from one
//! rough surface, each with its own piston, tilt, noise and dropouts; every grid-neighbour pair
//! registered by the crate's phase correlation, one link corrupted on purpose, then
//! `solve_positions` and `solve_planes` against the truth.

mod support;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use support::{cut, Defects, Surface};
use surfstream_core::raster::{RasterView, Shape};
use surfstream_matcher::{
    solve_planes, solve_positions, Link, PhaseCorrelator, PhaseParams, PlaneCorrection, SolveParams,
};

const TILE: usize = 256;
const STEP: f64 = 205.0; // 20 % overlap
const NOISE_UM: f64 = 0.02;

struct Scan {
    rows: usize,
    cols: usize,
    tiles: Vec<Vec<f32>>,
    truth_px: Vec<[f64; 2]>,
    stage_px: Vec<[f64; 2]>,
    defects: Vec<Defects>,
}

fn scan(rows: usize, cols: usize, seed: u64, corr_len_px: f64, cutoff: f64) -> Scan {
    let n = 768;
    let surface = Surface::rough(n, n, seed, corr_len_px, 0.8, cutoff);
    let mut rng = ChaCha8Rng::seed_from_u64(seed + 100);
    let mut s = Scan {
        rows,
        cols,
        tiles: Vec::new(),
        truth_px: Vec::new(),
        stage_px: Vec::new(),
        defects: Vec::new(),
    };
    for r in 0..rows {
        for c in 0..cols {
            let nominal = [20.0 + c as f64 * STEP, 20.0 + r as f64 * STEP];
            let truth = [
                nominal[0] + rng.gen_range(-4.0..4.0),
                nominal[1] + rng.gen_range(-4.0..4.0),
            ];
            let (fx, fy) = (truth[0].fract(), truth[1].fract());
            let (_, shifted) = surface.render_pair(fx, fy);
            let mut tile = cut(
                &shifted,
                n,
                truth[0].floor() as usize,
                truth[1].floor() as usize,
                TILE,
                TILE,
            );
            let d = Defects::random(&mut rng, NOISE_UM, 0.05, 1);
            d.apply(&mut tile, TILE, TILE, &mut rng);
            s.tiles.push(tile);
            s.truth_px.push(truth);
            s.stage_px.push(nominal);
            s.defects.push(d);
        }
    }
    s
}

fn raster(t: &[f32]) -> RasterView<'_, f32> {
    RasterView::new(t, Shape::new(TILE, TILE)).expect("tile size")
}

/// Every grid-neighbour pair, registered; (a, b, offset).
fn register_all(s: &Scan) -> Vec<(usize, usize, [f64; 2])> {
    let mut corr = PhaseCorrelator::new();
    let params = PhaseParams::default();
    let mut out = Vec::new();
    for r in 0..s.rows {
        for c in 0..s.cols {
            let a = r * s.cols + c;
            let right = (c + 1 < s.cols).then_some(a + 1);
            let down = (r + 1 < s.rows).then_some(a + s.cols);
            for b in [right, down].into_iter().flatten() {
                let nominal = [
                    s.stage_px[b][0] - s.stage_px[a][0],
                    s.stage_px[b][1] - s.stage_px[a][1],
                ];
                let reg = corr.register(raster(&s.tiles[a]), raster(&s.tiles[b]), nominal, &params);
                let off = reg
                    .offset_px
                    .unwrap_or_else(|| panic!("pair {a}-{b}: {:?}", reg.rejection));
                out.push((a, b, off));
            }
        }
    }
    out
}

/// Position errors after removing the mean translation: (rms, max), px.
fn position_errors(got: &[[f64; 2]], truth: &[[f64; 2]]) -> (f64, f64) {
    let n = got.len() as f64;
    let mean = [0, 1].map(|k| got.iter().zip(truth).map(|(g, t)| g[k] - t[k]).sum::<f64>() / n);
    let errs: Vec<f64> = got
        .iter()
        .zip(truth)
        .map(|(g, t)| (g[0] - t[0] - mean[0]).hypot(g[1] - t[1] - mean[1]))
        .collect();
    let rms = (errs.iter().map(|e| e * e).sum::<f64>() / n).sqrt();
    (rms, errs.iter().cloned().fold(0.0, f64::max))
}

#[test]
fn global_solve_recovers_positions_and_removes_an_injected_outlier() {
    let s = scan(3, 3, 7, 20.0, 0.35);
    let pairs = register_all(&s);
    assert_eq!(pairs.len(), 12);
    let mut links: Vec<Link> = pairs
        .iter()
        .map(|&(a, b, off)| Link {
            a,
            b,
            offset_px: off,
            sigma_px: 0.05,
        })
        .collect();
    // Pairwise accuracy first: every link within 0.1 px of the truth.
    for l in &links {
        for k in 0..2 {
            let t = s.truth_px[l.b][k] - s.truth_px[l.a][k];
            assert!((l.offset_px[k] - t).abs() < 0.1, "{l:?}: truth {t}");
        }
    }
    // A link one period of a periodic texture off (what a pairwise matcher can get wrong).
    let bad = 5;
    links[bad].offset_px[1] += 11.0;
    let sol = solve_positions(&s.stage_px, &links, &SolveParams::default()).expect("solve");
    let removed: Vec<usize> = (0..links.len()).filter(|&k| !sol.links[k].kept).collect();
    assert_eq!(removed, vec![bad]);
    assert!(sol.linked.iter().all(|&l| l));
    let (rms, max) = position_errors(&sol.positions_px, &s.truth_px);
    assert!(rms < 0.05 && max < 0.1, "rms {rms} px, max {max} px");
    // Without the solve's outlier removal the same link would have moved tiles by pixels.
    let stage_rms = position_errors(&s.stage_px, &s.truth_px).0;
    assert!(stage_rms > 1.0, "{stage_rms}");
}

#[test]
fn global_z_alignment_removes_piston_and_tilt_below_the_noise() {
    // Band-limited like an objective's transfer function (cutoff 0.15 cycles/px): the cubic
    // resampling of the neighbour at the sub-pixel offset is then accurate to well below the
    // noise (0.006 um rms without noise; bilinear left 0.028 um, and plane errors of 0.025 um).
    let s = scan(3, 3, 11, 20.0, 0.15);
    let pairs = register_all(&s);
    let overlaps: Vec<(usize, usize)> = pairs.iter().map(|p| (p.0, p.1)).collect();
    let rasters: Vec<RasterView<'_, f32>> = s.tiles.iter().map(|t| raster(t)).collect();
    let sol = solve_planes(&rasters, &s.truth_px, &overlaps, 0, 1).expect("planes");
    // The truth relative to the gauge tile 0: correction_i at tile i's pixel = its defect plane
    // minus tile 0's defect plane at the same point of the surface.
    let d0 = &s.defects[0];
    let mut worst_rms: f64 = 0.0;
    for (i, got) in sol.corrections.iter().enumerate() {
        let d = &s.defects[i];
        let dx = s.truth_px[i][0] - s.truth_px[0][0];
        let dy = s.truth_px[i][1] - s.truth_px[0][1];
        let want = PlaneCorrection {
            piston_um: d.piston_um
                - d0.piston_um
                - d0.tilt_x_um_per_px * dx
                - d0.tilt_y_um_per_px * dy,
            tilt_x_um_per_px: d.tilt_x_um_per_px - d0.tilt_x_um_per_px,
            tilt_y_um_per_px: d.tilt_y_um_per_px - d0.tilt_y_um_per_px,
        };
        // RMS over the tile of the plane left after correction: sqrt(dp^2 + dtx^2 var(x) +
        // dty^2 var(y)) with var = (n^2 - 1) / 12 for n pixels.
        let var = ((TILE * TILE) as f64 - 1.0) / 12.0;
        let rms = ((got.piston_um - want.piston_um).powi(2)
            + (got.tilt_x_um_per_px - want.tilt_x_um_per_px).powi(2) * var
            + (got.tilt_y_um_per_px - want.tilt_y_um_per_px).powi(2) * var)
            .sqrt();
        worst_rms = worst_rms.max(rms);
    }
    // The defects were up to +-5 um piston and +-0.64 um of tilt at the tile edges; what is
    // left is below the noise on every tile (the farthest tile from the gauge is the worst).
    assert!(
        worst_rms < NOISE_UM,
        "worst residual plane rms {worst_rms} um, noise {NOISE_UM} um"
    );
    // Over the overlaps, only noise (sqrt(2) x 0.02 um) and resampling remain.
    assert!(
        sol.rms_before_um > 1.0 && sol.rms_residual_um < 2.0 * NOISE_UM,
        "{} -> {} um",
        sol.rms_before_um,
        sol.rms_residual_um
    );
}

#[test]
fn tile_without_trustworthy_links_is_placed_by_the_stage() {
    let s = scan(2, 2, 3, 20.0, 0.35);
    let pairs = register_all(&s);
    // Tile 3's links are refused (as on a featureless or periodic tile): it keeps its stage
    // position in the frame the other tiles define.
    let links: Vec<Link> = pairs
        .iter()
        .filter(|p| p.1 != 3)
        .map(|&(a, b, off)| Link {
            a,
            b,
            offset_px: off,
            sigma_px: 0.05,
        })
        .collect();
    let sol = solve_positions(&s.stage_px, &links, &SolveParams::default()).expect("solve");
    assert_eq!(sol.linked, vec![true, true, true, false]);
    let (rms, _) = position_errors(&sol.positions_px[..3], &s.truth_px[..3]);
    assert!(rms < 0.05, "{rms}");
    for k in 0..2 {
        assert!((sol.positions_px[3][k] - s.stage_px[3][k]).abs() < 0.5);
    }
}

#[test]
fn solve_planes_refuses_malformed_input() {
    let t = vec![0.0f32; TILE * TILE];
    let small = vec![0.0f32; 16];
    let r = raster(&t);
    let s4 = RasterView::new(&small, Shape::new(4, 4)).expect("4x4");
    let p = [[0.0, 0.0], [200.0, 0.0]];
    assert!(solve_planes(&[r, s4], &p, &[(0, 1)], 0, 1).is_err());
    assert!(solve_planes(&[r, r], &p[..1], &[(0, 1)], 0, 1).is_err());
    assert!(solve_planes(&[r, r], &p, &[(0, 2)], 0, 1).is_err());
    assert!(solve_planes(&[r, r], &p, &[(0, 1)], 5, 1).is_err());
    assert!(solve_planes(&[r, r], &p, &[(0, 1)], 0, 0).is_err());
    assert!(solve_planes(&[r, r], &[[f64::NAN, 0.0], [1.0, 0.0]], &[(0, 1)], 0, 1).is_err());
}
