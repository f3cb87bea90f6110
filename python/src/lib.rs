//! `surfstream._native`: the Python module's compiled half. Every function is a thin shell
//! over the crates the CLI uses (surfstream_io's readers and writers, surfstream_core's
//! metrology and filters, surfstream_wavelet, surfstream_mesher): no algorithm lives here.
//! The Python half (pysrc/surfstream) holds the `Surface` class, the exceptions and the
//! calls of the CLI binary for graphs and stitching.
//!
//! Arrays: height maps arrive as C-contiguous float64 numpy arrays borrowed read-only (no
//! copy; the Python side makes a contiguous float64 copy only when the caller's array is not
//! one) and results leave as numpy arrays that own the Rust `Vec` they were computed into (no
//! copy). The GIL is released (`Python::detach`) for every computation and file access.

use std::path::PathBuf;

use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray2, PyReadonlyArray2};
use pyo3::prelude::*;
use pyo3::types::PyBytes;

use surfstream_core::filter::{self, RobustSettings};
use surfstream_core::frame::{from_frame_heights, to_frame_heights};
use surfstream_core::metrology::{self, ArealPsd, Grid};
use surfstream_core::{Sampling, Shape};
use surfstream_io::formats::{read_surface, write_surface, Metadata, Surface};
use surfstream_io::preview::{encode_map_png, robust_range_um};
use surfstream_wavelet::{
    separate_map, BaseChoice, LevelChoice, MapSummary, Mode, PoolOp, SeparationMethod,
    SeparationSettings, SeparationSink, StreamOptions,
};

/// Which `surfstream` exception (pysrc/surfstream/_errors.py) an error becomes.
#[derive(Clone, Copy)]
enum Kind {
    /// `surfstream.Error`: anything else (a computation that cannot be done on these data).
    Other,
    /// `surfstream.PathError` (also a `FileNotFoundError`): the path does not exist.
    Path,
    /// `surfstream.FormatError`: an unsupported extension or a file its reader refuses.
    Format,
    /// `surfstream.ParameterError` (also a `ValueError`): an argument out of range.
    Parameter,
}

impl Kind {
    fn class_name(self) -> &'static str {
        match self {
            Kind::Other => "Error",
            Kind::Path => "PathError",
            Kind::Format => "FormatError",
            Kind::Parameter => "ParameterError",
        }
    }
}

/// An error on its way to Python: the kind and the message, formatted as the CLI prints it
/// (`{:#}`: every context, outermost first).
struct Failure(Kind, String);

impl Failure {
    fn new(kind: Kind, e: impl std::fmt::Display) -> Self {
        Failure(kind, e.to_string())
    }
    fn of(kind: Kind, e: anyhow::Error) -> Self {
        Failure(kind, format!("{e:#}"))
    }
}

impl From<Failure> for PyErr {
    fn from(f: Failure) -> PyErr {
        Python::attach(|py| {
            let class = py
                .import("surfstream._errors")
                .and_then(|m| m.getattr(f.0.class_name()));
            match class.and_then(|c| c.call1((f.1.clone(),))) {
                Ok(value) => PyErr::from_value(value),
                Err(e) => e,
            }
        })
    }
}

/// A reader's error: a missing path or folder is a PathError, another I/O failure a plain
/// Error, anything the reader says about the contents (or the extension) a FormatError.
fn read_failure(e: anyhow::Error) -> Failure {
    let io = e
        .chain()
        .find_map(|c| c.downcast_ref::<std::io::Error>())
        .map(|io| io.kind());
    let kind = match io {
        Some(std::io::ErrorKind::NotFound) | Some(std::io::ErrorKind::IsADirectory) => Kind::Path,
        Some(_) => Kind::Other,
        None => Kind::Format,
    };
    Failure::of(kind, e)
}

fn metrology_failure(e: metrology::MetrologyError) -> Failure {
    let kind = match e {
        metrology::MetrologyError::Param(_) => Kind::Parameter,
        _ => Kind::Other,
    };
    Failure::new(kind, e)
}

fn filter_failure(e: filter::FilterError) -> Failure {
    let kind = match e {
        filter::FilterError::Param(_) => Kind::Parameter,
        _ => Kind::Other,
    };
    Failure::new(kind, e)
}

/// The borrowed heights of a C-contiguous float64 array, and its rows and cols.
fn heights<'a>(a: &'a PyReadonlyArray2<'_, f64>) -> PyResult<(&'a [f64], usize, usize)> {
    let (rows, cols) = a.as_array().dim();
    let s = a.as_slice().map_err(|_| {
        Failure::new(
            Kind::Parameter,
            "heights: expected a C-contiguous float64 array (Surface makes one)",
        )
    })?;
    if rows == 0 || cols == 0 {
        return Err(Failure::new(
            Kind::Parameter,
            format!("heights: empty map ({rows} x {cols}, rows x cols)"),
        )
        .into());
    }
    Ok((s, rows, cols))
}

/// A row-major `Vec` handed to numpy as a `rows x cols` array that owns it (no copy).
fn to_numpy(
    py: Python<'_>,
    v: Vec<f64>,
    rows: usize,
    cols: usize,
) -> PyResult<Bound<'_, PyArray2<f64>>> {
    let a = Array2::from_shape_vec((rows, cols), v)
        .map_err(|e| Failure::new(Kind::Other, format!("result shape: {e}")))?;
    Ok(a.into_pyarray(py))
}

fn metrology_grid(
    h: &[f64],
    rows: usize,
    cols: usize,
    px: f64,
    py_: f64,
) -> Result<Grid<'_>, Failure> {
    Grid::new(h, rows, cols, px, py_).map_err(metrology_failure)
}

fn filter_grid(
    rows: usize,
    cols: usize,
    pitch_x_um: f64,
    pitch_y_um: f64,
) -> Result<Sampling, Failure> {
    let g = Sampling::new(Shape::new(rows, cols), pitch_x_um, pitch_y_um)
        .map_err(|e| filter_failure(e.into()))?;
    g.shape()
        .check(rows * cols)
        .map_err(|e| filter_failure(e.into()))?;
    Ok(g)
}

/// Reads a height-map file: (heights um, pitch x um, pitch y um, metadata as JSON).
#[pyfunction]
fn read(py: Python<'_>, path: PathBuf) -> PyResult<(Bound<'_, PyArray2<f64>>, f64, f64, String)> {
    // A folder: the CLI's message, naming `read` (PathError).
    let s = py.detach(|| {
        surfstream_io::input::not_a_folder(&path, "read")
            .and_then(|()| read_surface(&path))
            .map_err(read_failure)
    })?;
    let meta = serde_json::to_string(&s.metadata).map_err(|e| Failure::new(Kind::Other, e))?;
    let (px, py_) = (s.pitch_x_um, s.pitch_y_um);
    Ok((
        to_numpy(py, s.heights_um, s.height, s.width)?,
        px,
        py_,
        meta,
    ))
}

/// Writes a height map by the path's extension (.x3p, .npy: the CLI's writers).
#[pyfunction]
fn write(
    py: Python<'_>,
    path: PathBuf,
    heights_um: PyReadonlyArray2<'_, f64>,
    pitch_x_um: f64,
    pitch_y_um: f64,
) -> PyResult<()> {
    let (h, rows, cols) = heights(&heights_um)?;
    py.detach(|| {
        filter_grid(rows, cols, pitch_x_um, pitch_y_um)?;
        // The writers take an owned Surface: the one copy of a write.
        let s = Surface {
            width: cols,
            height: rows,
            pitch_x_um,
            pitch_y_um,
            heights_um: h.to_vec(),
            metadata: Metadata {
                format: "python".into(),
                pitch_known: true,
                ..Metadata::default()
            },
        };
        // The same classes as reading: a missing folder is a PathError, an extension the
        // writers do not take a FormatError.
        write_surface(&path, &s).map_err(read_failure)
    })?;
    Ok(())
}

/// The pre-processing steps of `surfstream prep` (surfstream_io::prep), each `(name, arg)`
/// in the verb's words, in order: (heights, pitch x, pitch y, what each step did as JSON).
#[pyfunction]
#[allow(clippy::type_complexity)]
fn prep<'py>(
    py: Python<'py>,
    heights_um: PyReadonlyArray2<'py, f64>,
    pitch_x_um: f64,
    pitch_y_um: f64,
    steps: Vec<(String, String)>,
) -> PyResult<(Bound<'py, PyArray2<f64>>, f64, f64, String)> {
    let (h, rows, cols) = heights(&heights_um)?;
    let out = py.detach(|| -> Result<_, Failure> {
        filter_grid(rows, cols, pitch_x_um, pitch_y_um)?;
        let steps = steps
            .iter()
            .map(|(n, a)| surfstream_io::prep::Step::parse(n, a))
            .collect::<anyhow::Result<Vec<_>>>()
            .map_err(|e| Failure::new(Kind::Parameter, format!("{e:#}")))?;
        let s = Surface {
            width: cols,
            height: rows,
            pitch_x_um,
            pitch_y_um,
            heights_um: h.to_vec(),
            metadata: Metadata {
                format: "python".into(),
                pitch_known: true,
                ..Metadata::default()
            },
        };
        let (out, done) = surfstream_io::prep::run(&s, &steps)
            .map_err(|e| Failure::new(Kind::Other, format!("{e:#}")))?;
        let done = serde_json::to_string(&done).map_err(|e| Failure::new(Kind::Other, e))?;
        Ok((out, done))
    })?;
    let (s, done) = out;
    let (px, py_) = (s.pitch_x_um, s.pitch_y_um);
    Ok((
        to_numpy(py, s.heights_um, s.height, s.width)?,
        px,
        py_,
        done,
    ))
}

/// ISO 25178 parameters: [(name, value, unit, family)], the CLI's order and units.
#[pyfunction]
#[pyo3(signature = (heights_um, pitch_x_um, pitch_y_um, all=false, pruning_pct=5.0))]
fn params(
    py: Python<'_>,
    heights_um: PyReadonlyArray2<'_, f64>,
    pitch_x_um: f64,
    pitch_y_um: f64,
    all: bool,
    pruning_pct: f64,
) -> PyResult<Vec<(&'static str, f64, &'static str, &'static str)>> {
    let (h, rows, cols) = heights(&heights_um)?;
    if !(pruning_pct.is_finite() && pruning_pct >= 0.0) {
        return Err(Failure::new(
            Kind::Parameter,
            format!("pruning_pct {pruning_pct}: expected a finite number >= 0"),
        )
        .into());
    }
    let values = py.detach(|| -> Result<_, Failure> {
        let g = metrology_grid(h, rows, cols, pitch_x_um, pitch_y_um)?;
        let named = if all {
            metrology::all_params_pruned(&g, pruning_pct)
                .map_err(metrology_failure)?
                .named()
        } else {
            metrology::params(&g)
                .map_err(metrology_failure)?
                .named_values()
        };
        Ok(named
            .into_iter()
            .map(|v| (v.name, v.value, v.unit, v.family))
            .collect())
    })?;
    Ok(values)
}

/// The heights minus their least-squares plane (metrology::level_plane, `params --level`).
#[pyfunction]
fn level<'py>(
    py: Python<'py>,
    heights_um: PyReadonlyArray2<'py, f64>,
    pitch_x_um: f64,
    pitch_y_um: f64,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let (h, rows, cols) = heights(&heights_um)?;
    let out = py.detach(|| -> Result<_, Failure> {
        let g = metrology_grid(h, rows, cols, pitch_x_um, pitch_y_um)?;
        metrology::level_plane(&g).map_err(metrology_failure)
    })?;
    to_numpy(py, out, rows, cols)
}

/// The least-squares polynomial form of `order` and the residual: (residual, form, the
/// coefficients, the residual RMS um).
#[pyfunction]
#[allow(clippy::type_complexity)]
fn remove_form<'py>(
    py: Python<'py>,
    heights_um: PyReadonlyArray2<'py, f64>,
    pitch_x_um: f64,
    pitch_y_um: f64,
    order: usize,
) -> PyResult<(
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray2<f64>>,
    Vec<f64>,
    f64,
)> {
    let (h, rows, cols) = heights(&heights_um)?;
    let (residual, form, coefficients, rms) = py.detach(|| -> Result<_, Failure> {
        let grid = filter_grid(rows, cols, pitch_x_um, pitch_y_um)?;
        // The filters run in f32 about the mean, as frames carry heights (DESIGN §2).
        let (offset, h32) = to_frame_heights(h);
        let f = filter::fit_polynomial(&h32, grid, order).map_err(filter_failure)?;
        let mut form = f.evaluate(grid);
        let residual: Vec<f64> = h.iter().zip(&form).map(|(&z, &s)| z - offset - s).collect();
        for s in form.iter_mut() {
            *s += offset;
        }
        let mut coefficients = f.coefficients.clone();
        if let Some(c0) = coefficients.first_mut() {
            *c0 += offset;
        }
        Ok((residual, form, coefficients, f.residual_rms_um))
    })?;
    Ok((
        to_numpy(py, residual, rows, cols)?,
        to_numpy(py, form, rows, cols)?,
        coefficients,
        rms,
    ))
}

/// The ISO 16610-61 Gaussian mean surface for cutoff `cutoff_um`.
#[pyfunction]
fn gaussian<'py>(
    py: Python<'py>,
    heights_um: PyReadonlyArray2<'py, f64>,
    pitch_x_um: f64,
    pitch_y_um: f64,
    cutoff_um: f64,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let (h, rows, cols) = heights(&heights_um)?;
    let out = py.detach(|| -> Result<_, Failure> {
        let grid = filter_grid(rows, cols, pitch_x_um, pitch_y_um)?;
        let (offset, h32) = to_frame_heights(h);
        let mean = filter::gaussian_filter(&h32, grid, cutoff_um).map_err(filter_failure)?;
        Ok(from_frame_heights(offset, &mean))
    })?;
    to_numpy(py, out, rows, cols)
}

/// The ISO 16610-71 robust Gaussian mean surface: (mean, iterations, converged).
#[pyfunction]
#[pyo3(signature = (heights_um, pitch_x_um, pitch_y_um, cutoff_um, max_iterations=30, tolerance=1e-3))]
fn robust_gaussian<'py>(
    py: Python<'py>,
    heights_um: PyReadonlyArray2<'py, f64>,
    pitch_x_um: f64,
    pitch_y_um: f64,
    cutoff_um: f64,
    max_iterations: usize,
    tolerance: f64,
) -> PyResult<(Bound<'py, PyArray2<f64>>, usize, bool)> {
    let (h, rows, cols) = heights(&heights_um)?;
    let (out, it, conv) = py.detach(|| -> Result<_, Failure> {
        let grid = filter_grid(rows, cols, pitch_x_um, pitch_y_um)?;
        let (offset, h32) = to_frame_heights(h);
        let settings = RobustSettings {
            cutoff_um,
            max_iterations,
            tolerance,
        };
        let fit = filter::robust_gaussian_filter(&h32, grid, &settings).map_err(filter_failure)?;
        Ok((
            from_frame_heights(offset, &fit.mean),
            fit.iterations,
            fit.converged,
        ))
    })?;
    Ok((to_numpy(py, out, rows, cols)?, it, conv))
}

/// The datum and roughness of [`separate_map`] kept whole, for numpy.
#[derive(Default)]
struct WholeMaps {
    datum: Vec<f32>,
    roughness: Vec<f32>,
}

impl SeparationSink for WholeMaps {
    fn begin(&mut self, _datum_title: &str) -> anyhow::Result<()> {
        Ok(())
    }
    fn push_rows(&mut self, datum: &[f32], roughness: &[f32]) -> anyhow::Result<()> {
        self.datum.extend_from_slice(datum);
        self.roughness.extend_from_slice(roughness);
        Ok(())
    }
    fn whole(&mut self, datum: Vec<f32>, roughness: Vec<f32>, _cols: usize) -> anyhow::Result<()> {
        (self.datum, self.roughness) = (datum, roughness);
        Ok(())
    }
}

/// `separate`'s summary: [`separate_map`]'s ([`MapSummary`], `separate.json`'s keys) and the
/// offset its heights are relative to.
#[derive(serde::Serialize)]
struct SeparationSummary {
    #[serde(flatten)]
    separation: MapSummary,
    z_offset_um: f64,
}

/// Datum / roughness separation, the `separate` verb's function ([`separate_map`]): (datum um absolute,
/// roughness um, summary JSON, warnings).
#[pyfunction]
#[pyo3(signature = (heights_um, pitch_x_um, pitch_y_um, method="wavelet", wavelet="sym5", level=None, mode="symmetric", cutoff_um=None, lambda_s_um=None))]
#[allow(clippy::too_many_arguments, clippy::type_complexity)]
fn separate<'py>(
    py: Python<'py>,
    heights_um: PyReadonlyArray2<'py, f64>,
    pitch_x_um: f64,
    pitch_y_um: f64,
    method: &str,
    wavelet: &str,
    level: Option<&str>,
    mode: &str,
    cutoff_um: Option<f64>,
    lambda_s_um: Option<f64>,
) -> PyResult<(
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray2<f64>>,
    String,
    Vec<String>,
)> {
    let (h, rows, cols) = heights(&heights_um)?;
    let bad = |e: String| Failure::new(Kind::Parameter, e);
    let method = SeparationMethod::parse(method, cutoff_um).map_err(bad)?;
    // One parser per option, shared with the CLI and the wavelet node.
    let base: BaseChoice = wavelet.parse().map_err(|e| bad(format!("wavelet {e}")))?;
    // None: 8, or the deepest level that fits the map, silently (the verb's default).
    let level: LevelChoice = match level {
        Some(level) => level.parse().map_err(|e| bad(format!("level {e}")))?,
        None => LevelChoice::Default,
    };
    let mode: Mode = mode.parse().map_err(|e| bad(format!("mode {e}")))?;
    // The verb's defaults for what Python does not return (the pooled map), so that the
    // summary is the verb's and the node's.
    let settings = SeparationSettings {
        method,
        lambda_s_um,
        base,
        level,
        mode,
        pool_block: 4,
        pool_op: PoolOp::Max,
    };
    let (datum, roughness, summary, warnings) = py.detach(|| -> Result<_, Failure> {
        let grid = filter_grid(rows, cols, pitch_x_um, pitch_y_um)?;
        let (z_offset_um, h32) = to_frame_heights(h);
        // The verb's and the wavelet node's function: it chooses the path (streamed for a
        // named wavelet at a fixed / default level) and the rows come back whole.
        let mut sink = WholeMaps::default();
        let map = separate_map(&settings, &h32, &grid, &StreamOptions::default(), &mut sink)
            .map_err(|e| Failure::of(Kind::Other, e))?;
        drop(h32);
        let summary = serde_json::to_string(&SeparationSummary {
            separation: map.summary,
            z_offset_um,
        })
        .map_err(|e| Failure::new(Kind::Other, e))?;
        // The datum comes back absolute (f64), the roughness as the difference (no offset).
        let datum = from_frame_heights(z_offset_um, &sink.datum);
        let roughness: Vec<f64> = sink.roughness.iter().map(|&r| f64::from(r)).collect();
        Ok((datum, roughness, summary, map.warning.into_iter().collect()))
    })?;
    Ok((
        to_numpy(py, datum, rows, cols)?,
        to_numpy(py, roughness, rows, cols)?,
        summary,
        warnings,
    ))
}

/// Meshes the heights as an STL at `path`: the `mesh` verb's function, with its names and
/// defaults ([`surfstream_mesher::MesherConfig`], checked by the mesher, then
/// [`surfstream_mesher::mesh_surface`], streamed); returns its record as JSON (the verb's
/// OUT.json without the input file).
#[pyfunction]
#[pyo3(signature = (path, heights_um, pitch_x_um, pitch_y_um, tolerance=None, epsilon_um=None, epsilon_sq=None, level=false, target=None, grid=false, max_triangles=None, region_px=None, model_method="balanced", roughness_um=None, remove_spikes=false, sheet=false, holes=false, ascii=false, units=None, base_depth_um=None, curve=true))]
#[allow(clippy::too_many_arguments)]
fn mesh(
    py: Python<'_>,
    path: PathBuf,
    heights_um: PyReadonlyArray2<'_, f64>,
    pitch_x_um: f64,
    pitch_y_um: f64,
    tolerance: Option<&str>,
    epsilon_um: Option<f64>,
    epsilon_sq: Option<f64>,
    level: bool,
    target: Option<&str>,
    grid: bool,
    max_triangles: Option<usize>,
    region_px: Option<usize>,
    model_method: &str,
    roughness_um: Option<PyReadonlyArray2<'_, f64>>,
    remove_spikes: bool,
    sheet: bool,
    holes: bool,
    ascii: bool,
    units: Option<&str>,
    base_depth_um: Option<f64>,
    curve: bool,
) -> PyResult<String> {
    use surfstream_core::raster::Shape;
    use surfstream_mesher::outliers::OutlierPolicy;
    use surfstream_mesher::{
        mesh_surface, parse_choice, prepare_heights, MeshError, MeshKind, MeshMethod, MeshOutputs,
        MesherConfig, MissingSamples, StlFormat, Tolerance,
    };
    let (h, rows, cols) = heights(&heights_um)?;
    let bad = |e: String| PyErr::from(Failure::new(Kind::Parameter, e));
    // What the verb's flags refuse together (clap's conflicts), named as Python names them.
    let conflicts = [
        (
            epsilon_um.is_some() && epsilon_sq.is_some(),
            "give epsilon_um or epsilon_sq, not both",
        ),
        (
            tolerance.is_some() && (epsilon_um.is_some() || epsilon_sq.is_some()),
            "give tolerance or a fixed bound (epsilon_um / epsilon_sq), not both",
        ),
        (
            holes && !sheet,
            "holes=True needs sheet=True (a solid is closed)",
        ),
        (
            grid && target.is_none(),
            "grid=True needs a target (the engine's regular grid)",
        ),
        (
            grid && (tolerance.is_some() || epsilon_um.is_some() || epsilon_sq.is_some()),
            "grid=True meshes the engine's regular grid: no tolerance or fixed bound",
        ),
        (
            target.is_some() && (sheet || holes || ascii || units.is_some()),
            "target sets the kind, format and units: remove sheet / holes / ascii / units",
        ),
        (
            roughness_um.is_some() && (epsilon_um.is_some() || epsilon_sq.is_some()),
            "roughness_um is judged by the tolerance, not by a fixed bound",
        ),
        (
            !curve && (grid || epsilon_um.is_some() || epsilon_sq.is_some()),
            "curve=False is the tolerance search's: not with grid=True or a fixed bound",
        ),
    ];
    if let Some((_, why)) = conflicts.iter().find(|(c, _)| *c) {
        return Err(bad(why.to_string()));
    }
    let config = MesherConfig {
        units: units
            .map(|u| parse_choice("units", &u.to_ascii_lowercase()))
            .transpose()
            .map_err(bad)?
            .unwrap_or_default(),
        format: if ascii {
            StlFormat::Ascii
        } else {
            StlFormat::Binary
        },
        base_depth_um,
        method: if grid {
            MeshMethod::Grid
        } else {
            MeshMethod::Adaptive
        },
        epsilon_um,
        epsilon_sq_fraction: epsilon_sq,
        max_triangles,
        tolerance: tolerance
            .map(|t| {
                t.parse::<Tolerance>()
                    .map_err(|e| bad(format!("tolerance = {t:?}: {e}")))
            })
            .transpose()?,
        region_px,
        model_method: parse_choice("model_method", model_method).map_err(bad)?,
        outliers: if remove_spikes {
            OutlierPolicy::Remove
        } else {
            OutlierPolicy::Keep
        },
        level,
        kind: if sheet {
            MeshKind::Sheet
        } else {
            MeshKind::Solid
        },
        missing: if holes {
            MissingSamples::Holes
        } else {
            MissingSamples::Fill
        },
        target: target
            .map(|t| parse_choice("target", &t.to_ascii_lowercase()))
            .transpose()
            .map_err(bad)?,
        curve,
        ..MesherConfig::default()
    };
    let settings = config.settings().map_err(bad)?;
    let roughness = match &roughness_um {
        Some(r) => {
            let (r, r_rows, r_cols) = heights(r)?;
            if (r_rows, r_cols) != (rows, cols) {
                return Err(bad(format!(
                    "roughness_um is {r_rows} x {r_cols} (rows x cols); the heights are {rows} x \
                     {cols}: expected the same grid"
                )));
            }
            Some(to_frame_heights(r).1)
        }
        None => None,
    };
    let json = py.detach(|| -> Result<String, Failure> {
        filter_grid(rows, cols, pitch_x_um, pitch_y_um)?;
        let pitch = surfstream_core::Pitch::new(pitch_x_um, pitch_y_um)
            .map_err(|e| Failure::new(Kind::Parameter, e))?;
        // The mesher's own refusals (an infinite sample, a bound out of range, an STL named
        // otherwise) are the caller's parameters; the rest (nothing measured, a file) are not.
        let fail = |e: anyhow::Error| {
            let kind = if e.downcast_ref::<MeshError>().is_some() {
                Kind::Parameter
            } else {
                Kind::Other
            };
            Failure::of(kind, e)
        };
        let prepared = prepare_heights(h, Shape::new(rows, cols)).map_err(fail)?;
        let mut input = prepared.into_input(pitch);
        input.roughness_um = roughness.as_deref();
        // The verb's label, so that the STL bytes are the verb's.
        let label = settings.map_stl_label();
        let outputs = MeshOutputs {
            stl: &path,
            resampled_npy: None,
            stl_label: &label,
        };
        let mut outcome = mesh_surface(&settings, input, &outputs).map_err(fail)?;
        // Python's callers get the STL's path as they gave it (OUT.json, beside the STL,
        // names the file alone).
        outcome.report.file = path.display().to_string();
        serde_json::to_string(&outcome.report).map_err(|e| Failure::new(Kind::Other, e))
    })?;
    Ok(json)
}

/// The Abbott-Firestone curve: [(material ratio %, height um about the mean)].
#[pyfunction]
fn abbott(
    py: Python<'_>,
    heights_um: PyReadonlyArray2<'_, f64>,
    pitch_x_um: f64,
    pitch_y_um: f64,
    samples: usize,
) -> PyResult<Vec<(f64, f64)>> {
    let (h, rows, cols) = heights(&heights_um)?;
    Ok(py.detach(|| -> Result<_, Failure> {
        let g = metrology_grid(h, rows, cols, pitch_x_um, pitch_y_um)?;
        metrology::abbott_curve(&g, samples.max(2)).map_err(metrology_failure)
    })?)
}

/// The radially averaged PSD: [(wavelength um, power um^4)], longest wavelength first.
#[pyfunction]
fn psd(
    py: Python<'_>,
    heights_um: PyReadonlyArray2<'_, f64>,
    pitch_x_um: f64,
    pitch_y_um: f64,
) -> PyResult<Vec<(f64, f64)>> {
    let (h, rows, cols) = heights(&heights_um)?;
    Ok(py.detach(|| -> Result<_, Failure> {
        let g = metrology_grid(h, rows, cols, pitch_x_um, pitch_y_um)?;
        Ok(ArealPsd::of(&g).map_err(metrology_failure)?.radial())
    })?)
}

/// A small viridis PNG of the map (the report's colour map, common/io/src/preview.rs):
/// (PNG bytes, low um, high um of the colour range), or None when nothing is measured.
#[pyfunction]
fn preview_png<'py>(
    py: Python<'py>,
    heights_um: PyReadonlyArray2<'py, f64>,
    max_side_px: usize,
) -> PyResult<Option<(Bound<'py, PyBytes>, f64, f64)>> {
    let (h, rows, cols) = heights(&heights_um)?;
    let png = py.detach(|| -> Result<_, Failure> {
        let h32: Vec<f32> = h.iter().map(|&z| z as f32).collect();
        let Some(range) = robust_range_um(&h32) else {
            return Ok(None);
        };
        let m = encode_map_png(&h32, rows, cols, max_side_px.max(1), range)
            .map_err(|e| Failure::of(Kind::Other, e))?;
        Ok(Some((m.png, range)))
    })?;
    Ok(png.map(|(bytes, (lo, hi))| (PyBytes::new(py, &bytes), lo, hi)))
}

/// A height in um as the CLI prints it: 3 significant figures, nm below 1 um
/// (surfstream_core::units::height: "5.12 nm", "1.27 um"), for the reprs.
#[pyfunction]
fn height_text(v_um: f64) -> String {
    surfstream_core::units::height(v_um)
}

/// Every extension the readers take (lower case, no dot).
#[pyfunction]
fn readable_extensions() -> Vec<&'static str> {
    surfstream_io::formats::EXTENSIONS.to_vec()
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(read, m)?)?;
    m.add_function(wrap_pyfunction!(write, m)?)?;
    m.add_function(wrap_pyfunction!(params, m)?)?;
    m.add_function(wrap_pyfunction!(level, m)?)?;
    m.add_function(wrap_pyfunction!(remove_form, m)?)?;
    m.add_function(wrap_pyfunction!(gaussian, m)?)?;
    m.add_function(wrap_pyfunction!(robust_gaussian, m)?)?;
    m.add_function(wrap_pyfunction!(prep, m)?)?;
    m.add_function(wrap_pyfunction!(separate, m)?)?;
    m.add_function(wrap_pyfunction!(mesh, m)?)?;
    m.add_function(wrap_pyfunction!(abbott, m)?)?;
    m.add_function(wrap_pyfunction!(psd, m)?)?;
    m.add_function(wrap_pyfunction!(preview_png, m)?)?;
    m.add_function(wrap_pyfunction!(readable_extensions, m)?)?;
    m.add_function(wrap_pyfunction!(height_text, m)?)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
