//! The replay node's source from its graph parameters: `source = "simulated"` (the stage
//! simulator: stage, specimen and pacing keys in one flat table), `"scan"` (a scan directory)
//! or `"mcap"` (a recording), each made into a [`StageRun`] plus the scan description that
//! goes into run.json.
//!
//! Files are only read here (a scan directory, a recording, a specimen .npy); what the run
//! writes (the truth, the specimen) is the node shell's.

use std::path::PathBuf;

use anyhow::{anyhow, bail, Result};
use serde::Deserialize;
use serde_json::json;
use surfstream_core::frame::{FrameHeader, FrameKind, HeightMap};
use surfstream_io::recording::{read_recording, Recorded};
use surfstream_runtime::graph::{params_from_table, NodeContext};

use crate::run::{Pacing, StageRun, TileSource};
use crate::scan_dir::load_scan;
use crate::{generate_virtual_specimen, plan_scan, SpecimenParams, StageParams, VirtualSpecimen};

/// A source ready to run, with what run.json says about it.
pub struct OpenedSource {
    pub run: StageRun,
    /// The scan: name, source, grid, tile size, pitch, ...
    pub scan: serde_json::Value,
    /// One entry per tile in acquisition order: index, grid row / col, stage position.
    pub tiles: Vec<serde_json::Value>,
    /// The graph asked for the specimen to be saved beside the outputs (simulated only).
    pub save_specimen: bool,
}

impl OpenedSource {
    /// The simulated specimen (for `save_specimen`).
    pub fn specimen(&self) -> Option<&crate::VirtualSpecimen> {
        self.run.specimen()
    }
}

fn default_pacing() -> String {
    "realtime".into()
}
fn default_field_time_s() -> f64 {
    1.0
}
fn fast() -> String {
    "fast".into()
}
fn original() -> String {
    "original".into()
}
fn default_topic() -> String {
    "stage/tiles".into()
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ScanParams {
    #[allow(dead_code)]
    source: String,
    path: PathBuf,
    #[serde(default = "fast")]
    pacing: String,
    #[serde(default = "default_field_time_s")]
    field_time_s: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct McapParams {
    #[allow(dead_code)]
    source: String,
    path: PathBuf,
    #[serde(default = "default_topic")]
    topic: String,
    #[serde(default = "original")]
    pacing: String,
}

/// Keys of the simulated source that are not stage parameters.
const SPECIMEN_KEYS: &[&str] = &[
    "sa_um",
    "hurst",
    "correlation_length_um",
    "waviness_amplitude_um",
    "waviness_wavelength_um",
    "waviness_components",
    "form_sag_um",
    "roughness_period_px",
];

/// Opens the source the node's parameters name; errors name the graph and the node.
pub fn open_source(ctx: &NodeContext) -> Result<OpenedSource> {
    let source = ctx
        .params
        .get("source")
        .and_then(|v| v.as_str())
        .ok_or_else(|| {
            anyhow!(
                "graph '{}', node '{}': params.source is missing: expected \"simulated\", \"scan\" or \"mcap\"",
                ctx.graph_name,
                ctx.node_id
            )
        })?
        .to_string();
    match source.as_str() {
        "simulated" => simulated(ctx),
        "scan" => scan(ctx, ctx.params()?),
        "mcap" => mcap(ctx, ctx.params()?),
        other => bail!(
            "graph '{}', node '{}': source = {other:?}: expected \"simulated\", \"scan\" or \"mcap\"",
            ctx.graph_name,
            ctx.node_id
        ),
    }
}

fn err_in(ctx: &NodeContext, e: impl std::fmt::Display) -> anyhow::Error {
    anyhow!("graph '{}', node '{}': {e}", ctx.graph_name, ctx.node_id)
}

fn pacing_from(name: &str, field_time_s: f64, ctx: &NodeContext) -> Result<Pacing> {
    Pacing::from_name(name, field_time_s).map_err(|e| anyhow!("node '{}': {e}", ctx.node_id))
}

fn simulated(ctx: &NodeContext) -> Result<OpenedSource> {
    // Split the flat parameter table: node keys, specimen keys, and the stage's own.
    let mut stage_t = ctx.params.clone();
    stage_t.remove("source");
    let pacing = stage_t
        .remove("pacing")
        .map(|v| v.as_str().map(str::to_string));
    let pacing = match pacing {
        None => default_pacing(),
        Some(Some(s)) => s,
        Some(None) => bail!(err_in(ctx, "pacing: expected a string")),
    };
    let field_time_s = match stage_t.remove("field_time_s") {
        None => default_field_time_s(),
        Some(v) => v
            .as_float()
            .or_else(|| v.as_integer().map(|i| i as f64))
            .ok_or_else(|| err_in(ctx, "field_time_s: expected a number of seconds"))?,
    };
    let save_specimen = match stage_t.remove("save_specimen") {
        None => false,
        Some(toml::Value::Boolean(b)) => b,
        Some(_) => bail!(err_in(ctx, "save_specimen: expected true or false")),
    };
    let specimen_file = match stage_t.remove("specimen") {
        None => None,
        Some(toml::Value::String(s)) => Some(PathBuf::from(s)),
        Some(_) => bail!(err_in(
            ctx,
            "specimen: expected a path to a .npy height map (um)"
        )),
    };
    let mut spec_t = toml::Table::new();
    for k in SPECIMEN_KEYS {
        if let Some(v) = stage_t.remove(*k) {
            spec_t.insert(k.to_string(), v);
        }
    }
    let stage: StageParams =
        params_from_table(&stage_t).map_err(|e| err_in(ctx, format!("bad params: {e}")))?;
    if let Some(seed) = ctx.params.get("seed") {
        spec_t.entry("seed").or_insert(seed.clone());
    }
    let base: SpecimenParams =
        params_from_table(&spec_t).map_err(|e| err_in(ctx, format!("bad params: {e}")))?;
    let plan = plan_scan(&stage).map_err(|e| err_in(ctx, e))?;
    let specimen = match &specimen_file {
        Some(path) => {
            let arr = surfstream_io::npy::read_npy(path)?;
            let shape = surfstream_core::raster::Shape::new(arr.rows, arr.cols);
            VirtualSpecimen::Raster(
                crate::Specimen::from_heights(arr.data, shape, stage.pitch_um)
                    .map_err(|e| anyhow!("{}: {e}", path.display()))?,
            )
        }
        None => {
            generate_virtual_specimen(&plan.specimen_params(&base)).map_err(|e| err_in(ctx, e))?
        }
    };
    plan.check_specimen(&specimen).map_err(|e| err_in(ctx, e))?;
    let (tw, th) = (plan.tile_width_px, plan.tile_height_px);
    let scan = json!({
        "name": ctx.graph_name,
        "source": "simulated",
        "rows": stage.rows,
        "cols": stage.cols,
        "tile_width_px": tw,
        "tile_height_px": th,
        "pitch_x_um": stage.pitch_um,
        "pitch_y_um": stage.pitch_um,
        "overlap": stage.overlap_xy(),
        "specimen": specimen_file.as_ref().map(|p| p.display().to_string()).unwrap_or_else(|| "generated".into()),
        "truth_file": "truth.json",
    });
    let tiles = plan
        .tiles
        .iter()
        .map(|t| {
            json!({ "index": t.index, "row": t.row, "col": t.col,
                    "stage_x_um": t.stage_position_um[0], "stage_y_um": t.stage_position_um[1] })
        })
        .collect();
    let pacing = pacing_from(&pacing, field_time_s, ctx)?;
    Ok(OpenedSource {
        run: StageRun::new(
            TileSource::Simulated {
                specimen,
                plan: Box::new(plan),
            },
            pacing,
            Vec::new(),
        ),
        scan,
        tiles,
        save_specimen,
    })
}

fn scan(ctx: &NodeContext, p: ScanParams) -> Result<OpenedSource> {
    let dir = load_scan(&p.path)?;
    let mut frames = Vec::with_capacity(dir.tiles.len());
    let mut tiles = Vec::with_capacity(dir.tiles.len());
    for (k, t) in dir.tiles.into_iter().enumerate() {
        let header = FrameHeader {
            kind: FrameKind::Tile as u32,
            tile_index: k as u32,
            tile_row: t.entry.row as u32,
            tile_col: t.entry.col as u32,
            width: dir.tile_width_px as u32,
            height: dir.tile_height_px as u32,
            pitch_x_um: dir.scan.pitch_x_um,
            pitch_y_um: dir.scan.pitch_y_um,
            origin_x_um: t.entry.stage_x_um,
            origin_y_um: t.entry.stage_y_um,
            z_offset_um: dir.z_offset_um,
            ..Default::default()
        };
        tiles.push(
            json!({ "index": k, "row": t.entry.row, "col": t.entry.col, "file": t.entry.file,
                           "stage_x_um": t.entry.stage_x_um, "stage_y_um": t.entry.stage_y_um }),
        );
        frames.push(HeightMap {
            header,
            heights: t.heights_um,
        });
    }
    let scan = json!({
        "name": dir.scan.name,
        "source": "scan",
        "manifest": dir.manifest_path.display().to_string(),
        "rows": dir.scan.rows,
        "cols": dir.scan.cols,
        "tile_width_px": dir.tile_width_px,
        "tile_height_px": dir.tile_height_px,
        "pitch_x_um": dir.scan.pitch_x_um,
        "pitch_y_um": dir.scan.pitch_y_um,
        "height_unit": dir.scan.height_unit,
        "z_offset_um": dir.z_offset_um,
    });
    Ok(OpenedSource {
        run: StageRun::new(
            TileSource::Frames(frames),
            pacing_from(&p.pacing, p.field_time_s, ctx)?,
            Vec::new(),
        ),
        scan,
        tiles,
        save_specimen: false,
    })
}

/// The guards a scan directory's tiles pass, for a recorded tile (a recording can be edited or
/// corrupt like any file): a plausible pitch, finite stage positions, a z offset and heights
/// within +-1 m ([`surfstream_io::formats::MAX_PLAUSIBLE_HEIGHT_UM`]). The error names the
/// recording, the tile and the field.
fn check_recorded_tile(path: &std::path::Path, topic: &str, k: usize, f: &HeightMap) -> Result<()> {
    use crate::scan_dir::{MAX_PITCH_UM, MIN_PITCH_UM};
    let at = format!(
        "{}: topic {topic:?}, tile #{} (index {})",
        path.display(),
        k + 1,
        f.header.tile_index
    );
    let h = &f.header;
    for (field, v) in [("pitch_x_um", h.pitch_x_um), ("pitch_y_um", h.pitch_y_um)] {
        if !(MIN_PITCH_UM..=MAX_PITCH_UM).contains(&v) {
            bail!("{at}: {field} = {v}: expected a pitch between {MIN_PITCH_UM} and {MAX_PITCH_UM} um");
        }
    }
    for (field, v) in [
        ("origin_x_um", h.origin_x_um),
        ("origin_y_um", h.origin_y_um),
    ] {
        if !v.is_finite() || v.abs() > 1e9 {
            bail!("{at}: {field} = {v}: expected a finite stage position within +-1 km (in um)");
        }
    }
    let limit = surfstream_io::formats::MAX_PLAUSIBLE_HEIGHT_UM;
    if !(h.z_offset_um.is_finite() && h.z_offset_um.abs() <= limit) {
        bail!(
            "{at}: z_offset_um = {:e}: expected a height within +-{limit:e} um (+-1 m): physically absurd for a profiler (a corrupt or edited recording)",
            h.z_offset_um
        );
    }
    let cols = (h.width as usize).max(1);
    let bad = f
        .heights
        .iter()
        .enumerate()
        .filter(|(_, z)| !z.is_nan() && (f64::from(**z) + h.z_offset_um).abs() > limit)
        .map(|(i, z)| (i, f64::from(*z) + h.z_offset_um));
    let mut count = 0usize;
    let mut first = None;
    for (i, z) in bad {
        count += 1;
        first.get_or_insert((i, z));
    }
    if let Some((i, z)) = first {
        bail!(
            "{at}: {count} height(s) beyond +-{limit:e} um, the first {z:.3e} um at row {}, col {}: physically absurd for a profiler (a corrupt point or a wrong unit)",
            i / cols,
            i % cols
        );
    }
    Ok(())
}

fn mcap(ctx: &NodeContext, p: McapParams) -> Result<OpenedSource> {
    // A FIFO or a device would block the reader forever.
    if !std::fs::metadata(&p.path).is_ok_and(|m| m.is_file()) {
        bail!(
            "{}: not a regular file: expected a .mcap recording",
            p.path.display()
        );
    }
    let rec = read_recording(&p.path)?;
    let mut frames = Vec::new();
    let mut offsets_ns = Vec::new();
    let mut first_log = None;
    for m in rec.messages.into_iter().filter(|m| m.topic == p.topic) {
        if let Recorded::Frame(f) = m.message {
            if f.header.has(surfstream_core::flags::END_OF_SCAN) {
                continue;
            }
            if f.header.kind() != Some(FrameKind::Tile) {
                bail!(
                    "{}: topic {:?} carries {} frames, expected tiles",
                    p.path.display(),
                    p.topic,
                    f.header.kind().map(|k| k.name()).unwrap_or("unknown")
                );
            }
            check_recorded_tile(&p.path, &p.topic, frames.len(), &f)?;
            let t0 = *first_log.get_or_insert(m.log_time_ns);
            offsets_ns.push(m.log_time_ns.saturating_sub(t0));
            frames.push(f);
        }
    }
    let Some(first) = frames.first().map(|f| f.header) else {
        let topics: Vec<_> = rec.channels.iter().map(|c| c.topic.clone()).collect();
        bail!(
            "{}: no tile frames on topic {:?}; the recording has topics {:?}",
            p.path.display(),
            p.topic,
            topics
        );
    };
    let tiles = frames
        .iter()
        .map(|f| {
            json!({ "index": f.header.tile_index, "row": f.header.tile_row, "col": f.header.tile_col,
                    "stage_x_um": f.header.origin_x_um, "stage_y_um": f.header.origin_y_um })
        })
        .collect();
    let scan = json!({
        "name": ctx.graph_name,
        "source": "mcap",
        "recording": p.path.display().to_string(),
        "topic": p.topic,
        "tiles": frames.len(),
        "tile_width_px": first.width,
        "tile_height_px": first.height,
        "pitch_x_um": first.pitch_x_um,
        "pitch_y_um": first.pitch_y_um,
    });
    let pacing = pacing_from(&p.pacing, 1.0, ctx)?;
    Ok(OpenedSource {
        run: StageRun::new(TileSource::Frames(frames), pacing, offsets_ns),
        scan,
        tiles,
        save_specimen: false,
    })
}
