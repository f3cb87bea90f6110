//! surfstream-core: the types and small algorithms every surfstream crate shares, with no
//! transport and no file formats: the frame ([`frame`]), the one raster type ([`raster`]),
//! the tile plane correction ([`plane`]), atomic output files ([`fsutil`]), ISO 25178
//! parameters ([`metrology`]) and image similarity ([`similarity`]).

pub mod canvas;
pub mod frame;
pub mod fsutil;
pub mod metrology;
pub mod plane;
pub mod raster;
pub mod similarity;

pub use frame::{flags, FrameHeader, FrameKind, FrameView, HeightMap, TileRegistration};
pub use plane::PlaneCorrection;
pub use raster::{Raster, RasterView, Shape, ShapeError};
