//! `surfstream launch`: one node per process, frames over iceoryx2 shared memory (DESIGN §3).
//!
//! Per output port: a publish-subscribe service `surfstream/<graph>/<node>/<port>`, an event
//! service of the same name for wake-ups, and `<name>/ready` for the startup handshake.
//! Lossless ports never overflow: the publisher waits for one "ready" per expected subscriber
//! before its first send (iceoryx2 drops samples for subscribers that have not attached yet;
//! see [`LosslessHandshake`]), every `send()` must reach that many receivers, and a full queue fails loudly after the
//! graph's backpressure timeout. Latest-wins ports overwrite (buffer 1, history 1).
//! Each node waits on one WaitSet (inputs + a housekeeping tick), never busy-polls, and at the
//! end keeps its publishers alive until every subscriber has left, so nothing in flight is lost
//! when a process exits. Runs are isolated by an iceoryx2 prefix (a "domain").

use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Result};
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::port::update_connections::UpdateConnections;
use iceoryx2::port::{BackpressureAction, BackpressureInfo};
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::{event as event_factory, publish_subscribe as ps_factory};

use crate::graph::{service_name, Delivery, InputSpec, NodeContext, OutputSpec, PortKind};
use crate::node::{
    deliver, stamp_for_port, Input, NodeLogic, NodeReport, NodeStats, Outbox, Output, SequencedPort,
};
use surfstream_core::frame::{FrameHeader, FrameView, TileRegistration};

/// Set by a termination request (SIGTERM / SIGINT, see [`crate::shell`]): the event loop stops
/// with an error, so ports are dropped and partial files removed on the way out.
pub static STOP_REQUESTED: std::sync::atomic::AtomicBool =
    std::sync::atomic::AtomicBool::new(false);

/// Called from every loop a node can wait in: stops on a termination request or when the
/// launcher is gone, and tells the launcher this node is alive (see [`crate::watchdog`]).
fn check_stop() -> Result<()> {
    if STOP_REQUESTED.load(std::sync::atomic::Ordering::Relaxed) {
        bail!("stopped by a termination request");
    }
    crate::watchdog::check_launcher()?;
    crate::watchdog::beat();
    Ok(())
}

/// Lossless queue depth per subscriber. Nodes drain eagerly, so this only absorbs bursts.
const LOSSLESS_BUFFER: usize = 8;
/// Housekeeping: dead-node cleanup and upstream liveness checks.
const HOUSEKEEPING: Duration = Duration::from_millis(250);
/// Event ids on a port's event service.
const EVENT_DATA: usize = 1;

type FrameFactory = ps_factory::PortFactory<ipc::Service, [f32], FrameHeader>;
type RegFactory = ps_factory::PortFactory<ipc::Service, TileRegistration, ()>;
type EventFactory = event_factory::PortFactory<ipc::Service>;

/// The iceoryx2 configuration of one isolated domain (a fixed prefix per launcher slot).
pub fn domain_config(prefix: &str) -> Result<Config> {
    // iceoryx2 warns on stderr that no config file was loaded: we configure it in code.
    set_log_level(LogLevel::Error);
    let mut cfg = Config::default();
    cfg.global.prefix = FileName::new(prefix.as_bytes())
        .map_err(|e| anyhow!("invalid iceoryx2 domain prefix {prefix:?}: {e:?}"))?;
    // Node and service records in this user's private folder, not the shared /tmp/iceoryx2
    // (which the first user to launch owns, and no other user may then enter).
    let root = crate::slots::iceoryx2_root()?;
    let root_text = format!("{}/", root.display());
    let root_path = iceoryx2::prelude::Path::new(root_text.as_bytes())
        .map_err(|e| anyhow!("{}: not usable as the iceoryx2 root: {e:?}", root.display()))?;
    cfg.global.set_root_path(&root_path);
    Ok(cfg)
}

/// A timed wait woken by a signal (SIGSTOP and SIGCONT do that: EINTR) is a spurious wake-up,
/// not a failure: the caller's loop waits again.
pub fn retry_if_interrupted(
    e: iceoryx2::port::listener::ListenerWaitError,
) -> std::result::Result<(), iceoryx2::port::listener::ListenerWaitError> {
    match e {
        iceoryx2::port::listener::ListenerWaitError::InterruptSignal => Ok(()),
        e => Err(e),
    }
}

/// Creates an iceoryx2 node in `domain` with signal handling left to us.
pub fn create_node(cfg: &Config, name: &str) -> Result<Node<ipc::Service>> {
    let node_name: NodeName = name
        .try_into()
        .map_err(|e| anyhow!("invalid node name {name:?}: {e:?}"))?;
    NodeBuilder::new()
        .name(&node_name)
        .config(cfg)
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<ipc::Service>()
        .map_err(|e| anyhow!("cannot create iceoryx2 node {name:?}: {e:?}"))
}

/// Removes what dead processes left behind in a domain; returns how many nodes were cleaned.
pub fn cleanup_dead_nodes(cfg: &Config) -> Result<usize> {
    let mut cleaned = 0;
    Node::<ipc::Service>::list(cfg, |state| {
        if let NodeState::Dead(view) = state {
            if view.try_remove_stale_resources().is_ok() {
                cleaned += 1;
            }
        }
        CallbackProgression::Continue
    })
    .map_err(|e| anyhow!("cannot list iceoryx2 nodes: {e:?}"))?;
    Ok(cleaned)
}

/// Removes every file of a domain that nobody can be using any more: shared memory, node and
/// service records, including half-removed records of a node killed mid-cleanup (iceoryx2
/// lists those as `Undefined` and cannot remove them). Only for a domain whose owner holds it
/// exclusively (the launcher's slot lock) with no process of it alive. Keeps the per-prefix
/// management file, which iceoryx2 expects to stay. Returns how many entries were removed.
pub fn wipe_domain(cfg: &Config) -> usize {
    let prefix = String::from_utf8_lossy(cfg.global.prefix.as_bytes()).to_string();
    let root = std::path::PathBuf::from(
        String::from_utf8_lossy(cfg.global.root_path().as_bytes()).to_string(),
    );
    let mut removed = 0;
    let mut remove_prefixed = |dir: &std::path::Path, ids: &mut Vec<String>| {
        let Ok(entries) = std::fs::read_dir(dir) else {
            return;
        };
        for e in entries.flatten() {
            let name = e.file_name().to_string_lossy().to_string();
            if !name.starts_with(&prefix) || name.ends_with("global_mgmt") || !e.path().is_file() {
                continue;
            }
            if let Some(id) = name[prefix.len()..].split('.').next() {
                ids.push(id.to_string());
            }
            if std::fs::remove_file(e.path()).is_ok() {
                removed += 1;
            }
        }
    };
    let mut ids = Vec::new();
    remove_prefixed(std::path::Path::new("/dev/shm"), &mut Vec::new());
    remove_prefixed(&root.join("services"), &mut Vec::new());
    remove_prefixed(&root.join("nodes"), &mut ids);
    // A node's directory is named by its id (unprefixed) and holds only prefixed records. Its
    // monitor file may be gone already (a node killed mid-cleanup), so every directory is
    // looked at: one holding records of this domain only is this domain's.
    let nodes = root.join("nodes");
    let mut dirs_removed = 0;
    let dirs: Vec<_> = std::fs::read_dir(&nodes)
        .map(|d| {
            d.flatten()
                .map(|e| e.path())
                .filter(|p| p.is_dir())
                .collect()
        })
        .unwrap_or_default();
    for dir in dirs {
        let names: Vec<String> = std::fs::read_dir(&dir)
            .map(|d| {
                d.flatten()
                    .map(|e| e.file_name().to_string_lossy().to_string())
                    .collect()
            })
            .unwrap_or_default();
        let ours = !names.is_empty() && names.iter().all(|n| n.starts_with(&prefix));
        let listed = dir
            .file_name()
            .is_some_and(|n| ids.iter().any(|id| *id == n.to_string_lossy()));
        if ours || (listed && names.is_empty()) {
            remove_prefixed(&dir, &mut Vec::new());
            if std::fs::remove_dir(&dir).is_ok() {
                dirs_removed += 1;
            }
        } else if names.is_empty() && is_older_than(&dir, STALE_EMPTY_NODE_DIR) {
            // An empty node folder of any domain, long past any node's creation: a node killed
            // between creating its folder and its first record.
            if std::fs::remove_dir(&dir).is_ok() {
                dirs_removed += 1;
            }
        }
    }
    removed + dirs_removed
}

/// An empty node folder older than this cannot belong to a node still being created.
const STALE_EMPTY_NODE_DIR: Duration = Duration::from_secs(60);

fn is_older_than(path: &std::path::Path, age: Duration) -> bool {
    std::fs::metadata(path)
        .and_then(|m| m.modified())
        .ok()
        .and_then(|t| t.elapsed().ok())
        .is_some_and(|e| e > age)
}

/// Node folders under the iceoryx2 root's `nodes/` that hold a record of `cfg`'s domain (a
/// node alive or not cleaned up), for tests and diagnostics.
pub fn node_dirs_of_domain(cfg: &Config) -> Vec<std::path::PathBuf> {
    let prefix = String::from_utf8_lossy(cfg.global.prefix.as_bytes()).to_string();
    let root = std::path::PathBuf::from(
        String::from_utf8_lossy(cfg.global.root_path().as_bytes()).to_string(),
    );
    std::fs::read_dir(root.join("nodes"))
        .map(|d| {
            d.flatten()
                .map(|e| e.path())
                .filter(|p| p.is_dir())
                .filter(|p| {
                    std::fs::read_dir(p).is_ok_and(|mut d| {
                        d.any(|e| {
                            e.is_ok_and(|e| e.file_name().to_string_lossy().starts_with(&prefix))
                        })
                    })
                })
                .collect()
        })
        .unwrap_or_default()
}

/// Counts the nodes (alive or dead) registered in a domain.
pub fn count_nodes(cfg: &Config) -> Result<usize> {
    let mut n = 0;
    Node::<ipc::Service>::list(cfg, |_| {
        n += 1;
        CallbackProgression::Continue
    })
    .map_err(|e| anyhow!("cannot list iceoryx2 nodes: {e:?}"))?;
    Ok(n)
}

fn svc_name(name: &str) -> Result<ServiceName> {
    name.try_into()
        .map_err(|e| anyhow!("invalid service name {name:?}: {e:?}"))
}

/// Opens a service, retrying while another process is creating the same one.
fn retry<T, E: std::fmt::Debug>(
    what: &str,
    deadline: Instant,
    mut f: impl FnMut() -> std::result::Result<T, E>,
) -> Result<T> {
    loop {
        match f() {
            Ok(v) => return Ok(v),
            Err(e) => {
                if Instant::now() > deadline {
                    bail!("{what}: {e:?}");
                }
                std::thread::sleep(Duration::from_millis(5));
            }
        }
    }
}

/// Quality of service per delivery: both ends pass the same values (iceoryx2 verifies them).
fn open_frames(
    node: &Node<ipc::Service>,
    name: &str,
    delivery: Delivery,
    subscribers: usize,
    deadline: Instant,
) -> Result<FrameFactory> {
    let sname = svc_name(name)?;
    retry(
        &format!("cannot open frame service {name}"),
        deadline,
        || {
            let b = node
                .service_builder(&sname)
                .publish_subscribe::<[f32]>()
                .user_header::<FrameHeader>();
            match delivery {
                Delivery::Lossless => b
                    .enable_safe_overflow(false)
                    .subscriber_max_buffer_size(LOSSLESS_BUFFER)
                    .subscriber_max_borrowed_samples(1)
                    .history_size(0)
                    .max_publishers(1)
                    .max_subscribers(subscribers.max(1))
                    .max_nodes(subscribers + 2)
                    .open_or_create(),
                Delivery::LatestWins => b
                    .enable_safe_overflow(true)
                    .subscriber_max_buffer_size(1)
                    .subscriber_max_borrowed_samples(1)
                    .history_size(1)
                    .max_publishers(1)
                    .max_subscribers(4)
                    .max_nodes(6)
                    .open_or_create(),
            }
        },
    )
}

fn open_registrations(
    node: &Node<ipc::Service>,
    name: &str,
    subscribers: usize,
    deadline: Instant,
) -> Result<RegFactory> {
    let sname = svc_name(name)?;
    retry(
        &format!("cannot open registration service {name}"),
        deadline,
        || {
            node.service_builder(&sname)
                .publish_subscribe::<TileRegistration>()
                .enable_safe_overflow(false)
                .subscriber_max_buffer_size(64)
                .subscriber_max_borrowed_samples(1)
                .history_size(0)
                .max_publishers(1)
                .max_subscribers(subscribers.max(1))
                .max_nodes(subscribers + 2)
                .open_or_create()
        },
    )
}

fn open_events(node: &Node<ipc::Service>, name: &str, deadline: Instant) -> Result<EventFactory> {
    let sname = svc_name(name)?;
    retry(
        &format!("cannot open event service {name}"),
        deadline,
        || {
            node.service_builder(&sname)
                .event()
                .max_listeners(16)
                .max_notifiers(16)
                .max_nodes(20)
                .open_or_create()
        },
    )
}

/// Opens (or creates) an event service, e.g. the launcher's ready / go services.
pub fn open_event_service(node: &Node<ipc::Service>, name: &str) -> Result<EventFactory> {
    open_events(node, name, Instant::now() + Duration::from_secs(10))
}

enum Sender {
    Frames(FrameFactory, Publisher<ipc::Service, [f32], FrameHeader>),
    Registrations(RegFactory, Publisher<ipc::Service, TileRegistration, ()>),
}

impl SequencedPort for OutPort {
    fn port_name(&self) -> &str {
        &self.port
    }
    fn next_sequence(&mut self) -> u64 {
        self.sequence += 1;
        self.sequence - 1
    }
}

struct OutPort {
    port: String,
    delivery: Delivery,
    expected: usize,
    sender: Sender,
    wake: iceoryx2::port::notifier::Notifier<ipc::Service>,
    ready_listener: Option<iceoryx2::port::listener::Listener<ipc::Service>>,
    _ready_service: EventFactory,
    _wake_service: EventFactory,
    sequence: u64,
}

impl OutPort {
    fn subscribers_now(&self) -> usize {
        match &self.sender {
            Sender::Frames(f, _) => f.dynamic_config().number_of_subscribers(),
            Sender::Registrations(f, _) => f.dynamic_config().number_of_subscribers(),
        }
    }
}

enum Receiver {
    Frames(FrameFactory, Subscriber<ipc::Service, [f32], FrameHeader>),
    Registrations(RegFactory, Subscriber<ipc::Service, TileRegistration, ()>),
}

struct InPort {
    port: String,
    topic: String,
    receiver: Receiver,
    listener: iceoryx2::port::listener::Listener<ipc::Service>,
    _wake_service: EventFactory,
}

impl InPort {
    fn publishers_now(&self) -> usize {
        match &self.receiver {
            Receiver::Frames(f, _) => f.dynamic_config().number_of_publishers(),
            Receiver::Registrations(f, _) => f.dynamic_config().number_of_publishers(),
        }
    }
    fn update_connections(&self) -> Result<()> {
        match &self.receiver {
            Receiver::Frames(_, s) => s.update_connections(),
            Receiver::Registrations(_, s) => s.update_connections(),
        }
        .map_err(|e| {
            anyhow!(
                "input '{}': cannot connect to {}: {e:?}",
                self.port,
                self.topic
            )
        })
    }
}

/// How the process learns it may start and tells it is ready (only under the launcher), and
/// the other nodes by whose progress its waits are judged.
pub struct LauncherLink {
    pub ready_service: String,
    pub go_service: String,
    pub peers: crate::watchdog::Peers,
}

/// Names of the launcher's control services of a graph (no peers: every wait is judged by its
/// own length; see [`LauncherLink::watching`]).
pub fn launcher_link(graph: &str) -> LauncherLink {
    LauncherLink {
        ready_service: service_name(graph, "launcher", "ready"),
        go_service: service_name(graph, "launcher", "go"),
        peers: crate::watchdog::Peers::default(),
    }
}

impl LauncherLink {
    /// Judges this node's waits by the heartbeats of `peers` (issue 36: liveness, not
    /// wall-clock limits).
    pub fn watching(mut self, peers: crate::watchdog::Peers) -> Self {
        self.peers = peers;
        self
    }
}

/// Runs one node as this process's only iceoryx2 node until it finishes: open outputs, open
/// inputs, the lossless handshake, the launcher's start signal, the event loop, then hold the
/// outputs until every subscriber has left.
pub fn run_node(
    ctx: &NodeContext,
    logic: &mut dyn NodeLogic,
    cfg: &Config,
    launcher: Option<&LauncherLink>,
) -> Result<NodeReport> {
    let node = create_node(cfg, &format!("{}/{}", ctx.graph_name, ctx.node_id))?;
    let startup = Startup::of(ctx);
    let no_peers = crate::watchdog::Peers::default();
    let peers = launcher.map_or(&no_peers, |l| &l.peers);
    let mut outs = ctx
        .outputs
        .iter()
        .map(|o| open_output(&node, ctx, o, &startup, peers))
        .collect::<Result<Vec<_>>>()?;
    let ins = ctx
        .inputs
        .iter()
        .map(|i| open_input(&node, ctx, i, &startup, peers))
        .collect::<Result<Vec<_>>>()?;
    LosslessHandshake::await_subscribers(&mut outs, &startup, peers)?;
    if let Some(link) = launcher {
        join_launcher(&node, link, ctx.inputs.is_empty(), &startup)?;
    }
    let stats = event_loop(&node, ctx, logic, &ins, &mut outs)?;
    // Leave inputs, then hold outputs: samples in flight (and a panorama in a freshly grown
    // segment) stay readable until consumed.
    drop(ins);
    hold_until_subscribers_left(&node, ctx, &outs, peers)?;
    NodeReport::finished(ctx, stats, logic)
}

/// The startup budget (issue 36): a startup wait fails when the nodes it waits on made no
/// progress (no heartbeat) for `startup_timeout_s`, so a slow start on a loaded machine is
/// waited for and a stopped or hung peer is not. Without peers (no launcher) the wait's own
/// length is the measure.
struct Startup {
    timeout: Duration,
}

impl Startup {
    fn of(ctx: &NodeContext) -> Self {
        Self {
            timeout: Duration::from_secs_f64(ctx.startup_timeout_s),
        }
    }
    /// The deadline of one short step begun now (opening a service another process is
    /// creating at the same moment).
    fn deadline(&self) -> Instant {
        Instant::now() + self.timeout
    }
    /// Whether the peers of `progress` made no progress for the startup timeout.
    fn expired(&self, progress: &crate::watchdog::Progress) -> bool {
        progress.silent_longer_than(self.timeout)
    }
    fn seconds(&self) -> f64 {
        self.timeout.as_secs_f64()
    }
}

/// The lossless handshake (DESIGN §3). iceoryx2 delivers a sample only to the subscribers
/// connected when it is sent, so a publisher that sends before a subscriber attached would
/// lose that subscriber's first frames silently. The handshake has three steps:
///
/// 1. [`LosslessHandshake::listen`]: each lossless output opens the listener of
///    `<service>/ready` *before* its publisher exists, so no subscriber's "ready" can be missed;
/// 2. [`LosslessHandshake::announce`]: each subscriber, once connected to the publisher,
///    notifies `<service>/ready` once;
/// 3. [`LosslessHandshake::await_subscribers`]: each lossless output waits for as many
///    "ready"s as the graph wired subscribers to it, or fails after the startup timeout
///    saying how many came.
///
/// Guarantee: when `await_subscribers` returns, every subscriber the graph wired to a lossless
/// output is connected, so the first sample reaches all of them. From then on every send
/// checks that it reached that many receivers (`send_all`): a lossless channel never drops
/// without failing loudly. Latest-wins outputs take no part.
struct LosslessHandshake;

impl LosslessHandshake {
    fn ready_service(service: &str) -> String {
        format!("{service}/ready")
    }

    /// Step 1, publisher side: the ready listener of a lossless output (none for latest-wins).
    fn listen(
        ready_service: &EventFactory,
        service: &str,
        delivery: Delivery,
    ) -> Result<Option<iceoryx2::port::listener::Listener<ipc::Service>>> {
        match delivery {
            Delivery::Lossless => ready_service
                .listener_builder()
                .create()
                .map(Some)
                .map_err(|e| anyhow!("{service}/ready: cannot create listener: {e:?}")),
            Delivery::LatestWins => Ok(None),
        }
    }

    /// Step 2, subscriber side: tells the producer of `service` this subscriber is connected.
    fn announce(node: &Node<ipc::Service>, service: &str, deadline: Instant) -> Result<()> {
        let ready = open_events(node, &Self::ready_service(service), deadline)?;
        let n = ready
            .notifier_builder()
            .create()
            .map_err(|e| anyhow!("{service}/ready: cannot create notifier: {e:?}"))?;
        n.notify()
            .map_err(|e| anyhow!("{service}/ready: notify failed: {e:?}"))?;
        Ok(())
    }

    /// Step 3, publisher side: waits until every lossless output has heard "ready" from all
    /// the subscribers the graph wired to it.
    fn await_subscribers(
        outs: &mut [OutPort],
        startup: &Startup,
        peers: &crate::watchdog::Peers,
    ) -> Result<()> {
        for o in outs {
            let Some(listener) = o.ready_listener.take() else {
                continue;
            };
            let progress = peers.consumers(&o.port);
            let mut ready = 0u64;
            while ready < o.expected as u64 {
                check_stop()?;
                if startup.expired(&progress) {
                    bail!(
                        "output '{}': only {ready} of {} subscribers attached, and they made no progress for {:.0} s ([graph] startup_timeout_s)",
                        o.port,
                        o.expected,
                        startup.seconds()
                    );
                }
                listener
                    .timed_wait(|e| ready += e.count, Duration::from_millis(100))
                    .map(|_| ())
                    .or_else(retry_if_interrupted)
                    .map_err(|e| anyhow!("output '{}': ready wait failed: {e:?}", o.port))?;
            }
        }
        Ok(())
    }
}

/// Opens one output port: ready listener (handshake step 1), then publisher and wake-up
/// notifier.
fn open_output(
    node: &Node<ipc::Service>,
    ctx: &NodeContext,
    o: &OutputSpec,
    startup: &Startup,
    peers: &crate::watchdog::Peers,
) -> Result<OutPort> {
    let deadline = startup.deadline();
    let name = ctx.service_name(&ctx.node_id, &o.port);
    let ready_service = open_events(node, &LosslessHandshake::ready_service(&name), deadline)?;
    let ready_listener = LosslessHandshake::listen(&ready_service, &name, o.delivery)?;
    let backpressure = Duration::from_secs_f64(ctx.backpressure_timeout_s);
    let receivers = peers.consumers(&o.port);
    let handler = move |info: &BackpressureInfo| {
        // Blocked by a full downstream queue is not a stall of this node: keep beating, so the
        // launcher names the receiver that does not drain.
        crate::watchdog::beat();
        // A receiver that keeps beating is slow, not stuck (issue 36): the send fails only
        // after its receivers made no progress for the backpressure timeout.
        if info.elapsed_time > backpressure
            && receivers.silent_for().min(info.elapsed_time) > backpressure
        {
            BackpressureAction::DiscardDataAndFail
        } else {
            BackpressureAction::Retry
        }
    };
    let sender = match o.kind {
        PortKind::Frames => {
            let f = open_frames(node, &name, o.delivery, o.subscribers, deadline)?;
            let p = f
                .publisher_builder()
                .initial_max_slice_len(1 << 20)
                .allocation_strategy(AllocationStrategy::PowerOfTwo)
                .max_loaned_samples(1)
                .backpressure_strategy(match o.delivery {
                    Delivery::Lossless => BackpressureStrategy::RetryUntilDelivered,
                    Delivery::LatestWins => BackpressureStrategy::DiscardData,
                })
                .set_backpressure_handler(handler)
                .create()
                .map_err(|e| anyhow!("{name}: cannot create publisher: {e:?}"))?;
            Sender::Frames(f, p)
        }
        PortKind::Registrations => {
            let f = open_registrations(node, &name, o.subscribers, deadline)?;
            let p = f
                .publisher_builder()
                .max_loaned_samples(1)
                .backpressure_strategy(BackpressureStrategy::RetryUntilDelivered)
                .set_backpressure_handler(handler)
                .create()
                .map_err(|e| anyhow!("{name}: cannot create publisher: {e:?}"))?;
            Sender::Registrations(f, p)
        }
    };
    let wake_service = open_events(node, &name, deadline)?;
    let wake = wake_service
        .notifier_builder()
        .create()
        .map_err(|e| anyhow!("{name}: cannot create notifier: {e:?}"))?;
    Ok(OutPort {
        port: o.port.clone(),
        delivery: o.delivery,
        expected: match o.delivery {
            Delivery::Lossless => o.subscribers,
            Delivery::LatestWins => 0,
        },
        sender,
        wake,
        ready_listener,
        _ready_service: ready_service,
        _wake_service: wake_service,
        sequence: 0,
    })
}

/// Opens one input port: subscriber and wake-up listener, waits for the producer's publisher,
/// connects, and on a lossless input announces itself (handshake step 2).
fn open_input(
    node: &Node<ipc::Service>,
    ctx: &NodeContext,
    i: &InputSpec,
    startup: &Startup,
    peers: &crate::watchdog::Peers,
) -> Result<InPort> {
    let deadline = startup.deadline();
    let name = ctx.service_name(&i.from_node, &i.from_port);
    let receiver = match i.kind {
        PortKind::Frames => {
            let f = open_frames(node, &name, i.delivery, i.producer_subscribers, deadline)?;
            let s = f
                .subscriber_builder()
                .create()
                .map_err(|e| anyhow!("{name}: cannot create subscriber: {e:?}"))?;
            Receiver::Frames(f, s)
        }
        PortKind::Registrations => {
            let f = open_registrations(node, &name, i.producer_subscribers, deadline)?;
            let s = f
                .subscriber_builder()
                .create()
                .map_err(|e| anyhow!("{name}: cannot create subscriber: {e:?}"))?;
            Receiver::Registrations(f, s)
        }
    };
    let wake_service = open_events(node, &name, deadline)?;
    let listener = wake_service
        .listener_builder()
        .create()
        .map_err(|e| anyhow!("{name}: cannot create listener: {e:?}"))?;
    let port = InPort {
        port: i.port.clone(),
        topic: i.topic(),
        receiver,
        listener,
        _wake_service: wake_service,
    };
    // Startup only: wait (politely) for the producer's publisher to exist, as long as the
    // producer makes progress.
    let producer = peers.node(&i.from_node);
    while port.publishers_now() == 0 {
        check_stop()?;
        if startup.expired(&producer) {
            bail!(
                "input '{}': producer {} did not appear, and node '{}' made no progress for {:.0} s ([graph] startup_timeout_s)",
                i.port,
                i.topic(),
                i.from_node,
                startup.seconds()
            );
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    port.update_connections()?;
    if i.delivery == Delivery::Lossless {
        LosslessHandshake::announce(node, &name, startup.deadline())?;
    }
    Ok(port)
}

/// Under the launcher: report ready, and a source (no inputs) waits for "go", so no source
/// sends before every node of the graph is up.
fn join_launcher(
    node: &Node<ipc::Service>,
    link: &LauncherLink,
    is_source: bool,
    startup: &Startup,
) -> Result<()> {
    let go_service = open_events(node, &link.go_service, startup.deadline())?;
    let go = go_service
        .listener_builder()
        .create()
        .map_err(|e| anyhow!("{}: cannot create listener: {e:?}", link.go_service))?;
    let ready_service = open_events(node, &link.ready_service, startup.deadline())?;
    ready_service
        .notifier_builder()
        .create()
        .map_err(|e| anyhow!("{}: cannot create notifier: {e:?}", link.ready_service))?
        .notify()
        .map_err(|e| anyhow!("{}: notify failed: {e:?}", link.ready_service))?;
    if is_source {
        // The launcher says "go" when every node is ready: wait as long as the graph starts up.
        let graph = link.peers.all();
        let mut started = false;
        while !started {
            check_stop()?;
            if startup.expired(&graph) {
                bail!(
                    "the launcher did not say 'go', and no node of the graph made progress for {:.0} s ([graph] startup_timeout_s)",
                    startup.seconds()
                );
            }
            go.timed_wait(|_| started = true, Duration::from_millis(100))
                .map(|_| ())
                .or_else(retry_if_interrupted)
                .map_err(|e| anyhow!("go wait failed: {e:?}"))?;
        }
    }
    Ok(())
}

/// The event loop: one WaitSet over the inputs' wake-ups and a housekeeping tick; each round
/// drains every input, fires a due timer, sends what the logic produced and, on the tick,
/// checks that producers are still alive. Returns the node's message statistics.
fn event_loop(
    node: &Node<ipc::Service>,
    ctx: &NodeContext,
    logic: &mut dyn NodeLogic,
    ins: &[InPort],
    outs: &mut [OutPort],
) -> Result<NodeStats> {
    let waitset = WaitSetBuilder::new()
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<ipc::Service>()
        .map_err(|e| anyhow!("cannot create WaitSet: {e:?}"))?;
    let _guards = ins
        .iter()
        .map(|p| {
            waitset
                .attach_notification(&p.listener)
                .map_err(|e| anyhow!("cannot attach input '{}': {e:?}", p.port))
        })
        .collect::<Result<Vec<_>>>()?;
    let tick = waitset
        .attach_interval(HOUSEKEEPING)
        .map_err(|e| anyhow!("cannot attach housekeeping tick: {e:?}"))?;
    let mut stats = NodeStats::default();
    let mut outbox = Outbox::default();
    let mut housekeeping_due = false;
    let mut ended = vec![false; ins.len()];
    while !logic.finished() {
        check_stop()?;
        waitset
            .wait_and_process_once_with_timeout(
                |id| {
                    if id.has_event_from(&tick) {
                        housekeeping_due = true;
                    }
                    CallbackProgression::Continue
                },
                wait_timeout(logic),
            )
            .map_err(|e| anyhow!("WaitSet wait failed: {e:?}"))?;
        // Receive eagerly: clear wake-ups, then drain every queue.
        for (p, ended) in ins.iter().zip(ended.iter_mut()).filter(|(_, e)| !**e) {
            p.listener
                .try_wait(|_| {})
                .map_err(|e| anyhow!("input '{}': listener failed: {e:?}", p.port))?;
            *ended = drain(p, logic, &mut stats, &mut outbox)?;
        }
        if logic.next_wakeup().is_some_and(|w| w <= Instant::now()) {
            logic.on_timer(&mut outbox)?;
        }
        logic.on_drained(&mut outbox)?;
        send_all(ctx, outs, &mut outbox, &mut stats)?;
        if housekeeping_due {
            housekeeping_due = false;
            node.try_cleanup_dead_nodes();
            check_producers_alive(ins, &ended)?;
            check_stop()?;
        }
    }
    Ok(stats)
}

/// How long the WaitSet may sleep: until the logic's next timer, at most one housekeeping
/// period, and not at all while the logic has work pending.
fn wait_timeout(logic: &dyn NodeLogic) -> Duration {
    logic
        .next_wakeup()
        .map(|w| w.saturating_duration_since(Instant::now()))
        .unwrap_or(HOUSEKEEPING)
        .min(if logic.has_pending_work() {
            Duration::ZERO
        } else {
            HOUSEKEEPING
        })
}

/// An input whose producer is gone with nothing left to read, before its end of scan, is an
/// error (the producer died or exited early), not a reason to wait forever.
fn check_producers_alive(ins: &[InPort], ended: &[bool]) -> Result<()> {
    for (p, _) in ins.iter().zip(ended).filter(|(_, e)| !**e) {
        if p.publishers_now() == 0 && !has_pending(p)? {
            bail!(
                "input '{}': producer {} is gone before end of scan (it died or exited early)",
                p.port,
                p.topic
            );
        }
    }
    Ok(())
}

/// Keeps the lossless publishers alive until every subscriber has left, so nothing in flight
/// is lost when this process exits. Bounded by liveness (issue 36): a subscriber still at work
/// (beating) is waited for however long it takes; the wait fails when the subscribers made
/// no progress for twice the backpressure timeout (the launcher's stall watch normally names
/// a stuck one first). Without peers (no launcher), after twice the backpressure timeout.
fn hold_until_subscribers_left(
    node: &Node<ipc::Service>,
    ctx: &NodeContext,
    outs: &[OutPort],
    peers: &crate::watchdog::Peers,
) -> Result<()> {
    let limit = Duration::from_secs_f64(2.0 * ctx.backpressure_timeout_s);
    for o in outs.iter().filter(|o| o.delivery == Delivery::Lossless) {
        let subscribers = peers.consumers(&o.port);
        while o.subscribers_now() > 0 {
            check_stop()?;
            if subscribers.silent_longer_than(limit) {
                bail!(
                    "output '{}': {} subscriber(s) still attached after this node finished, and they made no progress for {:.0} s: a downstream node does not drain",
                    o.port,
                    o.subscribers_now(),
                    limit.as_secs_f64()
                );
            }
            node.try_cleanup_dead_nodes();
            std::thread::sleep(Duration::from_millis(10));
        }
    }
    Ok(())
}

fn has_pending(p: &InPort) -> Result<bool> {
    match &p.receiver {
        Receiver::Frames(_, s) => s.has_samples(),
        Receiver::Registrations(_, s) => s.has_samples(),
    }
    .map_err(|e| anyhow!("input '{}': {e:?}", p.port))
}

/// Drains one input; returns true once its end-of-scan marker was delivered.
fn drain(
    p: &InPort,
    logic: &mut dyn NodeLogic,
    stats: &mut NodeStats,
    outbox: &mut Outbox,
) -> Result<bool> {
    loop {
        let end = match &p.receiver {
            Receiver::Frames(_, s) => {
                let Some(sample) = s.receive().map_err(|e| {
                    anyhow!("input '{}' ({}): receive failed: {e:?}", p.port, p.topic)
                })?
                else {
                    return Ok(false);
                };
                let header = sample.user_header();
                let heights: &[f32] = sample.payload();
                if heights.len() != header.len() {
                    bail!(
                        "input '{}' ({}): frame {} has {} heights, header says {} rows x {} cols",
                        p.port,
                        p.topic,
                        header.sequence,
                        heights.len(),
                        header.height,
                        header.width
                    );
                }
                let input = Input::Frame(FrameView { header, heights });
                let end = input.is_end_of_scan();
                deliver(logic, stats, &p.port, input, outbox)?;
                end
            }
            Receiver::Registrations(_, s) => {
                let Some(sample) = s.receive().map_err(|e| {
                    anyhow!("input '{}' ({}): receive failed: {e:?}", p.port, p.topic)
                })?
                else {
                    return Ok(false);
                };
                let input = Input::Registration(sample.payload());
                let end = input.is_end_of_scan();
                deliver(logic, stats, &p.port, input, outbox)?;
                end
            }
        };
        if end {
            return Ok(true);
        }
    }
}

fn send_all(
    ctx: &NodeContext,
    outs: &mut [OutPort],
    outbox: &mut Outbox,
    stats: &mut NodeStats,
) -> Result<()> {
    for (port, mut msg) in outbox.take() {
        let o = stamp_for_port(ctx, outs, &port, &mut msg)?;
        let receivers = match (&o.sender, &mut msg) {
            (Sender::Frames(_, publisher), Output::Frame(f)) => {
                let mut sample = publisher.loan_slice_uninit(f.heights.len()).map_err(|e| {
                    anyhow!("output '{port}': cannot loan {} heights: {e:?}", f.heights.len())
                })?;
                *sample.user_header_mut() = f.header;
                copy_releasing_source(&mut f.heights, sample.payload_mut());
                // SAFETY: copy_releasing_source wrote every element (equal lengths: the loan
                // was made for f.heights.len()).
                let sample = unsafe { sample.assume_init() };
                sample.send()
            }
            (Sender::Registrations(_, publisher), Output::Registration(r)) => {
                let sample = publisher
                    .loan_uninit()
                    .map_err(|e| anyhow!("output '{port}': cannot loan: {e:?}"))?;
                sample.write_payload(*r).send()
            }
            _ => bail!("node '{}': wrong message kind for output '{port}'", ctx.node_id),
        }
        .map_err(|e| {
            anyhow!(
                "output '{port}': send failed (a subscriber's queue stayed full for {:.0} s, or it died): {e:?}",
                ctx.backpressure_timeout_s
            )
        })?;
        if receivers < o.expected {
            bail!(
                "output '{port}': message {} reached {receivers} of {} subscribers: a lossless channel must not drop",
                o.sequence - 1,
                o.expected
            );
        }
        o.wake
            .notify_with_custom_event_id(EventId::new(EVENT_DATA))
            .map_err(|e| anyhow!("output '{port}': wake-up notify failed: {e:?}"))?;
        stats.on_sent(&port, &msg, receivers);
    }
    Ok(())
}

/// Heights copied per band by [`copy_releasing_source`] (16 MiB).
const RELEASE_BAND: usize = 1 << 22;

/// Copies a frame's heights into its loaned sample band by band, handing each copied band's
/// whole pages back to the system (`MADV_DONTNEED`: they read as zero afterwards). The frame is
/// dropped right after the send, so its values are not needed again; without this, a final
/// panorama (4 B/px) existed twice, in the node's memory and in shared memory, at the peak.
fn copy_releasing_source(src: &mut [f32], dst: &mut [std::mem::MaybeUninit<f32>]) {
    for (s, d) in src
        .chunks_mut(RELEASE_BAND)
        .zip(dst.chunks_mut(RELEASE_BAND))
    {
        for (d, &v) in d.iter_mut().zip(s.iter()) {
            d.write(v);
        }
        release_pages(s);
    }
}

/// Returns the whole pages inside `values` to the system; they read as 0.0 afterwards.
fn release_pages(values: &mut [f32]) {
    // SAFETY: sysconf has no preconditions.
    let page = match usize::try_from(unsafe { libc::sysconf(libc::_SC_PAGESIZE) }) {
        Ok(p) if p > 0 => p,
        _ => return,
    };
    let start = values.as_mut_ptr() as usize;
    let end = start + std::mem::size_of_val(values);
    let (first, last) = (start.div_ceil(page) * page, end / page * page);
    if last > first {
        // SAFETY: [first, last) lies inside `values`, which we borrow mutably, in private
        // anonymous memory (the heap or a mapping of its own); MADV_DONTNEED makes those pages
        // read as zero, a valid f32, and touches nothing outside them (the allocator's own
        // bookkeeping sits outside the slice).
        unsafe {
            libc::madvise(
                first as *mut libc::c_void,
                last - first,
                libc::MADV_DONTNEED,
            );
        }
    }
}

#[cfg(test)]
mod release_tests {
    use super::*;

    #[test]
    fn a_frame_copied_into_its_sample_arrives_whole_and_its_source_pages_go_back() {
        let n = RELEASE_BAND * 2 + 12345;
        let mut src: Vec<f32> = (0..n).map(|i| i as f32 * 0.25 - 7.0).collect();
        let want = src.clone();
        let mut dst = vec![std::mem::MaybeUninit::<f32>::uninit(); n];
        copy_releasing_source(&mut src, &mut dst);
        // SAFETY: every element was written.
        let got: Vec<f32> = dst.iter().map(|v| unsafe { v.assume_init() }).collect();
        assert_eq!(got, want);
        // The whole pages inside each band were released: they read as zero now (read
        // volatile: the compiler cannot know that madvise changed them). A band's partial
        // first and last pages keep their values.
        let released = src[RELEASE_BAND / 2..RELEASE_BAND / 2 + 4096]
            .iter()
            // SAFETY: a reference to an initialised f32.
            .all(|v| unsafe { std::ptr::read_volatile(v) } == 0.0);
        assert!(released);
    }
}
