//! surfstream-core: the types and small algorithms every surfstream crate shares, with no
//! transport and no file formats: the frame ([`frame`]), the one raster type ([`raster`]) and
//! the growing canvas built on it ([`canvas`]),
//! the tile plane correction ([`plane`]), atomic output files ([`fsutil`]), ISO 25178
//! parameters ([`metrology`]), image similarity ([`similarity`]), FFT sizes ([`fft`]), ISO 16610 filters and form removal ([`filter`]) and the
//! AVX2 dispatch of hot loops ([`simd`]); the model-vs-measurement table (Table 6,
//! [`deviation`]); spill files for data that need not stay in memory ([`store`]); the typed run.json and node
//! reports ([`record`]); numbers as a person reads them: significant figures, heights in nm
//! below 1 µm ([`units`]).

pub mod canvas;
pub mod deviation;
pub mod fft;
pub mod filter;
pub mod frame;
pub mod fsutil;
pub mod liveness;
pub mod metrology;
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
