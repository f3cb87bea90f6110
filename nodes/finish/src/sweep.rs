//! Settings a user compares (`surfstream finish --sweep revolution-rpm=200,250,300`): the base
//! setting calibrated once, every other setting run in full (the DEM on its own process)
//! with the constants fitted on the base, so that each setting's series is a prediction.
//! The base's finish.json and finish.html gain the `sweep` record: Sa/Sq/Sz versus time per
//! setting.

use std::path::Path;
use std::sync::atomic::AtomicBool;

use anyhow::{anyhow, bail, Result};
use surfstream_core::record;

use crate::process::finish_record;
use crate::run::{outputs, FinishOptions, Model};
use crate::summary::{FinishSummary, Sweep, SweepSetting};

/// What a sweep varies.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SweepParameter {
    RevolutionRpm,
    RotationRpm,
    MediaDiameterMm,
}

impl SweepParameter {
    pub const NAMES: &'static str = "revolution-rpm, rotation-rpm or media-diameter-mm";

    pub fn name(self) -> &'static str {
        match self {
            SweepParameter::RevolutionRpm => "revolution-rpm",
            SweepParameter::RotationRpm => "rotation-rpm",
            SweepParameter::MediaDiameterMm => "media-diameter-mm",
        }
    }

    /// The parameter's value in `o`.
    pub fn get(self, o: &FinishOptions) -> f64 {
        match self {
            SweepParameter::RevolutionRpm => o.machine.revolution_rpm,
            SweepParameter::RotationRpm => o.machine.counter_rotation_rpm,
            SweepParameter::MediaDiameterMm => o.media.diameter_mm,
        }
    }

    /// Sets the value in `o`, and in its macro run (the paper's senses: revolution clockwise,
    /// rotation counter-clockwise), which then runs again for the setting.
    fn set(self, o: &mut FinishOptions, v: f64) {
        match self {
            SweepParameter::RevolutionRpm => o.machine.revolution_rpm = v,
            SweepParameter::RotationRpm => o.machine.counter_rotation_rpm = v,
            SweepParameter::MediaDiameterMm => o.media.diameter_mm = v,
        }
        if let Some(m) = &mut o.machine_run {
            match self {
                SweepParameter::RevolutionRpm => m.revolution_rpm = -v.abs(),
                SweepParameter::RotationRpm => m.rotation_rpm = v.abs(),
                SweepParameter::MediaDiameterMm => m.media.diameter_mm = v,
            }
        }
    }
}

/// A sweep: one parameter over values.
#[derive(Debug, Clone, PartialEq)]
pub struct SweepSpec {
    pub parameter: SweepParameter,
    pub values: Vec<f64>,
}

impl SweepSpec {
    /// Parses `NAME=V1,V2,...` (the `--sweep` flag).
    pub fn parse(s: &str) -> Result<Self> {
        let (name, vals) = s.split_once('=').ok_or_else(|| {
            anyhow!(
                "--sweep {s:?}: expected NAME=V1,V2,... with NAME {}",
                SweepParameter::NAMES
            )
        })?;
        let parameter = match name.trim() {
            "revolution-rpm" => SweepParameter::RevolutionRpm,
            "rotation-rpm" => SweepParameter::RotationRpm,
            "media-diameter-mm" => SweepParameter::MediaDiameterMm,
            other => bail!(
                "--sweep {s:?}: unknown parameter {other:?}, expected {}",
                SweepParameter::NAMES
            ),
        };
        let values = vals
            .split(',')
            .map(|v| {
                v.trim()
                    .parse::<f64>()
                    .ok()
                    .filter(|x| x.is_finite() && *x > 0.0)
                    .ok_or_else(|| anyhow!("--sweep {s:?}: {v:?} is not a number > 0"))
            })
            .collect::<Result<Vec<_>>>()?;
        if values.is_empty() {
            bail!("--sweep {s:?}: expected at least one value");
        }
        Ok(SweepSpec { parameter, values })
    }
}

/// The base setting's options with one sweep value, the constants fitted on the base given,
/// no calibration and no ideal model.
fn setting_options(
    base: &FinishOptions,
    fitted: &FinishSummary,
    spec: &SweepSpec,
    v: f64,
) -> Result<FinishOptions> {
    let laws = fitted
        .wear_laws
        .as_ref()
        .ok_or_else(|| anyhow!("sweep: the base run made no prediction (the contact field with a completed cycle is needed)"))?;
    let mut o = base.clone();
    spec.parameter.set(&mut o, v);
    o.k_finnie_per_pa = Some(laws.k_finnie_per_pa * laws.scale);
    o.archard_k_over_h_per_pa = Some(laws.archard_k_over_h_per_pa * laws.scale);
    o.calibrate = None;
    o.ideal = None;
    // A given macro record is of the base setting only: every other setting runs its own
    // machine (when there is one), or its contacts would be the base's.
    if o.machine_run.is_some() {
        o.macro_contacts = None;
    }
    Ok(o)
}

fn setting_of(s: &FinishSummary, value: f64, dir: &str, calibrated_here: bool) -> SweepSetting {
    SweepSetting {
        value,
        dir: dir.into(),
        calibrated_here,
        after: s.after.clone(),
        series: s.series.clone(),
    }
}

/// Runs the base setting (calibrated as `base` says) into `out_dir`, then every other value of
/// `spec` into `out_dir/sweep_<name>_<value>` with the base's fitted constants; the engine
/// budget is shared equally. Returns the base's record with its `sweep`.
pub fn finish_sweep(
    model: &Model,
    base: &FinishOptions,
    spec: &SweepSpec,
    out_dir: &Path,
    stop: &AtomicBool,
    say: &mut dyn FnMut(&str),
) -> Result<FinishSummary> {
    let base_value = spec.parameter.get(base);
    let others: Vec<f64> = spec
        .values
        .iter()
        .cloned()
        .filter(|v| (v - base_value).abs() > 1e-9 * base_value.abs())
        .collect();
    let share = base.time_budget_s / (1 + others.len()) as f64;
    let base_opts = FinishOptions {
        time_budget_s: share,
        ..base.clone()
    };
    say(&format!(
        "finish: sweep of {}: the base ({} = {base_value}) calibrated, then {} setting(s) predicted, {share:.0} s of engine budget each",
        spec.parameter.name(),
        spec.parameter.name(),
        others.len()
    ));
    let mut record = finish_record(model, &base_opts, out_dir, stop, say)?;
    let mut settings = vec![setting_of(&record, base_value, ".", true)];
    for v in others {
        if record.partial || stop.load(std::sync::atomic::Ordering::Relaxed) {
            break;
        }
        let o = FinishOptions {
            time_budget_s: share,
            ..setting_options(base, &record, spec, v)?
        };
        let dir = format!("sweep_{}_{v}", spec.parameter.name());
        say(&format!(
            "finish: sweep: {} = {v} into {dir}",
            spec.parameter.name()
        ));
        let s = finish_record(model, &o, &out_dir.join(&dir), stop, say)?;
        record.partial |= s.partial;
        settings.push(setting_of(&s, v, &dir, false));
    }
    settings.sort_by(|a, b| a.value.total_cmp(&b.value));
    record.sweep = Some(Sweep {
        parameter: spec.parameter.name().into(),
        settings,
        note: "the base setting's one scale (both wear laws) fitted once; every other setting run in full (its own DEM segments, rates and tables) with the constants that scale makes: their series are predictions".into(),
    });
    rewrite(out_dir, &record)?;
    Ok(record)
}

/// finish.json and finish.html of `out_dir` again, from `record` and the maps written there.
fn rewrite(out_dir: &Path, record: &FinishSummary) -> Result<()> {
    let value = record::to_value(record);
    let path = out_dir.join(outputs::SUMMARY);
    surfstream_core::fsutil::write_atomic(&path, |w| {
        serde_json::to_writer_pretty(w, &value).map_err(|e| anyhow!("{}: {e}", path.display()))
    })?;
    let rd = |f: &str| {
        let p = out_dir.join(f);
        surfstream_io::npy::read_npy_f64(&p).map_err(|e| anyhow!("{}: {e}", p.display()))
    };
    let (o, w, f) = (
        rd(outputs::ORIGINAL)?,
        rd(outputs::WORN)?,
        rd(outputs::WEAR)?,
    );
    let ideal = match out_dir.join(outputs::WEAR_IDEAL).is_file() {
        true => Some(rd(outputs::WEAR_IDEAL)?.data),
        false => None,
    };
    crate::html::write_report(
        &out_dir.join(outputs::HTML),
        record,
        &o.data,
        &w.data,
        &f.data,
        ideal.as_deref(),
        o.rows,
        o.cols,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_sweep_flag_names_its_parameter_and_values() {
        let s = SweepSpec::parse("revolution-rpm=200,250,300").unwrap();
        assert_eq!(s.parameter, SweepParameter::RevolutionRpm);
        assert_eq!(s.values, vec![200.0, 250.0, 300.0]);
        let e = SweepSpec::parse("speed=1").unwrap_err().to_string();
        assert!(e.contains("unknown parameter \"speed\""), "{e}");
        let e = SweepSpec::parse("media-diameter-mm=3,x")
            .unwrap_err()
            .to_string();
        assert!(e.contains("\"x\" is not a number"), "{e}");
        let mut o = FinishOptions::default();
        SweepParameter::MediaDiameterMm.set(&mut o, 2.0);
        assert_eq!(SweepParameter::MediaDiameterMm.get(&o), 2.0);
    }
}
