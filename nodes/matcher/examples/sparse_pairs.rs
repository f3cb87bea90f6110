//! Pairwise registration over many scan directories at once, scored against each one's
//! ground_truth.json: the raw pair estimates before the global solve (how `scripts/bench_sparse.py`
//! sets are diagnosed). Prints, per directory group (name up to "_s<seed>"), pairs answered,
//! within 0.5 px of the truth, wrong by > 1 px, and the RMS error of the answered pairs; with
//! `--pairs`, every pair beyond 0.3 px or refused.
//!
//! `cargo run --release -p surfstream-matcher --example sparse_pairs -- [--pairs] DIR...`

#[path = "support/scan.rs"]
#[allow(dead_code)]
mod support;

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::Result;
use support::Scan;
use surfstream_matcher::{PhaseCorrelator, PhaseParams, ScanTruth};

#[derive(Default)]
struct Tally {
    pairs: usize,
    answered: usize,
    within: usize,
    wrong: usize,
    sq: f64,
    /// Refused pairs with a one-direction (ridge) answer, those within 0.5 px across, and the
    /// sum of squared errors across.
    directional: usize,
    dir_within: usize,
    dir_sq: f64,
}

fn main() -> Result<()> {
    let mut verbose = false;
    let mut dirs = Vec::new();
    for a in std::env::args().skip(1) {
        if a == "--pairs" {
            verbose = true;
        } else {
            dirs.push(a);
        }
    }
    let params = PhaseParams::default();
    let mut corr = PhaseCorrelator::new();
    let mut groups: BTreeMap<String, Tally> = BTreeMap::new();
    for d in &dirs {
        let dir = Path::new(d);
        let tiles = Scan::load(&dir.join("scan.toml"))?;
        let truth = ScanTruth::read(&dir.join("ground_truth.json"))?;
        let name = dir.file_name().unwrap_or_default().to_string_lossy();
        let group = name
            .rsplit_once("_s")
            .map_or(name.to_string(), |g| g.0.to_string());
        let g = groups.entry(group).or_default();
        for (a, b) in tiles.neighbour_pairs() {
            let Some(t) = truth.true_offset_px(a as u64, b as u64) else {
                continue;
            };
            let nominal = tiles.nominal_offset_px(a, b);
            let r = corr.register(tiles.raster(a)?, tiles.raster(b)?, nominal, &params);
            g.pairs += 1;
            let err = r.offset_px.map(|o| (o[0] - t[0]).hypot(o[1] - t[1]));
            let dir_err = r.directional.filter(|_| r.offset_px.is_none()).map(|d| {
                (d.offset_px[0] - t[0]) * d.normal[0] + (d.offset_px[1] - t[1]) * d.normal[1]
            });
            if let Some(e) = dir_err {
                g.directional += 1;
                g.dir_within += (e.abs() <= 0.5) as usize;
                g.dir_sq += e * e;
            }
            if let Some(e) = err {
                g.answered += 1;
                g.sq += e * e;
                g.within += (e <= 0.5) as usize;
                g.wrong += (e > 1.0) as usize;
            }
            if verbose && err.is_none_or(|e| e > 0.3) {
                // How far the best candidate (refined) is from the truth, answered or not, and
                // the NCC of the runner-up candidate.
                let best_err = r.shift_from_nominal_px.map(|s| {
                    let e = (nominal[0] + s[0] - t[0]).hypot(nominal[1] + s[1] - t[1]);
                    (e * 1000.0).round() / 1000.0
                });
                let second = r.candidates.get(1).map_or(f64::NAN, |c| c.ncc);
                println!(
                    "{name} {a}-{b}: err {:?} best {best_err:?} 2nd ncc {second:.3} across {:?} \
                     shift {:?} ncc {:.3} round {:.3} {}",
                    err.map(|e| (e * 1000.0).round() / 1000.0),
                    dir_err.map(|e| (e * 1000.0).round() / 1000.0),
                    r.shift_from_nominal_px
                        .map(|s| [(s[0] * 10.0).round() / 10.0, (s[1] * 10.0).round() / 10.0]),
                    r.ncc,
                    r.peak_roundness,
                    r.rejection.map(|e| e.to_string()).unwrap_or_default()
                );
            }
        }
    }
    println!(
        "| group | pairs | answered | within 0.5 px | wrong > 1 px | rms of answered px | \
         one-direction answers | within 0.5 px across | rms across px |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    let mut all = Tally::default();
    for (k, g) in &groups {
        println!(
            "| {k} | {} | {} | {} | {} | {:.3} | {} | {} | {:.3} |",
            g.pairs,
            g.answered,
            g.within,
            g.wrong,
            (g.sq / g.answered.max(1) as f64).sqrt(),
            g.directional,
            g.dir_within,
            (g.dir_sq / g.directional.max(1) as f64).sqrt()
        );
        all.directional += g.directional;
        all.dir_within += g.dir_within;
        all.dir_sq += g.dir_sq;
        all.pairs += g.pairs;
        all.answered += g.answered;
        all.within += g.within;
        all.wrong += g.wrong;
        all.sq += g.sq;
    }
    println!(
        "| all | {} | {} | {} | {} | {:.3} | {} | {} | {:.3} |",
        all.pairs,
        all.answered,
        all.within,
        all.wrong,
        (all.sq / all.answered.max(1) as f64).sqrt(),
        all.directional,
        all.dir_within,
        (all.dir_sq / all.directional.max(1) as f64).sqrt()
    );
    Ok(())
}
