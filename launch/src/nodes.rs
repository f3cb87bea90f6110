//! The node kinds the CLI links: each crate's declared ports (for graph validation) and its
//! logic (for `run`, threads). `launch` starts the `surfstream-<kind>` binaries instead, which
//! call the same `build` functions. A new node kind is one line here.

use anyhow::{bail, Result};
use surfstream_runtime::graph::{NodeContext, NodePorts, NodeRegistry};
use surfstream_runtime::node::NodeLogic;

type Build = fn(&NodeContext) -> Result<Box<dyn NodeLogic + Send>>;

/// Every linked node kind, in the order graph-file errors list them.
const KINDS: &[(NodePorts, Build)] = &[
    (
        surfstream_replay::ports::PORTS,
        surfstream_replay::node::build,
    ),
    (
        surfstream_matcher::ports::PORTS,
        surfstream_matcher::node::build,
    ),
    (
        surfstream_fusion::ports::PORTS,
        surfstream_fusion::node::build,
    ),
    (
        surfstream_wavelet::ports::PORTS,
        surfstream_wavelet::node::build,
    ),
    (
        surfstream_mesher::ports::PORTS,
        surfstream_mesher::node::build,
    ),
    (
        surfstream_recorder::ports::PORTS,
        surfstream_recorder::node::build,
    ),
    (
        surfstream_finish::ports::PORTS,
        surfstream_finish::node::build,
    ),
];

/// The node kinds a graph run by this CLI may use.
pub fn registry() -> NodeRegistry {
    // Parameters that name a file the node writes: refused unless inside the out dir.
    NodeRegistry::new(KINDS.iter().map(|(ports, _)| *ports))
        .with_output_files("recorder", &["path"])
        .with_output_files("mesher", &["file"])
        // Checked when the graph is read: no two outputs, and none of the run's own files.
        .with_output_default("recorder", "path", "recording.mcap")
        .with_output_default("mesher", "file", "surface.stl")
        .with_reserved_outputs(crate::outdir::RESERVED_NAMES)
}

/// The logic of `ctx`'s node kind, for a run in threads.
pub fn build(ctx: &NodeContext) -> Result<Box<dyn NodeLogic + Send>> {
    match KINDS.iter().find(|(ports, _)| ports.kind == ctx.node_kind) {
        Some((_, build)) => build(ctx),
        None => bail!(
            "node '{}': unknown node kind {:?}",
            ctx.node_id,
            ctx.node_kind
        ),
    }
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
