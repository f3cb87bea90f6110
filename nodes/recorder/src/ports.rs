//! The ports of the recorder node, as graph files wire them.

use surfstream_core::record::{NodeRecord, RecorderReport};
use surfstream_runtime::graph::{InputDef, NodePorts};

/// A sink of any inputs, whatever their names and kinds.
pub const PORTS: NodePorts = NodePorts {
    kind: RecorderReport::NODE_KIND,
    inputs: &[InputDef::ANY],
    outputs: &[],
};
