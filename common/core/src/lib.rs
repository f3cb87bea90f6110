//! surfstream-core: the types and small algorithms every surfstream crate shares, with no
//! transport and no file formats: the frame ([`frame`]), the one raster type ([`raster`]), its
//! sampling and checked pitch ([`sampling`]) and the growing canvas built on it ([`canvas`]),
//! the tile plane correction ([`plane`]), ISO 25178 parameters ([`metrology`]), ISO 16610
//! filters and form removal ([`filter`]), image similarity ([`similarity`]), the
//! model-vs-measurement table (Table 6, [`deviation`]), FFT sizes ([`fft`]), the AVX2 dispatch
//! of hot loops ([`simd`]), atomic output files ([`fsutil`]), spill files for data that need
//! not stay in memory ([`store`]), the typed run.json and node reports ([`record`]),
//! heartbeats from long computations ([`liveness`]), order statistics without a sorted copy
//! ([`order`]) and numbers as a person reads them:
//! significant figures, heights in nm below 1 µm ([`units`]).
//!
//! Not for: moving data between processes (surfstream-runtime), reading or writing file
//! formats (surfstream-io), or an algorithm only one node uses (that node's crate). What lives
//! here is shared by several crates, so a change here is a change for all of them
//! (docs/architecture.md §1, §12).

pub mod canvas;
pub mod choice;
pub mod deviation;
pub mod fft;
pub mod filter;
pub mod frame;
pub mod fsutil;
pub mod liveness;
pub mod metrology;
pub mod order;
pub mod plane;
pub mod raster;
pub mod record;
pub mod sampling;
pub mod simd;
pub mod similarity;
pub mod store;
pub mod units;

pub use frame::{flags, FrameHeader, FrameKind, FrameView, HeightMap, TileRegistration};
pub use plane::PlaneCorrection;
pub use raster::{Raster, RasterView, Shape, ShapeError};
pub use sampling::{ParamError, Pitch, Sampling};
