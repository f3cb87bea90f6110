//! The node kinds of the runtime's own tests and transport benchmark: a source and two sinks
//! with the ports of replay, matcher and recorder (the runtime links no node crate). Included
//! with `#[path]` by tests/transport.rs and examples/transport_bench.rs.

use surfstream_runtime::graph::NodeRegistry;

/// The test's node kinds: a source and two sinks (the runtime links no node crate).
pub fn registry() -> NodeRegistry {
    use surfstream_runtime::graph::{Delivery, InputDef, NodePorts, PortDef, PortKind};
    const KINDS: &[NodePorts] = &[
        NodePorts {
            kind: "replay",
            inputs: &[],
            outputs: &[PortDef::new("tiles", PortKind::Frames, Delivery::Lossless)],
        },
        NodePorts {
            kind: "matcher",
            inputs: &[InputDef::required("tiles", PortKind::Frames)],
            outputs: &[PortDef::new(
                "registrations",
                PortKind::Registrations,
                Delivery::Lossless,
            )],
        },
        NodePorts {
            kind: "recorder",
            inputs: &[InputDef::ANY],
            outputs: &[],
        },
    ];
    NodeRegistry::new(KINDS.iter().copied())
}
