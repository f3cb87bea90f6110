//! surfstream-common: what two or more surfstream crates share: the frame, graph files,
//! channels and transport, recording, file formats and previews.

pub mod frame;
pub mod fsutil;

pub use frame::{flags, FrameHeader, FrameKind, FrameView, HeightMap, TileRegistration};
