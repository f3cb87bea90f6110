//! `surfstream run`: the whole graph in one process, nodes as threads joined by crossbeam
//! channels, calling the same [`NodeLogic`] as the processes do.
//!
//! Channels are bounded (backpressure) and a send that waits longer than the graph's
//! backpressure timeout fails loudly, as over iceoryx2. A node whose upstream disappears
//! without an end-of-scan marker fails; the first failure is reported with its node.
//!
//! Liveness, as under `launch` ([`crate::watchdog`]): every node thread beats (its loop, a send
//! waiting on a full queue, and the long computations through `surfstream_core::liveness`),
//! and [`run_graph_supervised`] names a node silent for the stall deadline and stops the
//! graph, as it does on a stop signal ([`crate::stop`]): a hung read (a FIFO as a tile file)
//! no longer hangs `run` silently.

use std::cell::RefCell;
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Result};
use crossbeam_channel::{bounded, Receiver, Select, SendTimeoutError, Sender, TrySendError};

use crate::graph::{Delivery, NodeContext};
use crate::node::{
    deliver, stamp_for_port, Input, NodeLogic, NodeReport, NodeStats, Outbox, Output, SequencedPort,
};

/// Queue depth of a lossless in-process channel.
const LOSSLESS_DEPTH: usize = 16;
/// How often an idle node without timers looks up (sources need their wake-ups only).
const HOUSEKEEPING: Duration = Duration::from_millis(500);

type Message = Arc<Output>;
/// One consumer of an output port: its id, the sender of its queue, its heartbeat.
type Consumer = (String, Sender<Message>, Arc<Beat>);
/// (producer id, output port) -> its consumers.
type Fanout = BTreeMap<(String, String), Vec<Consumer>>;

struct InputChannel {
    port: String,
    topic: String,
    rx: Receiver<Message>,
    ended: bool,
}

struct OutputChannel {
    port: String,
    delivery: Delivery,
    txs: Vec<Consumer>,
    sequence: u64,
}

impl SequencedPort for OutputChannel {
    fn port_name(&self) -> &str {
        &self.port
    }
    fn next_sequence(&mut self) -> u64 {
        self.sequence += 1;
        self.sequence - 1
    }
}

/// Marks failures that are consequences of another node's failure (a closed channel), so the
/// root cause is what gets reported.
#[derive(Debug)]
struct Consequence(String);
impl std::fmt::Display for Consequence {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}
impl std::error::Error for Consequence {}

/// A node ready to run as a thread.
pub struct InProcessNode {
    pub context: NodeContext,
    pub logic: Box<dyn NodeLogic + Send>,
}

/// Process-wide clock of the in-process heartbeats.
fn epoch() -> Instant {
    static EPOCH: OnceLock<Instant> = OnceLock::new();
    *EPOCH.get_or_init(Instant::now)
}

fn now_ns() -> u64 {
    epoch().elapsed().as_nanos() as u64
}

/// The last beat of one node thread (ns since [`epoch`]).
#[derive(Default)]
struct Beat(AtomicU64);

impl Beat {
    fn beat(&self) {
        self.0.store(now_ns(), Ordering::Relaxed);
    }
    fn silent_for(&self) -> Duration {
        Duration::from_nanos(now_ns().saturating_sub(self.0.load(Ordering::Relaxed)))
    }
    /// How long the node made no progress: its own silence, unless worker threads (a
    /// computation fanned out with rayon, which beat anonymously) were busy meanwhile.
    fn no_progress_for(&self) -> Duration {
        self.silent_for().min(anonymous_silence())
    }
}

/// How long since a thread that runs no node last beat.
fn anonymous_silence() -> Duration {
    Duration::from_nanos(now_ns().saturating_sub(ANONYMOUS_BEAT.load(Ordering::Relaxed)))
}

thread_local! {
    /// The heartbeat of the node this thread runs (none on other threads).
    static CURRENT: RefCell<Option<Arc<Beat>>> = const { RefCell::new(None) };
}
/// Beats from threads that run no node (rayon workers of a node's computation).
static ANONYMOUS_BEAT: AtomicU64 = AtomicU64::new(0);

/// The core's liveness hook under `run`: the calling node thread's heartbeat.
fn beat_current() {
    let mine = CURRENT.with(|c| c.borrow().as_ref().map(|b| b.beat()).is_some());
    if !mine {
        ANONYMOUS_BEAT.store(now_ns(), Ordering::Relaxed);
    }
}

/// How [`run_graph_supervised`] watches the graph.
#[derive(Debug, Clone, Copy)]
pub struct Supervision {
    /// A node thread silent this long is named and the graph stopped (`[graph]
    /// stall_timeout_s`).
    pub stall_timeout: Duration,
    /// How long the threads get to end after a stop (stall or signal) before the run returns
    /// its error without them.
    pub grace: Duration,
}

/// Runs every node on its own thread until all finish; returns their reports in graph order.
pub fn run_graph(nodes: Vec<InProcessNode>) -> Result<Vec<NodeReport>> {
    run_graph_supervised(nodes, None)
}

/// [`run_graph`] with a stall watch and the stop signals of [`crate::stop`] (`None`: no watch,
/// the threads are joined as they end).
pub fn run_graph_supervised(
    nodes: Vec<InProcessNode>,
    supervision: Option<Supervision>,
) -> Result<Vec<NodeReport>> {
    surfstream_core::liveness::set_hook(beat_current);
    let stop = Arc::new(AtomicBool::new(false));
    // One channel per (consumer, input port); producers keep the senders.
    let mut senders: Fanout = BTreeMap::new();
    let mut receivers: Vec<Vec<InputChannel>> = Vec::new();
    // Every node's heartbeat, made before any thread starts: a sender waiting on a full queue
    // judges the wait by its consumer's progress (issue 36).
    let beats: Vec<Arc<Beat>> = nodes
        .iter()
        .map(|_| {
            let b = Arc::new(Beat::default());
            b.beat();
            b
        })
        .collect();
    for (n, beat) in nodes.iter().zip(&beats) {
        let mut ins = Vec::new();
        for i in &n.context.inputs {
            let depth = match i.delivery {
                Delivery::Lossless => LOSSLESS_DEPTH,
                Delivery::LatestWins => 1,
            };
            let (tx, rx) = bounded(depth);
            senders
                .entry((i.from_node.clone(), i.from_port.clone()))
                .or_default()
                .push((n.context.node_id.clone(), tx, beat.clone()));
            ins.push(InputChannel {
                port: i.port.clone(),
                topic: i.topic(),
                rx,
                ended: false,
            });
        }
        receivers.push(ins);
    }
    let mut handles = Vec::new();
    for ((n, inputs), beat) in nodes.into_iter().zip(receivers).zip(beats) {
        let outputs = n
            .context
            .outputs
            .iter()
            .map(|o| OutputChannel {
                port: o.port.clone(),
                delivery: o.delivery,
                txs: senders
                    .remove(&(n.context.node_id.clone(), o.port.clone()))
                    .unwrap_or_default(),
                sequence: 0,
            })
            .collect();
        let id = n.context.node_id.clone();
        let (thread_beat, thread_stop) = (beat.clone(), stop.clone());
        let handle = std::thread::Builder::new()
            .name(id.clone())
            .spawn(move || {
                CURRENT.with(|c| *c.borrow_mut() = Some(thread_beat));
                run_node(n.context, n.logic, inputs, outputs, &thread_stop)
            })
            .map_err(|e| anyhow!("cannot start thread for node '{id}': {e}"))?;
        handles.push((id, handle, beat));
    }
    if let Some(sup) = supervision {
        if let Some(reason) = watch(&handles, &sup) {
            // Every node stops at its next step; a thread stuck in a read or a computation is
            // left behind (the process ends after the error is recorded).
            stop.store(true, Ordering::SeqCst);
            let deadline = Instant::now() + sup.grace;
            while Instant::now() < deadline && handles.iter().any(|(_, h, _)| !h.is_finished()) {
                std::thread::sleep(Duration::from_millis(20));
            }
            for (_, h, _) in handles {
                if h.is_finished() {
                    let _ = h.join();
                }
            }
            return Err(reason);
        }
    }
    let handles: Vec<_> = handles.into_iter().map(|(id, h, _)| (id, h)).collect();
    let mut reports = Vec::new();
    let mut errors: Vec<(String, anyhow::Error)> = Vec::new();
    for (id, h) in handles {
        match h.join() {
            Ok(Ok(r)) => reports.push(r),
            Ok(Err(e)) => errors.push((id, e)),
            Err(_) => errors.push((id, anyhow!("panicked"))),
        }
    }
    if !errors.is_empty() {
        // Nodes that saw the stop request before the watch did: the signal is the cause.
        if let Some(sig) = crate::stop::signal() {
            return Err(crate::stop::interrupted(sig));
        }
        // An error of the operating system (a full disk) is the cause before any other.
        let root = errors
            .iter()
            .position(|(_, e)| crate::stdio::is_no_space(e))
            .or_else(|| {
                errors
                    .iter()
                    .position(|(_, e)| e.downcast_ref::<Consequence>().is_none())
            })
            .unwrap_or(0);
        let (id, e) = errors.swap_remove(root);
        bail!("node '{id}' failed: {e:#}");
    }
    Ok(reports)
}

type Handles = Vec<(
    String,
    std::thread::JoinHandle<Result<NodeReport>>,
    Arc<Beat>,
)>;

/// Waits until every thread ended (`None`), or a stop signal or a stall says to stop the graph.
fn watch(handles: &Handles, sup: &Supervision) -> Option<anyhow::Error> {
    loop {
        if let Some(sig) = crate::stop::signal() {
            return Some(crate::stop::interrupted(sig));
        }
        if handles.iter().all(|(_, h, _)| h.is_finished()) {
            return None;
        }
        let anonymous = anonymous_silence();
        let stalled = handles
            .iter()
            .filter(|(_, h, _)| !h.is_finished())
            .map(|(id, _, b)| (id, b.silent_for()))
            .filter(|(_, silent)| *silent > sup.stall_timeout)
            .max_by_key(|(_, silent)| *silent);
        // A computation fanned out to worker threads beats from them: not a stall.
        if let Some((id, silent)) = stalled.filter(|_| anonymous > sup.stall_timeout) {
            return Some(anyhow!(
                "stalled: node '{id}' made no progress for {:.0} s (hung, e.g. reading a FIFO or a dead network file, or one computation longer than [graph] stall_timeout_s = {:.0}); the graph is stopped",
                silent.as_secs_f64(),
                sup.stall_timeout.as_secs_f64()
            ));
        }
        std::thread::sleep(crate::watchdog::BEAT_PERIOD);
    }
}

fn run_node(
    ctx: NodeContext,
    mut logic: Box<dyn NodeLogic + Send>,
    mut inputs: Vec<InputChannel>,
    mut outputs: Vec<OutputChannel>,
    stop: &AtomicBool,
) -> Result<NodeReport> {
    let mut stats = NodeStats::default();
    let mut outbox = Outbox::default();
    let timeout = Duration::from_secs_f64(ctx.backpressure_timeout_s);
    while !logic.finished() {
        beat_current();
        if stop.load(Ordering::Relaxed) || crate::ipc::STOP_REQUESTED.load(Ordering::Relaxed) {
            return Err(anyhow!(Consequence(format!(
                "node '{}': stopped (the graph is being stopped)",
                ctx.node_id
            ))));
        }
        // Wait for input or the next timer, without spinning.
        let wake = logic.next_wakeup();
        let wait = wake
            .map(|w| w.saturating_duration_since(Instant::now()))
            .unwrap_or(HOUSEKEEPING)
            .min(if logic.has_pending_work() {
                Duration::ZERO
            } else {
                HOUSEKEEPING
            });
        let open: Vec<usize> = (0..inputs.len()).filter(|&i| !inputs[i].ended).collect();
        if open.is_empty() {
            if !wait.is_zero() && wake.is_some() {
                std::thread::sleep(wait);
            } else if wake.is_none() && !inputs.is_empty() && !logic.has_pending_work() {
                bail!(
                    "node '{}': all inputs ended but the node did not finish",
                    ctx.node_id
                );
            }
        } else {
            let mut sel = Select::new();
            for &i in &open {
                sel.recv(&inputs[i].rx);
            }
            let _ = sel.ready_timeout(wait);
        }
        // Receive eagerly: drain every queue.
        for ch in inputs.iter_mut().filter(|c| !c.ended) {
            loop {
                match ch.rx.try_recv() {
                    Ok(msg) => {
                        let input = match msg.as_ref() {
                            Output::Frame(f) => Input::Frame(f.view()),
                            Output::Registration(r) => Input::Registration(r),
                        };
                        let end = input.is_end_of_scan();
                        deliver(logic.as_mut(), &mut stats, &ch.port, input, &mut outbox)?;
                        if end {
                            ch.ended = true;
                            break;
                        }
                    }
                    Err(crossbeam_channel::TryRecvError::Empty) => break,
                    Err(crossbeam_channel::TryRecvError::Disconnected) => {
                        return Err(anyhow!(Consequence(format!(
                            "input '{}' ({}) closed before end of scan: its producer stopped",
                            ch.port, ch.topic
                        ))));
                    }
                }
            }
        }
        if logic.next_wakeup().is_some_and(|w| w <= Instant::now()) {
            logic.on_timer(&mut outbox)?;
        }
        // Compute lazily, once on the coalesced state.
        logic.on_drained(&mut outbox)?;
        send_all(&ctx, &mut outputs, &mut outbox, &mut stats, timeout)?;
    }
    let report = NodeReport::finished(&ctx, stats, logic.as_ref());
    // The node's state and queues go now, not when the thread is joined, and under a budget
    // their freed pages go back to the system: the nodes still running (the mesher's phase
    // after the fusion and the wavelet) then fit in what the finished ones held.
    drop((logic, inputs, outputs, outbox));
    crate::memory::release_freed_pages(ctx.memory.budget_bytes);
    report
}

fn send_all(
    ctx: &NodeContext,
    outputs: &mut [OutputChannel],
    outbox: &mut Outbox,
    stats: &mut NodeStats,
    timeout: Duration,
) -> Result<()> {
    for (port, mut msg) in outbox.take() {
        let ch = stamp_for_port(ctx, outputs, &port, &mut msg)?;
        let msg = Arc::new(msg);
        let mut delivered = 0;
        for (consumer, tx, consumer_beat) in &ch.txs {
            match ch.delivery {
                Delivery::Lossless => match send_beating(tx, msg.clone(), consumer_beat, timeout) {
                    Ok(()) => delivered += 1,
                    Err(SendTimeoutError::Timeout(_)) => bail!(
                        "output '{port}' -> '{consumer}': downstream queue full and '{consumer}' made no progress for {:.1} s (backpressure timeout)",
                        timeout.as_secs_f64()
                    ),
                    Err(SendTimeoutError::Disconnected(_)) => {
                        return Err(anyhow!(Consequence(format!(
                            "output '{port}' -> '{consumer}': the consumer is gone; message would be lost"
                        ))))
                    }
                },
                Delivery::LatestWins => match tx.try_send(msg.clone()) {
                    Ok(()) => delivered += 1,
                    Err(TrySendError::Full(_)) | Err(TrySendError::Disconnected(_)) => {}
                },
            }
        }
        stats.on_sent(&port, &msg, delivered);
    }
    Ok(())
}

/// A lossless send that waits for room, beating while it waits: the sender of a full queue is
/// alive, the receiver that does not drain is the one to name. The wait fails only when the
/// consumer made no progress (no beat of its own or of its worker threads) for `timeout`: a
/// slow consumer on a loaded machine is waited for, as under `launch` (issue 36), a stuck one
/// is not.
fn send_beating(
    tx: &Sender<Message>,
    mut msg: Message,
    consumer: &Beat,
    timeout: Duration,
) -> std::result::Result<(), SendTimeoutError<Message>> {
    loop {
        let left = timeout.saturating_sub(consumer.no_progress_for());
        match tx.send_timeout(msg, left.min(crate::watchdog::BEAT_PERIOD)) {
            Err(SendTimeoutError::Timeout(m)) if !left.is_zero() => {
                beat_current();
                if crate::ipc::STOP_REQUESTED.load(Ordering::Relaxed) {
                    return Err(SendTimeoutError::Disconnected(m));
                }
                msg = m;
            }
            other => return other,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::node::Input;

    /// A node that hangs in one call (like a read of a FIFO) without beating, or finishes.
    struct Hangs {
        hang: Option<Duration>,
        done: bool,
    }

    impl NodeLogic for Hangs {
        fn on_input(&mut self, _: &str, _: Input<'_>, _: &mut Outbox) -> Result<()> {
            Ok(())
        }
        fn on_drained(&mut self, _: &mut Outbox) -> Result<()> {
            if let Some(d) = self.hang.take() {
                std::thread::sleep(d);
            }
            self.done = true;
            Ok(())
        }
        fn finished(&self) -> bool {
            self.done
        }
    }

    fn node(id: &str, hang: Option<Duration>) -> InProcessNode {
        InProcessNode {
            context: NodeContext {
                graph_name: "g".into(),
                node_id: id.into(),
                node_kind: "test".into(),
                params: toml::Table::new(),
                out_dir: "/nonexistent".into(),
                inputs: vec![],
                outputs: vec![],
                backpressure_timeout_s: 5.0,
                startup_timeout_s: 5.0,
                scan_id: 1,
                memory: crate::memory::MemoryPlan::unlimited("/nonexistent".into()),
            },
            logic: Box::new(Hangs { hang, done: false }),
        }
    }

    #[test]
    fn a_node_hung_in_one_call_is_named_as_stalled_under_run() {
        let sup = Supervision {
            stall_timeout: Duration::from_millis(600),
            grace: Duration::from_millis(100),
        };
        let e = run_graph_supervised(
            vec![
                node("quick", None),
                node("stuck", Some(Duration::from_secs(5))),
            ],
            Some(sup),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("stalled: node 'stuck' made no progress"), "{e}");
        // Nodes that finish in time are not stalls.
        let ok = run_graph_supervised(
            vec![node("quick", Some(Duration::from_millis(50)))],
            Some(sup),
        );
        assert!(ok.is_ok());
    }

    /// Sends `count` registrations on "out", then its end marker.
    struct Burst {
        count: u32,
        sent: bool,
    }

    impl NodeLogic for Burst {
        fn on_input(&mut self, _: &str, _: Input<'_>, _: &mut Outbox) -> Result<()> {
            Ok(())
        }
        fn on_drained(&mut self, out: &mut Outbox) -> Result<()> {
            if !self.sent {
                for k in 0..self.count {
                    let reg = surfstream_core::TileRegistration {
                        tile_index: k,
                        ..Default::default()
                    };
                    out.send_registration("out", reg);
                }
                out.end_registrations("out", self.count, 0);
                self.sent = true;
            }
            Ok(())
        }
        fn finished(&self) -> bool {
            self.sent
        }
    }

    /// Takes `first_call` on its first message (beating every 20 ms through the core's
    /// liveness hook, or silent), then drains the rest at once.
    struct SlowFirst {
        first_call: Duration,
        beats: bool,
        seen: u32,
        ended: bool,
    }

    impl NodeLogic for SlowFirst {
        fn on_input(&mut self, _: &str, input: Input<'_>, _: &mut Outbox) -> Result<()> {
            if input.is_end_of_scan() {
                self.ended = true;
                return Ok(());
            }
            if self.seen == 0 {
                let t0 = Instant::now();
                while t0.elapsed() < self.first_call {
                    std::thread::sleep(Duration::from_millis(20));
                    if self.beats {
                        surfstream_core::liveness::beat();
                    }
                }
            }
            self.seen += 1;
            Ok(())
        }
        fn on_drained(&mut self, _: &mut Outbox) -> Result<()> {
            Ok(())
        }
        fn finished(&self) -> bool {
            self.ended
        }
        fn report(&self) -> anyhow::Result<serde_json::Value> {
            Ok(serde_json::json!({ "seen": self.seen }))
        }
    }

    fn wired(backpressure_timeout_s: f64, first_call: Duration, beats: bool) -> Vec<InProcessNode> {
        use crate::graph::{InputSpec, OutputSpec, PortKind};
        let ctx = |id: &str| NodeContext {
            node_id: id.into(),
            backpressure_timeout_s,
            ..node(id, None).context
        };
        let mut src = ctx("src");
        src.outputs = vec![OutputSpec {
            port: "out".into(),
            kind: PortKind::Registrations,
            delivery: Delivery::Lossless,
            subscribers: 1,
        }];
        let mut slow = ctx("slow");
        slow.inputs = vec![InputSpec {
            port: "in".into(),
            from_node: "src".into(),
            from_port: "out".into(),
            kind: PortKind::Registrations,
            delivery: Delivery::Lossless,
            producer_subscribers: 1,
        }];
        vec![
            InProcessNode {
                context: src,
                logic: Box::new(Burst {
                    count: LOSSLESS_DEPTH as u32 + 4,
                    sent: false,
                }),
            },
            InProcessNode {
                context: slow,
                logic: Box::new(SlowFirst {
                    first_call,
                    beats,
                    seen: 0,
                    ended: false,
                }),
            },
        ]
    }

    /// Issue 36: under `run` a lossless send blocked by a full queue fails only when its
    /// consumer made no progress for the backpressure timeout, as under `launch`. A consumer
    /// that works (and beats) for 4x the timeout on one message is slow, not stuck: every
    /// message arrives (before, the send failed after the timeout of wall-clock waiting). A
    /// consumer silent for that long is still named.
    #[test]
    fn a_send_waits_for_a_slow_consumer_that_beats_and_fails_for_a_silent_one() {
        let timeout_s = 1.0;
        let reports = run_graph(wired(timeout_s, Duration::from_secs(4), true))
            .expect("a slow consumer that beats is waited for");
        let seen = reports
            .iter()
            .find(|r| r.node_id == "slow")
            .map(|r| r.report["seen"].as_u64());
        assert_eq!(seen, Some(Some(LOSSLESS_DEPTH as u64 + 4)), "{reports:?}");
        let e = run_graph(wired(timeout_s, Duration::from_secs(4), false))
            .expect_err("a silent consumer was waited for");
        let e = format!("{e:#}");
        assert!(
            e.contains("node 'src' failed")
                && e.contains("'slow' made no progress for 1.0 s (backpressure timeout)"),
            "{e}"
        );
    }

    /// A node whose report cannot be written as JSON (a map keyed by pairs): the run fails
    /// naming the node and the record, instead of recording `null` for it.
    struct UnwritableReport;

    impl NodeLogic for UnwritableReport {
        fn on_input(&mut self, _: &str, _: Input<'_>, _: &mut Outbox) -> Result<()> {
            Ok(())
        }
        fn on_drained(&mut self, _: &mut Outbox) -> Result<()> {
            Ok(())
        }
        fn finished(&self) -> bool {
            true
        }
        fn report(&self) -> Result<serde_json::Value> {
            let by_pair: std::collections::BTreeMap<(u32, u32), f64> =
                [((0, 1), 1.0)].into_iter().collect();
            Ok(surfstream_core::record::to_value(&by_pair)?)
        }
    }

    #[test]
    fn a_report_that_cannot_be_written_fails_the_node_by_name() {
        let n = InProcessNode {
            logic: Box::new(UnwritableReport),
            ..node("reporter", None)
        };
        let e = format!("{:#}", run_graph(vec![n]).unwrap_err());
        assert!(e.contains("node 'reporter' failed"), "{e}");
        assert!(
            e.contains("the test node's report cannot be written"),
            "{e}"
        );
        assert!(e.contains("key must be a string"), "{e}");
    }
}
