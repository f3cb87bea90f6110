//! surfstream-mesher: height field -> closed triangle solid -> STL, so that discrete-element
//! simulators (EDEM, LIGGGHTS, Yade, MercuryDPM) can import a measured surface as a wall.
//!
//! The library is plain functions over in-memory data (DESIGN §1): no IPC, no files.
//!
//! - Input: [`HeightFieldRef`], a borrowed height map as carried by a frame (DESIGN §2): `f32`
//!   heights in um relative to `z_offset_um`, row-major, rows growing with y and columns with
//!   x, NaN = not measured, with pitches and the scan position of sample (0, 0).
//! - [`grid_solid`] meshes it on its own grid into a [`SolidMesh`]: the measured top surface
//!   (two triangles per grid cell), four vertical side walls and a flat base, closed and
//!   watertight with outward normals. Missing samples are filled first ([`fill_missing`]).
//!   Coordinates keep the map's axes (no flips), are scaled to a [`LengthUnit`] (mm by default)
//!   and, by default, re-centred so that f32 STL keeps sub-nanometre resolution; the shift is
//!   returned as `offset_um` so that `scan_um = vertex * unit.um_per_unit() + offset_um`.
//! - [`close_top_surface`] (walls and base for any top surface with a convex rim) is separate
//!   from the grid so that the adaptive re-mesher that replaces the grid can reuse it.
//! - [`write_stl_binary`] / [`write_stl_ascii`] write the solid; [`check_closed`] verifies
//!   watertightness, orientation and volume.
//!
//! ```
//! use surfstream_mesher::{check_closed, grid_solid, write_stl_binary, HeightFieldRef, SolidParams};
//!
//! let heights_um = [0.0f32, 1.0, 2.0, 0.5, f32::NAN, 1.5];
//! let map = HeightFieldRef::new(&heights_um, 3, 2, 0.8148, 0.8148).with_origin(100.0, 20.0);
//! let solid = grid_solid(map, &SolidParams::default())?;
//! assert_eq!(solid.filled_samples, 1);
//! assert!(check_closed(&solid).watertight);
//! let mut stl = Vec::new();
//! write_stl_binary(&mut stl, &solid, "surfstream solid")?;
//! assert_eq!(stl.len() as u64, surfstream_mesher::stl::binary_stl_len(solid.triangles.len()));
//! # Ok::<(), surfstream_mesher::MeshError>(())
//! ```

pub mod adaptive;
pub mod check;
pub mod error;
pub mod fidelity;
pub mod field;
mod geom;
pub mod solid;
pub mod stl;
pub mod tin;

pub use adaptive::{mesh_height_field, AdaptiveMesh, Epsilon, MeshKind, MeshParams};
pub use check::{check_closed, MeshCheck};
pub use error::{MeshError, Result};
pub use field::{fill_missing, HeightFieldRef};
pub use solid::{
    close_top_surface, default_base_depth_um, grid_solid, LengthUnit, SolidMesh, SolidParams,
};
pub use stl::{write_stl_ascii, write_stl_binary};
pub use tin::{triangulate, MissingSamples, Tin, TinParams};
pub mod node;
pub mod ports;
