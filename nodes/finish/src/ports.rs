//! The ports of the finish node, as graph files wire them.

use surfstream_core::record::NodeRecord;
use surfstream_runtime::graph::{InputDef, NodePorts, PortKind};

use surfstream_core::record::finish::FinishReport;

/// A sink: the surface to finish (the pooled map or the panorama), and optionally the datum,
/// the ideal (form-only) model that the paper's comparison runs beside it.
pub const PORTS: NodePorts = NodePorts {
    kind: FinishReport::NODE_KIND,
    inputs: &[
        InputDef::required("surface", PortKind::Frames),
        InputDef::optional("datum", PortKind::Frames),
    ],
    outputs: &[],
};
