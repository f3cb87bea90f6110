//! Graph files (DESIGN §4): which nodes run, with which parameters, wired how.
//!
//! A graph is read from TOML, validated as a whole (every error names the file and the field),
//! overridden from the command line (`--set NODE.PARAM=VALUE`, `--out DIR`), and then resolved:
//! every node learns its inputs, its outputs and how many subscribers each output has, which is
//! what the lossless handshake waits for.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use serde::{Deserialize, Serialize};

/// What travels on a port.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PortKind {
    /// HeightMap frames (`[f32]` payload + [`surfstream_core::FrameHeader`]).
    Frames,
    /// [`surfstream_core::TileRegistration`] messages.
    Registrations,
}

/// Delivery guarantee of a port (DESIGN §3).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Delivery {
    /// Never drops: handshake, backpressure with a timeout, receiver counts checked.
    Lossless,
    /// Latest value wins (previews, status): safe overflow, buffer 1, history 1.
    LatestWins,
}

/// An output port of a node kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PortDef {
    pub name: &'static str,
    pub kind: PortKind,
    pub delivery: Delivery,
}

/// An input port of a node kind. `name = "*"` accepts any input name (the recorder).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct InputDef {
    pub name: &'static str,
    /// `None`: any kind.
    pub kind: Option<PortKind>,
    pub required: bool,
}

const fn out(name: &'static str, kind: PortKind, delivery: Delivery) -> PortDef {
    PortDef {
        name,
        kind,
        delivery,
    }
}
const fn inp(name: &'static str, kind: Option<PortKind>, required: bool) -> InputDef {
    InputDef {
        name,
        kind,
        required,
    }
}

/// The node kinds, their binaries' ports. One table, so the launcher and every node agree.
pub fn node_kind_ports(kind: &str) -> Option<(&'static [InputDef], &'static [PortDef])> {
    use Delivery::*;
    use PortKind::*;
    const REPLAY_OUT: &[PortDef] = &[out("tiles", Frames, Lossless)];
    const MATCHER_IN: &[InputDef] = &[inp("tiles", Some(Frames), true)];
    const MATCHER_OUT: &[PortDef] = &[out("registrations", Registrations, Lossless)];
    const FUSION_IN: &[InputDef] = &[
        inp("tiles", Some(Frames), true),
        inp("registrations", Some(Registrations), true),
    ];
    const FUSION_OUT: &[PortDef] = &[
        out("panorama", Frames, Lossless),
        out("preview", Frames, LatestWins),
    ];
    const WAVELET_IN: &[InputDef] = &[inp("panorama", Some(Frames), true)];
    const WAVELET_OUT: &[PortDef] = &[
        out("datum", Frames, Lossless),
        out("roughness", Frames, Lossless),
        out("pooled", Frames, Lossless),
    ];
    // Which of these the mesher needs follows its `surface` parameter (its build checks it):
    // `surface` for the pooled map or the panorama, `datum` and/or `roughness` otherwise.
    const MESHER_IN: &[InputDef] = &[
        inp("surface", Some(Frames), false),
        inp("datum", Some(Frames), false),
        inp("roughness", Some(Frames), false),
    ];
    const RECORDER_IN: &[InputDef] = &[inp("*", None, false)];
    Some(match kind {
        "replay" => (&[], REPLAY_OUT),
        "matcher" => (MATCHER_IN, MATCHER_OUT),
        "fusion" => (FUSION_IN, FUSION_OUT),
        "wavelet" => (WAVELET_IN, WAVELET_OUT),
        "mesher" => (MESHER_IN, &[]),
        "recorder" => (RECORDER_IN, &[]),
        _ => return None,
    })
}

/// The node kinds a graph may use.
pub const NODE_KINDS: &[&str] = &[
    "replay", "matcher", "fusion", "wavelet", "mesher", "recorder",
];

/// `[graph]` section.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GraphSection {
    pub name: String,
    #[serde(default = "default_out_dir")]
    pub out_dir: PathBuf,
    /// How long a lossless send may wait for a full downstream queue before failing loudly.
    #[serde(default = "default_backpressure_timeout_s")]
    pub backpressure_timeout_s: f64,
    /// How long startup (attach, handshake, readiness) may take before failing loudly.
    #[serde(default = "default_startup_timeout_s")]
    pub startup_timeout_s: f64,
}

fn default_out_dir() -> PathBuf {
    PathBuf::from("out")
}
fn default_backpressure_timeout_s() -> f64 {
    60.0
}
fn default_startup_timeout_s() -> f64 {
    30.0
}

/// One `[[node]]` entry.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NodeEntry {
    pub id: String,
    pub node: String,
    #[serde(default)]
    pub params: toml::Table,
    /// input port -> "node id/output port"
    #[serde(default)]
    pub inputs: BTreeMap<String, String>,
}

/// A graph file as written.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GraphFile {
    pub graph: GraphSection,
    #[serde(default, rename = "node")]
    pub nodes: Vec<NodeEntry>,
}

/// A resolved input: where it comes from.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct InputSpec {
    /// The input port's name at this node.
    pub port: String,
    /// Producing node id.
    pub from_node: String,
    /// Producing node's output port.
    pub from_port: String,
    pub kind: PortKind,
    pub delivery: Delivery,
    /// Subscribers the producer's port has in all (both ends must create the service alike).
    pub producer_subscribers: usize,
}

impl InputSpec {
    /// "node/port" of the producer: the channel's topic.
    pub fn topic(&self) -> String {
        format!("{}/{}", self.from_node, self.from_port)
    }
}

/// A resolved output.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct OutputSpec {
    pub port: String,
    pub kind: PortKind,
    pub delivery: Delivery,
    /// Number of inputs wired to this port: the handshake waits for this many subscribers.
    pub subscribers: usize,
}

/// Everything one node needs to start: its identity, parameters and wiring.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct NodeContext {
    pub graph_name: String,
    pub node_id: String,
    pub node_kind: String,
    pub params: toml::Table,
    pub out_dir: PathBuf,
    pub inputs: Vec<InputSpec>,
    pub outputs: Vec<OutputSpec>,
    pub backpressure_timeout_s: f64,
    pub startup_timeout_s: f64,
    /// Identifies this run's scan in every frame header.
    pub scan_id: u64,
}

impl NodeContext {
    /// Deserialises the node's parameters, naming the node and the field on error.
    pub fn params<T: serde::de::DeserializeOwned>(&self) -> Result<T> {
        params_from_table(&self.params).map_err(|e| {
            anyhow!(
                "graph '{}', node '{}' ({}): bad params: {e}",
                self.graph_name,
                self.node_id,
                self.node_kind
            )
        })
    }

    /// The iceoryx2 service name of one of this node's output ports.
    pub fn service_name(&self, node_id: &str, port: &str) -> String {
        service_name(&self.graph_name, node_id, port)
    }
}

/// Deserialises a parameter table; the error names the offending key where TOML knows it.
pub fn params_from_table<T: serde::de::DeserializeOwned>(
    table: &toml::Table,
) -> std::result::Result<T, String> {
    // Through text, so the error carries a span that points at the key.
    let text = toml::to_string(table).map_err(|e| e.to_string())?;
    toml::from_str(&text).map_err(|e: toml::de::Error| {
        let key = e.span().and_then(|span| {
            let start = text[..span.start.min(text.len())]
                .rfind('\n')
                .map_or(0, |i| i + 1);
            let line = &text[start..];
            line.split_once('=').map(|(k, _)| k.trim().to_string())
        });
        match key {
            Some(k) if !k.is_empty() && !k.starts_with('[') => format!("{k}: {}", e.message()),
            _ => e.message().to_string(),
        }
    })
}

/// `surfstream/<graph>/<node>/<port>` (DESIGN §3).
pub fn service_name(graph: &str, node_id: &str, port: &str) -> String {
    format!("surfstream/{graph}/{node_id}/{port}")
}

impl GraphFile {
    /// Reads and validates a graph file.
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("{}: cannot read graph file", path.display()))?;
        Self::parse(&text, &path.display().to_string())
    }

    /// Parses and validates graph TOML; `origin` names the file in errors.
    pub fn parse(text: &str, origin: &str) -> Result<Self> {
        let graph: GraphFile =
            toml::from_str(text).map_err(|e| anyhow!("{origin}: not a valid graph file: {e}"))?;
        graph.validate(origin)?;
        Ok(graph)
    }

    /// Checks names, kinds and wiring.
    pub fn validate(&self, origin: &str) -> Result<()> {
        let valid_name = |s: &str| {
            !s.is_empty()
                && s.len() <= 64
                && s.chars()
                    .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
        };
        if !valid_name(&self.graph.name) {
            bail!(
                "{origin}: [graph] name = {:?}: expected 1-64 characters of [A-Za-z0-9_-]",
                self.graph.name
            );
        }
        if !(self.graph.backpressure_timeout_s > 0.0
            && self.graph.backpressure_timeout_s.is_finite())
        {
            bail!(
                "{origin}: [graph] backpressure_timeout_s: expected a positive number of seconds"
            );
        }
        if !(self.graph.startup_timeout_s > 0.0 && self.graph.startup_timeout_s.is_finite()) {
            bail!("{origin}: [graph] startup_timeout_s: expected a positive number of seconds");
        }
        if self.nodes.is_empty() {
            bail!("{origin}: no [[node]] entries: a graph needs at least one node");
        }
        let mut ids = BTreeMap::new();
        for (i, n) in self.nodes.iter().enumerate() {
            if !valid_name(&n.id) {
                bail!(
                    "{origin}: node #{} id = {:?}: expected 1-64 characters of [A-Za-z0-9_-]",
                    i + 1,
                    n.id
                );
            }
            if ids.insert(n.id.as_str(), n).is_some() {
                bail!(
                    "{origin}: node id {:?} is used twice: ids must be unique",
                    n.id
                );
            }
            if node_kind_ports(&n.node).is_none() {
                bail!(
                    "{origin}: node '{}': node = {:?}: expected one of {}",
                    n.id,
                    n.node,
                    NODE_KINDS.join(", ")
                );
            }
        }
        for n in &self.nodes {
            let (ins, _) = node_kind_ports(&n.node).ok_or_else(|| anyhow!("unreachable"))?;
            let any = ins.iter().any(|d| d.name == "*");
            for def in ins.iter().filter(|d| d.required) {
                if !n.inputs.contains_key(def.name) {
                    bail!(
                        "{origin}: node '{}' ({}): inputs.{} is missing: expected \"node id/port\"",
                        n.id,
                        n.node,
                        def.name
                    );
                }
            }
            for (port, source) in &n.inputs {
                let def = ins.iter().find(|d| d.name == port || d.name == "*");
                let Some(def) = def else {
                    let names: Vec<_> = ins.iter().map(|d| d.name).collect();
                    bail!(
                        "{origin}: node '{}' ({}): unknown input {:?}: expected {}",
                        n.id,
                        n.node,
                        port,
                        if names.is_empty() {
                            "no inputs".to_string()
                        } else {
                            names.join(", ")
                        }
                    );
                };
                let (from_node, from_port) = source.split_once('/').ok_or_else(|| {
                    anyhow!(
                        "{origin}: node '{}': inputs.{port} = {source:?}: expected \"node id/port\"",
                        n.id
                    )
                })?;
                let producer = ids.get(from_node).ok_or_else(|| {
                    anyhow!(
                        "{origin}: node '{}': inputs.{port} = {source:?}: no node with id {from_node:?}",
                        n.id
                    )
                })?;
                let (_, outs) =
                    node_kind_ports(&producer.node).ok_or_else(|| anyhow!("unreachable"))?;
                let out = outs.iter().find(|o| o.name == from_port).ok_or_else(|| {
                    let names: Vec<_> = outs.iter().map(|o| o.name).collect();
                    anyhow!(
                        "{origin}: node '{}': inputs.{port} = {source:?}: node '{from_node}' ({}) has no output {from_port:?}; it has {}",
                        n.id,
                        producer.node,
                        if names.is_empty() { "none".to_string() } else { names.join(", ") }
                    )
                })?;
                if let Some(k) = def.kind {
                    if k != out.kind {
                        bail!(
                            "{origin}: node '{}': inputs.{port} = {source:?}: carries {:?}, expected {:?}",
                            n.id,
                            out.kind,
                            k
                        );
                    }
                }
                if from_node == n.id {
                    bail!(
                        "{origin}: node '{}': inputs.{port}: a node cannot read its own output",
                        n.id
                    );
                }
                let _ = any;
            }
        }
        Ok(())
    }

    /// Applies `--set NODE.PARAM=VALUE`; VALUE is read as a TOML value, else as a string.
    pub fn apply_override(&mut self, assignment: &str) -> Result<()> {
        let (key, value) = assignment
            .split_once('=')
            .ok_or_else(|| anyhow!("--set {assignment:?}: expected NODE.PARAM=VALUE"))?;
        let (node_id, param) = key
            .split_once('.')
            .ok_or_else(|| anyhow!("--set {assignment:?}: expected NODE.PARAM=VALUE"))?;
        let node = self
            .nodes
            .iter_mut()
            .find(|n| n.id == node_id)
            .ok_or_else(|| {
                anyhow!("--set {assignment:?}: the graph has no node with id {node_id:?}")
            })?;
        let parsed: toml::Value = toml::from_str::<toml::Table>(&format!("v = {value}"))
            .ok()
            .and_then(|mut t| t.remove("v"))
            .unwrap_or_else(|| toml::Value::String(value.to_string()));
        node.params.insert(param.to_string(), parsed);
        Ok(())
    }

    /// How many inputs read `node/port`.
    pub fn subscribers_of(&self, node_id: &str, port: &str) -> usize {
        let topic = format!("{node_id}/{port}");
        self.nodes
            .iter()
            .flat_map(|c| c.inputs.values())
            .filter(|s| **s == topic)
            .count()
    }

    /// Resolves every node's wiring. `out_dir` must already be final (absolute for processes).
    pub fn resolve(&self, scan_id: u64) -> Result<Vec<NodeContext>> {
        let mut contexts = Vec::with_capacity(self.nodes.len());
        for n in &self.nodes {
            let (_, outs) = node_kind_ports(&n.node)
                .ok_or_else(|| anyhow!("node '{}': unknown kind {:?}", n.id, n.node))?;
            let mut inputs = Vec::new();
            for (port, source) in &n.inputs {
                let (from_node, from_port) = source
                    .split_once('/')
                    .ok_or_else(|| anyhow!("node '{}': inputs.{port}: bad source", n.id))?;
                let producer = self
                    .nodes
                    .iter()
                    .find(|p| p.id == from_node)
                    .ok_or_else(|| {
                        anyhow!("node '{}': inputs.{port}: no node {from_node}", n.id)
                    })?;
                let (_, pouts) = node_kind_ports(&producer.node)
                    .ok_or_else(|| anyhow!("node '{}': unknown kind", producer.id))?;
                let def = pouts.iter().find(|o| o.name == from_port).ok_or_else(|| {
                    anyhow!("node '{}': inputs.{port}: no port {from_port}", n.id)
                })?;
                inputs.push(InputSpec {
                    port: port.clone(),
                    from_node: from_node.to_string(),
                    from_port: from_port.to_string(),
                    kind: def.kind,
                    delivery: def.delivery,
                    producer_subscribers: self.subscribers_of(from_node, from_port),
                });
            }
            let outputs = outs
                .iter()
                .map(|o| OutputSpec {
                    port: o.name.to_string(),
                    kind: o.kind,
                    delivery: o.delivery,
                    subscribers: self.subscribers_of(&n.id, o.name),
                })
                .collect();
            contexts.push(NodeContext {
                graph_name: self.graph.name.clone(),
                node_id: n.id.clone(),
                node_kind: n.node.clone(),
                params: n.params.clone(),
                out_dir: self.graph.out_dir.clone(),
                inputs,
                outputs,
                backpressure_timeout_s: self.graph.backpressure_timeout_s,
                startup_timeout_s: self.graph.startup_timeout_s,
                scan_id,
            });
        }
        Ok(contexts)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const DEMO: &str = r#"
[graph]
name = "demo"
out_dir = "out/demo"

[[node]]
id = "stage"
node = "replay"
params = { source = "simulated", rows = 2 }

[[node]]
id = "matcher"
node = "matcher"
inputs = { tiles = "stage/tiles" }

[[node]]
id = "fusion"
node = "fusion"
inputs = { tiles = "stage/tiles", registrations = "matcher/registrations" }

[[node]]
id = "rec"
node = "recorder"
inputs = { tiles = "stage/tiles", panorama = "fusion/panorama" }
"#;

    #[test]
    fn resolves_wiring_and_subscriber_counts() {
        let g = GraphFile::parse(DEMO, "demo.toml").unwrap();
        let ctx = g.resolve(7).unwrap();
        let stage = &ctx[0];
        assert_eq!(stage.outputs[0].port, "tiles");
        assert_eq!(stage.outputs[0].subscribers, 3);
        let fusion = &ctx[2];
        assert_eq!(fusion.inputs.len(), 2);
        assert_eq!(
            fusion
                .outputs
                .iter()
                .find(|o| o.port == "panorama")
                .unwrap()
                .subscribers,
            1
        );
    }

    #[test]
    fn errors_name_file_and_field() {
        let bad = DEMO.replace(
            "stage/tiles\" }\n\n[[node]]\nid = \"fusion\"",
            "stage/tile\" }\n\n[[node]]\nid = \"fusion\"",
        );
        let e = GraphFile::parse(&bad, "g.toml").unwrap_err().to_string();
        assert!(
            e.contains("g.toml") && e.contains("inputs.tiles") && e.contains("no output"),
            "{e}"
        );

        let e = GraphFile::parse(
            "[graph]\nname = \"x\"\n[[node]]\nid=\"a\"\nnode=\"warp\"\n",
            "h.toml",
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("h.toml") && e.contains("warp") && e.contains("expected one of"),
            "{e}"
        );

        let e = GraphFile::parse("[graph]\nnam = \"x\"\n", "i.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("i.toml") && e.contains("nam"), "{e}");

        let e = GraphFile::parse(
            "[graph]\nname = \"x\"\n[[node]]\nid=\"m\"\nnode=\"matcher\"\n",
            "j.toml",
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("inputs.tiles is missing"), "{e}");
    }

    #[test]
    fn overrides_parse_toml_values() {
        let mut g = GraphFile::parse(DEMO, "demo.toml").unwrap();
        g.apply_override("stage.rows=3").unwrap();
        g.apply_override("stage.source=scan").unwrap();
        g.apply_override("stage.overlap=0.2").unwrap();
        let p = &g.nodes[0].params;
        assert_eq!(p["rows"].as_integer(), Some(3));
        assert_eq!(p["source"].as_str(), Some("scan"));
        assert_eq!(p["overlap"].as_float(), Some(0.2));
        assert!(g.apply_override("nobody.x=1").is_err());
        assert!(g.apply_override("stage-rows").is_err());
    }
}
