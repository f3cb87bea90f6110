//! The process shell every `surfstream-<node>` binary shares: read the resolved graph the
//! launcher wrote, build the node's logic, run it over iceoryx2, leave a report, exit 0 or
//! print one clear error and exit 1.

use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};

use crate::graph::NodeContext;
use crate::ipc;
use crate::node::{NodeLogic, NodeReport};

/// File name of the resolved graph inside the out dir.
pub const RESOLVED_GRAPH: &str = "graph.resolved.json";

/// Where a node leaves its report.
pub fn report_path(out_dir: &Path, node_id: &str) -> PathBuf {
    out_dir.join("nodes").join(format!("{node_id}.json"))
}

/// Writes a node report atomically.
pub fn write_report(out_dir: &Path, report: &NodeReport) -> Result<()> {
    let path = report_path(out_dir, &report.node_id);
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir)
            .with_context(|| format!("{}: cannot create", dir.display()))?;
    }
    surfstream_core::fsutil::write_atomic(&path, |w| {
        serde_json::to_writer(w, report).map_err(|e| anyhow!("{}: {e}", path.display()))
    })
}

/// Reads the resolved graph: every node's context.
pub fn load_graph(graph: &Path) -> Result<Vec<NodeContext>> {
    let text = std::fs::read_to_string(graph)
        .with_context(|| format!("{}: cannot read resolved graph", graph.display()))?;
    serde_json::from_str(&text)
        .map_err(|e| anyhow!("{}: not a resolved graph: {e}", graph.display()))
}

/// Reads the resolved graph and returns the context of `node_id`.
pub fn load_context(graph: &Path, node_id: &str) -> Result<NodeContext> {
    context_in(load_graph(graph)?, graph, node_id)
}

fn context_in(all: Vec<NodeContext>, graph: &Path, node_id: &str) -> Result<NodeContext> {
    all.into_iter()
        .find(|c| c.node_id == node_id)
        .ok_or_else(|| anyhow!("{}: no node with id {node_id:?}", graph.display()))
}

const USAGE: &str =
    "usage: surfstream-<node> --graph RESOLVED_GRAPH.json --node ID --domain PREFIX [--launched]\n\
  Started by `surfstream launch`; run `surfstream --help` for the user-facing commands.";

struct Args {
    graph: PathBuf,
    node: String,
    domain: String,
    launched: bool,
}

fn parse_args(kind: &str) -> Result<Args> {
    let mut graph = None;
    let mut node = None;
    let mut domain = None;
    let mut launched = false;
    let mut it = std::env::args().skip(1);
    while let Some(a) = it.next() {
        match a.as_str() {
            "--graph" => graph = it.next().map(PathBuf::from),
            "--node" => node = it.next(),
            "--domain" => domain = it.next(),
            "--launched" => launched = true,
            "-h" | "--help" => {
                println!("surfstream-{kind}: one node of a surfstream graph.\n{USAGE}");
                std::process::exit(0);
            }
            other => bail!("unexpected argument {other:?}\n{USAGE}"),
        }
    }
    Ok(Args {
        graph: graph.ok_or_else(|| anyhow!("--graph is required\n{USAGE}"))?,
        node: node.ok_or_else(|| anyhow!("--node is required\n{USAGE}"))?,
        domain: domain.ok_or_else(|| anyhow!("--domain is required\n{USAGE}"))?,
        launched,
    })
}

/// The whole `main` of a node binary.
pub fn node_main(kind: &str, build: fn(&NodeContext) -> Result<Box<dyn NodeLogic + Send>>) -> ! {
    // A log on a full disk: the cause goes to the launcher in the exit status.
    crate::stdio::discard_unwritable_stderr();
    crate::stdio::exit_cleanly_on_stream_panics();
    let code = match run(kind, build) {
        Ok(()) => 0,
        Err(e) => {
            use std::io::Write;
            let _ = writeln!(std::io::stderr(), "surfstream-{kind}: error: {e:#}");
            if crate::stdio::is_no_space(&e) {
                crate::stdio::EXIT_NO_SPACE
            } else {
                1
            }
        }
    };
    std::process::exit(code)
}

fn run(kind: &str, build: fn(&NodeContext) -> Result<Box<dyn NodeLogic + Send>>) -> Result<()> {
    let args = parse_args(kind)?;
    // SIGTERM / SIGINT: finish the current step, then leave through the normal error path.
    ctrlc::set_handler(|| ipc::STOP_REQUESTED.store(true, std::sync::atomic::Ordering::Relaxed))
        .map_err(|e| anyhow!("cannot install the termination handler: {e}"))?;
    crate::slots::validate_prefix(&args.domain)?;
    let all = load_graph(&args.graph)?;
    let ctx = context_in(all.clone(), &args.graph, &args.node)?;
    // Its waits are judged by the progress of the nodes it waits on (issue 36).
    let peers = crate::watchdog::Peers::of(&all, &ctx);
    crate::memory::return_freed_buffers(ctx.memory.budget_bytes);
    if ctx.node_kind != kind {
        bail!(
            "node '{}' is a {} node, not {kind}",
            ctx.node_id,
            ctx.node_kind
        );
    }
    if args.launched {
        // Heartbeat for the launcher's stall watch, and a node never outlives its launcher.
        crate::watchdog::install(&ctx.out_dir, &ctx.node_id)?;
    }
    let mut logic = build(&ctx)?;
    let cfg = ipc::domain_config(&args.domain)?;
    let link = ipc::launcher_link(&ctx.graph_name).watching(peers);
    let report = ipc::run_node(&ctx, logic.as_mut(), &cfg, args.launched.then_some(&link))
        .with_context(|| format!("node '{}'", ctx.node_id))?;
    write_report(&ctx.out_dir, &report)
}
