//! The model-vs-measurement deviation of the reference study's Table 6, run once after the
//! nodes finish (runjson::write calls [`attach`]): reads the out dir's rasters by rows (a band
//! of rows of each at a time, [`NpyRows`]) into [`Table6::judge_streamed`], which computes the
//! table (conventions in surfstream_core::deviation) exactly as the in-memory
//! [`Table6::judge`] does, without holding any whole raster: the launcher's memory does not
//! grow with the scan (issue 17).
//!
//! Measured surface: the fused panorama (`panorama.npy`). Model stages, each judged on its own
//! grid: "datum+roughness" (`datum.npy` + `roughness.npy`, the panorama grid), "pooled"
//! (`pooled.npy` at the pooled pitch) and "mesh" (`mesh_resampled.npy`, the mesher's STL
//! surface re-sampled on the grid it meshed, at that grid's pitch). run.json says which grid
//! (`grid`: rows x cols, cell size in panorama pixels, pitch). Regions: S1..Sn = each tile's
//! footprint in the panorama (from its final position), and "panorama" = the whole map.
//!
//! The threshold defaults to [`DEFAULT_THRESHOLD_PCT`]; a graph file changes it with a
//! `[deviation]` table (`threshold_percent = 2`), the command line with
//! `--set deviation.threshold_percent=2` ([`Settings`]).
//!
//! Also writes `panorama.x3p` (the stitched panorama for MountainsMap, Gwyddion, surfalize),
//! streamed from panorama.npy by rows ([`x3p::write_by_rows`]: the same file as the in-memory
//! writer's, byte for byte where data.bin is stored; the same entries where it is deflated).

use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};
use serde_json::{json, Map, Value};
use surfstream_core::deviation::{Region, RowSource, StageVerdict, StreamedStage, Table6, JUDGED};
use surfstream_core::metrology::Params;
use surfstream_core::raster::Shape;
use surfstream_io::formats::{x3p, Metadata, Surface};
use surfstream_io::npy::NpyRows;
use surfstream_runtime::graph::GraphFile;

/// Threshold e of Table 6, in percent.
pub const DEFAULT_THRESHOLD_PCT: f64 = 5.0;

/// Settings of the Table-6 evaluation: a `[deviation]` table in the graph file, or
/// `--set deviation.threshold_percent=VALUE` (which wins). The graph parser keeps the table
/// as it is ([`GraphFile::deviation`]); [`Settings::from_graph`] reads it.
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

impl Settings {
    /// The settings of a parsed graph's `[deviation]` table (the defaults without one).
    pub fn from_graph(graph: &GraphFile, origin: &str) -> Result<Self> {
        let Some(table) = &graph.deviation else {
            return Ok(Self::default());
        };
        let settings: Settings = toml::Value::Table(table.clone())
            .try_into()
            .map_err(|e| anyhow!("{origin}: [deviation]: {e}"))?;
        settings.check(origin)
    }
}

/// An npy file of the out dir read by rows.
struct NpySource(NpyRows);

impl NpySource {
    fn open(path: &Path) -> Result<Self> {
        Ok(Self(NpyRows::open(path)?))
    }
}

impl RowSource for NpySource {
    fn shape(&self) -> Shape {
        Shape {
            rows: self.0.rows(),
            cols: self.0.cols(),
        }
    }
    fn read_rows(&mut self, row0: usize, rows: usize, out: &mut Vec<f64>) -> Result<(), String> {
        self.0
            .read_rows_f64(row0, rows, out)
            .map_err(|e| format!("{e:#}"))
    }
}

/// datum + roughness, row by row (the model on the panorama grid).
struct SumSource {
    a: NpySource,
    b: NpySource,
    scratch: Vec<f64>,
}

impl RowSource for SumSource {
    fn shape(&self) -> Shape {
        self.a.shape()
    }
    fn read_rows(&mut self, row0: usize, rows: usize, out: &mut Vec<f64>) -> Result<(), String> {
        self.a.read_rows(row0, rows, out)?;
        self.b.read_rows(row0, rows, &mut self.scratch)?;
        out.iter_mut()
            .zip(&self.scratch)
            .for_each(|(a, b)| *a += *b);
        Ok(())
    }
}

/// The panorama's geometry (origin, pitch) as the fusion node reported it.
struct Geometry {
    origin_um: (f64, f64),
    pitch_um: (f64, f64),
}

fn geometry(run: &Value) -> Result<Geometry> {
    let g = run["stages"]
        .as_object()
        .and_then(|s| {
            s.values()
                .find_map(|r| r.get("panorama").filter(|p| p.get("origin_x_um").is_some()))
        })
        .context("no node report carries the panorama geometry (origin, pitch)")?;
    let f = |k: &str| g[k].as_f64().with_context(|| format!("panorama {k}"));
    Ok(Geometry {
        pitch_um: (f("pitch_x_um")?, f("pitch_y_um")?),
        // Without an origin there are no tile footprints, only the whole map.
        origin_um: (
            g["origin_x_um"].as_f64().unwrap_or(f64::NAN),
            g["origin_y_um"].as_f64().unwrap_or(f64::NAN),
        ),
    })
}

/// S1..Sn from run.json's tiles (final x_um / y_um) and scan (tile size), then the whole map.
fn regions(run: &Value, geometry: &Geometry, panorama: Shape) -> Vec<Region> {
    let mut out = Vec::new();
    if let (Some(tiles), Some(tw), Some(th)) = (
        run["tiles"].as_array(),
        run["scan"]["tile_width_px"].as_u64(),
        run["scan"]["tile_height_px"].as_u64(),
    ) {
        let tile = Shape {
            rows: th as usize,
            cols: tw as usize,
        };
        let origin_known = geometry.origin_um.0.is_finite() && geometry.origin_um.1.is_finite();
        for (k, t) in tiles.iter().enumerate().filter(|_| origin_known) {
            let (Some(x), Some(y)) = (t["x_um"].as_f64(), t["y_um"].as_f64()) else {
                continue;
            };
            out.extend(Region::tile_footprint(
                format!("S{}", k + 1),
                (x, y),
                geometry.origin_um,
                geometry.pitch_um,
                tile,
                panorama,
            ));
        }
    }
    out.push(Region::whole(panorama));
    out
}

/// The model stages the out dir holds, each on its own grid, read by rows.
fn model_stages(out: &Path, panorama: Shape) -> Result<Vec<StreamedStage<'static>>> {
    let mut stages = Vec::new();
    let datum = out.join("datum.npy");
    let rough = out.join("roughness.npy");
    if datum.exists() && rough.exists() {
        let d = NpySource::open(&datum)?;
        let r = NpySource::open(&rough)?;
        if d.shape() != panorama || r.shape() != panorama {
            bail!(
                "datum {} / roughness {} differ from the panorama {panorama}",
                d.shape(),
                r.shape()
            );
        }
        let sum = SumSource {
            a: d,
            b: r,
            scratch: Vec::new(),
        };
        stages.push(StreamedStage::on_measured_grid(
            "datum+roughness",
            Box::new(sum),
        ));
    }
    // The pooled map, and the mesher's surface re-sampled on its grid (the pooled map's, the
    // panorama's...): the model one and two stages further, each at its own pitch.
    for (name, file) in [("pooled", "pooled.npy"), ("mesh", "mesh_resampled.npy")] {
        let path = out.join(file);
        if path.exists() {
            let source = NpySource::open(&path)?;
            stages.push(StreamedStage::pooled(name, Box::new(source), panorama));
        }
    }
    Ok(stages)
}

fn params_json(p: &Option<Params>) -> Value {
    match p {
        Some(p) => serde_json::to_value(p).unwrap_or(Value::Null),
        None => Value::Null,
    }
}

/// run.json's layout of one stage's verdict; `pitch_um` is the measured (panorama) pitch.
fn stage_json(s: &StageVerdict, pitch_um: (f64, f64)) -> Value {
    let regions: Map<String, Value> = s
        .regions
        .iter()
        .map(|r| {
            let deviation: Map<String, Value> = r
                .deviation_pct
                .iter()
                .map(|(name, d)| (name.to_string(), d.map_or(Value::Null, |d| json!(d))))
                .collect();
            (
                r.region.clone(),
                json!({
                    "measured": params_json(&r.measured),
                    "model": params_json(&r.model),
                    "deviation_pct": deviation,
                    "pass": r.pass,
                }),
            )
        })
        .collect();
    let grid = json!({
        "rows": s.grid.rows,
        "cols": s.grid.cols,
        "cell_px": s.cell_px,
        "pitch_x_um": pitch_um.0 * s.cell_px as f64,
        "pitch_y_um": pitch_um.1 * s.cell_px as f64,
        "name": if s.cell_px == 1 {
            "panorama grid".to_string()
        } else {
            format!("own grid, {0} x {0} px cells", s.cell_px)
        },
    });
    json!({ "regions": regions, "pass": s.pass, "grid": grid })
}

/// Writes the panorama as X3P, read from panorama.npy a band of rows at a time (the map is
/// never held whole; [`x3p::write_by_rows`]).
fn write_x3p(out: &Path, pano: &mut NpySource, geometry: &Geometry) -> Result<()> {
    let shape = pano.shape();
    let surface = Surface {
        width: shape.cols,
        height: shape.rows,
        pitch_x_um: geometry.pitch_um.0,
        pitch_y_um: geometry.pitch_um.1,
        heights_um: Vec::new(),
        metadata: Metadata {
            format: "npy".into(),
            pitch_known: true,
            ..Metadata::default()
        },
    };
    x3p::write_by_rows(&out.join("panorama.x3p"), &surface, |row0, rows, buf| {
        pano.0.read_rows_f64(row0, rows, buf)
    })
}

/// Computes Table 6 from the out dir's rasters, read by rows.
fn evaluate(
    out: &Path,
    run: &Value,
    threshold_pct: f64,
    pano: &mut NpySource,
    geometry: &Geometry,
) -> Result<Value> {
    let shape = pano.shape();
    let regions = regions(run, geometry, shape);
    let mut stages = model_stages(out, shape)?;
    let table = Table6::judge_streamed(
        pano,
        geometry.pitch_um,
        &mut stages,
        &regions,
        threshold_pct,
    )?;
    let stages: Map<String, Value> = table
        .stages
        .iter()
        .map(|s| (s.stage.clone(), stage_json(s, geometry.pitch_um)))
        .collect();
    Ok(json!({
            "measured": "panorama.npy",
            "threshold_pct": threshold_pct,
            "judged": JUDGED,
            "conventions": "ISO 25178 over points valid in both maps, mean removed, no levelling; each stage on its own grid at its own pitch (grid); deviation = (model - measured) / measured * 100; pass = |deviation| <= threshold for Sa, Sq, Sz",
            "regions": regions.iter().map(|r| json!({"name": r.name, "row0": r.row0, "col0": r.col0, "rows": r.rows, "cols": r.cols})).collect::<Vec<_>>(),
            "stages": stages,
            "pass": table.pass,
    }))
}

/// Adds "deviation" (Table 6) to run.json and writes panorama.x3p when the out dir holds a
/// panorama. An output that cannot be written (panorama.x3p on a full disk) fails the run;
/// a Table 6 that cannot be computed is recorded in run.json (and on stderr).
pub fn attach(out: &Path, mut run: Value, threshold_percent: f64) -> Result<Value> {
    if !out.join("panorama.npy").exists() {
        return Ok(run);
    }
    let inputs = NpySource::open(&out.join("panorama.npy")).and_then(|p| Ok((p, geometry(&run)?)));
    let entry = match inputs {
        Ok((mut pano, geometry)) => {
            write_x3p(out, &mut pano, &geometry)?;
            if let Some(files) = run["files"].as_array_mut() {
                files.push(json!("panorama.x3p"));
                files.sort_by(|a, b| a.as_str().cmp(&b.as_str()));
                files.dedup();
            }
            evaluate(out, &run, threshold_percent, &mut pano, &geometry)
        }
        Err(e) => Err(e),
    };
    let entry = entry.unwrap_or_else(|e| {
        eprintln!("surfstream: model-vs-measurement deviation not computed: {e:#}");
        json!({ "error": format!("{e:#}") })
    });
    if let Some(o) = run.as_object_mut() {
        o.insert("deviation".into(), entry);
    }
    Ok(run)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn settings_from_graph_text_and_set() {
        let parse = |text: &str| {
            GraphFile::parse(text, "g.toml", &crate::nodes::registry())
                .and_then(|g| Settings::from_graph(&g, "g.toml"))
        };
        let text = "[graph]\nname = \"g\"\n\n[deviation]\nthreshold_percent = 2.5\n\n[[node]]\nid = \"a\"\nnode = \"replay\"\n";
        assert_eq!(parse(text).unwrap().threshold_percent, 2.5);
        // No table: the default applies.
        let plain = "[graph]\nname = \"g\"\n[[node]]\nid = \"a\"\nnode = \"replay\"\n";
        assert_eq!(parse(plain).unwrap(), Settings::default());
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
        let e = parse(&format!("{plain}[deviation]\nthreshold = 1\n")).unwrap_err();
        assert!(e.to_string().contains("[deviation]"), "{e}");
        let e = parse(&format!("{plain}[deviation]\nthreshold_percent = 0\n")).unwrap_err();
        assert!(e.to_string().contains("g.toml"), "{e}");
    }
}
