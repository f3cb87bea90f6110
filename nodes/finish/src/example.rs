//! A finish.json for the tests of its readers (finish.html, the node's report), and the
//! report's round trip. The records themselves are core's (`surfstream_core::record::finish`:
//! every record the project writes is in core's record module); the examples stay here, beside
//! the pages whose tests read them.

use crate::setting::{BarrelMachine, Media, Workpiece};
use serde_json::{json, Value};
use surfstream_core::record;
use surfstream_core::record::finish::FinishSummary;

/// Surface parameters: Sa, Sq, Spk as given, the others 1.
pub(crate) fn params(sa: f64, sq: f64, spk: f64) -> Value {
    json!({"Sa": sa, "Sq": sq, "Spk": spk, "Sp": 1.0, "Sv": 1.0, "Sz": 1.0, "Ssk": 1.0,
           "Sku": 1.0, "Sdq": 1.0, "Sk": 1.0, "Svk": 1.0, "Smr1": 1.0, "Smr2": 1.0})
}

pub(crate) fn cycle(n: usize, acceleration_factor: f64, sa: f64) -> Value {
    json!({
        "cycle": n, "dir": format!("cycle_{n:02}"), "command": "liggghts", "triangles": 800,
        "mesh_block_stride": 1, "passes": 3, "steps_per_pass": 200, "timestep_s": 1.8e-7,
        "simulated_s": 1e-4, "engine_s": 2.0, "engine_cpu_s": 1.0,
        "cost_per_triangle_step_s": 1e-8, "cpu_per_triangle_step_s": 5e-9,
        "acceleration_factor": acceleration_factor, "wear_scale": 1.0, "target_reached": false,
        "k_finnie_equivalent_per_pa": 1e-12,
        "volume_check": {"liggghts_um3": 1.0, "grid_um3": 1.0, "unmapped_um3": 0.0,
                         "relative_error": 1e-15},
        "archard_volume_um3": 0.5, "contacts": {}, "contact_field": null,
        "after": params(sa, 1.6, 1.2),
    })
}

/// The fields every finish.json has, the curves straight lines.
pub(crate) fn minimal() -> Value {
    let curve = |scale: f64| {
        json!({
            "material_ratio_pct": (0..=100).map(|k| k as f64).collect::<Vec<_>>(),
            "height_um": (0..=100).map(|k| scale * (50.0 - k as f64) / 25.0).collect::<Vec<_>>(),
        })
    };
    json!({
        "model": "out/demo/panorama.x3p", "cycles_completed": 0, "cycles_requested": 1,
        "before": params(1.3157, 1.64, 1.51), "after": params(1.2692, 1.57, 1.10),
        "abbott_before": curve(1.0), "abbott_after": curve(0.9),
        "timings": {"engine_s": 0.0, "total_s": 1.0},
    })
}

/// A series point at `t` s with Sa `sa` (Sq = 1.25 Sa, Sz = 10 Sa, ...).
pub(crate) fn point(t: f64, sa: f64, fitted: bool) -> Value {
    json!({"time_s": t, "Sa": sa, "Sq": 1.25 * sa, "Sz": 10.0 * sa, "Spk": 0.8 * sa,
           "Svk": 1.1 * sa, "Sk": 3.0 * sa,
           "abbott": {"material_ratio_pct": [0.0, 50.0, 100.0], "height_um": [sa, 0.0, -sa]},
           "fitted": if fitted { vec!["Sa"] } else { vec![] }})
}

/// A prediction: the series, the laws, both baselines with a noise, the fitted list.
pub(crate) fn predicted() -> FinishSummary {
    let mut s = record::to_value(&summary()).unwrap();
    let series = |k: f64| -> Vec<Value> {
        [60.0, 120.0, 180.0, 240.0, 300.0]
            .iter()
            .enumerate()
            .map(|(i, t)| point(*t, k * (1.3 - 0.14 * i as f64), false))
            .collect()
    };
    let mut dem = series(1.0);
    dem[4] = point(300.0, 0.74, true);
    let baseline = |what: &str, sq: f64, within: Vec<&str>| {
        json!({"what": what, "fitted_parameter": "p", "fitted_value": 0.5,
               "after": params(0.74, sq, 0.4), "series": series(1.0), "within_noise": within})
    };
    let extra = json!({
        "series": dem,
        "after": params(0.74, 0.93, 0.4),
        "fitted": ["calibration.fit.scale", "series[time_s = calibration time].Sa"],
        "wear_laws": {"impact_rate_per_m2_s": 6.72e7, "sliding_work_j_per_m2_s": 1884.0,
                      "sliding_normal_forces_n": [0.0358], "sliding_contact_depths_um": [0.05],
                      "archard_k_over_h_per_pa": 5e-14, "k_finnie_per_pa": 6e-12, "scale": 2.5,
                      "scale_is": "fitted once", "calibration_time_s": 300.0,
                      "rates_from": "the barrel kinematics", "impact_share_of_volume": 0.25},
        "baselines": {"constant_wear": baseline("constant", 1.6, vec!["Sq"]),
                      "plateau": baseline("plateau", 1.9, vec![]),
                      "noise": {"Sq": 0.05, "Sz": 0.3, "Spk": 0.1, "Svk": 0.1, "Sk": 0.2,
                                "from": "odd vs even cycles"}},
        "sweep": {"parameter": "revolution-rpm", "note": "one calibration",
                  "settings": [
                      {"value": 200.0, "dir": "sweep_revolution-rpm_200", "calibrated_here": false,
                       "after": params(0.9, 1.1, 0.5), "series": series(1.2)},
                      {"value": 300.0, "dir": ".", "calibrated_here": true,
                       "after": params(0.74, 0.93, 0.4), "series": series(1.0)}]},
    });
    for (k, v) in extra.as_object().unwrap() {
        s[k] = v.clone();
    }
    typed(s)
}

pub(crate) fn typed(v: Value) -> FinishSummary {
    serde_json::from_value(v).expect("a finish.json")
}

pub(crate) fn summary() -> FinishSummary {
    let mut s = minimal();
    let extra = json!({
        "cycles_completed": 2, "cycles_requested": 3, "partial": true,
        "setting": {
            "patch": {"pitch_um": [0.5, 0.5], "size_um": [20.0, 15.0], "rows_cols": [30, 40],
                      "in_model_rows_cols_origin": [0, 0], "meshed_area_rows_cols": [48, 58],
                      "guard_band_um": 45.0, "boundary": "guard band", "levelled": "plane",
                      "filled_samples": 0},
            "media": Media::default(),
            "workpiece": Workpiece::default(),
            "machine": BarrelMachine::default(),
            "action": {"media_velocity_m_s": 1.618, "pressure_pa": 3997.19,
                       "impact_angle_deg": 20.0, "acceleration_m_s2": 133.2, "source": "barrel"},
            "press_force_n": 0.0358, "k_finnie_per_pa": 1e-10, "archard_k_over_h_per_pa": 5e-14,
            "process_time_s": 300.0, "timestep_s": 1.8e-7, "ranks": 1, "max_triangles": 20000,
            "time_budget_s": 60.0, "seed": 1, "wear_depth": "along z",
            "acceleration": "process time / cycles / simulated time",
        },
        "cycles": [cycle(1, 97095.8, 1.3), cycle(2, 37759.5, 1.2)],
        "timings": {"engine_s": 314.4, "engine_cpu_s": 42.5, "surfstream_overhead_s": 9.6,
                    "overhead_share_of_engine": 0.0306, "total_s": 324.0, "simulated_s": 0.006},
        "volume_check": {"relative_error": 2.7e-14, "what": "largest error"},
        "calibration": {"kind": "Sa before/after", "target_sa_um": 0.5844,
                        "k_finnie_fitted_per_pa": 9.01e-17},
        "probe": {"dir": "probe", "engine_s": 1.5, "engine_cpu_s": 0.7, "triangles": 800,
                  "steps": 400, "cost_per_triangle_step_s": 4.7e-9},
        "sim": {"finnie_vs_archard": 0.221, "worn_vs_measured_after": null},
        "wear": {"finnie_volume_um3": 120.0, "archard_volume_um3": 60.0,
                 "max_depth_um": 0.8, "mean_depth_um": 0.1},
        "ideal_model": {"source": "graph input 'datum'", "dir": "ideal", "engine_s": 2.0,
                        "volume_um3": 100.0, "sim_wear_maps": 0.025, "note": "same passes",
                        "sim_predictions": 0.031, "wear_map": "wear_ideal.npy"},
        "paper": {"before": {"Sa": 1.272}, "after": {"Sa": 0.565}, "process_time_s": 300},
        "outputs": ["wear.npy", "finish.json"],
    });
    for (k, v) in extra.as_object().unwrap() {
        s[k] = v.clone();
    }
    typed(s)
}

#[cfg(test)]
mod tests {
    use serde_json::Value;
    use surfstream_core::record;
    use surfstream_core::record::finish::{FinishReport, FinishSummary};

    /// The report as the node built it before it was typed: finish.json's value with the
    /// curves and cycles removed by key, `dir` inserted.
    fn report_by_key(s: &FinishSummary, dir: &str) -> Value {
        let mut v = record::to_value(s).unwrap();
        let o = v.as_object_mut().expect("finish.json is an object");
        for k in ["abbott_before", "abbott_after", "cycles", "macro"] {
            assert!(o.remove(k).is_some(), "finish.json has {k}");
        }
        o.insert("dir".into(), Value::from(dir));
        v
    }

    #[test]
    fn the_report_is_finish_json_without_curves_and_cycles_plus_the_folder() {
        for s in [
            super::summary(),
            super::typed(super::minimal()),
            super::predicted(),
        ] {
            let typed = record::to_value(&FinishReport::of(s.clone(), "fin")).unwrap();
            assert_eq!(typed, report_by_key(&s, "fin"));
            assert_eq!(
                serde_json::to_string_pretty(&typed).unwrap(),
                serde_json::to_string_pretty(&report_by_key(&s, "fin")).unwrap()
            );
            // The launcher reads it back as the same record.
            let back: FinishReport = record::from_value(&typed, "report").unwrap();
            assert_eq!(back.dir, "fin");
            assert_eq!(back.before.sa, s.before.sa);
        }
    }
}
