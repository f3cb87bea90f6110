//! The recorder node: every input is one MCAP channel named after its producer ("node/port").

use std::collections::BTreeMap;
use std::path::PathBuf;

use anyhow::{anyhow, bail, Result};
use serde::Deserialize;
use serde_json::json;
use surfstream_io::recording::{ChannelId, Recorder};
use surfstream_runtime::graph::{NodeContext, PortKind};
use surfstream_runtime::node::{Input, NodeLogic, Outbox};

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

struct Channel {
    id: ChannelId,
    topic: String,
    ended: bool,
    messages: u64,
}

pub struct RecorderNode {
    recorder: Option<Recorder>,
    path: PathBuf,
    channels: BTreeMap<String, Channel>,
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
    let path = ctx.out_dir.join(&p.path);
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir)
            .map_err(|e| anyhow!("{}: cannot create: {e}", dir.display()))?;
    }
    let mut recorder = Recorder::create(&path)?;
    let mut channels = BTreeMap::new();
    for i in &ctx.inputs {
        let topic = i.topic();
        let meta: BTreeMap<String, String> = [
            ("graph", ctx.graph_name.clone()),
            ("node", i.from_node.clone()),
            ("port", i.from_port.clone()),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect();
        let id = match i.kind {
            PortKind::Frames => recorder.add_frame_channel(&topic, meta)?,
            PortKind::Registrations => recorder.add_registration_channel(&topic, meta)?,
        };
        channels.insert(
            i.port.clone(),
            Channel {
                id,
                topic,
                ended: false,
                messages: 0,
            },
        );
    }
    Ok(Box::new(RecorderNode {
        recorder: Some(recorder),
        path,
        channels,
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
        let ch = self
            .channels
            .get_mut(port)
            .ok_or_else(|| anyhow!("recorder: message on unknown input '{port}'"))?;
        let rec = self
            .recorder
            .as_mut()
            .ok_or_else(|| anyhow!("recorder already finished"))?;
        let t = wall_clock_ns();
        match input {
            Input::Frame(f) => rec.write_frame(ch.id, f.header, f.heights, t)?,
            Input::Registration(r) => rec.write_registration(ch.id, r, t)?,
        }
        ch.messages += 1;
        if input.is_end_of_scan() {
            ch.ended = true;
        }
        Ok(())
    }

    fn on_drained(&mut self, _: &mut Outbox) -> Result<()> {
        if !self.finished && self.channels.values().all(|c| c.ended) {
            if let Some(rec) = self.recorder.take() {
                rec.finish()?;
            }
            self.finished = true;
        }
        Ok(())
    }

    fn finished(&self) -> bool {
        self.finished
    }

    fn report(&self) -> serde_json::Value {
        let topics: BTreeMap<_, _> = self
            .channels
            .values()
            .map(|c| (c.topic.clone(), c.messages))
            .collect();
        json!({ "file": self.path.file_name().map(|f| f.to_string_lossy().to_string()), "messages": topics })
    }
}
