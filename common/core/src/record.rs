//! Typed records (DESIGN §6): run.json and the node reports it is assembled from, as serde
//! structs shared by the writers (the nodes, the launcher) and the readers (the launcher's
//! run.json assembly, the verdict, Table 6's geometry, report.html), so the compiler ties a
//! field's writer to its readers.
//!
//! Key order: serde_json is built without `preserve_order`, so a JSON object is a sorted map
//! and every file surfstream wrote so far lists its keys alphabetically. Writers turn a record
//! into a value with [`to_value`] before writing it, which keeps that order whatever the
//! declaration order here (and keeps run.json byte-identical to the `json!` it replaces).
//!
//! What stays a JSON value inside a record, and why: the mesher's, the wavelet's final and the
//! finishing node's summaries (their fields depend on the method and the target, and they are
//! shown as they are), the matcher's pairs and global solve (the matcher's own diagnostics),
//! the fusion's chunk statistics (a fusion type), each node's parameters (the
//! graph file's table) and Table 6 (`deviation`, written and read by the launcher alone).

use std::collections::BTreeMap;

use serde::{Deserialize, Deserializer, Serialize};
use serde_json::Value;

use crate::metrology::Params;

/// A record as a JSON value with its keys sorted (how every report and run.json is written).
pub fn to_value<T: Serialize>(record: &T) -> Value {
    // Serializing these structs cannot fail (string keys, no custom serializers that error).
    serde_json::to_value(record).unwrap_or(Value::Null)
}

/// A record read back from a JSON value, the error naming what was expected.
pub fn from_value<T: for<'de> Deserialize<'de>>(value: &Value, what: &str) -> Result<T, String> {
    T::deserialize(value).map_err(|e| format!("{what}: {e}"))
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

/// The matcher's report.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MatcherReport {
    pub method: String,
    pub tiles: Vec<MatcherTile>,
    /// Every neighbour pair's registration and outcome (the matcher's own diagnostics).
    pub pairs: Vec<Value>,
    /// The global solve's summary (null until the end of scan).
    pub global: Value,
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
    /// The final pass's summary (fields depend on the method; null until the end of scan).
    #[serde(rename = "final")]
    pub final_pass: Value,
}

/// The recorder's report.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RecorderReport {
    pub file: Option<String>,
    /// Messages written per topic.
    pub messages: BTreeMap<String, u64>,
}

/// The two times the mesher's report carries for the latency table: the causing tile's
/// acquisition and the STL written (CLOCK_MONOTONIC, ns).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MeshWritten {
    pub t_acquired_ns: u64,
    pub t_written_ns: u64,
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
    /// How the figures were measured.
    pub source: String,
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
    pub pairs: Vec<Value>,
    pub latency_ms: LatencySummary,
    pub messages: BTreeMap<String, MessageCounts>,
    /// Each node's report by node id.
    pub stages: BTreeMap<String, Value>,
    /// Each node's parameters as run.
    pub parameters: BTreeMap<String, Value>,
    /// Every file of the out dir, sorted.
    pub files: Vec<String>,
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
        let v = to_value(&t);
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
        assert_eq!(to_value(&t), alone);
    }

    #[test]
    fn the_scan_is_tagged_by_its_source_and_a_wrong_field_is_named() {
        let v = json!({"source": "mcap", "name": "n", "recording": "r.mcap", "topic": "t",
            "tiles": 4, "tile_width_px": 8, "tile_height_px": 6, "pitch_x_um": 1.0,
            "pitch_y_um": 1.0});
        let s: ScanRecord = from_value(&v, "scan").unwrap();
        assert_eq!(s.grid(), None);
        assert_eq!(s.tile_px(), (8, 6));
        assert_eq!(to_value(&s), v);
        let mut bad = v.clone();
        bad["tiles"] = json!("four");
        let e = from_value::<ScanRecord>(&bad, "run.json scan").unwrap_err();
        assert!(e.starts_with("run.json scan: "), "{e}");
    }
}
