//! The ports of the mesher node, as graph files wire them.

use surfstream_core::record::{MeshReport, NodeRecord};
use surfstream_runtime::graph::{InputDef, NodePorts, PortKind};

/// A sink. Which inputs it needs follows its `surface` parameter (its build checks it):
/// `surface` for the pooled map or the panorama, `datum` and/or `roughness` otherwise.
pub const PORTS: NodePorts = NodePorts {
    kind: MeshReport::NODE_KIND,
    inputs: &[
        InputDef::optional("surface", PortKind::Frames),
        InputDef::optional("datum", PortKind::Frames),
        InputDef::optional("roughness", PortKind::Frames),
    ],
    outputs: &[],
};
