//! The replay node's source from its graph parameters ([`crate::config::Config`]):
//! `source = "simulated"` (the stage simulator), `"scan"` (a scan directory) or `"mcap"` (a
//! recording), each made into a [`StageRun`] plus the scan description that goes into
//! run.json.
//!
//! Files are only read here (a scan directory, a recording, a specimen .npy); what the run
//! writes (the truth, the specimen) is the node shell's.

use anyhow::{anyhow, bail, Result};
use surfstream_core::frame::{FrameHeader, FrameKind, HeightMap};
use surfstream_core::record::{ScanRecord, SourceTile};
use surfstream_core::{Sampling, Shape};
use surfstream_io::recording::{read_recording, Recorded};
use surfstream_runtime::graph::NodeContext;

pub use crate::config::SimulatedParams;
use crate::config::{Config, McapConfig, ScanConfig};
use crate::run::{StageRun, TileSource};
use crate::scan_dir::load_scan;
use crate::{generate_virtual_specimen, plan_scan, VirtualSpecimen};

/// A source ready to run, with what run.json says about it.
pub struct OpenedSource {
    pub run: StageRun,
    /// The scan: name, source, grid, tile size, pitch, ...
    pub scan: ScanRecord,
    /// One entry per tile in acquisition order: index, grid row / col, stage position.
    pub tiles: Vec<SourceTile>,
    /// The graph asked for the specimen to be saved beside the outputs (simulated only).
    pub save_specimen: bool,
}

impl OpenedSource {
    /// The simulated specimen (for `save_specimen`).
    pub fn specimen(&self) -> Option<&crate::VirtualSpecimen> {
        self.run.specimen()
    }
}

/// Opens the source the node's parameters name; errors name the graph and the node.
pub fn open_source(ctx: &NodeContext) -> Result<OpenedSource> {
    match Config::from_table(&ctx.params).map_err(|e| err_in(ctx, e))? {
        Config::Simulated(p) => simulated(ctx, p),
        Config::Scan(p) => scan(ctx, p),
        Config::Mcap(p) => mcap(ctx, p),
    }
}

/// `e` as said by this node: "graph 'G', node 'N': e".
pub(crate) fn err_in(ctx: &NodeContext, e: impl std::fmt::Display) -> anyhow::Error {
    anyhow!("graph '{}', node '{}': {e}", ctx.graph_name, ctx.node_id)
}

fn simulated(ctx: &NodeContext, params: SimulatedParams) -> Result<OpenedSource> {
    let pacing = params.pacing().map_err(|e| err_in(ctx, e))?;
    let SimulatedParams {
        save_specimen,
        specimen_file,
        stage,
        specimen: base,
        ..
    } = params;
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
    let (overlap_x, overlap_y) = stage.overlap_xy();
    let scan = ScanRecord::Simulated {
        name: ctx.graph_name.clone(),
        rows: stage.rows,
        cols: stage.cols,
        tile_width_px: tw,
        tile_height_px: th,
        pitch_x_um: stage.pitch_um,
        pitch_y_um: stage.pitch_um,
        overlap: [overlap_x, overlap_y],
        specimen: specimen_file
            .as_ref()
            .map(|p| p.display().to_string())
            .unwrap_or_else(|| "generated".into()),
        truth_file: "truth.json".into(),
    };
    let tiles = plan
        .tiles
        .iter()
        .map(|t| SourceTile {
            index: t.index as u32,
            row: t.row as u32,
            col: t.col as u32,
            file: None,
            stage_x_um: t.stage_position_um[0],
            stage_y_um: t.stage_position_um[1],
        })
        .collect();
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

fn scan(ctx: &NodeContext, p: ScanConfig) -> Result<OpenedSource> {
    let pacing = p.run_pacing().map_err(|e| err_in(ctx, e))?;
    let dir = load_scan(&p.path)?;
    let mut frames = Vec::with_capacity(dir.tiles.len());
    let mut tiles = Vec::with_capacity(dir.tiles.len());
    // Every tile's sampling but its origin (the tile's stage position).
    let tile = Sampling::of(
        Shape::new(dir.tile_height_px, dir.tile_width_px),
        dir.scan.pitch,
    );
    for (k, t) in dir.tiles.into_iter().enumerate() {
        let header = FrameHeader {
            kind: FrameKind::Tile as u32,
            tile_index: k as u32,
            tile_row: t.entry.row as u32,
            tile_col: t.entry.col as u32,
            z_offset_um: dir.z_offset_um,
            ..FrameHeader::at(&tile.with_origin(t.entry.stage_x_um, t.entry.stage_y_um)?)
        };
        tiles.push(SourceTile {
            index: k as u32,
            row: t.entry.row as u32,
            col: t.entry.col as u32,
            file: Some(t.entry.file.clone()),
            stage_x_um: t.entry.stage_x_um,
            stage_y_um: t.entry.stage_y_um,
        });
        frames.push(HeightMap {
            header,
            heights: t.heights_um,
        });
    }
    let scan = ScanRecord::Scan {
        name: dir.scan.name.clone(),
        manifest: dir.manifest_path.display().to_string(),
        rows: dir.scan.rows,
        cols: dir.scan.cols,
        tile_width_px: dir.tile_width_px,
        tile_height_px: dir.tile_height_px,
        pitch_x_um: dir.scan.pitch.x_um(),
        pitch_y_um: dir.scan.pitch.y_um(),
        height_unit: dir.scan.height_unit.clone(),
        z_offset_um: dir.z_offset_um,
    };
    Ok(OpenedSource {
        run: StageRun::new(TileSource::Frames(frames), pacing, Vec::new()),
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
    if f.heights.iter().all(|z| z.is_nan()) {
        bail!(
            "{at}: every one of its {} heights is NaN (not measured): expected a tile with measured points",
            f.heights.len()
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

fn mcap(ctx: &NodeContext, p: McapConfig) -> Result<OpenedSource> {
    let pacing = p.run_pacing().map_err(|e| err_in(ctx, e))?;
    // A FIFO or a device would block the reader forever.
    surfstream_io::input::check_regular_file(&p.path, "a .mcap recording")?;
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
        .map(|f| SourceTile {
            index: f.header.tile_index,
            row: f.header.tile_row,
            col: f.header.tile_col,
            file: None,
            stage_x_um: f.header.origin_x_um,
            stage_y_um: f.header.origin_y_um,
        })
        .collect();
    let scan = ScanRecord::Mcap {
        name: ctx.graph_name.clone(),
        recording: p.path.display().to_string(),
        topic: p.topic.clone(),
        tiles: frames.len(),
        tile_width_px: first.width as usize,
        tile_height_px: first.height as usize,
        pitch_x_um: first.pitch_x_um,
        pitch_y_um: first.pitch_y_um,
    };
    Ok(OpenedSource {
        run: StageRun::new(TileSource::Frames(frames), pacing, offsets_ns),
        scan,
        tiles,
        save_specimen: false,
    })
}
