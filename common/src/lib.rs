//! surfstream-common: what two or more surfstream crates share: the frame, graph files,
//! channels and transport, recording, file formats and previews.

pub mod formats;
pub mod frame;
pub mod fsutil;
pub mod graph;
pub mod inproc;
pub mod ipc;
pub mod latency;
pub mod metrology;
pub mod node;
pub mod npy;
pub mod preview;
pub mod recording;
pub mod shell;
pub mod similarity;

pub use frame::{flags, FrameHeader, FrameKind, FrameView, HeightMap, TileRegistration};
