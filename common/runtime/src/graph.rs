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

impl PortDef {
    pub const fn new(name: &'static str, kind: PortKind, delivery: Delivery) -> Self {
        Self {
            name,
            kind,
            delivery,
        }
    }
}

/// An input port of a node kind. `name = "*"` accepts any input name (the recorder).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct InputDef {
    pub name: &'static str,
    /// `None`: any kind.
    pub kind: Option<PortKind>,
    pub required: bool,
}

impl InputDef {
    /// An input the graph must wire.
    pub const fn required(name: &'static str, kind: PortKind) -> Self {
        Self {
            name,
            kind: Some(kind),
            required: true,
        }
    }
    /// An input the graph may leave unwired (the node's build decides what it needs).
    pub const fn optional(name: &'static str, kind: PortKind) -> Self {
        Self {
            name,
            kind: Some(kind),
            required: false,
        }
    }
    /// Any number of inputs of any name and kind (the recorder).
    pub const ANY: Self = Self {
        name: "*",
        kind: None,
        required: false,
    };
}

/// The ports of one node kind. Each node crate declares its own (`surfstream_<kind>::ports::PORTS`),
/// so adding a node kind touches only its crate and the registry its caller builds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct NodePorts {
    /// The `node = "..."` name in graph files; the binary is `surfstream-<kind>`.
    pub kind: &'static str,
    pub inputs: &'static [InputDef],
    pub outputs: &'static [PortDef],
}

/// The node kinds a graph may use, in the order errors list them. Built by the caller from the
/// node crates it links (the launcher links them all); node binaries need none, since the
/// resolved context the launcher hands them already carries their wiring.
#[derive(Debug, Clone, Default)]
pub struct NodeRegistry {
    kinds: Vec<NodePorts>,
    /// (kind, parameter) pairs that name a file the node writes: relative to the out dir.
    output_files: Vec<(&'static str, &'static str)>,
    /// (kind, parameter, the name written when the parameter is not given).
    output_defaults: Vec<(&'static str, &'static str, &'static str)>,
    /// Names in the out dir no node output may take (the run's own files); a trailing `*`
    /// makes a prefix.
    reserved_outputs: Vec<&'static str>,
}

impl NodeRegistry {
    pub fn new(kinds: impl IntoIterator<Item = NodePorts>) -> Self {
        Self {
            kinds: kinds.into_iter().collect(),
            output_files: Vec::new(),
            output_defaults: Vec::new(),
            reserved_outputs: Vec::new(),
        }
    }

    /// Declares the file a node of `kind` writes when its output parameter `param` is not
    /// given, so two nodes that would write one file are found when the graph is read.
    pub fn with_output_default(
        mut self,
        kind: &'static str,
        param: &'static str,
        default: &'static str,
    ) -> Self {
        self.output_defaults.push((kind, param, default));
        self
    }

    /// Declares names of the out dir that no node output may take: the run's record, its
    /// marker, its logs, the fixed outputs of the nodes (issue 36: a recorder writing
    /// `run.json` lost the recording). A trailing `*` makes a prefix (`report*`).
    pub fn with_reserved_outputs(mut self, names: &[&'static str]) -> Self {
        self.reserved_outputs.extend_from_slice(names);
        self
    }

    fn reserved(&self, first: &str) -> Option<&'static str> {
        self.reserved_outputs
            .iter()
            .copied()
            .find(|r| match r.strip_suffix('*') {
                Some(prefix) => first.starts_with(prefix),
                None => first == *r,
            })
    }

    /// Declares parameters of `kind` that name a file the node writes. The graph is refused
    /// when one is not a relative name inside the out dir (no absolute path, no `..`): every
    /// file a run writes goes through its staging folder and its lock.
    pub fn with_output_files(mut self, kind: &'static str, params: &[&'static str]) -> Self {
        self.output_files.extend(params.iter().map(|&p| (kind, p)));
        self
    }

    /// The ports of `kind`, if the registry knows it.
    pub fn ports(&self, kind: &str) -> Option<&NodePorts> {
        self.kinds.iter().find(|k| k.kind == kind)
    }

    /// The known kinds' names, in registry order.
    pub fn kind_names(&self) -> Vec<&'static str> {
        self.kinds.iter().map(|k| k.kind).collect()
    }
}

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
    /// Memory the run should stay within, GB (10^9 bytes); nodes that hold whole-scan state
    /// (the fusion's panorama chunks) spill to disk beyond their share. `None`: no limit.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub memory_budget_gb: Option<f64>,
    /// How long a launched node may make no progress (stopped, hung, or one computation this
    /// long) before the launcher names it and stops the graph (see [`crate::watchdog`]).
    #[serde(default = "default_stall_timeout_s")]
    pub stall_timeout_s: f64,
}

impl GraphSection {
    /// The `[graph]` values' own checks (names, durations, budget), where the graph file is read
    /// and again after a `--set graph.KEY=VALUE`.
    pub fn check(&self, origin: &str) -> Result<()> {
        if !valid_name(&self.name) {
            bail!(
                "{origin}: [graph] name = {:?}: expected 1-64 characters of [A-Za-z0-9_-]",
                self.name
            );
        }
        for (field, seconds) in [
            ("backpressure_timeout_s", self.backpressure_timeout_s),
            ("startup_timeout_s", self.startup_timeout_s),
            ("stall_timeout_s", self.stall_timeout_s),
        ] {
            check_duration_s(&format!("[graph] {field}"), seconds)
                .map_err(|e| anyhow!("{origin}: {e}"))?;
        }
        if let Some(gb) = self.memory_budget_gb {
            if !(gb > 0.0 && gb.is_finite()) {
                bail!(
                    "{origin}: [graph] memory_budget_gb = {gb}: expected a positive number of GB"
                );
            }
        }
        Ok(())
    }
}

/// A graph or node name: 1-64 characters of [A-Za-z0-9_-].
fn valid_name(s: &str) -> bool {
    !s.is_empty()
        && s.len() <= 64
        && s.chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
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
fn default_stall_timeout_s() -> f64 {
    60.0
}

/// A `--set` VALUE: a TOML value when it reads as one, else the text as a string.
fn toml_value(value: &str) -> toml::Value {
    toml::from_str::<toml::Table>(&format!("v = {value}"))
        .ok()
        .and_then(|mut t| t.remove("v"))
        .unwrap_or_else(|| toml::Value::String(value.to_string()))
}

/// The longest duration a graph may ask for (timeouts, the stage's field time): 30 days. Longer
/// values are typos or probes (1e20 s does not fit a `Duration`), refused when the graph is read.
pub const MAX_DURATION_S: f64 = 30.0 * 24.0 * 3600.0;

/// Checks one duration in seconds: positive, finite, at most [`MAX_DURATION_S`].
pub fn check_duration_s(what: &str, seconds: f64) -> Result<()> {
    if !(seconds > 0.0 && seconds <= MAX_DURATION_S) {
        bail!(
            "{what} = {seconds}: expected a positive number of seconds, at most {MAX_DURATION_S} (30 days)"
        );
    }
    Ok(())
}

/// Checks that `value` names a file inside the out dir: relative, no `..`, not empty, not
/// the out dir itself (`.`).
pub fn check_relative_output(value: &str) -> std::result::Result<(), String> {
    let path = Path::new(value);
    if value.is_empty() {
        return Err("expected a file name relative to the out dir, got an empty name".into());
    }
    if !path
        .components()
        .any(|c| matches!(c, std::path::Component::Normal(_)))
    {
        return Err(format!(
            "{value:?} names the out dir itself, not a file in it: give a file name"
        ));
    }
    if path.is_absolute() {
        return Err(format!(
            "{value:?} is an absolute path: every file a run writes lives in its out dir; give a name relative to it"
        ));
    }
    if path.components().any(|c| {
        !matches!(
            c,
            std::path::Component::Normal(_) | std::path::Component::CurDir
        )
    }) {
        return Err(format!(
            "{value:?} leaves the out dir (a `..` component): give a name inside it"
        ));
    }
    Ok(())
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
    /// `[deviation]`: the launcher's model-vs-measurement settings (Table 6). No node reads
    /// it; the graph keeps it so the launcher reads it from the parsed file.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub deviation: Option<toml::Table>,
    /// `[outputs]`: which files the run keeps (`set = "model"` or `"full"`, the default); the
    /// launcher's, like `[deviation]` (`--outputs` overrides it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub outputs: Option<OutputsSection>,
}

/// A graph's `[outputs]` table.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OutputsSection {
    /// "model": the STL, run.json, report.html and the small records; "full": every file.
    #[serde(default)]
    pub set: surfstream_core::record::OutputChoice,
}

impl GraphFile {
    /// The output set the graph asks for (the full set when it has no `[outputs]`).
    pub fn output_choice(&self) -> surfstream_core::record::OutputChoice {
        self.outputs.as_ref().map(|o| o.set).unwrap_or_default()
    }

    /// Sets the output set (`--outputs`), over the graph's `[outputs]`.
    pub fn set_output_choice(&mut self, set: surfstream_core::record::OutputChoice) {
        self.outputs = Some(OutputsSection { set });
    }
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
    /// The run's memory plan (`[graph] memory_budget_gb`, MemAvailable, spill folder),
    /// resolved once by the launcher for every node.
    pub memory: crate::memory::MemoryPlan,
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

    /// The node's parameters as its typed config `T`, and the settings `settle` checks them
    /// into (the errors name the graph and the node; `settle`'s name the key). Each node's
    /// `check` and `build` start here.
    pub fn settings<T: serde::de::DeserializeOwned, S>(
        &self,
        settle: impl FnOnce(&T) -> std::result::Result<S, String>,
    ) -> Result<(T, S)> {
        let config: T = self.params()?;
        let settings = settle(&config)
            .map_err(|e| anyhow!("graph '{}', node '{}': {e}", self.graph_name, self.node_id))?;
        Ok((config, settings))
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
    /// Reads and validates a graph file against the node kinds of `registry`.
    pub fn load(path: &Path, registry: &NodeRegistry) -> Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("{}: cannot read graph file", path.display()))?;
        Self::parse(&text, &path.display().to_string(), registry)
    }

    /// Parses and validates graph TOML; `origin` names the file in errors.
    pub fn parse(text: &str, origin: &str, registry: &NodeRegistry) -> Result<Self> {
        let graph: GraphFile =
            toml::from_str(text).map_err(|e| anyhow!("{origin}: not a valid graph file: {e}"))?;
        graph.validate(origin, registry)?;
        Ok(graph)
    }

    /// The files the nodes' output parameters name (given, or the kind's default), each as its
    /// path components inside the out dir: (node id, kind, parameter, name, components).
    fn output_names<'a>(
        &'a self,
        registry: &NodeRegistry,
    ) -> Vec<(&'a NodeEntry, &'static str, String, Vec<String>)> {
        let mut names = Vec::new();
        for n in &self.nodes {
            for &(_, param) in registry.output_files.iter().filter(|(k, _)| *k == n.node) {
                let given = n.params.get(param).and_then(|v| v.as_str());
                let default = registry
                    .output_defaults
                    .iter()
                    .find(|(k, p, _)| *k == n.node && *p == param)
                    .map(|(_, _, d)| *d);
                let Some(name) = given.or(default) else {
                    continue;
                };
                let parts = Path::new(name)
                    .components()
                    .filter_map(|c| match c {
                        std::path::Component::Normal(s) => Some(s.to_string_lossy().to_string()),
                        _ => None,
                    })
                    .collect();
                names.push((n, param, name.to_string(), parts));
            }
        }
        names
    }

    /// Refuses output names that would overwrite the run's own files or each other (issue
    /// 36), before any process starts, naming the node and the field.
    fn check_output_names(&self, origin: &str, registry: &NodeRegistry) -> Result<()> {
        let names = self.output_names(registry);
        for (n, param, name, parts) in &names {
            let Some(first) = parts.first() else {
                continue;
            };
            if let Some(r) = registry.reserved(first) {
                bail!(
                    "{origin}: node '{}' ({}): params.{param} = {name:?}: {:?} is a name the run itself writes in its out dir ({}): choose another name",
                    n.id,
                    n.node,
                    r.trim_end_matches('*'),
                    registry.reserved_outputs.join(", ")
                );
            }
        }
        for (k, (n, param, name, parts)) in names.iter().enumerate() {
            for (m, p2, name2, parts2) in &names[..k] {
                let shorter = parts.len().min(parts2.len());
                if parts[..shorter] == parts2[..shorter] {
                    bail!(
                        "{origin}: node '{}' ({}): params.{param} = {name:?} collides with node '{}' ({}) params.{p2} = {name2:?}{}: two outputs would write one file; give each its own name",
                        n.id,
                        n.node,
                        m.id,
                        m.node,
                        if m.params.contains_key(*p2) { "" } else { " (its default)" }
                    );
                }
            }
        }
        Ok(())
    }

    /// Checks names, kinds (those of `registry`) and wiring.
    pub fn validate(&self, origin: &str, registry: &NodeRegistry) -> Result<()> {
        self.graph.check(origin)?;
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
            if registry.ports(&n.node).is_none() {
                bail!(
                    "{origin}: node '{}': node = {:?}: expected one of {}",
                    n.id,
                    n.node,
                    registry.kind_names().join(", ")
                );
            }
            for &(_, param) in registry.output_files.iter().filter(|(k, _)| *k == n.node) {
                let Some(value) = n.params.get(param) else {
                    continue;
                };
                let Some(text) = value.as_str() else {
                    bail!(
                        "{origin}: node '{}' ({}): params.{param} = {value}: expected a file name (a string)",
                        n.id,
                        n.node
                    );
                };
                check_relative_output(text).map_err(|e| {
                    anyhow!(
                        "{origin}: node '{}' ({}): params.{param}: {e}",
                        n.id,
                        n.node
                    )
                })?;
            }
        }
        self.check_output_names(origin, registry)?;
        for n in &self.nodes {
            let ins = registry
                .ports(&n.node)
                .ok_or_else(|| anyhow!("unreachable"))?
                .inputs;
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
                let outs = registry
                    .ports(&producer.node)
                    .ok_or_else(|| anyhow!("unreachable"))?
                    .outputs;
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
            }
        }
        if let Some(cycle) = self.find_cycle() {
            bail!(
                "{origin}: the wiring has a cycle ({}): every node waits for its upstream's end of scan, so a cycle never ends; wire the graph as a chain or a tree",
                cycle.join(" -> ")
            );
        }
        Ok(())
    }

    /// A cycle of the wiring (producer -> consumer), as node ids from its first node back to
    /// it, if there is one.
    pub fn find_cycle(&self) -> Option<Vec<String>> {
        // Depth-first search; state 1 = on the current path, 2 = done.
        let consumers: Vec<Vec<usize>> = self
            .nodes
            .iter()
            .map(|p| {
                let mut c: Vec<usize> = self
                    .nodes
                    .iter()
                    .enumerate()
                    .filter(|(_, n)| {
                        n.inputs
                            .values()
                            .any(|s| s.split_once('/').is_some_and(|(from, _)| from == p.id))
                    })
                    .map(|(i, _)| i)
                    .collect();
                c.dedup();
                c
            })
            .collect();
        let mut state = vec![0u8; self.nodes.len()];
        for start in 0..self.nodes.len() {
            if state[start] != 0 {
                continue;
            }
            // Iterative DFS: (node, next consumer to visit).
            let mut path: Vec<(usize, usize)> = vec![(start, 0)];
            state[start] = 1;
            while let Some(&mut (node, ref mut next)) = path.last_mut() {
                if let Some(&c) = consumers[node].get(*next) {
                    *next += 1;
                    match state[c] {
                        0 => {
                            state[c] = 1;
                            path.push((c, 0));
                        }
                        1 => {
                            let from = path.iter().position(|(n, _)| *n == c).unwrap_or(0);
                            let mut ids: Vec<String> = path[from..]
                                .iter()
                                .map(|(n, _)| self.nodes[*n].id.clone())
                                .collect();
                            ids.push(self.nodes[c].id.clone());
                            return Some(ids);
                        }
                        _ => {}
                    }
                } else {
                    state[node] = 2;
                    path.pop();
                }
            }
        }
        None
    }

    /// `--set graph.KEY=VALUE`: any `[graph]` setting, read as the graph file would read it
    /// (VALUE as a TOML value, else as a string) and checked as the graph file is.
    fn override_graph_setting(&mut self, assignment: &str, key: &str, value: &str) -> Result<()> {
        let mut table = toml::Table::try_from(&self.graph)
            .map_err(|e| anyhow!("--set {assignment:?}: cannot represent [graph]: {e}"))?;
        table.insert(key.to_string(), toml_value(value));
        let graph: GraphSection = table.try_into().map_err(|e| {
            anyhow!(
                "--set {assignment:?}: [graph] {key} = {value}: {e} (the [graph] settings: name, \
                 out_dir, backpressure_timeout_s, startup_timeout_s, memory_budget_gb, \
                 stall_timeout_s)"
            )
        })?;
        graph.check(&format!("--set {assignment:?}"))?;
        self.graph = graph;
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
        if node_id == "graph" {
            return self.override_graph_setting(assignment, param, value);
        }
        let node = self
            .nodes
            .iter_mut()
            .find(|n| n.id == node_id)
            .ok_or_else(|| {
                anyhow!("--set {assignment:?}: the graph has no node with id {node_id:?}")
            })?;
        node.params.insert(param.to_string(), toml_value(value));
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
    pub fn resolve(&self, scan_id: u64, registry: &NodeRegistry) -> Result<Vec<NodeContext>> {
        let mut contexts = Vec::with_capacity(self.nodes.len());
        // One plan for the run: every node divides the same budget and MemAvailable.
        let memory = crate::memory::MemoryPlan::resolve(
            self.graph.memory_budget_gb.map(|gb| (gb * 1e9) as u64),
            self.graph.out_dir.clone(),
        );
        for n in &self.nodes {
            let outs = registry
                .ports(&n.node)
                .ok_or_else(|| anyhow!("node '{}': unknown kind {:?}", n.id, n.node))?
                .outputs;
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
                let pouts = registry
                    .ports(&producer.node)
                    .ok_or_else(|| anyhow!("node '{}': unknown kind", producer.id))?
                    .outputs;
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
                memory: memory.clone(),
            });
        }
        Ok(contexts)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The test's own node kinds (the runtime links no node crate).
    fn registry() -> NodeRegistry {
        use Delivery::*;
        use PortKind::*;
        const KINDS: &[NodePorts] = &[
            NodePorts {
                kind: "replay",
                inputs: &[],
                outputs: &[PortDef::new("tiles", Frames, Lossless)],
            },
            NodePorts {
                kind: "matcher",
                inputs: &[InputDef::required("tiles", Frames)],
                outputs: &[PortDef::new("registrations", Registrations, Lossless)],
            },
            NodePorts {
                kind: "fusion",
                inputs: &[
                    InputDef::required("tiles", Frames),
                    InputDef::required("registrations", Registrations),
                ],
                outputs: &[
                    PortDef::new("panorama", Frames, Lossless),
                    PortDef::new("preview", Frames, LatestWins),
                ],
            },
            NodePorts {
                kind: "recorder",
                inputs: &[InputDef::ANY],
                outputs: &[],
            },
        ];
        NodeRegistry::new(KINDS.iter().copied()).with_output_files("recorder", &["path"])
    }

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
        let g = GraphFile::parse(DEMO, "demo.toml", &registry()).unwrap();
        let ctx = g.resolve(7, &registry()).unwrap();
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
    fn memory_budget_reaches_every_node_and_is_checked() {
        let g = GraphFile::parse(DEMO, "demo.toml", &registry()).unwrap();
        assert!(g.resolve(7, &registry()).unwrap()[2]
            .memory
            .budget_bytes
            .is_none());
        let with = DEMO.replace(
            "out_dir = \"out/demo\"",
            "out_dir = \"o\"\nmemory_budget_gb = 2.5",
        );
        let mut g = GraphFile::parse(&with, "demo.toml", &registry()).unwrap();
        let ctx = g.resolve(7, &registry()).unwrap();
        assert!(ctx
            .iter()
            .all(|c| c.memory.budget_bytes == Some(2_500_000_000)
                && c.memory == ctx[0].memory
                && c.memory.spill_dir == c.out_dir));
        g.apply_override("graph.memory_budget_gb=0.5").unwrap();
        assert_eq!(g.graph.memory_budget_gb, Some(0.5));
        assert!(g.apply_override("graph.memory_budget_gb=lots").is_err());
        // Every [graph] setting can be set, and is checked as the graph file's would be.
        g.apply_override("graph.stall_timeout_s=3600").unwrap();
        assert_eq!(g.graph.stall_timeout_s, 3600.0);
        let e = g
            .apply_override("graph.stall_timeout_s=-1")
            .unwrap_err()
            .to_string();
        assert!(e.contains("stall_timeout_s = -1"), "{e}");
        assert_eq!(
            g.graph.stall_timeout_s, 3600.0,
            "a refused value changes nothing"
        );
        let e = g.apply_override("graph.nope=1").unwrap_err().to_string();
        assert!(e.contains("nope") && e.contains("stall_timeout_s"), "{e}");
        assert!(g.apply_override("graph.memory_budget_gb=-2").is_err());
        let bad = DEMO.replace("out_dir = \"out/demo\"", "memory_budget_gb = -1");
        let e = GraphFile::parse(&bad, "g.toml", &registry())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("g.toml") && e.contains("memory_budget_gb"),
            "{e}"
        );
    }

    #[test]
    fn errors_name_file_and_field() {
        let bad = DEMO.replace(
            "stage/tiles\" }\n\n[[node]]\nid = \"fusion\"",
            "stage/tile\" }\n\n[[node]]\nid = \"fusion\"",
        );
        let e = GraphFile::parse(&bad, "g.toml", &registry())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("g.toml") && e.contains("inputs.tiles") && e.contains("no output"),
            "{e}"
        );

        let e = GraphFile::parse(
            "[graph]\nname = \"x\"\n[[node]]\nid=\"a\"\nnode=\"warp\"\n",
            "h.toml",
            &registry(),
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("h.toml")
                && e.contains("warp")
                && e.contains("expected one of replay, matcher, fusion, recorder"),
            "{e}"
        );

        let e = GraphFile::parse("[graph]\nnam = \"x\"\n", "i.toml", &registry())
            .unwrap_err()
            .to_string();
        assert!(e.contains("i.toml") && e.contains("nam"), "{e}");

        let e = GraphFile::parse(
            "[graph]\nname = \"x\"\n[[node]]\nid=\"m\"\nnode=\"matcher\"\n",
            "j.toml",
            &registry(),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("inputs.tiles is missing"), "{e}");
    }

    #[test]
    fn reads_the_outputs_table() {
        use surfstream_core::record::OutputChoice;
        let g = GraphFile::parse(DEMO, "demo.toml", &registry()).unwrap();
        assert_eq!(g.output_choice(), OutputChoice::Full);
        let mut g = GraphFile::parse(
            &format!("{DEMO}\n[outputs]\nset = \"model\"\n"),
            "demo.toml",
            &registry(),
        )
        .unwrap();
        assert_eq!(g.output_choice(), OutputChoice::Model);
        g.set_output_choice(OutputChoice::Full);
        assert_eq!(g.output_choice(), OutputChoice::Full);
        // The error names the file, the line with the key and what is expected.
        for (bad, said) in [
            ("set = \"small\"", "expected `model` or `full`"),
            ("keep = \"model\"", "expected `set`"),
        ] {
            let e = GraphFile::parse(
                &format!("{DEMO}\n[outputs]\n{bad}\n"),
                "demo.toml",
                &registry(),
            )
            .unwrap_err()
            .to_string();
            assert!(
                e.contains("demo.toml") && e.contains(bad) && e.contains(said),
                "{e}"
            );
        }
    }

    #[test]
    fn keeps_the_launchers_deviation_table() {
        let g = GraphFile::parse(
            &format!("{DEMO}\n[deviation]\nthreshold_percent = 2\n"),
            "demo.toml",
            &registry(),
        )
        .unwrap();
        let table = g.deviation.unwrap();
        assert_eq!(table["threshold_percent"].as_integer(), Some(2));
        assert!(GraphFile::parse(DEMO, "demo.toml", &registry())
            .unwrap()
            .deviation
            .is_none());
    }

    #[test]
    fn overrides_parse_toml_values() {
        let mut g = GraphFile::parse(DEMO, "demo.toml", &registry()).unwrap();
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

    #[test]
    fn output_files_outside_the_out_dir_are_refused() {
        for bad in ["/abs/x.mcap", "../../x.mcap", "sub/../../x.mcap", ""] {
            let text = DEMO.replace(
                "inputs = { tiles = \"stage/tiles\", panorama = \"fusion/panorama\" }",
                &format!(
                    "inputs = {{ tiles = \"stage/tiles\", panorama = \"fusion/panorama\" }}\nparams = {{ path = {bad:?} }}"
                ),
            );
            assert_ne!(text, DEMO);
            let e = GraphFile::parse(&text, "g.toml", &registry())
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("g.toml") && e.contains("node 'rec'") && e.contains("params.path"),
                "{bad}: {e}"
            );
        }
        for good in ["x.mcap", "sub/x.mcap", "./x.mcap"] {
            let text = DEMO.replace(
                "inputs = { tiles = \"stage/tiles\", panorama = \"fusion/panorama\" }",
                &format!(
                    "inputs = {{ tiles = \"stage/tiles\", panorama = \"fusion/panorama\" }}\nparams = {{ path = {good:?} }}"
                ),
            );
            GraphFile::parse(&text, "g.toml", &registry()).unwrap();
        }
        // An override is checked too (the launcher validates again after --set).
        let mut g = GraphFile::parse(DEMO, "demo.toml", &registry()).unwrap();
        g.apply_override("rec.path=/tmp/elsewhere.mcap").unwrap();
        assert!(g.validate("demo.toml", &registry()).is_err());
    }

    #[test]
    fn output_names_that_collide_or_take_the_runs_own_files_are_refused() {
        let reg = registry()
            .with_output_default("recorder", "path", "recording.mcap")
            .with_reserved_outputs(&["run.json", "FAILED", "logs", "report*"]);
        let with_path = |path: &str| {
            DEMO.replace(
                "inputs = { tiles = \"stage/tiles\", panorama = \"fusion/panorama\" }",
                &format!(
                    "inputs = {{ tiles = \"stage/tiles\", panorama = \"fusion/panorama\" }}\nparams = {{ path = {path:?} }}"
                ),
            )
        };
        for (bad, why) in [
            ("run.json", "a name the run itself writes"),
            ("FAILED", "a name the run itself writes"),
            ("./report.html", "a name the run itself writes"),
            ("logs/stage.stderr", "a name the run itself writes"),
            (".", "names the out dir itself"),
            ("./.", "names the out dir itself"),
        ] {
            let e = GraphFile::parse(&with_path(bad), "g.toml", &reg)
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("g.toml")
                    && e.contains("node 'rec'")
                    && e.contains("params.path")
                    && e.contains(why),
                "{bad}: {e}"
            );
        }
        GraphFile::parse(&with_path("tiles.mcap"), "g.toml", &reg).unwrap();
        // Two recorders: one with the default name, one naming it (or a folder above it).
        let second = |path: Option<&str>| {
            format!(
                "{}\n[[node]]\nid = \"rec2\"\nnode = \"recorder\"\ninputs = {{ tiles = \"stage/tiles\" }}\n{}",
                DEMO,
                path.map(|p| format!("params = {{ path = {p:?} }}\n")).unwrap_or_default()
            )
        };
        for clash in [None, Some("recording.mcap"), Some("./recording.mcap")] {
            let e = GraphFile::parse(&second(clash), "g.toml", &reg)
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("node 'rec2'")
                    && e.contains("collides with node 'rec'")
                    && e.contains("(its default)"),
                "{clash:?}: {e}"
            );
        }
        GraphFile::parse(&second(Some("other.mcap")), "g.toml", &reg).unwrap();
    }

    #[test]
    fn a_cycle_is_refused_when_the_graph_is_read() {
        // The matcher reads the fusion's panorama, the fusion the matcher's registrations.
        let text = DEMO.replace(
            "id = \"matcher\"\nnode = \"matcher\"\ninputs = { tiles = \"stage/tiles\" }",
            "id = \"matcher\"\nnode = \"matcher\"\ninputs = { tiles = \"fusion/panorama\" }",
        );
        assert_ne!(text, DEMO);
        let e = GraphFile::parse(&text, "c.toml", &registry())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("c.toml")
                && e.contains("cycle")
                && (e.contains("matcher -> fusion -> matcher")
                    || e.contains("fusion -> matcher -> fusion")),
            "{e}"
        );
        assert!(GraphFile::parse(DEMO, "demo.toml", &registry())
            .unwrap()
            .find_cycle()
            .is_none());
    }

    #[test]
    fn absurd_timeouts_are_refused_not_panicked_on() {
        for (field, value) in [
            ("backpressure_timeout_s", "1e300"),
            ("startup_timeout_s", "1e20"),
            ("stall_timeout_s", "inf"),
            ("stall_timeout_s", "0"),
            ("startup_timeout_s", "nan"),
        ] {
            let text = DEMO.replace(
                "out_dir = \"out/demo\"",
                &format!("out_dir = \"o\"\n{field} = {value}"),
            );
            let e = GraphFile::parse(&text, "t.toml", &registry())
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("t.toml") && e.contains(field) && e.contains("at most"),
                "{field}={value}: {e}"
            );
        }
        let ok = DEMO.replace(
            "out_dir = \"out/demo\"",
            "out_dir = \"o\"\nstall_timeout_s = 3600",
        );
        GraphFile::parse(&ok, "t.toml", &registry()).unwrap();
    }
}
