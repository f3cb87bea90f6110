//! The replay node: the graph's source of tiles, from a simulated stage, a scan directory or
//! an MCAP recording, paced like the instrument or as fast as possible.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};
use serde::Deserialize;
use serde_json::json;
use surfstream_core::frame::{monotonic_ns, FrameHeader, FrameKind, HeightMap};
use surfstream_io::recording::{read_recording, Recorded};
use surfstream_runtime::graph::{params_from_table, NodeContext};
use surfstream_runtime::node::{Input, NodeLogic, Outbox};

use crate::scan_dir::load_scan;
use crate::{
    acquire_tile, generate_specimen, plan_scan, truth_for, ScanPlan, Specimen, SpecimenParams,
    StageParams,
};

const PORT: &str = "tiles";

/// Where tiles come from.
enum Source {
    Simulated {
        specimen: Specimen,
        plan: Box<ScanPlan>,
    },
    /// Tiles already in memory (scan directory, recording), with their headers.
    Frames(Vec<HeightMap>),
}

/// When to emit the next tile.
#[derive(Debug, Clone, Copy)]
enum Pacing {
    Fast,
    /// One field every `field_time`, like the instrument.
    Fixed(Duration),
    /// The recording's own gaps (log times, ns since the first message).
    Original,
}

pub struct ReplayNode {
    source: Source,
    pacing: Pacing,
    /// Original-timing offsets per tile (recordings only).
    offsets_ns: Vec<u64>,
    started: Option<Instant>,
    next: usize,
    done: bool,
    scan: serde_json::Value,
    tiles: Vec<serde_json::Value>,
}

fn pacing_from(name: &str, field_time_s: f64, ctx: &NodeContext) -> Result<Pacing> {
    Ok(match name {
        "fast" => Pacing::Fast,
        "realtime" => {
            if !(field_time_s.is_finite() && field_time_s > 0.0) {
                bail!("node '{}': field_time_s = {field_time_s}: expected seconds > 0", ctx.node_id);
            }
            Pacing::Fixed(Duration::from_secs_f64(field_time_s))
        }
        "original" => Pacing::Original,
        other => bail!(
            "node '{}': pacing = {other:?}: expected \"realtime\" (field_time_s per field), \"fast\", or \"original\" (recordings)",
            ctx.node_id
        ),
    })
}

fn default_pacing() -> String {
    "realtime".into()
}
fn default_field_time_s() -> f64 {
    1.0
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

fn fast() -> String {
    "fast".into()
}
fn original() -> String {
    "original".into()
}
fn default_topic() -> String {
    "stage/tiles".into()
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
];

/// Builds the node from its graph parameters.
pub fn build(ctx: &NodeContext) -> Result<Box<dyn NodeLogic + Send>> {
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
    let node: ReplayNode = match source.as_str() {
        "simulated" => simulated(ctx)?,
        "scan" => {
            let p: ScanParams = ctx.params()?;
            scan(ctx, p)?
        }
        "mcap" => {
            let p: McapParams = ctx.params()?;
            mcap(ctx, p)?
        }
        other => bail!(
            "graph '{}', node '{}': source = {other:?}: expected \"simulated\", \"scan\" or \"mcap\"",
            ctx.graph_name,
            ctx.node_id
        ),
    };
    Ok(Box::new(node))
}

fn err_in(ctx: &NodeContext, e: impl std::fmt::Display) -> anyhow::Error {
    anyhow!("graph '{}', node '{}': {e}", ctx.graph_name, ctx.node_id)
}

fn simulated(ctx: &NodeContext) -> Result<ReplayNode> {
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
            Specimen::from_heights(arr.data, arr.cols, arr.rows, stage.pitch_um)
                .map_err(|e| anyhow!("{}: {e}", path.display()))?
        }
        None => generate_specimen(&plan.specimen_params(&base)).map_err(|e| err_in(ctx, e))?,
    };
    plan.check_specimen(&specimen).map_err(|e| err_in(ctx, e))?;
    // The truth beside the outputs, so users and tests can score the result.
    std::fs::create_dir_all(&ctx.out_dir)
        .with_context(|| format!("{}: cannot create", ctx.out_dir.display()))?;
    let truth_path = ctx.out_dir.join("truth.json");
    let truth = truth_for(&plan);
    surfstream_core::fsutil::write_atomic(&truth_path, |w| {
        serde_json::to_writer_pretty(w, &truth)
            .map_err(|e| anyhow!("{}: {e}", truth_path.display()))
    })?;
    if save_specimen {
        // The whole virtual part, so a test or a user can compare the panorama with it.
        let path = ctx.out_dir.join("specimen.npy");
        surfstream_io::npy::write_npy_f32(
            &path,
            &specimen.heights,
            specimen.height,
            specimen.width,
        )?;
    }
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
    Ok(ReplayNode::new(
        Source::Simulated {
            specimen,
            plan: Box::new(plan),
        },
        pacing_from(&pacing, field_time_s, ctx)?,
        Vec::new(),
        scan,
        tiles,
    ))
}

fn scan(ctx: &NodeContext, p: ScanParams) -> Result<ReplayNode> {
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
    Ok(ReplayNode::new(
        Source::Frames(frames),
        pacing_from(&p.pacing, p.field_time_s, ctx)?,
        Vec::new(),
        scan,
        tiles,
    ))
}

fn mcap(ctx: &NodeContext, p: McapParams) -> Result<ReplayNode> {
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
            let t0 = *first_log.get_or_insert(m.log_time_ns);
            offsets_ns.push(m.log_time_ns.saturating_sub(t0));
            frames.push(f);
        }
    }
    if frames.is_empty() {
        let topics: Vec<_> = rec.channels.iter().map(|c| c.topic.clone()).collect();
        bail!(
            "{}: no tile frames on topic {:?}; the recording has topics {:?}",
            p.path.display(),
            p.topic,
            topics
        );
    }
    let first = frames[0].header;
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
    Ok(ReplayNode::new(
        Source::Frames(frames),
        pacing,
        offsets_ns,
        scan,
        tiles,
    ))
}

impl ReplayNode {
    fn new(
        source: Source,
        pacing: Pacing,
        offsets_ns: Vec<u64>,
        scan: serde_json::Value,
        tiles: Vec<serde_json::Value>,
    ) -> Self {
        ReplayNode {
            source,
            pacing,
            offsets_ns,
            started: None,
            next: 0,
            done: false,
            scan,
            tiles,
        }
    }

    fn tile_count(&self) -> usize {
        match &self.source {
            Source::Simulated { plan, .. } => plan.tiles.len(),
            Source::Frames(f) => f.len(),
        }
    }

    fn acquire(&mut self, k: usize) -> HeightMap {
        match &mut self.source {
            Source::Simulated { specimen, plan } => {
                let t = &plan.tiles[k];
                let heights = acquire_tile(specimen, t, &plan.params);
                let header = FrameHeader {
                    kind: FrameKind::Tile as u32,
                    tile_index: k as u32,
                    tile_row: t.row as u32,
                    tile_col: t.col as u32,
                    width: plan.tile_width_px as u32,
                    height: plan.tile_height_px as u32,
                    pitch_x_um: plan.params.pitch_um,
                    pitch_y_um: plan.params.pitch_um,
                    origin_x_um: t.stage_position_um[0],
                    origin_y_um: t.stage_position_um[1],
                    ..Default::default()
                };
                HeightMap { header, heights }
            }
            // Move the tile out: it is sent once.
            Source::Frames(f) => std::mem::replace(
                &mut f[k],
                HeightMap {
                    header: FrameHeader::default(),
                    heights: Vec::new(),
                },
            ),
        }
    }
}

impl NodeLogic for ReplayNode {
    fn on_input(&mut self, port: &str, _: Input<'_>, _: &mut Outbox) -> Result<()> {
        bail!("the replay node has no inputs (got a message on '{port}')")
    }

    fn on_drained(&mut self, _: &mut Outbox) -> Result<()> {
        Ok(())
    }

    fn next_wakeup(&self) -> Option<Instant> {
        if self.done {
            return None;
        }
        let Some(t0) = self.started else {
            return Some(Instant::now());
        };
        Some(match self.pacing {
            Pacing::Fast => Instant::now(),
            Pacing::Fixed(d) => t0 + d * self.next as u32,
            Pacing::Original => {
                t0 + Duration::from_nanos(self.offsets_ns.get(self.next).copied().unwrap_or(0))
            }
        })
    }

    fn on_timer(&mut self, out: &mut Outbox) -> Result<()> {
        self.started.get_or_insert_with(Instant::now);
        let k = self.next;
        let mut tile = self.acquire(k);
        tile.header.t_acquired_ns = monotonic_ns();
        out.send_frame(PORT, tile);
        self.next += 1;
        if self.next == self.tile_count() {
            out.end_frames(PORT, k as u32, monotonic_ns());
            self.done = true;
        }
        Ok(())
    }

    fn finished(&self) -> bool {
        self.done
    }

    fn report(&self) -> serde_json::Value {
        let mut sent = BTreeMap::new();
        sent.insert("tiles", self.next);
        json!({ "scan": self.scan, "tiles": self.tiles, "sent": sent })
    }
}
