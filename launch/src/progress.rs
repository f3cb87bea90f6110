//! Progress of `launch`, `run` and `stitch`: one line per registered tile (index, grid row x
//! col, NCC, position in um, placed by registration or by stage fallback) and an ETA while the
//! stage scans; an indicatif bar above the lines when stderr is a terminal, plain lines
//! otherwise (logs, CI, tests).
//!
//! Where the launcher learns of a tile: it subscribes to the matcher's `registrations` channel
//! like any other consumer, through a small observer node added to the resolved graph
//! ([`attach_observer`]). That channel carries one ~100-byte message per tile (plus one per
//! tile after the global solve), so the observer costs nothing next to the pipeline; it only
//! hands each message to a printing thread over an unbounded in-process channel and never
//! waits on the terminal, so it drains its lossless queue at once and can never hold back the
//! matcher (the launcher is no bottleneck). Under `run` it is one more thread of the graph;
//! under `launch` a thread of the launcher with its own iceoryx2 node, taking part in the
//! startup handshake like the recorder. Node reports (run.json) come too late for progress:
//! they are written when the run ends. Its own report is left out of run.json ([`is_observer`]).

use std::io::IsTerminal;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use anyhow::Result;
use crossbeam_channel::{unbounded, Receiver, Sender};
use surfstream_core::frame::{flags, placed_by};
use surfstream_core::record::{MatcherReport, NodeRecord, ReplayReport};
use surfstream_runtime::graph::{InputSpec, NodeContext, PortKind};
use surfstream_runtime::node::{Input, NodeLogic, NodeReport, Outbox};

/// Node kind and id of the observer (never a kind a graph file may name).
pub const OBSERVER_KIND: &str = "launcher-progress";
const OBSERVER_ID: &str = "launcher-progress";
/// The matcher's output the observer reads.
const REGISTRATIONS: &str = "registrations";

/// One tile's live registration, as the matcher published it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TileEvent {
    pub index: u32,
    pub x_um: f64,
    pub y_um: f64,
    /// Best link NCC (0 if none).
    pub ncc: f64,
    /// Neighbour links tried (0: the first tile, placed where the stage put it as the anchor).
    pub links_tried: u32,
    pub by_stage: bool,
    /// The end-of-scan solve's placement (the one the panorama and run.json use), not the
    /// streaming one.
    pub is_final: bool,
}

/// Where each tile sits in the grid and how many there are, from the source's parameters
/// (`None` where the source does not say before it runs: a recording).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Layout {
    /// (row, col) by acquisition index.
    pub grid: Vec<(usize, usize)>,
    /// Tiles the source will send when it does not give a grid (a recording's tile messages,
    /// [`surfstream_replay::planned::planned_tiles`], as the live view counts them).
    pub planned: Option<usize>,
}

impl Layout {
    pub fn total(&self) -> Option<usize> {
        (!self.grid.is_empty())
            .then_some(self.grid.len())
            .or(self.planned)
    }
}

/// True for an observer's context or report (this printer's or the live view's,
/// [`crate::live`]): not part of the user's graph.
pub fn is_observer(kind: &str) -> bool {
    kind == OBSERVER_KIND || crate::live::is_observer(kind)
}

/// Removes the observer's report (run.json describes the user's graph only).
pub fn drop_observer_reports(reports: &mut Vec<NodeReport>) {
    reports.retain(|r| !is_observer(&r.node_kind));
}

/// Adds the observer to resolved contexts, subscribed to the (first) matcher's registrations:
/// the matcher's port and every other consumer of it count one more subscriber, so the
/// lossless handshake waits for the observer too. Returns false (nothing added) for a graph
/// without a matcher.
pub fn attach_observer(contexts: &mut Vec<NodeContext>) -> bool {
    if contexts.iter().any(|c| c.node_id == OBSERVER_ID) {
        return false; // a user's node has the id: no progress rather than a clash
    }
    let Some(k) = contexts.iter().position(|c| {
        c.node_kind == MatcherReport::NODE_KIND && c.outputs.iter().any(|o| o.port == REGISTRATIONS)
    }) else {
        return false;
    };
    let matcher_id = contexts[k].node_id.clone();
    let Some(out) = contexts[k]
        .outputs
        .iter_mut()
        .find(|o| o.port == REGISTRATIONS)
    else {
        return false;
    };
    out.subscribers += 1;
    let (delivery, subscribers) = (out.delivery, out.subscribers);
    for c in contexts.iter_mut() {
        for i in &mut c.inputs {
            if i.from_node == matcher_id && i.from_port == REGISTRATIONS {
                i.producer_subscribers = subscribers;
            }
        }
    }
    let mut ctx = contexts[k].clone();
    ctx.node_id = OBSERVER_ID.into();
    ctx.node_kind = OBSERVER_KIND.into();
    ctx.params = toml::Table::new();
    ctx.outputs = Vec::new();
    ctx.inputs = vec![InputSpec {
        port: REGISTRATIONS.into(),
        from_node: matcher_id,
        from_port: REGISTRATIONS.into(),
        kind: PortKind::Registrations,
        delivery,
        producer_subscribers: subscribers,
    }];
    contexts.push(ctx);
    true
}

/// The grid of the graph's source node: the simulated stage's serpentine, or a scan
/// directory's `[[tile]]` list.
pub fn layout(contexts: &[NodeContext]) -> Layout {
    let Some(src) = contexts
        .iter()
        .find(|c| c.node_kind == ReplayReport::NODE_KIND)
    else {
        return Layout::default();
    };
    // The node's own reading of its parameters; a table it refuses has no layout (the
    // launcher's check names what is wrong).
    let Ok(config) = surfstream_replay::Config::from_table(&src.params) else {
        return Layout::default();
    };
    match &config {
        surfstream_replay::Config::Simulated(p) => {
            let (rows, cols) = (p.stage.rows, p.stage.cols);
            if rows.saturating_mul(cols) > surfstream_replay::stage::MAX_TILES {
                return Layout::default();
            }
            Layout {
                grid: surfstream_replay::serpentine_order(rows, cols),
                planned: None,
            }
        }
        surfstream_replay::Config::Scan(s) => scan_layout(&s.manifest()),
        surfstream_replay::Config::Mcap(_) => Layout {
            grid: Vec::new(),
            planned: surfstream_replay::planned::planned_tiles(&config),
        },
    }
}

/// The `[[tile]]` rows and cols of a scan.toml (the loader checks the rest when the run starts).
fn scan_layout(manifest: &std::path::Path) -> Layout {
    #[derive(serde::Deserialize)]
    struct Tile {
        row: usize,
        col: usize,
    }
    #[derive(serde::Deserialize)]
    struct Manifest {
        #[serde(default)]
        tile: Vec<Tile>,
    }
    std::fs::read_to_string(manifest)
        .ok()
        .and_then(|t| toml::from_str::<Manifest>(&t).ok())
        .map(|m| Layout {
            grid: m.tile.iter().map(|t| (t.row, t.col)).collect(),
            planned: None,
        })
        .unwrap_or_default()
}

/// The observer's logic: forwards each live registration to the printer, never blocks.
struct Observer {
    tx: Sender<TileEvent>,
    done: bool,
}

impl NodeLogic for Observer {
    fn on_input(&mut self, _port: &str, input: Input<'_>, _: &mut Outbox) -> Result<()> {
        if let Input::Registration(r) = input {
            if r.has(flags::END_OF_SCAN) {
                self.done = true;
            } else {
                // The printer may have gone (terminal closed): progress is best effort.
                let _ = self.tx.send(TileEvent {
                    index: r.tile_index,
                    x_um: r.x_um,
                    y_um: r.y_um,
                    ncc: r.quality,
                    links_tried: r.links_tried,
                    by_stage: r.placed_by == placed_by::STAGE,
                    is_final: r.has(flags::FINAL),
                });
            }
        }
        Ok(())
    }
    fn on_drained(&mut self, _: &mut Outbox) -> Result<()> {
        Ok(())
    }
    fn finished(&self) -> bool {
        self.done
    }
}

/// The printing side: started before the graph, finished after it.
pub struct Progress {
    tx: Option<Sender<TileEvent>>,
    printer: Option<JoinHandle<()>>,
}

impl Progress {
    /// Starts the printer for the graph's tiles (a bar if stderr is a terminal).
    pub fn start(contexts: &[NodeContext]) -> Self {
        let layout = layout(contexts);
        let (tx, rx) = unbounded();
        let bar = std::io::stderr().is_terminal();
        let printer = std::thread::Builder::new()
            .name("progress".into())
            .spawn(move || print_events(rx, layout, bar))
            .ok();
        Progress {
            tx: Some(tx),
            printer,
        }
    }

    /// The observer node's logic, feeding this printer.
    pub fn observer(&self) -> Box<dyn NodeLogic + Send> {
        let (dead, _) = unbounded();
        Box::new(Observer {
            tx: self.tx.clone().unwrap_or(dead),
            done: false,
        })
    }

    /// Waits for the last line to be printed.
    pub fn finish(mut self) {
        self.tx = None;
        if let Some(p) = self.printer.take() {
            let _ = p.join();
        }
    }
}

/// One progress line: "tile 3/4  row 1 x col 0  NCC 0.991  at (14.10, 223.55) um  registration".
pub fn line(e: &TileEvent, layout: &Layout, done: usize, eta: Option<Duration>) -> String {
    let of = layout.total().map(|t| format!("/{t}")).unwrap_or_default();
    let grid = layout
        .grid
        .get(e.index as usize)
        .map(|(r, c)| format!("row {r} x col {c}"))
        .unwrap_or_else(|| "row ? x col ?".into());
    let eta = eta
        .map(|d| format!("  ETA {}", human(d)))
        .unwrap_or_default();
    let (ncc, how) = match (e.by_stage, e.links_tried) {
        (true, _) => (format!("NCC {:.3}", e.ncc), "STAGE FALLBACK"),
        (false, 0) => ("NCC   -  ".to_string(), "anchor (no neighbour yet)"),
        (false, _) => (format!("NCC {:.3}", e.ncc), "registration"),
    };
    format!(
        "tile {}{of} ({done} done)  {grid}  {ncc}  at ({:.2}, {:.2}) um  {how}{eta}",
        e.index, e.x_um, e.y_um,
    )
}

/// The line that corrects a tile's streaming line when the end-of-scan solve placed it the
/// other way (the verdict and run.json count the final placement, which the panorama uses):
/// `None` when both agree.
pub fn final_differs(
    e: &TileEvent,
    streaming_by_stage: Option<bool>,
    layout: &Layout,
) -> Option<String> {
    let was = streaming_by_stage?;
    if was == e.by_stage {
        return None;
    }
    let grid = layout
        .grid
        .get(e.index as usize)
        .map(|(r, c)| format!("row {r} x col {c}"))
        .unwrap_or_else(|| "row ? x col ?".into());
    Some(if e.by_stage {
        format!(
            "tile {}  {grid}  final solve: STAGE FALLBACK (its links were removed as inconsistent with the rest of the scan; the streaming line said registration)",
            e.index
        )
    } else {
        format!(
            "tile {}  {grid}  final solve: registration at ({:.2}, {:.2}) um (later tiles linked it; the streaming line said STAGE FALLBACK)",
            e.index, e.x_um, e.y_um
        )
    })
}

fn human(d: Duration) -> String {
    let s = d.as_secs();
    if s >= 60 {
        format!("{}m{:02}s", s / 60, s % 60)
    } else {
        format!("{s}s")
    }
}

/// The remaining time at the pace so far (None before the second tile or without a total).
pub fn eta(started: Instant, now: Instant, done: usize, total: Option<usize>) -> Option<Duration> {
    let total = total?;
    if done < 2 || done >= total {
        return None;
    }
    let per_tile = now.duration_since(started).as_secs_f64() / done as f64;
    Some(Duration::from_secs_f64(per_tile * (total - done) as f64))
}

fn print_events(rx: Receiver<TileEvent>, layout: Layout, bar: bool) {
    let started = Instant::now();
    // The bar appears with the first tile and goes with the last, so the launcher's own
    // lines before ("scan started") and the nodes' after (final passes) are not drawn over.
    let mut pb: Option<indicatif::ProgressBar> = None;
    let mut done = 0usize;
    // How each tile's streaming line placed it, to tell where the final solve differs.
    let mut streaming: std::collections::BTreeMap<u32, bool> = Default::default();
    for e in rx {
        if e.is_final {
            if let Some(text) = final_differs(&e, streaming.get(&e.index).copied(), &layout) {
                match &pb {
                    Some(b) => b.println(text),
                    None => eprintln!("{text}"),
                }
            }
            continue;
        }
        streaming.insert(e.index, e.by_stage);
        done += 1;
        if bar && pb.is_none() && layout.total().is_none_or(|t| done <= t) {
            pb = Some(new_bar(&layout));
        }
        // The bar shows its own ETA; plain lines carry it.
        let eta = if pb.is_some() {
            None
        } else {
            eta(started, Instant::now(), done, layout.total())
        };
        let text = line(&e, &layout, done, eta);
        match &pb {
            Some(b) => {
                b.println(text);
                b.inc(1);
                if layout.total().is_some_and(|t| done >= t) {
                    b.finish_and_clear();
                    pb = None;
                }
            }
            None => eprintln!("{text}"),
        }
    }
    if let Some(b) = pb {
        b.finish_and_clear();
    }
}

fn new_bar(layout: &Layout) -> indicatif::ProgressBar {
    let pb = match layout.total() {
        Some(t) => indicatif::ProgressBar::new(t as u64),
        None => indicatif::ProgressBar::new_spinner(),
    };
    pb.set_draw_target(indicatif::ProgressDrawTarget::stderr());
    let template = if layout.total().is_some() {
        "{spinner} [{bar:30}] {pos}/{len} tiles registered, {elapsed} elapsed, ETA {eta}"
    } else {
        "{spinner} {pos} tiles registered, {elapsed} elapsed"
    };
    if let Ok(style) = indicatif::ProgressStyle::with_template(template) {
        pb.set_style(style.progress_chars("=> "));
    }
    pb.enable_steady_tick(Duration::from_millis(200));
    pb
}

/// The launch-side observer: its own iceoryx2 node on a launcher thread. Returns when the
/// matcher's end of scan arrived, or the graph failed (the runtime's liveness checks and stop
/// flag end it).
pub fn spawn_ipc_observer(
    ctx: NodeContext,
    progress: &Progress,
    cfg: iceoryx2::config::Config,
) -> Result<JoinHandle<()>> {
    let mut logic = progress.observer();
    std::thread::Builder::new()
        .name("progress-observer".into())
        .spawn(move || {
            let link = surfstream_runtime::ipc::launcher_link(&ctx.graph_name);
            // An error here is an echo of a node's failure, which the supervisor reports;
            // the graph's outcome never depends on the observer.
            let _ = surfstream_runtime::ipc::run_node(&ctx, logic.as_mut(), &cfg, Some(&link));
        })
        .map_err(|e| anyhow::anyhow!("cannot start the progress observer thread: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use surfstream_runtime::graph::{Delivery, OutputSpec};

    fn ctx(id: &str, kind: &str) -> NodeContext {
        NodeContext {
            graph_name: "g".into(),
            node_id: id.into(),
            node_kind: kind.into(),
            params: toml::Table::new(),
            out_dir: "/tmp/x".into(),
            inputs: vec![],
            outputs: vec![],
            backpressure_timeout_s: 1.0,
            startup_timeout_s: 1.0,
            scan_id: 7,
            memory: surfstream_runtime::memory::MemoryPlan::unlimited("/tmp/x".into()),
        }
    }

    #[test]
    fn the_observer_counts_as_one_more_subscriber_of_the_registrations() {
        let mut m = ctx("matcher", "matcher");
        m.outputs.push(OutputSpec {
            port: "registrations".into(),
            kind: PortKind::Registrations,
            delivery: Delivery::Lossless,
            subscribers: 1,
        });
        let mut f = ctx("fusion", "fusion");
        f.inputs.push(InputSpec {
            port: "registrations".into(),
            from_node: "matcher".into(),
            from_port: "registrations".into(),
            kind: PortKind::Registrations,
            delivery: Delivery::Lossless,
            producer_subscribers: 1,
        });
        let mut all = vec![ctx("stage", "replay"), m, f];
        assert!(attach_observer(&mut all));
        assert_eq!(all.len(), 4);
        assert_eq!(all[1].outputs[0].subscribers, 2);
        assert_eq!(all[2].inputs[0].producer_subscribers, 2);
        let o = &all[3];
        assert!(is_observer(&o.node_kind));
        assert_eq!(o.inputs[0].producer_subscribers, 2);
        assert_eq!(o.inputs[0].topic(), "matcher/registrations");
        assert!(o.outputs.is_empty());

        let mut none = vec![ctx("stage", "replay")];
        assert!(!attach_observer(&mut none));
        assert_eq!(none.len(), 1);
    }

    #[test]
    fn a_line_names_index_grid_ncc_position_and_how_it_was_placed() {
        let mut s = ctx("stage", "replay");
        s.params.insert("source".into(), "simulated".into());
        s.params.insert("rows".into(), 2.into());
        s.params.insert("cols".into(), 3.into());
        let layout = layout(&[s]);
        assert_eq!(layout.total(), Some(6));
        // Serpentine: index 3 is row 1, col 2.
        let e = TileEvent {
            index: 3,
            x_um: 1234.5678,
            y_um: -0.004,
            ncc: 0.98765,
            links_tried: 2,
            by_stage: false,
            is_final: false,
        };
        assert_eq!(
            line(&e, &layout, 4, Some(Duration::from_secs(75))),
            "tile 3/6 (4 done)  row 1 x col 2  NCC 0.988  at (1234.57, -0.00) um  registration  ETA 1m15s"
        );
        let first = TileEvent {
            index: 0,
            links_tried: 0,
            ..e
        };
        assert_eq!(
            line(&first, &layout, 1, None),
            "tile 0/6 (1 done)  row 0 x col 0  NCC   -    at (1234.57, -0.00) um  anchor (no neighbour yet)"
        );
        let e = TileEvent {
            by_stage: true,
            ..e
        };
        assert!(line(&e, &Layout::default(), 1, None)
            .ends_with("row ? x col ?  NCC 0.988  at (1234.57, -0.00) um  STAGE FALLBACK"));
    }

    #[test]
    fn eta_is_the_pace_so_far_times_the_tiles_left() {
        let t0 = Instant::now();
        let t1 = t0 + Duration::from_secs(10);
        assert_eq!(eta(t0, t1, 2, Some(6)), Some(Duration::from_secs(20)));
        assert_eq!(eta(t0, t1, 1, Some(6)), None);
        assert_eq!(eta(t0, t1, 6, Some(6)), None);
        assert_eq!(eta(t0, t1, 3, None), None);
    }

    #[test]
    fn a_final_placement_that_differs_from_the_streaming_line_is_told() {
        let layout = Layout {
            grid: vec![(0, 0), (0, 1)],
            planned: None,
        };
        let fin = |by_stage| TileEvent {
            index: 1,
            x_um: 10.0,
            y_um: 0.0,
            ncc: 0.9,
            links_tried: 1,
            by_stage,
            is_final: true,
        };
        // Streaming said STAGE FALLBACK, the final solve registration: the verdict's count.
        let t = final_differs(&fin(false), Some(true), &layout).unwrap();
        assert!(t.contains("tile 1") && t.contains("row 0 x col 1"), "{t}");
        assert!(t.contains("final solve: registration"), "{t}");
        let t = final_differs(&fin(true), Some(false), &layout).unwrap();
        assert!(t.contains("final solve: STAGE FALLBACK"), "{t}");
        assert!(final_differs(&fin(true), Some(true), &layout).is_none());
        assert!(final_differs(&fin(false), None, &layout).is_none());
    }
}
