//! surfstream-finish: the finishing simulation, the seed paper's last step, on a real DEM
//! engine (LIGGGHTS 3.8, started as a process), at two scales joined by contact statistics.
//!
//! - **Macro** ([`machine`]): the machine (the paper's centrifugal barrel) at the media scale
//!   in LIGGGHTS, in the drum's frame; the contacts its media make on a part plate become
//!   [`machine::MacroContacts`] (rates, speeds, forces, sliding work, samples), keeping only
//!   what softened media keep.
//! - **Micro** ([`passes`]): a patch of the surface model ([`grid::Patch`], with a guard band
//!   meshed and cropped) meshed by the project's tolerance mesher, and contacts drawn from the
//!   macro samples run on it at the media's real stiffness: Finnie wear from LIGGGHTS'
//!   `fix mesh/surface/stress`, Archard wear from its contact dump ([`contacts`]), both mapped
//!   to the grid keeping the volume ([`grid::NodeMap`]).
//! - **Prediction** ([`laws`], [`predict`]): the wear laws at the macro rates with the DEM's
//!   wear per contact, one scale fitted once ([`process::finish_record`]), the series over the
//!   process time, the no-DEM baselines, the sweep ([`sweep`]), the paper's comparison with
//!   the ideal model and a measured after-finish scan registered to the model ([`after`]).
//!
//! Without a macro run (`--no-macro`) the rates come from the barrel kinematics' assumptions
//! ([`setting::BarrelKinematics::action`]) and each cycle runs one medium at a time ([`script`]).
//! Plain functions; `node` is the graph node, `surfstream-finish` its process.
//!
//! Not for: meshing (it calls surfstream-mesher) or contact physics of its own: LIGGGHTS does
//! the DEM; this crate writes its inputs, runs it, reads its outputs and turns them into wear.

pub mod after;
pub mod config;
pub mod contacts;
pub mod engine;
#[cfg(test)]
pub(crate) mod example;
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
pub mod sweep;
pub mod vtk;

#[cfg(feature = "node")]
pub mod node;
#[cfg(feature = "node")]
pub mod ports;

pub use process::finish_record;
pub use run::{Calibration, FinishOptions, Model};
