//! surfstream-fusion: the growing panorama (DESIGN §8, "fusion").
//!
//! Tiles of an R x C serpentine scan arrive one at a time with their final scan position (the
//! position of pixel (0, 0), in um, generally not a multiple of the pitch) and a plane
//! correction from the matcher. [`Panorama::place`] folds each into a canvas:
//!
//! 1. **Grid.** The canvas grid has the tiles' pitch and is anchored at the first tile's
//!    origin: canvas pixel centres lie at `x = anchor_x_um + k * pitch_x_um` (likewise y), `k`
//!    any integer. The canvas grows left, up, right and down as tiles arrive; its pixels live
//!    in fixed 512 x 512 chunks created where tiles land ([`chunks`]), so growing moves no
//!    data, and with a memory budget the least recently touched chunks spill to disk.
//! 2. **Plane and z.** Each raw height gets the plane subtracted,
//!    `raw - (piston + tilt_x * (col - (w-1)/2) + tilt_y * (row - (h-1)/2))`, and is moved
//!    from the tile's `z_offset_um` into the canvas's (the first tile's), in f64.
//! 3. **Resampling.** The corrected tile is resampled onto the canvas grid by bilinear
//!    interpolation, only inside the hull of the tile's pixel centres (no extrapolation).
//!    NaN rule: NaN corners are left out and the others renormalised; the canvas pixel gets a
//!    value only if the measured corners carry at least half of the bilinear weight. On the
//!    grid this is an exact copy (NaN stays NaN); off the grid a hole keeps its size on
//!    average. A NaN never enters an arithmetic result, so it cannot contaminate a valid
//!    pixel.
//! 4. **Blending.** The paper's "gradual in-and-out" weights (eq. 5) in 2-D: a resampled pixel
//!    at distance `d` px from its tile's nearer left/right border has `wx = min((d + 0.5) /
//!    ramp_x, 1)`, likewise `wy`, and weight `wx * wy`. The ramp defaults to the nominal
//!    overlap ([`BlendParams`]). Weights never reach 0 inside a tile, so a pixel measured by
//!    any covering tile is valid in the panorama, and seams fade linearly in both directions
//!    and at the corners where four tiles meet. A ramp <= 0.5 px is the plain average (eq. 4).
//!    Accumulators: a running weighted mean and the weight sum per pixel, both f32 (see
//!    [`Panorama`]). The third method, wavelet fusion (eq. 6), replaces the weighted mean by
//!    a DWT fusion of each new tile with the canvas over its footprint ([`method`]).
//! 5. **Quality.** [`overlap_quality`] scores every overlap of the final panorama by SSIM
//!    (eq. 7) against the two tiles that meet there.
//!
//! [`Panorama::place`] returns the [`Region`] it changed (the tile's footprint); a node sends
//! [`Panorama::extract`] of that region downstream as a patch. The work per tile is
//! proportional to the tile, never to the panorama (apart from the amortised growth), and is
//! spread over rows with rayon. [`render`] re-renders from final positions at end of scan and
//! equals sequential placement bit for bit. [`Panorama::to_raster`] gives the full, trimmed
//! panorama. [`Panorama::reserve_um`] pre-sizes the canvas from the nominal scan extent, so a
//! live scan never pays a reallocation spike.
//!
//! Heights are f32 um, row-major, NaN = not measured; x grows with columns, y with rows. Bad
//! input (wrong payload length, zero size, non-finite numbers, infinite heights, pitch <= 0)
//! is a [`FusionError`] naming the field, never a panic.
//!
//! Not for: measuring where tiles sit (surfstream-matcher sends positions and planes) or
//! separating the panorama into datum and roughness (surfstream-wavelet).

pub mod chunks;
pub mod config;
mod error;
mod input;
pub mod method;
mod panorama;
mod quality;
mod resample;
pub mod stream;
pub mod zarr;

pub use chunks::{ChunkStats, TileSpill, CHUNK_BYTES, CHUNK_PX};
pub use config::{FusionConfig, ZarrChoice};
pub use error::{FusionError, Result};
pub use input::{BlendParams, PlaneCorrection, TileInput};
pub use method::{fuse_wavelet, fuse_wavelet_in, FusionMethod, WaveletFusion};
pub use panorama::{
    render, render_panorama, Panorama, PlacedRaster, Region, DEFAULT_MAX_CANVAS_PX,
};
pub use quality::{overlap_quality, overlap_quality_streamed, PairQuality, TileFootprint};
pub use stream::{FinalPanorama, FinalReport, FusionSettings, PanoramaPatch, StreamingFusion};
#[cfg(feature = "node")]
pub mod node;
#[cfg(feature = "node")]
pub mod ports;
