//! surfstream-io: files in and out: instrument height-map formats ([`formats`]), NumPy arrays
//! ([`npy`]) and the pitch sidecar beside each ([`sidecar`]), float32 TIFF ([`tiff`]), input
//! paths checked before they are opened ([`input`]), a run's output files ([`output`]), the
//! figures' shared drawing helpers ([`figure`]) and PNG previews with a colour scale
//! ([`preview`]), the pre-processing steps of `prep` ([`prep`]), the reader of truth files
//! ([`truth`]) and MCAP recordings ([`recording`]).
//!
//! Not for: the computations on the heights (parameters, filters, separation, meshing live in
//! surfstream-core and the node crates; [`prep`] chains core's steps), nor for graphs,
//! processes or transports: every function here takes a path or bytes and gives data, or the
//! reverse (docs/architecture.md §1, §13 on adding a reader).

pub mod figure;
pub mod formats;
pub mod input;
pub mod npy;
pub mod output;
pub mod prep;
pub mod preview;
pub mod recording;
pub mod sidecar;
pub mod tiff;
pub mod truth;
