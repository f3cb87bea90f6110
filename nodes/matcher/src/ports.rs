//! The ports of the matcher node, as graph files wire them.

use surfstream_core::record::{MatcherReport, NodeRecord};
use surfstream_runtime::graph::{Delivery, InputDef, NodePorts, PortDef, PortKind};

/// Tiles in, one registration per tile out.
pub const PORTS: NodePorts = NodePorts {
    kind: MatcherReport::NODE_KIND,
    inputs: &[InputDef::required("tiles", PortKind::Frames)],
    outputs: &[PortDef::new(
        "registrations",
        PortKind::Registrations,
        Delivery::Lossless,
    )],
};
