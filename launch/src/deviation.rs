//! The model-vs-measurement deviation of the reference study's Table 6, run once after the
//! nodes finish (runjson::write calls [`attach`]).
//!
//! Measured surface: the fused panorama (`panorama.npy`). Model stages: "datum+roughness"
//! (`datum.npy` + `roughness.npy`) and "pooled" (`pooled.npy`, each pooled cell spread back
//! over the panorama pixels it pooled: nearest re-sampling onto the panorama grid) and "mesh"
//! (`mesh_resampled.npy`, the mesher's STL surface re-sampled on the grid it meshed, spread
//! back onto the panorama grid the same way).
//!
//! Regions: S1..Sn = each tile's footprint in the panorama (from its final position), and
//! "panorama" = the whole map. Parameters (ISO 25178, mean removed, no levelling, over points
//! valid in the measured map and the model) for each region and stage; relative deviation
//! = (model - measured) / measured in %; a stage passes in a region when |deviation| <= e for
//! Sa, Sq and Sz (Table 6's parameters). The nine parameters are all reported; slope
//! parameters of a re-sampled model (Sdq, Sdr of the pooled map) differ by construction and
//! are not judged. e defaults to [`DEFAULT_THRESHOLD_PCT`]; a graph file changes it with a
//! `[deviation]` table (`threshold_percent = 2`), the command line with
//! `--set deviation.threshold_percent=2` ([`Settings`]).
//!
//! Also writes `panorama.x3p` (the stitched panorama for MountainsMap, Gwyddion, surfalize).

use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};
use serde_json::{json, Map, Value};
use surfstream_core::metrology::{self, Grid, Params};
use surfstream_io::formats::{self, Metadata, Surface};
use surfstream_io::npy::read_npy_f64;

/// Threshold e of Table 6, in percent.
pub const DEFAULT_THRESHOLD_PCT: f64 = 5.0;
/// The `--set` key and graph-file table of the settings below.
pub const SECTION: &str = "deviation";

/// Settings of the Table-6 evaluation: a `[deviation]` table in the graph file, or
/// `--set deviation.threshold_percent=VALUE` (which wins). The graph parser knows only
/// `[graph]` and `[[node]]`: the launcher takes this table out before parsing
/// ([`split_graph_text`]) and keeps the settings for the run ([`configure`]).
#[derive(Debug, Clone, Copy, PartialEq, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Settings {
    /// Threshold e in percent: a stage passes a region when |deviation| <= e for Sa, Sq, Sz.
    #[serde(default = "default_threshold_pct")]
    pub threshold_percent: f64,
}

fn default_threshold_pct() -> f64 {
    DEFAULT_THRESHOLD_PCT
}

impl Default for Settings {
    fn default() -> Self {
        DEFAULTS
    }
}

const DEFAULTS: Settings = Settings {
    threshold_percent: DEFAULT_THRESHOLD_PCT,
};

impl Settings {
    fn check(self, origin: &str) -> Result<Self> {
        let e = self.threshold_percent;
        if !(e.is_finite() && e > 0.0) {
            bail!("{origin}: deviation.threshold_percent is {e}, expected a finite number > 0 (percent)");
        }
        Ok(self)
    }

    /// Applies the `--set` assignments addressed to `deviation.` and returns the others (for
    /// the nodes), in order.
    pub fn apply_sets(&mut self, sets: &[String]) -> Result<Vec<String>> {
        let mut rest = Vec::new();
        for s in sets {
            let Some((key, value)) = s.split_once('=') else {
                rest.push(s.clone());
                continue;
            };
            let Some(name) = key.trim().strip_prefix("deviation.") else {
                rest.push(s.clone());
                continue;
            };
            match name {
                "threshold_percent" => {
                    self.threshold_percent = value.trim().parse().map_err(|_| {
                        anyhow!("--set {s:?}: expected a number of percent, e.g. deviation.threshold_percent=2")
                    })?;
                }
                other => bail!(
                    "--set {s:?}: the deviation settings have no '{other}' (known: threshold_percent)"
                ),
            }
        }
        self.check("--set")?;
        Ok(rest)
    }
}

/// Takes the `[deviation]` table out of a graph file's text: the settings, and the text the
/// graph parser gets (unchanged when there is no such table, so its error positions stay
/// those of the file).
pub fn split_graph_text(text: &str, origin: &str) -> Result<(String, Settings)> {
    let mut table: toml::Table =
        toml::from_str(text).map_err(|e| anyhow!("{origin}: not a valid graph file: {e}"))?;
    let Some(section) = table.remove(SECTION) else {
        return Ok((text.to_string(), Settings::default()));
    };
    let settings: Settings = section
        .try_into()
        .map_err(|e| anyhow!("{origin}: [deviation]: {e}"))?;
    let rest = toml::to_string(&table).map_err(|e| anyhow!("{origin}: {e}"))?;
    Ok((rest, settings.check(origin)?))
}

/// The parameters Table 6 judges.
pub const JUDGED: [&str; 3] = ["Sa", "Sq", "Sz"];

/// A rectangle of the panorama grid, pixels, end exclusive.
#[derive(Debug, Clone, PartialEq)]
pub struct Region {
    pub name: String,
    pub row0: usize,
    pub col0: usize,
    pub rows: usize,
    pub cols: usize,
}

/// The measured panorama and its regions.
pub struct Measured {
    pub heights_um: Vec<f64>,
    pub rows: usize,
    pub cols: usize,
    pub pitch_x_um: f64,
    pub pitch_y_um: f64,
    pub regions: Vec<Region>,
}

/// The heights of `region` of a `cols`-wide map where `mask` (same shape) is valid, NaN elsewhere.
fn crop(z: &[f64], mask: &[f64], cols: usize, r: &Region) -> Vec<f64> {
    let mut out = Vec::with_capacity(r.rows * r.cols);
    for row in r.row0..r.row0 + r.rows {
        let s = row * cols + r.col0;
        out.extend(
            z[s..s + r.cols]
                .iter()
                .zip(&mask[s..s + r.cols])
                .map(|(&v, &m)| if m.is_nan() { f64::NAN } else { v }),
        );
    }
    out
}

fn params_of(z: &[f64], r: &Region, px: f64, py: f64) -> Option<Params> {
    metrology::params(&Grid::new(z, r.rows, r.cols, px, py).ok()?).ok()
}

fn params_json(p: &Option<Params>) -> Value {
    match p {
        Some(p) => serde_json::to_value(p).unwrap_or(Value::Null),
        None => Value::Null,
    }
}

/// Table 6 for one model raster (same grid as the panorama): per region the model's
/// parameters, the measured ones, relative deviations (%) and pass/fail at `threshold_pct`.
pub fn compare_stage(
    m: &Measured,
    stage: &str,
    model_um: &[f64],
    threshold_pct: f64,
) -> Result<Value> {
    if model_um.len() != m.heights_um.len() {
        bail!(
            "stage {stage}: model has {} values, the panorama {} x {}",
            model_um.len(),
            m.rows,
            m.cols
        );
    }
    let mut regions = Map::new();
    let mut all_pass = true;
    for r in &m.regions {
        // Both over the points valid in both maps, so holes do not count as deviation.
        let measured = params_of(
            &crop(&m.heights_um, model_um, m.cols, r),
            r,
            m.pitch_x_um,
            m.pitch_y_um,
        );
        let model = params_of(
            &crop(model_um, &m.heights_um, m.cols, r),
            r,
            m.pitch_x_um,
            m.pitch_y_um,
        );
        let mut deviation = Map::new();
        let mut pass = measured.is_some() && model.is_some();
        if let (Some(a), Some(b)) = (&measured, &model) {
            for ((name, va), (_, vb)) in a.named().iter().zip(b.named()) {
                let d = (vb - va) / va * 100.0;
                deviation.insert(
                    name.to_string(),
                    if d.is_finite() { json!(d) } else { Value::Null },
                );
                if JUDGED.contains(name) && !(d.is_finite() && d.abs() <= threshold_pct) {
                    pass = false;
                }
            }
        }
        all_pass &= pass;
        regions.insert(
            r.name.clone(),
            json!({
                "measured": params_json(&measured),
                "model": params_json(&model),
                "deviation_pct": deviation,
                "pass": pass,
            }),
        );
    }
    Ok(json!({ "regions": regions, "pass": all_pass }))
}

/// Nearest re-sampling of a `factor` x `factor` pooled map back onto the `rows x cols` grid.
pub fn unpool(
    pooled: &[f64],
    p_rows: usize,
    p_cols: usize,
    rows: usize,
    cols: usize,
) -> Result<Vec<f64>> {
    let factor = cols.div_ceil(p_cols.max(1)).max(1);
    if cols.div_ceil(factor) != p_cols
        || rows.div_ceil(factor) != p_rows
        || pooled.len() != p_rows * p_cols
    {
        bail!("pooled map {p_rows} x {p_cols} is not a whole-factor pooling of the {rows} x {cols} panorama");
    }
    let mut out = Vec::with_capacity(rows * cols);
    for r in 0..rows {
        let src = &pooled[(r / factor) * p_cols..(r / factor + 1) * p_cols];
        out.extend((0..cols).map(|c| src[c / factor]));
    }
    Ok(out)
}

/// Tile footprints on the panorama grid from run.json's tiles (final x_um / y_um) and the
/// fusion's panorama geometry; clipped to the map.
pub fn tile_regions(
    tiles: &[Value],
    pano: &Value,
    tile_w: usize,
    tile_h: usize,
    rows: usize,
    cols: usize,
) -> Vec<Region> {
    let f = |k: &str| pano.get(k).and_then(Value::as_f64);
    let (Some(ox), Some(oy), Some(px), Some(py)) = (
        f("origin_x_um"),
        f("origin_y_um"),
        f("pitch_x_um"),
        f("pitch_y_um"),
    ) else {
        return Vec::new();
    };
    let mut out = Vec::new();
    for (k, t) in tiles.iter().enumerate() {
        let (Some(x), Some(y)) = (
            t.get("x_um").and_then(Value::as_f64),
            t.get("y_um").and_then(Value::as_f64),
        ) else {
            continue;
        };
        let c0 = ((x - ox) / px).round().max(0.0) as usize;
        let r0 = ((y - oy) / py).round().max(0.0) as usize;
        if c0 >= cols || r0 >= rows {
            continue;
        }
        out.push(Region {
            name: format!("S{}", k + 1),
            row0: r0,
            col0: c0,
            rows: tile_h.min(rows - r0),
            cols: tile_w.min(cols - c0),
        });
    }
    out
}

/// Reads the out dir's rasters, computes Table 6 and writes panorama.x3p.
fn evaluate(out: &Path, run: &Value, threshold_pct: f64) -> Result<Value> {
    let pano_path = out.join("panorama.npy");
    let pano = read_npy_f64(&pano_path)?;
    let geometry = run["stages"]
        .as_object()
        .and_then(|s| {
            s.values()
                .find_map(|r| r.get("panorama").filter(|p| p.get("origin_x_um").is_some()))
        })
        .cloned()
        .context("no node report carries the panorama geometry (origin, pitch)")?;
    let px = geometry["pitch_x_um"]
        .as_f64()
        .context("panorama pitch_x_um")?;
    let py = geometry["pitch_y_um"]
        .as_f64()
        .context("panorama pitch_y_um")?;
    let (rows, cols) = (pano.rows, pano.cols);
    let mut regions = Vec::new();
    if let (Some(tiles), Some(tw), Some(th)) = (
        run["tiles"].as_array(),
        run["scan"]["tile_width_px"].as_u64(),
        run["scan"]["tile_height_px"].as_u64(),
    ) {
        regions = tile_regions(tiles, &geometry, tw as usize, th as usize, rows, cols);
    }
    regions.push(Region {
        name: "panorama".into(),
        row0: 0,
        col0: 0,
        rows,
        cols,
    });
    let x3p = out.join("panorama.x3p");
    formats::write_surface(
        &x3p,
        &Surface {
            width: cols,
            height: rows,
            pitch_x_um: px,
            pitch_y_um: py,
            heights_um: pano.data.clone(),
            metadata: Metadata {
                format: "npy".into(),
                pitch_known: true,
                ..Metadata::default()
            },
        },
    )?;
    let measured = Measured {
        heights_um: pano.data,
        rows,
        cols,
        pitch_x_um: px,
        pitch_y_um: py,
        regions,
    };
    let mut stages = Map::new();
    let datum = out.join("datum.npy");
    let rough = out.join("roughness.npy");
    if datum.exists() && rough.exists() {
        let d = read_npy_f64(&datum)?;
        let r = read_npy_f64(&rough)?;
        if (d.rows, d.cols, r.rows, r.cols) != (rows, cols, rows, cols) {
            bail!(
                "datum {} x {} / roughness {} x {} differ from the panorama {rows} x {cols}",
                d.rows,
                d.cols,
                r.rows,
                r.cols
            );
        }
        let sum: Vec<f64> = d.data.iter().zip(&r.data).map(|(a, b)| a + b).collect();
        stages.insert(
            "datum+roughness".into(),
            compare_stage(&measured, "datum+roughness", &sum, threshold_pct)?,
        );
    }
    let pooled = out.join("pooled.npy");
    if pooled.exists() {
        let p = read_npy_f64(&pooled)?;
        let up = unpool(&p.data, p.rows, p.cols, rows, cols)
            .with_context(|| format!("{}", pooled.display()))?;
        stages.insert(
            "pooled".into(),
            compare_stage(&measured, "pooled", &up, threshold_pct)?,
        );
    }
    // The mesher's surface re-sampled on its grid (the pooled map's, the panorama's...):
    // the model one stage further, judged against the same measured panorama.
    let mesh = out.join("mesh_resampled.npy");
    if mesh.exists() {
        let m = read_npy_f64(&mesh)?;
        let up = unpool(&m.data, m.rows, m.cols, rows, cols)
            .with_context(|| format!("{}", mesh.display()))?;
        stages.insert(
            "mesh".into(),
            compare_stage(&measured, "mesh", &up, threshold_pct)?,
        );
    }
    let pass = stages.values().all(|s| s["pass"] == json!(true));
    Ok(json!({
            "measured": "panorama.npy",
            "threshold_pct": threshold_pct,
            "judged": JUDGED,
            "conventions": "ISO 25178 over points valid in both maps, mean removed, no levelling; deviation = (model - measured) / measured * 100; pass = |deviation| <= threshold for Sa, Sq, Sz",
            "regions": measured.regions.iter().map(|r| json!({"name": r.name, "row0": r.row0, "col0": r.col0, "rows": r.rows, "cols": r.cols})).collect::<Vec<_>>(),
            "stages": stages,
            "pass": pass,
    }))
}

/// Adds "deviation" (Table 6) to run.json and writes panorama.x3p when the out dir holds a
/// panorama; a failure is recorded in run.json (and on stderr), not fatal to the run.
pub fn attach(out: &Path, mut run: Value, threshold_percent: f64) -> Value {
    if !out.join("panorama.npy").exists() {
        return run;
    }
    let entry = match evaluate(out, &run, threshold_percent) {
        Ok(v) => {
            if let Some(files) = run["files"].as_array_mut() {
                files.push(json!("panorama.x3p"));
                files.sort_by(|a, b| a.as_str().cmp(&b.as_str()));
                files.dedup();
            }
            v
        }
        Err(e) => {
            eprintln!("surfstream: model-vs-measurement deviation not computed: {e:#}");
            json!({ "error": format!("{e:#}") })
        }
    };
    if let Some(o) = run.as_object_mut() {
        o.insert("deviation".into(), entry);
    }
    run
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn settings_from_graph_text_and_set() {
        let text = "[graph]\nname = \"g\"\n\n[deviation]\nthreshold_percent = 2.5\n\n[[node]]\nid = \"a\"\nnode = \"replay\"\n";
        let (rest, s) = split_graph_text(text, "g.toml").unwrap();
        assert_eq!(s.threshold_percent, 2.5);
        assert!(!rest.contains("deviation") && rest.contains("replay"));
        // No table: the text is passed on unchanged, the default applies.
        let plain = "[graph]\nname = \"g\"\n";
        assert_eq!(
            split_graph_text(plain, "g.toml").unwrap(),
            (plain.to_string(), Settings::default())
        );
        let mut s = Settings::default();
        let rest = s
            .apply_sets(&[
                "stage.rows=3".into(),
                "deviation.threshold_percent=1".into(),
            ])
            .unwrap();
        assert_eq!(
            (s.threshold_percent, rest),
            (1.0, vec!["stage.rows=3".to_string()])
        );
        // Bad values and unknown keys are clear errors naming the setting.
        for bad in [
            "deviation.threshold_percent=-1",
            "deviation.threshold_percent=x",
        ] {
            let e = Settings::default().apply_sets(&[bad.into()]).unwrap_err();
            assert!(e.to_string().contains("threshold_percent"), "{e}");
        }
        let e = Settings::default()
            .apply_sets(&["deviation.e=1".into()])
            .unwrap_err();
        assert!(e.to_string().contains("no 'e'"), "{e}");
        let e = split_graph_text(
            "[graph]\nname = \"g\"\n[deviation]\nthreshold = 1\n",
            "g.toml",
        )
        .unwrap_err();
        assert!(e.to_string().contains("[deviation]"), "{e}");
        let e = split_graph_text(
            "[graph]\nname = \"g\"\n[deviation]\nthreshold_percent = 0\n",
            "g.toml",
        )
        .unwrap_err();
        assert!(e.to_string().contains("g.toml"), "{e}");
    }

    #[test]
    fn unpool_spreads_cells() {
        let p = [1.0, 2.0, 3.0, 4.0];
        let u = unpool(&p, 2, 2, 3, 4).unwrap();
        assert_eq!(
            u,
            vec![1.0, 1.0, 2.0, 2.0, 1.0, 1.0, 2.0, 2.0, 3.0, 3.0, 4.0, 4.0]
        );
        assert!(unpool(&p, 2, 2, 3, 9).is_err()); // factor 5 from the columns, but 3 rows pool to 1
    }

    #[test]
    fn identical_model_passes_scaled_model_fails() {
        let (rows, cols) = (40, 60);
        let z: Vec<f64> = (0..rows * cols)
            .map(|i| ((i * 31 % 97) as f64).sin())
            .collect();
        let regions = tile_regions(
            &[
                json!({"x_um": 10.0, "y_um": 10.0}),
                json!({"x_um": 25.0, "y_um": 20.0}),
            ],
            &json!({"origin_x_um": 10.0, "origin_y_um": 10.0, "pitch_x_um": 0.5, "pitch_y_um": 0.5}),
            40,
            30,
            rows,
            cols,
        );
        assert_eq!(
            regions[1],
            Region {
                name: "S2".into(),
                row0: 20,
                col0: 30,
                rows: 20,
                cols: 30
            }
        );
        let m = Measured {
            heights_um: z.clone(),
            rows,
            cols,
            pitch_x_um: 0.5,
            pitch_y_um: 0.5,
            regions,
        };
        let same = compare_stage(&m, "same", &z, 5.0).unwrap();
        assert_eq!(same["pass"], json!(true));
        assert_eq!(same["regions"]["S1"]["deviation_pct"]["Sq"], json!(0.0));
        let scaled: Vec<f64> = z.iter().map(|v| v * 1.06).collect();
        let s = compare_stage(&m, "scaled", &scaled, 5.0).unwrap();
        assert_eq!(s["pass"], json!(false));
        let d = s["regions"]["S2"]["deviation_pct"]["Sa"].as_f64().unwrap();
        assert!((d - 6.0).abs() < 1e-9, "{d}");
        assert_eq!(
            compare_stage(&m, "scaled", &scaled, 7.0).unwrap()["pass"],
            json!(true)
        );
    }
}
