//! Typed records (DESIGN §6): run.json and the node reports it is assembled from, as serde
//! structs shared by the writers (the nodes, the launcher) and the readers (the launcher's
//! run.json assembly, the verdict, Table 6's geometry, report.html), so the compiler ties a
//! field's writer to its readers.
//!
//! Key order: serde_json is built without `preserve_order`, so a JSON object is a sorted map
//! and every file surfstream wrote so far lists its keys alphabetically. Writers turn a record
//! into a value with [`to_value`] before writing it, which keeps that order whatever the
//! declaration order here (and keeps run.json byte-identical to the untyped values it
//! replaced).
//!
//! What stays a JSON value inside a record, and why: the fusion's chunk statistics (a fusion
//! type), each node's report inside run.json's `stages` (its reader reads it through its
//! record) and each node's parameters (the graph file's table).
//!
//! Every record the project writes is here: the finishing node's finish.json and its report
//! too, in [`finish`] (with the plain data types they carry: the setting, the macro run's
//! contacts, the contact field), which its writer, finish.html and report.html read.

use std::collections::BTreeMap;

use serde::{Deserialize, Deserializer, Serialize};
use serde_json::Value;

use crate::metrology::Params;

pub mod finish;

/// A record that could not be written as JSON (a map with keys that are not strings, a custom
/// `Serialize` that failed): an error, so a report never turns into `null` unnoticed.
#[derive(Debug, thiserror::Error)]
#[error("record {record} cannot be written as JSON: {source}")]
pub struct RecordError {
    /// The record's type, as Rust names it.
    pub record: &'static str,
    #[source]
    pub source: serde_json::Error,
}

/// A record as a JSON value with its keys sorted (how every report and run.json is written).
pub fn to_value<T: Serialize + ?Sized>(record: &T) -> Result<Value, RecordError> {
    serde_json::to_value(record).map_err(|source| RecordError {
        record: std::any::type_name::<T>(),
        source,
    })
}

/// A record read back from a JSON value, the error naming what was expected.
pub fn from_value<T: for<'de> Deserialize<'de>>(value: &Value, what: &str) -> Result<T, String> {
    T::deserialize(value).map_err(|e| format!("{what}: {e}"))
}

/// A node's report record, with the kind of node that writes it: a reader finds a node's
/// report by the record it wants (`read_report::<ReplayReport>`), and the node's port
/// declaration names its kind by the same constant, so the kind is spelled once.
pub trait NodeRecord: for<'de> Deserialize<'de> {
    /// The node kind (the graph file's `node = "..."`).
    const NODE_KIND: &'static str;
}

impl NodeRecord for ReplayReport {
    const NODE_KIND: &'static str = "replay";
}

impl NodeRecord for MatcherReport {
    const NODE_KIND: &'static str = "matcher";
}

impl NodeRecord for FusionReport {
    const NODE_KIND: &'static str = "fusion";
}

impl NodeRecord for WaveletReport {
    const NODE_KIND: &'static str = "wavelet";
}

impl NodeRecord for MeshReport {
    const NODE_KIND: &'static str = "mesher";
}

impl NodeRecord for RecorderReport {
    const NODE_KIND: &'static str = "recorder";
}

/// Reads an f64 that serde_json wrote as `null` (NaN and infinities) back as NaN.
pub(crate) fn nan_if_null<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
}

// ---------------------------------------------------------------------------------------
// Node reports (each node's `NodeLogic::report`, `nodes/<id>.json`'s `report`, run.json's
// `stages.<id>`).

/// The source's description of the scan (the replay node's `scan`, run.json's `scan`), one
/// variant per source, tagged by `source`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "source", rename_all = "lowercase")]
pub enum ScanRecord {
    /// The simulated stage.
    Simulated {
        name: String,
        rows: usize,
        cols: usize,
        tile_width_px: usize,
        tile_height_px: usize,
        pitch_x_um: f64,
        pitch_y_um: f64,
        /// Overlap along x and y, fractions of a field.
        overlap: [f64; 2],
        /// The specimen's `.npy`, or "generated".
        specimen: String,
        truth_file: String,
    },
    /// A scan directory (`scan.toml`).
    Scan {
        name: String,
        manifest: String,
        rows: usize,
        cols: usize,
        tile_width_px: usize,
        tile_height_px: usize,
        pitch_x_um: f64,
        pitch_y_um: f64,
        height_unit: String,
        z_offset_um: f64,
    },
    /// An MCAP recording.
    Mcap {
        name: String,
        recording: String,
        topic: String,
        tiles: usize,
        tile_width_px: usize,
        tile_height_px: usize,
        pitch_x_um: f64,
        pitch_y_um: f64,
    },
}

impl ScanRecord {
    /// The tile grid, rows x cols (a recording does not state one).
    pub fn grid(&self) -> Option<(usize, usize)> {
        match self {
            ScanRecord::Simulated { rows, cols, .. } | ScanRecord::Scan { rows, cols, .. } => {
                Some((*rows, *cols))
            }
            ScanRecord::Mcap { .. } => None,
        }
    }
    /// The lateral pitch (x, y), um.
    pub fn pitch_um(&self) -> (f64, f64) {
        match self {
            ScanRecord::Simulated {
                pitch_x_um,
                pitch_y_um,
                ..
            }
            | ScanRecord::Scan {
                pitch_x_um,
                pitch_y_um,
                ..
            }
            | ScanRecord::Mcap {
                pitch_x_um,
                pitch_y_um,
                ..
            } => (*pitch_x_um, *pitch_y_um),
        }
    }
    /// One tile's size in pixels, (width, height).
    pub fn tile_px(&self) -> (usize, usize) {
        match self {
            ScanRecord::Simulated {
                tile_width_px,
                tile_height_px,
                ..
            }
            | ScanRecord::Scan {
                tile_width_px,
                tile_height_px,
                ..
            }
            | ScanRecord::Mcap {
                tile_width_px,
                tile_height_px,
                ..
            } => (*tile_width_px, *tile_height_px),
        }
    }
}

/// One tile as the source sent it (the replay node's `tiles`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SourceTile {
    pub index: u32,
    pub row: u32,
    pub col: u32,
    /// The tile's file (scan directories only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub file: Option<String>,
    /// Nominal stage position of pixel (0, 0), um.
    pub stage_x_um: f64,
    pub stage_y_um: f64,
}

/// The replay node's report.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ReplayReport {
    pub scan: ScanRecord,
    pub tiles: Vec<SourceTile>,
    /// Messages sent per output port.
    pub sent: BTreeMap<String, u64>,
}

/// Where a tile was placed while streaming, before the global solve.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StreamingPlacement {
    pub x_um: f64,
    pub y_um: f64,
    pub placed_by: String,
    pub links_tried: u32,
    #[serde(deserialize_with = "nan_if_null")]
    pub piston_um: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub tilt_x_um_per_px: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub tilt_y_um_per_px: f64,
}

/// A tile's final placement by the matcher (pixel (0, 0) in scan coordinates, um).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TilePlacement {
    pub x_um: f64,
    pub y_um: f64,
    /// "registration" or "stage".
    pub placed_by: String,
    pub links_accepted: u32,
    pub links_tried: u32,
    /// The best NCC among the tile's links the global solve kept (0 without one).
    #[serde(deserialize_with = "nan_if_null")]
    pub quality: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub piston_um: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub tilt_x_um_per_px: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub tilt_y_um_per_px: f64,
    pub streaming: StreamingPlacement,
    /// How many directions the tile's kept links fix: 2, 1 (the other from the stage, along
    /// `stage_direction`) or 0. Absent in reports written before it existed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub registered_directions: Option<u8>,
    /// With `registered_directions` 1: the unit direction (x, y) the stage alone placed the
    /// tile along.
    #[serde(default)]
    pub stage_direction: Option<[f64; 2]>,
}

/// One tile of the matcher's report.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MatcherTile {
    pub index: u32,
    pub row: u32,
    pub col: u32,
    #[serde(flatten)]
    pub placement: TilePlacement,
}

/// A one-direction answer of a refused pair (its NCC ridge fixes one direction).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DirectionalPair {
    pub offset_px: [f64; 2],
    /// The unit direction the ridge fixes.
    pub normal: [f64; 2],
    pub curvature_per_px2: [f64; 2],
    #[serde(deserialize_with = "nan_if_null")]
    pub ncc: f64,
    /// After the global solve, when it took the link.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub kept_by_global_solve: Option<bool>,
    #[serde(
        default,
        deserialize_with = "some_nan_array",
        skip_serializing_if = "Option::is_none"
    )]
    pub residual_px: Option<[f64; 2]>,
}

/// One neighbour pair's registration and outcome (the matcher's `pairs`, run.json's `pairs`):
/// what streaming found, and what the global solve made of it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MatcherPair {
    /// Tile indices.
    pub a: u32,
    pub b: u32,
    /// "horizontal" or "vertical".
    pub direction: String,
    /// b's offset from a by the stage, px.
    pub nominal_offset_px: [f64; 2],
    /// b's offset from a by the registration (null: refused).
    pub offset_px: Option<[f64; 2]>,
    #[serde(deserialize_with = "nan_if_null")]
    pub ncc: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub peak_ratio: f64,
    pub accepted: bool,
    /// Why the pair was refused (null: accepted).
    pub reason: Option<String>,
    /// Accepted as a distinct peak below the matcher's min_ncc (only written when true).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub accepted_below_min_ncc: bool,
    /// The measured offset disagrees with the layout's planned (nominal) offset by more than
    /// the stage error allows (only written when true): refused when weak, flagged when
    /// strong; the verdict fails on it with the layout as the cause (issue 36).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub layout_inconsistent: Option<LayoutMisfit>,
    /// The feature matcher's diagnostics (feature methods only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub features: Option<FeaturePairRecord>,
    /// After the global solve: b's offset from a in the final placement, px.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub final_offset_px: Option<[f64; 2]>,
    /// Height-difference samples of the overlap used by the plane solve.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub z_samples: Option<u64>,
    /// An ambiguous pair's candidate offsets, and the one the global solve took (null: none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub alternatives_px: Option<Vec<[f64; 2]>>,
    #[serde(
        default,
        deserialize_with = "present",
        skip_serializing_if = "Option::is_none"
    )]
    pub chosen_alternative: Option<Option<u64>>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub directional: Option<DirectionalPair>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub kept_by_global_solve: Option<bool>,
    /// (p_b - p_a) - offset in the final solution, px (links the solve took).
    #[serde(
        default,
        deserialize_with = "some_nan_array",
        skip_serializing_if = "Option::is_none"
    )]
    pub residual_px: Option<[f64; 2]>,
    /// The Lucas-Kanade refinement's covariance of `offset_px`, px², when it ran.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub offset_covariance_px2: Option<[[f64; 2]; 2]>,
    /// Its worst direction's standard deviation, px: the link's weight in the global solve.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub offset_sd_px: Option<f64>,
}

/// A link whose offset disagrees with the layout's plan (`pairs[].layout_inconsistent`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LayoutMisfit {
    /// |measured - nominal offset|, px.
    pub shift_px: f64,
    /// The bound it exceeds, px (from the stated stage error, `stage_sigma_px`).
    pub bound_px: f64,
    /// Refused (true: a weak link, not used) or only flagged (a strong link, kept).
    pub refused: bool,
}

/// Reads a key that is present, null or not: `Some(None)` for null (absent: the default,
/// `None`), so that it is written back as it was.
fn present<'de, D: Deserializer<'de>, T: Deserialize<'de>>(
    d: D,
) -> Result<Option<Option<T>>, D::Error> {
    Option::<T>::deserialize(d).map(Some)
}

/// The matcher's global solve over the whole scan (its `global`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GlobalSolveRecord {
    /// Links (accepted and chosen ambiguous pairs) and how many the solve removed.
    pub links: u64,
    pub links_removed: u64,
    #[serde(deserialize_with = "nan_if_null")]
    pub max_residual_px: f64,
    pub tiles_placed_by_stage: u64,
    /// One-direction links (refused pairs with a ridge) and how many were removed.
    pub directional_links: u64,
    pub directional_links_removed: u64,
    pub tiles_one_direction_by_stage: u64,
    pub stage_sigma_px: f64,
    pub outlier_px: f64,
    /// RMS of the overlaps' height differences before and after the plane solve, um.
    #[serde(deserialize_with = "nan_if_null")]
    pub z_rms_before_um: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub z_rms_residual_um: f64,
    /// The feature matchers' scores against a truth file (null otherwise).
    pub features: Option<FeatureSummaryRecord>,
}

/// r and AP of one feature-matched pair against a truth file (the matcher's `efficiency`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MatchQuality {
    pub matches: usize,
    pub correct: usize,
    /// Matching efficiency r (the paper's eq. 2).
    pub r: Option<f64>,
    /// Average precision of the ranked matches.
    pub average_precision: Option<f64>,
    pub tolerance_px: f64,
}

/// One pair's feature-matcher diagnostics (run.json `pairs[].features`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FeaturePairRecord {
    /// "harris" or "sift".
    pub method: String,
    /// Features detected in a's and in b's overlap.
    pub features_a: usize,
    pub features_b: usize,
    pub one_way_matches: usize,
    pub two_way_matches: usize,
    /// RANSAC inliers.
    pub inliers: usize,
    /// Residual rotation (degrees) and scale of b against a by a similarity fit of the inliers.
    pub rotation_deg: Option<f64>,
    pub scale: Option<f64>,
    /// Why the pair was refused (null: accepted).
    pub reason: Option<String>,
    /// r and AP against the truth file, when one is given.
    pub truth: Option<MatchQuality>,
}

/// The feature matchers' scores over the scan against a truth file (run.json
/// `global.features`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FeatureSummaryRecord {
    /// The truth file.
    pub truth: String,
    pub pairs_with_truth: usize,
    /// Pairs with at least one match (the means are over these).
    pub pairs_with_matches: usize,
    pub mean_r: Option<f64>,
    /// Mean average precision.
    pub map: Option<f64>,
    pub correct_match_tolerance_px: f64,
}

/// The matcher's report.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MatcherReport {
    pub method: String,
    pub tiles: Vec<MatcherTile>,
    /// Every neighbour pair's registration and outcome.
    pub pairs: Vec<MatcherPair>,
    /// The global solve's summary (null until the end of scan).
    pub global: Option<GlobalSolveRecord>,
}

/// The final panorama's size, place, offset and invalid pixels (the fusion's `panorama`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PanoramaSummary {
    pub width_px: usize,
    pub height_px: usize,
    /// Scan position of pixel (0, 0), um.
    #[serde(deserialize_with = "nan_if_null")]
    pub origin_x_um: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub origin_y_um: f64,
    pub pitch_x_um: f64,
    pub pitch_y_um: f64,
    pub z_offset_um: f64,
    pub invalid_px: usize,
}

/// The fusion's `panorama.tiles.json` beside panorama.npy ([`PanoramaTiles`]).
pub const PANORAMA_TILES: &str = "panorama.tiles.json";

/// Where every tile lies on the final panorama (the fusion's [`PANORAMA_TILES`], written with
/// panorama.npy before the final panorama is sent): the panorama's grid and each placed
/// tile's final position and size. The mesher reads it to judge Table 6's tile regions
/// (`surfstream_core::deviation::tile_regions`) in its tolerance search.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PanoramaTiles {
    pub panorama: PanoramaSummary,
    /// In tile index order.
    pub tiles: Vec<PlacedTile>,
}

/// One tile of [`PanoramaTiles`]: pixel (0, 0) in scan coordinates (um, the final
/// registration's) and its size.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PlacedTile {
    pub index: u32,
    pub x_um: f64,
    pub y_um: f64,
    pub width_px: usize,
    pub height_px: usize,
}

/// SSIM of one overlap (the fusion's `fusion_pairs`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PairQuality {
    /// Tile indices, `tile_a < tile_b`.
    pub tile_a: u32,
    pub tile_b: u32,
    /// Overlap rectangle in panorama pixels.
    pub width_px: usize,
    pub height_px: usize,
    /// Pixels of the rectangle both tiles measured.
    pub valid_px: usize,
    /// SSIM(fused, tile a), SSIM(fused, tile b) over the overlap, and their mean (NaN
    /// without a valid pixel).
    #[serde(deserialize_with = "nan_if_null")]
    pub ssim_a: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub ssim_b: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub ssim_mean: f64,
}

/// The fusion's chunked canvas.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FusionMemory {
    pub chunk_px: usize,
    pub chunk_budget_bytes: Option<u64>,
    /// The chunk store's statistics (null before the first tile).
    pub chunks: Value,
}

/// The fusion's report.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FusionReport {
    pub method: String,
    pub patches: u64,
    /// Null until the end of scan.
    pub panorama: Option<PanoramaSummary>,
    pub files: Vec<String>,
    pub rerendered_from_final_registrations: bool,
    pub final_registrations: u64,
    /// How the SSIM of overlaps is defined.
    pub ssim: String,
    /// SSIM of every overlap.
    pub fusion_pairs: Vec<PairQuality>,
    pub memory: FusionMemory,
}

/// The wavelet's report.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WaveletReport {
    pub live_patches: u64,
    /// The final pass's summary (null until the end of scan).
    #[serde(rename = "final")]
    pub final_pass: Option<FinalSummary>,
}

// ---------------------------------------------------------------------------------------
// The wavelet's separation summary (run.json's `stages.<wavelet>.final`, and the `separate`
// verb's separate.json): written by `surfstream_wavelet` (which re-exports these under the
// same names), read by report.html (the level of the PSD's scale).

/// One point of the energy curve.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct EnergyPoint {
    pub level: usize,
    /// E(cA_l) / (E(cA_l) + E(details 1..l)), in [0, 1].
    #[serde(deserialize_with = "nan_if_null")]
    pub approx_energy_fraction: f64,
}

/// Reconstruction RMSE of one base (eq. 10).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BaseRmse {
    pub wavelet: String,
    pub level: usize,
    /// sqrt(mean((x - waverec2(wavedec2(x)))^2)) over the valid pixels, um.
    #[serde(deserialize_with = "nan_if_null")]
    pub rmse_um: f64,
}

/// Height statistics of the valid pixels, um (ISO 25178 definitions, no levelling).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct HeightStats {
    #[serde(deserialize_with = "nan_if_null")]
    pub mean_um: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub sa_um: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub sq_um: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub sz_um: f64,
}

/// What pooling did to the height statistics: before, after and after - before.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PoolingBias {
    pub before: HeightStats,
    pub after: HeightStats,
    pub shift: HeightStats,
}

/// The wavelet separation's choices and their evidence.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SeparationChoices {
    pub wavelet: String,
    pub mode: String,
    pub level: usize,
    /// The level the energy rule picks (whether or not it was used).
    pub level_min_energy: Option<usize>,
    pub energy_curve: Vec<EnergyPoint>,
    pub energy_curve_note: String,
    /// Eq. 10 per base, when the base was chosen by it.
    pub base_rmse: Option<Vec<BaseRmse>>,
    pub base_rmse_note: Option<String>,
    /// Pooling block, px.
    pub pool: usize,
    pub pool_op: String,
    pub pooling_bias: Option<PoolingBias>,
}

/// A wavelet separation: the choices and their evidence, and the level's equivalent cutoff.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WaveletSummary {
    #[serde(flatten)]
    pub choices: SeparationChoices,
    /// "wavelet".
    pub method: String,
    /// Along x, at the map's x pitch.
    #[serde(deserialize_with = "nan_if_null")]
    pub equivalent_cutoff_um: f64,
    /// Along y, only when the y pitch differs from the x pitch.
    #[serde(
        default,
        deserialize_with = "some_nan_if_null",
        skip_serializing_if = "Option::is_none"
    )]
    pub equivalent_cutoff_y_um: Option<f64>,
    pub equivalent_cutoff_definition: String,
}

/// An ISO 16610 L-filter separation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FilterSummary {
    pub method: String,
    /// lambda_c, um.
    #[serde(deserialize_with = "nan_if_null")]
    pub cutoff_um: f64,
    /// lambda_s, um (none: no S-filter).
    pub lambda_s_um: Option<f64>,
    /// [a, b, c] of the plane removed before filtering and added back, um.
    #[serde(deserialize_with = "nan_array")]
    pub plane_removed_um: [f64; 3],
    /// Robust filter only.
    pub robust_iterations: Option<usize>,
    pub robust_converged: Option<bool>,
    pub pool: usize,
    pub pool_op: String,
    pub pooling_bias: Option<PoolingBias>,
}

/// The separation of one map: the wavelet's choices or the filter's. Untagged: a filter
/// summary lacks the wavelet's keys (`wavelet`, `level`, ...), so it fails the first layout.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum MapSummary {
    Wavelet(WaveletSummary),
    Filter(FilterSummary),
}

impl MapSummary {
    /// The datum's title in previews.
    pub fn datum_title(&self) -> String {
        match self {
            MapSummary::Wavelet(w) => {
                format!(
                    "datum, {} level {} (um)",
                    w.choices.wavelet, w.choices.level
                )
            }
            MapSummary::Filter(f) => {
                format!("datum, {} lambda_c {} um (um)", f.method, f.cutoff_um)
            }
        }
    }

    /// The decomposition level (a wavelet separation only).
    pub fn level(&self) -> Option<usize> {
        match self {
            MapSummary::Wavelet(w) => Some(w.choices.level),
            MapSummary::Filter(_) => None,
        }
    }
}

/// The wavelet node's final pass: the separation's summary with what only the node knows.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FinalSummary {
    #[serde(flatten)]
    pub separation: MapSummary,
    /// Why the level asked for was lowered; absent when it was not.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub warning: Option<String>,
    pub level_requested: Option<usize>,
    /// (cols, rows).
    pub panorama_px: [usize; 2],
    /// (cols, rows).
    pub pooled_px: [usize; 2],
    pub files: Vec<String>,
    pub streamed: bool,
}

/// The recorder's report.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RecorderReport {
    pub file: Option<String>,
    /// Messages written per topic.
    pub messages: BTreeMap<String, u64>,
}

// ---------------------------------------------------------------------------------------
// The mesher's report (its `summary`: the job's statistics of the mesh and the node's
// files, wiring and times; run.json's `stages.<mesher>`)

/// Reads `[f64; N]` written with NaN as null.
fn nan_array<'de, D: Deserializer<'de>, const N: usize>(d: D) -> Result<[f64; N], D::Error> {
    let v: Vec<Option<f64>> = Vec::deserialize(d)?;
    let n = v.len();
    let a: [Option<f64>; N] = v
        .try_into()
        .map_err(|_| serde::de::Error::invalid_length(n, &format!("{N} numbers").as_str()))?;
    Ok(a.map(|v| v.unwrap_or(f64::NAN)))
}

/// Reads an optional f64 whose key, when present, may be null (NaN): `Some(NaN)`, so that it
/// is written back as the null it was.
fn some_nan_if_null<'de, D: Deserializer<'de>>(d: D) -> Result<Option<f64>, D::Error> {
    nan_if_null(d).map(Some)
}

/// [`nan_array`] of an optional key.
fn some_nan_array<'de, D: Deserializer<'de>, const N: usize>(
    d: D,
) -> Result<Option<[f64; N]>, D::Error> {
    nan_array(d).map(Some)
}

/// Sa, Sq, Sz (um) and Sdr (%) of a levelled surface (the mesher's fidelity).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LevelledParams {
    #[serde(deserialize_with = "nan_if_null")]
    pub sa_um: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub sq_um: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub sz_um: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub sdr_percent: f64,
}

/// The mesh's vertical error over the measured samples.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct VerticalError {
    #[serde(deserialize_with = "nan_if_null")]
    pub max_um: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub rms_um: f64,
    pub samples: u64,
    /// Measured samples no triangle covers.
    pub uncovered: u64,
}

/// An adaptive mesh's fidelity: the bound, the error reached, the parameters of the field and
/// of the mesh re-sampled on it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MeshFidelity {
    #[serde(deserialize_with = "nan_if_null")]
    pub epsilon_um: f64,
    pub error: VerticalError,
    pub bound_met: bool,
    pub field: Option<LevelledParams>,
    pub mesh: Option<LevelledParams>,
}

/// The tolerance a model was made to, percent of the measured value per region.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ModelTolerance {
    pub sa_pct: f64,
    pub sq_pct: f64,
    pub sz_pct: f64,
    /// The limit on the pointwise residual RMS, percent of Sq.
    #[serde(
        default,
        deserialize_with = "some_nan_if_null",
        skip_serializing_if = "Option::is_none"
    )]
    pub residual_pct: Option<f64>,
    /// The limit on the largest pointwise |mesh - measurement| (means removed), percent of Sq.
    #[serde(
        default,
        deserialize_with = "some_nan_if_null",
        skip_serializing_if = "Option::is_none"
    )]
    pub max_error_pct: Option<f64>,
    /// The limit on the roughness the mesh carries (mesh - datum against the measured
    /// roughness), percent, per parameter.
    #[serde(
        default,
        deserialize_with = "some_nan_if_null",
        skip_serializing_if = "Option::is_none"
    )]
    pub roughness_pct: Option<f64>,
}

/// One region of the chosen mesh against the measurement.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RegionFitRecord {
    pub region: String,
    pub samples: u64,
    /// Sa, Sq, Sz of the measurement, um.
    #[serde(deserialize_with = "nan_array")]
    pub measured_um: [f64; 3],
    /// (model - measured) / measured * 100 for Sa, Sq, Sz.
    #[serde(deserialize_with = "nan_array")]
    pub deviation_pct: [f64; 3],
    #[serde(deserialize_with = "nan_if_null")]
    pub residual_pct_of_sq: f64,
    /// The largest pointwise |mesh - measurement| (both means removed), um and percent of the
    /// measured Sq (records written before the pointwise bound have none).
    #[serde(
        default,
        deserialize_with = "some_nan_if_null",
        skip_serializing_if = "Option::is_none"
    )]
    pub max_error_um: Option<f64>,
    #[serde(
        default,
        deserialize_with = "some_nan_if_null",
        skip_serializing_if = "Option::is_none"
    )]
    pub max_error_pct_of_sq: Option<f64>,
    /// (model - measured) / measured * 100 of the roughness the mesh carries, Sa, Sq, Sz
    /// (when the roughness is judged).
    #[serde(
        default,
        deserialize_with = "some_nan_array",
        skip_serializing_if = "Option::is_none"
    )]
    pub roughness_deviation_pct: Option<[f64; 3]>,
}

/// One mesh of the tolerance search (the fidelity-cost curve).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CurvePointRecord {
    #[serde(deserialize_with = "nan_if_null")]
    pub epsilon_um: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub epsilon_sq_fraction: f64,
    pub surface_triangles: u64,
    #[serde(deserialize_with = "nan_if_null")]
    pub triangles_per_measured_px: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub worst_sa_pct: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub worst_sq_pct: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub worst_sz_pct: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub worst_residual_pct_of_sq: f64,
    /// Largest pointwise error over the regions, percent of the region's Sq.
    #[serde(
        default,
        deserialize_with = "some_nan_if_null",
        skip_serializing_if = "Option::is_none"
    )]
    pub worst_max_error_pct_of_sq: Option<f64>,
    /// Worst |deviation| of the roughness the mesh carries (when it is judged), percent.
    #[serde(
        default,
        deserialize_with = "some_nan_if_null",
        skip_serializing_if = "Option::is_none"
    )]
    pub worst_roughness_pct: Option<f64>,
    pub worst_region: String,
    pub pass: bool,
    pub over_budget: bool,
    pub chosen: bool,
}

/// What the tolerance search found (the mesher's `tolerance`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ToleranceRecord {
    pub tolerance: ModelTolerance,
    pub target_share: f64,
    pub region_px: u64,
    /// Regions judged: the whole map, the windows and the tile footprints.
    pub regions: u64,
    /// Of those, Table 6's tile regions (S1...; 0, not written: not known to the mesher, or a
    /// record from before it judged them: old records round-trip unchanged).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub footprints: u64,
    pub measured_px: u64,
    pub met: bool,
    pub surface_triangles: u64,
    #[serde(deserialize_with = "nan_if_null")]
    pub triangles_per_measured_px: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub epsilon_um: f64,
    /// Why the tolerance is not met; None when it is.
    pub reason: Option<String>,
    /// Every region of the chosen mesh, worst first.
    pub region_fits: Vec<RegionFitRecord>,
    pub curve: Vec<CurvePointRecord>,
    /// The angle bound's refinement of the chosen mesh (an engine's bound, e.g. LIGGGHTS').
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub angles: Option<AngleRecord>,
    /// The form every region was judged without: the measured field's least-squares plane
    /// (`params --level`'s), subtracted from the measurement and the mesh alike, so a tilt
    /// does not hide the roughness from the bounds; Table 6 judges the mesh stage the same
    /// way. Absent: a record from before (regions judged about their mean only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub judged_plane: Option<FormPlane>,
}

/// What the angle bound did to the chosen mesh (the mesher's `tolerance.angles`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AngleRecord {
    /// The bound, degrees.
    pub bound_deg: f64,
    /// Smallest angle of any triangle before and after the refinement, degrees (null: no
    /// triangle).
    #[serde(deserialize_with = "nan_if_null")]
    pub min_angle_before_deg: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub min_angle_deg: f64,
    /// Triangles below the bound before and after.
    pub below_bound_before: u64,
    pub below_bound: u64,
    /// Triangles before and after (the refinement's cost).
    pub triangles_before: u64,
    pub triangles: u64,
}

/// The spikes the mesher found (its `outliers`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OutliersRecord {
    pub rule: String,
    #[serde(deserialize_with = "nan_if_null")]
    pub threshold_um: f64,
    pub count: u64,
    /// The largest spikes, largest |excess| first.
    pub largest: Vec<Spike>,
    #[serde(deserialize_with = "nan_if_null")]
    pub sz_um: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub sz_without_spikes_um: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub sz_effect_pct: f64,
    /// "keep" or "remove".
    pub policy: String,
    pub removed: u64,
}

/// One spike (an entry of the mesher's `outliers.largest`; the mesher's own type too).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Spike {
    pub row: usize,
    pub col: usize,
    /// Height, um relative to the map's z offset.
    #[serde(deserialize_with = "nan_if_null")]
    pub height_um: f64,
    /// Height above (+) or below (-) the median of its neighbours, um.
    #[serde(deserialize_with = "nan_if_null")]
    pub excess_um: f64,
}

/// The simulator a mesh was made for and what it imports (the mesher's `target`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EngineTargetRecord {
    /// "liggghts", "mercurydpm", "edem" or "yade".
    pub engine: String,
    /// ASCII (true) or binary STL.
    pub ascii: bool,
    /// A closed solid (true) or the open surface.
    pub solid: bool,
    /// The STL's length unit ("m", "mm", "um").
    pub units: String,
    /// "grid" or "adaptive".
    pub method: String,
    /// Most surface triangles the engine is given.
    pub max_triangles: u64,
    /// Smallest interior angle every triangle must have, degrees.
    pub min_angle_deg: f64,
}

/// What an adaptive mesh adds to the mesher's report.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AdaptiveMeshRecord {
    /// "solid" or "sheet".
    pub kind: String,
    pub offset_rule: String,
    pub surface_triangles: u64,
    pub missing_samples: u64,
    /// How missing samples were treated ("fill", "holes").
    pub missing: String,
    pub budget_reached: bool,
    pub fidelity: MeshFidelity,
    /// With an angle bound (an engine's target): the element quality of the mesh written, as
    /// the engines' grid sheets report theirs.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub element_quality: Option<AngleQuality>,
}

/// The angle bound's outcome as element quality (an adaptive mesh's `element_quality`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AngleQuality {
    #[serde(deserialize_with = "nan_if_null")]
    pub min_angle_deg: f64,
    pub min_angle_bound_deg: f64,
    pub below_bound: u64,
}

impl From<&AngleRecord> for AngleQuality {
    fn from(a: &AngleRecord) -> Self {
        Self {
            min_angle_deg: a.min_angle_deg,
            min_angle_bound_deg: a.bound_deg,
            below_bound: a.below_bound,
        }
    }
}

/// The element quality of an engine's regular-grid sheet (its `element_quality`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ElementQuality {
    /// Smallest interior angle of any triangle, degrees.
    pub min_angle_deg: f64,
    /// Most triangles sharing one vertex.
    pub max_triangles_per_vertex: u64,
    /// Triangles with the same three vertices as another.
    pub duplicate_triangles: u64,
}

/// What block averaging cost an engine's grid sheet: Sa, Sq, Sz, Sdr of the measured field and
/// of the meshed grid.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct GridSheetFidelity {
    pub measured: Option<LevelledParams>,
    pub meshed_grid: Option<LevelledParams>,
}

/// What an engine's regular-grid sheet (a target with `method = "grid"`) adds to the mesher's
/// report.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GridSheetRecord {
    /// "sheet".
    pub kind: String,
    /// Side of the blocks averaged into one grid sample.
    pub block_stride: u64,
    /// The meshed grid, [rows, cols].
    pub grid_rows_cols: [u64; 2],
    /// Sample spacing of the meshed grid, um (x, y).
    pub meshed_pitch_um: [f64; 2],
    pub element_quality: ElementQuality,
    pub fidelity: GridSheetFidelity,
}

/// The method's own part of the mesher's report, keyed beside the common fields: an adaptive
/// mesh or an engine's grid sheet (the full-grid solid has none). Untagged and flattened: the
/// two share key names (`kind`, `fidelity`) with different contents, and an untagged enum tries
/// each layout on every key, where a flattened struct would take the keys it knows.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum MeshMethodRecord {
    Adaptive(AdaptiveMeshRecord),
    GridSheet(GridSheetRecord),
}

/// The least-squares plane the mesher removed before meshing: z = `z_um` + `slope_x_um_per_um`
/// x + `slope_y_um_per_um` y, x and y in um from sample (0, 0) of the grid meshed along its
/// columns and rows, z absolute (um, the surface frame's z offset included).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FormPlane {
    pub z_um: f64,
    pub slope_x_um_per_um: f64,
    pub slope_y_um_per_um: f64,
}

/// The mesher's report.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MeshReport {
    /// The STL, relative to the out dir (a graph), its file name (the `mesh` verb) or its path
    /// as given (Python).
    #[serde(alias = "stl")]
    pub file: String,
    /// The input file and its format (the `mesh` verb; absent in a graph).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub input: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub input_format: Option<String>,
    /// The mesh re-sampled on the grid it meshed (`.npy`; a graph's).
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub resampled: String,
    /// The graph channel each input port read.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub sources: BTreeMap<String, String>,
    /// When the meshed frame was acquired and the STL written (ns, a graph's; absent: 0).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub t_acquired_ns: u64,
    #[serde(default, skip_serializing_if = "is_zero")]
    pub t_written_ns: u64,
    /// Seconds spent meshing (not writing).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mesh_s: Option<f64>,
    #[serde(default)]
    pub live_frames_skipped: u64,
    /// "binary" or "ascii".
    pub format: String,
    /// The STL's length unit ("mm", "um").
    pub units: String,
    /// scan_um = vertex * um_per_unit + offset_um.
    #[serde(deserialize_with = "nan_array")]
    pub offset_um: [f64; 3],
    pub triangles: u64,
    pub top_triangles: u64,
    pub vertices: u64,
    pub filled_samples: u64,
    pub base_depth_um: Option<f64>,
    pub watertight: bool,
    pub consistently_oriented: bool,
    /// Degenerate and duplicate triangles the closed-solid check found (absent: none).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub degenerate_triangles: u64,
    #[serde(default, skip_serializing_if = "is_zero")]
    pub duplicate_triangles: u64,
    /// [cols, rows] of the grid meshed.
    pub grid_px: [u64; 2],
    #[serde(deserialize_with = "nan_array")]
    pub pitch_um: [f64; 2],
    /// The surface meshed ("panorama", "pooled", ...; absent: a map from a file).
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub surface: String,
    /// The form removed before meshing ("least-squares plane"; absent: the mean only). The
    /// mesh and its tolerance are then of the levelled surface.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub form_removed: Option<String>,
    /// The plane removed (with `form_removed`): Table 6 levels the panorama by it instead of
    /// fitting its own (absent: none removed, or a report from before it was recorded).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub form_plane: Option<FormPlane>,
    /// The simulator the mesh was made for (absent: none named).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub target: Option<EngineTargetRecord>,
    /// "adaptive" or "grid".
    pub method: String,
    /// The adaptive mesh's or the engine grid sheet's own fields.
    #[serde(flatten)]
    pub method_record: Option<MeshMethodRecord>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tolerance: Option<ToleranceRecord>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub outliers: Option<OutliersRecord>,
}

fn is_zero(v: &u64) -> bool {
    *v == 0
}

impl MeshReport {
    /// The adaptive mesh's part (None for a grid).
    pub fn adaptive(&self) -> Option<&AdaptiveMeshRecord> {
        match &self.method_record {
            Some(MeshMethodRecord::Adaptive(a)) => Some(a),
            _ => None,
        }
    }
}

// ---------------------------------------------------------------------------------------
// Table 6 (run.json's `deviation`, written by the launcher's deviation pass)

/// Limits or tolerances on the three judged parameters, percent.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct JudgedPct {
    #[serde(rename = "Sa")]
    pub sa: f64,
    #[serde(rename = "Sq")]
    pub sq: f64,
    #[serde(rename = "Sz")]
    pub sz: f64,
}

impl JudgedPct {
    /// The same limit for the three.
    pub fn all(pct: f64) -> Self {
        Self {
            sa: pct,
            sq: pct,
            sz: pct,
        }
    }
    /// The limit of a judged parameter by name ("Sa", "Sq", "Sz").
    pub fn get(&self, name: &str) -> Option<f64> {
        match name {
            "Sa" => Some(self.sa),
            "Sq" => Some(self.sq),
            "Sz" => Some(self.sz),
            _ => None,
        }
    }
}

/// One region of Table 6, in panorama pixels.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RegionRecord {
    pub name: String,
    pub row0: usize,
    pub col0: usize,
    pub rows: usize,
    pub cols: usize,
}

/// The grid a stage was judged on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StageGrid {
    /// "panorama grid" or "own grid, N x N px cells".
    pub name: String,
    pub rows: usize,
    pub cols: usize,
    /// Panorama pixels per cell.
    pub cell_px: usize,
    pub pitch_x_um: f64,
    pub pitch_y_um: f64,
}

/// One stage in one region.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RegionDeviation {
    /// Null when no point is valid in both maps.
    pub measured: Option<Params>,
    pub model: Option<Params>,
    /// (model - measured) / measured * 100 per parameter, null where not finite.
    pub deviation_pct: BTreeMap<String, Option<f64>>,
    /// RMS of the pointwise difference / measured Sq * 100 (stages on the measured grid).
    pub residual_rms_pct_of_sq: Option<f64>,
    pub pass: bool,
}

impl RegionDeviation {
    /// The deviation of a parameter, percent, when finite.
    pub fn deviation(&self, name: &str) -> Option<f64> {
        self.deviation_pct.get(name).copied().flatten()
    }
}

/// One model stage over every region.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StageDeviation {
    /// By region name.
    pub regions: BTreeMap<String, RegionDeviation>,
    pub pass: bool,
    /// False: reported, not counted in the verdict.
    pub judged: bool,
    pub note: String,
    /// The measured file it is compared with.
    pub measured: String,
    pub limits_pct: JudgedPct,
    pub worst_region: Option<String>,
    pub worst_residual_rms_pct_of_sq: Option<f64>,
    pub grid: StageGrid,
}

/// Table 6: every model stage against the measurement.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Table6Record {
    pub measured: String,
    pub threshold_pct: f64,
    /// The model's tolerance when the mesher made it from one.
    pub model_tolerance_pct: Option<JudgedPct>,
    /// The judged parameters.
    pub judged: Vec<String>,
    pub conventions: String,
    pub regions: Vec<RegionRecord>,
    /// By stage name.
    pub stages: BTreeMap<String, StageDeviation>,
    pub pass: bool,
}

/// run.json's `deviation`: Table 6, or why it could not be computed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum DeviationRecord {
    Table(Box<Table6Record>),
    NotComputed { error: String },
}

// ---------------------------------------------------------------------------------------
// run.json

/// The graph that ran.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GraphRef {
    pub name: String,
    pub file: String,
}

/// A tile of run.json: the source's facts joined with the matcher's placement, on `index`
/// (only the source's when no matcher ran).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TileRecord {
    #[serde(flatten)]
    pub source: SourceTile,
    #[serde(flatten, default, skip_serializing_if = "Option::is_none")]
    pub placement: Option<TilePlacement>,
}

/// p50 / p95 / max in milliseconds, and the sample count.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Percentiles {
    pub p50: f64,
    pub p95: f64,
    pub max: f64,
    pub n: usize,
}

/// run.json's `latency_ms`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct LatencySummary {
    /// "tile_to_<stage>": acquisition of the causing tile -> the stage's live frame sent.
    #[serde(flatten)]
    pub end_to_end: BTreeMap<String, Percentiles>,
    /// "last_tile_to_final_<stage>": acquisition of the last tile -> the stage's final frame.
    pub final_frames: BTreeMap<String, Percentiles>,
    /// "<stage>_to_<stage>": between consecutive stages, for the same causing tile.
    pub hops: BTreeMap<String, Percentiles>,
    /// "<node> <- <port>": send -> receive of every channel.
    pub transport: BTreeMap<String, Percentiles>,
}

/// One node's message counts (run.json's `messages.<id>`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MessageCounts {
    /// Per input port.
    pub received: BTreeMap<String, u64>,
    /// Per output port.
    pub sent: BTreeMap<String, u64>,
    /// Per output port: the sum of the receiver counts of every send.
    pub deliveries: BTreeMap<String, u64>,
}

/// Peak resident memory (run.json's `peak_rss`), bytes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PeakRss {
    pub process_bytes: Option<u64>,
    pub nodes_bytes: BTreeMap<String, Option<u64>>,
    pub run_bytes_at_most: Option<u64>,
    pub memory_budget_gb: Option<f64>,
    /// Each node's share of the budget by node id (the memory plan's
    /// `node_shares_bytes`), bytes; empty without a budget.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub shares_bytes: BTreeMap<String, u64>,
    /// What went beyond the plan, one entry per node over its share (under `launch`) or the
    /// run's one process over the whole budget (under `run`, where every node's figure is
    /// that process's peak); empty when everything kept to the plan or without a budget.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub over_plan: Vec<OverPlan>,
    /// How the figures were measured.
    pub source: String,
}

/// One part of a run whose peak memory went beyond its share of the plan (run.json's
/// `peak_rss.over_plan`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OverPlan {
    /// A node id, or "run" for the one process of `surfstream run`.
    pub part: String,
    pub peak_bytes: u64,
    pub share_bytes: u64,
}

/// Which files a graph run keeps in its out dir (`--outputs`, a graph's `[outputs] set`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum OutputChoice {
    /// The model and what reads it: the STL, run.json, report.html with report_maps/, the
    /// small JSON records, logs; without the height-map arrays (.npy, .zarr, .x3p, the
    /// previews) and the recording (.mcap).
    Model,
    /// Every file the run writes.
    #[default]
    Full,
}

impl OutputChoice {
    /// Its name as written: "model" or "full".
    pub fn name(self) -> &'static str {
        match self {
            OutputChoice::Model => "model",
            OutputChoice::Full => "full",
        }
    }
}

impl std::fmt::Display for OutputChoice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for OutputChoice {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "model" => Ok(OutputChoice::Model),
            "full" => Ok(OutputChoice::Full),
            _ => Err(format!(
                "{s:?}: expected \"model\" (the STL, run.json, report.html and the small records) or \"full\" (every file)"
            )),
        }
    }
}

/// run.json's `outputs`: the set the run kept and what it removed of its own files at the end
/// (the arrays Table 6 and report.html read before they went).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OutputsRecord {
    pub set: OutputChoice,
    /// Paths relative to the out dir, sorted (a folder such as panorama.zarr by its name).
    pub removed: Vec<String>,
    pub removed_bytes: u64,
}

/// run.json.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunRecord {
    pub surfstream_version: String,
    /// "launch" or "run".
    pub mode: String,
    pub graph: GraphRef,
    /// Null when the graph has no replay node.
    pub scan: Option<ScanRecord>,
    pub tiles: Vec<TileRecord>,
    /// The matcher's pairs.
    pub pairs: Vec<MatcherPair>,
    pub latency_ms: LatencySummary,
    pub messages: BTreeMap<String, MessageCounts>,
    /// Each node's report by node id.
    pub stages: BTreeMap<String, Value>,
    /// Each node's parameters as run.
    pub parameters: BTreeMap<String, Value>,
    /// Every file of the out dir, sorted (report.html and report_maps/ come after it).
    pub files: Vec<String>,
    /// The output set and what it removed (absent in run.json written before issue 35: read
    /// as the full set).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub outputs: Option<OutputsRecord>,
    pub elapsed_s: f64,
    /// Table 6 (absent when no panorama was written).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub deviation: Option<DeviationRecord>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub peak_rss: Option<PeakRss>,
}

impl RunRecord {
    /// Reads run.json.
    pub fn read(path: &std::path::Path) -> Result<RunRecord, String> {
        let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
        serde_json::from_str(&text).map_err(|e| format!("{}: {e}", path.display()))
    }

    /// The first stage whose report reads as `T` (stages are keyed by node id, which the
    /// graph names; a node kind has one report type).
    pub fn stage<T: for<'de> Deserialize<'de>>(&self) -> Option<T> {
        self.stages.values().find_map(|v| T::deserialize(v).ok())
    }
}

// ---------------------------------------------------------------------------------------
// truth.json / ground_truth.json: where a simulated scan's tiles truly are

/// An (x, y) pair.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Xy {
    /// Along x (columns).
    pub x: f64,
    /// Along y (rows).
    pub y: f64,
}

/// One tile's truth: written by the simulated stage (`surfstream_replay::GroundTruth`, as
/// truth.json) and, in the same layout, by `bench/make_tiles.py` (ground_truth.json); read by
/// the matcher's scorer (`surfstream_io::truth::ScanTruth`) and the fusion comparison.
/// Fields in the order the stage has always written them (truth.json is written straight
/// from the struct, not through [`to_value`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TileTruth {
    /// Acquisition index.
    pub index: usize,
    /// Grid row.
    pub row: usize,
    /// Grid column.
    pub col: usize,
    /// Commanded position of pixel (0, 0), specimen px `[x, y]`.
    pub nominal_origin_px: [f64; 2],
    /// The same in um: what the stage reports.
    pub stage_position_um: [f64; 2],
    /// True position of pixel (0, 0), specimen px `[x, y]`.
    pub true_origin_px: [f64; 2],
    /// The same in um (NaN when read from a make_tiles.py file, which does not write it).
    #[serde(default = "nan_pair", deserialize_with = "nan_pair_if_null")]
    pub true_origin_um: [f64; 2],
    /// `true_origin_px - nominal_origin_px`.
    pub stage_error_px: [f64; 2],
    /// Piston, um.
    pub piston: f64,
    /// Tilt along x (height change across the tile), um.
    pub tilt_x: f64,
    /// Tilt along y, um.
    pub tilt_y: f64,
}

fn nan_pair() -> [f64; 2] {
    [f64::NAN; 2]
}

fn nan_pair_if_null<'de, D: Deserializer<'de>>(d: D) -> Result<[f64; 2], D::Error> {
    Ok(Option::<[f64; 2]>::deserialize(d)?.unwrap_or_else(nan_pair))
}

/// What surfstream reads of a truth file (truth.json, ground_truth.json): the pitch and the
/// tiles; the other keys (the conventions, the grid, the degradations, the pairs) are for
/// people, the Python scorer and the writer's own record.
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct TruthRecord {
    /// Pixel pitch in micrometres (absent in a file that does not say it).
    #[serde(default)]
    pub pixel_pitch_um: Option<Xy>,
    /// Tiles in acquisition order.
    pub tiles: Vec<TileTruth>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn placement() -> TilePlacement {
        TilePlacement {
            x_um: 1.5,
            y_um: -2.0,
            placed_by: "registration".into(),
            links_accepted: 1,
            links_tried: 2,
            quality: 0.9,
            piston_um: f64::NAN,
            tilt_x_um_per_px: 0.0,
            tilt_y_um_per_px: 0.0,
            streaming: StreamingPlacement {
                x_um: 1.0,
                y_um: -2.0,
                placed_by: "stage".into(),
                links_tried: 0,
                piston_um: 0.0,
                tilt_x_um_per_px: 0.0,
                tilt_y_um_per_px: 0.0,
            },
            registered_directions: Some(2),
            stage_direction: None,
        }
    }

    #[test]
    fn a_joined_tile_is_the_union_of_the_source_and_the_matcher_keys() {
        let t = TileRecord {
            source: SourceTile {
                index: 3,
                row: 1,
                col: 0,
                file: None,
                stage_x_um: 0.0,
                stage_y_um: 100.0,
            },
            placement: Some(placement()),
        };
        let v = to_value(&t).unwrap();
        let keys: Vec<&str> = v.as_object().unwrap().keys().map(String::as_str).collect();
        assert_eq!(
            keys,
            [
                "col",
                "index",
                "links_accepted",
                "links_tried",
                "piston_um",
                "placed_by",
                "quality",
                "registered_directions",
                "row",
                "stage_direction",
                "stage_x_um",
                "stage_y_um",
                "streaming",
                "tilt_x_um_per_px",
                "tilt_y_um_per_px",
                "x_um",
                "y_um"
            ]
        );
        // NaN is written as null and read back as NaN.
        assert_eq!(v["piston_um"], Value::Null);
        let back: TileRecord = from_value(&v, "tile").unwrap();
        assert!(back.placement.as_ref().unwrap().piston_um.is_nan());
        assert_eq!(back.source, t.source);
        // A source tile alone has no placement.
        let alone = json!({"index": 0, "row": 0, "col": 0, "stage_x_um": 0.0, "stage_y_um": 0.0});
        let t: TileRecord = from_value(&alone, "tile").unwrap();
        assert!(t.placement.is_none());
        assert_eq!(to_value(&t).unwrap(), alone);
    }

    #[test]
    fn the_scan_is_tagged_by_its_source_and_a_wrong_field_is_named() {
        let v = json!({"source": "mcap", "name": "n", "recording": "r.mcap", "topic": "t",
            "tiles": 4, "tile_width_px": 8, "tile_height_px": 6, "pitch_x_um": 1.0,
            "pitch_y_um": 1.0});
        let s: ScanRecord = from_value(&v, "scan").unwrap();
        assert_eq!(s.grid(), None);
        assert_eq!(s.tile_px(), (8, 6));
        assert_eq!(to_value(&s).unwrap(), v);
        let mut bad = v.clone();
        bad["tiles"] = json!("four");
        let e = from_value::<ScanRecord>(&bad, "run.json scan").unwrap_err();
        assert!(e.starts_with("run.json scan: "), "{e}");
    }

    #[test]
    fn table6_reads_back_with_unmeasured_parameters_and_an_error_is_its_own_variant() {
        let nine = |v: Value| {
            let keys = ["Sa", "Sq", "Sp", "Sv", "Sz", "Ssk", "Sku", "Sdq", "Sdr"];
            Value::Object(keys.iter().map(|k| (k.to_string(), v.clone())).collect())
        };
        let mut measured = nine(json!(1.5));
        measured["Ssk"] = Value::Null;
        let v = json!({ "measured": "panorama.npy", "threshold_pct": 5.0,
            "model_tolerance_pct": { "Sa": 1.0, "Sq": 1.0, "Sz": 3.0 },
            "judged": ["Sa", "Sq", "Sz"], "conventions": "c",
            "regions": [{ "name": "panorama", "row0": 0, "col0": 0, "rows": 4, "cols": 5 }],
            "stages": { "mesh": { "pass": false, "judged": true, "note": "n",
                "measured": "panorama.npy", "limits_pct": { "Sa": 1.0, "Sq": 1.0, "Sz": 3.0 },
                "worst_region": "panorama", "worst_residual_rms_pct_of_sq": null,
                "grid": { "name": "panorama grid", "rows": 4, "cols": 5, "cell_px": 1,
                    "pitch_x_um": 0.5, "pitch_y_um": 0.5 },
                "regions": { "panorama": { "measured": measured, "model": null,
                    "deviation_pct": { "Sa": 2.5, "Ssk": null },
                    "residual_rms_pct_of_sq": 40.0, "pass": false } } } },
            "pass": false });
        let d: DeviationRecord = from_value(&v, "deviation").unwrap();
        let DeviationRecord::Table(t) = &d else {
            panic!("a table reads as a table: {d:?}")
        };
        let r = &t.stages["mesh"].regions["panorama"];
        assert!(r.measured.unwrap().ssk.is_nan());
        assert_eq!(r.measured.unwrap().by_name("Sa"), Some(1.5));
        assert_eq!(
            (r.deviation("Sa"), r.deviation("Ssk"), r.deviation("Sz")),
            (Some(2.5), None, None)
        );
        assert_eq!(t.stages["mesh"].limits_pct.get("Sz"), Some(3.0));
        // Written back: the same value (NaN as null).
        assert_eq!(to_value(&d).unwrap(), v);
        let e = json!({ "error": "panorama.npy: no such file" });
        let d: DeviationRecord = from_value(&e, "deviation").unwrap();
        assert!(matches!(&d, DeviationRecord::NotComputed { error } if error.contains("no such")));
        assert_eq!(to_value(&d).unwrap(), e);
        // A table missing a field is not silently read as something else.
        let mut bad = v.clone();
        bad.as_object_mut().unwrap().remove("stages");
        assert!(from_value::<DeviationRecord>(&bad, "deviation").is_err());
    }

    fn grid_mesh() -> Value {
        json!({ "file": "surface.stl", "resampled": "mesh_resampled.npy",
            "sources": { "surface": "fusion/panorama" }, "t_acquired_ns": 1, "t_written_ns": 2,
            "live_frames_skipped": 0, "format": "binary", "units": "mm",
            "offset_um": [1.0, 2.0, 3.0], "triangles": 12, "top_triangles": 8, "vertices": 8,
            "filled_samples": 0, "base_depth_um": 10.0, "watertight": true,
            "consistently_oriented": true, "grid_px": [3, 2], "pitch_um": [0.5, 0.5],
            "surface": "panorama", "method": "grid" })
    }

    #[test]
    fn a_grid_mesh_has_no_adaptive_part_and_an_adaptive_one_reads_its_fidelity() {
        let g = grid_mesh();
        let m: MeshReport = from_value(&g, "mesher").unwrap();
        assert!(m.adaptive().is_none() && m.tolerance.is_none() && m.outliers.is_none());
        assert_eq!(to_value(&m).unwrap(), g);
        let mut a = grid_mesh();
        let extra = json!({ "method": "adaptive", "kind": "solid", "offset_rule": "r",
            "surface_triangles": 8, "missing_samples": 0, "missing": "fill",
            "budget_reached": false,
            "fidelity": { "epsilon_um": 0.1, "bound_met": true, "field": null,
                "mesh": { "sa_um": 1.0, "sq_um": 1.2, "sz_um": 5.0, "sdr_percent": null },
                "error": { "max_um": null, "rms_um": 0.01, "samples": 6, "uncovered": 0 } },
            "tolerance": { "tolerance": { "sa_pct": 1.0, "sq_pct": 1.0, "sz_pct": 3.0 },
                "target_share": 0.5, "region_px": 64, "regions": 1, "measured_px": 6,
                "met": true, "surface_triangles": 8, "triangles_per_measured_px": 1.3,
                "epsilon_um": 0.1, "reason": null,
                "region_fits": [{ "region": "whole", "samples": 6,
                    "measured_um": [1.0, 1.2, null], "deviation_pct": [0.1, -0.1, 0.0],
                    "residual_pct_of_sq": 20.0 }],
                "curve": [] } });
        for (k, v) in extra.as_object().unwrap() {
            a[k] = v.clone();
        }
        let m: MeshReport = from_value(&a, "mesher").unwrap();
        let f = m.adaptive().unwrap().fidelity;
        assert!(f.error.max_um.is_nan() && f.mesh.unwrap().sdr_percent.is_nan());
        assert!(m.tolerance.as_ref().unwrap().region_fits[0].measured_um[2].is_nan());
        assert_eq!(to_value(&m).unwrap(), a);
        // Not a mesher's report: no triangles.
        let mut other = grid_mesh();
        other.as_object_mut().unwrap().remove("triangles");
        assert!(from_value::<MeshReport>(&other, "mesher").is_err());
    }

    #[test]
    fn an_engine_grid_sheet_reads_as_its_own_part_beside_the_adaptive_one() {
        // The grid sheet shares `kind` and `fidelity` with the adaptive part, with other
        // contents: the untagged part must read each layout whole and write it back as it was.
        let mut g = grid_mesh();
        let extra = json!({ "target": { "engine": "edem", "ascii": false, "solid": true,
                "units": "mm", "method": "grid", "max_triangles": 1000000, "min_angle_deg": 1.0 },
            "kind": "sheet", "block_stride": 2,
            "grid_rows_cols": [2, 3], "meshed_pitch_um": [1.0, 1.0],
            "element_quality": { "min_angle_deg": 45.0, "max_triangles_per_vertex": 6,
                "duplicate_triangles": 0 },
            "fidelity": { "measured": { "sa_um": 1.0, "sq_um": 1.2, "sz_um": 5.0,
                "sdr_percent": 2.0 }, "meshed_grid": null } });
        for (k, v) in extra.as_object().unwrap() {
            g[k] = v.clone();
        }
        let m: MeshReport = from_value(&g, "mesher").unwrap();
        assert!(m.adaptive().is_none());
        assert_eq!(
            m.target
                .as_ref()
                .map(|t| (t.engine.as_str(), t.max_triangles)),
            Some(("edem", 1_000_000))
        );
        let Some(MeshMethodRecord::GridSheet(s)) = &m.method_record else {
            panic!("a grid sheet reads as one: {:?}", m.method_record)
        };
        assert_eq!(
            (s.block_stride, s.element_quality.max_triangles_per_vertex),
            (2, 6)
        );
        assert!(s.fidelity.meshed_grid.is_none());
        assert_eq!(to_value(&m).unwrap(), g);
        // An adaptive mesh with an angle bound carries the element quality of the bound.
        let mut a = grid_mesh();
        let extra = json!({ "method": "adaptive", "kind": "sheet", "offset_rule": "r",
            "surface_triangles": 8, "missing_samples": 0, "missing": "fill",
            "budget_reached": false,
            "element_quality": { "min_angle_deg": 1.5, "min_angle_bound_deg": 1.0,
                "below_bound": 0 },
            "fidelity": { "epsilon_um": 0.1, "bound_met": true, "field": null, "mesh": null,
                "error": { "max_um": 0.05, "rms_um": 0.01, "samples": 6, "uncovered": 0 } } });
        for (k, v) in extra.as_object().unwrap() {
            a[k] = v.clone();
        }
        let m: MeshReport = from_value(&a, "mesher").unwrap();
        let q = m.adaptive().and_then(|r| r.element_quality);
        assert_eq!(q.map(|q| q.min_angle_bound_deg), Some(1.0));
        assert_eq!(to_value(&m).unwrap(), a);
    }

    #[test]
    fn a_pair_writes_back_the_keys_it_was_read_with() {
        // Streaming's keys alone, then the global solve's (a null chosen alternative and a
        // NaN residual stay present, as null).
        let streamed = json!({ "a": 0, "b": 1, "direction": "horizontal",
            "nominal_offset_px": [900.0, 0.0], "offset_px": null, "ncc": 0.2,
            "peak_ratio": 1.1, "accepted": false, "reason": "low NCC" });
        let p: MatcherPair = from_value(&streamed, "pair").unwrap();
        assert!(!p.accepted_below_min_ncc && p.kept_by_global_solve.is_none());
        assert_eq!(to_value(&p).unwrap(), streamed);
        let mut solved = streamed.clone();
        for (k, v) in json!({ "final_offset_px": [900.5, 0.25], "z_samples": 40,
            "alternatives_px": [[900.0, 0.0], [880.0, 1.0]], "chosen_alternative": null,
            "kept_by_global_solve": false, "residual_px": [null, 0.5] })
        .as_object()
        .unwrap()
        {
            solved[k] = v.clone();
        }
        let p: MatcherPair = from_value(&solved, "pair").unwrap();
        assert_eq!(p.chosen_alternative, Some(None));
        assert!(p.residual_px.unwrap()[0].is_nan());
        assert_eq!(to_value(&p).unwrap(), solved);
    }

    #[test]
    fn the_spikes_read_back_as_spikes_and_write_back_as_they_were() {
        let mut a = grid_mesh();
        a["outliers"] = json!({ "rule": "8 sigma", "threshold_um": 0.4, "count": 2,
            "largest": [{ "row": 12, "col": 17, "height_um": 9.5, "excess_um": 9.0 },
                { "row": 3, "col": 0, "height_um": null, "excess_um": -2.5 }],
            "sz_um": 12.0, "sz_without_spikes_um": 3.0, "sz_effect_pct": 300.0,
            "policy": "remove", "removed": 2 });
        let m: MeshReport = from_value(&a, "mesher").unwrap();
        let o = m.outliers.as_ref().unwrap();
        assert_eq!((o.largest[0].row, o.largest[0].col), (12, 17));
        assert!(o.largest[1].height_um.is_nan() && o.largest[1].excess_um == -2.5);
        assert_eq!(to_value(&m).unwrap(), a);
        // A spike without its position is not a spike.
        a["outliers"]["largest"][0]
            .as_object_mut()
            .unwrap()
            .remove("row");
        assert!(from_value::<MeshReport>(&a, "mesher").is_err());
    }

    fn wavelet_final() -> Value {
        json!({ "wavelet": "db2", "mode": "symmetric", "level": 3, "level_min_energy": 2,
            "energy_curve": [{ "level": 1, "approx_energy_fraction": 0.9 },
                { "level": 2, "approx_energy_fraction": 0.5 }],
            "energy_curve_note": "n", "base_rmse": [{ "wavelet": "db2", "level": 3,
                "rmse_um": 1e-15 }], "base_rmse_note": "eq. 10",
            "pool": 4, "pool_op": "max",
            "pooling_bias": { "before": { "mean_um": 0.0, "sa_um": 1.0, "sq_um": 1.2,
                    "sz_um": 8.0 },
                "after": { "mean_um": 0.5, "sa_um": 0.9, "sq_um": 1.1, "sz_um": 6.0 },
                "shift": { "mean_um": 0.5, "sa_um": -0.1, "sq_um": -0.1, "sz_um": -2.0 } },
            "method": "wavelet", "equivalent_cutoff_um": 12.5, "equivalent_cutoff_y_um": null,
            "equivalent_cutoff_definition": "d", "warning": "lowered",
            "level_requested": 8, "panorama_px": [40, 30], "pooled_px": [10, 8],
            "files": ["datum.npy"], "streamed": true })
    }

    #[test]
    fn a_wavelet_final_summary_reads_its_level_and_writes_back_as_it_was() {
        let report = json!({ "live_patches": 3, "final": wavelet_final() });
        let r: WaveletReport = from_value(&report, "wavelet").unwrap();
        let f = r.final_pass.as_ref().unwrap();
        assert_eq!(f.separation.level(), Some(3));
        let MapSummary::Wavelet(w) = &f.separation else {
            panic!("a wavelet summary reads as one: {:?}", f.separation)
        };
        assert!(w.equivalent_cutoff_y_um.unwrap().is_nan());
        assert_eq!(w.choices.base_rmse.as_ref().unwrap()[0].wavelet, "db2");
        assert_eq!(f.panorama_px, [40, 30]);
        assert_eq!(to_value(&r).unwrap(), report);
        // Without a y cutoff, a base ranking or a warning, none is written back.
        let mut plain = wavelet_final();
        for k in ["equivalent_cutoff_y_um", "warning"] {
            plain.as_object_mut().unwrap().remove(k);
        }
        plain["base_rmse"] = Value::Null;
        plain["base_rmse_note"] = Value::Null;
        let f: FinalSummary = from_value(&plain, "final").unwrap();
        assert!(f.warning.is_none());
        assert_eq!(to_value(&f).unwrap(), plain);
        // Before the end of scan the summary is null.
        let early = json!({ "live_patches": 0, "final": null });
        let r: WaveletReport = from_value(&early, "wavelet").unwrap();
        assert!(r.final_pass.is_none());
        assert_eq!(to_value(&r).unwrap(), early);
        // A summary without its level is neither layout's.
        let mut broken = wavelet_final();
        broken.as_object_mut().unwrap().remove("level");
        assert!(from_value::<FinalSummary>(&broken, "final").is_err());
    }

    #[test]
    fn a_filter_final_summary_reads_as_the_filter_and_has_no_level() {
        let filter = json!({ "method": "gaussian", "cutoff_um": 80.0, "lambda_s_um": null,
            "plane_removed_um": [0.1, null, -0.2], "robust_iterations": null,
            "robust_converged": null, "pool": 4, "pool_op": "mean", "pooling_bias": null,
            "level_requested": null, "panorama_px": [40, 30], "pooled_px": [10, 8],
            "files": [], "streamed": false });
        let f: FinalSummary = from_value(&filter, "final").unwrap();
        let MapSummary::Filter(s) = &f.separation else {
            panic!("a filter summary reads as one: {:?}", f.separation)
        };
        assert!(s.plane_removed_um[1].is_nan());
        assert_eq!(f.separation.level(), None);
        assert_eq!(
            f.separation.datum_title(),
            "datum, gaussian lambda_c 80 um (um)"
        );
        assert_eq!(to_value(&f).unwrap(), filter);
    }

    #[test]
    fn output_choice_reads_its_two_names_and_run_json_without_outputs_is_full() {
        assert_eq!("model".parse::<OutputChoice>(), Ok(OutputChoice::Model));
        assert_eq!("full".parse::<OutputChoice>(), Ok(OutputChoice::Full));
        let e = "small".parse::<OutputChoice>().unwrap_err();
        assert!(
            e.contains("\"small\"") && e.contains("model") && e.contains("full"),
            "{e}"
        );
        let rec = OutputsRecord {
            set: OutputChoice::Model,
            removed: vec!["panorama.npy".into()],
            removed_bytes: 8,
        };
        let v = to_value(&rec).unwrap();
        assert_eq!(
            v,
            json!({ "set": "model", "removed": ["panorama.npy"], "removed_bytes": 8 })
        );
        assert_eq!(from_value::<OutputsRecord>(&v, "outputs"), Ok(rec));
        assert_eq!(OutputChoice::default(), OutputChoice::Full);
    }

    /// A map keyed by numbers pairs cannot be a JSON object; a custom `Serialize` may fail.
    #[test]
    fn a_record_that_cannot_be_serialized_is_an_error_not_null() {
        let by_pair: BTreeMap<(u32, u32), f64> = [((0, 1), 2.0)].into_iter().collect();
        let e = to_value(&by_pair).unwrap_err();
        assert!(e.to_string().contains("BTreeMap"), "{e}");
        assert!(e.to_string().contains("key must be a string"), "{e}");

        struct Refuses;
        impl Serialize for Refuses {
            fn serialize<S: serde::Serializer>(&self, _: S) -> Result<S::Ok, S::Error> {
                Err(serde::ser::Error::custom("no JSON for this one"))
            }
        }
        let e = to_value(&Refuses).unwrap_err();
        assert!(e.to_string().contains("Refuses"), "{e}");
        assert!(e.to_string().contains("no JSON for this one"), "{e}");
    }
}
