//! One recording session: every wired input is one MCAP channel named after its producer
//! ("node/port"), each message is written as it arrives, and the file is finished once every
//! input has ended its scan.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{anyhow, Result};
use surfstream_core::record::{self, RecorderReport};
use surfstream_io::recording::{ChannelId, Recorder};
use surfstream_runtime::graph::{InputSpec, PortKind};
use surfstream_runtime::node::Input;

struct Channel {
    id: ChannelId,
    topic: String,
    ended: bool,
    messages: u64,
}

/// The recording of one graph run's wired inputs.
pub struct RecordingSession {
    /// `None` once finished.
    recorder: Option<Recorder>,
    path: PathBuf,
    /// Per input port.
    channels: BTreeMap<String, Channel>,
}

impl RecordingSession {
    /// Creates the recording at `path` (and its folder) with one channel per input; each
    /// channel's metadata names the graph and the producing node and port.
    pub fn create(path: &Path, graph_name: &str, inputs: &[InputSpec]) -> Result<Self> {
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir)
                .map_err(|e| anyhow!("{}: cannot create: {e}", dir.display()))?;
        }
        let mut recorder = Recorder::create(path)?;
        let mut channels = BTreeMap::new();
        for i in inputs {
            let topic = i.topic();
            let meta: BTreeMap<String, String> = [
                ("graph", graph_name.to_string()),
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
        Ok(Self {
            recorder: Some(recorder),
            path: path.to_path_buf(),
            channels,
        })
    }

    /// Writes one message of input `port`, stamped with `log_time_ns`.
    pub fn record(&mut self, port: &str, input: Input<'_>, log_time_ns: u64) -> Result<()> {
        let ch = self
            .channels
            .get_mut(port)
            .ok_or_else(|| anyhow!("recorder: message on unknown input '{port}'"))?;
        let rec = self
            .recorder
            .as_mut()
            .ok_or_else(|| anyhow!("recorder already finished"))?;
        match input {
            Input::Frame(f) => rec.write_frame(ch.id, f.header, f.heights, log_time_ns)?,
            Input::Registration(r) => rec.write_registration(ch.id, r, log_time_ns)?,
        }
        ch.messages += 1;
        if input.is_end_of_scan() {
            ch.ended = true;
        }
        Ok(())
    }

    /// Finishes the file once every input has ended; true when the recording is complete.
    pub fn finish_when_all_ended(&mut self) -> Result<bool> {
        if self.recorder.is_some() && self.channels.values().all(|c| c.ended) {
            if let Some(rec) = self.recorder.take() {
                rec.finish()?;
            }
        }
        Ok(self.recorder.is_none())
    }

    /// The file name and the messages written per topic, for run.json.
    pub fn report(&self) -> Result<serde_json::Value, record::RecordError> {
        let topics: BTreeMap<_, _> = self
            .channels
            .values()
            .map(|c| (c.topic.clone(), c.messages))
            .collect();
        record::to_value(&RecorderReport {
            file: self
                .path
                .file_name()
                .map(|f| f.to_string_lossy().to_string()),
            messages: topics,
        })
    }
}
