//! Node kind -> the node crate's logic, for `run` (threads). `launch` starts the
//! `surfstream-<kind>` binaries instead, which call the same `build` functions.

use anyhow::{bail, Result};
use surfstream_runtime::graph::NodeContext;
use surfstream_runtime::node::NodeLogic;

pub fn build(ctx: &NodeContext) -> Result<Box<dyn NodeLogic + Send>> {
    match ctx.node_kind.as_str() {
        "replay" => surfstream_replay::node::build(ctx),
        "matcher" => surfstream_matcher::node::build(ctx),
        "fusion" => surfstream_fusion::node::build(ctx),
        "wavelet" => surfstream_wavelet::node::build(ctx),
        "mesher" => surfstream_mesher::node::build(ctx),
        "recorder" => surfstream_recorder::node::build(ctx),
        other => bail!("node '{}': unknown node kind {other:?}", ctx.node_id),
    }
}
