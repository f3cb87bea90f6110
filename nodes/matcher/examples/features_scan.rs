//! The feature matchers (Harris + NCC, SIFT) pair by pair on scan directories with
//! `ground_truth.json` beside `scan.toml` (what `stitch_anchors.py generate` writes), scored
//! like the anchors' pairwise rows: the raw pair estimate against the true offset, before any
//! global solve. Prints per method and per texture (the set name's first field): pairs, share
//! answered, share within 0.5 px, share wrong by more than 2 px, max error, mean r, MAP, the
//! median residual rotation and the median time per pair.
//!
//! `RAYON_NUM_THREADS=1 cargo run --release -p surfstream-matcher --example features_scan -- \
//!     bench-out/stitch/data [harris|sift|both]`
//! (a directory of sets, or one set's scan.toml; FEATURES_WINDOW_RADIUS=N changes the NCC
//! window, FEATURES_VERBOSE=1 prints every pair)

#[path = "support/scan.rs"]
mod support;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{anyhow, bail, Result};
use support::{median, Scan};
use surfstream_matcher::efficiency::{aggregate, MatchQuality};
use surfstream_matcher::{register_pair_features, FeatureMethod, FeatureParams, ScanTruth};

#[derive(Default)]
struct Stats {
    pairs: usize,
    answered: usize,
    within_half: usize,
    over_two: usize,
    max_err: f64,
    qualities: Vec<MatchQuality>,
    rotations_deg: Vec<f64>,
    ms: Vec<f64>,
    reasons: BTreeMap<String, usize>,
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let root = PathBuf::from(
        args.get(1)
            .ok_or_else(|| anyhow!("usage: features_scan DIR|SCAN.toml [harris|sift|both]"))?,
    );
    let methods = match args.get(2).map(|s| s.as_str()).unwrap_or("both") {
        "harris" => vec![FeatureMethod::Harris],
        "sift" => vec![FeatureMethod::Sift],
        "both" => vec![FeatureMethod::Harris, FeatureMethod::Sift],
        m => bail!("method {m:?}: expected harris, sift or both"),
    };
    let mut scans = Vec::new();
    if root.is_dir() {
        for e in std::fs::read_dir(&root)? {
            let p = e?.path().join("scan.toml");
            if p.exists()
                && p.parent()
                    .is_some_and(|d| d.join("ground_truth.json").exists())
            {
                scans.push(p);
            }
        }
        scans.sort();
    } else {
        scans.push(root.clone());
    }
    if scans.is_empty() {
        bail!("{}: no scan.toml with ground_truth.json", root.display());
    }
    // FEATURES_WINDOW_RADIUS=N: NCC windows of half side N px instead of the default.
    let window_radius: Option<usize> = std::env::var("FEATURES_WINDOW_RADIUS")
        .ok()
        .map(|v| v.parse())
        .transpose()?;
    // FEATURES_VERBOSE=1: one line per pair on stderr.
    let verbose = std::env::var_os("FEATURES_VERBOSE").is_some();
    let mut stats: BTreeMap<(String, String), Stats> = BTreeMap::new();
    for scan in &scans {
        let dir = scan.parent().unwrap_or(Path::new("."));
        let texture = dir
            .file_name()
            .and_then(|n| n.to_str())
            .and_then(|n| n.split("__").next())
            .unwrap_or("?")
            .to_string();
        let truth = ScanTruth::read(&dir.join("ground_truth.json"))?;
        let tiles = Scan::load(scan)?;
        for &method in &methods {
            let mut params = FeatureParams::for_method(method);
            if let Some(r) = window_radius {
                params.window_radius_px = r;
            }
            for (a, b) in tiles.neighbour_pairs() {
                let nominal = tiles.nominal_offset_px(a, b);
                let t0 = Instant::now();
                let f =
                    register_pair_features(tiles.raster(a)?, tiles.raster(b)?, nominal, &params);
                let ms = t0.elapsed().as_secs_f64() * 1e3;
                let true_off = truth
                    .true_offset_px(a as u64, b as u64)
                    .ok_or_else(|| anyhow!("{}: no truth for tile pair", dir.display()))?;
                let s = stats
                    .entry((method.name().to_string(), texture.clone()))
                    .or_default();
                s.pairs += 1;
                s.ms.push(ms);
                s.qualities.push(f.quality(true_off, 1.0));
                if let Some(r) = f.rotation_deg {
                    s.rotations_deg.push(r.abs());
                }
                if verbose {
                    eprintln!(
                            "{} {} {}-{}: features {:?}, one-way {}, two-way {}, inliers {}, truth {:?}, answer {:?}, {}",
                            dir.display(), method.name(), a, b, f.features,
                            f.one_way_matches, f.matches.len(), f.inliers, true_off,
                            f.registration.offset_px, f.reason().unwrap_or_default()
                        );
                }
                if let Some(rej) = &f.registration.rejection {
                    // The rejection's variant name.
                    let kind = format!("{rej:?}");
                    let kind = kind.split([' ', '{', '(']).next().unwrap_or("").to_string();
                    *s.reasons.entry(kind).or_default() += 1;
                }
                if let Some(o) = f.registration.offset_px {
                    s.answered += 1;
                    let e = (o[0] - true_off[0]).abs().max((o[1] - true_off[1]).abs());
                    s.within_half += usize::from(e <= 0.5);
                    s.over_two += usize::from(e > 2.0);
                    s.max_err = s.max_err.max(e);
                }
            }
        }
    }
    println!(
        "{} sets; pair estimates before any global solve; error = max over x, y of |estimate - truth|",
        scans.len()
    );
    println!("| method | texture | pairs | answered | <=0.5px | >2px | max err px | mean r | MAP | median abs rotation deg | median ms/pair |");
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    let mut totals: BTreeMap<String, Stats> = BTreeMap::new();
    let pct = |n: usize, d: usize| 100.0 * n as f64 / d.max(1) as f64;
    let print = |m: &str, tex: &str, s: &Stats| {
        let (r, map, _) = aggregate(&s.qualities);
        println!(
            "| {m} | {tex} | {} | {:.0}% | {:.0}% | {:.0}% | {:.2} | {:.3} | {:.3} | {:.3} | {:.1} |",
            s.pairs,
            pct(s.answered, s.pairs),
            pct(s.within_half, s.pairs),
            pct(s.over_two, s.pairs),
            s.max_err,
            r.unwrap_or(f64::NAN),
            map.unwrap_or(f64::NAN),
            median(s.rotations_deg.clone()),
            median(s.ms.clone()),
        );
    };
    for ((m, tex), s) in &stats {
        print(m, tex, s);
        let t = totals.entry(m.clone()).or_default();
        t.pairs += s.pairs;
        t.answered += s.answered;
        t.within_half += s.within_half;
        t.over_two += s.over_two;
        t.max_err = t.max_err.max(s.max_err);
        t.qualities.extend(s.qualities.iter().copied());
        t.rotations_deg.extend(s.rotations_deg.iter().copied());
        t.ms.extend(s.ms.iter().copied());
    }
    for (m, s) in &totals {
        print(m, "all", s);
    }
    for ((m, tex), s) in &stats {
        println!("{m} / {tex}: not answered: {:?}", s.reasons);
    }
    Ok(())
}
