//! The model from a tolerance (issue 22) on the surfaces that break a fixed pooling: one deep
//! scratch, one isolated spike, white noise, a tilted plane. Each mesh is judged here
//! independently of the mesher: its surface triangles are interpolated at every measured
//! sample by a brute-force barycentric search, and Sa, Sq, Sz (mean removed) compared with the
//! measurement's. Either the tolerance is met (and Sz within it) or the report says which
//! region fails and why.

use surfstream_core::raster::{RasterView, Shape};
use surfstream_core::Pitch;
use surfstream_mesher::tolerance::ModelMethod;
use surfstream_mesher::{
    mesh_streaming_to_tolerance, mesh_to_tolerance, AdaptiveMesh, Epsilon, LengthUnit, MeshKind,
    MeshParams, MissingSamples, ScanPlacement, SolidParams, Tolerance, ToleranceSettings,
};

const ROWS: usize = 96;
const COLS: usize = 112;

fn noise(n: usize, seed: u64) -> Vec<f64> {
    let mut state = seed;
    (0..n)
        .map(|_| {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        })
        .collect()
}

/// A smooth rough surface (um) with a little noise.
fn rough() -> Vec<f32> {
    let r = noise(ROWS * COLS, 7);
    (0..ROWS * COLS)
        .map(|k| {
            let (x, y) = ((k % COLS) as f64 / 9.0, (k / COLS) as f64 / 11.0);
            (x.sin() * y.cos() + 0.3 * (2.3 * x + 1.1 * y).sin() + 0.05 * r[k]) as f32
        })
        .collect()
}

fn params() -> MeshParams {
    MeshParams {
        epsilon: Epsilon::SqFraction(0.05),
        max_triangles: None,
        kind: MeshKind::Sheet,
        missing: MissingSamples::Fill,
        // Scan coordinates in um, not re-centred: vertex = (column, row, height).
        solid: SolidParams {
            units: LengthUnit::Um,
            base_depth_um: None,
            recentre: false,
        },
        block_samples: Some(40),
    }
}

fn settings(t: &str) -> ToleranceSettings {
    ToleranceSettings {
        tolerance: t.parse().unwrap(),
        region_px: Some(48),
        ..Default::default()
    }
}

/// The sheet's surface at every sample, by an independent barycentric search (NaN: not
/// covered).
fn interpolate(m: &AdaptiveMesh) -> Vec<f64> {
    let mut out = vec![f64::NAN; ROWS * COLS];
    for t in &m.mesh.triangles[..m.mesh.top_triangles] {
        let p = t.map(|v| m.mesh.vertices[v as usize]);
        let (x0, x1) = (
            p.iter().map(|v| v[0]).fold(f64::INFINITY, f64::min).floor() as usize,
            p.iter().map(|v| v[0]).fold(0.0, f64::max).ceil() as usize,
        );
        let (y0, y1) = (
            p.iter().map(|v| v[1]).fold(f64::INFINITY, f64::min).floor() as usize,
            p.iter().map(|v| v[1]).fold(0.0, f64::max).ceil() as usize,
        );
        let det =
            (p[1][0] - p[0][0]) * (p[2][1] - p[0][1]) - (p[2][0] - p[0][0]) * (p[1][1] - p[0][1]);
        for y in y0..=y1.min(ROWS - 1) {
            for x in x0..=x1.min(COLS - 1) {
                let (px, py) = (x as f64, y as f64);
                let l1 = ((px - p[0][0]) * (p[2][1] - p[0][1])
                    - (p[2][0] - p[0][0]) * (py - p[0][1]))
                    / det;
                let l2 = ((p[1][0] - p[0][0]) * (py - p[0][1])
                    - (px - p[0][0]) * (p[1][1] - p[0][1]))
                    / det;
                let l0 = 1.0 - l1 - l2;
                if l0 >= -1e-9 && l1 >= -1e-9 && l2 >= -1e-9 {
                    out[y * COLS + x] = l0 * p[0][2] + l1 * p[1][2] + l2 * p[2][2];
                }
            }
        }
    }
    out
}

/// Sa, Sq, Sz (mean removed) over the samples valid in both.
fn params_of(z: &[f64], valid: &[bool]) -> [f64; 3] {
    let v: Vec<f64> = z
        .iter()
        .zip(valid)
        .filter(|(_, &ok)| ok)
        .map(|(&z, _)| z)
        .collect();
    let mean = v.iter().sum::<f64>() / v.len() as f64;
    let sa = v.iter().map(|z| (z - mean).abs()).sum::<f64>() / v.len() as f64;
    let sq = (v.iter().map(|z| (z - mean).powi(2)).sum::<f64>() / v.len() as f64).sqrt();
    let sz = v.iter().copied().fold(f64::NEG_INFINITY, f64::max)
        - v.iter().copied().fold(f64::INFINITY, f64::min);
    [sa, sq, sz]
}

/// Meshes `z` to tolerance `t`; returns the mesh, the report and the whole map's Sa, Sq, Sz
/// deviations (%) found independently.
fn model(
    z: &[f32],
    t: &str,
    max_triangles: Option<usize>,
) -> (AdaptiveMesh, surfstream_mesher::ToleranceReport, [f64; 3]) {
    model_with(z, t, max_triangles, ModelMethod::Balanced)
}

fn model_with(
    z: &[f32],
    t: &str,
    max_triangles: Option<usize>,
    method: ModelMethod,
) -> (AdaptiveMesh, surfstream_mesher::ToleranceReport, [f64; 3]) {
    let heights = RasterView::new(z, Shape::new(ROWS, COLS)).unwrap();
    let at = ScanPlacement::new(Pitch::new(1.0, 1.0).expect("a positive pitch"));
    let mut p = params();
    p.max_triangles = max_triangles;
    let s = ToleranceSettings {
        method,
        ..settings(t)
    };
    let (m, r) = mesh_to_tolerance(heights, None, &at, &p, &s, &[]).unwrap();
    let mesh = interpolate(&m);
    let valid: Vec<bool> = z
        .iter()
        .zip(&mesh)
        .map(|(a, b)| !a.is_nan() && !b.is_nan())
        .collect();
    let zf: Vec<f64> = z.iter().map(|&v| f64::from(v)).collect();
    let (a, b) = (params_of(&zf, &valid), params_of(&mesh, &valid));
    let dev = [0, 1, 2].map(|k| (b[k] - a[k]) / a[k] * 100.0);
    (m, r, dev)
}

fn within(dev: [f64; 3], t: &Tolerance) -> bool {
    dev[0].abs() <= t.sa_pct && dev[1].abs() <= t.sq_pct && dev[2].abs() <= t.sz_pct
}

#[test]
fn a_deep_narrow_scratch_keeps_sz() {
    let mut z = rough();
    // One pixel wide, 8 x the surface's amplitude deep, along a slanted line.
    for x in 10..100 {
        let y = 20 + x / 3;
        z[y * COLS + x] -= 8.0;
    }
    let (_, r, dev) = model(&z, "sa=1,sq=1,sz=3", None);
    assert!(r.met, "{:?}", r.reason);
    assert!(within(dev, &r.tolerance), "independent deviations {dev:?}");
    // The scratch's floor is a vertex: Sz is exact.
    assert!(dev[2].abs() < 1e-6, "{dev:?}");
    assert!(
        r.triangles_per_measured_px <= 0.5,
        "{}",
        r.triangles_per_measured_px
    );
}

#[test]
fn an_isolated_spike_keeps_sz() {
    let mut z = rough();
    z[50 * COLS + 61] += 25.0;
    let (_, r, dev) = model(&z, "sa=1,sq=1,sz=3", None);
    assert!(r.met, "{:?}", r.reason);
    assert!(within(dev, &r.tolerance), "{dev:?}");
    assert!(dev[2].abs() < 1e-6, "{dev:?}");
}

#[test]
fn white_noise_within_a_small_budget_names_the_region_and_the_cause() {
    let z: Vec<f32> = noise(ROWS * COLS, 3).iter().map(|&v| v as f32).collect();
    // Without a budget the tolerance is met on noise too, at some cost.
    let (_, free, dev) = model(&z, "sa=1,sq=1,sz=3", None);
    assert!(free.met, "{:?}", free.reason);
    assert!(within(dev, &free.tolerance), "{dev:?}");
    // A budget that only the coarsest (failing) mesh fits: the report says so, and where.
    let coarsest = free
        .curve
        .iter()
        .map(|c| c.surface_triangles)
        .min()
        .unwrap();
    assert!(coarsest < free.surface_triangles);
    let (m, r, dev) = model(&z, "sa=1,sq=1,sz=3", Some(coarsest));
    assert!(m.surface_triangles <= coarsest);
    // The report reads as the record run.json's readers use (verdict, report.html) and is
    // written back the same: a field added here and not there fails this.
    for report in [&free, &r] {
        let v = serde_json::to_value(report).unwrap();
        let rec: surfstream_core::record::ToleranceRecord =
            surfstream_core::record::from_value(&v, "tolerance").unwrap();
        assert_eq!(surfstream_core::record::to_value(&rec).unwrap(), v);
    }
    assert!(!r.met);
    let reason = r.reason.unwrap();
    // The region named is beyond the tolerance, found here too (or the residual bound).
    let name = reason["region ".len()..].split(':').next().unwrap();
    let w = surfstream_mesher::tolerance::windows(Shape::new(ROWS, COLS), 48)
        .into_iter()
        .find(|w| w.name == name)
        .unwrap();
    let mesh = interpolate(&m);
    let inside = |k: usize| {
        let (y, x) = (k / COLS, k % COLS);
        (w.row0..w.row0 + w.rows).contains(&y) && (w.col0..w.col0 + w.cols).contains(&x)
    };
    let valid: Vec<bool> = (0..ROWS * COLS)
        .map(|k| inside(k) && !mesh[k].is_nan())
        .collect();
    let zf: Vec<f64> = z.iter().map(|&v| f64::from(v)).collect();
    let (a, b) = (params_of(&zf, &valid), params_of(&mesh, &valid));
    let dev_region = [0, 1, 2].map(|k| (b[k] - a[k]) / a[k] * 100.0);
    assert!(
        !within(dev_region, &r.tolerance) || reason.contains("residual"),
        "{dev_region:?} {reason}"
    );
    assert!(reason.starts_with("region "), "{reason}");
    assert!(
        reason.contains(&format!("max_triangles = {coarsest}")),
        "{reason}"
    );
    // Sz still holds: the extremes are vertices.
    assert!(dev[2].abs() < 3.0, "{dev:?}");
    // Below the coarsest mesh: a typed error a caller can act on (finish gives a larger
    // budget on it), naming both counts.
    let heights = RasterView::new(&z, Shape::new(ROWS, COLS)).unwrap();
    let at = ScanPlacement::new(Pitch::new(1.0, 1.0).expect("a positive pitch"));
    let mut p = params();
    p.max_triangles = Some(coarsest - 1);
    let e =
        mesh_to_tolerance(heights, None, &at, &p, &settings("sa=1,sq=1,sz=3"), &[]).unwrap_err();
    match &e {
        surfstream_mesher::MeshError::CoarsestOverBudget {
            triangles, budget, ..
        } => assert_eq!((*triangles, *budget), (coarsest, coarsest - 1), "{e}"),
        other => panic!("expected CoarsestOverBudget, got {other}"),
    }
}

#[test]
fn a_tilted_plane_is_two_triangles() {
    let z: Vec<f32> = (0..ROWS * COLS)
        .map(|k| (0.02 * (k % COLS) as f64 - 0.01 * (k / COLS) as f64) as f32)
        .collect();
    let (m, r, dev) = model(&z, "sa=1,sq=1,sz=3", None);
    assert!(r.met);
    assert!(dev.iter().all(|d| d.abs() < 1e-3), "{dev:?}");
    // The blocks' corners and extremes only: far below one triangle per 100 samples.
    assert!(
        m.surface_triangles * 100 < ROWS * COLS,
        "{}",
        m.surface_triangles
    );
}

#[test]
fn the_streamed_search_chooses_the_same_mesh() {
    let z = rough();
    let heights = RasterView::new(&z, Shape::new(ROWS, COLS)).unwrap();
    let at = ScanPlacement::new(Pitch::new(1.0, 1.0).expect("a positive pitch"));
    let s = settings("sa=1,sq=1,sz=3");
    let (m, r) = mesh_to_tolerance(heights, None, &at, &params(), &s, &[]).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let (sm, sr) =
        mesh_streaming_to_tolerance(heights, None, &at, &params(), &s, &[], dir.path()).unwrap();
    assert_eq!(sm.counts.top_triangles, m.surface_triangles);
    assert_eq!(sr.curve, r.curve);
    assert_eq!(sm.resampled_um.len(), m.resampled_um.len());
    // A tighter tolerance never needs fewer triangles at its chosen point.
    let (_, tight) = mesh_to_tolerance(
        heights,
        None,
        &at,
        &params(),
        &settings("sa=0.2,sq=0.2,sz=1"),
        &[],
    )
    .unwrap();
    assert!(tight.surface_triangles >= r.surface_triangles || !tight.met);
}

#[test]
fn the_balance_meets_the_tolerance_on_noise_with_fewer_triangles_than_greedy_insertion() {
    // A waviness under white noise of the same spread (the waviness's Sq is 0.5, uniform
    // noise of width 1.7 has Sq 0.49): greedy insertion over-shoots Sa and Sq until it
    // follows the noise; the block balance pulls them back at fewer triangles. (On a
    // surface whose noise is a small share, greedy insertion alone can need fewer: with
    // noise of Sq 0.14 here it did, docs/model.md.) Over five draws of the noise: on one
    // draw the two can come within a few per cent either way (seed 21: 12 539 balanced,
    // 12 349 greedy, since the regions are judged without the field's plane), so the
    // claim is the total's.
    let params_only = "sa=1,sq=1,sz=3,res=off,max=off";
    let surface = |seed: u64| -> Vec<f32> {
        let r = noise(ROWS * COLS, seed);
        (0..ROWS * COLS)
            .map(|k| {
                let (x, y) = ((k % COLS) as f64 / 14.0, (k / COLS) as f64 / 17.0);
                (x.sin() * y.cos() + 1.7 * r[k]) as f32
            })
            .collect()
    };
    let (mut total_greedy, mut total_balanced) = (0, 0);
    for seed in 21..=25 {
        let z = surface(seed);
        let (mg, greedy, dev_g) = model_with(&z, params_only, None, ModelMethod::Greedy);
        let (mb, balanced, dev_b) = model_with(&z, params_only, None, ModelMethod::Balanced);
        assert!(
            greedy.met && balanced.met,
            "seed {seed}: {:?} {:?}",
            greedy.reason,
            balanced.reason
        );
        assert!(within(dev_g, &greedy.tolerance), "seed {seed}: {dev_g:?}");
        assert!(within(dev_b, &balanced.tolerance), "seed {seed}: {dev_b:?}");
        eprintln!(
            "seed {seed}: balanced {} greedy {}",
            mb.surface_triangles, mg.surface_triangles
        );
        total_greedy += mg.surface_triangles;
        total_balanced += mb.surface_triangles;
    }
    assert!(
        total_balanced < total_greedy,
        "balanced {total_balanced} vs greedy {total_greedy} over five draws"
    );
    let z = surface(21);
    let (_, balanced, _) = model_with(&z, params_only, None, ModelMethod::Balanced);
    // The default pointwise bounds then ask for pointwise fidelity too.
    let (_, bounded, _) = model(&z, "sa=1,sq=1,sz=3", None);
    assert!(bounded.met, "{:?}", bounded.reason);
    assert!(bounded
        .region_fits
        .iter()
        .all(|f| f.residual_pct_of_sq <= 20.0 && f.max_error_pct_of_sq <= 50.0));
    assert!(bounded.surface_triangles >= balanced.surface_triangles);
}

/// The largest |mesh - measurement| and the residual RMS (both means removed), percent of the
/// measured Sq, over the samples of a window valid in both: judged here, from the triangles.
fn pointwise_pct(z: &[f32], mesh: &[f64], w: &surfstream_mesher::tolerance::Window) -> [f64; 2] {
    let mut pairs = Vec::new();
    for y in w.row0..w.row0 + w.rows {
        for x in w.col0..w.col0 + w.cols {
            let (a, b) = (f64::from(z[y * COLS + x]), mesh[y * COLS + x]);
            if !(a.is_nan() || b.is_nan()) {
                pairs.push((a, b));
            }
        }
    }
    let n = pairs.len() as f64;
    let (ma, mb) = pairs
        .iter()
        .fold((0.0, 0.0), |(s, t), (a, b)| (s + a / n, t + b / n));
    let sq = (pairs.iter().map(|(a, _)| (a - ma).powi(2)).sum::<f64>() / n).sqrt();
    let d = pairs.iter().map(|(a, b)| (b - mb) - (a - ma));
    let max = d.clone().fold(0.0f64, |m, e| m.max(e.abs()));
    let rms = (d.map(|e| e * e).sum::<f64>() / n).sqrt();
    [max / sq * 100.0, rms / sq * 100.0]
}

#[test]
fn the_default_tolerance_bounds_every_point_in_every_window() {
    // The default (Sa, Sq 1 %, Sz 3 %, residual RMS 20 %, largest error 50 % of Sq): judged
    // here from the triangles, every window's largest pointwise error is within half its Sq
    // and the residual within a fifth, where the parameters alone (res=off, max=off) depart
    // by more: the pointwise bound is what makes the difference.
    let z = rough();
    let (m, r, dev) = model(&z, "", None);
    assert!(r.met, "{:?}", r.reason);
    assert!(within(dev, &r.tolerance), "{dev:?}");
    assert_eq!(r.tolerance.max_error_pct, Some(50.0));
    let mesh = interpolate(&m);
    let w = surfstream_mesher::tolerance::windows(Shape::new(ROWS, COLS), 48);
    for win in &w {
        let [max, rms] = pointwise_pct(&z, &mesh, win);
        assert!(
            max <= 50.0 && rms <= 20.0,
            "{}: max {max} %, RMS {rms} %",
            win.name
        );
        let fit = r.region_fits.iter().find(|f| f.region == win.name).unwrap();
        assert!(
            (fit.max_error_pct_of_sq - max).abs() < 0.5,
            "{fit:?} vs {max}"
        );
    }
    let (loose_m, loose, _) = model(&z, "res=off,max=off", None);
    let loose_mesh = interpolate(&loose_m);
    let worst = w
        .iter()
        .map(|win| pointwise_pct(&z, &loose_mesh, win)[0])
        .fold(0.0, f64::max);
    assert!(
        worst > 50.0,
        "the parameters alone already bound every point: {worst} %"
    );
    // The triangle counts are not compared: without a pointwise limit the search has no
    // coarsest bound worth judging and walks the whole series, the block balance adding
    // samples at every step, which every finer mesh keeps (here 2 269 surface triangles
    // against the default's 1 730, which starts at the bound its largest error allows).
    eprintln!(
        "default {} surface triangles, res=off,max=off {}",
        r.surface_triangles, loose.surface_triangles
    );
}

/// A waviness under white noise (um) and its noise (the roughness a separation would find).
fn wavy_noise(seed: u64, noise_amp: f64) -> (Vec<f32>, Vec<f32>) {
    let r = noise(ROWS * COLS, seed);
    (0..ROWS * COLS)
        .map(|k| {
            let (x, y) = ((k % COLS) as f64 / 14.0, (k / COLS) as f64 / 17.0);
            let g = noise_amp * r[k];
            ((x.sin() * y.cos() + g) as f32, g as f32)
        })
        .unzip()
}

#[test]
fn a_bisected_checkpoint_passes_with_fewer_triangles_than_the_coarse_one_above_it() {
    // Waviness under noise, the roughness judged: the first passing coarse checkpoint is
    // well above the last failing one, and a bound between them (a bisection, or the step
    // just below a near miss of the pointwise bounds) passes with fewer triangles.
    let (z, g) = wavy_noise(22, 0.5);
    let heights = RasterView::new(&z, Shape::new(ROWS, COLS)).unwrap();
    let at = ScanPlacement::new(Pitch::new(1.0, 1.0).expect("a positive pitch"));
    let s = settings("sa=1,sq=1,sz=3");
    let (m, r) = mesh_to_tolerance(heights, Some(&g), &at, &params(), &s, &[]).unwrap();
    assert!(r.met, "{:?}", r.reason);
    // The series starts at the coarsest bound tried (the bisection's lie between).
    let coarsest = r
        .curve
        .iter()
        .map(|c| c.epsilon_sq_fraction)
        .fold(0.0, f64::max);
    let coarse: Vec<f64> = surfstream_mesher::tolerance::checkpoint_fractions(coarsest).collect();
    let is_coarse = |f: f64| coarse.iter().any(|c| (c - f).abs() < 1e-12);
    let chosen = r.curve.iter().find(|c| c.chosen).unwrap();
    assert!(
        !is_coarse(chosen.epsilon_sq_fraction),
        "chosen at a coarse checkpoint: {:?}",
        r.curve
    );
    // A coarse checkpoint finer than it, when one was judged, passes too, with more
    // triangles; the one coarser than it fails.
    let above = r
        .curve
        .iter()
        .filter(|c| {
            is_coarse(c.epsilon_sq_fraction) && c.epsilon_sq_fraction < chosen.epsilon_sq_fraction
        })
        .max_by(|a, b| a.epsilon_sq_fraction.total_cmp(&b.epsilon_sq_fraction));
    if let Some(above) = above {
        assert!(
            above.pass && above.surface_triangles > chosen.surface_triangles,
            "{above:?}"
        );
    }
    let below = r
        .curve
        .iter()
        .filter(|c| {
            is_coarse(c.epsilon_sq_fraction) && c.epsilon_sq_fraction > chosen.epsilon_sq_fraction
        })
        .min_by(|a, b| a.epsilon_sq_fraction.total_cmp(&b.epsilon_sq_fraction))
        .unwrap();
    assert!(!below.pass, "{below:?}");
    assert_eq!(m.surface_triangles, chosen.surface_triangles);
    // Judged here: the heights and the roughness the mesh carries (roughness + mesh -
    // measurement) over the whole map.
    let mesh = interpolate(&m);
    let valid: Vec<bool> = mesh.iter().map(|v| !v.is_nan()).collect();
    assert!(valid.iter().all(|&v| v));
    let zf: Vec<f64> = z.iter().map(|&v| f64::from(v)).collect();
    let (a, b) = (params_of(&zf, &valid), params_of(&mesh, &valid));
    let dev = [0, 1, 2].map(|k| (b[k] - a[k]) / a[k] * 100.0);
    assert!(within(dev, &r.tolerance), "{dev:?}");
    let gf: Vec<f64> = g.iter().map(|&v| f64::from(v)).collect();
    let carried: Vec<f64> = (0..gf.len()).map(|k| gf[k] + mesh[k] - zf[k]).collect();
    let (ga, gb) = (params_of(&gf, &valid), params_of(&carried, &valid));
    for k in 0..2 {
        let d = (gb[k] - ga[k]) / ga[k] * 100.0;
        assert!(d.abs() <= 5.0, "roughness {k}: {d}");
    }
    // The streamed search makes the same checkpoints and writes the same mesh.
    let dir = tempfile::tempdir().unwrap();
    let (sm, sr) =
        mesh_streaming_to_tolerance(heights, Some(&g), &at, &params(), &s, &[], dir.path())
            .unwrap();
    assert_eq!(sr.curve, r.curve);
    assert_eq!(sm.counts.top_triangles, m.surface_triangles);
    assert_eq!(sm.resampled_um, m.resampled_um);
}

#[test]
fn without_the_curve_the_search_writes_the_same_mesh_from_its_own_meshes() {
    // The default tolerance (a pointwise limit, so the series has a coarse side above the
    // coarsest bound worth judging): with `curve` off the curve's own meshes (the coarse side,
    // finer points) are not made; what is left is the search's checkpoints, the same ones,
    // and the same mesh is chosen and written.
    let z = rough();
    let heights = RasterView::new(&z, Shape::new(ROWS, COLS)).unwrap();
    let at = ScanPlacement::new(Pitch::new(1.0, 1.0).expect("a positive pitch"));
    let on = settings("");
    let off = ToleranceSettings { curve: false, ..on };
    let (m_on, r_on) = mesh_to_tolerance(heights, None, &at, &params(), &on, &[]).unwrap();
    let (m_off, r_off) = mesh_to_tolerance(heights, None, &at, &params(), &off, &[]).unwrap();
    assert!(
        r_on.met && r_off.met,
        "{:?} {:?}",
        r_on.reason,
        r_off.reason
    );
    assert!(
        r_on.curve.len() >= 6 && r_off.curve.len() < r_on.curve.len(),
        "{} and {} points",
        r_on.curve.len(),
        r_off.curve.len()
    );
    let chosen = r_on.curve.iter().find(|c| c.chosen).unwrap();
    let coarser = |c: &&surfstream_mesher::tolerance::CurvePoint| {
        c.epsilon_sq_fraction > chosen.epsilon_sq_fraction
    };
    // The points left are the search's: each one as the full curve has it, none coarser
    // than the coarsest the search judged.
    for p in &r_off.curve {
        assert!(r_on.curve.contains(p), "{p:?} not in {:?}", r_on.curve);
    }
    assert!(r_on.curve.iter().filter(coarser).count() > r_off.curve.iter().filter(coarser).count());
    assert_eq!(r_off.curve.iter().find(|c| c.chosen), Some(chosen));
    assert_eq!(m_off.surface_triangles, m_on.surface_triangles);
    assert_eq!(m_off.resampled_um, m_on.resampled_um);
    assert_eq!(r_off.region_fits, r_on.region_fits);
    // The streamed search likewise.
    let dir = tempfile::tempdir().unwrap();
    let (sm, sr) =
        mesh_streaming_to_tolerance(heights, None, &at, &params(), &off, &[], dir.path()).unwrap();
    assert_eq!(sr.curve, r_off.curve);
    assert_eq!(sm.resampled_um, m_on.resampled_um);
}
