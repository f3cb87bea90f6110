//! The mesher node's `surface` parameter (issue item 4), through its `NodeLogic` as both
//! runtimes drive it: the datum alone is meshed and judged against the datum (not the surface
//! it came from), datum + roughness against their sum, the node waits for every input's end of
//! scan, and wiring that does not match the choice is refused when the graph is read.

use surfstream_core::frame::{flags, FrameHeader, FrameKind, HeightMap};
use surfstream_core::raster::{RasterView, Shape};
use surfstream_mesher::fidelity::field_params;
use surfstream_mesher::node::MesherNode;
use surfstream_runtime::graph::{Delivery, InputSpec, NodeContext, PortKind};
use surfstream_runtime::node::{Input, NodeLogic, Outbox};

const W: usize = 96;
const H: usize = 72;
const PITCH_UM: f64 = 3.2;

fn pitch() -> surfstream_core::Pitch {
    surfstream_core::Pitch::square(PITCH_UM).expect("a positive pitch")
}

fn ctx(surface: &str, ports: &[(&str, &str)], out_dir: &std::path::Path) -> NodeContext {
    NodeContext {
        graph_name: "surface_choice".into(),
        node_id: "mesher".into(),
        node_kind: "mesher".into(),
        params: toml::from_str(&format!(
            "surface = \"{surface}\"\nepsilon_um = 0.01\nunits = \"um\"\nfile = \"{surface}.stl\""
        ))
        .expect("test params"),
        out_dir: out_dir.to_path_buf(),
        inputs: ports
            .iter()
            .map(|(port, from)| InputSpec {
                port: (*port).into(),
                from_node: "wavelet".into(),
                from_port: (*from).into(),
                kind: PortKind::Frames,
                delivery: Delivery::Lossless,
                producer_subscribers: 1,
            })
            .collect(),
        outputs: Vec::new(),
        backpressure_timeout_s: 60.0,
        startup_timeout_s: 30.0,
        scan_id: 7,
        memory: surfstream_runtime::memory::MemoryPlan::unlimited(std::env::temp_dir()),
    }
}

/// The test grid: H rows x W columns.
fn grid(heights: &[f32]) -> RasterView<'_, f32> {
    RasterView::new(heights, Shape::new(H, W)).unwrap()
}

/// A smooth datum (a tilted bowl) and a rough roughness (a fine deterministic ripple and
/// noise), um.
fn datum_and_roughness() -> (Vec<f32>, Vec<f32>) {
    let mut state = 0x2545_F491_4F6C_DD1Du64;
    let mut datum = Vec::with_capacity(W * H);
    let mut roughness = Vec::with_capacity(W * H);
    for k in 0..W * H {
        let (x, y) = ((k % W) as f64 / W as f64, (k / W) as f64 / H as f64);
        datum.push((3.0 * (x - 0.5).powi(2) + 2.0 * (y - 0.4).powi(2) + 0.5 * x) as f32);
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        let r = (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5;
        roughness.push((0.2 * (40.0 * x + 31.0 * y).sin() + 0.1 * r) as f32);
    }
    (datum, roughness)
}

fn frame(kind: FrameKind, heights: &[f32]) -> HeightMap {
    HeightMap {
        header: FrameHeader {
            kind: kind as u32,
            flags: flags::FINAL,
            scan_id: 7,
            width: W as u32,
            height: H as u32,
            pitch_x_um: PITCH_UM,
            pitch_y_um: PITCH_UM,
            origin_x_um: 1000.0,
            origin_y_um: -500.0,
            z_offset_um: 40.0,
            ..Default::default()
        },
        heights: heights.to_vec(),
    }
}

fn send(node: &mut MesherNode, port: &str, f: &HeightMap) {
    let mut out = Outbox::default();
    node.on_input(port, Input::Frame(f.view()), &mut out)
        .unwrap_or_else(|e| panic!("{port}: {e:#}"));
}

fn end(node: &mut MesherNode, port: &str) {
    let eos = HeightMap {
        header: FrameHeader::end_of_scan(7, 1, 0, 0),
        heights: Vec::new(),
    };
    send(node, port, &eos);
}

fn sq_of(report: &serde_json::Value, which: &str) -> f64 {
    report["fidelity"][which]["sq_um"]
        .as_f64()
        .unwrap_or_else(|| panic!("no fidelity.{which}.sq_um in {report}"))
}

#[test]
fn datum_alone_is_meshed_and_judged_against_the_datum() {
    let dir = tempfile::tempdir().unwrap();
    let (datum, roughness) = datum_and_roughness();
    let datum_sq = field_params(grid(&datum), pitch()).unwrap().sq_um;
    let sum: Vec<f32> = datum.iter().zip(&roughness).map(|(d, r)| d + r).collect();
    let sum_sq = field_params(grid(&sum), pitch()).unwrap().sq_um;

    let mut node = MesherNode::new(&ctx("datum", &[("datum", "datum")], dir.path())).unwrap();
    send(&mut node, "datum", &frame(FrameKind::Datum, &datum));
    end(&mut node, "datum");
    assert!(node.finished());
    let wall = node.report().unwrap();
    assert_eq!(wall["surface"], "datum");
    assert_eq!(wall["sources"]["datum"], "wavelet/datum");
    assert!((sq_of(&wall, "field") - datum_sq).abs() < 1e-9, "{wall}");
    assert!(wall["fidelity"]["bound_met"].as_bool().unwrap());
    assert!(wall["fidelity"]["error"]["max_um"].as_f64().unwrap() <= 0.01);
    assert!(wall["watertight"].as_bool().unwrap());
    assert!(dir.path().join("datum.stl").is_file());

    // Datum + roughness: a different surface (the sum), waited for on both inputs.
    let ports = [("datum", "datum"), ("roughness", "roughness")];
    let mut node = MesherNode::new(&ctx("datum+roughness", &ports, dir.path())).unwrap();
    send(&mut node, "datum", &frame(FrameKind::Datum, &datum));
    end(&mut node, "datum");
    assert!(!node.finished(), "meshed before the roughness ended");
    send(
        &mut node,
        "roughness",
        &frame(FrameKind::Roughness, &roughness),
    );
    end(&mut node, "roughness");
    assert!(node.finished());
    let full = node.report().unwrap();
    assert!((sq_of(&full, "field") - sum_sq).abs() < 1e-9, "{full}");
    assert!(full["fidelity"]["bound_met"].as_bool().unwrap());
    // The smooth datum is a coarse wall: far fewer triangles at the same bound.
    let (t_wall, t_full) = (
        wall["surface_triangles"].as_u64().unwrap(),
        full["surface_triangles"].as_u64().unwrap(),
    );
    assert!(
        t_wall * 5 < t_full,
        "datum {t_wall} vs datum+roughness {t_full}"
    );

    // The roughness alone.
    let mut node =
        MesherNode::new(&ctx("roughness", &[("roughness", "roughness")], dir.path())).unwrap();
    send(
        &mut node,
        "roughness",
        &frame(FrameKind::Roughness, &roughness),
    );
    end(&mut node, "roughness");
    let r = node.report().unwrap();
    let rough_sq = field_params(grid(&roughness), pitch()).unwrap().sq_um;
    assert!((sq_of(&r, "field") - rough_sq).abs() < 1e-9, "{r}");
}

#[test]
fn wiring_must_match_the_choice() {
    let dir = tempfile::tempdir().unwrap();
    let err = |surface: &str, ports: &[(&str, &str)]| {
        MesherNode::new(&ctx(surface, ports, dir.path()))
            .err()
            .map(|e| format!("{e:#}"))
            .unwrap_or_else(|| panic!("{surface} with {ports:?} was accepted"))
    };
    let e = err("datum+roughness", &[("datum", "datum")]);
    assert!(e.contains("needs the input 'roughness'"), "{e}");
    let e = err("datum", &[("surface", "pooled")]);
    assert!(e.contains("needs the input 'datum'"), "{e}");
    let e = err("pooled", &[("surface", "pooled"), ("datum", "datum")]);
    assert!(e.contains("'datum' is wired but"), "{e}");
    let e = err("flat", &[("surface", "pooled")]);
    assert!(e.contains("surface") && e.contains("node 'mesher'"), "{e}");
    assert!(MesherNode::new(&ctx("panorama", &[("surface", "panorama")], dir.path())).is_ok());
}

#[test]
fn datum_and_roughness_on_different_grids_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let (datum, roughness) = datum_and_roughness();
    let ports = [("datum", "datum"), ("roughness", "roughness")];
    let mut node = MesherNode::new(&ctx("datum+roughness", &ports, dir.path())).unwrap();
    let mut r = frame(FrameKind::Roughness, &roughness);
    r.header.pitch_x_um *= 4.0;
    send(&mut node, "datum", &frame(FrameKind::Datum, &datum));
    send(&mut node, "roughness", &r);
    end(&mut node, "datum");
    let mut out = Outbox::default();
    let eos = HeightMap {
        header: FrameHeader::end_of_scan(7, 1, 0, 0),
        heights: Vec::new(),
    };
    let e = node
        .on_input("roughness", Input::Frame(eos.view()), &mut out)
        .expect_err("different grids accepted");
    assert!(format!("{e:#}").contains("not on the same grid"), "{e:#}");
    assert!(!dir.path().join("datum+roughness.stl").exists());
}
