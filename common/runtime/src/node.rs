//! The contract between a node's algorithm and the two ways of running a graph.
//!
//! A node is a [`NodeLogic`]: it is handed every received message in channel order
//! ([`NodeLogic::on_input`], cheap: apply it to local state), then once per wake-up, after the
//! queues were drained, asked to compute on the coalesced state ([`NodeLogic::on_drained`]).
//! It never sees a transport: the same logic runs as a process over iceoryx2
//! ([`crate::ipc`]) and as a thread over crossbeam ([`crate::inproc`]), which is why the two
//! modes give bit-identical outputs.

use std::collections::BTreeMap;
use std::time::Instant;

use anyhow::Context;
use serde::{Deserialize, Serialize};

use surfstream_core::frame::{monotonic_ns, FrameHeader, FrameView, HeightMap, TileRegistration};

/// A received message, borrowed (from shared memory under `launch`).
#[derive(Debug, Clone, Copy)]
pub enum Input<'a> {
    Frame(FrameView<'a>),
    Registration(&'a TileRegistration),
}

impl Input<'_> {
    pub fn is_end_of_scan(&self) -> bool {
        match self {
            Input::Frame(f) => f.header.has(surfstream_core::flags::END_OF_SCAN),
            Input::Registration(r) => r.has(surfstream_core::flags::END_OF_SCAN),
        }
    }
    fn trace(&self) -> (u32, u64, u64, u32, u32) {
        match self {
            Input::Frame(f) => (
                f.header.tile_index,
                f.header.t_acquired_ns,
                f.header.t_sent_ns,
                f.header.kind,
                f.header.flags,
            ),
            Input::Registration(r) => (r.tile_index, r.t_acquired_ns, r.t_sent_ns, 0, r.flags),
        }
    }
}

/// An output port as a transport holds it: its name and its message counter.
pub(crate) trait SequencedPort {
    fn port_name(&self) -> &str;
    /// The sequence number of the next message, advanced.
    fn next_sequence(&mut self) -> u64;
}

/// Finds the output port `port` of `ctx`'s node among `ports` and stamps `msg` with the port's
/// next sequence number, the scan id and the send time: the same for both transports, so
/// `run` and `launch` number messages alike.
pub(crate) fn stamp_for_port<'p, P: SequencedPort>(
    ctx: &crate::graph::NodeContext,
    ports: &'p mut [P],
    port: &str,
    msg: &mut Output,
) -> anyhow::Result<&'p mut P> {
    let p = ports
        .iter_mut()
        .find(|p| p.port_name() == port)
        .ok_or_else(|| {
            anyhow::anyhow!(
                "node '{}' sent on unknown output port '{port}'",
                ctx.node_id
            )
        })?;
    msg.stamp(p.next_sequence(), ctx.scan_id);
    Ok(p)
}

/// A message a node publishes.
#[derive(Debug, Clone, PartialEq)]
pub enum Output {
    Frame(HeightMap),
    Registration(TileRegistration),
}

impl Output {
    pub fn is_end_of_scan(&self) -> bool {
        match self {
            Output::Frame(f) => f.header.has(surfstream_core::flags::END_OF_SCAN),
            Output::Registration(r) => r.has(surfstream_core::flags::END_OF_SCAN),
        }
    }
    /// Stamps the per-channel sequence number and the send time.
    pub fn stamp(&mut self, sequence: u64, scan_id: u64) {
        let now = monotonic_ns();
        match self {
            Output::Frame(f) => {
                f.header.sequence = sequence;
                f.header.scan_id = scan_id;
                f.header.t_sent_ns = now;
            }
            Output::Registration(r) => {
                r.sequence = sequence;
                r.scan_id = scan_id;
                r.t_sent_ns = now;
            }
        }
    }
    fn trace(&self) -> (u32, u64, u64, u32, u32) {
        match self {
            Output::Frame(f) => (
                f.header.tile_index,
                f.header.t_acquired_ns,
                f.header.t_sent_ns,
                f.header.kind,
                f.header.flags,
            ),
            Output::Registration(r) => (r.tile_index, r.t_acquired_ns, r.t_sent_ns, 0, r.flags),
        }
    }
}

/// Messages produced during one callback, sent by the runtime when the callback returns.
#[derive(Debug, Default)]
pub struct Outbox {
    pub(crate) items: Vec<(String, Output)>,
}

impl Outbox {
    pub fn send_frame(&mut self, port: &str, frame: HeightMap) {
        self.items.push((port.to_string(), Output::Frame(frame)));
    }
    pub fn send_registration(&mut self, port: &str, reg: TileRegistration) {
        self.items
            .push((port.to_string(), Output::Registration(reg)));
    }
    /// Closes a frame port: the END_OF_SCAN marker.
    pub fn end_frames(&mut self, port: &str, tile_index: u32, t_acquired_ns: u64) {
        self.send_frame(
            port,
            HeightMap {
                header: FrameHeader::end_of_scan(0, 0, tile_index, t_acquired_ns),
                heights: Vec::new(),
            },
        );
    }
    /// Closes a registration port.
    pub fn end_registrations(&mut self, port: &str, tile_index: u32, t_acquired_ns: u64) {
        self.send_registration(
            port,
            TileRegistration {
                tile_index,
                flags: surfstream_core::flags::END_OF_SCAN,
                t_acquired_ns,
                ..Default::default()
            },
        );
    }
    pub fn take(&mut self) -> Vec<(String, Output)> {
        std::mem::take(&mut self.items)
    }
    pub fn is_empty(&self) -> bool {
        self.items.is_empty()
    }
}

/// A node's algorithm, as the runtimes drive it.
pub trait NodeLogic {
    /// One received message, in channel order. Apply it to local state; defer heavy work to
    /// [`NodeLogic::on_drained`].
    fn on_input(&mut self, port: &str, input: Input<'_>, out: &mut Outbox) -> anyhow::Result<()>;

    /// All input queues were drained: compute once on the coalesced state.
    fn on_drained(&mut self, out: &mut Outbox) -> anyhow::Result<()>;

    /// Sources (no inputs): when to be called next by [`NodeLogic::on_timer`]; `None` = never.
    fn next_wakeup(&self) -> Option<Instant> {
        None
    }

    /// Sources: the time from [`NodeLogic::next_wakeup`] has come.
    fn on_timer(&mut self, _out: &mut Outbox) -> anyhow::Result<()> {
        Ok(())
    }

    /// More to do without new input (e.g. the final pass after the last live outputs went
    /// out): the runtime calls [`NodeLogic::on_drained`] again without waiting.
    fn has_pending_work(&self) -> bool {
        false
    }

    /// Everything final is out, every output port closed: the node may exit.
    fn finished(&self) -> bool;

    /// Node-specific facts for run.json (positions, qualities, files written, ...). An error
    /// (a record that cannot be written as JSON) fails the node instead of writing `null`.
    fn report(&self) -> anyhow::Result<serde_json::Value> {
        Ok(serde_json::Value::Null)
    }
}

/// One message as seen on the wire, for latency accounting.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct TraceEvent {
    pub tile_index: u32,
    pub kind: u32,
    pub flags: u32,
    pub t_acquired_ns: u64,
    pub t_sent_ns: u64,
    /// Receive time (received messages only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub t_received_ns: Option<u64>,
}

/// Message counts and traces of one node, per port.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct NodeStats {
    /// input port -> events
    pub received: BTreeMap<String, Vec<TraceEvent>>,
    /// output port -> events
    pub sent: BTreeMap<String, Vec<TraceEvent>>,
    /// output port -> sum of receiver counts reported by the transport
    pub deliveries: BTreeMap<String, u64>,
}

impl NodeStats {
    pub fn on_received(&mut self, port: &str, input: &Input<'_>) {
        record(
            &mut self.received,
            port,
            input.trace(),
            Some(monotonic_ns()),
        );
    }
    pub fn on_sent(&mut self, port: &str, output: &Output, receivers: usize) {
        record(&mut self.sent, port, output.trace(), None);
        *self.deliveries.entry(port.to_string()).or_default() += receivers as u64;
    }
}

fn record(
    events: &mut BTreeMap<String, Vec<TraceEvent>>,
    port: &str,
    (tile_index, t_acquired_ns, t_sent_ns, kind, flags): (u32, u64, u64, u32, u32),
    t_received_ns: Option<u64>,
) {
    events
        .entry(port.to_string())
        .or_default()
        .push(TraceEvent {
            tile_index,
            kind,
            flags,
            t_acquired_ns,
            t_sent_ns,
            t_received_ns,
        });
}

/// What a node leaves behind for the launcher: written to `<out>/nodes/<id>.json` by a process,
/// handed over directly by a thread.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct NodeReport {
    pub node_id: String,
    pub node_kind: String,
    pub stats: NodeStats,
    pub report: serde_json::Value,
    /// CLOCK_MONOTONIC when the node finished.
    pub t_finished_ns: u64,
    /// Peak resident memory of the node's process when it finished (VmHWM, bytes): its own
    /// under `launch`, the whole process (every node) under `run`. `None` off Linux.
    #[serde(default)]
    pub peak_rss_bytes: Option<u64>,
}

/// This process's peak resident memory so far (VmHWM of /proc/self/status), in bytes.
pub fn peak_rss_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

impl NodeReport {
    /// The report of a node that has just finished; its logic's report failing is the node's
    /// failure (both transports name the node's id around this error).
    pub fn finished(
        ctx: &crate::graph::NodeContext,
        stats: NodeStats,
        logic: &dyn NodeLogic,
    ) -> anyhow::Result<Self> {
        let report = logic
            .report()
            .with_context(|| format!("the {} node's report cannot be written", ctx.node_kind))?;
        Ok(NodeReport {
            node_id: ctx.node_id.clone(),
            node_kind: ctx.node_kind.clone(),
            stats,
            report,
            t_finished_ns: monotonic_ns(),
            peak_rss_bytes: peak_rss_bytes(),
        })
    }
}

/// Feeds one message to the logic and records it.
pub(crate) fn deliver(
    logic: &mut dyn NodeLogic,
    stats: &mut NodeStats,
    port: &str,
    input: Input<'_>,
    out: &mut Outbox,
) -> anyhow::Result<()> {
    stats.on_received(port, &input);
    logic.on_input(port, input, out)
}
