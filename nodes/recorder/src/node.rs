//! The recorder node: a shell around [`RecordingSession`] (every input is one MCAP channel
//! named after its producer, "node/port"), stamping each message with the wall clock.

use std::path::PathBuf;

use anyhow::{bail, Result};
use serde::Deserialize;
use surfstream_runtime::graph::NodeContext;
use surfstream_runtime::node::{Input, NodeLogic, Outbox};

use crate::RecordingSession;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Params {
    /// Recording file, relative to the out dir.
    #[serde(default = "default_path")]
    path: PathBuf,
}

fn default_path() -> PathBuf {
    PathBuf::from("recording.mcap")
}

pub struct RecorderNode {
    session: RecordingSession,
    finished: bool,
}

pub fn build(ctx: &NodeContext) -> Result<Box<dyn NodeLogic + Send>> {
    let p: Params = ctx.params()?;
    if ctx.inputs.is_empty() {
        bail!(
            "graph '{}', node '{}': a recorder needs at least one input",
            ctx.graph_name,
            ctx.node_id
        );
    }
    // Every file of a run lives in its out dir (staged, locked): no absolute path, no `..`.
    let name = p.path.to_str().ok_or_else(|| {
        anyhow::anyhow!(
            "graph '{}', node '{}': params.path: not UTF-8",
            ctx.graph_name,
            ctx.node_id
        )
    })?;
    surfstream_runtime::graph::check_relative_output(name).map_err(|e| {
        anyhow::anyhow!(
            "graph '{}', node '{}' (recorder): params.path: {e}",
            ctx.graph_name,
            ctx.node_id
        )
    })?;
    let path = ctx.out_dir.join(&p.path);
    let session = RecordingSession::create(&path, &ctx.graph_name, &ctx.inputs)?;
    Ok(Box::new(RecorderNode {
        session,
        finished: false,
    }))
}

fn wall_clock_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos() as u64)
        .unwrap_or(0)
}

impl NodeLogic for RecorderNode {
    fn on_input(&mut self, port: &str, input: Input<'_>, _: &mut Outbox) -> Result<()> {
        self.session.record(port, input, wall_clock_ns())
    }

    fn on_drained(&mut self, _: &mut Outbox) -> Result<()> {
        if !self.finished {
            self.finished = self.session.finish_when_all_ended()?;
        }
        Ok(())
    }

    fn finished(&self) -> bool {
        self.finished
    }

    fn report(&self) -> anyhow::Result<serde_json::Value> {
        Ok(self.session.report()?)
    }
}
