//! The recorder node: a shell around [`RecordingSession`] (every input is one MCAP channel
//! named after its producer, "node/port"), stamping each message with the wall clock.

use std::path::PathBuf;

use anyhow::{bail, Result};
use serde::Deserialize;
use surfstream_runtime::graph::NodeContext;
use surfstream_runtime::node::{Input, NodeLogic, Outbox};

use crate::RecordingSession;

/// The recorder's `params` table.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RecorderConfig {
    /// Recording file, relative to the out dir (default recording.mcap).
    pub path: PathBuf,
}

impl RecorderConfig {
    /// The key of [`RecorderConfig::path`] (the graph reader keeps every output file inside
    /// the out dir, and no two alike).
    pub const PATH_KEY: &'static str = "path";
    /// [`RecorderConfig::path`] when not given.
    pub const DEFAULT_PATH: &'static str = "recording.mcap";
}

impl Default for RecorderConfig {
    fn default() -> Self {
        Self {
            path: PathBuf::from(Self::DEFAULT_PATH),
        }
    }
}

/// The node's parameters and wiring checked as [`build`] checks them, with no file created.
pub fn check(ctx: &NodeContext) -> Result<()> {
    config(ctx).map(drop)
}

fn config(ctx: &NodeContext) -> Result<RecorderConfig> {
    let p: RecorderConfig = ctx.params()?;
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
    Ok(p)
}

pub struct RecorderNode {
    session: RecordingSession,
    finished: bool,
}

pub fn build(ctx: &NodeContext) -> Result<Box<dyn NodeLogic + Send>> {
    let p = config(ctx)?;
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
