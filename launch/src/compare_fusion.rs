//! `surfstream stitch SCAN --compare-fusion --out DIR`: the paper's Table 2. The scan is
//! stitched three times, once per fusion method (average, gradual, wavelet), into
//! `DIR/<method>/`, and the SSIM of every overlap (the fusion node's `fusion_pairs`) is
//! summarised side by side.
//!
//! When the scan directory also holds `specimen.npy` and `ground_truth.json` (what
//! `make_tiles.py` writes), each panorama is also scored against the specimen it was cut from:
//! the panorama is placed on the specimen through tile 0 (its final position against its true
//! origin: this fixes the free global shift of a stitch), the specimen is sampled bilinearly at
//! every panorama pixel, the least-squares plane of the difference is removed (a stitch's
//! absolute height and tilt are free too), and the RMS of what is left is the height error;
//! SSIM of the panorama against the sampled specimen (same plane removed) is given beside it.

use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use serde_json::Value;
use surfstream_core::metrology::{level_plane, Grid, MetrologyError};
use surfstream_core::raster::Shape;
use surfstream_core::record::{self, FusionReport, OutputChoice, RunRecord};
use surfstream_core::similarity::ssim;

use surfstream_runtime::graph::GraphFile;

use crate::{launcher, stitch_graph};

const METHODS: [&str; 3] = ["average", "gradual", "wavelet"];

/// How each method's stitch is set up: the command line's `--set`, `--method`, and what
/// `--tolerance` / `--outputs` do to a graph (`prepare`, applied to every method's graph).
pub struct Methods<'a> {
    pub set: &'a [String],
    pub method: Option<&'a str>,
    pub outputs: Option<OutputChoice>,
    pub prepare: &'a dyn Fn(&mut GraphFile) -> Result<()>,
}

pub fn run(scan: &Path, out: &Path, how: &Methods) -> Result<()> {
    let (set, method) = (how.set, how.method);
    if let Some(s) = set
        .iter()
        .find(|s| s.trim_start().starts_with("fusion.method"))
    {
        bail!("--compare-fusion runs every fusion method itself: drop --set {s}");
    }
    let scan_dir = if scan.is_dir() {
        scan.to_path_buf()
    } else {
        scan.parent()
            .map_or_else(|| PathBuf::from("."), Path::to_path_buf)
    };
    if Truth::present(&scan_dir) && how.outputs == Some(OutputChoice::Model) {
        bail!(
            "--compare-fusion --outputs model: {} holds specimen.npy and ground_truth.json, and \
             the height error against the specimen reads each method's panorama.npy, which the \
             model set does not keep: use --outputs full (the default)",
            scan_dir.display()
        );
    }
    let truth = Truth::load(&scan_dir)?;
    let mut rows = Vec::new();
    for m in METHODS {
        let dir = out.join(m);
        let mut set_m = set.to_vec();
        set_m.push(format!("fusion.method={m}"));
        let (mut graph, deviation) = stitch_graph(scan, dir.clone(), &set_m, method)?;
        (how.prepare)(&mut graph)?;
        let claim = crate::outdir::Claim {
            inputs: crate::outdir::inputs_of(&graph, &dir),
            force: false,
        };
        launcher::run_in_process(graph, scan, deviation, &claim)?;
        rows.push(score(m, &dir, truth.as_ref())?);
    }
    println!();
    println!("Fusion methods (paper Table 2), SSIM of every overlap (Wang et al. 2004: 11x11 Gaussian window, sigma 1.5; mean of SSIM(fused, tile a) and SSIM(fused, tile b)):");
    println!();
    println!("| method | overlaps | mean SSIM | min SSIM | height RMS error vs specimen (um) | SSIM vs specimen |");
    println!("|---|---|---|---|---|---|");
    for r in &rows {
        let opt = |v: Option<f64>, d: usize| v.map_or("-".to_string(), |v| format!("{v:.d$}"));
        println!(
            "| {} | {} | {:.4} | {:.4} | {} | {} |",
            r.method,
            r.pairs,
            r.mean_ssim,
            r.min_ssim,
            opt(r.rms_error_um, 5),
            opt(r.ssim_vs_specimen, 4)
        );
    }
    println!();
    println!("outputs: {}/{{{}}}", out.display(), METHODS.join(","));
    Ok(())
}

struct Row {
    method: &'static str,
    pairs: usize,
    mean_ssim: f64,
    min_ssim: f64,
    rms_error_um: Option<f64>,
    ssim_vs_specimen: Option<f64>,
}

fn read_json(path: &Path) -> Result<Value> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("{}: cannot read", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("{}: not valid JSON", path.display()))
}

fn score(method: &'static str, dir: &Path, truth: Option<&Truth>) -> Result<Row> {
    let fpath = dir.join("nodes").join("fusion.json");
    let node: surfstream_runtime::node::NodeReport = serde_json::from_value(read_json(&fpath)?)
        .with_context(|| format!("{}: not a node report", fpath.display()))?;
    let fusion: FusionReport = record::from_value(&node.report, &fpath.display().to_string())
        .map_err(|e| anyhow!("{e} (the fusion's report)"))?;
    // A pair without a valid pixel has no SSIM (NaN, written as null).
    let ssims: Vec<f64> = (fusion.fusion_pairs.iter())
        .map(|p| p.ssim_mean)
        .filter(|s| !s.is_nan())
        .collect();
    let mean_ssim = ssims.iter().sum::<f64>() / ssims.len().max(1) as f64;
    let min_ssim = ssims.iter().copied().fold(f64::NAN, f64::min);
    let (rms_error_um, ssim_vs_specimen) = match truth {
        Some(t) => {
            let (rms, s) = t.compare(dir, &fusion, &fpath)?;
            (Some(rms), s)
        }
        None => (None, None),
    };
    Ok(Row {
        method,
        pairs: ssims.len(),
        mean_ssim,
        min_ssim,
        rms_error_um,
        ssim_vs_specimen,
    })
}

/// The specimen and tile 0's true origin, from make_tiles.py's files.
struct Truth {
    specimen: surfstream_io::npy::NpyArray<f32>,
    origin0_px: [f64; 2],
}

impl Truth {
    /// The scan directory holds the specimen and its truth (make_tiles.py's files).
    fn present(scan_dir: &Path) -> bool {
        scan_dir.join("specimen.npy").exists() && scan_dir.join("ground_truth.json").exists()
    }

    fn load(scan_dir: &Path) -> Result<Option<Truth>> {
        let (spec, gt) = (
            scan_dir.join("specimen.npy"),
            scan_dir.join("ground_truth.json"),
        );
        if !Self::present(scan_dir) {
            return Ok(None);
        }
        let text = std::fs::read_to_string(&gt)
            .with_context(|| format!("{}: cannot read", gt.display()))?;
        let truth: surfstream_core::record::TruthRecord = serde_json::from_str(&text)
            .with_context(|| {
                format!(
                    "{}: not a truth file (tiles[].true_origin_px)",
                    gt.display()
                )
            })?;
        let origin0_px = truth
            .tiles
            .first()
            .map(|t| t.true_origin_px)
            .with_context(|| format!("{}: tiles: expected at least one tile", gt.display()))?;
        let specimen = surfstream_io::npy::read_npy(&spec)?;
        Ok(Some(Truth {
            specimen,
            origin0_px,
        }))
    }

    /// Bilinear sample of the specimen at (x, y) specimen pixels; NaN outside or on a hole.
    fn sample(&self, x: f64, y: f64) -> f64 {
        let s = &self.specimen;
        let (x0, y0) = (x.floor(), y.floor());
        if x0 < 0.0 || y0 < 0.0 || x0 + 1.0 >= s.cols as f64 || y0 + 1.0 >= s.rows as f64 {
            return f64::NAN;
        }
        let (c, r) = (x0 as usize, y0 as usize);
        let (fx, fy) = (x - x0, y - y0);
        let v = |r: usize, c: usize| f64::from(s.get(r, c));
        (1.0 - fy) * ((1.0 - fx) * v(r, c) + fx * v(r, c + 1))
            + fy * ((1.0 - fx) * v(r + 1, c) + fx * v(r + 1, c + 1))
    }

    /// (height RMS error, SSIM) of `dir`'s panorama against the specimen.
    fn compare(
        &self,
        dir: &Path,
        fusion: &FusionReport,
        fpath: &Path,
    ) -> Result<(f64, Option<f64>)> {
        let run_path = dir.join("run.json");
        let run = RunRecord::read(&run_path).map_err(|e| anyhow!(e))?;
        let Some(tile0) = run.tiles.first().and_then(|t| t.placement.as_ref()) else {
            bail!("{}: tiles[0] has no final position", run_path.display());
        };
        let (x0_um, y0_um) = (tile0.x_um, tile0.y_um);
        let Some(g) = fusion.panorama else {
            bail!("{}: report.panorama missing", fpath.display());
        };
        let (ox, oy, px, py) = (g.origin_x_um, g.origin_y_um, g.pitch_x_um, g.pitch_y_um);
        let pano = surfstream_io::npy::read_npy(dir.join("panorama.npy"))?;
        let shape = Shape {
            rows: pano.rows,
            cols: pano.cols,
        };
        // The panorama and the specimen sampled under each of its pixels.
        let mut p = Vec::with_capacity(shape.len());
        let mut t = Vec::with_capacity(shape.len());
        for r in 0..shape.rows {
            for c in 0..shape.cols {
                let sx = self.origin0_px[0] + (ox + c as f64 * px - x0_um) / px;
                let sy = self.origin0_px[1] + (oy + r as f64 * py - y0_um) / py;
                p.push(f64::from(pano.get(r, c)));
                t.push(self.sample(sx, sy));
            }
        }
        // The difference without its least-squares plane (a stitch's height and tilt are free);
        // NaN where either map has no value.
        let diff: Vec<f64> = p
            .iter()
            .zip(&t)
            .map(|(p, t)| {
                if p.is_finite() && t.is_finite() {
                    p - t
                } else {
                    f64::NAN
                }
            })
            .collect();
        let grid = Grid::new(&diff, shape.rows, shape.cols, 1.0, 1.0)?;
        let levelled = match level_plane(&grid) {
            Err(MetrologyError::NoValidPoint) => {
                bail!("{}: no pixel overlaps the specimen", dir.display())
            }
            other => other?,
        };
        let mut sq = 0.0;
        let mut n = 0usize;
        let mut a = vec![f32::NAN; shape.len()];
        let mut b = vec![f32::NAN; shape.len()];
        for (i, d) in levelled.iter().enumerate().filter(|(_, d)| !d.is_nan()) {
            sq += d * d;
            n += 1;
            // The panorama with the difference's plane removed, against the specimen.
            a[i] = (t[i] + d) as f32;
            b[i] = t[i] as f32;
        }
        let (rows, cols) = (shape.rows, shape.cols);
        let s = ssim(&a, &b, rows, cols, None).ok().map(|s| s.mssim);
        Ok(((sq / n.max(1) as f64).sqrt(), s))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use surfstream_core::record::{FusionMemory, PairQuality};

    /// Table 2's SSIM columns from the fusion's node report as the node writes it (a pair
    /// without a valid pixel has a NaN SSIM, written as null, and is left out).
    #[test]
    fn ssim_of_the_overlaps_comes_from_the_fusion_node_report() {
        let pair = |ssim_mean| PairQuality {
            tile_a: 0,
            tile_b: 1,
            width_px: 10,
            height_px: 100,
            valid_px: 1000,
            ssim_a: ssim_mean,
            ssim_b: ssim_mean,
            ssim_mean,
        };
        let report = FusionReport {
            method: "gradual".into(),
            patches: 2,
            panorama: None,
            files: Vec::new(),
            rerendered_from_final_registrations: true,
            final_registrations: 2,
            ssim: String::new(),
            fusion_pairs: vec![pair(0.9), pair(f64::NAN), pair(0.7)],
            memory: FusionMemory {
                chunk_px: 512,
                chunk_budget_bytes: None,
                chunks: Value::Null,
            },
        };
        let node = serde_json::json!({ "node_id": "fusion", "node_kind": "fusion",
            "stats": { "received": {}, "sent": {}, "deliveries": {} },
            "report": record::to_value(&report).unwrap(), "t_finished_ns": 1 });
        let d = tempfile::tempdir().unwrap();
        std::fs::create_dir(d.path().join("nodes")).unwrap();
        std::fs::write(d.path().join("nodes/fusion.json"), node.to_string()).unwrap();
        let row = score("gradual", d.path(), None).unwrap();
        assert_eq!(row.pairs, 2);
        assert!((row.mean_ssim - 0.8).abs() < 1e-12 && row.min_ssim == 0.7);
        // A report that is not the fusion's is named.
        std::fs::write(d.path().join("nodes/fusion.json"), "{}").unwrap();
        let e = score("gradual", d.path(), None).err().unwrap().to_string();
        assert!(e.contains("fusion.json: not a node report"), "{e}");
    }
}
