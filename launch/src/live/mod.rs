//! Watching a run live (issue 34): `--view` serves one page (the growing panorama, the tile
//! grid coloured by placement, progress, the running and the final verdict) and
//! `/state.json`; `--foxglove` streams the same to Foxglove over its WebSocket protocol.
//!
//! Where the view learns of the run: like the progress printer ([`crate::progress`]) it is
//! an observer added to the resolved graph, not a node of the user's graph. It subscribes to
//! the source's `tiles` and the matcher's `registrations` (lossless: it counts as one more
//! subscriber in the handshake, and drains them at once into [`state::LiveState`], never
//! waiting on a reader) and to the fusion's latest-wins `preview` (it may miss a patch, which
//! it counts). Under `run` it is one more thread of the graph; under `launch` a launcher thread
//! with its own iceoryx2 node. The node reports (`nodes/<id>.json`, as each node finishes) and
//! run.json (at the end) give the running and the final verdict, read as the same typed
//! records report.html reads.
//!
//! Readers (page, SSE streams, Foxglove clients) take snapshots under a short lock and are
//! woken by a condition variable; a slow reader gets the newest state when it is ready
//! (latest wins for itself, skips counted), so no reader can hold back the observer, and the
//! observer never holds back a lossless channel. Docs: docs/live.md.

pub mod foxglove;
pub mod http;
pub mod messages;
pub mod state;

use std::net::{SocketAddr, TcpListener};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, OnceLock};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};
use surfstream_core::frame::flags;
use surfstream_core::record::{FusionReport, MatcherReport, NodeRecord, ReplayReport};
use surfstream_runtime::graph::{InputSpec, NodeContext, PortKind};
use surfstream_runtime::node::{Input, NodeLogic, NodeReport, Outbox};

use state::LiveState;

/// Node kind and id of the live observer (never a kind a graph file may name).
pub const OBSERVER_KIND: &str = "launcher-live";
const OBSERVER_ID: &str = "launcher-live";

/// The flags of `launch`, `run` and `stitch`.
#[derive(clap::Args, Clone, Debug, Default)]
pub struct ViewArgs {
    /// Serve a live page of the run (panorama, tile grid, progress, verdict) at ADDR:PORT, or a
    /// PORT on 127.0.0.1 (default: 127.0.0.1 and a free port); the URL is printed on stderr.
    /// Read-only; loopback unless an address is given. Put it after the graph file, or write
    /// --view=ADDR:PORT.
    #[arg(long, value_name = "ADDR:PORT", num_args = 0..=1, default_missing_value = "127.0.0.1:0")]
    pub view: Option<String>,
    /// Keep serving the live page (and Foxglove) this many seconds after the run ended
    /// (default 0: exit with the run; Ctrl-C ends the wait).
    #[arg(long, value_name = "S", default_value_t = 0.0)]
    pub view_linger_s: f64,
    /// Show a stop button on the live page that stops the run (as Ctrl-C would).
    #[arg(long)]
    pub view_allow_stop: bool,
    /// Stream the run over the Foxglove WebSocket protocol at ADDR:PORT, or a PORT on 127.0.0.1
    /// (default: 127.0.0.1 and a free port): tiles as foxglove.Grid, the panorama preview as an
    /// image, the tile boxes as a scene.
    #[arg(long, value_name = "ADDR:PORT", num_args = 0..=1, default_missing_value = "127.0.0.1:0")]
    pub foxglove: Option<String>,
}

/// The state and its change signal, shared by the observer and every reader.
pub struct Shared {
    state: Mutex<LiveState>,
    changed: Condvar,
}

impl Shared {
    pub fn new(state: LiveState) -> Arc<Self> {
        Arc::new(Shared {
            state: Mutex::new(state),
            changed: Condvar::new(),
        })
    }

    /// The state, locked (a reader that panicked while holding it leaves it usable).
    pub fn lock(&self) -> MutexGuard<'_, LiveState> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Changes the state and wakes every reader.
    pub fn update(&self, f: impl FnOnce(&mut LiveState)) {
        f(&mut self.lock());
        self.changed.notify_all();
    }

    /// Waits until the state's version differs from `seen` or `timeout` passed; returns the
    /// guard.
    pub fn wait_change(&self, seen: u64, timeout: Duration) -> MutexGuard<'_, LiveState> {
        let guard = self.lock();
        match self
            .changed
            .wait_timeout_while(guard, timeout, |s| s.version == seen)
        {
            Ok((g, _)) => g,
            Err(e) => e.into_inner().0,
        }
    }
}

/// The live view of this process's run (one per process: the CLI runs one graph).
struct Live {
    shared: Arc<Shared>,
    linger: Duration,
    urls: Vec<String>,
    /// The out dir the run moves into when complete (report.html, run.json).
    out: PathBuf,
    watcher: Mutex<Option<JoinHandle<()>>>,
}

static LIVE: OnceLock<Live> = OnceLock::new();

/// Parses `--view` / `--foxglove`: ADDR:PORT, or a PORT on loopback.
pub fn parse_addr(flag: &str, value: &str) -> Result<SocketAddr> {
    if let Ok(port) = value.parse::<u16>() {
        return Ok(SocketAddr::from(([127, 0, 0, 1], port)));
    }
    value.parse::<SocketAddr>().map_err(|_| {
        let hint = if value.ends_with(".toml") || Path::new(value).exists() {
            format!(
                " ('{value}' looks like a file: put --{flag} after the graph file, or write --{flag}=ADDR:PORT)"
            )
        } else {
            String::new()
        };
        anyhow!(
            "--{flag} {value}: expected ADDR:PORT (e.g. 127.0.0.1:8080, [::1]:8080) or a PORT{hint}"
        )
    })
}

/// Starts the servers `args` asks for (none: nothing happens) before the run, and prints
/// their URLs. `out` is the run's out dir (report.html is served from it when the run ends).
pub fn start(args: &ViewArgs, out: &Path) -> Result<()> {
    if args.view.is_none() && args.foxglove.is_none() {
        return Ok(());
    }
    if !(args.view_linger_s.is_finite() && args.view_linger_s >= 0.0) {
        bail!(
            "--view-linger-s {}: expected a number of seconds >= 0",
            args.view_linger_s
        );
    }
    if LIVE.get().is_some() {
        bail!("the live view is already running in this process");
    }
    let shared = Shared::new(LiveState::new("", Vec::new(), args.view_allow_stop));
    let mut urls = Vec::new();
    if let Some(v) = &args.view {
        let addr = parse_addr("view", v)?;
        let listener = TcpListener::bind(addr)
            .with_context(|| format!("--view {addr}: cannot listen there"))?;
        let local = listener
            .local_addr()
            .with_context(|| format!("--view {addr}: no local address"))?;
        let server = http::Server {
            shared: shared.clone(),
            out: out.to_path_buf(),
            loopback_only: local.ip().is_loopback(),
            port: local.port(),
            allow_stop: args.view_allow_stop,
        };
        http::spawn(listener, server)?;
        let url = format!("http://{}/", url_host(local));
        eprintln!("surfstream: live view at {url} (read-only; state at {url}state.json)");
        urls.push(url);
    }
    if let Some(v) = &args.foxglove {
        let addr = parse_addr("foxglove", v)?;
        let listener = TcpListener::bind(addr)
            .with_context(|| format!("--foxglove {addr}: cannot listen there"))?;
        let local = listener
            .local_addr()
            .with_context(|| format!("--foxglove {addr}: no local address"))?;
        foxglove::spawn(listener, shared.clone())?;
        let url = format!("ws://{}", url_host(local));
        eprintln!(
            "surfstream: Foxglove live stream at {url} (Foxglove: Open connection, Foxglove WebSocket)"
        );
        urls.push(url);
    }
    let live = Live {
        shared,
        linger: Duration::from_secs_f64(args.view_linger_s),
        urls,
        out: out.to_path_buf(),
        watcher: Mutex::new(None),
    };
    LIVE.set(live)
        .map_err(|_| anyhow!("the live view is already running in this process"))
}

fn url_host(a: SocketAddr) -> String {
    match a {
        SocketAddr::V4(v) => v.to_string(),
        SocketAddr::V6(v) => format!("[{}]:{}", v.ip(), v.port()),
    }
}

/// True for the live observer's context or report: not part of the user's graph.
pub fn is_observer(kind: &str) -> bool {
    kind == OBSERVER_KIND
}

/// The inputs the observer reads: (producer kind, port, delivery of interest).
const WATCHED: [(&str, &str, PortKind); 3] = [
    (ReplayReport::NODE_KIND, "tiles", PortKind::Frames),
    (
        MatcherReport::NODE_KIND,
        "registrations",
        PortKind::Registrations,
    ),
    (FusionReport::NODE_KIND, "preview", PortKind::Frames),
];

/// Adds the live observer to resolved contexts when a view is running (else nothing): it
/// subscribes to the first source's tiles, the first matcher's registrations and the first
/// fusion's preview that the graph has; lossless ports count one more subscriber, so their
/// handshake waits for it. Starts watching the run's node reports.
pub fn attach(contexts: &mut Vec<NodeContext>) {
    let Some(live) = LIVE.get() else {
        return;
    };
    if contexts.iter().any(|c| c.node_id == OBSERVER_ID) || contexts.is_empty() {
        return;
    }
    let mut inputs = Vec::new();
    for (kind, port, _) in WATCHED {
        if let Some(input) = subscribe(contexts, kind, port) {
            inputs.push(input);
        }
    }
    let layout = crate::progress::layout(contexts);
    let graph = contexts[0].graph_name.clone();
    let staging = contexts[0].out_dir.clone();
    let nodes: Vec<(String, String)> = contexts
        .iter()
        .filter(|c| !crate::progress::is_observer(&c.node_kind))
        .map(|c| (c.node_id.clone(), c.node_kind.clone()))
        .collect();
    // The source's plan: its grid where its parameters give one, else its count (a
    // recording's summary), known before its first tile.
    let planned = layout.total().or_else(|| {
        let source = contexts
            .iter()
            .find(|c| c.node_kind == ReplayReport::NODE_KIND)?;
        let config = surfstream_replay::Config::from_table(&source.params).ok()?;
        surfstream_replay::planned::planned_tiles(&config)
    });
    // The pair log of the matcher the observer reads.
    let pair_log = contexts
        .iter()
        .find(|c| c.node_kind == MatcherReport::NODE_KIND)
        .map(|c| surfstream_matcher::pair_log::path(&c.out_dir, &c.node_id));
    live.shared.update(|s| {
        let mut fresh = LiveState::new(&graph, layout.grid, s.stop_allowed);
        fresh.tiles_planned = planned;
        fresh.viewers = s.viewers;
        fresh.version = s.version + 1;
        *s = fresh;
    });
    if !inputs.is_empty() {
        let mut ctx = contexts[0].clone();
        ctx.node_id = OBSERVER_ID.into();
        ctx.node_kind = OBSERVER_KIND.into();
        ctx.params = toml::Table::new();
        ctx.outputs = Vec::new();
        ctx.inputs = inputs;
        contexts.push(ctx);
    }
    let shared = live.shared.clone();
    let watcher = std::thread::Builder::new()
        .name("live-reports".into())
        .spawn(move || watch_reports(&shared, &staging, nodes, pair_log))
        .ok();
    if let Ok(mut w) = live.watcher.lock() {
        *w = watcher;
    }
}

/// The observer's input on `kind`'s `port` (the first such node), counted as a subscriber.
fn subscribe(contexts: &mut [NodeContext], kind: &str, port: &str) -> Option<InputSpec> {
    let k = contexts
        .iter()
        .position(|c| c.node_kind == kind && c.outputs.iter().any(|o| o.port == port))?;
    let producer = contexts[k].node_id.clone();
    let out = contexts[k].outputs.iter_mut().find(|o| o.port == port)?;
    let lossless = out.delivery == surfstream_runtime::graph::Delivery::Lossless;
    if lossless {
        out.subscribers += 1;
    }
    let (delivery, subscribers, port_kind) = (out.delivery, out.subscribers, out.kind);
    if lossless {
        for c in contexts.iter_mut() {
            for i in &mut c.inputs {
                if i.from_node == producer && i.from_port == port {
                    i.producer_subscribers = subscribers;
                }
            }
        }
    }
    Some(InputSpec {
        port: port.into(),
        from_node: producer,
        from_port: port.into(),
        kind: port_kind,
        delivery,
        producer_subscribers: subscribers,
    })
}

/// Reads the matcher's pair log as it grows (each pair as the matcher decides it), and each
/// node's report as it appears in the staging folder (under `launch` each node writes its own
/// when it finishes; under `run` all are written when the graph ends).
fn watch_reports(
    shared: &Shared,
    staging: &Path,
    mut nodes: Vec<(String, String)>,
    pair_log: Option<PathBuf>,
) {
    let mut tail = pair_log.map(surfstream_matcher::pair_log::PairLogTail::new);
    while !nodes.is_empty() && !shared.lock().run_ended {
        if let Some(t) = &mut tail {
            match t.read_new() {
                Ok(pairs) => shared.update(|s| s.on_streaming_pairs(&pairs)),
                // Written by the matcher only; a bad line is said once, the rest still read.
                Err(e) => eprintln!("surfstream: live view: {e:#}"),
            }
        }
        nodes.retain(|(id, kind)| {
            let path = surfstream_runtime::shell::report_path(staging, id);
            let Ok(text) = std::fs::read_to_string(&path) else {
                return true;
            };
            match serde_json::from_str::<NodeReport>(&text) {
                Ok(r) => {
                    shared.update(|s| s.on_node_report(id, kind, &r.report));
                    false
                }
                Err(_) => true, // written atomically: a parse error is another writer's file
            }
        });
        std::thread::sleep(Duration::from_millis(250));
    }
}

/// The observer's logic: every message into the shared state, at once.
struct Observer {
    shared: Arc<Shared>,
    ended: Vec<String>,
    inputs: Vec<String>,
    /// Tiles registered, and tiles whose preview patch arrived.
    registered: std::collections::BTreeSet<u32>,
    previewed: std::collections::BTreeSet<u32>,
}

impl NodeLogic for Observer {
    fn on_input(&mut self, port: &str, input: Input<'_>, _: &mut Outbox) -> Result<()> {
        if input.is_end_of_scan() && !self.ended.iter().any(|p| p == port) {
            self.ended.push(port.into());
        }
        let now = Instant::now();
        match (port, input) {
            ("registrations", Input::Registration(r)) => {
                let r = *r;
                if !r.has(flags::END_OF_SCAN) {
                    self.registered.insert(r.tile_index);
                }
                self.shared.update(|s| s.on_registration(&r, now));
            }
            ("tiles", Input::Frame(f)) if !f.header.has(flags::END_OF_SCAN) => {
                let tile = f.to_owned();
                self.shared.update(|s| s.on_tile(tile));
            }
            ("preview", Input::Frame(f)) if !f.header.has(flags::END_OF_SCAN) => {
                let patch = f.to_owned();
                self.previewed.insert(patch.header.tile_index);
                self.shared.update(|s| s.on_preview(patch));
            }
            _ => {}
        }
        Ok(())
    }
    fn on_drained(&mut self, _: &mut Outbox) -> Result<()> {
        Ok(())
    }
    /// Every input ended; or the lossless ones did and every tile's preview patch came: a
    /// latest-wins end marker may be lost (under `run`, a full queue drops the newer message),
    /// and the view must not wait for it.
    fn finished(&self) -> bool {
        let ended = |p: &str| self.ended.iter().any(|e| e == p);
        let lossless_ended = self.inputs.iter().all(|p| p == "preview" || ended(p));
        lossless_ended
            && (ended("preview")
                || !self.inputs.iter().any(|p| p == "preview")
                || self.registered.iter().all(|i| self.previewed.contains(i)))
    }
}

/// The observer node's logic (under `run`, a thread of the graph).
pub fn observer(ctx: &NodeContext) -> Result<Box<dyn NodeLogic + Send>> {
    let live = LIVE
        .get()
        .ok_or_else(|| anyhow!("the live observer is in the graph but no view is running"))?;
    Ok(Box::new(Observer {
        shared: live.shared.clone(),
        ended: Vec::new(),
        inputs: ctx.inputs.iter().map(|i| i.port.clone()).collect(),
        registered: Default::default(),
        previewed: Default::default(),
    }))
}

/// The launch-side observer: its own iceoryx2 node on a launcher thread, ending with the
/// scan (or with the graph's failure: the runtime's stop flag and liveness checks end it).
pub fn spawn_ipc_observer(
    ctx: NodeContext,
    cfg: iceoryx2::config::Config,
) -> Result<JoinHandle<()>> {
    let mut logic = observer(&ctx)?;
    std::thread::Builder::new()
        .name("live-observer".into())
        .spawn(move || {
            let link = surfstream_runtime::ipc::launcher_link(&ctx.graph_name);
            // An error here echoes a node's failure, which the supervisor reports; the
            // graph's outcome never depends on the observer.
            let _ = surfstream_runtime::ipc::run_node(&ctx, logic.as_mut(), &cfg, Some(&link));
        })
        .map_err(|e| anyhow!("cannot start the live observer thread: {e}"))
}

/// The verb returned: the final verdict from run.json (or the error), then the linger.
pub fn end(outcome: std::result::Result<(), &anyhow::Error>) {
    let Some(live) = LIVE.get() else {
        return;
    };
    let run = live.out.join("run.json");
    live.shared.update(|s| {
        s.run_ended = true;
        match outcome {
            Ok(()) => match surfstream_core::record::RunRecord::read(&run) {
                Ok(r) => s.on_run_record(&r, &live.out),
                Err(e) => s.on_run_failed(&format!("no run record: {e}")),
            },
            Err(e) => s.on_run_failed(&format!("{e:#}")),
        }
    });
    if let Ok(mut w) = live.watcher.lock() {
        if let Some(w) = w.take() {
            let _ = w.join();
        }
    }
    if live.linger.is_zero() || surfstream_runtime::stop::signal().is_some() {
        // Let open pages read the final state before the process exits.
        std::thread::sleep(Duration::from_millis(300));
        return;
    }
    eprintln!(
        "surfstream: the live view stays at {} for {:.0} s (Ctrl-C ends it)",
        live.urls.join(" and "),
        live.linger.as_secs_f64()
    );
    let until = Instant::now() + live.linger;
    while Instant::now() < until && surfstream_runtime::stop::signal().is_none() {
        std::thread::sleep(Duration::from_millis(100));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use surfstream_runtime::graph::{Delivery, OutputSpec};

    fn ctx(id: &str, kind: &str, outputs: &[(&str, Delivery)]) -> NodeContext {
        NodeContext {
            graph_name: "g".into(),
            node_id: id.into(),
            node_kind: kind.into(),
            params: toml::Table::new(),
            out_dir: "/tmp/x".into(),
            inputs: vec![],
            outputs: outputs
                .iter()
                .map(|(p, d)| OutputSpec {
                    port: (*p).into(),
                    kind: if *p == "registrations" {
                        PortKind::Registrations
                    } else {
                        PortKind::Frames
                    },
                    delivery: *d,
                    subscribers: 1,
                })
                .collect(),
            backpressure_timeout_s: 1.0,
            startup_timeout_s: 1.0,
            scan_id: 7,
            memory: surfstream_runtime::memory::MemoryPlan::unlimited("/tmp/x".into()),
        }
    }

    #[test]
    fn the_observer_is_one_more_subscriber_of_the_lossless_ports_only() {
        let mut all = vec![
            ctx("stage", "replay", &[("tiles", Delivery::Lossless)]),
            ctx(
                "fusion",
                "fusion",
                &[
                    ("panorama", Delivery::Lossless),
                    ("preview", Delivery::LatestWins),
                ],
            ),
        ];
        all[1].inputs.push(InputSpec {
            port: "tiles".into(),
            from_node: "stage".into(),
            from_port: "tiles".into(),
            kind: PortKind::Frames,
            delivery: Delivery::Lossless,
            producer_subscribers: 1,
        });
        let tiles = subscribe(&mut all, "replay", "tiles").unwrap();
        assert_eq!(all[0].outputs[0].subscribers, 2);
        assert_eq!(all[1].inputs[0].producer_subscribers, 2);
        assert_eq!(tiles.producer_subscribers, 2);
        assert_eq!(tiles.topic(), "stage/tiles");
        let preview = subscribe(&mut all, "fusion", "preview").unwrap();
        assert_eq!(preview.delivery, Delivery::LatestWins);
        assert_eq!(all[1].outputs[1].subscribers, 1);
        assert!(subscribe(&mut all, "matcher", "registrations").is_none());
    }

    #[test]
    fn view_addresses_are_addr_port_or_a_loopback_port() {
        assert_eq!(
            parse_addr("view", "8080").unwrap(),
            "127.0.0.1:8080".parse().unwrap()
        );
        assert_eq!(
            parse_addr("view", "0.0.0.0:9000").unwrap(),
            "0.0.0.0:9000".parse().unwrap()
        );
        let e = parse_addr("view", "launch/graphs/demo.toml").unwrap_err();
        assert!(e.to_string().contains("after the graph file"), "{e}");
        let e = parse_addr("foxglove", "localhost").unwrap_err();
        assert!(
            e.to_string()
                .contains("--foxglove localhost: expected ADDR:PORT"),
            "{e}"
        );
    }
}
