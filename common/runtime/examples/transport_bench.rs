//! Transport cost per hop: surfstream's lossless channel next to raw iceoryx2, same run,
//! same machine, two processes each, interleaved rounds.
//!
//!   cargo run --release -p surfstream-runtime --example transport_bench -- [FRAMES] [SIDE] [ROUNDS]
//!
//! Both sides send SIDE x SIDE f32 frames (default 1024: 4 MiB), one every 5 ms so latency is
//! measured rather than throughput, to a subscriber woken by a WaitSet. The clock starts
//! before the producer copies its finished frame into shared memory and stops when the
//! consumer holds it: what a node pays to hand a computed frame to the next node.

#[path = "../tests/support/registry.rs"]
mod registry;
use registry::registry;
use std::time::{Duration, Instant};

use iceoryx2::port::update_connections::UpdateConnections;
use iceoryx2::prelude::*;
use surfstream_core::frame::monotonic_ns;
use surfstream_core::{FrameHeader, FrameKind, HeightMap};
use surfstream_runtime::graph::GraphFile;
use surfstream_runtime::ipc as ss;
use surfstream_runtime::latency::percentiles_ms;
use surfstream_runtime::node::{Input, NodeLogic, Outbox};

const GAP: Duration = Duration::from_millis(5);

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    if args.get(1).map(String::as_str) == Some("--role") {
        return child(&args[2], &args[3], args[4].parse()?, args[5].parse()?);
    }
    let frames: usize = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(300);
    let side: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(1024);
    let rounds: usize = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(3);
    let domain = format!("ssb{}_", std::process::id() % 10000);
    println!("transport bench: {frames} frames of {side}x{side} f32 ({:.1} MiB), {rounds} rounds, interleaved", (side * side * 4) as f64 / 1048576.0);
    let (mut raw_all, mut ours_all, mut raw_after_all) = (Vec::new(), Vec::new(), Vec::new());
    for round in 0..rounds {
        let mut raw = run_raw(&domain, frames, side, round)?;
        raw_after_all.extend(raw.split_off(frames));
        let ours = run_ours(&domain, frames, side, round)?;
        let (r, o) = (
            percentiles_ms(&raw).unwrap(),
            percentiles_ms(&ours).unwrap(),
        );
        println!(
            "round {round}: raw iceoryx2 p50 {:.3} ms p95 {:.3} ms | surfstream p50 {:.3} ms p95 {:.3} ms",
            r.p50, r.p95, o.p50, o.p95
        );
        raw_all.extend(raw);
        ours_all.extend(ours);
    }
    let (r, o) = (
        percentiles_ms(&raw_all).unwrap(),
        percentiles_ms(&ours_all).unwrap(),
    );
    println!("all rounds ({} frames each side):", raw_all.len());
    println!(
        "  raw iceoryx2 + WaitSet : p50 {:.1} us  p95 {:.1} us  max {:.1} us",
        r.p50 * 1e3,
        r.p95 * 1e3,
        r.max * 1e3
    );
    let a = percentiles_ms(&raw_after_all).unwrap();
    println!(
        "  raw, clock after copy  : p50 {:.1} us  p95 {:.1} us  max {:.1} us  (pure hand-over, as in notes/iceoryx2.md)",
        a.p50 * 1e3,
        a.p95 * 1e3,
        a.max * 1e3
    );
    println!(
        "  surfstream channel     : p50 {:.1} us  p95 {:.1} us  max {:.1} us",
        o.p50 * 1e3,
        o.p95 * 1e3,
        o.max * 1e3
    );
    println!(
        "  ratio surfstream / raw : p50 {:.2}x  p95 {:.2}x",
        o.p50 / r.p50,
        o.p95 / r.p95
    );
    for entry in std::fs::read_dir("/dev/shm")?.flatten() {
        if entry.file_name().to_string_lossy().starts_with(&domain) {
            let _ = std::fs::remove_file(entry.path());
        }
    }
    Ok(())
}

fn spawn(
    role: &str,
    domain: &str,
    frames: usize,
    side: usize,
) -> anyhow::Result<std::process::Child> {
    Ok(std::process::Command::new(std::env::current_exe()?)
        .args([
            "--role",
            role,
            domain,
            &frames.to_string(),
            &side.to_string(),
        ])
        .stdout(std::process::Stdio::piped())
        .spawn()?)
}

fn collect(child: std::process::Child) -> anyhow::Result<Vec<u64>> {
    let out = child.wait_with_output()?;
    anyhow::ensure!(out.status.success(), "subscriber failed");
    Ok(String::from_utf8(out.stdout)?
        .split_whitespace()
        .filter_map(|s| s.parse().ok())
        .collect())
}

// ---------------------------------------------------------------- raw iceoryx2

fn raw_service(
    node: &Node<ipc::Service>,
    name: &str,
) -> anyhow::Result<
    iceoryx2::service::port_factory::publish_subscribe::PortFactory<ipc::Service, [f32], [u64; 2]>,
> {
    let sname: ServiceName = name.try_into().map_err(|e| anyhow::anyhow!("{e:?}"))?;
    node.service_builder(&sname)
        .publish_subscribe::<[f32]>()
        .user_header::<[u64; 2]>()
        .enable_safe_overflow(false)
        .subscriber_max_buffer_size(8)
        .subscriber_max_borrowed_samples(1)
        .history_size(0)
        .max_publishers(1)
        .max_subscribers(1)
        .max_nodes(3)
        .open_or_create()
        .map_err(|e| anyhow::anyhow!("{e:?}"))
}

fn run_raw(domain: &str, frames: usize, side: usize, round: usize) -> anyhow::Result<Vec<u64>> {
    let cfg = ss::domain_config(domain)?;
    let node = ss::create_node(&cfg, "bench/raw-pub")?;
    let name = format!("bench/raw{round}");
    let svc = raw_service(&node, &name)?;
    let ev = ss::open_event_service(&node, &name)?;
    let notifier = ev
        .notifier_builder()
        .create()
        .map_err(|e| anyhow::anyhow!("{e:?}"))?;
    let publisher = svc
        .publisher_builder()
        .initial_max_slice_len(side * side)
        .max_loaned_samples(1)
        .create()
        .map_err(|e| anyhow::anyhow!("{e:?}"))?;
    let child = spawn(&format!("raw{round}"), domain, frames, side)?;
    // Handshake: the subscriber attached and is listening (it sends one ready frame back by
    // raising the subscriber count; then we give it a moment to update its connections).
    while svc.dynamic_config().number_of_subscribers() == 0 {
        std::thread::sleep(Duration::from_millis(1));
    }
    std::thread::sleep(Duration::from_millis(200));
    let frame: Vec<f32> = (0..side * side).map(|i| i as f32).collect();
    for _ in 0..frames {
        let t = monotonic_ns();
        let sample = publisher
            .loan_slice_uninit(frame.len())
            .map_err(|e| anyhow::anyhow!("{e:?}"))?;
        let mut sample = sample.write_from_slice(&frame);
        // [before the copy, after the copy]: both clocks, so both costs can be reported.
        *sample.user_header_mut() = [t, monotonic_ns()];
        let n = sample.send().map_err(|e| anyhow::anyhow!("{e:?}"))?;
        anyhow::ensure!(n == 1, "raw frame dropped");
        notifier.notify().map_err(|e| anyhow::anyhow!("{e:?}"))?;
        std::thread::sleep(GAP);
    }
    let samples = collect(child)?;
    anyhow::ensure!(
        samples.len() == 2 * frames,
        "raw: {} of {frames} frames arrived",
        samples.len() / 2
    );
    Ok(samples)
}

// ---------------------------------------------------------------- surfstream channel

struct Source {
    frame: Vec<f32>,
    side: u32,
    left: usize,
    next_at: Instant,
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
        (!self.done).then_some(self.next_at)
    }
    fn on_timer(&mut self, out: &mut Outbox) -> anyhow::Result<()> {
        if self.left == 0 {
            out.end_frames("tiles", 0, 0);
            self.done = true;
            return Ok(());
        }
        let header = FrameHeader {
            kind: FrameKind::Tile as u32,
            width: self.side,
            height: self.side,
            t_acquired_ns: monotonic_ns(),
            ..Default::default()
        };
        out.send_frame(
            "tiles",
            HeightMap {
                header,
                heights: self.frame.clone(),
            },
        );
        self.left -= 1;
        self.next_at = Instant::now() + GAP;
        Ok(())
    }
    fn finished(&self) -> bool {
        self.done
    }
}

#[derive(Default)]
struct Sink {
    ended: bool,
}
impl NodeLogic for Sink {
    fn on_input(&mut self, _: &str, input: Input<'_>, _: &mut Outbox) -> anyhow::Result<()> {
        self.ended |= input.is_end_of_scan();
        Ok(())
    }
    fn on_drained(&mut self, _: &mut Outbox) -> anyhow::Result<()> {
        Ok(())
    }
    fn finished(&self) -> bool {
        self.ended
    }
}

fn bench_graph(round: usize) -> anyhow::Result<Vec<surfstream_runtime::graph::NodeContext>> {
    let text = format!("[graph]\nname = \"bench{round}\"\n[[node]]\nid = \"src\"\nnode = \"replay\"\n[[node]]\nid = \"sink\"\nnode = \"matcher\"\ninputs = {{ tiles = \"src/tiles\" }}\n");
    GraphFile::parse(&text, "bench", &registry())?.resolve(round as u64, &registry())
}

fn run_ours(domain: &str, frames: usize, side: usize, round: usize) -> anyhow::Result<Vec<u64>> {
    let cfg = ss::domain_config(domain)?;
    let ctx = bench_graph(round)?
        .into_iter()
        .find(|c| c.node_id == "src")
        .ok_or_else(|| anyhow::anyhow!("src"))?;
    let child = spawn(&format!("ours{round}"), domain, frames, side)?;
    let mut src = Source {
        frame: (0..side * side).map(|i| i as f32).collect(),
        side: side as u32,
        left: frames,
        next_at: Instant::now(),
        done: false,
    };
    ss::run_node(&ctx, &mut src, &cfg, None)?;
    let samples = collect(child)?;
    anyhow::ensure!(
        samples.len() == frames,
        "surfstream: {} of {frames} frames arrived",
        samples.len()
    );
    Ok(samples)
}

// ---------------------------------------------------------------- subscriber processes

fn child(role: &str, domain: &str, frames: usize, side: usize) -> anyhow::Result<()> {
    let cfg = ss::domain_config(domain)?;
    let mut lat = Vec::with_capacity(frames);
    let mut after_copy = Vec::with_capacity(frames);
    if let Some(round) = role.strip_prefix("raw") {
        let node = ss::create_node(&cfg, "bench/raw-sub")?;
        let name = format!("bench/raw{round}");
        let svc = raw_service(&node, &name)?;
        let sub = svc
            .subscriber_builder()
            .create()
            .map_err(|e| anyhow::anyhow!("{e:?}"))?;
        sub.update_connections()
            .map_err(|e| anyhow::anyhow!("{e:?}"))?;
        let ev = ss::open_event_service(&node, &name)?;
        let listener = ev
            .listener_builder()
            .create()
            .map_err(|e| anyhow::anyhow!("{e:?}"))?;
        let ws = WaitSetBuilder::new()
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<ipc::Service>()
            .map_err(|e| anyhow::anyhow!("{e:?}"))?;
        let _g = ws
            .attach_notification(&listener)
            .map_err(|e| anyhow::anyhow!("{e:?}"))?;
        while lat.len() < frames {
            ws.wait_and_process_once_with_timeout(
                |_| CallbackProgression::Continue,
                Duration::from_secs(5),
            )
            .map_err(|e| anyhow::anyhow!("{e:?}"))?;
            listener
                .try_wait(|_| {})
                .map_err(|e| anyhow::anyhow!("{e:?}"))?;
            while let Some(s) = sub.receive().map_err(|e| anyhow::anyhow!("{e:?}"))? {
                let now = monotonic_ns();
                assert_eq!(s.payload().len(), side * side);
                let [before, after] = *s.user_header();
                lat.push(now - before);
                after_copy.push(now - after);
            }
        }
    } else {
        let round: usize = role.trim_start_matches("ours").parse()?;
        let ctx = bench_graph(round)?
            .into_iter()
            .find(|c| c.node_id == "sink")
            .ok_or_else(|| anyhow::anyhow!("sink"))?;
        let mut sink = Sink::default();
        let report = ss::run_node(&ctx, &mut sink, &cfg, None)?;
        for e in report.stats.received.get("tiles").into_iter().flatten() {
            if e.kind == FrameKind::Tile as u32 {
                lat.push(e.t_received_ns.unwrap_or(0) - e.t_sent_ns);
            }
        }
    }
    let text: Vec<String> = lat.iter().chain(&after_copy).map(u64::to_string).collect();
    println!("{}", text.join(" "));
    Ok(())
}
