//! The two runtimes carry frames losslessly and in order, with the same logic.

#[path = "support/registry.rs"]
mod registry;
use registry::registry;
use std::time::Instant;

use surfstream_core::{FrameHeader, FrameKind, HeightMap};
use surfstream_runtime::graph::GraphFile;
use surfstream_runtime::node::{Input, NodeLogic, Outbox};
use surfstream_runtime::{inproc, ipc};

const N: u32 = 40;
const SIDE: u32 = 512;

struct Source {
    next: u32,
    done: bool,
}
impl NodeLogic for Source {
    fn on_input(&mut self, _: &str, _: Input<'_>, _: &mut Outbox) -> anyhow::Result<()> {
        Ok(())
    }
    fn on_drained(&mut self, _: &mut Outbox) -> anyhow::Result<()> {
        Ok(())
    }
    fn next_wakeup(&self) -> Option<Instant> {
        (!self.done).then(Instant::now)
    }
    fn on_timer(&mut self, out: &mut Outbox) -> anyhow::Result<()> {
        // Bursts of 5 frames: more than a queue holds, so backpressure is exercised.
        for _ in 0..5 {
            if self.next == N {
                out.end_frames("tiles", N - 1, 0);
                self.done = true;
                return Ok(());
            }
            let i = self.next;
            let header = FrameHeader {
                kind: FrameKind::Tile as u32,
                tile_index: i,
                width: SIDE,
                height: SIDE,
                t_acquired_ns: surfstream_core::frame::monotonic_ns(),
                ..Default::default()
            };
            let heights = (0..SIDE * SIDE).map(|k| (k ^ i) as f32).collect();
            out.send_frame("tiles", HeightMap { header, heights });
            self.next += 1;
        }
        Ok(())
    }
    fn finished(&self) -> bool {
        self.done
    }
}

#[derive(Default)]
struct Sink {
    seen: Vec<u32>,
    ended: bool,
}
impl NodeLogic for Sink {
    fn on_input(&mut self, _: &str, input: Input<'_>, _: &mut Outbox) -> anyhow::Result<()> {
        if let Input::Frame(f) = input {
            if f.header.has(surfstream_core::flags::END_OF_SCAN) {
                self.ended = true;
            } else {
                let i = f.header.tile_index;
                assert_eq!(f.heights.len(), (SIDE * SIDE) as usize);
                assert!(f
                    .heights
                    .iter()
                    .enumerate()
                    .all(|(k, v)| *v == ((k as u32) ^ i) as f32));
                self.seen.push(i);
            }
        }
        Ok(())
    }
    fn on_drained(&mut self, _: &mut Outbox) -> anyhow::Result<()> {
        Ok(())
    }
    fn finished(&self) -> bool {
        self.ended
    }
    fn report(&self) -> anyhow::Result<serde_json::Value> {
        Ok(serde_json::json!({ "seen": self.seen }))
    }
}

fn graph(name: &str) -> GraphFile {
    let text = format!(
        r#"
[graph]
name = "{name}"
[[node]]
id = "src"
node = "replay"
[[node]]
id = "a"
node = "matcher"
inputs = {{ tiles = "src/tiles" }}
[[node]]
id = "b"
node = "recorder"
inputs = {{ tiles = "src/tiles" }}
"#
    );
    GraphFile::parse(&text, "test", &registry()).unwrap()
}

fn check(reports: &[surfstream_runtime::node::NodeReport]) {
    let expect: Vec<u32> = (0..N).collect();
    for r in reports.iter().filter(|r| r.node_id != "src") {
        assert_eq!(
            r.report["seen"],
            serde_json::json!(expect),
            "node {}",
            r.node_id
        );
    }
    let src = reports.iter().find(|r| r.node_id == "src").unwrap();
    assert_eq!(src.stats.sent["tiles"].len(), N as usize + 1);
    assert_eq!(src.stats.deliveries["tiles"], 2 * (N as u64 + 1));
}

#[test]
fn in_process_is_lossless_and_ordered() {
    let ctxs = graph("inproc").resolve(1, &registry()).unwrap();
    let nodes = ctxs
        .into_iter()
        .map(|c| {
            let logic: Box<dyn NodeLogic + Send> = if c.node_id == "src" {
                Box::new(Source {
                    next: 0,
                    done: false,
                })
            } else {
                Box::new(Sink::default())
            };
            inproc::InProcessNode { context: c, logic }
        })
        .collect();
    check(&inproc::run_graph(nodes).unwrap());
}

#[test]
fn iceoryx2_is_lossless_and_ordered_with_two_subscribers() {
    let domain = format!("sst{}_", std::process::id() % 100000);
    let cfg = ipc::domain_config(&domain).unwrap();
    let ctxs = graph("ipc").resolve(2, &registry()).unwrap();
    let handles: Vec<_> = ctxs
        .into_iter()
        .map(|c| {
            let cfg = cfg.clone();
            std::thread::spawn(move || {
                let mut logic: Box<dyn NodeLogic + Send> = if c.node_id == "src" {
                    Box::new(Source {
                        next: 0,
                        done: false,
                    })
                } else {
                    Box::new(Sink::default())
                };
                ipc::run_node(&c, logic.as_mut(), &cfg, None)
            })
        })
        .collect();
    let reports: Vec<_> = handles
        .into_iter()
        .map(|h| h.join().unwrap().unwrap())
        .collect();
    check(&reports);
    assert_eq!(
        ipc::count_nodes(&cfg).unwrap(),
        0,
        "every node removed its resources"
    );
    let _ = std::fs::remove_file(format!("/dev/shm/{domain}global_mgmt"));
}
