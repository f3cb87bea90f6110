#[path = "../tests/support/mod.rs"]
mod support;
use surfstream_matcher::{PhaseCorrelator, PhaseParams, RasterRef};
use support::{make_pair, surface_size, PairSpec, Surface};
fn main() {
    let args: Vec<String> = std::env::args().collect();
    let arg = |i: usize, d: f64| -> f64 { args.get(i).and_then(|s| s.parse().ok()).unwrap_or(d) };
    let tile = arg(1, 256.0) as usize;
    let noise = arg(2, 0.0);
    let nan = arg(3, 0.3);
    let blobs = arg(4, 3.0) as usize;
    let per_case = arg(5, 10.0) as usize;
    let thr = arg(6, 0.2);
    let p = PhaseParams::default();
    let mut corr = PhaseCorrelator::new();
    let mut seed = 1u64;
    for overlap in [0.1, 0.2, 0.3] {
        let n = surface_size(tile, overlap);
        for k in 0..per_case {
            let surface = Surface::rough(n, 1000 + seed, 40.0, 0.8, 0.25);
            for horizontal in [true, false] {
                let spec = PairSpec { noise_um: noise, nan_fraction: nan, nan_blobs: blobs, ..PairSpec::new(tile, overlap, horizontal, seed * 7 + k as u64) };
                seed += 1;
                let pair = make_pair(&surface, &spec);
                let a = RasterRef { heights: &pair.a, width: pair.w, height: pair.h };
                let b = RasterRef { heights: &pair.b, width: pair.w, height: pair.h };
                let r = corr.register(a, b, pair.nominal_offset_px, &p);
                let t = pair.true_offset_px;
                if let Some(o) = r.offset_px {
                    let e = [o[0]-t[0], o[1]-t[1]];
                    if e[0].abs().max(e[1].abs()) > thr {
                        println!("ov {overlap} h {horizontal} seed {} true ({:8.3},{:8.3}) err ({:+.3},{:+.3}) ncc {:.3} ratio {:.2} cands {:?}", seed-1, t[0], t[1], e[0], e[1], r.ncc, r.peak_ratio, r.candidates.iter().map(|c| (c.offset_px, (c.ncc*1000.0).round()/1000.0)).collect::<Vec<_>>());
                    }
                } else { println!("ov {overlap} h {horizontal} rejected {:?}", r.rejection); }
            }
        }
    }
}
