//! surfstream-finish: the finishing simulation, the seed paper's last step, on a real DEM
//! engine (LIGGGHTS 3.8, started as a process).
//!
//! A patch of the surface model ([`grid::Patch`]: centred, with a guard band that is meshed
//! and cropped) is meshed with the project's mesher for LIGGGHTS, and media spheres
//! ([`setting::Media`], ceramic defaults) are sent over it with the relative velocity and
//! pressure of a centrifugal barrel machine ([`setting::BarrelMachine::action`], the paper's
//! 300 r/min at 135 mm). LIGGGHTS computes Finnie wear per triangle
//! (`fix mesh/surface/stress ... wear finnie`); Archard wear comes from its contact dump
//! ([`contacts`]). Both are mapped to the grid keeping the volume ([`grid::NodeMap`]), scaled
//! by the acceleration factor (process time / simulated time) or fitted to a calibration
//! target, and subtracted; the worn surface is re-meshed for the next cycle ([`process::finish_record`]).
//!
//! Plain functions; `node` is the graph node, `surfstream-finish` its process.

pub mod config;
pub mod contacts;
pub mod engine;
pub mod field;
pub mod grid;
pub mod html;
pub mod laws;
pub mod machine;
pub mod passes;
pub mod predict;
pub mod process;
pub mod run;
pub mod script;
pub mod setting;
pub mod summary;
pub mod sweep;
pub mod vtk;

#[cfg(feature = "node")]
pub mod node;
#[cfg(feature = "node")]
pub mod ports;

pub use process::finish_record;
pub use run::{Calibration, FinishOptions, Model};
