//! surfstream-replay: the acquisition stage of surfstream, the graph's source of tiles.
//!
//! This crate is the library behind the `surfstream-replay` node. Tiles come from the
//! simulated profiler stage, a scan directory ([`scan_dir`]: `scan.toml` plus tile files) or an
//! MCAP recording; [`source::open_source`] opens the one a graph names and [`StageRun`] hands
//! the tiles out in acquisition order with the pacing's decisions (as fast as possible, one
//! field per `field_time_s` like the instrument, or a recording's own timing). The node
//! (`node`) is only the process shell around them.
//!
//! The simulated stage is plain functions over in-memory height maps (no IPC, no files, no
//! globals):
//!
//! 1. [`generate_specimen`] synthesises a virtual specimen from [`SpecimenParams`]: self-affine
//!    roughness (FFT synthesis, Hurst exponent and roll-off, scaled to an exact Sa) plus
//!    waviness plus form, like a barrel-finished aluminium sheet (Sa ~ 1.3 um).
//! 2. [`plan_scan`] turns [`StageParams`] into a [`ScanPlan`]: the specimen size the scan needs
//!    and, for every tile in serpentine acquisition order (row 0 left to right, row 1 right to
//!    left, ...), its nominal (commanded) origin and stage position, its true origin (nominal
//!    plus a seeded Gaussian stage error) and its piston and tilt.
//! 3. [`acquire_tile`] measures one tile: the specimen resampled bicubically at the true
//!    sub-pixel origin, plus piston, tilt and white noise, with NaN dropouts.
//! 4. [`truth_for`] gives the [`GroundTruth`] the node writes beside the output (`truth.json`),
//!    in the layout of `bench/make_tiles.py` so that `bench/score_registration.py` can score a run.
//!
//! Conventions (DESIGN.md §2): heights in micrometres, f32, row-major, NaN = not measured;
//! pixel coordinates are (x, y) = (column, row) of the specimen; scan coordinates are
//! micrometres with the specimen's pixel (0, 0) at (0, 0) um, so `um = px * pitch_um`.
//!
//! Everything random is drawn from ChaCha8 streams keyed by the seed and by what is drawn (a
//! spectrum column, a tile index), so results are bit-identical for a seed on a machine,
//! whatever the order in which tiles are acquired and however many threads run.
//!
//! ```
//! use surfstream_replay::{acquire_tile, generate_specimen, plan_scan, truth_for};
//! use surfstream_replay::{SpecimenParams, StageParams};
//!
//! let stage = StageParams { tile_px: 64, ..StageParams::default() };
//! let plan = plan_scan(&stage)?;
//! let specimen = generate_specimen(&plan.specimen_params(&SpecimenParams::default()))?;
//! plan.check_specimen(&specimen)?;
//! let tile = acquire_tile(&specimen, &plan.tiles[0], &stage);
//! assert_eq!(tile.len(), 64 * 64);
//! let truth = truth_for(&plan);
//! assert_eq!(truth.pairs.len(), 4);
//! # Ok::<(), surfstream_replay::ReplayError>(())
//! ```
//!
//! Not for: registering, blending or judging the tiles (the matcher onwards), nor for parsing
//! instrument files (surfstream-io reads them; this crate lays them out as a scan and sends
//! them).

pub mod acquire;
pub mod config;
pub mod error;
pub mod infer;
pub mod planned;
mod rng;
pub mod run;
pub mod source;
pub mod specimen;
pub mod stage;
pub mod truth;

pub use acquire::{acquire_tile, sample_bicubic};
pub use config::{Config, PacingChoice};
pub use error::{ReplayError, Result};
pub use run::{DueTile, Pacing, StageRun, TileSource};
pub use specimen::{
    generate_specimen, generate_virtual_specimen, PeriodicSpecimen, Specimen, SpecimenParams,
    SpecimenSurface, VirtualSpecimen,
};
pub use stage::{plan_scan, serpentine_order, ScanPlan, StageParams, TilePlan};
pub use truth::{truth_for, GroundTruth};
pub mod node;
pub mod ports;
pub mod scan_dir;
