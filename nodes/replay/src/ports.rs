//! The ports of the replay node, as graph files wire them.

use surfstream_core::record::{NodeRecord, ReplayReport};
use surfstream_runtime::graph::{Delivery, NodePorts, PortDef, PortKind};

/// A source: no inputs; the tiles in acquisition order, then end of scan.
pub const PORTS: NodePorts = NodePorts {
    kind: ReplayReport::NODE_KIND,
    inputs: &[],
    outputs: &[PortDef::new("tiles", PortKind::Frames, Delivery::Lossless)],
};
