#[path = "../tests/support/mod.rs"]
mod support;
use surfstream_matcher::{PhaseCorrelator, PhaseParams, RasterRef, SubPixel};
use support::{make_pair, surface_size, PairSpec, Surface};
fn main() {
    let args: Vec<String> = std::env::args().collect();
    let arg = |i: usize, d: f64| -> f64 { args.get(i).and_then(|s| s.parse().ok()).unwrap_or(d) };
    let tile = arg(1, 256.0) as usize;
    let noise = arg(2, 0.0);
    let nan = arg(3, 0.3);
    let blobs = arg(4, 3.0) as usize;
    let per_case = arg(5, 4.0) as usize;
    let corr_len = arg(6, 40.0);
    let cutoff = arg(7, 0.25);
    let p = PhaseParams::default();
    let q = PhaseParams { subpixel: SubPixel::PhaseGaussian, ..PhaseParams::default() };
    let mut corr = PhaseCorrelator::new();
    let mut seed = 1u64;
    for overlap in [0.1, 0.2, 0.3] {
        let n = surface_size(tile, overlap);
        for k in 0..per_case {
            let surface = Surface::rough(n, 1000 + seed, corr_len, 0.8, cutoff);
            for horizontal in [true, false] {
                let spec = PairSpec { noise_um: noise, nan_fraction: nan, nan_blobs: blobs, ..PairSpec::new(tile, overlap, horizontal, seed * 7 + k as u64) };
                seed += 1;
                let pair = make_pair(&surface, &spec);
                let a = RasterRef { heights: &pair.a, width: pair.w, height: pair.h };
                let b = RasterRef { heights: &pair.b, width: pair.w, height: pair.h };
                let t = pair.true_offset_px;
                let r = corr.register(a, b, pair.nominal_offset_px, &q);
                let r2 = corr.register(a, b, pair.nominal_offset_px, &p);
                if let (Some(o), Some(o2)) = (r.offset_px, r2.offset_px) {
                    eprintln!("ov {overlap} h {horizontal:5} ncc {:.3} err ncc ({:+.3},{:+.3}) pc ({:+.3},{:+.3})", r.ncc, o[0]-t[0], o[1]-t[1], o2[0]-t[0], o2[1]-t[1]);
                }
            }
        }
    }
}
