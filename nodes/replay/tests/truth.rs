//! The truth file: make_tiles.py's layout, readable by bench/score_registration.py.

use serde_json::Value;
use surfstream_replay::{plan_scan, truth_for, SpecimenParams, StageParams};

fn plan(rows: usize, cols: usize) -> surfstream_replay::ScanPlan {
    plan_scan(&StageParams {
        rows,
        cols,
        tile_px: 200,
        ..StageParams::default()
    })
    .expect("valid")
}

fn f(v: &Value) -> f64 {
    v.as_f64().expect("number")
}

/// What score_registration.py computes, transcribed with the same key accesses
/// (`gt["pixel_pitch_um"]["x"]`, `t["index"]`, `t["true_origin_px"]`, `p["a"]`, `p["b"]`,
/// `p["true_offset_px"]`, run tiles' `index`, `x_um`, `y_um`): returns (max pair error, global
/// RMS) in px.
fn score(gt: &Value, run: &Value) -> (f64, f64) {
    let px = f(&gt["pixel_pitch_um"]["x"]);
    let py = f(&gt["pixel_pitch_um"]["y"]);
    let mut truth = std::collections::BTreeMap::new();
    for t in gt["tiles"].as_array().expect("tiles") {
        let o = t["true_origin_px"].as_array().expect("true_origin_px");
        truth.insert(t["index"].as_u64().expect("index"), (f(&o[0]), f(&o[1])));
    }
    let mut est = std::collections::BTreeMap::new();
    for t in run["tiles"].as_array().expect("run tiles") {
        est.insert(
            t["index"].as_u64().expect("index"),
            (f(&t["x_um"]) / px, f(&t["y_um"]) / py),
        );
    }
    let mut max_err: f64 = 0.0;
    for p in gt["pairs"].as_array().expect("pairs") {
        let (a, b) = (p["a"].as_u64().expect("a"), p["b"].as_u64().expect("b"));
        let off = p["true_offset_px"].as_array().expect("true_offset_px");
        let ex = (est[&b].0 - est[&a].0) - f(&off[0]);
        let ey = (est[&b].1 - est[&a].1) - f(&off[1]);
        max_err = max_err.max(ex.hypot(ey));
    }
    let n = truth.len() as f64;
    let mx = truth.keys().map(|i| est[i].0 - truth[i].0).sum::<f64>() / n;
    let my = truth.keys().map(|i| est[i].1 - truth[i].1).sum::<f64>() / n;
    let ms = truth
        .keys()
        .map(|i| (est[i].0 - truth[i].0 - mx).powi(2) + (est[i].1 - truth[i].1 - my).powi(2))
        .sum::<f64>()
        / n;
    (max_err, ms.sqrt())
}

fn run_json(plan: &surfstream_replay::ScanPlan, use_truth: bool) -> Value {
    let tiles: Vec<Value> = plan
        .tiles
        .iter()
        .map(|t| {
            let p = if use_truth { t.true_origin_um } else { t.stage_position_um };
            serde_json::json!({"index": t.index, "x_um": p[0], "y_um": p[1], "placed_by": "registration"})
        })
        .collect();
    serde_json::json!({ "tiles": tiles })
}

#[test]
fn truth_has_make_tiles_keys() {
    let p = plan(2, 3);
    let gt = serde_json::to_value(truth_for(&p)).expect("serialize");
    assert_eq!(f(&gt["pixel_pitch_um"]["x"]), 0.8148);
    assert_eq!(f(&gt["pixel_pitch_um"]["y"]), 0.8148);
    let grid = &gt["grid"];
    assert_eq!(grid["rows"], 2);
    assert_eq!(grid["cols"], 3);
    assert_eq!(grid["order"], "serpentine");
    assert_eq!(grid["tile_shape_px"], serde_json::json!([200, 200]));
    assert_eq!(f(&grid["overlap"]["x"]), 0.1);
    assert_eq!(f(&grid["overlap"]["y"]), 0.1);
    assert!((f(&grid["nominal_step_px"]["x"]) - 180.0).abs() < 1e-9);
    assert!((f(&grid["nominal_overlap_px"]["y"]) - 20.0).abs() < 1e-9);
    for key in ["coords", "height_unit", "nan", "pair_offset"] {
        assert!(gt["conventions"][key].is_string(), "conventions.{key}");
    }
    for key in [
        "stage_sigma_px",
        "backlash_px",
        "noise_sigma",
        "piston_sigma",
        "tilt_sigma",
        "dropout_fraction",
        "dropout_blobs_mean",
        "blob_radius_px",
    ] {
        assert!(!gt["degradation"][key].is_null(), "degradation.{key}");
    }
    assert_eq!(gt["params"]["rows"], 2);
    let tiles = gt["tiles"].as_array().expect("tiles");
    assert_eq!(tiles.len(), 6);
    for (k, t) in tiles.iter().enumerate() {
        assert_eq!(t["index"], k);
        for key in [
            "nominal_origin_px",
            "stage_position_um",
            "true_origin_px",
            "true_origin_um",
            "stage_error_px",
        ] {
            assert_eq!(t[key].as_array().map(Vec::len), Some(2), "tiles[{k}].{key}");
        }
        for key in ["row", "col", "piston", "tilt_x", "tilt_y"] {
            assert!(t[key].is_number(), "tiles[{k}].{key}");
        }
    }
}

#[test]
fn pairs_are_grid_neighbours_with_true_offsets() {
    let p = plan(3, 4);
    let truth = truth_for(&p);
    // rows * (cols - 1) horizontal + (rows - 1) * cols vertical
    assert_eq!(truth.pairs.len(), 3 * 3 + 2 * 4);
    let horizontal = truth
        .pairs
        .iter()
        .filter(|q| q.direction == "horizontal")
        .count();
    assert_eq!(horizontal, 9);
    for q in &truth.pairs {
        let (a, b) = (&p.tiles[q.a], &p.tiles[q.b]);
        match q.direction.as_str() {
            "horizontal" => assert_eq!((b.row, b.col), (a.row, a.col + 1)),
            "vertical" => assert_eq!((b.row, b.col), (a.row + 1, a.col)),
            other => panic!("direction {other}"),
        }
        for k in 0..2 {
            assert_eq!(
                q.true_offset_px[k],
                b.true_origin_px[k] - a.true_origin_px[k]
            );
            assert_eq!(
                q.nominal_offset_px[k],
                b.nominal_origin_px[k] - a.nominal_origin_px[k]
            );
        }
    }
    // serpentine: tile (1, 0) is acquired last in row 1
    assert!(truth
        .pairs
        .iter()
        .any(|q| q.a == 0 && q.b == 7 && q.direction == "vertical"));
}

#[test]
fn scorer_reads_the_truth_and_scores_true_positions_as_perfect() {
    let p = plan(3, 3);
    let text = serde_json::to_string_pretty(
        &truth_for(&p).with_specimen(&p.specimen_params(&SpecimenParams::default())),
    )
    .expect("serialize");
    let gt: Value = serde_json::from_str(&text).expect("parse");
    assert_eq!(gt["specimen"]["width_px"], p.specimen_width_px);
    assert_eq!(gt["specimen"]["generated"]["sa_um"], 1.3);
    let (pair, global) = score(&gt, &run_json(&p, true));
    assert!(pair < 1e-9 && global < 1e-9, "{pair} {global}");
    // Placing by stage positions alone is wrong by about the stage error (sigma 3 px).
    let (pair, global) = score(&gt, &run_json(&p, false));
    assert!(pair > 1.0 && global > 0.5, "{pair} {global}");
}
