//! The separation of one whole map, shared by the wavelet node's final pass
//! ([`crate::final_separation_with`]) and the `surfstream separate` verb, so the two cannot
//! drift: [`separate_map`] chooses the path, computes, hands datum / roughness rows to a
//! [`SeparationSink`] (each caller writes its own files) and returns the pooled map and the
//! typed summary ([`MapSummary`]).
//!
//! Three paths, as [`crate::final_pass_streams`] decides:
//! * a named wavelet at a fixed or the default level streams ([`crate::separate_streamed`]):
//!   memory is a band of rows plus the map, rows reach the sink in order;
//! * base by RMSE or level by minimum energy runs the in-memory [`crate::analyse`] (both
//!   choices look at the whole map, every base / every level);
//! * the ISO 16610 filter methods run [`crate::filter_separation`] (FFT over the whole map).
//!
//! The in-memory paths hand the sink their whole maps ([`SeparationSink::whole`]).

use anyhow::{anyhow, bail, Result};
/// The summary types are the run record's ([`surfstream_core::record`]): report.html reads
/// the node's back. They keep their names here.
pub use surfstream_core::record::{FilterSummary, MapSummary, WaveletSummary};
use surfstream_core::Sampling;

use crate::method::{equivalent_cutoff_um, filter_separation, level_lowered_warning};
use crate::options::{final_pass_streams, SeparationSettings};
use crate::select::SeparationChoices;
use crate::stream::StreamOptions;
use crate::{
    analyse, default_level, energy_curve_streamed, level_by_min_energy, pool, pooling_bias,
    separate_streamed, BaseChoice, LevelChoice, Pooled, SeparationMethod, Wavelet,
};

/// How run.json and `separate.json` define the wavelet's equivalent cutoff.
pub const CUTOFF_DEFINITION: &str = "wavelength at which the level's approximation passes 50 % amplitude: T(w) = prod_{k<level} |H(2^k w)|^2 / 2, H the decomposition low-pass, aliasing ignored (nodes/wavelet/src/method.rs)";

/// Rows per call when a whole map is handed on as rows ([`push_in_bands`]): bounds the
/// writers' conversion buffers, not the map.
const WHOLE_MAP_BAND_ROWS: usize = 256;

/// Where the datum and roughness of [`separate_map`] go, row by row in order.
pub trait SeparationSink {
    /// Called once, before the first row, with the datum's title (previews).
    fn begin(&mut self, datum_title: &str) -> Result<()>;
    /// The next whole rows of datum and roughness (same length, a multiple of the columns).
    fn push_rows(&mut self, datum: &[f32], roughness: &[f32]) -> Result<()>;
    /// The in-memory paths' whole maps (after [`SeparationSink::begin`]); by default handed
    /// on as rows ([`push_in_bands`]). A sink that keeps the maps takes them here uncopied.
    fn whole(&mut self, datum: Vec<f32>, roughness: Vec<f32>, cols: usize) -> Result<()> {
        push_in_bands(self, &datum, &roughness, cols)
    }
}

/// `datum` and `roughness` (`cols` columns) to `sink` in bands of rows.
pub fn push_in_bands<S: SeparationSink + ?Sized>(
    sink: &mut S,
    datum: &[f32],
    roughness: &[f32],
    cols: usize,
) -> Result<()> {
    let band = WHOLE_MAP_BAND_ROWS * cols.max(1);
    for (d, r) in datum.chunks(band).zip(roughness.chunks(band)) {
        sink.push_rows(d, r)?;
    }
    Ok(())
}

/// The result of [`separate_map`] besides the rows given to the sink.
#[derive(Debug)]
pub struct SeparatedMap {
    pub summary: MapSummary,
    /// Why the level asked for was lowered (wavelet only; each caller prints it its way).
    pub warning: Option<String>,
    pub pooled: Pooled,
    /// The streamed path ran ([`final_pass_streams`]).
    pub streamed: bool,
}

/// Separates `heights` (row-major on `grid`, µm relative to the caller's offset, NaN = not
/// measured) as `settings` say: datum / roughness rows go to `sink`, the pooled map and the
/// summary are returned. Streams where [`final_pass_streams`] says so.
pub fn separate_map(
    settings: &SeparationSettings,
    heights: &[f32],
    grid: &Sampling,
    stream: &StreamOptions,
    sink: &mut dyn SeparationSink,
) -> Result<SeparatedMap> {
    if heights.len() != grid.rows() * grid.cols() {
        bail!(
            "wavelet: the map holds {} heights, its shape says {} x {}",
            heights.len(),
            grid.rows(),
            grid.cols()
        );
    }
    match (settings.method, settings.base) {
        (SeparationMethod::Wavelet, BaseChoice::Named(w)) if final_pass_streams(settings) => {
            streamed_wavelet(settings, &w, heights, grid, stream, sink)
        }
        (SeparationMethod::Wavelet, _) => in_memory_wavelet(settings, heights, grid, sink),
        (method, _) => filter(settings, method, heights, grid, sink),
    }
}

/// A named wavelet at a fixed / default level, band by band ([`separate_streamed`]).
fn streamed_wavelet(
    settings: &SeparationSettings,
    w: &Wavelet,
    heights: &[f32],
    grid: &Sampling,
    stream: &StreamOptions,
    sink: &mut dyn SeparationSink,
) -> Result<SeparatedMap> {
    let (rows, cols) = (grid.rows(), grid.cols());
    let level = default_level(rows, cols, w, settings.fixed_level())?;
    let curve = energy_curve_streamed(heights, rows, cols, w, settings.mode, stream)?;
    let pooled = pool(heights, rows, cols, settings.pool_block, settings.pool_op)?;
    let choices = SeparationChoices {
        wavelet: w.name().into(),
        mode: settings.mode.name().into(),
        level,
        level_min_energy: level_by_min_energy(&curve),
        energy_curve: curve,
        energy_curve_note: crate::select::ENERGY_CURVE_NOTE.into(),
        base_rmse: None,
        base_rmse_note: None,
        pool: settings.pool_block,
        pool_op: settings.pool_op.name().into(),
        pooling_bias: pooling_bias(heights, &pooled.heights),
    };
    let (summary, warning) = wavelet_summary(choices, settings, w, grid);
    sink.begin(&summary.datum_title())?;
    separate_streamed(
        heights,
        rows,
        cols,
        w,
        settings.mode,
        Some(level),
        stream,
        |_, d, r| sink.push_rows(d, r),
    )
    .map_err(|e| anyhow!("wavelet: streamed separation: {e}"))?;
    Ok(SeparatedMap {
        summary,
        warning,
        pooled,
        streamed: true,
    })
}

/// Base by RMSE or level by minimum energy: [`analyse`] over the whole map.
fn in_memory_wavelet(
    settings: &SeparationSettings,
    heights: &[f32],
    grid: &Sampling,
    sink: &mut dyn SeparationSink,
) -> Result<SeparatedMap> {
    let analysis = analyse(
        heights,
        grid.rows(),
        grid.cols(),
        settings.base,
        settings.level,
        settings.mode,
        settings.pool_block,
        settings.pool_op,
    )?;
    let w = analysis.wavelet;
    let (choices, separation, pooled) = analysis.into_parts();
    let (summary, warning) = wavelet_summary(choices, settings, &w, grid);
    sink.begin(&summary.datum_title())?;
    sink.whole(separation.datum, separation.roughness, grid.cols())?;
    Ok(SeparatedMap {
        summary,
        warning,
        pooled,
        streamed: false,
    })
}

/// An ISO 16610 L-filter ([`filter_separation`]) over the whole map.
fn filter(
    settings: &SeparationSettings,
    method: SeparationMethod,
    heights: &[f32],
    grid: &Sampling,
    sink: &mut dyn SeparationSink,
) -> Result<SeparatedMap> {
    let s = filter_separation(heights, *grid, method, settings.lambda_s_um)
        .map_err(|e| anyhow!("wavelet: {} separation: {e}", method.name()))?;
    let pooled = pool(
        heights,
        grid.rows(),
        grid.cols(),
        settings.pool_block,
        settings.pool_op,
    )?;
    let summary = MapSummary::Filter(FilterSummary {
        method: method.name().into(),
        cutoff_um: method.cutoff_um().unwrap_or(f64::NAN),
        lambda_s_um: settings.lambda_s_um,
        plane_removed_um: s.plane_um,
        robust_iterations: s.robust_iterations.map(|r| r.0),
        robust_converged: s.robust_iterations.map(|r| r.1),
        pool: settings.pool_block,
        pool_op: settings.pool_op.name().into(),
        pooling_bias: pooling_bias(heights, &pooled.heights),
    });
    sink.begin(&summary.datum_title())?;
    sink.whole(s.datum, s.roughness, grid.cols())?;
    Ok(SeparatedMap {
        summary,
        warning: None,
        pooled,
        streamed: false,
    })
}

/// The wavelet's choices with its equivalent cutoff and, when a level asked for explicitly
/// was lowered, why. The default is min([`crate::DEFAULT_LEVEL`], the deepest level that fits the
/// map), chosen silently: a map too small for level 8 is no mistake of the user's.
fn wavelet_summary(
    choices: SeparationChoices,
    settings: &SeparationSettings,
    w: &Wavelet,
    grid: &Sampling,
) -> (MapSummary, Option<String>) {
    let level = choices.level;
    let (pitch_x_um, pitch_y_um) = (grid.pitch_x_um(), grid.pitch_y_um());
    let warning = match settings.level {
        LevelChoice::Fixed(requested) => level_lowered_warning(w, requested, level, pitch_x_um),
        LevelChoice::Default | LevelChoice::MinEnergy => None,
    };
    let summary = MapSummary::Wavelet(WaveletSummary {
        choices,
        method: "wavelet".into(),
        equivalent_cutoff_um: equivalent_cutoff_um(w, level, pitch_x_um),
        equivalent_cutoff_y_um: (pitch_y_um != pitch_x_um)
            .then(|| equivalent_cutoff_um(w, level, pitch_y_um)),
        equivalent_cutoff_definition: CUTOFF_DEFINITION.into(),
    });
    (summary, warning)
}
