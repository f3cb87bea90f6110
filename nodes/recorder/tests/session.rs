//! A recording session without a graph: one channel per input named after its producer, every
//! message written, the file finished only when every input has ended, and read back whole.

use surfstream_core::frame::{flags, FrameHeader, FrameKind, HeightMap, TileRegistration};
use surfstream_io::recording::{read_recording, Recorded};
use surfstream_recorder::RecordingSession;
use surfstream_runtime::graph::{Delivery, InputSpec, PortKind};
use surfstream_runtime::node::Input;

fn input(port: &str, from_node: &str, kind: PortKind) -> InputSpec {
    InputSpec {
        port: port.into(),
        from_node: from_node.into(),
        from_port: port.into(),
        kind,
        delivery: Delivery::Lossless,
        producer_subscribers: 1,
    }
}

#[test]
fn records_every_input_and_finishes_when_all_have_ended() {
    let dir = std::env::temp_dir().join(format!("surfstream-recorder-{}", std::process::id()));
    let path = dir.join("nested/run.mcap");
    let inputs = [
        input("tiles", "stage", PortKind::Frames),
        input("registrations", "matcher", PortKind::Registrations),
    ];
    let mut s = RecordingSession::create(&path, "g", &inputs).unwrap();
    let tile = HeightMap {
        header: FrameHeader {
            kind: FrameKind::Tile as u32,
            width: 3,
            height: 2,
            ..Default::default()
        },
        heights: vec![1.0, 2.0, 3.0, 4.0, 5.0, f32::NAN],
    };
    s.record("tiles", Input::Frame(tile.view()), 10).unwrap();
    let end = HeightMap {
        header: FrameHeader::end_of_scan(1, 1, 0, 0),
        heights: Vec::new(),
    };
    s.record("tiles", Input::Frame(end.view()), 20).unwrap();
    assert!(s.record("nowhere", Input::Frame(end.view()), 21).is_err());
    // One input still open: not finished.
    assert!(!s.finish_when_all_ended().unwrap());
    let reg = TileRegistration {
        flags: flags::END_OF_SCAN,
        ..Default::default()
    };
    s.record("registrations", Input::Registration(&reg), 30)
        .unwrap();
    assert!(s.finish_when_all_ended().unwrap());
    assert!(s.finish_when_all_ended().unwrap());
    assert!(s.record("tiles", Input::Frame(tile.view()), 40).is_err());
    let report = s.report().unwrap();
    assert_eq!(report["file"], "run.mcap");
    assert_eq!(report["messages"]["stage/tiles"], 2);
    assert_eq!(report["messages"]["matcher/registrations"], 1);

    let rec = read_recording(&path).unwrap();
    let topics: Vec<_> = rec.channels.iter().map(|c| c.topic.as_str()).collect();
    assert_eq!(topics, ["stage/tiles", "matcher/registrations"]);
    assert_eq!(rec.messages.len(), 3);
    match &rec.messages[0].message {
        Recorded::Frame(f) => {
            assert_eq!(f.heights[..5], tile.heights[..5]);
            assert!(f.heights[5].is_nan());
        }
        other => panic!("expected the tile, got {other:?}"),
    }
    std::fs::remove_dir_all(&dir).ok();
}
