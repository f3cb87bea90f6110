//! Validation of the ISO 16610 filters and form removal (common/core/src/filter): analytic
//! transmission, end effects, holes, robustness, form coefficients, and parity with
//! scipy.ndimage.gaussian_filter (the Python of SURFSTREAM_PYTHON or the repo's .test-venv).

use std::f64::consts::PI;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::Command;

use surfstream_core::filter::{
    fit_polynomial, gaussian_filter, robust_gaussian_filter, scale_limited, sigma_px,
    weighting_function, LFilter, RobustSettings,
};
use surfstream_core::{Sampling, Shape};

/// A `rows x cols` map from `f(x_um, y_um)`.
fn map(grid: Sampling, mut f: impl FnMut(f64, f64) -> f64) -> Vec<f32> {
    (0..grid.rows() * grid.cols())
        .map(|i| {
            let (r, c) = (i / grid.cols(), i % grid.cols());
            f(c as f64 * grid.pitch_x_um(), r as f64 * grid.pitch_y_um()) as f32
        })
        .collect()
}

/// Amplitude of the sinusoid of wavelength `lambda_um` along x (or y) in `z`, over the points
/// at least `margin` px from every edge: least squares on sin and cos.
fn amplitude(z: &[f32], grid: Sampling, lambda_um: f64, along_x: bool, margin: usize) -> f64 {
    let (mut ss, mut cc, mut sc, mut zs, mut zc) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for r in margin..grid.rows() - margin {
        for c in margin..grid.cols() - margin {
            let t = if along_x {
                c as f64 * grid.pitch_x_um()
            } else {
                r as f64 * grid.pitch_y_um()
            };
            let (s, k) = (
                (2.0 * PI * t / lambda_um).sin(),
                (2.0 * PI * t / lambda_um).cos(),
            );
            let v = f64::from(z[r * grid.cols() + c]);
            ss += s * s;
            cc += k * k;
            sc += s * k;
            zs += v * s;
            zc += v * k;
        }
    }
    let det = ss * cc - sc * sc;
    let a = (zs * cc - zc * sc) / det;
    let b = (zc * ss - zs * sc) / det;
    (a * a + b * b).sqrt()
}

#[test]
fn gaussian_transmission_is_50_percent_at_the_cutoff() {
    // lambda_c = 40 um at 0.5 um pitch (x) and 0.4 um (y): the kernel spans 80 / 100 px.
    let grid = Sampling::new(Shape::new(400, 512), 0.5, 0.4).unwrap();
    let lc = 40.0;
    let margin = 110;
    for (lambda, along_x) in [(lc, true), (lc, false), (2.0 * lc, true), (lc / 2.0, false)] {
        let z = map(grid, |x, y| {
            let t = if along_x { x } else { y };
            (2.0 * PI * t / lambda).sin() + 3.0
        });
        let out = gaussian_filter(&z, grid, lc).unwrap();
        let centred: Vec<f32> = out.iter().map(|v| v - 3.0).collect();
        let got = amplitude(&centred, grid, lambda, along_x, margin);
        // ISO 16610-61: a0/a = exp(-pi (alpha lambda_c / lambda)^2).
        let alpha2 = std::f64::consts::LN_2 / PI;
        let want = (-PI * alpha2 * (lc / lambda).powi(2)).exp();
        eprintln!("lambda {lambda} um along x {along_x}: transmission {got:.5} (ISO {want:.5})");
        assert!(
            (got - want).abs() < 0.01 * want,
            "lambda {lambda} along x {along_x}: transmission {got}, want {want}"
        );
        if lambda == lc {
            assert!((got - 0.5).abs() < 0.005, "{got}");
        }
    }
}

#[test]
fn a_plane_is_kept_away_from_edges_and_with_form_removal_up_to_them() {
    let grid = Sampling::square(Shape::new(200, 260), 0.5).unwrap();
    let lc = 25.0;
    let (sx, sy) = (0.03, -0.02); // um per um
    let plane = |x: f64, y: f64| 5.0 + sx * x + sy * y;
    let z = map(grid, plane);
    let out = gaussian_filter(&z, grid, lc).unwrap();
    let h = (lc / 0.5) as usize;
    let mut interior_err = 0.0f64;
    for r in h..grid.rows() - h {
        for c in h..grid.cols() - h {
            let want = plane(c as f64 * 0.5, r as f64 * 0.5);
            interior_err = interior_err.max((f64::from(out[r * grid.cols() + c]) - want).abs());
        }
    }
    assert!(interior_err < 2e-5, "interior error {interior_err} um");
    // At the left edge the normalised weights are one-sided: the mean moves inwards by the
    // centroid of the half kernel (sampled at the pitch, centre included), so the plane is
    // biased by slope x shift (the documented zeroth-order end correction).
    let r = grid.rows() / 2;
    let taps: Vec<(f64, f64)> = (0..=h)
        .map(|j| (j as f64 * 0.5, weighting_function(j as f64 * 0.5, lc)))
        .collect();
    let shift_um =
        taps.iter().map(|(x, w)| x * w).sum::<f64>() / taps.iter().map(|t| t.1).sum::<f64>();
    // ~ sigma sqrt(2 / pi) of the continuous half-Gaussian, less for the centre sample.
    assert!((shift_um / (sigma_px(lc, 0.5) * 0.5 * (2.0 / PI).sqrt()) - 0.96).abs() < 0.02);
    let want_bias = sx * shift_um;
    let bias = f64::from(out[r * grid.cols()]) - plane(0.0, r as f64 * 0.5);
    assert!(
        (bias - want_bias).abs() < 1e-3 * want_bias,
        "edge bias {bias}, expected {want_bias}"
    );
    // With the plane removed first (the S-F -> S-L chain), the L-filter output is the plane's
    // residual, zero to the very edge, and the S-L surface is zero everywhere.
    let s = scale_limited(&z, grid, 1, None, Some(lc), LFilter::Gaussian).unwrap();
    let l = s.l_mean.unwrap();
    let worst = l
        .iter()
        .chain(&s.sl.unwrap())
        .fold(0.0f32, |m, v| m.max(v.abs()));
    assert!(worst < 2e-5, "{worst}");
}

#[test]
fn holes_do_not_spread_beyond_the_kernel() {
    let grid = Sampling::square(Shape::new(180, 220), 0.5).unwrap();
    let lc = 20.0;
    let z = map(grid, |x, y| {
        (2.0 * PI * x / 15.0).sin() + 0.5 * (2.0 * PI * y / 33.0).cos() + 0.01 * x
    });
    let full = gaussian_filter(&z, grid, lc).unwrap();
    let mut holed = z.clone();
    let (r0, r1, c0, c1) = (70, 95, 100, 130);
    for r in r0..r1 {
        holed[r * grid.cols() + c0..r * grid.cols() + c1].fill(f32::NAN);
    }
    let out = gaussian_filter(&holed, grid, lc).unwrap();
    let reach = (lc / 0.5).ceil() as usize; // the kernel's half width, px
    let (mut far, mut near_changed) = (0.0f32, 0.0f32);
    for r in 0..grid.rows() {
        for c in 0..grid.cols() {
            let i = r * grid.cols() + c;
            let inside = (r0..r1).contains(&r) && (c0..c1).contains(&c);
            assert_eq!(
                out[i].is_nan(),
                inside,
                "NaN exactly on the hole ({r}, {c})"
            );
            let dr = r.saturating_sub(r1 - 1).max(r0.saturating_sub(r));
            let dc = c.saturating_sub(c1 - 1).max(c0.saturating_sub(c));
            if dr.max(dc) > reach {
                far = far.max((out[i] - full[i]).abs());
            } else if !inside {
                near_changed = near_changed.max((out[i] - full[i]).abs());
            }
        }
    }
    // Beyond the support the hole changes nothing but FFT round-off; inside it, it does.
    assert!(far < 2e-5, "far from the hole the output moved by {far}");
    assert!(
        near_changed > 1e-3,
        "the hole should matter near it: {near_changed}"
    );
}

#[test]
fn robust_filter_ignores_spikes_and_a_deep_scratch_the_gaussian_follows() {
    let grid = Sampling::square(Shape::new(256, 256), 0.5).unwrap();
    let lc = 25.0;
    // Fine texture (0.2 um) on a level surface, 0.5 % of the points spiked by +40 um, and a
    // 3 px wide scratch 15 um deep along y.
    let mut z = map(grid, |x, y| 0.2 * ((1.3 * x).sin() * (1.7 * y).cos()));
    let mut state = 12345u64;
    for v in z.iter_mut() {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        if (state >> 33).is_multiple_of(200) {
            *v += 40.0;
        }
    }
    for r in 0..grid.rows() {
        for c in 120..123 {
            z[r * grid.cols() + c] -= 15.0;
        }
    }
    z[5] = f32::NAN;
    let plain = gaussian_filter(&z, grid, lc).unwrap();
    let robust = robust_gaussian_filter(&z, grid, &RobustSettings::new(lc)).unwrap();
    assert!(robust.converged, "{} iterations", robust.iterations);
    assert!(robust.mean[5].is_nan());
    let worst = |m: &[f32]| {
        m.iter()
            .filter(|v| v.is_finite())
            .fold(0.0f32, |a, v| a.max(v.abs()))
    };
    let (wp, wr) = (worst(&plain), worst(&robust.mean));
    eprintln!(
        "max |mean - 0|: plain Gaussian {wp:.4} um, robust {wr:.4} um ({} iterations, c = {:.3} um)",
        robust.iterations, robust.c_um
    );
    // The true mean surface is 0: the plain filter is pulled by ~0.2 um (spikes) and more
    // near the scratch; the robust one stays within the texture's own ripple.
    assert!(wp > 0.5, "plain Gaussian deviation {wp}");
    assert!(wr < 0.05, "robust deviation {wr}");
    assert!(wp > 20.0 * wr, "plain {wp} vs robust {wr}");
    // The spikes and the scratch get zero weight.
    let rejected = robust
        .weights
        .iter()
        .zip(&z)
        .filter(|(w, v)| v.is_finite() && v.abs() > 10.0 && **w > 0.0)
        .count();
    assert_eq!(rejected, 0);
}

#[test]
fn polynomial_form_recovers_known_coefficients() {
    let grid = Sampling::new(Shape::new(150, 210), 0.8, 0.6).unwrap();
    // Third order in the normalised coordinates (u, v in [-1, 1]).
    let want: [((usize, usize), f64); 10] = [
        ((0, 0), 12.0),
        ((1, 0), 1.5),
        ((0, 1), -0.75),
        ((2, 0), 0.4),
        ((1, 1), -0.3),
        ((0, 2), 0.25),
        ((3, 0), 0.1),
        ((2, 1), -0.05),
        ((1, 2), 0.07),
        ((0, 3), -0.12),
    ];
    let (cx, hx) = (209.0 / 2.0 * 0.8, 209.0 / 2.0 * 0.8);
    let (cy, hy) = (149.0 / 2.0 * 0.6, 149.0 / 2.0 * 0.6);
    let mut z = map(grid, |x, y| {
        let (u, v) = ((x - cx) / hx, (y - cy) / hy);
        want.iter()
            .map(|&((i, j), c)| c * u.powi(i as i32) * v.powi(j as i32))
            .sum()
    });
    for i in (0..z.len()).step_by(7) {
        z[i] = f32::NAN;
    }
    let f = fit_polynomial(&z, grid, 3).unwrap();
    for &((i, j), c) in &want {
        let k = f.terms.iter().position(|&t| t == (i, j)).unwrap();
        assert!(
            (f.coefficients[k] - c).abs() < 2e-5,
            "u^{i} v^{j}: {} vs {c}",
            f.coefficients[k]
        );
    }
    assert!(f.residual_rms_um < 1e-5);
    // A plane fit of the same map leaves the curvature: residual well above round-off.
    let plane = fit_polynomial(&z, grid, 1).unwrap();
    assert_eq!(plane.terms, vec![(0, 0), (1, 0), (0, 1)]);
    assert!(plane.residual_rms_um > 0.05);
    assert!(fit_polynomial(&z, grid, 11).is_err());
    assert!(fit_polynomial(
        &[1.0, f32::NAN, 2.0, 3.0],
        Sampling::square(Shape::new(2, 2), 1.0).unwrap(),
        1
    )
    .is_ok());
    assert!(fit_polynomial(
        &[1.0, f32::NAN, f32::NAN, 3.0],
        Sampling::square(Shape::new(2, 2), 1.0).unwrap(),
        1
    )
    .is_err());
}

fn python() -> PathBuf {
    if let Some(p) = std::env::var_os("SURFSTREAM_PYTHON") {
        return PathBuf::from(p);
    }
    let venv = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../.test-venv/bin/python");
    assert!(
        venv.exists(),
        "no Python test environment: set SURFSTREAM_PYTHON or run scripts/test.sh"
    );
    venv
}

/// A little-endian f64 .npy (the format is four lines of spec; no crate needed).
fn write_npy(path: &Path, v: &[f64], rows: usize, cols: usize) {
    let mut header =
        format!("{{'descr': '<f8', 'fortran_order': False, 'shape': ({rows}, {cols}), }}");
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut f = std::fs::File::create(path).unwrap();
    f.write_all(b"\x93NUMPY\x01\x00").unwrap();
    f.write_all(&(header.len() as u16).to_le_bytes()).unwrap();
    f.write_all(header.as_bytes()).unwrap();
    for x in v {
        f.write_all(&x.to_le_bytes()).unwrap();
    }
}

#[test]
fn parity_with_scipy_gaussian_filter_and_surfalizes_old_sigma() {
    let grid = Sampling::new(Shape::new(160, 200), 0.5, 0.7).unwrap();
    let lc = 16.0;
    let mut state = 7u64;
    let z = map(grid, |x, y| {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1);
        (x / 9.0).sin() + (y / 5.0).cos() + ((state >> 40) as f64 / (1u64 << 24) as f64 - 0.5)
    });
    let ours = gaussian_filter(&z, grid, lc).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("z.npy");
    write_npy(
        &input,
        &z.iter().map(|&v| f64::from(v)).collect::<Vec<_>>(),
        grid.rows(),
        grid.cols(),
    );
    let (sx, sy) = (sigma_px(lc, 0.5), sigma_px(lc, 0.7));
    let (hx, hy) = ((lc / 0.5).ceil(), (lc / 0.7).ceil());
    // scipy's kernel radius is int(truncate * sigma + 0.5): give it our half width per axis.
    let script = format!(
        r#"
import sys, numpy as np, scipy.ndimage as nd
z = np.load(sys.argv[1])
ref = nd.gaussian_filter1d(z, {sx}, axis=1, truncate={tx}, mode='reflect')
ref = nd.gaussian_filter1d(ref, {sy}, axis=0, truncate={ty}, mode='reflect')
np.save(sys.argv[2], ref)
# surfalize before 0.8.2 (issue fredericjs/surfalize#7): sigma = cutoff / (2 sqrt(2 ln 2)),
# i.e. the cutoff taken as the kernel's full width at half maximum. Transmission at lambda_c:
t = np.arange(4096) * 0.5
wave = np.sin(2 * np.pi * t / {lc})
for name, sigma in (('old', {lc} / 0.5 / (2 * np.sqrt(2 * np.log(2)))), ('fixed', {lc} / 0.5 / np.pi * np.sqrt(np.log(2) / 2))):
    out = nd.gaussian_filter1d(wave, sigma, mode='wrap')
    print(name, np.abs(out[1000:3000]).max())
"#,
        tx = (hx + 0.4) / sx,
        ty = (hy + 0.4) / sy,
    );
    let output = dir.path().join("ref.npy");
    let run = Command::new(python())
        .arg("-c")
        .arg(&script)
        .arg(&input)
        .arg(&output)
        .output()
        .expect("python runs");
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let bytes = std::fs::read(&output).unwrap();
    let hlen = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
    let reference: Vec<f64> = bytes[10 + hlen..]
        .chunks_exact(8)
        .map(|b| f64::from_le_bytes(b.try_into().unwrap()))
        .collect();
    assert_eq!(reference.len(), z.len());
    let (mx, my) = (hx as usize, hy as usize);
    let mut worst = 0.0f64;
    for r in my..grid.rows() - my {
        for c in mx..grid.cols() - mx {
            let i = r * grid.cols() + c;
            worst = worst.max((f64::from(ours[i]) - reference[i]).abs());
        }
    }
    eprintln!("max interior |ours - scipy| = {worst:.2e} um");
    assert!(worst < 1e-5, "interior difference to scipy {worst}");
    // The old conversion passes 2.8 % at lambda_c instead of 50 %.
    let text = String::from_utf8_lossy(&run.stdout);
    let value = |name: &str| -> f64 {
        text.lines()
            .find_map(|l| l.strip_prefix(name)?.trim().parse().ok())
            .unwrap_or_else(|| panic!("{name} in {text}"))
    };
    let (old, fixed) = (value("old "), value("fixed "));
    eprintln!(
        "scipy transmission at lambda_c: fixed sigma {fixed:.4}, surfalize < 0.8.2 sigma {old:.4}"
    );
    assert!((fixed - 0.5).abs() < 0.005, "fixed sigma: {fixed}");
    let want_old = (-2.0 * PI * PI / (8.0 * std::f64::consts::LN_2)).exp();
    assert!(
        (old - want_old).abs() < 0.002,
        "old sigma: {old} vs {want_old}"
    );
}

/// The filters and the form fit give the same bits whatever the number of threads: their sums
/// over rayon's work are added in a fixed order. (Before, rayon's reduce paired partial sums as
/// the threads happened to split the work, and a filtered map's last bits changed from run to
/// run.)
#[test]
fn filters_do_not_depend_on_the_thread_count() {
    let grid = Sampling::new(Shape::new(700, 900), 0.8, 0.7).unwrap();
    let mut z = map(grid, |x, y| {
        50.0 + 2.0 * (0.013 * x).sin() + 0.7 * (0.021 * y + 0.3).cos() + 1e-3 * x * y.sqrt()
    });
    for k in (0..z.len()).step_by(97) {
        z[k] = f32::NAN;
    }
    let bits32 = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<u32>>();
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let form = fit_polynomial(&z, grid, 2).unwrap();
            let mut bits: Vec<u64> = form.coefficients.iter().map(|c| c.to_bits()).collect();
            bits.push(form.residual_rms_um.to_bits());
            let smooth = gaussian_filter(&z, grid, 80.0).unwrap();
            let robust = robust_gaussian_filter(&z, grid, &RobustSettings::new(80.0)).unwrap();
            (bits, bits32(&smooth), bits32(&robust.mean))
        })
    };
    let one = run(1);
    for threads in [2, 3, 5, 8] {
        let other = run(threads);
        assert!(other.0 == one.0, "form fit differs with {threads} threads");
        assert!(
            other.1 == one.1,
            "Gaussian filter differs with {threads} threads"
        );
        assert!(
            other.2 == one.2,
            "robust Gaussian filter differs with {threads} threads"
        );
    }
}
