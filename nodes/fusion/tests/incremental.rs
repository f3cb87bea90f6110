//! Incremental equals batch: a 3 x 3 scan streamed tile by tile through the fusion node and
//! the wavelet node (their `NodeLogic`, as both runtimes drive them: live patches while tiles
//! arrive, then end of scan) ends in a final panorama, datum and roughness that equal, bit for
//! bit, the batch computation (`render` of all tiles, then `separate`). The matcher's FINAL
//! registrations (globally solved positions) are sent before its end of scan, so the final
//! panorama must be the re-render at those positions, not the streamed one.

use std::collections::BTreeMap;

use surfstream_core::frame::{
    flags, FrameHeader, FrameKind, FrameView, HeightMap, TileRegistration,
};
use surfstream_core::raster::{RasterView, Shape};
use surfstream_core::Pitch;
use surfstream_fusion::{render, BlendParams, FusionMethod, PlaneCorrection, TileInput};
use surfstream_runtime::graph::{Delivery, NodeContext, OutputSpec, PortKind};
use surfstream_runtime::node::{Input, NodeLogic, Outbox, Output};
use surfstream_wavelet::{separate, Mode, Wavelet};

fn pitch() -> Pitch {
    Pitch::square(PITCH_UM).expect("a positive pitch")
}

const PITCH_UM: f64 = 0.8;
const TILE_PX: usize = 64;
const STEP_PX: f64 = 52.0;

fn ctx(kind: &str, params: &str) -> NodeContext {
    NodeContext {
        graph_name: "incremental".into(),
        node_id: kind.into(),
        node_kind: kind.into(),
        params: toml::from_str(params).expect("test params"),
        out_dir: std::env::temp_dir(),
        inputs: Vec::new(),
        outputs: Vec::new(),
        backpressure_timeout_s: 60.0,
        startup_timeout_s: 30.0,
        scan_id: 1,
        memory: surfstream_runtime::memory::MemoryPlan::unlimited(std::env::temp_dir()),
    }
}

fn surface(x_um: f64, y_um: f64) -> f64 {
    12.0 + (x_um / 9.0).sin() * (y_um / 13.0).cos() + 0.3 * (x_um / 2.1 + y_um / 3.7).sin()
}

/// Tile `i` of a 3 x 3 serpentine: heights with a plane added (the matcher's correction takes
/// it off), a few holes; its streamed registration is off by a fraction of a pixel, the FINAL
/// one is exact.
fn tile(i: usize) -> (HeightMap, TileRegistration, TileRegistration) {
    let (r, k) = (i / 3, i % 3);
    let c = if r % 2 == 0 { k } else { 2 - k };
    let x_um = (c as f64 * STEP_PX + 0.37 * r as f64) * PITCH_UM;
    let y_um = (r as f64 * STEP_PX - 0.21 * c as f64) * PITCH_UM;
    let plane = PlaneCorrection {
        piston_um: 0.4 * i as f64 - 1.0,
        tilt_x_um_per_px: 0.001 * (i as f64 - 4.0),
        tilt_y_um_per_px: -0.0007 * i as f64,
    };
    let centre = (TILE_PX - 1) as f64 / 2.0;
    let mut heights = Vec::with_capacity(TILE_PX * TILE_PX);
    for row in 0..TILE_PX {
        for col in 0..TILE_PX {
            let z = surface(x_um + col as f64 * PITCH_UM, y_um + row as f64 * PITCH_UM)
                + plane.piston_um
                + plane.tilt_x_um_per_px * (col as f64 - centre)
                + plane.tilt_y_um_per_px * (row as f64 - centre);
            let hole = (row * 31 + col * 17 + i * 7).is_multiple_of(97);
            heights.push(if hole { f32::NAN } else { z as f32 });
        }
    }
    let header = FrameHeader {
        kind: FrameKind::Tile as u32,
        tile_index: i as u32,
        tile_row: r as u32,
        tile_col: c as u32,
        width: TILE_PX as u32,
        height: TILE_PX as u32,
        pitch_x_um: PITCH_UM,
        pitch_y_um: PITCH_UM,
        origin_x_um: x_um,
        origin_y_um: y_um,
        t_acquired_ns: 1000 + i as u64,
        ..Default::default()
    };
    let exact = TileRegistration {
        tile_index: i as u32,
        x_um,
        y_um,
        piston_um: plane.piston_um,
        tilt_x_um_per_px: plane.tilt_x_um_per_px,
        tilt_y_um_per_px: plane.tilt_y_um_per_px,
        t_acquired_ns: header.t_acquired_ns,
        ..Default::default()
    };
    let streamed = TileRegistration {
        x_um: x_um + 0.3 * PITCH_UM,
        y_um: y_um - 0.2 * PITCH_UM,
        ..exact
    };
    let final_reg = TileRegistration {
        flags: flags::FINAL,
        ..exact
    };
    (HeightMap { header, heights }, streamed, final_reg)
}

/// Feed every output frame of one port to a node's input.
/// Feeds `to` the frames of `outs` on `port`; returns what it emitted while receiving them
/// (the wavelet node's final pass runs as the final panorama arrives).
fn forward(
    outs: &[(String, Output)],
    port: &str,
    to: &mut dyn NodeLogic,
    to_port: &str,
) -> Vec<(String, Output)> {
    let mut sink = Outbox::default();
    for (p, o) in outs {
        if let (true, Output::Frame(f)) = (p == port, o) {
            let view = FrameView {
                header: &f.header,
                heights: &f.heights,
            };
            to.on_input(to_port, Input::Frame(view), &mut sink)
                .expect("node accepts its input");
        }
    }
    sink.take()
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|z| z.to_bits()).collect()
}

#[test]
fn streamed_3x3_scan_ends_bit_identical_to_batch() {
    for method in ["gradual", "wavelet"] {
        let mut fusion = surfstream_fusion::node::build(&ctx(
            "fusion",
            &format!("method = \"{method}\"\nwrite_files = false"),
        ))
        .unwrap();
        // The wavelet node builds its final datum / roughness frames only for a wired port.
        let mut wavelet_ctx = ctx("wavelet", "write_files = false\nlive_margin_px = 24");
        wavelet_ctx.outputs = ["datum", "roughness", "pooled"]
            .into_iter()
            .map(|port| OutputSpec {
                port: port.into(),
                kind: PortKind::Frames,
                delivery: Delivery::Lossless,
                subscribers: 1,
            })
            .collect();
        let mut wavelet = surfstream_wavelet::node::build(&wavelet_ctx).unwrap();
        let tiles: Vec<_> = (0..9).map(tile).collect();
        let mut live = 0usize;
        let mut finals: BTreeMap<String, HeightMap> = BTreeMap::new();
        let step = |fusion: &mut Box<dyn NodeLogic + Send>,
                    wavelet: &mut Box<dyn NodeLogic + Send>,
                    finals: &mut BTreeMap<String, HeightMap>|
         -> usize {
            let mut out = Outbox::default();
            fusion.on_drained(&mut out).unwrap();
            let outs = out.take();
            let on_arrival = forward(&outs, "panorama", wavelet.as_mut(), "panorama");
            let mut wout = Outbox::default();
            wavelet.on_drained(&mut wout).unwrap();
            let mut n = 0;
            for (port, o) in on_arrival.into_iter().chain(wout.take()) {
                if let Output::Frame(f) = o {
                    if f.header.has(flags::FINAL) {
                        finals.insert(port, f);
                    } else if !f.header.has(flags::END_OF_SCAN) {
                        n += 1;
                    }
                }
            }
            for (port, o) in outs {
                if let (true, Output::Frame(f)) = (port == "panorama", o) {
                    if f.header.has(flags::FINAL) {
                        finals.insert("panorama".into(), f);
                    }
                }
            }
            n
        };
        let mut sink = Outbox::default();
        for (t, reg, _) in &tiles {
            let view = FrameView {
                header: &t.header,
                heights: &t.heights,
            };
            fusion
                .on_input("tiles", Input::Frame(view), &mut sink)
                .unwrap();
            fusion
                .on_input("registrations", Input::Registration(reg), &mut sink)
                .unwrap();
            live += step(&mut fusion, &mut wavelet, &mut finals);
        }
        // End of scan: the matcher's FINAL registrations, then both ends of scan.
        for (_, _, fin) in &tiles {
            fusion
                .on_input("registrations", Input::Registration(fin), &mut sink)
                .unwrap();
        }
        let eos_reg = TileRegistration {
            flags: flags::END_OF_SCAN,
            ..Default::default()
        };
        let eos = FrameHeader::end_of_scan(0, 0, 8, 0);
        fusion
            .on_input(
                "tiles",
                Input::Frame(FrameView {
                    header: &eos,
                    heights: &[],
                }),
                &mut sink,
            )
            .unwrap();
        fusion
            .on_input("registrations", Input::Registration(&eos_reg), &mut sink)
            .unwrap();
        for _ in 0..10 {
            if fusion.finished() && wavelet.finished() {
                break;
            }
            live += step(&mut fusion, &mut wavelet, &mut finals);
        }
        assert!(
            fusion.finished() && wavelet.finished(),
            "{method}: nodes did not finish"
        );
        assert!(live > 0, "{method}: no live patches were published");
        let report = fusion.report().unwrap();
        assert_eq!(report["rerendered_from_final_registrations"], true);
        let pairs = report["fusion_pairs"].as_array().expect("fusion_pairs");
        assert_eq!(
            pairs.len(),
            20,
            "{method}: 12 edges + 8 corners of a 3 x 3 scan"
        );

        // Batch: render all tiles at their FINAL positions, then separate.
        let inputs: Vec<TileInput<'_>> = tiles
            .iter()
            .map(|(t, _, f)| TileInput {
                index: t.header.tile_index,
                heights: RasterView::new(&t.heights, Shape::new(TILE_PX, TILE_PX)).unwrap(),
                x_um: f.x_um,
                y_um: f.y_um,
                plane: PlaneCorrection {
                    piston_um: f.piston_um,
                    tilt_x_um_per_px: f.tilt_x_um_per_px,
                    tilt_y_um_per_px: f.tilt_y_um_per_px,
                },
                z_offset_um: 0.0,
            })
            .collect();
        let m = FusionMethod::by_name(method).unwrap();
        let params = match m {
            FusionMethod::Gradual => {
                BlendParams::from_overlap_px(TILE_PX as f64 / 2.0, TILE_PX as f64 / 2.0)
            }
            _ => BlendParams::average(),
        };
        let wf = (m == FusionMethod::Wavelet).then(surfstream_fusion::WaveletFusion::default);
        let pano = surfstream_fusion::render_panorama(pitch(), &inputs, params, wf)
            .unwrap()
            .to_raster();
        if m == FusionMethod::Gradual {
            assert_eq!(
                bits(render(pitch(), &inputs, params).unwrap().heights.values()),
                bits(pano.heights.values())
            );
        }
        let batch = separate(
            pano.heights.values(),
            pano.heights.rows(),
            pano.heights.cols(),
            &Wavelet::by_name("sym5").unwrap(),
            Mode::Symmetric,
            None,
        )
        .unwrap();
        let got = |k: &str| {
            &finals
                .get(k)
                .unwrap_or_else(|| panic!("{method}: no final {k}"))
                .heights
        };
        assert_eq!(
            bits(got("panorama")),
            bits(pano.heights.values()),
            "{method}: panorama"
        );
        assert_eq!(bits(got("datum")), bits(&batch.datum), "{method}: datum");
        assert_eq!(
            bits(got("roughness")),
            bits(&batch.roughness),
            "{method}: roughness"
        );
        let p = &finals["panorama"].header;
        assert_eq!(
            (p.width as usize, p.height as usize),
            (pano.heights.cols(), pano.heights.rows())
        );
    }
}
