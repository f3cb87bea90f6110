//! The node kinds the CLI links: each crate's declared ports (for graph validation), its
//! parameter check (every node's `check`: its typed config read and checked as `build` will,
//! with nothing started or written) and its logic (for `run`, threads). `launch` starts the
//! `surfstream-<kind>` binaries instead, which call the same `build` functions. A new node
//! kind is one line here.

use anyhow::{bail, Result};
use surfstream_runtime::graph::{NodeContext, NodePorts, NodeRegistry};
use surfstream_runtime::node::NodeLogic;

type Build = fn(&NodeContext) -> Result<Box<dyn NodeLogic + Send>>;
type Check = fn(&NodeContext) -> Result<()>;

/// Every linked node kind, in the order graph-file errors list them.
const KINDS: &[(NodePorts, Check, Build)] = &[
    (
        surfstream_replay::ports::PORTS,
        surfstream_replay::node::check,
        surfstream_replay::node::build,
    ),
    (
        surfstream_matcher::ports::PORTS,
        surfstream_matcher::node::check,
        surfstream_matcher::node::build,
    ),
    (
        surfstream_fusion::ports::PORTS,
        surfstream_fusion::node::check,
        surfstream_fusion::node::build,
    ),
    (
        surfstream_wavelet::ports::PORTS,
        surfstream_wavelet::node::check,
        surfstream_wavelet::node::build,
    ),
    (
        surfstream_mesher::ports::PORTS,
        surfstream_mesher::node::check,
        surfstream_mesher::node::build,
    ),
    (
        surfstream_recorder::ports::PORTS,
        surfstream_recorder::node::check,
        surfstream_recorder::node::build,
    ),
    (
        surfstream_finish::ports::PORTS,
        surfstream_finish::node::check,
        surfstream_finish::node::build,
    ),
];

/// The node kinds a graph run by this CLI may use.
pub fn registry() -> NodeRegistry {
    // Parameters that name a file the node writes: refused unless inside the out dir.
    use surfstream_core::record::{MeshReport, NodeRecord, RecorderReport};
    use surfstream_mesher::MesherConfig as Mesher;
    use surfstream_recorder::node::RecorderConfig as Recorder;
    let (recorder, mesher) = (RecorderReport::NODE_KIND, MeshReport::NODE_KIND);
    NodeRegistry::new(KINDS.iter().map(|(ports, ..)| *ports))
        .with_output_files(recorder, &[Recorder::PATH_KEY])
        .with_output_files(mesher, &[Mesher::FILE_KEY])
        // Checked when the graph is read: no two outputs, and none of the run's own files.
        .with_output_default(recorder, Recorder::PATH_KEY, Recorder::DEFAULT_PATH)
        .with_output_default(mesher, Mesher::FILE_KEY, Mesher::DEFAULT_FILE)
        .with_reserved_outputs(crate::outdir::RESERVED_NAMES)
}

/// The entry of `ctx`'s node kind.
fn kind(ctx: &NodeContext) -> Result<&'static (NodePorts, Check, Build)> {
    match KINDS.iter().find(|(ports, ..)| ports.kind == ctx.node_kind) {
        Some(entry) => Ok(entry),
        None => bail!(
            "node '{}': unknown node kind {:?}",
            ctx.node_id,
            ctx.node_kind
        ),
    }
}

/// `ctx`'s parameters checked by its node kind, before anything is started or written.
pub fn check(ctx: &NodeContext) -> Result<()> {
    (kind(ctx)?.1)(ctx)
}

/// The logic of `ctx`'s node kind, for a run in threads.
pub fn build(ctx: &NodeContext) -> Result<Box<dyn NodeLogic + Send>> {
    (kind(ctx)?.2)(ctx)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_linked_kind_is_registered_once_in_pipeline_order() {
        // The order is the one graph-file errors list ("expected one of ...").
        assert_eq!(
            registry().kind_names(),
            ["replay", "matcher", "fusion", "wavelet", "mesher", "recorder", "finish"]
        );
    }
}
