//! The ports of the fusion node, as graph files wire them.

use surfstream_core::record::{FusionReport, NodeRecord};
use surfstream_runtime::graph::{Delivery, InputDef, NodePorts, PortDef, PortKind};

/// Tiles and their registrations in; panorama patches (lossless) and a preview (latest wins)
/// out.
pub const PORTS: NodePorts = NodePorts {
    kind: FusionReport::NODE_KIND,
    inputs: &[
        InputDef::required("tiles", PortKind::Frames),
        InputDef::required("registrations", PortKind::Registrations),
    ],
    outputs: &[
        PortDef::new("panorama", PortKind::Frames, Delivery::Lossless),
        PortDef::new("preview", PortKind::Frames, Delivery::LatestWins),
    ],
};
