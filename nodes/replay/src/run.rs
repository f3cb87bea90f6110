//! A replay run: the tiles of one scan in acquisition order, and when each one is due.
//!
//! [`StageRun`] owns where the tiles come from ([`TileSource`]: the simulated stage, which
//! measures each tile when it is due, or frames already in memory from a scan directory or a
//! recording) and the pacing decision ([`Pacing`]). The node shell only asks when the next
//! tile is due ([`StageRun::next_due`]) and takes it ([`StageRun::next_tile`]); clocks are
//! passed in, so the decisions are tested without waiting.

use std::time::{Duration, Instant};

use surfstream_core::frame::{FrameHeader, FrameKind, HeightMap};

use crate::{acquire_tile, ScanPlan, VirtualSpecimen};

/// Where tiles come from.
pub enum TileSource {
    /// The simulated stage: each tile is measured from the specimen when it is due.
    Simulated {
        specimen: VirtualSpecimen,
        plan: Box<ScanPlan>,
    },
    /// Tiles already in memory (scan directory, recording), with their headers, in
    /// acquisition order.
    Frames(Vec<HeightMap>),
}

/// When to emit the next tile.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Pacing {
    /// As fast as the graph takes them.
    Fast,
    /// One field every `Duration`, like the instrument.
    Fixed(Duration),
    /// The recording's own gaps (log times, ns since the first message).
    Original,
}

/// The longest time per field a simulated stage may take (30 days, as the graph's timeouts).
pub const MAX_FIELD_TIME_S: f64 = 30.0 * 24.0 * 3600.0;

/// One tile handed to the graph.
pub struct DueTile {
    pub frame: HeightMap,
    /// Acquisition index of the tile.
    pub index: usize,
    /// The scan's last tile: end of scan follows.
    pub last: bool,
}

/// The tiles of one scan in acquisition order, with the pacing that releases them.
pub struct StageRun {
    source: TileSource,
    pacing: Pacing,
    /// Original-timing offsets per tile (recordings only).
    offsets_ns: Vec<u64>,
    /// When the first tile went out: the pacing's time zero.
    started: Option<Instant>,
    next: usize,
}

impl StageRun {
    /// A run over `source`; `offsets_ns` (one per tile, from the first) only for
    /// [`Pacing::Original`].
    pub fn new(source: TileSource, pacing: Pacing, offsets_ns: Vec<u64>) -> Self {
        Self {
            source,
            pacing,
            offsets_ns,
            started: None,
            next: 0,
        }
    }

    /// Number of tiles in the scan.
    pub fn tile_count(&self) -> usize {
        match &self.source {
            TileSource::Simulated { plan, .. } => plan.tiles.len(),
            TileSource::Frames(f) => f.len(),
        }
    }

    /// Tiles handed out so far.
    pub fn sent(&self) -> usize {
        self.next
    }

    /// Every tile has been handed out.
    pub fn is_done(&self) -> bool {
        self.next >= self.tile_count()
    }

    /// The simulated stage's plan (for the truth written beside the outputs).
    pub fn plan(&self) -> Option<&ScanPlan> {
        match &self.source {
            TileSource::Simulated { plan, .. } => Some(plan),
            TileSource::Frames(_) => None,
        }
    }

    /// The simulated specimen (for saving it beside the outputs).
    pub fn specimen(&self) -> Option<&VirtualSpecimen> {
        match &self.source {
            TileSource::Simulated { specimen, .. } => Some(specimen),
            TileSource::Frames(_) => None,
        }
    }

    /// When the next tile is due (`now` before the first one; `None` when done).
    pub fn next_due(&self, now: Instant) -> Option<Instant> {
        if self.is_done() {
            return None;
        }
        let Some(t0) = self.started else {
            return Some(now);
        };
        Some(match self.pacing {
            Pacing::Fast => now,
            Pacing::Fixed(d) => t0 + d * self.next as u32,
            Pacing::Original => {
                t0 + Duration::from_nanos(self.offsets_ns.get(self.next).copied().unwrap_or(0))
            }
        })
    }

    /// The next tile in acquisition order (measured now for the simulated stage), or `None`
    /// when every tile has been handed out. `now` starts the pacing's clock on the first call.
    pub fn next_tile(&mut self, now: Instant) -> Option<DueTile> {
        if self.is_done() {
            return None;
        }
        self.started.get_or_insert(now);
        let k = self.next;
        let frame = self.acquire(k);
        self.next += 1;
        Some(DueTile {
            frame,
            index: k,
            last: self.is_done(),
        })
    }

    fn acquire(&mut self, k: usize) -> HeightMap {
        match &mut self.source {
            TileSource::Simulated { specimen, plan } => {
                let t = &plan.tiles[k];
                let heights = acquire_tile(specimen, t, &plan.params);
                let header = FrameHeader {
                    kind: FrameKind::Tile as u32,
                    tile_index: k as u32,
                    tile_row: t.row as u32,
                    tile_col: t.col as u32,
                    width: plan.tile_width_px as u32,
                    height: plan.tile_height_px as u32,
                    pitch_x_um: plan.params.pitch_um,
                    pitch_y_um: plan.params.pitch_um,
                    origin_x_um: t.stage_position_um[0],
                    origin_y_um: t.stage_position_um[1],
                    ..Default::default()
                };
                HeightMap { header, heights }
            }
            // Move the tile out: it is sent once.
            TileSource::Frames(f) => std::mem::replace(
                &mut f[k],
                HeightMap {
                    header: FrameHeader::default(),
                    heights: Vec::new(),
                },
            ),
        }
    }
}
