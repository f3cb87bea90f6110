//! finish.json as typed records, for readers outside this crate (the run's report.html):
//! the fields they show, each optional where a partial or older run may lack it.

use std::path::Path;

use anyhow::{Context, Result};
use serde::Deserialize;

use crate::field::WearTable;
use crate::run::SurfaceParams;

/// The parts of finish.json a report shows.
#[derive(Debug, Clone, Deserialize)]
pub struct FinishSummary {
    pub model: String,
    #[serde(default)]
    pub partial: bool,
    pub cycles_completed: usize,
    pub cycles_requested: usize,
    /// "contact-field" or "sampled-map" (absent before the contact field: sampled).
    #[serde(default)]
    pub wear_model: Option<String>,
    pub before: SurfaceParams,
    pub after: SurfaceParams,
    #[serde(default)]
    pub calibration: Option<CalibrationSummary>,
    #[serde(default)]
    pub contact_field: Option<ContactFieldSummary>,
    #[serde(default)]
    pub paper: Option<PaperValues>,
    pub abbott_before: AbbottSummary,
    pub abbott_after: AbbottSummary,
    pub timings: Timings,
}

#[derive(Debug, Clone, Deserialize)]
pub struct CalibrationSummary {
    pub kind: String,
    #[serde(default)]
    pub target_sa_um: Option<f64>,
    #[serde(default)]
    pub k_finnie_fitted_per_pa: Option<f64>,
    #[serde(default)]
    pub sa_after_um: Option<f64>,
    #[serde(default)]
    pub relative_error: Option<f64>,
    #[serde(default)]
    pub reached: Option<bool>,
    #[serde(default)]
    pub tolerance_percent: Option<f64>,
}

#[derive(Debug, Clone, Default, Deserialize)]
pub struct CheckMean {
    pub auc_gap_predicts_worn: Option<f64>,
    pub dem_volume_within_reach: Option<f64>,
    pub cells_within_reach: Option<f64>,
    pub dem_worn_cells: Option<f64>,
}

#[derive(Debug, Clone, Deserialize)]
pub struct ContactFieldSummary {
    pub ball_radius_um: f64,
    pub impacts_over_process: f64,
    pub table: WearTable,
    #[serde(default)]
    pub check_mean: CheckMean,
    #[serde(default)]
    pub worn_cells_after: Option<f64>,
}

#[derive(Debug, Clone, Deserialize)]
pub struct PaperValues {
    pub before: std::collections::BTreeMap<String, f64>,
    pub after: std::collections::BTreeMap<String, f64>,
}

#[derive(Debug, Clone, Deserialize)]
pub struct AbbottSummary {
    pub material_ratio_pct: Vec<f64>,
    pub height_um: Vec<f64>,
}

#[derive(Debug, Clone, Deserialize)]
pub struct Timings {
    pub engine_s: f64,
    pub total_s: f64,
}

impl FinishSummary {
    /// Reads `path` (a finish.json); an error names the file and the field.
    pub fn read(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("{}: cannot read", path.display()))?;
        serde_json::from_str(&text).with_context(|| {
            format!(
                "{}: not a finish.json this surfstream reads (fields model, before, after, abbott_before, abbott_after, timings, ...)",
                path.display()
            )
        })
    }
}
