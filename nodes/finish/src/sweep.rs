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
use surfstream_core::record::finish::{
    same_time_s, FinishSummary, SeriesPoint, Sweep, SweepComparison, SweepSetting,
};

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

fn setting_of(
    s: &FinishSummary,
    value: f64,
    dir: &str,
    calibrated_here: bool,
    compared_at_s: f64,
) -> SweepSetting {
    SweepSetting {
        value,
        dir: dir.into(),
        calibrated_here,
        sa_compared_um: SeriesPoint::at(&s.series, compared_at_s).map(|p| p.sa),
        sa_noise_um: s
            .baselines
            .as_ref()
            .and_then(|b| b.noise.as_ref())
            .and_then(|n| n.sa),
        sa_macro_noise_um: s
            .macro_run
            .as_ref()
            .and_then(|m| macro_counting_noise_um(m.contacts.impacts, &s.series, compared_at_s)),
        after: s.after.clone(),
        series: s.series.clone(),
    }
}

/// The Sa at `time_s` that the counting noise of `impacts` macro-run impacts stands for
/// (`SweepSetting::sa_macro_noise_um`): the process's impact rate is N impacts over the
/// recording, so it is known to 1/sqrt(N) at best, and a rate off by a share e wears by
/// `time_s` what the true rate wears by `time_s` (1 + e). dSa/dt is the series' slope across
/// `time_s` (between the points either side of it). None without impacts or a slope.
pub fn macro_counting_noise_um(impacts: usize, series: &[SeriesPoint], time_s: f64) -> Option<f64> {
    if impacts == 0 {
        return None;
    }
    let at = SeriesPoint::at(series, time_s);
    let before = series
        .iter()
        .rfind(|p| p.time_s < time_s && !same_time_s(p.time_s, time_s));
    let after = series
        .iter()
        .find(|p| p.time_s > time_s && !same_time_s(p.time_s, time_s));
    let (a, b) = match (before, at, after) {
        (Some(a), _, Some(b)) => (a, b),
        (Some(a), Some(b), None) | (None, Some(a), Some(b)) => (a, b),
        _ => return None,
    };
    let slope_um_per_s = (b.sa - a.sa) / (b.time_s - a.time_s);
    let e = 1.0 / (impacts as f64).sqrt();
    Some(slope_um_per_s.abs() * time_s * e).filter(|n| n.is_finite())
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
    // Settings are compared where the base was calibrated: by the process time their Sa may
    // all sit at the envelope's floor.
    let compared_at_s = base.calibrate_at_s.unwrap_or(base.process_time_s);
    let mut settings = vec![setting_of(&record, base_value, ".", true, compared_at_s)];
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
        settings.push(setting_of(&s, v, &dir, false, compared_at_s));
    }
    settings.sort_by(|a, b| a.value.total_cmp(&b.value));
    let envelope_sa_um = record
        .contact_field
        .as_ref()
        .and_then(|c| c.envelope.as_ref())
        .map(|e| e.sa_um);
    let (comparisons, verdict) = compare_settings(
        spec.parameter.name(),
        &settings,
        compared_at_s,
        record.before.sa,
        envelope_sa_um,
    );
    record.sweep = Some(Sweep {
        compared_at_s,
        envelope_sa_um,
        parameter: spec.parameter.name().into(),
        settings,
        note: "the base setting's one scale (both wear laws) fitted once; every other setting run in full (its own DEM segments, rates and tables) with the constants that scale makes: their series are predictions".into(),
        comparisons,
        verdict,
    });
    rewrite(out_dir, &record)?;
    Ok(record)
}

/// Every pair of `settings` (sorted by value) compared by Sa at `time_s` (the calibration
/// time) against the noise of the difference, and the sentence that says which the DEM tells
/// apart. A sweep is a basis for choosing only where its settings differ by more than the
/// DEM's sampling noise, and before they reach the envelope's Sa (`envelope_sa_um`, where every
/// setting ends): the user must see when they do not.
pub fn compare_settings(
    parameter: &str,
    settings: &[SweepSetting],
    time_s: f64,
    before_sa_um: f64,
    envelope_sa_um: Option<f64>,
) -> (Vec<SweepComparison>, String) {
    let mut comparisons = Vec::new();
    for (i, a) in settings.iter().enumerate() {
        for b in &settings[i + 1..] {
            let (Some(sa_a), Some(sa_b)) = (a.sa_compared_um, b.sa_compared_um) else {
                continue;
            };
            // The DEM tables' noise of both settings and, where they ran the machine, their
            // macro runs' counting noise, added in quadrature.
            let noise_um = match (a.sa_noise_um, b.sa_noise_um) {
                (Some(x), Some(y)) => Some(
                    x.hypot(y)
                        .hypot(a.sa_macro_noise_um.unwrap_or(0.0))
                        .hypot(b.sa_macro_noise_um.unwrap_or(0.0)),
                ),
                _ => None,
            };
            let d = sa_b - sa_a;
            comparisons.push(SweepComparison {
                values: [a.value, b.value],
                sa_difference_um: d,
                noise_um,
                apart: noise_um.map(|n| d.abs() > n),
            });
        }
    }
    let pair = |c: &SweepComparison| {
        format!(
            "{} vs {} ({:+.3} um{})",
            c.values[0],
            c.values[1],
            c.sa_difference_um,
            c.noise_um
                .map(|n| format!(", noise {n:.3}"))
                .unwrap_or_default()
        )
    };
    let list = |f: &dyn Fn(&SweepComparison) -> bool| {
        comparisons
            .iter()
            .filter(|c| f(c))
            .map(pair)
            .collect::<Vec<_>>()
            .join("; ")
    };
    let at = format!("Sa at {time_s:.0} s");
    let mut verdict = if comparisons.is_empty() {
        format!("fewer than two settings with {at}: nothing to compare")
    } else if comparisons.iter().any(|c| c.apart.is_none()) {
        format!(
            "no noise estimate for every setting (a run of one cycle has no second DEM table): the differences in {at} ({}) cannot be told from the DEM's sampling noise; run two cycles or more",
            list(&|_| true)
        )
    } else if comparisons.iter().all(|c| c.apart == Some(false)) {
        format!(
            "no two settings of {parameter} differ in {at} by more than their noise ({}): this sweep does not tell them apart, it is not yet a basis for choosing",
            list(&|_| true)
        )
    } else {
        let apart = list(&|c| c.apart == Some(true));
        let within = list(&|c| c.apart == Some(false));
        if within.is_empty() {
            format!("every pair of settings of {parameter} differs in {at} by more than its noise: {apart}")
        } else {
            format!("apart by more than their noise in {at}: {apart}; within it (not told apart): {within}")
        }
    };
    // Within a tenth of the way from the start to the envelope's Sa, a setting is saturated:
    // its small noise there is the floor's, not a precise DEM.
    if let Some(floor) = envelope_sa_um {
        let near: Vec<String> = settings
            .iter()
            .filter(|st| {
                st.sa_compared_um
                    .is_some_and(|sa| sa - floor < 0.1 * (before_sa_um - floor))
            })
            .map(|st| st.value.to_string())
            .collect();
        if !near.is_empty() {
            verdict += &format!(
                ". Near the envelope's Sa ({floor:.3} um, where every setting ends) at {time_s:.0} s: {parameter} = {}; there the settings are saturated, and a small noise is the floor's",
                near.join(", ")
            );
        }
    }
    (comparisons, verdict)
}

/// finish.json and finish.html of `out_dir` again, from `record` and the maps written there.
fn rewrite(out_dir: &Path, record: &FinishSummary) -> Result<()> {
    let value = record::to_value(record)?;
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

    fn setting(value: f64, sa: f64, noise: Option<f64>) -> SweepSetting {
        let z = 0.0;
        let params = crate::run::SurfaceParams {
            sa: z,
            sq: z,
            sp: z,
            sv: z,
            sz: z,
            ssk: z,
            sku: z,
            sdq: z,
            sk: z,
            spk: z,
            svk: z,
            smr1: z,
            smr2: z,
        };
        SweepSetting {
            value,
            dir: ".".into(),
            calibrated_here: false,
            sa_compared_um: Some(sa),
            sa_noise_um: noise,
            sa_macro_noise_um: None,
            after: params,
            series: vec![],
        }
    }

    fn point(time_s: f64, sa: f64) -> SeriesPoint {
        SeriesPoint {
            time_s,
            sa,
            sq: sa,
            sz: sa,
            spk: sa,
            svk: sa,
            sk: sa,
            abbott: surfstream_core::record::finish::AbbottSummary {
                material_ratio_pct: vec![],
                height_um: vec![],
            },
            fitted: vec![],
        }
    }

    #[test]
    fn the_macro_runs_impact_count_stands_for_the_sa_its_rate_error_wears() {
        // Sa falls 0.2 um between 240 and 360 s: 1/600 um/s across 300 s. 400 impacts: a
        // rate known to 5 %, 15 s of process at 300 s, 0.025 um of Sa.
        let series = [point(240.0, 0.9), point(300.0, 0.8), point(360.0, 0.7)];
        let n = macro_counting_noise_um(400, &series, 300.0).unwrap();
        assert!((n - 0.025).abs() < 1e-12, "{n}");
        // At the series' last point the slope is the one before it.
        let n = macro_counting_noise_um(400, &series, 360.0).unwrap();
        assert!((n - 360.0 / 600.0 * 0.05).abs() < 1e-12, "{n}");
        // No impacts, or a time with no slope across it: no estimate.
        assert_eq!(macro_counting_noise_um(0, &series, 300.0), None);
        assert_eq!(macro_counting_noise_um(400, &series[..1], 240.0), None);
        // A pair apart on the tables' noise alone is within it once the counting noise is
        // added: 0.05 apart, tables 0.03 each (0.042), counting 0.03 each (0.06 in all).
        let mut s = [
            setting(200.0, 0.65, Some(0.03)),
            setting(300.0, 0.60, Some(0.03)),
        ];
        let (c, _) = compare_settings("revolution-rpm", &s, 300.0, 1.3, None);
        assert_eq!(c[0].apart, Some(true));
        s.iter_mut()
            .for_each(|st| st.sa_macro_noise_um = Some(0.03));
        let (c, verdict) = compare_settings("revolution-rpm", &s, 300.0, 1.3, None);
        assert!((c[0].noise_um.unwrap() - 0.06).abs() < 1e-12);
        assert_eq!(c[0].apart, Some(false), "{verdict}");
    }

    #[test]
    fn settings_are_told_apart_only_beyond_their_noise() {
        // 200 vs 300 r/min apart by 0.2 um with noises 0.03 and 0.04 (quadrature 0.05): apart;
        // 250 sits within the noise of 300.
        let s = [
            setting(200.0, 0.70, Some(0.03)),
            setting(250.0, 0.54, Some(0.04)),
            setting(300.0, 0.50, Some(0.04)),
        ];
        let (c, verdict) = compare_settings("revolution-rpm", &s, 300.0, 1.3, Some(0.2));
        assert_eq!(c.len(), 3);
        assert_eq!(c[0].values, [200.0, 250.0]);
        assert!((c[0].sa_difference_um + 0.16).abs() < 1e-12);
        assert!((c[0].noise_um.unwrap() - 0.05).abs() < 1e-12);
        assert_eq!(c[0].apart, Some(true));
        assert_eq!(c[2].values, [250.0, 300.0]);
        assert_eq!(c[2].apart, Some(false));
        assert!(verdict.contains("in Sa at 300 s"), "{verdict}");
        assert!(
            verdict.contains("200 vs 300 (-0.200 um, noise 0.050)"),
            "{verdict}"
        );
        assert!(
            verdict.contains("within it (not told apart): 250 vs 300"),
            "{verdict}"
        );
        assert!(!verdict.contains("envelope"), "{verdict}");
        // All within: said as not a basis for choosing.
        let s = [
            setting(200.0, 0.50, Some(0.1)),
            setting(300.0, 0.45, Some(0.1)),
        ];
        let (_, verdict) = compare_settings("revolution-rpm", &s, 300.0, 1.3, None);
        assert!(
            verdict.contains("not yet a basis for choosing"),
            "{verdict}"
        );
        // A setting without a noise estimate: no claim either way.
        let s = [setting(200.0, 0.9, None), setting(300.0, 0.45, Some(0.01))];
        let (c, verdict) = compare_settings("revolution-rpm", &s, 300.0, 1.3, None);
        assert_eq!(c[0].apart, None);
        assert!(
            verdict.contains("cannot be told from the DEM's sampling noise"),
            "{verdict}"
        );
        // A setting at the envelope's Sa is saturated, and said to be: 0.45 is within a tenth
        // of the way from 1.3 to 0.44.
        let s = [
            setting(200.0, 0.45, Some(0.0004)),
            setting(300.0, 0.60, Some(0.01)),
        ];
        let (c, verdict) = compare_settings("revolution-rpm", &s, 300.0, 1.3, Some(0.44));
        assert_eq!(c[0].apart, Some(true));
        assert!(
            verdict.contains("Near the envelope's Sa (0.440 um, where every setting ends) at 300 s: revolution-rpm = 200;"),
            "{verdict}"
        );
    }

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
