//! The streamed separation (`separate_streamed`) against the in-memory reference
//! (`separate`): the same bits, for every mode, levels 1..=max, odd / even / non-square sides,
//! holes (whole rows at the top, middle and bottom, scattered pixels), band sizes that do not
//! divide the rows, a map smaller than one band, and levels kept in memory or in files.

use surfstream_wavelet::{
    dwt_max_level, energy_curve, energy_curve_streamed, separate, separate_streamed, Mode,
    StreamOptions, Wavelet,
};

/// Deterministic pseudo-random values in [-1, 1) (splitmix64).
fn noise(n: usize, seed: u64) -> Vec<f32> {
    let mut s = seed;
    (0..n)
        .map(|_| {
            s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = s;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^= z >> 31;
            ((z >> 11) as f64 / (1u64 << 52) as f64 - 1.0) as f32
        })
        .collect()
}

/// A tilted wavy surface with noise, and holes: whole rows and scattered pixels.
fn surface(rows: usize, cols: usize, seed: u64, holes: &[usize]) -> Vec<f32> {
    let n = noise(rows * cols, seed);
    let mut h: Vec<f32> = (0..rows * cols)
        .map(|i| {
            let (r, c) = ((i / cols) as f32, (i % cols) as f32);
            5.0 + 0.02 * r - 0.01 * c + (0.21 * c).sin() + 0.3 * (0.13 * r).cos() + 0.1 * n[i]
        })
        .collect();
    for &r in holes {
        h[r * cols..(r + 1) * cols].fill(f32::NAN);
    }
    for i in (7..rows * cols).step_by(53) {
        h[i] = f32::NAN;
    }
    h
}

fn streamed(
    h: &[f32],
    rows: usize,
    cols: usize,
    w: &Wavelet,
    mode: Mode,
    level: usize,
    opts: &StreamOptions,
) -> (Vec<f32>, Vec<f32>, usize) {
    let mut datum = Vec::new();
    let mut rough = Vec::new();
    let mut next_row = 0;
    let used = separate_streamed(h, rows, cols, w, mode, Some(level), opts, |r0, d, r| {
        // Rows arrive in order, whole.
        assert_eq!(r0, next_row);
        assert_eq!(d.len() % cols, 0);
        assert_eq!(d.len(), r.len());
        next_row += d.len() / cols;
        datum.extend_from_slice(d);
        rough.extend_from_slice(r);
        Ok(())
    })
    .expect("streamed separation");
    assert_eq!(next_row, rows);
    (datum, rough, used)
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

fn check(rows: usize, cols: usize, holes: &[usize], names: &[&str], opts: &StreamOptions) {
    let h = surface(rows, cols, (rows * 1000 + cols) as u64, holes);
    for name in names {
        let w = Wavelet::by_name(name).expect("listed");
        let max = dwt_max_level(rows.min(cols), w.filter_len());
        for mode in [Mode::Symmetric, Mode::Periodization] {
            for level in 1..=max {
                let reference = separate(&h, rows, cols, &w, mode, Some(level)).expect("separates");
                let (d, r, used) = streamed(&h, rows, cols, &w, mode, level, opts);
                assert_eq!(used, reference.level);
                let at = format!("{rows}x{cols} {name} {mode} level {level} {opts:?}");
                assert!(bits(&d) == bits(&reference.datum), "datum differs: {at}");
                assert!(
                    bits(&r) == bits(&reference.roughness),
                    "roughness differs: {at}"
                );
            }
        }
    }
}

#[test]
fn bit_identical_odd_even_non_square_with_holes() {
    let small_bands = StreamOptions {
        band_rows: Some(7),
        memory_store_max_bytes: 0,
        spill_dir: None,
    };
    // Odd x even, rows of holes at the top, middle and bottom.
    check(
        83,
        64,
        &[0, 1, 40, 41, 42, 82],
        &["db1", "db2", "sym5", "coif2"],
        &small_bands,
    );
    // Even x odd, wider than tall.
    check(64, 101, &[30], &["db3", "sym4"], &small_bands);
    // Odd x odd, a band of 5 (does not divide 77), levels kept in memory.
    let mem = StreamOptions {
        band_rows: Some(5),
        ..StreamOptions::default()
    };
    check(77, 77, &[76], &["db2", "sym5"], &mem);
}

#[test]
fn bit_identical_every_wavelet_default_bands() {
    // The default band is larger than this map: one band, every wavelet.
    let names: Vec<&str> = Wavelet::names().collect();
    let h = surface(90, 71, 3, &[2, 50]);
    for name in names {
        let w = Wavelet::by_name(name).expect("listed");
        if dwt_max_level(71, w.filter_len()) == 0 {
            continue;
        }
        for mode in [Mode::Symmetric, Mode::Periodization] {
            let reference = separate(&h, 90, 71, &w, mode, None).expect("separates");
            let (d, r, used) = streamed(
                &h,
                90,
                71,
                &w,
                mode,
                reference.level,
                &StreamOptions::default(),
            );
            assert_eq!(used, reference.level);
            assert!(bits(&d) == bits(&reference.datum), "{name} {mode}");
            assert!(bits(&r) == bits(&reference.roughness), "{name} {mode}");
        }
    }
}

#[test]
fn larger_map_many_bands_files() {
    // Several default-free bands per level at every level, levels in files.
    let opts = StreamOptions {
        band_rows: Some(33),
        memory_store_max_bytes: 0,
        spill_dir: Some(std::env::temp_dir()),
    };
    check(517, 300, &[0, 200, 201, 516], &["sym5"], &opts);
}

#[test]
fn errors_match_the_reference() {
    let w = Wavelet::by_name("sym5").expect("listed");
    let opts = StreamOptions::default();
    let ok = |_: usize, _: &[f32], _: &[f32]| Ok(());
    let nan = vec![f32::NAN; 400];
    assert!(separate_streamed(&nan, 20, 20, &w, Mode::Symmetric, None, &opts, ok).is_err());
    let small = vec![1.0f32; 17 * 30];
    assert!(separate_streamed(&small, 17, 30, &w, Mode::Symmetric, None, &opts, ok).is_err());
    assert!(separate_streamed(&small, 17, 31, &w, Mode::Symmetric, None, &opts, ok).is_err());
    // A failing sink stops the pass with its error.
    let h = surface(40, 40, 1, &[]);
    let e = separate_streamed(&h, 40, 40, &w, Mode::Symmetric, None, &opts, |_, _, _| {
        anyhow::bail!("disk full")
    })
    .expect_err("sink error");
    assert!(e.to_string().contains("disk full"), "{e}");
}

#[test]
fn energy_curve_agrees_to_round_off() {
    let h = surface(150, 131, 9, &[0, 75]);
    let w = Wavelet::by_name("sym5").expect("listed");
    let opts = StreamOptions {
        band_rows: Some(9),
        memory_store_max_bytes: 0,
        spill_dir: None,
    };
    for mode in [Mode::Symmetric, Mode::Periodization] {
        let a = energy_curve(&h, 150, 131, &w, mode).expect("curve");
        let b = energy_curve_streamed(&h, 150, 131, &w, mode, &opts).expect("curve");
        assert_eq!(a.len(), b.len());
        assert!(!a.is_empty());
        for (p, q) in a.iter().zip(&b) {
            assert_eq!(p.level, q.level);
            let (x, y) = (p.approx_energy_fraction, q.approx_energy_fraction);
            assert!(
                (x - y).abs() <= 1e-12 * x.abs().max(1e-300),
                "{mode}: {x} vs {y}"
            );
        }
    }
}

/// The energy curves (in memory and streamed) are the same bits whatever the number of
/// threads: their sums over rayon's work are added in a fixed order (rayon's reduce paired
/// them as the threads split the work, so the curve's last bits changed from run to run).
#[test]
fn energy_curves_do_not_depend_on_the_thread_count() {
    let (rows, cols) = (600, 517);
    let h = surface(rows, cols, 11, &[3, 400]);
    let w = Wavelet::by_name("sym5").expect("listed");
    let opts = StreamOptions {
        band_rows: Some(64),
        ..StreamOptions::default()
    };
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("pool");
        pool.install(|| {
            let curve = |c: Vec<surfstream_wavelet::EnergyPoint>| {
                c.iter()
                    .map(|p| p.approx_energy_fraction.to_bits())
                    .collect::<Vec<u64>>()
            };
            let a = energy_curve(&h, rows, cols, &w, Mode::Symmetric).expect("curve");
            let b =
                energy_curve_streamed(&h, rows, cols, &w, Mode::Symmetric, &opts).expect("curve");
            (curve(a), curve(b))
        })
    };
    let one = run(1);
    for threads in [2, 3, 8] {
        let other = run(threads);
        assert!(
            other.0 == one.0,
            "in-memory curve differs with {threads} threads"
        );
        assert!(
            other.1 == one.1,
            "streamed curve differs with {threads} threads"
        );
    }
}
