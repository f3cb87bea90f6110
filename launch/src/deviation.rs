//! The model-vs-measurement deviation of the reference study's Table 6, run once after the
//! nodes finish (runjson::write calls [`attach`]): reads the out dir's rasters by rows (a band
//! of rows of each at a time, [`NpyRows`]) into [`Table6::judge_streamed`], which computes the
//! table (conventions in surfstream_core::deviation) exactly as the in-memory
//! [`Table6::judge`] does, without holding any whole raster: the launcher's memory does not
//! grow with the scan (issue 17).
//!
//! Measured surface: the fused panorama (`panorama.npy`). Model stages, each judged on its own
//! grid: "mesh" (`mesh_resampled.npy`, the mesher's STL surface re-sampled on the grid it
//! meshed: the panorama's by default, so at every measured point), judged at the model's
//! tolerance when the mesher made it from one; "pooled" (`pooled.npy` at the pooled pitch),
//! judged only when the STL was made from it; and "roughness (mesh - datum)": the roughness the
//! simulator sees against the measured `roughness.npy` (it replaced "datum+roughness", which
//! is the panorama by construction and could not fail). Stages on the panorama grid also get
//! the pointwise residual RMS per region in percent of Sq, and every stage its worst region.
//! run.json says which grid (`grid`: rows x cols, cell size in panorama pixels, pitch).
//! Regions: S1..Sn = each tile's footprint in the panorama (from its final position), and
//! "panorama" = the whole map.
//!
//! The threshold defaults to [`DEFAULT_THRESHOLD_PCT`]; a graph file changes it with a
//! `[deviation]` table (`threshold_percent = 2`), the command line with
//! `--set deviation.threshold_percent=2` ([`Settings`]).
//!
//! Also writes `panorama.x3p` (the stitched panorama for MountainsMap, Gwyddion, surfalize),
//! streamed from panorama.npy by rows ([`x3p::write_by_rows`]: the same file as the in-memory
//! writer's, byte for byte where data.bin is stored; the same entries where it is deflated).

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};
use surfstream_core::deviation::{
    residual_pct_of_sq, tile_regions, Region, RowSource, StageVerdict, StreamedStage, Table6,
    JUDGED,
};
use surfstream_core::raster::Shape;
use surfstream_core::record::{
    DeviationRecord, FormPlane, FusionReport, JudgedPct, MeshReport, RegionDeviation, RegionRecord,
    RunRecord, StageDeviation, StageGrid, Table6Record,
};
use surfstream_core::Pitch;
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

/// The panorama's geometry (origin, pitch) as the fusion node reported it.
struct Geometry {
    origin_um: (f64, f64),
    pitch: Pitch,
}

fn geometry(run: &RunRecord) -> Result<Geometry> {
    let g = run
        .stage::<FusionReport>()
        .and_then(|f| f.panorama)
        .context("no node report carries the panorama geometry (origin, pitch)")?;
    Ok(Geometry {
        pitch: Pitch::new(g.pitch_x_um, g.pitch_y_um)
            .context("run.json: stages.<fusion>.panorama's pitch")?,
        // Without a finite origin there are no tile footprints, only the whole map.
        origin_um: (g.origin_x_um, g.origin_y_um),
    })
}

/// S1..Sn from run.json's tiles (final x_um / y_um) and scan (tile size), then the whole map.
fn regions(run: &RunRecord, geometry: &Geometry, panorama: Shape) -> Vec<Region> {
    let mut out = Vec::new();
    if let Some(scan) = &run.scan {
        let (tw, th) = scan.tile_px();
        let tile = Shape { rows: th, cols: tw };
        let tiles =
            (run.tiles.iter()).map(|t| t.placement.as_ref().map(|p| ((p.x_um, p.y_um), tile)));
        out = tile_regions(tiles, geometry.origin_um, geometry.pitch, panorama);
    }
    out.push(Region::whole(panorama));
    out
}

/// mesh_resampled - datum, row by row: the roughness the simulator sees (the model on the
/// panorama grid minus the datum the separation found).
struct DiffSource {
    a: PlaneSource<NpySource>,
    b: NpySource,
    scratch: Vec<f64>,
}

impl RowSource for DiffSource {
    fn shape(&self) -> Shape {
        self.a.shape()
    }
    fn read_rows(&mut self, row0: usize, rows: usize, out: &mut Vec<f64>) -> Result<(), String> {
        self.a.read_rows(row0, rows, out)?;
        self.b.read_rows(row0, rows, &mut self.scratch)?;
        out.iter_mut()
            .zip(&self.scratch)
            .for_each(|(a, b)| *a -= *b);
        Ok(())
    }
}

/// A raster with a plane's slopes taken off (`sign` -1) or put back (+1): it adds `sign` times
/// `bx` x col plus `by` x row (heights per pixel step). The mean does not matter: Table 6
/// removes each region's own.
struct PlaneSource<S> {
    inner: S,
    slopes_per_px: (f64, f64),
    sign: f64,
}

impl<S: RowSource> RowSource for PlaneSource<S> {
    fn shape(&self) -> Shape {
        self.inner.shape()
    }
    fn read_rows(&mut self, row0: usize, rows: usize, out: &mut Vec<f64>) -> Result<(), String> {
        self.inner.read_rows(row0, rows, out)?;
        let (bx, by) = self.slopes_per_px;
        if bx == 0.0 && by == 0.0 {
            return Ok(()); // a mesh of the heights as measured: nothing to add
        }
        let cols = self.inner.shape().cols.max(1);
        for (r, row) in out.chunks_mut(cols).enumerate() {
            let base = by * (row0 + r) as f64;
            for (i, z) in row.iter_mut().enumerate() {
                *z += self.sign * (base + bx * i as f64);
            }
        }
        Ok(())
    }
}

/// The least-squares plane's slopes (height per column, per row) over the valid points of a
/// raster read by bands of rows: the plane `params --level` and the mesher's `level` remove
/// (the same fit; summed here from centred moments, so equal to rounding).
fn plane_slopes_per_px(src: &mut dyn RowSource) -> Result<(f64, f64)> {
    let shape = src.shape();
    let (cx, cy) = (shape.cols as f64 / 2.0, shape.rows as f64 / 2.0);
    // n, sums of x, y, z, xx, xy, yy, xz, yz about the centre (x = col, y = row).
    let mut m = [0.0f64; 9];
    let mut band = Vec::new();
    const BAND_ROWS: usize = 256;
    for row0 in (0..shape.rows).step_by(BAND_ROWS) {
        let rows = BAND_ROWS.min(shape.rows - row0);
        src.read_rows(row0, rows, &mut band)
            .map_err(|e| anyhow::anyhow!("panorama.npy: {e}"))?;
        for (r, row) in band.chunks(shape.cols.max(1)).enumerate() {
            let y = (row0 + r) as f64 - cy;
            for (i, &z) in row.iter().enumerate() {
                if z.is_finite() {
                    let x = i as f64 - cx;
                    for (acc, v) in
                        m.iter_mut()
                            .zip([1.0, x, y, z, x * x, x * y, y * y, x * z, y * z])
                    {
                        *acc += v;
                    }
                }
            }
        }
    }
    let [n, sx, sy, sz, sxx, sxy, syy, sxz, syz] = m;
    anyhow::ensure!(
        n >= 3.0,
        "panorama.npy: fewer than 3 measured points, no plane to level by"
    );
    let (vxx, vxy, vyy) = (sxx - sx * sx / n, sxy - sx * sy / n, syy - sy * sy / n);
    let (vxz, vyz) = (sxz - sx * sz / n, syz - sy * sz / n);
    let det = vxx * vyy - vxy * vxy;
    anyhow::ensure!(
        det.abs() > 0.0,
        "panorama.npy: the measured points are on a line, no plane to level by"
    );
    Ok(((vxz * vyy - vyz * vxy) / det, (vyz * vxx - vxz * vxy) / det))
}

/// What the mesher reported in run.json: the surface it meshed and its tolerance (percent:
/// Sa, Sq, Sz), when it made the model from one.
struct MeshInfo {
    surface: Option<String>,
    tolerance: Option<[f64; 3]>,
    /// The mesher removed the least-squares plane first (`form_removed`): the STL and
    /// mesh_resampled.npy are of the levelled surface.
    levelled: bool,
    /// The plane it removed (`form_plane`; absent from reports before it was recorded: then
    /// Table 6 fits the panorama's own).
    form_plane: Option<FormPlane>,
    /// The plane the tolerance judged every region without (`tolerance.judged_plane`), the
    /// mesh being of the heights as measured: Table 6 judges the mesh stage without it too,
    /// the panorama and the mesh alike (issue 33: form before roughness).
    judged_plane: Option<FormPlane>,
}

fn mesh_info(run: &RunRecord) -> MeshInfo {
    let m = run.stage::<MeshReport>();
    let tolerance = (m.as_ref().and_then(|m| m.tolerance.as_ref()))
        .map(|t| [t.tolerance.sa_pct, t.tolerance.sq_pct, t.tolerance.sz_pct]);
    MeshInfo {
        levelled: m.as_ref().is_some_and(|m| m.form_removed.is_some()),
        form_plane: m.as_ref().and_then(|m| m.form_plane),
        judged_plane: (m.as_ref().and_then(|m| m.tolerance.as_ref())).and_then(|t| t.judged_plane),
        surface: m.map(|m| m.surface),
        tolerance,
    }
}

/// How a stage is judged: the file it is compared with, its limits (Sa, Sq, Sz, percent),
/// whether it counts in the verdict and why not.
struct StageRule {
    measured: &'static str,
    limits: [f64; 3],
    judged: bool,
    note: &'static str,
}

/// The mesh stage: the model the STL carries, on the panorama grid (at every measured point)
/// when the panorama was meshed.
const MESH_STAGE: &str = "mesh";
/// The roughness the simulator sees (mesh - datum) against the measured roughness.
const DEM_ROUGHNESS_STAGE: &str = "roughness (mesh - datum)";

/// The model stages the out dir holds that are judged against the panorama, each on its own
/// grid, read by rows: the pooled map and the mesher's surface re-sampled on the grid it meshed
/// (the panorama's, at every measured point; or the pooled map's).
fn model_stages(out: &Path, panorama: Shape) -> Result<Vec<StreamedStage<'static>>> {
    let mut stages = Vec::new();
    for (name, file) in [("pooled", "pooled.npy"), (MESH_STAGE, "mesh_resampled.npy")] {
        let path = out.join(file);
        if path.exists() {
            let source = NpySource::open(&path)?;
            stages.push(StreamedStage::pooled(name, Box::new(source), panorama));
        }
    }
    Ok(stages)
}

/// run.json's record of one stage's verdict; `pitch` is the measured (panorama) pitch,
/// `residuals` the pointwise residual per region (percent of Sq; stages on the measured grid).
/// Also whether it leaves the table passing (a stage not judged does not count).
fn stage_record(
    s: &StageVerdict,
    pitch: Pitch,
    rule: &StageRule,
    residuals: &[Option<f64>],
) -> (StageDeviation, bool) {
    let mut worst: Option<(String, f64)> = None;
    let mut stage_pass = true;
    let regions: BTreeMap<String, RegionDeviation> = s
        .regions
        .iter()
        .enumerate()
        .map(|(k, r)| {
            let deviation_pct = (r.deviation_pct.iter())
                .map(|(name, d)| (name.to_string(), *d))
                .collect();
            // Judged at the stage's limits (Sa, Sq, Sz).
            let mut ratio = 0.0f64;
            let mut pass = r.measured.is_some() && r.model.is_some();
            for (name, limit) in JUDGED.iter().zip(rule.limits) {
                let d = r
                    .deviation_pct
                    .iter()
                    .find(|(n, _)| n == name)
                    .and_then(|(_, d)| *d);
                match d {
                    Some(d) => {
                        ratio = ratio.max(d.abs() / limit);
                        pass &= d.abs() <= limit;
                    }
                    None => pass = false,
                }
            }
            if worst.as_ref().is_none_or(|w| ratio > w.1) {
                worst = Some((r.region.clone(), ratio));
            }
            stage_pass &= pass;
            let region = RegionDeviation {
                measured: r.measured,
                model: r.model,
                deviation_pct,
                residual_rms_pct_of_sq: residuals.get(k).copied().flatten(),
                pass,
            };
            (r.region.clone(), region)
        })
        .collect();
    let grid = StageGrid {
        rows: s.grid.rows,
        cols: s.grid.cols,
        cell_px: s.cell_px,
        pitch_x_um: pitch.x_um() * s.cell_px as f64,
        pitch_y_um: pitch.y_um() * s.cell_px as f64,
        name: if s.cell_px == 1 {
            "panorama grid".to_string()
        } else {
            format!("own grid, {0} x {0} px cells", s.cell_px)
        },
    };
    let worst_residual = residuals
        .iter()
        .flatten()
        .copied()
        .fold(None, |a: Option<f64>, r| Some(a.map_or(r, |a| a.max(r))));
    let [sa, sq, sz] = rule.limits;
    (
        StageDeviation {
            regions,
            pass: stage_pass,
            judged: rule.judged,
            note: rule.note.into(),
            measured: rule.measured.into(),
            limits_pct: JudgedPct { sa, sq, sz },
            worst_region: worst.map(|w| w.0),
            worst_residual_rms_pct_of_sq: worst_residual,
            grid,
        },
        stage_pass || !rule.judged,
    )
}

/// Writes the panorama as X3P, read from panorama.npy a band of rows at a time (the map is
/// never held whole; [`x3p::write_by_rows`]).
fn write_x3p(out: &Path, pano: &mut NpySource, geometry: &Geometry) -> Result<()> {
    let shape = pano.shape();
    let surface = Surface {
        width: shape.cols,
        height: shape.rows,
        pitch_x_um: geometry.pitch.x_um(),
        pitch_y_um: geometry.pitch.y_um(),
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
    run: &RunRecord,
    threshold_pct: f64,
    pano: &mut NpySource,
    geometry: &Geometry,
) -> Result<Table6Record> {
    let regions = regions(run, geometry, pano.shape());
    let info = mesh_info(run);
    judge_out_dir(out, &regions, &info, threshold_pct, pano, geometry)
}

/// Table 6 of the out dir's rasters in `regions`, the mesh judged as `info` says it was made.
fn judge_out_dir(
    out: &Path,
    regions: &[Region],
    info: &MeshInfo,
    threshold_pct: f64,
    pano: &mut NpySource,
    geometry: &Geometry,
) -> Result<Table6Record> {
    let shape = pano.shape();
    // A levelled mesh (the mesher's `level`) is judged against the levelled panorama: the
    // tolerance was met on the roughness, not on the tilt (issue 33). The other stages keep
    // the panorama as measured.
    let pano_path = out.join("panorama.npy");
    // The plane the mesher removed, per panorama pixel, so that the mesh and the panorama
    // are levelled by one plane; a report without it: the panorama's own fit.
    let per_px = |p: FormPlane| {
        (
            p.slope_x_um_per_um * geometry.pitch.x_um(),
            p.slope_y_um_per_um * geometry.pitch.y_um(),
        )
    };
    let slopes = match (info.levelled, info.form_plane, info.judged_plane) {
        (false, _, None) => None,
        (false, _, Some(p)) | (true, Some(p), _) => Some(per_px(p)),
        (true, None, _) => Some(plane_slopes_per_px(&mut NpySource::open(&pano_path)?)?),
    };
    // A mesh of the heights as measured judged without the tolerance's plane carries the
    // plane: it is levelled like the panorama (a levelled mesh has none to remove, and gets
    // it back for the roughness stage below).
    let mesh_carries_plane = !info.levelled && slopes.is_some();
    let mesh_judged = |a: NpySource| PlaneSource {
        inner: a,
        slopes_per_px: if mesh_carries_plane {
            slopes.unwrap_or((0.0, 0.0))
        } else {
            (0.0, 0.0)
        },
        sign: -1.0,
    };
    let levelled_pano = || -> Result<PlaneSource<NpySource>> {
        Ok(PlaneSource {
            inner: NpySource::open(&pano_path)?,
            slopes_per_px: slopes.unwrap_or((0.0, 0.0)),
            sign: -1.0,
        })
    };
    let (mut levelled_mesh, mut stages): (Vec<_>, Vec<_>) = model_stages(out, shape)?
        .into_iter()
        .partition(|s| slopes.is_some() && s.name == MESH_STAGE);
    if mesh_carries_plane && !levelled_mesh.is_empty() {
        levelled_mesh = vec![StreamedStage::pooled(
            MESH_STAGE,
            Box::new(mesh_judged(NpySource::open(
                &out.join("mesh_resampled.npy"),
            )?)),
            shape,
        )];
    }
    let mut table =
        Table6::judge_streamed(pano, geometry.pitch, &mut stages, regions, threshold_pct)?;
    if !levelled_mesh.is_empty() {
        let t = Table6::judge_streamed(
            &mut levelled_pano()?,
            geometry.pitch,
            &mut levelled_mesh,
            regions,
            threshold_pct,
        )?;
        table.stages.extend(t.stages);
    }
    // The mesh is judged at the model's tolerance when it was made from one.
    let model_limits = info.tolerance.unwrap_or([threshold_pct; 3]);
    let meshed_pooled = info.surface.as_deref() == Some("pooled");
    let mesh_path = out.join("mesh_resampled.npy");
    let mut out_stages = BTreeMap::new();
    let mut pass = true;
    for s in &table.stages {
        let rule = match s.stage.as_str() {
            MESH_STAGE => StageRule {
                measured: if mesh_carries_plane {
                    "panorama.npy less the tolerance's least-squares plane (the mesh too)"
                } else if slopes.is_some() {
                    "panorama.npy less its least-squares plane"
                } else {
                    "panorama.npy"
                },
                limits: model_limits,
                judged: true,
                note: "the STL's surface interpolated on the grid it meshed",
            },
            _ => StageRule {
                measured: "panorama.npy",
                limits: [threshold_pct; 3],
                judged: meshed_pooled,
                note: if meshed_pooled {
                    "the pooled map the STL was made from"
                } else {
                    "reported, not judged: the STL was not made from the pooled map"
                },
            },
        };
        let residuals = if s.cell_px == 1 && s.stage == MESH_STAGE {
            let mut m = mesh_judged(NpySource::open(&mesh_path)?);
            if slopes.is_some() {
                residual_pct_of_sq(&mut levelled_pano()?, &mut m, regions)?
            } else {
                residual_pct_of_sq(pano, &mut m, regions)?
            }
        } else {
            Vec::new()
        };
        let (v, ok) = stage_record(s, geometry.pitch, &rule, &residuals);
        pass &= ok;
        out_stages.insert(s.stage.clone(), v);
    }
    // The roughness the simulator sees: mesh - datum against the measured roughness, on the
    // panorama grid. Unlike datum + roughness (the panorama by construction) it can fail.
    // A levelled mesh gets the plane back first: datum and roughness are of the panorama as
    // measured.
    let mesh_as_measured = |a: NpySource| PlaneSource {
        inner: a,
        slopes_per_px: if mesh_carries_plane {
            (0.0, 0.0)
        } else {
            slopes.unwrap_or((0.0, 0.0))
        },
        sign: 1.0,
    };
    let (datum, rough) = (out.join("datum.npy"), out.join("roughness.npy"));
    if datum.exists() && rough.exists() && mesh_path.exists() {
        let mut measured = NpySource::open(&rough)?;
        let a = NpySource::open(&mesh_path)?;
        if a.shape() == shape && measured.shape() == shape {
            let diff = DiffSource {
                a: mesh_as_measured(a),
                b: NpySource::open(&datum)?,
                scratch: Vec::new(),
            };
            let mut st = vec![StreamedStage::on_measured_grid(
                DEM_ROUGHNESS_STAGE,
                Box::new(diff),
            )];
            let t = Table6::judge_streamed(
                &mut measured,
                geometry.pitch,
                &mut st,
                regions,
                threshold_pct,
            )?;
            let mut model = DiffSource {
                a: mesh_as_measured(NpySource::open(&mesh_path)?),
                b: NpySource::open(&datum)?,
                scratch: Vec::new(),
            };
            let residuals = residual_pct_of_sq(&mut measured, &mut model, regions)?;
            let rule = StageRule {
                measured: "roughness.npy",
                limits: [threshold_pct; 3],
                judged: true,
                note: "the roughness the simulator sees: mesh minus datum against the measured roughness",
            };
            for s in &t.stages {
                let (v, ok) = stage_record(s, geometry.pitch, &rule, &residuals);
                pass &= ok;
                out_stages.insert(s.stage.clone(), v);
            }
        }
    }
    Ok(Table6Record {
        measured: "panorama.npy".into(),
        threshold_pct,
        model_tolerance_pct: info.tolerance.map(|[sa, sq, sz]| JudgedPct { sa, sq, sz }),
        judged: JUDGED.iter().map(|j| j.to_string()).collect(),
        conventions: CONVENTIONS.into(),
        regions: (regions.iter())
            .map(|r| RegionRecord {
                name: r.name.clone(),
                row0: r.row0,
                col0: r.col0,
                rows: r.rows,
                cols: r.cols,
            })
            .collect(),
        stages: out_stages,
        pass,
    })
}

/// How Table 6 is computed, as run.json states it.
const CONVENTIONS: &str = "ISO 25178 over points valid in both maps, mean removed, no levelling (but the mesh stage: a mesh made levelled, the mesher's form_removed, is compared with the panorama less the same least-squares plane, and gets the plane back for the roughness stage; a mesh whose tolerance was judged without the panorama's least-squares plane, tolerance.judged_plane, is compared with the panorama less that plane, the mesh less it too); each stage on its own grid at its own pitch (grid); deviation = (model - measured) / measured * 100; the mesh passes when |deviation| <= the model's tolerance (else the threshold) for Sa, Sq, Sz, the other stages at the threshold; residual_rms_pct_of_sq = RMS of the pointwise difference (means removed) / measured Sq * 100; a stage with judged = false is reported, not counted";

/// Adds "deviation" (Table 6) to run.json and, when `with_x3p` (the full output set), writes
/// panorama.x3p when the out dir holds a panorama. An output that cannot be written
/// (panorama.x3p on a full disk) fails the run; a Table 6 that cannot be computed is recorded
/// in run.json (and on stderr).
pub fn attach(
    out: &Path,
    run: &mut RunRecord,
    threshold_percent: f64,
    with_x3p: bool,
) -> Result<()> {
    if !out.join("panorama.npy").exists() {
        return Ok(());
    }
    let inputs = NpySource::open(&out.join("panorama.npy")).and_then(|p| Ok((p, geometry(run)?)));
    let entry = match inputs {
        Ok((mut pano, geometry)) => {
            if with_x3p {
                write_x3p(out, &mut pano, &geometry)?;
                run.files.push("panorama.x3p".into());
                run.files.sort();
                run.files.dedup();
            }
            evaluate(out, run, threshold_percent, &mut pano, &geometry)
                .map(|t| DeviationRecord::Table(Box::new(t)))
        }
        Err(e) => Err(e),
    };
    let entry = entry.unwrap_or_else(|e| {
        eprintln!("surfstream: model-vs-measurement deviation not computed: {e:#}");
        DeviationRecord::NotComputed {
            error: format!("{e:#}"),
        }
    });
    run.deviation = Some(entry);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The tilted panoramas of the levelling tests: a plane of 0.05 and -0.03 um per pixel (4
    /// and 1.8 um over the map) under a roughness of about 0.2 um.
    const TILTED_ROWS: usize = 60;
    const TILTED_COLS: usize = 80;
    const TILT_PER_PX: (f64, f64) = (0.05, -0.03);

    fn tilted_roughness(r: usize, c: usize) -> f64 {
        let (y, x) = (r as f64, c as f64);
        0.3 * (x * 0.7).sin() * (y * 0.9).cos() + 0.15 * (x * 0.23 + y * 0.31).sin()
    }

    fn tilt_at(r: usize, c: usize) -> f64 {
        TILT_PER_PX.0 * c as f64 + TILT_PER_PX.1 * r as f64
    }

    /// `f` at every pixel of the tilted tests' grid, row-major.
    fn on_tilted_grid(f: &dyn Fn(usize, usize) -> f64) -> Vec<f64> {
        (0..TILTED_ROWS * TILTED_COLS)
            .map(|k| f(k / TILTED_COLS, k % TILTED_COLS))
            .collect()
    }

    /// A mesh the mesher made levelled (its `level`: the least-squares plane removed) is
    /// judged against the panorama less that plane, and its roughness stage gets the plane
    /// back: a perfect levelled model passes every stage. Judged as a mesh of the raw heights
    /// (the rule before), the same files fail by the tilt.
    #[test]
    fn a_levelled_mesh_is_judged_on_the_levelled_panorama() {
        let dir = tempfile::tempdir().unwrap();
        let (rows, cols) = (TILTED_ROWS, TILTED_COLS);
        let (bx, by) = TILT_PER_PX;
        let (rough, tilt, at) = (tilted_roughness, tilt_at, on_tilted_grid);
        let pano = at(&|r, c| tilt(r, c) + rough(r, c) + 7.0);
        // The mesher's levelled surface: the panorama less its own least-squares plane (the
        // roughness is not exactly orthogonal to a plane, so take the fitted one).
        let write = |name: &str, v: &[f64]| {
            surfstream_io::npy::write_npy_f64(dir.path().join(name), v, rows, cols).unwrap()
        };
        write("panorama.npy", &pano);
        let (fx, fy) =
            plane_slopes_per_px(&mut NpySource::open(&dir.path().join("panorama.npy")).unwrap())
                .unwrap();
        assert!(
            (fx - bx).abs() < 2e-3 && (fy - by).abs() < 2e-3,
            "{fx} {fy}"
        );
        let mesh = at(&|r, c| pano[r * cols + c] - fx * c as f64 - fy * r as f64 + 0.9);
        write("mesh_resampled.npy", &mesh);
        let datum = at(&|r, c| tilt(r, c) + 7.0);
        write("datum.npy", &datum);
        write(
            "roughness.npy",
            &at(&|r, c| pano[r * cols + c] - datum[r * cols + c]),
        );
        let geometry = Geometry {
            origin_um: (0.0, 0.0),
            pitch: Pitch::new(1.0, 1.0).unwrap(),
        };
        let regions = [Region::whole(Shape { rows, cols })];
        let judge_with = |levelled: bool, form_plane: Option<FormPlane>| {
            let info = MeshInfo {
                surface: Some("panorama".into()),
                tolerance: Some([1.0, 1.0, 3.0]),
                levelled,
                form_plane,
                judged_plane: None,
            };
            let mut pano = NpySource::open(&dir.path().join("panorama.npy")).unwrap();
            judge_out_dir(dir.path(), &regions, &info, 5.0, &mut pano, &geometry).unwrap()
        };
        let judge = |levelled: bool| judge_with(levelled, None);
        let t = judge(true);
        let mesh = &t.stages[MESH_STAGE];
        assert_eq!(mesh.measured, "panorama.npy less its least-squares plane");
        assert!(t.pass, "{:?}", t.stages);
        for stage in [MESH_STAGE, DEM_ROUGHNESS_STAGE] {
            let s = &t.stages[stage];
            let region = &s.regions["panorama"];
            assert!(region.pass, "{stage}: {region:?}");
            for name in JUDGED {
                let d = region.deviation_pct[name];
                assert!(d.is_some_and(|d| d.abs() < 1e-6), "{stage} {name}: {d:?}");
            }
            let residual = region.residual_rms_pct_of_sq.unwrap();
            assert!(residual < 1e-6, "{stage}: residual {residual} % of Sq");
        }
        // The same mesh taken for one of the raw heights fails by the tilt.
        let raw = judge(false);
        assert!(!raw.stages[MESH_STAGE].regions["panorama"].pass);
        assert!(!raw.pass);
        // The plane the mesher recorded is the one Table 6 levels by: the fitted plane gives
        // the same table, a plane of half the tilt fails it.
        let plane = |f: f64| FormPlane {
            z_um: 0.0,
            slope_x_um_per_um: f * fx,
            slope_y_um_per_um: f * fy,
        };
        let recorded = judge_with(true, Some(plane(1.0)));
        assert!(recorded.pass, "{:?}", recorded.stages);
        assert_eq!(recorded.stages[MESH_STAGE], t.stages[MESH_STAGE]);
        let wrong = judge_with(true, Some(plane(0.5)));
        assert!(!wrong.stages[MESH_STAGE].regions["panorama"].pass);
    }

    /// A mesh of the heights as measured (tilt kept in the STL) whose tolerance was judged
    /// without the panorama's plane (`tolerance.judged_plane`): Table 6 levels the panorama
    /// and the mesh by that plane, so a mesh that loses a tenth of the roughness fails
    /// where, about the mean alone, the tilt hides it; the roughness stage takes the mesh as
    /// it is (no plane to give back).
    #[test]
    fn a_mesh_judged_without_the_plane_is_levelled_with_the_panorama() {
        let (rows, cols) = (TILTED_ROWS, TILTED_COLS);
        let (rough, tilt, at) = (tilted_roughness, tilt_at, on_tilted_grid);
        let geometry = Geometry {
            origin_um: (0.0, 0.0),
            pitch: Pitch::new(1.0, 1.0).unwrap(),
        };
        let regions = [Region::whole(Shape { rows, cols })];
        let judge = |roughness_kept: f64, judged_plane: bool| {
            let dir = tempfile::tempdir().unwrap();
            let write = |name: &str, v: &[f64]| {
                surfstream_io::npy::write_npy_f64(dir.path().join(name), v, rows, cols).unwrap()
            };
            write("panorama.npy", &at(&|r, c| tilt(r, c) + rough(r, c) + 7.0));
            let (fx, fy) = plane_slopes_per_px(
                &mut NpySource::open(&dir.path().join("panorama.npy")).unwrap(),
            )
            .unwrap();
            write(
                "mesh_resampled.npy",
                &at(&|r, c| tilt(r, c) + roughness_kept * rough(r, c) + 7.9),
            );
            write("datum.npy", &at(&|r, c| tilt(r, c) + 7.0));
            write("roughness.npy", &at(&rough));
            let info = MeshInfo {
                surface: Some("panorama".into()),
                tolerance: Some([1.0, 1.0, 3.0]),
                levelled: false,
                form_plane: None,
                judged_plane: judged_plane.then_some(FormPlane {
                    z_um: 7.0,
                    slope_x_um_per_um: fx,
                    slope_y_um_per_um: fy,
                }),
            };
            let mut pano = NpySource::open(&dir.path().join("panorama.npy")).unwrap();
            judge_out_dir(dir.path(), &regions, &info, 5.0, &mut pano, &geometry).unwrap()
        };
        let same = judge(1.0, true);
        assert_eq!(
            same.stages[MESH_STAGE].measured,
            "panorama.npy less the tolerance's least-squares plane (the mesh too)"
        );
        assert!(same.pass, "{:?}", same.stages);
        for stage in [MESH_STAGE, DEM_ROUGHNESS_STAGE] {
            let region = &same.stages[stage].regions["panorama"];
            for name in JUDGED {
                let d = region.deviation_pct[name];
                assert!(d.is_some_and(|d| d.abs() < 1e-6), "{stage} {name}: {d:?}");
            }
        }
        // A tenth of the roughness lost: about the mean the tilt hides it, without the plane
        // it fails (Sa and Sq about -10 %).
        let about_mean = judge(0.9, false);
        assert!(about_mean.stages[MESH_STAGE].regions["panorama"].pass);
        let levelled = judge(0.9, true);
        let region = &levelled.stages[MESH_STAGE].regions["panorama"];
        assert!(!region.pass, "{region:?}");
        let sq = region.deviation_pct["Sq"].unwrap();
        assert!((sq + 10.0).abs() < 1.0, "Sq {sq} %");
    }

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
