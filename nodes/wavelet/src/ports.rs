//! The ports of the wavelet node, as graph files wire them.

use surfstream_core::record::{NodeRecord, WaveletReport};
use surfstream_runtime::graph::{Delivery, InputDef, NodePorts, PortDef, PortKind};

/// The panorama in; its datum, roughness and pooled map out.
pub const PORTS: NodePorts = NodePorts {
    kind: WaveletReport::NODE_KIND,
    inputs: &[InputDef::required("panorama", PortKind::Frames)],
    outputs: &[
        PortDef::new("datum", PortKind::Frames, Delivery::Lossless),
        PortDef::new("roughness", PortKind::Frames, Delivery::Lossless),
        PortDef::new("pooled", PortKind::Frames, Delivery::Lossless),
    ],
};
