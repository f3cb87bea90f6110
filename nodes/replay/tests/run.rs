//! The replay run without IPC: tiles in acquisition order, each once, with the pacing's due
//! times; and the source opened from graph parameters.

use std::time::{Duration, Instant};

use surfstream_core::frame::{FrameHeader, HeightMap};
use surfstream_replay::source::open_source;
use surfstream_replay::{
    acquire_tile, generate_specimen, plan_scan, Pacing, PacingChoice, SpecimenParams, StageParams,
    StageRun, TileSource,
};
use surfstream_runtime::graph::NodeContext;

fn frame(index: u32) -> HeightMap {
    HeightMap {
        header: FrameHeader {
            tile_index: index,
            width: 2,
            height: 1,
            ..Default::default()
        },
        heights: vec![index as f32; 2],
    }
}

#[test]
fn simulated_run_yields_the_plan_in_serpentine_order_with_fixed_pacing() {
    let stage = StageParams {
        rows: 2,
        cols: 3,
        tile_px: 32,
        ..StageParams::default()
    };
    let plan = plan_scan(&stage).unwrap();
    let specimen = generate_specimen(&plan.specimen_params(&SpecimenParams::default())).unwrap();
    let expected: Vec<Vec<f32>> = plan
        .tiles
        .iter()
        .map(|t| acquire_tile(&specimen, t, &stage))
        .collect();
    let order: Vec<(u32, u32)> = plan
        .tiles
        .iter()
        .map(|t| (t.row as u32, t.col as u32))
        .collect();
    let field = Duration::from_millis(250);
    let mut run = StageRun::new(
        TileSource::Simulated {
            specimen: surfstream_replay::VirtualSpecimen::Raster(specimen),
            plan: Box::new(plan),
        },
        Pacing::Fixed(field),
        Vec::new(),
    );
    assert_eq!(run.tile_count(), 6);
    assert!(run.plan().is_some() && run.specimen().is_some());
    let t0 = Instant::now();
    // Before the first tile: due at once.
    assert_eq!(run.next_due(t0), Some(t0));
    for k in 0..6 {
        let tile = run.next_tile(t0 + field * k as u32).unwrap();
        assert_eq!(tile.index, k);
        assert_eq!(tile.last, k == 5);
        let h = tile.frame.header;
        assert_eq!((h.tile_row, h.tile_col), order[k]);
        assert_eq!((h.width, h.height), (32, 32));
        // Bit-identical to acquiring the tile directly.
        assert_eq!(
            tile.frame
                .heights
                .iter()
                .map(|v| v.to_bits())
                .collect::<Vec<_>>(),
            expected[k].iter().map(|v| v.to_bits()).collect::<Vec<_>>()
        );
        if k < 5 {
            // Paced from the first tile's time, not from the last call.
            assert_eq!(run.next_due(t0), Some(t0 + field * (k as u32 + 1)));
        }
    }
    assert!(run.is_done());
    assert_eq!(run.sent(), 6);
    assert_eq!(run.next_due(t0), None);
    assert!(run.next_tile(t0).is_none());
}

#[test]
fn frames_run_hands_each_frame_once_with_original_timing() {
    let mut run = StageRun::new(
        TileSource::Frames(vec![frame(0), frame(1), frame(2)]),
        Pacing::Original,
        vec![0, 5_000_000, 7_000_000],
    );
    let t0 = Instant::now();
    let first = run.next_tile(t0).unwrap();
    assert_eq!((first.index, first.frame.heights[0]), (0, 0.0));
    assert_eq!(run.next_due(t0), Some(t0 + Duration::from_millis(5)));
    run.next_tile(t0).unwrap();
    assert_eq!(run.next_due(t0), Some(t0 + Duration::from_millis(7)));
    let last = run.next_tile(t0).unwrap();
    assert!(last.last && last.frame.header.tile_index == 2);
    assert!(run.is_done() && run.plan().is_none());
}

#[test]
fn fast_pacing_is_always_due_and_an_empty_run_is_done() {
    let mut run = StageRun::new(
        TileSource::Frames(vec![frame(0), frame(1)]),
        Pacing::Fast,
        vec![],
    );
    let t0 = Instant::now();
    run.next_tile(t0).unwrap();
    let later = t0 + Duration::from_secs(3);
    assert_eq!(run.next_due(later), Some(later));
    let empty = StageRun::new(TileSource::Frames(Vec::new()), Pacing::Fast, vec![]);
    assert!(empty.is_done() && empty.next_due(t0).is_none());
}

#[test]
fn pacing_names_are_checked() {
    let from_name = |name: &str, field_time_s: f64| {
        PacingChoice::from_name(name).and_then(|c| c.pacing(field_time_s))
    };
    assert_eq!(from_name("fast", 0.0), Ok(Pacing::Fast));
    assert_eq!(
        from_name("realtime", 0.5),
        Ok(Pacing::Fixed(Duration::from_millis(500)))
    );
    assert!(from_name("realtime", 0.0)
        .unwrap_err()
        .contains("field_time_s = 0"));
    assert!(from_name("slow", 1.0)
        .unwrap_err()
        .contains("expected \"realtime\""));
}

fn context(params: &str) -> NodeContext {
    NodeContext {
        graph_name: "g".into(),
        node_id: "stage".into(),
        node_kind: "replay".into(),
        params: toml::from_str(params).unwrap(),
        out_dir: std::env::temp_dir(),
        inputs: Vec::new(),
        outputs: Vec::new(),
        backpressure_timeout_s: 1.0,
        startup_timeout_s: 1.0,
        scan_id: 1,
        memory: surfstream_runtime::memory::MemoryPlan::unlimited(std::env::temp_dir()),
    }
}

#[test]
fn simulated_source_from_graph_params() {
    let s = open_source(&context(
        "source = \"simulated\"\nrows = 1\ncols = 2\ntile_px = 32\npacing = \"fast\"\nsa_um = 0.5\nsave_specimen = true",
    ))
    .unwrap();
    assert_eq!(s.run.tile_count(), 2);
    assert_eq!(s.tiles.len(), 2);
    assert!(s.save_specimen && s.specimen().is_some());
    assert!(matches!(
        s.scan,
        surfstream_core::record::ScanRecord::Simulated {
            tile_width_px: 32,
            ..
        }
    ));

    let e = open_source(&context("source = \"simulated\"\npacing = \"slow\""));
    let e = e.err().unwrap().to_string();
    assert!(
        e.contains("node 'stage': pacing = \"slow\": expected"),
        "{e}"
    );
    let e = open_source(&context("rows = 1")).err().unwrap().to_string();
    assert!(e.contains("params.source is missing"), "{e}");
    let e = open_source(&context("source = \"tape\""))
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("source = \"tape\""), "{e}");
}
