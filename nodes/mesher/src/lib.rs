//! surfstream-mesher: a height field -> an error-bounded triangle mesh -> STL, so that
//! discrete-element simulators (EDEM, LIGGGHTS, Yade, MercuryDPM, Rocky) can import a measured
//! surface as a wall, with a report of how faithful the mesh is.
//!
//! The library is plain functions and types over in-memory data (DESIGN §1): no IPC.
//!
//! - Input: a height field is a [`RasterView`](surfstream_core::raster::RasterView) of `f32`
//!   heights (`rows x cols`, row-major, rows growing with y and columns with x, NaN = not
//!   measured; the payload of a frame, DESIGN §2) placed in scan coordinates by a
//!   [`ScanPlacement`] (pitches, the position of sample (0, 0), the z offset the heights are
//!   relative to).
//! - [`mesh_height_field`] is the mesher: error-bounded greedy insertion ([`tin`]: start from
//!   the grid's corners, insert the sample farthest from the mesh until every measured sample
//!   is within `epsilon` vertically, or a triangle budget is reached). The grid is cut into
//!   blocks meshed in parallel; the sides two blocks share are simplified once and kept
//!   exactly by both, so the pieces join without a crack and the result does not depend on
//!   the thread count. The bound is absolute or a fraction of the surface's Sq ([`Epsilon`]).
//!   The top becomes a closed solid (side walls and a flat base, [`close_top_surface`]) or
//!   stays an open sheet ([`MeshKind`]); missing samples are filled ([`fill_missing`]) or, for
//!   a sheet, left as holes ([`MissingSamples`]).
//! - Fidelity ([`fidelity`]): the achieved vertical error, and Sa, Sq, Sz, Sdr of the mesh
//!   resampled on the grid beside those of the height field, both levelled by the field's
//!   least-squares plane (the project's metrology, `surfstream_core::metrology`).
//! - [`grid_solid`] is the reference: two triangles per grid cell, closed the same way.
//! - Coordinates keep the map's axes (no flips), are scaled to a [`LengthUnit`] (mm by
//!   default) and re-centred so that f32 STL keeps sub-nanometre resolution; the shift is
//!   returned as `offset_um`, `scan_um = vertex * unit.um_per_unit() + offset_um`.
//!   [`write_stl_binary`] / [`write_stl_ascii`] write a solid, [`check_closed`] verifies
//!   watertightness, orientation and volume.
//! - Bounded memory ([`stream`], issue 17): [`mesh_streaming`] and [`grid_streaming`] make the
//!   same meshes, STL bytes and checks without holding the triangle or vertex lists (triangles
//!   spilled to an unnamed file, the check settled block by block); the node and the `mesh`
//!   verb use them (and [`mesh_streaming_to_tolerance`]). The streamed path is the product:
//!   the in-memory [`mesh_height_field`], [`mesh_to_tolerance`] and [`MeshJob::mesh`] remain
//!   as the tests' oracle (and for the examples, which hold small maps).
//! - One front door ([`config`]): [`MesherConfig`] (a graph's params, the `mesh` verb's flags,
//!   Python's keywords; every choice an enum) checked into the one [`MeshSettings`]; one entry
//!   point ([`map`]: [`mesh_surface`]) that the node, the verb and Python call; one record,
//!   `surfstream_core::record::MeshReport` (run.json's `stages.mesher`, the verb's OUT.json,
//!   Python's dict).
//! - In a graph ([`job`]): [`MeshJob`] takes the final frame of the chosen surface
//!   ([`SurfaceChoice`]: pooled, panorama, datum, roughness, or datum + roughness summed), and
//!   meshes it once every input has ended its scan; `node` is the process shell around it.
//!
//! ```
//! use surfstream_core::raster::{RasterView, Shape};
//! use surfstream_core::Pitch;
//! use surfstream_mesher::{check_closed, grid_solid, write_stl_binary, ScanPlacement, SolidParams};
//!
//! // 2 rows x 3 columns, one missing sample.
//! let heights_um = [0.0f32, 1.0, 2.0, 0.5, f32::NAN, 1.5];
//! let heights = RasterView::new(&heights_um, Shape::new(2, 3))?;
//! let at = ScanPlacement::new(Pitch::square(0.8148)?).with_origin(100.0, 20.0);
//! let solid = grid_solid(heights, &at, &SolidParams::default())?;
//! assert_eq!(solid.filled_samples, 1);
//! assert!(check_closed(&solid).watertight);
//! let mut stl = Vec::new();
//! write_stl_binary(&mut stl, &solid, "surfstream solid")?;
//! assert_eq!(stl.len() as u64, surfstream_mesher::stl::binary_stl_len(solid.triangles.len()));
//! # Ok::<(), surfstream_mesher::MeshError>(())
//! ```
//!
//! Not for: choosing or separating the surface (surfstream-wavelet makes the datum and
//! roughness it may mesh), nor for running a DEM engine: the engines import the STL, and
//! surfstream-finish runs LIGGGHTS on it.

pub mod adaptive;
pub mod check;
pub mod config;
pub mod error;
pub mod fidelity;
pub mod field;
mod geom;
pub mod job;
pub mod map;
pub mod outliers;
pub mod report;
pub mod solid;
pub mod stl;
pub mod stream;
pub mod target;
pub mod tin;
pub mod tolerance;

pub use adaptive::{mesh_height_field, AdaptiveMesh, Epsilon, MeshCounts, MeshKind, MeshParams};
pub use check::{check_closed, MeshCheck};
pub use config::{parse_choice, MeshMethod, MeshSettings, MesherConfig, StlFormat, SurfaceChoice};
pub use error::{MeshError, Result};
pub use field::{fill_missing, ScanPlacement};
pub use job::{MeshJob, MeshedSurface};
pub use map::{mesh_surface, prepare_heights, MeshInput, MeshMade, MeshOutcome, MeshOutputs};
pub use solid::{
    close_top_surface, default_base_depth_um, grid_solid, LengthUnit, SolidMesh, SolidParams,
};
pub use stl::{write_stl_ascii, write_stl_binary};
pub use stream::{grid_streaming, mesh_streaming, StreamedGrid, StreamedMesh};
pub use target::{grid_sheet_for, DemEngine, EngineProfile, TargetMesh, TargetMethod};
pub use tin::{triangulate, MissingSamples, Tin, TinParams};
pub use tolerance::{
    mesh_streaming_to_tolerance, mesh_to_tolerance, Tolerance, ToleranceReport, ToleranceSettings,
};
#[cfg(feature = "node")]
pub mod node;
#[cfg(feature = "node")]
pub mod ports;
