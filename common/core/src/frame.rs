//! The one frame type that carries every raster in the system (DESIGN §2), and the small fixed
//! messages that travel beside it.
//!
//! A frame is a `#[repr(C)]` [`FrameHeader`] plus a row-major `[f32]` payload of
//! `width * height` heights in micrometres relative to `z_offset_um`; NaN = not measured.
//! Scan coordinates: x grows along columns, y along rows, both in micrometres in the stage's
//! frame; `origin_*_um` is the position of pixel (0, 0).

use iceoryx2_bb_derive_macros::ZeroCopySend;
use iceoryx2_bb_elementary_traits::zero_copy_send::ZeroCopySend;
use serde::{Deserialize, Serialize};

use crate::{ParamError, Pitch, Sampling, Shape};

/// Versioned type name: two binaries with different header layouts refuse to connect.
pub const FRAME_TYPE_NAME: &str = "surfstream.FrameHeader.v1";
/// Versioned type name of [`TileRegistration`].
pub const REGISTRATION_TYPE_NAME: &str = "surfstream.TileRegistration.v1";

/// What a frame holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[repr(u32)]
pub enum FrameKind {
    Tile = 1,
    PanoramaPatch = 2,
    Panorama = 3,
    Datum = 4,
    Roughness = 5,
    Pooled = 6,
    /// A payload-less frame that only carries flags (end of scan).
    Marker = 7,
}

impl FrameKind {
    pub fn from_u32(v: u32) -> Option<Self> {
        Some(match v {
            1 => Self::Tile,
            2 => Self::PanoramaPatch,
            3 => Self::Panorama,
            4 => Self::Datum,
            5 => Self::Roughness,
            6 => Self::Pooled,
            7 => Self::Marker,
            _ => return None,
        })
    }
    pub fn name(self) -> &'static str {
        match self {
            Self::Tile => "tile",
            Self::PanoramaPatch => "panorama_patch",
            Self::Panorama => "panorama",
            Self::Datum => "datum",
            Self::Roughness => "roughness",
            Self::Pooled => "pooled",
            Self::Marker => "marker",
        }
    }
}

/// Frame flags (bit set).
pub mod flags {
    /// The frame is a final result (not a live patch).
    pub const FINAL: u32 = 1 << 0;
    /// No frame follows on this channel: the scan is over.
    pub const END_OF_SCAN: u32 = 1 << 1;
    /// The tile was placed by its stage position because registration gave no trustworthy answer.
    pub const PLACED_BY_STAGE: u32 = 1 << 2;
    /// A live patch computed on a bounded window: an approximation that the final pass replaces.
    pub const PREVIEW: u32 = 1 << 3;
}

/// The frame header (DESIGN §2). Plain numbers only, so it crosses shared memory as is.
#[derive(Debug, Default, Clone, Copy, PartialEq, ZeroCopySend, Serialize, Deserialize)]
#[type_name("surfstream.FrameHeader.v1")]
#[repr(C)]
pub struct FrameHeader {
    /// [`FrameKind`] as u32.
    pub kind: u32,
    /// [`flags`] bit set.
    pub flags: u32,
    /// Identifies one scan (seeded from the run), so frames of two scans never mix.
    pub scan_id: u64,
    /// Per-channel sequence number, 0, 1, 2, ...
    pub sequence: u64,
    /// Index (acquisition order) of the tile whose arrival caused this frame.
    pub tile_index: u32,
    /// Grid row / column of that tile (tiles only; 0 otherwise).
    pub tile_row: u32,
    pub tile_col: u32,
    pub width: u32,
    pub height: u32,
    pub _pad: u32,
    pub pitch_x_um: f64,
    pub pitch_y_um: f64,
    /// Scan position of pixel (0, 0). For a tile: the nominal stage position.
    pub origin_x_um: f64,
    pub origin_y_um: f64,
    /// Heights in the payload are relative to this (f64 keeps absolute heights exact).
    pub z_offset_um: f64,
    /// CLOCK_MONOTONIC (ns) when the causing tile was acquired.
    pub t_acquired_ns: u64,
    /// CLOCK_MONOTONIC (ns) when this frame was sent.
    pub t_sent_ns: u64,
}

impl FrameHeader {
    pub fn kind(&self) -> Option<FrameKind> {
        FrameKind::from_u32(self.kind)
    }
    pub fn has(&self, flag: u32) -> bool {
        self.flags & flag != 0
    }
    pub fn len(&self) -> usize {
        self.width as usize * self.height as usize
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Where the payload's samples lie: `height x width`, the pitch and the origin, checked
    /// by [`Sampling::new`] (a marker has no payload: its pitch is 0, an error).
    pub fn sampling(&self) -> Result<Sampling, ParamError> {
        Sampling::of(
            Shape::new(self.height as usize, self.width as usize),
            self.pitch()?,
        )
        .with_origin(self.origin_x_um, self.origin_y_um)
    }
    /// The payload's pitch, checked by [`Pitch::new`] (a marker's pitch is 0, an error).
    pub fn pitch(&self) -> Result<Pitch, ParamError> {
        Pitch::new(self.pitch_x_um, self.pitch_y_um)
    }
    /// A header whose `width`, `height`, pitch and origin are `sampling`'s, every other field
    /// default: the typed way into the wire fields (`FrameHeader { kind, .., ..at(s) }`).
    pub fn at(sampling: &Sampling) -> Self {
        Self {
            width: sampling.cols() as u32,
            height: sampling.rows() as u32,
            pitch_x_um: sampling.pitch_x_um(),
            pitch_y_um: sampling.pitch_y_um(),
            origin_x_um: sampling.origin_x_um(),
            origin_y_um: sampling.origin_y_um(),
            ..Default::default()
        }
    }
    /// The end-of-scan marker that closes a frame channel.
    pub fn end_of_scan(scan_id: u64, sequence: u64, tile_index: u32, t_acquired_ns: u64) -> Self {
        Self {
            kind: FrameKind::Marker as u32,
            flags: flags::END_OF_SCAN,
            scan_id,
            sequence,
            tile_index,
            t_acquired_ns,
            ..Default::default()
        }
    }
}

/// An owned frame: header plus heights.
#[derive(Debug, Clone, PartialEq)]
pub struct HeightMap {
    pub header: FrameHeader,
    pub heights: Vec<f32>,
}

impl HeightMap {
    pub fn view(&self) -> FrameView<'_> {
        FrameView {
            header: &self.header,
            heights: &self.heights,
        }
    }
}

/// A borrowed frame: what a node sees on input (a view into shared memory under `launch`).
#[derive(Debug, Clone, Copy)]
pub struct FrameView<'a> {
    pub header: &'a FrameHeader,
    pub heights: &'a [f32],
}

impl FrameView<'_> {
    pub fn to_owned(&self) -> HeightMap {
        HeightMap {
            header: *self.header,
            heights: self.heights.to_vec(),
        }
    }
}

/// How a tile's final position was decided.
pub mod placed_by {
    pub const REGISTRATION: u32 = 1;
    pub const STAGE: u32 = 2;
}

/// One tile's registration: where it goes and how its heights are levelled into the panorama.
/// Published once per tile by the matcher, then once more per tile (flag FINAL) when a global
/// solve revises positions at end of scan.
#[derive(Debug, Default, Clone, Copy, PartialEq, ZeroCopySend, Serialize, Deserialize)]
#[type_name("surfstream.TileRegistration.v1")]
#[repr(C)]
pub struct TileRegistration {
    pub scan_id: u64,
    pub sequence: u64,
    pub tile_index: u32,
    /// [`placed_by`] value.
    pub placed_by: u32,
    /// [`flags`] bit set (END_OF_SCAN closes the channel; such a message carries no tile).
    pub flags: u32,
    /// Number of neighbour links that were accepted for this tile.
    pub links_accepted: u32,
    /// Number of neighbour links that were tried.
    pub links_tried: u32,
    pub _pad: u32,
    /// Final scan position of the tile's pixel (0, 0).
    pub x_um: f64,
    pub y_um: f64,
    /// Height correction subtracted before blending: piston + tilt_x * (col - c0) + tilt_y * (row - r0),
    /// with (r0, c0) the tile centre; um and um per pixel.
    pub piston_um: f64,
    pub tilt_x_um_per_px: f64,
    pub tilt_y_um_per_px: f64,
    /// Best link quality (normalized cross-correlation of the overlap after levelling), 0 if none.
    pub quality: f64,
    pub t_acquired_ns: u64,
    pub t_sent_ns: u64,
}

impl TileRegistration {
    pub fn has(&self, flag: u32) -> bool {
        self.flags & flag != 0
    }
}

/// Monotonic clock (CLOCK_MONOTONIC, ns): shared by all processes on the machine, so latencies
/// across processes are differences of these.
pub fn monotonic_ns() -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes into the timespec we own.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

/// Absolute heights (um, f64) as a frame carries them: f32 relative to an f64 offset, here the
/// mean of the valid heights (0 when none), so absolute heights far from zero (MetroPro ~50 um,
/// a part 25 mm up the z axis) keep the f32's 7 digits for the surface's own variation.
/// Returns (z_offset_um, heights); [`from_frame_heights`] inverts it.
pub fn to_frame_heights(heights_um: &[f64]) -> (f64, Vec<f32>) {
    let z_offset_um = valid_mean(heights_um);
    (z_offset_um, to_frame_heights_at(heights_um, z_offset_um))
}

/// Absolute heights (um, f64) as f32 relative to a given `z_offset_um`: for tiles that share
/// one offset (a scan's, so overlaps compare without conversion). NaN stays NaN.
pub fn to_frame_heights_at(heights_um: &[f64], z_offset_um: f64) -> Vec<f32> {
    heights_um
        .iter()
        .map(|&z| (z - z_offset_um) as f32)
        .collect()
}

/// Absolute heights (um, f64) from a frame's `z_offset_um` and f32 payload.
pub fn from_frame_heights(z_offset_um: f64, heights: &[f32]) -> Vec<f64> {
    heights
        .iter()
        .map(|&z| f64::from(z) + z_offset_um)
        .collect()
}

/// The mean of the non-NaN values, 0 when there are none.
pub fn valid_mean(values: &[f64]) -> f64 {
    let (n, sum) = values
        .iter()
        .filter(|z| !z.is_nan())
        .fold((0usize, 0.0), |(n, s), &z| (n + 1, s + z));
    if n == 0 {
        0.0
    } else {
        sum / n as f64
    }
}
