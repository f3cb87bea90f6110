//! Timing of the wavelet node's kernels on generated fields (loads nothing):
//!
//! ```text
//! cargo run --release -p surfstream-wavelet --example bench_wavelet [-- [--only rt|sep|pool] [--inputs DIR] SIZE ...]
//! ```
//!
//! `--inputs DIR` reads `DIR/synth_<n>.npy` (float64), the arrays the anchors write with
//! `wavelet_anchor.py --save-inputs DIR` / `pooling_anchor.py --save-inputs DIR`, so both
//! sides time the same data; without it the fields are generated here.
//!
//! For each size (default 1024 2048 4096) prints the median over repeats of
//! * `wavedec2` + `waverec2`, sym5, level 8, symmetric, f64 (the PyWavelets anchor's headline);
//! * `separate`, sym5, level 8 (clamped to the map's maximum), symmetric, f32 in / out;
//! * 4 x 4 max pooling of an f32 map;
//!
//! and the peak heap memory one round trip needs beyond its input, in multiples of the f64
//! input's size (counted by a wrapping global allocator).

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

use surfstream_wavelet::{pool, separate, wavedec2, waverec2, Mode, PoolOp, Wavelet};

/// A self-affine-ish test surface: a few sines plus splitmix64 noise, in µm.
fn field(n: usize, seed: u64) -> Vec<f64> {
    let mut s = seed;
    let mut noise = move || {
        s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = s;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        (z >> 11) as f64 / (1u64 << 53) as f64 - 0.5
    };
    let mut out = Vec::with_capacity(n * n);
    for r in 0..n {
        for c in 0..n {
            let (y, x) = (r as f64 / n as f64, c as f64 / n as f64);
            out.push(
                3.0 * (6.0 * x).sin() * (4.0 * y).cos()
                    + 0.5 * (80.0 * x + 30.0 * y).sin()
                    + noise(),
            );
        }
    }
    out
}

/// (median, min) wall time in ms over `repeats` runs after one warm-up; (0, 0) if `repeats`
/// is 0. The min is reported too because a shared machine's load inflates medians.
fn time_ms(repeats: usize, mut f: impl FnMut()) -> (f64, f64) {
    if repeats == 0 {
        return (0.0, 0.0);
    }
    f(); // warm-up: page faults, rayon start-up
    let mut t: Vec<f64> = (0..repeats)
        .map(|_| {
            let t0 = Instant::now();
            f();
            t0.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    t.sort_by(f64::total_cmp);
    (t[t.len() / 2], t[0])
}

/// Counts live heap bytes so the example can report the round trip's peak working memory
/// exactly, independent of how the C allocator caches or returns pages.
struct Counting;

static LIVE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

// SAFETY: forwards every call to the system allocator unchanged; only counts bytes.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: same contract as the caller's.
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            let now = LIVE.fetch_add(layout.size(), Ordering::Relaxed) + layout.size();
            PEAK.fetch_max(now, Ordering::Relaxed);
        }
        p
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        // SAFETY: same contract as the caller's.
        let p = unsafe { System.alloc_zeroed(layout) };
        if !p.is_null() {
            let now = LIVE.fetch_add(layout.size(), Ordering::Relaxed) + layout.size();
            PEAK.fetch_max(now, Ordering::Relaxed);
        }
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: same contract as the caller's.
        unsafe { System.dealloc(ptr, layout) };
        LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: same contract as the caller's.
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
            let now = LIVE.fetch_add(new_size, Ordering::Relaxed) + new_size;
            PEAK.fetch_max(now, Ordering::Relaxed);
        }
        p
    }
}

#[global_allocator]
static ALLOC: Counting = Counting;

/// Heap bytes `f` needs beyond what is live when it starts (its peak working memory).
fn extra_peak_bytes(f: impl FnOnce()) -> usize {
    let base = LIVE.load(Ordering::Relaxed);
    PEAK.store(base, Ordering::Relaxed);
    f();
    PEAK.load(Ordering::Relaxed).saturating_sub(base)
}

fn main() -> anyhow::Result<()> {
    let mut args: Vec<String> = std::env::args().skip(1).collect();
    // `--only X` runs one kernel (for profiling); the others print as 0.
    let only = match args.iter().position(|a| a == "--only") {
        Some(i) if i + 1 < args.len() => {
            let v = args.remove(i + 1);
            args.remove(i);
            Some(v)
        }
        _ => None,
    };
    let inputs = match args.iter().position(|a| a == "--inputs") {
        Some(i) if i + 1 < args.len() => {
            let v = args.remove(i + 1);
            args.remove(i);
            Some(std::path::PathBuf::from(v))
        }
        _ => None,
    };
    let run = |what: &str| only.as_deref().is_none_or(|o| o == what);
    let sizes: Vec<usize> = args.iter().map(|a| a.parse()).collect::<Result<_, _>>()?;
    let sizes = if sizes.is_empty() {
        vec![1024, 2048, 4096]
    } else {
        sizes
    };
    let w = Wavelet::by_name("sym5").ok_or_else(|| anyhow::anyhow!("sym5 missing"))?;
    let mode = Mode::Symmetric;
    println!("rayon threads: {}", rayon::current_num_threads());
    println!("median (min) wall ms");
    println!(
        "{:>6} {:>18} {:>18} {:>18} {:>18}",
        "n", "dec+rec sym5 L8", "separate", "maxpool 4x4", "round-trip peak"
    );
    for n in sizes {
        let reps = if n <= 1024 {
            21
        } else if n <= 2048 {
            11
        } else {
            7
        };
        let x = match &inputs {
            Some(dir) => {
                let path = dir.join(format!("synth_{n}.npy"));
                let a = surfstream_io::npy::read_npy_f64(&path)?;
                anyhow::ensure!(
                    (a.rows, a.cols) == (n, n),
                    "{}: {} x {}, expected {n} x {n}",
                    path.display(),
                    a.rows,
                    a.cols
                );
                a.data
            }
            None => field(n, n as u64),
        };
        let x32: Vec<f32> = x.iter().map(|&v| v as f32).collect();

        let rt = time_ms(if run("rt") { reps } else { 0 }, || {
            let c = wavedec2(&x, n, n, &w, mode, 8).expect("wavedec2");
            let r = waverec2(&c, &w, mode).expect("waverec2");
            std::hint::black_box(r);
        });
        let sep = time_ms(if run("sep") { reps } else { 0 }, || {
            let s = separate(&x32, n, n, &w, mode, Some(8)).expect("separate");
            std::hint::black_box(s);
        });
        let mp = time_ms(if run("pool") { reps.max(11) } else { 0 }, || {
            let p = pool(&x32, n, n, 4, PoolOp::Max).expect("pool");
            std::hint::black_box(p);
        });

        // Peak heap of one round trip beyond the input it is given, relative to that input.
        let extra = extra_peak_bytes(|| {
            let c = wavedec2(&x, n, n, &w, mode, 8).expect("wavedec2");
            let r = waverec2(&c, &w, mode).expect("waverec2");
            std::hint::black_box(r);
        });
        let peak = format!("+{:.2} x input", extra as f64 / (8 * n * n) as f64);
        let ms = |(med, min): (f64, f64)| format!("{med:.2} ({min:.2})");
        println!(
            "{n:>6} {:>18} {:>18} {:>18} {peak:>18}",
            ms(rt),
            ms(sep),
            ms(mp)
        );
    }
    Ok(())
}
