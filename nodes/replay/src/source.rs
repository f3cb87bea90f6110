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
use surfstream_core::frame::{FrameHeader, FrameKind, HeightMap};
use surfstream_core::record::{ScanRecord, SourceTile};
use surfstream_core::{Sampling, Shape};
use surfstream_io::recording::{read_recording, Recorded};
use surfstream_runtime::graph::{params_from_table, NodeContext};

use crate::run::{Pacing, StageRun, TileSource};
use crate::scan_dir::load_scan;
use crate::{generate_virtual_specimen, plan_scan, SpecimenParams, StageParams, VirtualSpecimen};

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

/// The simulated source's parameters. The graph gives them as one flat table; this is the one
/// place that splits it into the node's own keys, the specimen's ([`SpecimenParams`]) and the
/// stage's ([`StageParams`], which refuses any key left over), so the node and the launcher's
/// check before a run cannot drift apart.
#[derive(Debug, Clone)]
pub struct SimulatedParams {
    /// `pacing`: "realtime" (default) or "fast".
    pub pacing: String,
    /// `field_time_s`: seconds per field under real-time pacing (default 1).
    pub field_time_s: f64,
    /// `save_specimen`: render the whole specimen beside the outputs (default false).
    pub save_specimen: bool,
    /// `specimen`: a .npy height map (um) scanned instead of the generated specimen.
    pub specimen_file: Option<PathBuf>,
    /// The stage: grid, overlap, tile size, pitch, errors, seed.
    pub stage: StageParams,
    /// The generated specimen's settings; its size follows from the scan plan
    /// ([`crate::ScanPlan::specimen_params`]). The seed is the stage's.
    pub specimen: SpecimenParams,
}

impl SimulatedParams {
    /// Keys the node itself reads (the rest go to the stage or the specimen).
    pub const NODE_KEYS: &'static [&'static str] = &[
        "source",
        "pacing",
        "field_time_s",
        "save_specimen",
        "specimen",
    ];
    /// Keys of the generated specimen.
    pub const SPECIMEN_KEYS: &'static [&'static str] = &[
        "sa_um",
        "hurst",
        "correlation_length_um",
        "waviness_amplitude_um",
        "waviness_wavelength_um",
        "waviness_components",
        "form_sag_um",
        "roughness_period_px",
    ];

    /// Splits a `source = "simulated"` parameter table. Errors name the field (the caller adds
    /// the graph and the node).
    pub fn from_table(params: &toml::Table) -> Result<Self> {
        let mut stage_t = params.clone();
        let pacing = match stage_t.remove("pacing") {
            None => default_pacing(),
            Some(toml::Value::String(s)) => s,
            Some(_) => bail!("pacing: expected a string"),
        };
        let field_time_s = match stage_t.remove("field_time_s") {
            None => default_field_time_s(),
            Some(v) => v
                .as_float()
                .or_else(|| v.as_integer().map(|i| i as f64))
                .ok_or_else(|| anyhow!("field_time_s: expected a number of seconds"))?,
        };
        let save_specimen = match stage_t.remove("save_specimen") {
            None => false,
            Some(toml::Value::Boolean(b)) => b,
            Some(_) => bail!("save_specimen: expected true or false"),
        };
        let specimen_file = match stage_t.remove("specimen") {
            None => None,
            Some(toml::Value::String(s)) => Some(PathBuf::from(s)),
            Some(_) => bail!("specimen: expected a path to a .npy height map (um)"),
        };
        stage_t.remove("source");
        let mut spec_t = toml::Table::new();
        for k in Self::SPECIMEN_KEYS {
            if let Some(v) = stage_t.remove(*k) {
                spec_t.insert(k.to_string(), v);
            }
        }
        if let Some(seed) = params.get("seed") {
            spec_t.insert("seed".into(), seed.clone());
        }
        let stage: StageParams =
            params_from_table(&stage_t).map_err(|e| anyhow!("bad params: {e}"))?;
        let specimen: SpecimenParams =
            params_from_table(&spec_t).map_err(|e| anyhow!("bad params: {e}"))?;
        Ok(Self {
            pacing,
            field_time_s,
            save_specimen,
            specimen_file,
            stage,
            specimen,
        })
    }

    /// The pacing these parameters name.
    pub fn pacing(&self) -> Result<Pacing> {
        Pacing::from_name(&self.pacing, self.field_time_s).map_err(|e| anyhow!("{e}"))
    }

    /// Everything that can be checked without generating the specimen: the pacing, the scan
    /// plan, and (for a generated specimen) its settings at the size the plan needs.
    pub fn check(&self) -> Result<crate::ScanPlan> {
        self.pacing()?;
        let plan = plan_scan(&self.stage)?;
        if self.specimen_file.is_none() {
            plan.specimen_params(&self.specimen).validate()?;
        }
        Ok(plan)
    }
}

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
    let SimulatedParams {
        pacing,
        field_time_s,
        save_specimen,
        specimen_file,
        stage,
        specimen: base,
    } = SimulatedParams::from_table(&ctx.params).map_err(|e| err_in(ctx, e))?;
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

fn mcap(ctx: &NodeContext, p: McapParams) -> Result<OpenedSource> {
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
    let pacing = pacing_from(&p.pacing, 1.0, ctx)?;
    Ok(OpenedSource {
        run: StageRun::new(TileSource::Frames(frames), pacing, offsets_ns),
        scan,
        tiles,
        save_specimen: false,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The keys the README's graph table documents for `source = "simulated"`, read from the
    /// README itself, so a key documented there and refused here fails this test.
    fn documented_simulated_keys() -> Vec<String> {
        let readme = include_str!("../../../README.md");
        let row = readme
            .lines()
            .find(|l| l.starts_with("| `replay` |"))
            .expect("README.md has the replay row of the graph table");
        let start = row
            .find("`source = \"simulated\"`")
            .expect("the replay row documents source = \"simulated\"");
        let end = row
            .find("`source = \"scan\"`")
            .expect("the replay row documents source = \"scan\"");
        row[start..end]
            .split('`')
            .skip(1)
            .step_by(2)
            .filter(|k| !k.is_empty() && k.chars().all(|c| c.is_ascii_lowercase() || c == '_'))
            .map(str::to_string)
            .collect()
    }

    /// A valid value for every key of the simulated source (documented or not).
    fn sample_value(key: &str) -> Option<toml::Value> {
        use toml::Value::{Boolean, Float, Integer, String as Text};
        Some(match key {
            "rows" | "cols" => Integer(2),
            "overlap" | "overlap_x" => Float(0.1),
            "overlap_y" => Float(0.15),
            "tile_px" => Integer(256),
            "tile_width_px" | "tile_height_px" => Integer(256),
            "pitch_um" => Float(0.8148),
            "stage_sigma_px" => Float(3.0),
            "backlash_px" => Float(0.5),
            "piston_sigma_um" | "tilt_sigma_um" => Float(0.5),
            "noise_um" => Float(0.02),
            "dropout_fraction" => Float(0.002),
            "seed" => Integer(7),
            "pacing" => Text("fast".into()),
            "field_time_s" => Float(0.5),
            "specimen" => Text("specimen.npy".into()),
            "save_specimen" => Boolean(false),
            "sa_um" => Float(1.3),
            "hurst" => Float(0.8),
            "correlation_length_um" => Float(40.0),
            "waviness_amplitude_um" => Float(2.0),
            "waviness_wavelength_um" => Float(400.0),
            "waviness_components" => Integer(3),
            "form_sag_um" => Float(5.0),
            "roughness_period_px" => Integer(1024),
            _ => return None,
        })
    }

    fn table(keys: &[String]) -> toml::Table {
        let mut t = toml::Table::new();
        t.insert("source".into(), toml::Value::String("simulated".into()));
        for k in keys {
            let v = sample_value(k)
                .unwrap_or_else(|| panic!("documented key {k:?}: give it a sample value here"));
            t.insert(k.clone(), v);
        }
        t
    }

    #[test]
    fn every_documented_key_is_accepted_by_the_check() {
        let keys = documented_simulated_keys();
        // The README row lists at least the grid and the key whose copy once drifted.
        for k in ["rows", "cols", "pacing", "sa_um", "roughness_period_px"] {
            assert!(keys.iter().any(|d| d == k), "{k} not found in {keys:?}");
        }
        // With `specimen`, the generated specimen's settings are not checked: check both ways.
        let without_file: Vec<String> = keys.iter().filter(|k| *k != "specimen").cloned().collect();
        let p = SimulatedParams::from_table(&table(&without_file))
            .unwrap_or_else(|e| panic!("documented keys {without_file:?} refused: {e:#}"));
        p.check()
            .unwrap_or_else(|e| panic!("documented keys {without_file:?} fail the check: {e:#}"));
        assert_eq!(p.specimen.roughness_period_px, Some(1024));
        assert_eq!(
            p.specimen.seed, 7,
            "the stage's seed also seeds the specimen"
        );
        assert_eq!(p.stage.seed, 7);
        assert_eq!(p.pacing, "fast");
        let p = SimulatedParams::from_table(&table(&keys)).expect("all documented keys");
        p.check().expect("with a specimen file");
        assert_eq!(p.specimen_file, Some(PathBuf::from("specimen.npy")));
    }

    #[test]
    fn every_key_of_the_split_is_accepted() {
        let all: Vec<String> = SimulatedParams::NODE_KEYS
            .iter()
            .chain(SimulatedParams::SPECIMEN_KEYS)
            .filter(|k| **k != "source" && **k != "specimen")
            .map(|k| k.to_string())
            .collect();
        let p = SimulatedParams::from_table(&table(&all)).expect("every split key");
        p.check().expect("valid sample values");
    }

    #[test]
    fn an_unknown_or_mistyped_key_is_named() {
        let mut t = table(&["rows".to_string()]);
        t.insert("roughnes_period_px".into(), toml::Value::Integer(1024));
        let e = SimulatedParams::from_table(&t).unwrap_err().to_string();
        assert!(e.contains("roughnes_period_px"), "{e}");
        let mut t = table(&[]);
        t.insert("save_specimen".into(), toml::Value::Integer(1));
        let e = SimulatedParams::from_table(&t).unwrap_err().to_string();
        assert!(e.contains("save_specimen"), "{e}");
        let mut t = table(&[]);
        t.insert("roughness_period_px".into(), toml::Value::Integer(4));
        let e = SimulatedParams::from_table(&t)
            .expect("split")
            .check()
            .unwrap_err()
            .to_string();
        assert!(e.contains("roughness_period_px"), "{e}");
    }
}
