//! The predictions of a finish: the wear laws ([`crate::laws`]) with the DEM's rates and
//! tables, one scale fitted once (or 1 for the constants as given), the worn patch at every
//! time of the series, the wear maps at intervals, and the no-DEM baselines at the same Sa
//! with the noise of the prediction beside them (docs/finish.md, "Predictions").

use std::path::Path;
use std::sync::atomic::AtomicBool;

use anyhow::{anyhow, Result};
use surfstream_core::metrology::{level_plane, params, AbbottCurve, Grid};

use crate::field::{Extrapolation, FieldGrid};
use crate::grid::Patch;
use crate::laws::{self, WearLaw, Worn};
use crate::run::{surface_params, SurfaceParams, MAX_FIELD_SCALE};
use surfstream_core::record::finish::{
    same_time_s, AbbottSummary, Baseline, Baselines, PredictionNoise, SeriesPoint, WearMaps,
};

/// Sa of the evaluated patch of `z` (patch and guard band), levelled by its plane, um.
pub fn sa_of_crop(patch: &Patch, z: &[f64]) -> Result<f64> {
    let c = patch.cropped(z);
    let g = Grid::of(&c, patch.crop_sampling())?;
    let l = level_plane(&g)?;
    let g = Grid::of(&l, patch.crop_sampling())?;
    Ok(params(&g)?.sa)
}

/// The parameters of the evaluated patch of `z` and its Abbott curve at 101 ratios.
pub fn point(
    patch: &Patch,
    time_s: f64,
    z: &[f64],
    fitted: Vec<String>,
) -> Result<(SeriesPoint, SurfaceParams)> {
    let (levelled, p) = surface_params(&patch.cropped(z), patch.crop_sampling())?;
    let g = Grid::of(&levelled, patch.crop_sampling())?;
    let a = AbbottCurve::of(&g)?;
    let ratios: Vec<f64> = (0..=100).map(f64::from).collect();
    let heights = ratios.iter().map(|r| a.smc(*r)).collect();
    Ok((
        SeriesPoint {
            time_s,
            sa: p.sa,
            sq: p.sq,
            sz: p.sz,
            spk: p.spk,
            svk: p.svk,
            sk: p.sk,
            abbott: AbbottSummary {
                material_ratio_pct: ratios,
                height_um: heights,
            },
            fitted,
        },
        p,
    ))
}

/// What a prediction needs.
pub struct PredictionInput<'a> {
    pub patch: &'a Patch,
    /// The original surface (patch and guard band).
    pub original_um: &'a [f64],
    pub grid: FieldGrid,
    pub laws: Vec<WearLaw>,
    /// The same laws with the tables of two disjoint sets of DEM segments (the noise).
    pub halves: Option<[Vec<WearLaw>; 2]>,
    pub calibration_time_s: f64,
    pub process_time_s: f64,
    /// The calibration target (None: the laws at scale 1, the constants as given).
    pub target_sa_um: Option<f64>,
    /// The series' times (ascending, the calibration and the process time among them).
    pub times_s: Vec<f64>,
    pub wear_map_every_s: f64,
    /// The constant-wear baseline wears the cells the ball touches: those within this of the
    /// ball's envelope (one step of the extrapolation), um.
    pub touch_um: f64,
    pub out_dir: &'a Path,
}

/// A prediction over the process.
pub struct Prediction {
    pub scale: f64,
    /// Whether the target Sa was reached (None without a target).
    pub reached: Option<bool>,
    pub fit: Option<Extrapolation>,
    pub series: Vec<SeriesPoint>,
    /// The surface at the process time.
    pub worn: Worn,
    pub extrapolation: Extrapolation,
    pub wear_maps: WearMaps,
    pub baselines: Baselines,
    /// Share of the volume the impact laws removed over the process.
    pub impact_share: f64,
}

/// Folder of the wear maps over time (in OUT).
pub const WEAR_MAPS_DIR: &str = "wear_maps";

/// The parameters compared with the baselines, and their fields.
type Compared = (
    &'static str,
    fn(&SurfaceParams) -> f64,
    fn(&PredictionNoise) -> f64,
);
const COMPARED: [Compared; 5] = [
    ("Sq", |p| p.sq, |n| n.sq),
    ("Sz", |p| p.sz, |n| n.sz),
    ("Spk", |p| p.spk, |n| n.spk),
    ("Svk", |p| p.svk, |n| n.svk),
    ("Sk", |p| p.sk, |n| n.sk),
];

/// Runs the prediction: the fit (with a target), the series with the wear maps, the
/// baselines and the noise.
pub fn predict(input: &PredictionInput, stop: &AtomicBool) -> Result<Prediction> {
    let (patch, g) = (input.patch, input.grid);
    let sa_of = |z: &[f64]| sa_of_crop(patch, z);
    let (scale, reached, fit) = match input.target_sa_um {
        Some(t) => {
            let (s, ok, e) = laws::fit_scale(
                input.original_um,
                g,
                &input.laws,
                input.calibration_time_s,
                MAX_FIELD_SCALE,
                t,
                stop,
                sa_of,
            )?;
            (s, Some(ok), Some(e))
        }
        None => (1.0, None, None),
    };
    // The series' times and the wear maps' (every `wear_map_every_s`), in one pass.
    let every = input.wear_map_every_s;
    let n_maps = (input.process_time_s / every + 1e-9).floor() as usize;
    let map_times: Vec<f64> = (1..=n_maps).map(|k| k as f64 * every).collect();
    let mut all: Vec<f64> = input.times_s.iter().chain(&map_times).cloned().collect();
    all.sort_by(|a, b| a.total_cmp(b));
    all.dedup_by(|a, b| same_time_s(*a, *b));
    let near = same_time_s;
    let maps_dir = input.out_dir.join(WEAR_MAPS_DIR);
    std::fs::create_dir_all(&maps_dir)
        .map_err(|e| anyhow!("{}: cannot create: {e}", maps_dir.display()))?;
    let mut series = Vec::new();
    let mut files = Vec::new();
    let mut last = Worn::new(input.original_um);
    let fitted_sa = input.target_sa_um.is_some();
    let extrapolation = laws::series(input.original_um, g, &input.laws, scale, &all, |t, w| {
        if input.times_s.iter().any(|s| near(*s, t)) {
            let fitted = if fitted_sa && near(t, input.calibration_time_s) {
                vec!["Sa".to_string()]
            } else {
                vec![]
            };
            series.push(point(patch, t, &w.heights_um, fitted)?.0);
        }
        if map_times.iter().any(|m| near(*m, t)) {
            let name = format!("wear_t{t:.1}s.npy");
            write_map(patch, &maps_dir.join(&name), &patch.cropped(&w.wear_um))?;
            files.push(name);
        }
        if near(t, input.process_time_s) {
            last = w.clone();
        }
        Ok(())
    })?;
    let total: f64 = last.wear_um.iter().sum();
    let impact_share = if total > 0.0 {
        last.impact_wear_um.iter().sum::<f64>() / total
    } else {
        0.0
    };
    let (_, after) = point(patch, input.process_time_s, &last.heights_um, vec![])?;
    // The baselines reach the prediction's Sa at the calibration time.
    let sa_cal = series
        .iter()
        .find(|p| near(p.time_s, input.calibration_time_s))
        .map(|p| p.sa)
        .ok_or_else(|| anyhow!("the series lacks the calibration time"))?;
    let noise = match &input.halves {
        Some(h) => Some(noise(input, h, scale, sa_cal, stop)?),
        None => None,
    };
    let within = |p: &SurfaceParams| -> Vec<String> {
        match &noise {
            Some(n) => COMPARED
                .iter()
                .filter(|(_, f, nf)| (f(&after) - f(p)).abs() <= nf(n))
                .map(|(k, _, _)| k.to_string())
                .collect(),
            None => vec![],
        }
    };
    let mut constant_wear = constant_wear(input, sa_cal, stop)?;
    constant_wear.within_noise = within(&constant_wear.after);
    let mut plateau = plateau(input, sa_cal)?;
    plateau.within_noise = within(&plateau.after);
    Ok(Prediction {
        scale,
        reached,
        fit,
        series,
        worn: last,
        extrapolation,
        wear_maps: WearMaps {
            every_s: every,
            dir: WEAR_MAPS_DIR.into(),
            files,
            note: "predicted wear depth along z on the evaluated patch (both laws), um, at every interval of the process time (the paper: every 10 s of its 60 s EDEM run)".into(),
        },
        baselines: Baselines {
            constant_wear,
            plateau,
            noise,
        },
        impact_share,
    })
}

/// A map of the evaluated patch as .npy with its sidecar (the pitch).
fn write_map(patch: &Patch, path: &Path, z: &[f64]) -> Result<()> {
    let geometry = surfstream_io::sidecar::NpyGeometry {
        pitch_x_um: patch.sampling.pitch_x_um(),
        pitch_y_um: patch.sampling.pitch_y_um(),
        origin_um: None,
    };
    surfstream_io::npy::write_npy_f64(path, z, patch.crop.rows, patch.crop.cols)
        .map_err(|e| anyhow!("{}: {e}", path.display()))?;
    surfstream_io::sidecar::write_sidecar(path, &geometry)
}

/// The prediction with each half's laws, fitted to `sa_cal`: the spread of the parameters
/// after the process time; and, at the prediction's own `scale`, the spread of Sa at the
/// calibration time.
fn noise(
    input: &PredictionInput,
    halves: &[Vec<WearLaw>; 2],
    scale: f64,
    sa_cal: f64,
    stop: &AtomicBool,
) -> Result<PredictionNoise> {
    let mut after = Vec::new();
    let mut sa_at_scale = Vec::new();
    for laws_half in halves {
        // At the calibration time, not the process time: by then a setting's Sa may sit at
        // the envelope's floor, where every table gives the same Sa and the spread says nothing.
        let mut w = Worn::new(input.original_um);
        laws::advance_worn(
            &mut w,
            input.grid,
            laws_half,
            input.calibration_time_s,
            scale,
        );
        sa_at_scale.push(sa_of_crop(input.patch, &w.heights_um)?);
        let (s, _, _) = laws::fit_scale(
            input.original_um,
            input.grid,
            laws_half,
            input.calibration_time_s,
            MAX_FIELD_SCALE,
            sa_cal,
            stop,
            |z| sa_of_crop(input.patch, z),
        )?;
        let mut w = Worn::new(input.original_um);
        laws::advance_worn(&mut w, input.grid, laws_half, input.process_time_s, s);
        after.push(point(input.patch, input.process_time_s, &w.heights_um, vec![])?.1);
    }
    let d = |f: fn(&SurfaceParams) -> f64| (f(&after[0]) - f(&after[1])).abs();
    Ok(PredictionNoise {
        sa: Some((sa_at_scale[0] - sa_at_scale[1]).abs()),
        sq: d(|p| p.sq),
        sz: d(|p| p.sz),
        spk: d(|p| p.spk),
        svk: d(|p| p.svk),
        sk: d(|p| p.sk),
        from: "|difference| after the process time between the predictions from the odd and the even cycles' DEM tables (different engine seeds): Sq..Sk after the process time, each fitted to the same Sa; Sa at the calibration time at the prediction's own scale (not refitted)".into(),
    })
}

/// A constant depth rate on every cell the ball touches (within [`PredictionInput::touch_um`]
/// of its envelope, re-closed every step), fitted to `sa_cal` at the calibration time. Where
/// the DEM's table makes the rate depend on the gap below the envelope, this one is the same
/// on every touched cell and nothing below: what the DEM adds is the difference.
fn constant_wear(input: &PredictionInput, sa_cal: f64, stop: &AtomicBool) -> Result<Baseline> {
    const UNIT_UM_PER_S: f64 = 1e-3;
    let laws_c = [WearLaw::Constant {
        depth_um_per_s: UNIT_UM_PER_S,
        reach_um: input.touch_um,
    }];
    let (s, reached, _) = laws::fit_scale(
        input.original_um,
        input.grid,
        &laws_c,
        input.calibration_time_s,
        MAX_FIELD_SCALE,
        sa_cal,
        stop,
        |z| sa_of_crop(input.patch, z),
    )?;
    let mut series = Vec::new();
    let mut after = None;
    laws::series(
        input.original_um,
        input.grid,
        &laws_c,
        s,
        &input.times_s,
        |t, w| {
            let (p, params) = point(input.patch, t, &w.heights_um, vec![])?;
            series.push(p);
            after = Some(params);
            Ok(())
        },
    )?;
    Ok(Baseline {
        what: format!(
            "a constant wear rate on every cell the ball-closed surface touches (within {:.3} um of it, one step of the extrapolation), re-closed every step: no DEM, no contact probability",
            input.touch_um
        ),
        fitted_parameter: "depth_um_per_s".into(),
        fitted_value: UNIT_UM_PER_S * s,
        reached,
        after: after.ok_or_else(|| anyhow!("no series time"))?,
        series,
        within_noise: vec![],
    })
}

/// A plateau cut (every height above a level cut to it): the level fitted to `sa_cal` at
/// the calibration time, the volume removed growing linearly with time.
fn plateau(input: &PredictionInput, sa_cal: f64) -> Result<Baseline> {
    let z = input.original_um;
    let level = laws::plateau_level_for_sa(z, sa_cal, |c| sa_of_crop(input.patch, c))?
        .ok_or_else(|| anyhow!("no plateau cut reaches Sa {sa_cal} um"))?;
    let removal_cal = laws::plateau_cut(z, level).1;
    let mut series = Vec::new();
    let mut after = None;
    for &t in &input.times_s {
        let l = laws::plateau_level_for_removal(z, removal_cal * t / input.calibration_time_s);
        let (p, params) = point(input.patch, t, &laws::plateau_cut(z, l).0, vec![])?;
        series.push(p);
        after = Some(params);
    }
    Ok(Baseline {
        what: "a plateau cut: every height above a level cut to it, the removed volume linear in time; no media at all".into(),
        fitted_parameter: "level_um (at the calibration time; the meshed area's heights)".into(),
        fitted_value: level,
        reached: true,
        after: after.ok_or_else(|| anyhow!("no series time"))?,
        series,
        within_noise: vec![],
    })
}
