//! The finish node's graph parameters and the options they make (plain: the node reads them,
//! tests and tools can build them without a graph).

use anyhow::{bail, Result};
use serde::Deserialize;

use crate::machine::MachineSetting;
use crate::run::{Calibration, FinishOptions};
use crate::setting::MediaPhysics;

/// The node's graph parameters.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FinishConfig {
    /// Sub-folder of the out dir for the outputs.
    #[serde(default = "default_dir")]
    pub dir: String,
    #[serde(default = "default_budget")]
    pub time_budget_s: f64,
    #[serde(default = "default_cycles")]
    pub cycles: usize,
    /// [width, height] um, or [side] um.
    #[serde(default)]
    pub patch_um: Option<Vec<f64>>,
    #[serde(default)]
    pub media_diameter_mm: Option<f64>,
    #[serde(default = "default_ranks")]
    pub ranks: usize,
    #[serde(default)]
    pub max_triangles: Option<usize>,
    #[serde(default)]
    pub passes: Option<usize>,
    /// Fit the wear coefficient so that Sa falls from `calibrate_sa_um[0]` to `[1]` (relative
    /// reduction applied to the model's own Sa) over the process time.
    #[serde(default)]
    pub calibrate_sa_um: Option<[f64; 2]>,
    #[serde(default)]
    pub k_finnie_per_pa: Option<f64>,
    /// "contact-field" (default) or "sampled-map".
    #[serde(default)]
    pub wear_model: Option<String>,
    /// Run the machine first (the macro run, default true, as `surfstream finish`); false:
    /// the barrel kinematics' rates and the one-medium segment (`--no-macro`).
    #[serde(default = "default_macro", rename = "macro")]
    pub macro_run: bool,
    /// The machine of the macro run: MachineSetting's fields (default the paper's machine,
    /// as `surfstream finish --machine FILE.toml`).
    #[serde(default)]
    pub machine: Option<MachineSetting>,
}

fn default_macro() -> bool {
    true
}

fn default_dir() -> String {
    "finish".into()
}
fn default_budget() -> f64 {
    300.0
}
fn default_cycles() -> usize {
    4
}
fn default_ranks() -> usize {
    1
}

impl FinishConfig {
    /// The simulation options, each parameter checked (a bad one named).
    pub fn options(&self) -> Result<FinishOptions> {
        let mut o = FinishOptions {
            time_budget_s: self.time_budget_s,
            cycles: self.cycles,
            ranks: self.ranks,
            passes: self.passes,
            ..Default::default()
        };
        if let Some(p) = &self.patch_um {
            o.patch_um = Some(match p.as_slice() {
                [s] => (*s, *s),
                [w, h] => (*w, *h),
                _ => bail!("params.patch_um = {p:?}: expected [side] or [width, height] in um"),
            });
        }
        if let Some(d) = self.media_diameter_mm {
            o.media.diameter_mm = d;
        }
        if let Some(t) = self.max_triangles {
            o.max_triangles = t;
        }
        if let Some(k) = self.k_finnie_per_pa {
            o.k_finnie_per_pa = Some(k);
        }
        if let Some([b, a]) = self.calibrate_sa_um {
            o.calibrate = Some(Calibration::Sa {
                before_um: Some(b),
                after_um: a,
            });
        }
        if let Some(m) = &self.wear_model {
            o.wear_model = crate::run::WearModel::parse(m)
                .map_err(|e| anyhow::anyhow!("params.wear_model: {e}"))?;
        }
        o.machine_run = if self.macro_run {
            let mut m = self.machine.clone().unwrap_or_default();
            // One media size for the machine and the patch.
            if let Some(d) = self.media_diameter_mm {
                m.media.diameter_mm = d;
            }
            m.check()?;
            Some(m)
        } else {
            None
        };
        o.media.validate()?;
        Ok(o)
    }
}
