//! The replay node's one front door: [`Config`], its graph parameters typed, one variant per
//! source (`source = "simulated"`, `"scan"` or `"mcap"`), with every default stated here
//! once. The node opens its source from it ([`crate::source::open_source`]) and the launcher's
//! checks before a run, its free-space estimate and its progress lines read it too, so no key
//! is read by name outside this file and the two cannot drift apart.
//!
//! Nothing here reads a tile; [`Config::check`] only looks at whether the source's file is
//! there (and plans the simulated scan without generating its specimen).

use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Result};
use serde::{Deserialize, Serialize};
use surfstream_runtime::graph::params_from_table;

use crate::run::{Pacing, MAX_FIELD_TIME_S};
use crate::{plan_scan, ScanPlan, SpecimenParams, StageParams};

/// Seconds per field under real-time pacing when the graph gives none.
pub const DEFAULT_FIELD_TIME_S: f64 = 1.0;

/// A recording's tile topic when the graph names none (what the recorder writes the replay's
/// tiles under).
pub const DEFAULT_TOPIC: &str = "stage/tiles";

/// The sources, as `source = "..."` names them (the message when it names none of them).
const SOURCES: &str = "expected \"simulated\", \"scan\" or \"mcap\"";

/// How the tiles are released, as a graph names it (`pacing = "..."`); with `field_time_s` it
/// becomes the run's [`Pacing`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PacingChoice {
    /// One field every `field_time_s`, like the instrument (the simulated stage's default).
    Realtime,
    /// As fast as the graph takes them (a scan directory's default).
    Fast,
    /// A recording's own gaps (a recording's default).
    Original,
}

impl std::str::FromStr for PacingChoice {
    type Err = String;
    fn from_str(name: &str) -> Result<Self, String> {
        match name {
            "realtime" => Ok(Self::Realtime),
            "fast" => Ok(Self::Fast),
            "original" => Ok(Self::Original),
            other => Err(format!(
                "{other:?}: expected \"realtime\" (field_time_s per field), \"fast\", or \"original\" (recordings)"
            )),
        }
    }
}

impl PacingChoice {
    /// The choice a name gives; the error names the key and what was expected (the same
    /// words for every source).
    pub fn from_name(name: &str) -> Result<Self, String> {
        name.parse().map_err(|e| format!("pacing = {e}"))
    }

    /// The run's pacing: real time at `field_time_s` per field, bounded (1e20 s does not fit
    /// a Duration, and no stage takes a month per field).
    pub fn pacing(self, field_time_s: f64) -> Result<Pacing, String> {
        Ok(match self {
            Self::Fast => Pacing::Fast,
            Self::Original => Pacing::Original,
            Self::Realtime => {
                if !(field_time_s > 0.0 && field_time_s <= MAX_FIELD_TIME_S) {
                    return Err(format!(
                        "field_time_s = {field_time_s}: expected seconds > 0 and at most {MAX_FIELD_TIME_S} (30 days)"
                    ));
                }
                Pacing::Fixed(std::time::Duration::from_secs_f64(field_time_s))
            }
        })
    }

    // The defaults per source, for serde.
    fn realtime() -> Self {
        Self::Realtime
    }
    fn fast() -> Self {
        Self::Fast
    }
    fn original() -> Self {
        Self::Original
    }
}

fn default_field_time_s() -> f64 {
    DEFAULT_FIELD_TIME_S
}

fn default_topic() -> String {
    DEFAULT_TOPIC.into()
}

/// The replay node's parameters: one variant per source, named by the table's `source` key.
// One value per node, read once: the variants' sizes do not matter.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone)]
pub enum Config {
    /// `source = "simulated"`: the stage simulator.
    Simulated(SimulatedParams),
    /// `source = "scan"`: a scan directory (`scan.toml` and its tiles).
    Scan(ScanConfig),
    /// `source = "mcap"`: a recording.
    Mcap(McapConfig),
}

/// `source = "scan"`: a scan directory.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScanConfig {
    /// `path`: a scan.toml or the folder holding one.
    pub path: PathBuf,
    /// `pacing`: "fast" (default), "realtime" or "original".
    #[serde(
        default = "PacingChoice::fast",
        deserialize_with = "surfstream_core::choice::from_text"
    )]
    pub pacing: PacingChoice,
    /// `field_time_s`: seconds per field under real-time pacing (default 1).
    #[serde(default = "default_field_time_s")]
    pub field_time_s: f64,
}

impl ScanConfig {
    /// The run's pacing.
    pub fn run_pacing(&self) -> Result<Pacing> {
        self.pacing
            .pacing(self.field_time_s)
            .map_err(|e| anyhow!("{e}"))
    }

    /// The manifest itself: `path`, or the scan.toml in it when it is a folder.
    pub fn manifest(&self) -> PathBuf {
        if self.path.is_dir() {
            self.path.join("scan.toml")
        } else {
            self.path.clone()
        }
    }
}

/// `source = "mcap"`: a recording.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct McapConfig {
    /// `path`: the .mcap recording.
    pub path: PathBuf,
    /// `topic`: the tiles' topic (default "stage/tiles").
    #[serde(default = "default_topic")]
    pub topic: String,
    /// `pacing`: "original" (default), "fast" or "realtime" (one field per second: a
    /// recording takes no `field_time_s`).
    #[serde(
        default = "PacingChoice::original",
        deserialize_with = "surfstream_core::choice::from_text"
    )]
    pub pacing: PacingChoice,
}

impl McapConfig {
    /// The run's pacing (real time is one field per second).
    pub fn run_pacing(&self) -> Result<Pacing> {
        self.pacing
            .pacing(DEFAULT_FIELD_TIME_S)
            .map_err(|e| anyhow!("{e}"))
    }
}

impl Config {
    /// The node's parameter table as its source's parameters. Errors name the field (the
    /// caller adds the graph and the node).
    pub fn from_table(params: &toml::Table) -> Result<Self> {
        let source = match params.get("source") {
            None => bail!("params.source is missing: {SOURCES}"),
            Some(toml::Value::String(s)) => s.as_str(),
            Some(other) => bail!("params.source = {other}: {SOURCES}"),
        };
        match source {
            "simulated" => Ok(Self::Simulated(SimulatedParams::from_table(params)?)),
            "scan" => Ok(Self::Scan(file_source(
                params,
                "a scan.toml or its directory",
            )?)),
            "mcap" => Ok(Self::Mcap(file_source(params, "a .mcap recording")?)),
            other => bail!("params.source = {other:?}: {SOURCES}"),
        }
    }

    /// The pacing the parameters name (a recording's real time is one field per second).
    pub fn pacing(&self) -> Result<Pacing> {
        match self {
            Self::Simulated(p) => p.pacing(),
            Self::Scan(s) => s.run_pacing(),
            Self::Mcap(m) => m.run_pacing(),
        }
    }

    /// Everything that can be checked before a run without reading tiles: the pacing, the
    /// simulated scan's plan and specimen settings, and that a scan's manifest or a recording
    /// is a regular file (a folder, FIFO or device is named for what it is, issue 36).
    pub fn check(&self) -> Result<()> {
        match self {
            Self::Simulated(p) => p.check().map(drop),
            Self::Scan(s) => {
                self.pacing()?;
                regular_file(&s.path, &s.manifest(), "a scan.toml or its directory")
            }
            Self::Mcap(m) => {
                self.pacing()?;
                regular_file(&m.path, &m.path, "a .mcap recording")
            }
        }
    }
}

/// A scan's or a recording's table without its `source`; a missing `path` is named with what
/// it should be.
fn file_source<T: serde::de::DeserializeOwned>(params: &toml::Table, expected: &str) -> Result<T> {
    if !params.contains_key("path") {
        bail!("params.path is missing: expected {expected}");
    }
    let mut t = params.clone();
    t.remove("source");
    params_from_table(&t).map_err(|e| anyhow!("params.{e}"))
}

/// `file` (the manifest `path` names, or `path` itself) is a regular file.
fn regular_file(path: &Path, file: &Path, expected: &str) -> Result<()> {
    surfstream_io::input::check_regular_file(file, expected)
        .map_err(|e| anyhow!("params.path = {:?}: {e}", path.display().to_string()))
}

/// The simulated source's parameters. The graph gives them as one flat table; this is the one
/// place that splits it into the node's own keys, the specimen's ([`SpecimenParams`]) and the
/// stage's ([`StageParams`], which refuses any key left over), so the node and the launcher's
/// check before a run cannot drift apart.
#[derive(Debug, Clone)]
pub struct SimulatedParams {
    /// `pacing`: "realtime" (default), "fast" or "original".
    pub pacing: PacingChoice,
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
            None => PacingChoice::realtime(),
            Some(toml::Value::String(s)) => PacingChoice::from_name(&s).map_err(|e| anyhow!(e))?,
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
        self.pacing
            .pacing(self.field_time_s)
            .map_err(|e| anyhow!("{e}"))
    }

    /// Everything that can be checked without generating the specimen: the pacing, the scan
    /// plan, and (for a generated specimen) its settings at the size the plan needs.
    pub fn check(&self) -> Result<ScanPlan> {
        self.pacing()?;
        let plan = plan_scan(&self.stage)?;
        if self.specimen_file.is_none() {
            plan.specimen_params(&self.specimen).validate()?;
        }
        Ok(plan)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> toml::Table {
        toml::from_str(text).expect("a TOML table")
    }

    #[test]
    fn each_source_gets_its_defaults_from_one_place() {
        let Config::Scan(s) =
            Config::from_table(&parse("source = \"scan\"\npath = \"d\"")).unwrap()
        else {
            panic!("not a scan");
        };
        assert_eq!((s.pacing, s.field_time_s), (PacingChoice::Fast, 1.0));
        let Config::Mcap(m) =
            Config::from_table(&parse("source = \"mcap\"\npath = \"r.mcap\"")).unwrap()
        else {
            panic!("not a recording");
        };
        assert_eq!(
            (m.pacing, m.topic.as_str()),
            (PacingChoice::Original, "stage/tiles")
        );
        let Config::Simulated(p) = Config::from_table(&parse("source = \"simulated\"")).unwrap()
        else {
            panic!("not simulated");
        };
        assert_eq!((p.pacing, p.field_time_s), (PacingChoice::Realtime, 1.0));
        assert!(matches!(
            Config::Simulated(p).pacing().unwrap(),
            Pacing::Fixed(d) if d.as_secs_f64() == 1.0
        ));
    }

    #[test]
    fn a_wrong_source_path_or_pacing_is_named_with_what_was_expected() {
        let e = |text: &str| format!("{:#}", Config::from_table(&parse(text)).unwrap_err());
        let missing = e("rows = 1");
        assert!(
            missing.contains("params.source is missing: expected \"simulated\""),
            "{missing}"
        );
        let tape = e("source = \"tape\"");
        assert!(
            tape.contains("params.source = \"tape\": expected"),
            "{tape}"
        );
        let number = e("source = 3");
        assert!(number.contains("params.source = 3"), "{number}");
        let no_path = e("source = \"mcap\"");
        assert!(
            no_path.contains("params.path is missing: expected a .mcap recording"),
            "{no_path}"
        );
        let slow = e("source = \"scan\"\npath = \"d\"\npacing = \"slow\"");
        // The same words whichever the source.
        assert!(
            slow.contains("params.pacing: \"slow\": expected \"realtime\""),
            "{slow}"
        );
        let slow = e("source = \"simulated\"\npacing = \"slow\"");
        assert!(
            slow.contains("pacing = \"slow\": expected \"realtime\""),
            "{slow}"
        );
        let seconds = e("source = \"scan\"\npath = \"d\"\nfield_time_s = \"one\"");
        assert!(seconds.contains("params.field_time_s"), "{seconds}");
        // A recording takes no field_time_s (its real time is one field per second).
        let typo = e("source = \"mcap\"\npath = \"r.mcap\"\nfield_time_s = 2");
        assert!(
            typo.contains("params.field_time_s") && typo.contains("unknown field"),
            "{typo}"
        );
    }

    #[test]
    fn the_check_names_the_field_time_and_the_path() {
        let c = Config::from_table(&parse(
            "source = \"scan\"\npath = \"/nonexistent/scan\"\npacing = \"realtime\"\nfield_time_s = 1e20",
        ))
        .unwrap();
        let e = format!("{:#}", c.check().unwrap_err());
        assert!(
            e.contains("field_time_s = 100000000000000000000") && e.contains("at most"),
            "{e}"
        );
        let dir = tempfile::tempdir().unwrap();
        let c = Config::from_table(&parse(&format!(
            "source = \"mcap\"\npath = {:?}",
            dir.path().display().to_string()
        )))
        .unwrap();
        let e = format!("{:#}", c.check().unwrap_err());
        assert!(
            e.contains("params.path = ") && e.contains("a folder"),
            "{e}"
        );
    }

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
        assert_eq!(p.pacing, PacingChoice::Fast);
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
