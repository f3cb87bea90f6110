//! The wavelet node's state and decisions, without IPC: what a panorama patch changes, what a
//! live pass publishes, what the final pass computes and writes.
//!
//! Live: [`LiveSeparation::apply_patch`] copies each arrived panorama patch into a mirror of
//! the panorama (fixed-size chunks, cheap), and [`LiveSeparation::live_pass`] separates once
//! over the region changed since the last pass plus a margin, at the level that window
//! supports, giving datum / roughness / pooled patches flagged PREVIEW. The work is bounded by
//! the window, not the panorama. A level-8 sym5 datum depends on ~2300 px around each pixel,
//! so live patches are approximations by construction.
//! Final: [`final_separation`] is the exact pass over the whole final panorama, identical to
//! the batch computation ([`crate::analyse`]), flagged FINAL and optionally written to files.
//! For a named wavelet at a fixed or the default level (the demo and every graph in
//! launch/graphs) it streams ([`crate::stream`]): datum and roughness are computed band by
//! band, written row by row (.npy and .png byte-identical to the whole-map writers), and
//! built as whole frames only when a consumer is wired to the port. Base by RMSE, level by
//! minimum energy and the ISO filter methods (FFT over the whole map) keep the in-memory path.

use std::path::PathBuf;

use anyhow::{anyhow, bail, Result};
use surfstream_core::canvas::GridRect;
use surfstream_core::frame::{flags, FrameHeader, FrameKind, FrameView, HeightMap};
use surfstream_core::raster::{RasterView, Shape};
use surfstream_core::store::{self, ChunkedGrid, GridChunk};
use surfstream_io::output::{NpyHeights, OutputWriter, SurfaceOutput, SurfaceStream};

use surfstream_core::{Pitch, Sampling};

use crate::final_pass::{push_in_bands, separate_map, SeparatedMap, SeparationSink};
use crate::method::filter_separation;
use crate::options::SeparationSettings;
use crate::stream::StreamOptions;
use crate::{default_level, pool, separate_streamed, Mode, PoolOp, SeparationMethod, Wavelet};

/// Largest mirror the live pass keeps, px (as the fusion's canvas limit): a patch whose
/// position is absurd (a wrong unit) is refused instead of exhausting memory.
const MAX_MIRROR_PX: usize = 1 << 31;

/// The panorama as far as patches told it, on the grid of the first patch.
#[derive(Debug)]
struct PanoramaMirror {
    anchor_um: [f64; 2],
    pitch: Pitch,
    z_offset_um: f64,
    /// What patches have covered so far.
    extent: Option<GridRect>,
    heights: ChunkedHeights,
}

/// Side of a mirror chunk, px.
const MIRROR_CHUNK: i64 = 256;

/// Heights on an unbounded grid in fixed `MIRROR_CHUNK`² chunks created as patches cover them:
/// memory follows the covered area (about 4 B/px), and growing never copies (a growing
/// array would hold up to ~2.25x the area, and old + new while it reallocates). Under a
/// memory budget ([`LiveSeparation::limit_mirror`]) at most `limit` chunks stay in memory: the
/// least recently used go to an unnamed spill file ([`surfstream_core::store::ChunkedGrid`]:
/// exact bits, little-endian f32) and come back when a patch or a live window touches them. A
/// live window is a patch plus its margin, far smaller than the budget, so the chunks a scan
/// has left behind are the ones that go.
#[derive(Debug, Default)]
struct ChunkedHeights {
    grid: ChunkedGrid<MirrorChunk>,
}

/// Bytes of one mirror chunk.
const MIRROR_CHUNK_BYTES: u64 = (MIRROR_CHUNK * MIRROR_CHUNK) as u64 * 4;

/// One mirror chunk's heights, row-major, NaN where no patch wrote.
#[derive(Debug)]
struct MirrorChunk(Box<[f32]>);

impl GridChunk for MirrorChunk {
    const BYTES: usize = MIRROR_CHUNK_BYTES as usize;
    fn encode(&self, out: &mut Vec<u8>) {
        out.extend(store::encode(&self.0));
    }
    fn decode(bytes: &[u8]) -> Self {
        let mut v = Vec::with_capacity(bytes.len() / 4);
        store::decode_into(bytes, &mut v);
        MirrorChunk(v.into_boxed_slice())
    }
}

impl ChunkedHeights {
    /// The chunks `rect` touches, with the part of `rect` inside each.
    fn pieces(rect: GridRect) -> impl Iterator<Item = ((i64, i64), GridRect)> {
        let (cy0, cy1) = (
            rect.y0.div_euclid(MIRROR_CHUNK),
            (rect.y1 - 1).div_euclid(MIRROR_CHUNK),
        );
        let (cx0, cx1) = (
            rect.x0.div_euclid(MIRROR_CHUNK),
            (rect.x1 - 1).div_euclid(MIRROR_CHUNK),
        );
        (cy0..=cy1).flat_map(move |cy| {
            (cx0..=cx1).filter_map(move |cx| {
                let chunk = GridRect {
                    x0: cx * MIRROR_CHUNK,
                    y0: cy * MIRROR_CHUNK,
                    x1: (cx + 1) * MIRROR_CHUNK,
                    y1: (cy + 1) * MIRROR_CHUNK,
                };
                chunk.intersect(&rect).map(|part| ((cx, cy), part))
            })
        })
    }

    /// Keep at most `limit` chunks in memory, spilling the rest into an unnamed file in `dir`.
    fn set_limit(&mut self, limit: usize, dir: PathBuf) {
        self.grid.set_limit(Some(limit), Some(dir));
    }

    /// Chunk `key` in memory (read back from the spill file if it went there), if it exists.
    fn load(&mut self, key: (i64, i64)) -> Result<bool> {
        self.grid.tick();
        self.grid
            .load(key)
            .map_err(|e| anyhow!("wavelet: the live mirror's {e}"))
    }

    /// Spills least recently used chunks until at most the limit stay, never one in `keep`.
    fn evict(&mut self, keep: GridRect) -> Result<()> {
        let kept: std::collections::HashSet<(i64, i64)> =
            Self::pieces(keep).map(|(k, _)| k).collect();
        self.grid
            .evict(|k| kept.contains(&k))
            .map_err(|e| anyhow!("wavelet: the live mirror's {e}"))
    }

    /// Copies row-major `values` (`rect`'s size, checked by the caller) into `rect`.
    fn write(&mut self, rect: GridRect, values: &[f32]) -> Result<()> {
        if rect.cols() == 0 || rect.rows() == 0 {
            return Ok(());
        }
        let w = rect.cols();
        for ((cx, cy), part) in Self::pieces(rect) {
            if !self.load((cx, cy))? {
                self.grid.insert(
                    (cx, cy),
                    MirrorChunk(
                        vec![f32::NAN; (MIRROR_CHUNK * MIRROR_CHUNK) as usize].into_boxed_slice(),
                    ),
                );
            }
            let Some(MirrorChunk(chunk)) = self.grid.get_mut((cx, cy)) else {
                continue;
            };
            let n = part.cols();
            for y in part.y0..part.y1 {
                let src = (y - rect.y0) as usize * w + (part.x0 - rect.x0) as usize;
                let dst =
                    ((y - cy * MIRROR_CHUNK) * MIRROR_CHUNK + part.x0 - cx * MIRROR_CHUNK) as usize;
                chunk[dst..dst + n].copy_from_slice(&values[src..src + n]);
            }
        }
        self.evict(rect)
    }

    /// The heights in `rect`, row-major; NaN where no patch wrote.
    fn read(&mut self, rect: GridRect) -> Result<Vec<f32>> {
        let w = rect.cols();
        let mut out = vec![f32::NAN; w * rect.rows()];
        if out.is_empty() {
            return Ok(out);
        }
        for ((cx, cy), part) in Self::pieces(rect) {
            if !self.load((cx, cy))? {
                continue;
            }
            let Some(MirrorChunk(chunk)) = self.grid.get((cx, cy)) else {
                continue;
            };
            let n = part.cols();
            for y in part.y0..part.y1 {
                let dst = (y - rect.y0) as usize * w + (part.x0 - rect.x0) as usize;
                let src =
                    ((y - cy * MIRROR_CHUNK) * MIRROR_CHUNK + part.x0 - cx * MIRROR_CHUNK) as usize;
                out[dst..dst + n].copy_from_slice(&chunk[src..src + n]);
            }
        }
        self.evict(rect)?;
        Ok(out)
    }
}

impl PanoramaMirror {
    /// The mirror of the panorama whose first patch `h` is; its pitch is checked here, once.
    fn new(h: &FrameHeader) -> Result<Self> {
        Ok(Self {
            anchor_um: [h.origin_x_um, h.origin_y_um],
            pitch: h
                .pitch()
                .map_err(|e| anyhow!("wavelet: panorama patch {}: {e}", h.sequence))?,
            z_offset_um: h.z_offset_um,
            extent: None,
            heights: ChunkedHeights::default(),
        })
    }

    /// Copies a patch in, growing the mirror as needed; returns the patch's grid rectangle.
    fn apply(&mut self, h: &FrameHeader, heights: &[f32]) -> Result<GridRect> {
        let other = |um: f64, mirror_um: f64| (um - mirror_um).abs() > 1e-9 * mirror_um;
        if other(h.pitch_x_um, self.pitch.x_um())
            || other(h.pitch_y_um, self.pitch.y_um())
            || (h.z_offset_um - self.z_offset_um).abs() > 0.0
        {
            bail!(
                "wavelet: panorama patch {} changes pitch or z offset mid-scan",
                h.sequence
            );
        }
        let grid = |origin: f64, anchor: f64, pitch: f64| {
            let k = ((origin - anchor) / pitch).round();
            (k.abs() <= MAX_MIRROR_PX as f64).then_some(k as i64)
        };
        let (Some(x0), Some(y0)) = (
            grid(h.origin_x_um, self.anchor_um[0], self.pitch.x_um()),
            grid(h.origin_y_um, self.anchor_um[1], self.pitch.y_um()),
        ) else {
            bail!(
                "wavelet: panorama patch {} lies off the panorama's grid",
                h.sequence
            );
        };
        let r = GridRect::at(x0, y0, Shape::new(h.height as usize, h.width as usize));
        let extent = self.extent.map_or(r, |e| e.union(&r));
        if extent.area().is_none_or(|a| a > MAX_MIRROR_PX) {
            bail!(
                "wavelet: panorama patch {} grows the panorama past {MAX_MIRROR_PX} px",
                h.sequence
            );
        }
        if heights.len() != r.cols() * r.rows() || heights.is_empty() {
            bail!(
                "wavelet: panorama patch {} holds {} heights, its header says {} x {}",
                h.sequence,
                heights.len(),
                h.height,
                h.width
            );
        }
        self.heights.write(r, heights)?;
        self.extent = Some(extent);
        Ok(r)
    }

    /// A frame header for grid rectangle `r` of this panorama, pooled by `scale`.
    fn header_for(&self, r: GridRect, kind: FrameKind, scale: usize) -> Result<FrameHeader> {
        let shape = Shape::new(r.rows().div_ceil(scale), r.cols().div_ceil(scale));
        let at = Sampling::of(shape, self.pitch.times(scale)?).with_origin(
            self.anchor_um[0] + r.x0 as f64 * self.pitch.x_um(),
            self.anchor_um[1] + r.y0 as f64 * self.pitch.y_um(),
        )?;
        Ok(FrameHeader {
            kind: kind as u32,
            z_offset_um: self.z_offset_um,
            ..FrameHeader::at(&at)
        })
    }
}

/// What one live pass publishes (flag PREVIEW): the changed region's datum and roughness, and
/// the pooled blocks that cover it.
#[derive(Debug, Clone)]
pub struct LivePatches {
    pub datum: HeightMap,
    pub roughness: HeightMap,
    pub pooled: Option<HeightMap>,
}

/// The live separation of a growing panorama.
#[derive(Debug)]
pub struct LiveSeparation {
    method: SeparationMethod,
    lambda_s_um: Option<f64>,
    wavelet: Wavelet,
    mode: Mode,
    level: Option<usize>,
    pool_block: usize,
    pool_op: PoolOp,
    margin_px: usize,
    mirror: Option<PanoramaMirror>,
    /// Mirror chunks kept in memory and the spill folder for the rest (under a budget).
    mirror_limit: Option<(usize, PathBuf)>,
    /// Bytes one live pass may hold (under a budget, the mirror's share): a larger changed
    /// region is served in bands of rows over several passes ([`live_band_rows`]).
    pass_limit_bytes: Option<usize>,
    /// Grid region changed since the last live pass.
    dirty: Option<GridRect>,
    /// Latest tile and oldest acquisition time among the patches not yet served.
    trace: Option<(u32, u64)>,
}

impl LiveSeparation {
    /// Live passes with `settings`, over the changed region plus `margin_px` of context.
    pub fn new(settings: &SeparationSettings, margin_px: usize) -> Result<Self> {
        Ok(Self {
            method: settings.method,
            lambda_s_um: settings.lambda_s_um,
            wavelet: settings.live_wavelet()?,
            mode: settings.mode,
            level: settings.fixed_level(),
            pool_block: settings.pool_block.max(1),
            pool_op: settings.pool_op,
            margin_px,
            mirror: None,
            mirror_limit: None,
            pass_limit_bytes: None,
            dirty: None,
            trace: None,
        })
    }

    /// Keep at most `bytes` of the mirror in memory; the rest goes to an unnamed file in
    /// `spill_dir` (see `ChunkedHeights`): bit-exact, the mirror reads back the same. One live
    /// pass then also holds about `bytes` at most: a changed region larger than that is served
    /// in bands of rows, one band per pass ([`live_band_rows`]); each band's window has its own
    /// margin of context, so live values near a band's edge may differ from one whole pass's
    /// (as they differ with how the patches coalesce), the final pass not at all.
    pub fn limit_mirror(&mut self, bytes: u64, spill_dir: PathBuf) {
        let chunks = (bytes / MIRROR_CHUNK_BYTES).max(1) as usize;
        if let Some(m) = &mut self.mirror {
            m.heights.set_limit(chunks, spill_dir.clone());
        }
        self.mirror_limit = Some((chunks, spill_dir));
        self.pass_limit_bytes = Some(usize::try_from(bytes).unwrap_or(usize::MAX));
    }

    /// Frees the mirror (a whole f32 copy of the panorama) once the final panorama is here
    /// and its live patches are out: the final pass must not hold it too.
    pub fn release_mirror(&mut self) {
        self.mirror = None;
        self.dirty = None;
        self.trace = None;
    }

    /// Folds a panorama patch into the mirror and marks its region changed.
    pub fn apply_patch(&mut self, header: &FrameHeader, heights: &[f32]) -> Result<()> {
        let m = match &mut self.mirror {
            Some(m) => m,
            none => {
                let mut m = PanoramaMirror::new(header)?;
                if let Some((chunks, dir)) = self.mirror_limit.clone() {
                    m.heights.set_limit(chunks, dir);
                }
                none.insert(m)
            }
        };
        let r = m.apply(header, heights)?;
        self.dirty = Some(self.dirty.map_or(r, |d| d.union(&r)));
        let t = self
            .trace
            .map_or(header.t_acquired_ns, |(_, t)| t.min(header.t_acquired_ns));
        self.trace = Some((header.tile_index, t));
        Ok(())
    }

    /// True when patches arrived since the last live pass.
    pub fn has_changes(&self) -> bool {
        self.dirty.is_some()
    }

    /// Separates the changed region (plus margin) once and clears the changes. `None` when
    /// there is nothing to publish: no change, an all-NaN window, or a window too small for
    /// even level 1 (the final pass covers it).
    pub fn live_pass(&mut self) -> Result<Option<LivePatches>> {
        let (Some(m), Some(mut dirty), Some((tile, t_acq))) =
            (&mut self.mirror, self.dirty.take(), self.trace.take())
        else {
            return Ok(None);
        };
        // A filter's datum depends on lambda_c around each point: take at least that much.
        let margin = match self.method.cutoff_um() {
            Some(lc) => {
                let reach = (lc / m.pitch.min_um()).ceil();
                self.margin_px.max(reach.min(1e6) as usize)
            }
            None => self.margin_px,
        };
        // Under a budget a pass separates a band of the changed rows; the rest stays changed
        // (with its trace) for the next pass. Under `pacing = fast` the changed region grows
        // to most of the panorama while the wavelet catches up, and a pass holds about 12
        // bytes per pixel of it (the window's heights, the datum and roughness rows): 381 MB
        // for the whole 6 x 6 demo, beside the fusion's chunks and the mirror.
        if let Some(band) = self
            .pass_limit_bytes
            .map(|limit| live_band_rows(limit, dirty.cols() + 2 * margin))
            .filter(|&band| band < dirty.rows())
        {
            let split = dirty.y0 + band as i64;
            self.dirty = Some(GridRect { y0: split, ..dirty });
            self.trace = Some((tile, t_acq));
            dirty.y1 = split;
        }
        let Some(window) = m
            .extent
            .and_then(|e| dirty.expand(margin as i64).intersect(&e))
        else {
            return Ok(None);
        };
        let heights = m.heights.read(window)?;
        if heights.iter().all(|z| z.is_nan()) {
            return Ok(None);
        }
        let (rows, cols) = (window.rows(), window.cols());
        // Only the changed region is published: the window's margin is context.
        let (dx, dy) = (
            (dirty.x0 - window.x0) as usize,
            (dirty.y0 - window.y0) as usize,
        );
        let (w, h) = (dirty.cols(), dirty.rows());
        let crop = |v: &[f32]| -> Vec<f32> {
            let mut c = Vec::with_capacity(w * h);
            for row in 0..h {
                let at = (row + dy) * cols + dx;
                c.extend_from_slice(&v[at..at + w]);
            }
            c
        };
        let sep = if self.method == SeparationMethod::Wavelet {
            let Ok(level) = default_level(rows, cols, &self.wavelet, self.level) else {
                return Ok(None);
            };
            // Streamed, cropping rows as they come: the same bits as `separate`, without the
            // window's f64 copies (a window can be most of the panorama under load).
            let (mut d, mut r) = (Vec::with_capacity(w * h), Vec::with_capacity(w * h));
            separate_streamed(
                &heights,
                rows,
                cols,
                &self.wavelet,
                self.mode,
                Some(level),
                &StreamOptions::default(),
                |r0, d_band, r_band| {
                    let rows_in = d_band.chunks_exact(cols).zip(r_band.chunks_exact(cols));
                    for (i, (d_row, r_row)) in rows_in.enumerate() {
                        if (dy..dy + h).contains(&(r0 + i)) {
                            d.extend_from_slice(&d_row[dx..dx + w]);
                            r.extend_from_slice(&r_row[dx..dx + w]);
                        }
                    }
                    Ok(())
                },
            )
            .map_err(|e| anyhow!("wavelet: live separation: {e}"))?;
            (d, r)
        } else {
            let grid = Sampling::of(Shape::new(rows, cols), m.pitch);
            let s = filter_separation(&heights, grid, self.method, self.lambda_s_um)
                .map_err(|e| anyhow!("wavelet: live {} separation: {e}", self.method.name()))?;
            (crop(&s.datum), crop(&s.roughness))
        };
        // The window's heights are not needed past the separation (the pooled map reads its
        // own blocks below): not held beside them.
        drop(heights);
        let stamp = |mut h: FrameHeader| {
            h.flags |= flags::PREVIEW;
            h.tile_index = tile;
            h.t_acquired_ns = t_acq;
            h
        };
        let datum = HeightMap {
            header: stamp(m.header_for(dirty, FrameKind::Datum, 1)?),
            heights: sep.0,
        };
        let roughness = HeightMap {
            header: stamp(m.header_for(dirty, FrameKind::Roughness, 1)?),
            heights: sep.1,
        };
        // Pooled blocks stay aligned to the mirror's grid so live patches tile seamlessly.
        let pooled = match m
            .extent
            .and_then(|e| dirty.align_out(self.pool_block).intersect(&e))
        {
            Some(a) => {
                let p = pool(
                    &m.heights.read(a)?,
                    a.rows(),
                    a.cols(),
                    self.pool_block,
                    self.pool_op,
                )?;
                let mut h = stamp(m.header_for(a, FrameKind::Pooled, self.pool_block)?);
                h.width = p.cols as u32;
                h.height = p.rows as u32;
                Some(HeightMap {
                    header: h,
                    heights: p.heights,
                })
            }
            None => None,
        };
        Ok(Some(LivePatches {
            datum,
            roughness,
            pooled,
        }))
    }
}

/// Rows of the changed region one live pass takes under `limit_bytes`, for a window `cols`
/// wide: about 12 bytes per pixel are held (the window's f32 heights, the datum and roughness
/// rows), and a band is at least [`MIN_LIVE_BAND_ROWS`] (a pass makes progress, and the
/// default level's decomposition fits in it).
fn live_band_rows(limit_bytes: usize, cols: usize) -> usize {
    (limit_bytes / (12 * cols.max(1))).max(MIN_LIVE_BAND_ROWS)
}

/// The fewest changed rows a banded live pass takes.
const MIN_LIVE_BAND_ROWS: usize = 256;

/// What the final pass publishes (flag FINAL) and reports.
#[derive(Debug, Clone)]
pub struct FinalSeparation {
    /// Only when asked for ([`FinalRequest::publish_datum`]): a whole frame, built from the
    /// rows as they stream.
    pub datum: Option<HeightMap>,
    pub roughness: Option<HeightMap>,
    pub pooled: HeightMap,
    /// What the node reports (run.json's `stages.wavelet.final`).
    pub summary: FinalSummary,
}

/// The final pass's summary: the separation's ([`crate::MapSummary`]) with what only the node
/// knows. A record of the run ([`surfstream_core::record::FinalSummary`]): the node reports
/// it in its `WaveletReport`, report.html reads it back.
pub use surfstream_core::record::FinalSummary;

/// What the final pass should produce besides its summary and pooled map.
#[derive(Debug)]
pub struct FinalRequest<'a> {
    /// Write `datum`, `roughness` and `pooled` (.npy + .png) here.
    pub files: Option<&'a mut OutputWriter>,
    /// Build the whole datum / roughness frames (a consumer is connected to the port).
    pub publish_datum: bool,
    pub publish_roughness: bool,
    /// Bands and level stores of the streamed pass.
    pub stream: StreamOptions,
}

/// [`final_separation_with`] building both frames, level stores beside the files.
pub fn final_separation(
    settings: &SeparationSettings,
    panorama: &HeightMap,
    files: Option<&mut OutputWriter>,
) -> Result<FinalSeparation> {
    let stream = StreamOptions {
        spill_dir: files.as_ref().map(|w| w.dir().to_path_buf()),
        ..StreamOptions::default()
    };
    final_separation_with(
        settings,
        panorama.view(),
        FinalRequest {
            files,
            publish_datum: true,
            publish_roughness: true,
            stream,
        },
    )
}

/// The exact separation of the final panorama ([`separate_map`], the `separate` verb's code
/// too); with a writer, also `datum`, `roughness` and `pooled` as .npy + .png (datum and
/// pooled absolute f64: they carry the panorama's offset; roughness relative f32: it has none
/// by nature). Borrows the panorama (the received frame itself: no copy of it is made). A
/// named wavelet at a fixed / default level streams ([`final_pass_streams`]): memory is a
/// band of rows plus the panorama, and the datum / roughness frames are built only when
/// asked for.
pub fn final_separation_with(
    settings: &SeparationSettings,
    panorama: FrameView<'_>,
    req: FinalRequest<'_>,
) -> Result<FinalSeparation> {
    let h = *panorama.header;
    let grid = h
        .sampling()
        .map_err(|e| anyhow!("wavelet: panorama frame: {e}"))?;
    let FinalRequest {
        mut files,
        publish_datum,
        publish_roughness,
        stream,
    } = req;
    // Every .npy gets its pitch sidecar (params on datum.npy runs at the panorama's pitch).
    if let Some(fw) = files.as_deref_mut() {
        fw.set_pitch_um(h.pitch_x_um, h.pitch_y_um);
    }
    let mut sink = FinalSink {
        files,
        streams: None,
        h,
        publish_datum,
        publish_roughness,
        datum: Vec::new(),
        roughness: Vec::new(),
    };
    let map = separate_map(settings, panorama.heights, &grid, &stream, &mut sink)?;
    if let Some(w) = &map.warning {
        eprintln!("wavelet: {w}");
    }
    sink.finish()?;
    finish_final(settings, &grid, &h, map, sink)
}

/// The shared tail: `pooled` written, the summary completed, the frames built.
fn finish_final(
    settings: &SeparationSettings,
    grid: &Sampling,
    h: &FrameHeader,
    map: SeparatedMap,
    sink: FinalSink<'_>,
) -> Result<FinalSeparation> {
    let SeparatedMap {
        summary: separation,
        warning,
        pooled,
        streamed,
    } = map;
    // The pooled map's pitch: the panorama's times the block, checked once for both uses.
    let pooled_pitch = grid
        .pitch()
        .times(settings.pool_block)
        .map_err(|e| anyhow!("wavelet: pooled map: {e}"))?;
    let mut written = Vec::new();
    if let Some(fw) = sink.files {
        let block = settings.pool_block;
        fw.set_pitch_um(pooled_pitch.x_um(), pooled_pitch.y_um());
        fw.write_surface(&SurfaceOutput {
            name: "pooled",
            heights: RasterView::new(&pooled.heights, Shape::new(pooled.rows, pooled.cols))?,
            z_offset_um: h.z_offset_um,
            npy: NpyHeights::Absolute,
            title: &format!("pooled {block}x{block} (um)"),
            x3p_pitch_um: None,
        })?;
        written = fw.files().to_vec();
    }
    let summary = FinalSummary {
        separation,
        warning,
        level_requested: settings.fixed_level(),
        panorama_px: [grid.cols(), grid.rows()],
        pooled_px: [pooled.cols, pooled.rows],
        files: written,
        streamed,
    };
    let header = |kind: FrameKind| FrameHeader {
        kind: kind as u32,
        flags: flags::FINAL,
        ..*h
    };
    let mut pooled_header = header(FrameKind::Pooled);
    pooled_header.width = pooled.cols as u32;
    pooled_header.height = pooled.rows as u32;
    pooled_header.pitch_x_um = pooled_pitch.x_um();
    pooled_header.pitch_y_um = pooled_pitch.y_um();
    let frame = |kind: FrameKind, keep: bool, heights: Vec<f32>| {
        keep.then(|| HeightMap {
            header: header(kind),
            heights,
        })
    };
    Ok(FinalSeparation {
        datum: frame(FrameKind::Datum, sink.publish_datum, sink.datum),
        roughness: frame(FrameKind::Roughness, sink.publish_roughness, sink.roughness),
        pooled: HeightMap {
            header: pooled_header,
            heights: pooled.heights,
        },
        summary,
    })
}

const ROUGHNESS_TITLE: &str = "roughness (um)";

/// The node's rows: datum and roughness .npy + .png as they arrive, and the whole frames
/// when a consumer is wired.
struct FinalSink<'a> {
    files: Option<&'a mut OutputWriter>,
    streams: Option<(SurfaceStream, SurfaceStream)>,
    h: FrameHeader,
    publish_datum: bool,
    publish_roughness: bool,
    datum: Vec<f32>,
    roughness: Vec<f32>,
}

impl FinalSink<'_> {
    fn write_rows(&mut self, datum: &[f32], roughness: &[f32]) -> Result<()> {
        if let Some((ds, rs)) = self.streams.as_mut() {
            ds.push_rows(datum)?;
            rs.push_rows(roughness)?;
        }
        Ok(())
    }

    /// Completes the two files (every row must have arrived).
    fn finish(&mut self) -> Result<()> {
        if let (Some(fw), Some((ds, rs))) = (self.files.as_deref_mut(), self.streams.take()) {
            fw.finish_surface(ds)?;
            fw.finish_surface(rs)?;
        }
        Ok(())
    }
}

impl SeparationSink for FinalSink<'_> {
    fn begin(&mut self, datum_title: &str) -> Result<()> {
        let Some(fw) = self.files.as_deref() else {
            return Ok(());
        };
        let (rows, cols, z) = (
            self.h.height as usize,
            self.h.width as usize,
            self.h.z_offset_um,
        );
        self.streams = Some((
            fw.begin_surface("datum", rows, cols, z, NpyHeights::Absolute, datum_title)?,
            fw.begin_surface(
                "roughness",
                rows,
                cols,
                z,
                NpyHeights::RelativeF32,
                ROUGHNESS_TITLE,
            )?,
        ));
        Ok(())
    }

    fn push_rows(&mut self, datum: &[f32], roughness: &[f32]) -> Result<()> {
        self.write_rows(datum, roughness)?;
        if self.publish_datum {
            self.datum.extend_from_slice(datum);
        }
        if self.publish_roughness {
            self.roughness.extend_from_slice(roughness);
        }
        Ok(())
    }

    /// The in-memory paths: the files by rows, the frames take the maps themselves.
    fn whole(&mut self, datum: Vec<f32>, roughness: Vec<f32>, cols: usize) -> Result<()> {
        if self.streams.is_some() {
            push_in_bands(&mut Files(self), &datum, &roughness, cols)?;
        }
        if self.publish_datum {
            self.datum = datum;
        }
        if self.publish_roughness {
            self.roughness = roughness;
        }
        Ok(())
    }
}

/// [`FinalSink`]'s files alone (the rows of a whole map, whose frames are moved, not copied).
struct Files<'s, 'a>(&'s mut FinalSink<'a>);

impl SeparationSink for Files<'_, '_> {
    fn begin(&mut self, _: &str) -> Result<()> {
        Ok(())
    }
    fn push_rows(&mut self, datum: &[f32], roughness: &[f32]) -> Result<()> {
        self.0.write_rows(datum, roughness)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::options::final_pass_streams;
    use crate::{analyse, BaseChoice, LevelChoice};
    use serde_json::json;

    fn json_of(s: &FinalSummary) -> serde_json::Value {
        serde_json::to_value(s).unwrap()
    }

    fn settings() -> SeparationSettings {
        SeparationSettings {
            method: SeparationMethod::Wavelet,
            lambda_s_um: None,
            base: BaseChoice::Named(Wavelet::by_name("db2").unwrap()),
            level: LevelChoice::Fixed(2),
            mode: Mode::Symmetric,
            pool_block: 4,
            pool_op: PoolOp::Max,
        }
    }

    /// A panorama patch at grid (x0, y0) of a 0.5 um grid anchored at (10, 20) um.
    fn patch(x0: i64, y0: i64, cols: u32, rows: u32, f: impl Fn(i64, i64) -> f32) -> HeightMap {
        let header = FrameHeader {
            kind: FrameKind::PanoramaPatch as u32,
            width: cols,
            height: rows,
            pitch_x_um: 0.5,
            pitch_y_um: 0.5,
            origin_x_um: 10.0 + x0 as f64 * 0.5,
            origin_y_um: 20.0 + y0 as f64 * 0.5,
            tile_index: 3,
            t_acquired_ns: 77,
            ..Default::default()
        };
        let heights = (0..rows as i64)
            .flat_map(|r| (0..cols as i64).map(move |c| (r, c)))
            .map(|(r, c)| f(x0 + c, y0 + r))
            .collect();
        HeightMap { header, heights }
    }

    fn surface(x: i64, y: i64) -> f32 {
        (x as f32 * 0.3).sin() + 0.01 * y as f32
    }

    /// The mirror checks the first patch's pitch once, and refuses a later patch whose pitch
    /// differs along either axis (only x used to be compared).
    #[test]
    fn the_mirror_checks_its_pitch_once_and_refuses_another() {
        let mut bad = patch(0, 0, 4, 3, |_, _| 1.0);
        bad.header.pitch_y_um = 0.0;
        let e = PanoramaMirror::new(&bad.header).unwrap_err().to_string();
        assert!(e.contains("pitch_y_um = 0"), "{e}");
        let first = patch(0, 0, 4, 3, |_, _| 1.0);
        let mut m = PanoramaMirror::new(&first.header).unwrap();
        m.apply(&first.header, &first.heights).unwrap();
        let mut other = patch(4, 0, 4, 3, |_, _| 1.0);
        other.header.pitch_y_um = 0.25;
        let e = m.apply(&other.header, &other.heights).unwrap_err();
        assert!(e.to_string().contains("changes pitch"), "{e}");
        // A pooled header: the pitch times the block, the origin on the mirror's grid.
        let r = GridRect::at(2, 1, Shape::new(5, 6));
        let h = m.header_for(r, FrameKind::Pooled, 4).unwrap();
        assert_eq!((h.width, h.height), (2, 2));
        assert_eq!((h.pitch_x_um, h.pitch_y_um), (2.0, 2.0));
        assert_eq!((h.origin_x_um, h.origin_y_um), (11.0, 20.5));
    }

    #[test]
    fn mirror_grows_in_every_direction_and_keeps_content() {
        let first = patch(0, 0, 4, 3, |_, _| 1.0);
        let mut m = PanoramaMirror::new(&first.header).unwrap();
        m.apply(&first.header, &first.heights).unwrap();
        for (x0, y0, v) in [(-5, 0, 2.0), (0, -4, 3.0), (6, 5, 4.0), (2, 1, 5.0)] {
            let p = patch(x0, y0, 4, 3, |_, _| v);
            let r = m.apply(&p.header, &p.heights).unwrap();
            assert_eq!(m.heights.read(r).unwrap(), p.heights);
        }
        let extent = m.extent.unwrap();
        assert_eq!(
            extent,
            GridRect {
                x0: -5,
                y0: -4,
                x1: 10,
                y1: 8
            }
        );
        assert_eq!(
            m.heights
                .read(GridRect {
                    x0: 0,
                    y0: 0,
                    x1: 2,
                    y1: 1
                })
                .unwrap(),
            vec![1.0, 1.0]
        );
        assert!(m
            .heights
            .read(GridRect {
                x0: 9,
                y0: -4,
                x1: 10,
                y1: -3
            })
            .unwrap()[0]
            .is_nan());
    }

    #[test]
    fn a_mirror_limited_to_a_few_chunks_spills_and_reads_back_every_bit() {
        let dir = std::env::temp_dir();
        let mut limited = ChunkedHeights::default();
        limited.set_limit(3, dir);
        let mut whole = ChunkedHeights::default();
        // Overlapping patches across many chunks, each later one partly over earlier ones.
        for k in 0..12i64 {
            let r = GridRect::at(k * 150 - 400, (k % 3) * 170 - 90, Shape::new(300, 330));
            let v: Vec<f32> = (0..300 * 330)
                .map(|i| (i as f32).sin() + k as f32)
                .collect();
            limited.write(r, &v).unwrap();
            whole.write(r, &v).unwrap();
            assert!(limited.grid.resident_len() <= 3.max(ChunkedHeights::pieces(r).count()));
        }
        assert!(limited.grid.has_spilled(), "nothing was spilled");
        let win = GridRect::at(-450, -120, Shape::new(700, 2200));
        let (a, b) = (limited.read(win).unwrap(), whole.read(win).unwrap());
        assert_eq!(
            a.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
            b.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
        );
    }

    #[test]
    fn chunked_mirror_reads_what_was_written_across_chunks() {
        let mut c = ChunkedHeights::default();
        let a = GridRect::at(-300, -20, Shape::new(600, 700));
        let va: Vec<f32> = (0..600 * 700).map(|i| i as f32).collect();
        c.write(a, &va).unwrap();
        assert_eq!(c.read(a).unwrap(), va);
        let b = GridRect::at(200, 250, Shape::new(10, 300));
        let vb = vec![-1.0f32; 3000];
        c.write(b, &vb).unwrap();
        // A window over both and beyond: b on top of a, NaN where nothing was written.
        let win = GridRect::at(-310, -30, Shape::new(700, 900));
        let got = c.read(win).unwrap();
        for (i, v) in got.iter().enumerate() {
            let (x, y) = (win.x0 + (i % 900) as i64, win.y0 + (i / 900) as i64);
            let inside = |r: &GridRect| x >= r.x0 && x < r.x1 && y >= r.y0 && y < r.y1;
            if inside(&b) {
                assert_eq!(*v, -1.0);
            } else if inside(&a) {
                assert_eq!(*v, ((y - a.y0) * 700 + (x - a.x0)) as f32);
            } else {
                assert!(v.is_nan());
            }
        }
    }

    #[test]
    fn a_bad_patch_is_refused_not_a_panic() {
        let mut live = LiveSeparation::new(&settings(), 8).unwrap();
        let p = patch(0, 0, 4, 3, |_, _| 0.0);
        assert!(live.apply_patch(&p.header, &p.heights[..5]).is_err());
        let mut far = patch(0, 0, 4, 3, |_, _| 0.0);
        live.apply_patch(&far.header, &far.heights).unwrap();
        far.header.origin_x_um = 1e300;
        assert!(live.apply_patch(&far.header, &far.heights).is_err());
        let mut z = patch(4, 0, 4, 3, |_, _| 0.0);
        z.header.z_offset_um = 1.0;
        assert!(live.apply_patch(&z.header, &z.heights).is_err());
    }

    #[test]
    fn live_pass_covers_the_changed_region_and_clears_it() {
        let mut live = LiveSeparation::new(&settings(), 8).unwrap();
        assert!(live.live_pass().unwrap().is_none());
        let a = patch(0, 0, 40, 30, surface);
        live.apply_patch(&a.header, &a.heights).unwrap();
        let b = patch(30, 2, 40, 30, surface);
        live.apply_patch(&b.header, &b.heights).unwrap();
        assert!(live.has_changes());
        let p = live.live_pass().unwrap().expect("a live pass");
        assert!(!live.has_changes());
        // The changed region is the union of both patches, on the first patch's grid.
        let d = p.datum.header;
        assert_eq!((d.width, d.height), (70, 32));
        assert_eq!((d.origin_x_um, d.origin_y_um), (10.0, 20.0));
        assert!(d.has(flags::PREVIEW));
        assert_eq!((d.tile_index, d.t_acquired_ns), (3, 77));
        // datum + roughness = heights where measured.
        let i = 5 * 70 + 35;
        let expected = surface(35, 5);
        assert!((p.datum.heights[i] + p.roughness.heights[i] - expected).abs() < 1e-5);
        let pooled = p.pooled.expect("pooled patch");
        assert_eq!(pooled.header.pitch_x_um, 2.0);
        assert_eq!((pooled.header.width, pooled.header.height), (18, 8));
        assert!(live.live_pass().unwrap().is_none());
        let c = patch(0, 40, 40, 30, surface);
        live.apply_patch(&c.header, &c.heights).unwrap();
        live.release_mirror();
        assert!(!live.has_changes());
        assert!(live.live_pass().unwrap().is_none());
    }

    #[test]
    fn under_a_limit_a_large_changed_region_is_served_in_bands_of_rows() {
        let mut live = LiveSeparation::new(&settings(), 8).unwrap();
        // 40 px wide windows (24 + 2 x 8 margin): a band is the smallest, 256 rows.
        let band = MIN_LIVE_BAND_ROWS;
        live.limit_mirror(12 * 40 * band as u64 / 2, std::env::temp_dir());
        let a = patch(0, 0, 24, 600, surface);
        live.apply_patch(&a.header, &a.heights).unwrap();
        let mut rows = Vec::new();
        while live.has_changes() {
            let p = live.live_pass().unwrap().expect("a live pass");
            let d = p.datum.header;
            assert_eq!(d.width, 24);
            assert_eq!((d.tile_index, d.t_acquired_ns), (3, 77));
            rows.push((d.origin_y_um, d.height));
        }
        // Three passes, top to bottom, that cover the region once.
        assert_eq!(rows, [(20.0, 256), (148.0, 256), (276.0, 88)]);
        assert!(live.live_pass().unwrap().is_none());
    }

    #[test]
    fn final_separation_by_a_filter_and_the_wavelet_cutoff_are_reported() {
        let mut pano = patch(0, 0, 48, 40, surface);
        pano.header.kind = FrameKind::Panorama as u32;
        let mut s = settings();
        s.method = SeparationMethod::Gaussian { cutoff_um: 8.0 };
        let f = final_separation(&s, &pano, None).unwrap();
        assert_eq!(json_of(&f.summary)["method"], "gaussian");
        assert_eq!(json_of(&f.summary)["cutoff_um"], 8.0);
        let (fd, fr) = (f.datum.unwrap(), f.roughness.unwrap());
        for ((d, r), h) in fd.heights.iter().zip(&fr.heights).zip(&pano.heights) {
            assert!((d + r - h).abs() < 1e-5);
        }
        // The wavelet: db2 level 2 at 0.5 um is 8 pitches (4 um), reported with a warning
        // when the level asked for does not fit.
        let w = final_separation(&settings(), &pano, None).unwrap();
        let cutoff = json_of(&w.summary)["equivalent_cutoff_um"]
            .as_f64()
            .unwrap();
        assert!((cutoff - 4.0).abs() < 0.2, "{cutoff}");
        assert!(json_of(&w.summary)["warning"].is_null());
        s = settings();
        s.level = LevelChoice::Fixed(9);
        let lowered = final_separation(&s, &pano, None).unwrap();
        let text = json_of(&lowered.summary)["warning"]
            .as_str()
            .unwrap()
            .to_string();
        assert!(text.contains("level 9 lowered to"), "{text}");
        // The default level (8) does not fit either: lowered silently, same cutoff convention.
        s.level = LevelChoice::Default;
        let default = final_separation(&s, &pano, None).unwrap();
        assert!(json_of(&default.summary)["warning"].is_null());
        assert_eq!(
            json_of(&default.summary)["level"],
            json_of(&lowered.summary)["level"]
        );
    }

    #[test]
    fn final_separation_equals_the_batch_analysis_and_writes_files() {
        let pano = patch(0, 0, 48, 40, surface);
        let mut pano = pano;
        pano.header.kind = FrameKind::Panorama as u32;
        pano.header.z_offset_um = 100.0;
        let dir = tempfile::tempdir().unwrap();
        let mut w = OutputWriter::new(dir.path());
        let f = final_separation(&settings(), &pano, Some(&mut w)).unwrap();
        let batch = analyse(
            &pano.heights,
            40,
            48,
            settings().base,
            settings().level,
            Mode::Symmetric,
            4,
            PoolOp::Max,
        )
        .unwrap();
        let datum_frame = f.datum.as_ref().unwrap();
        assert_eq!(datum_frame.heights, batch.separation.datum);
        assert_eq!(f.pooled.heights, batch.pooled.heights);
        assert!(datum_frame.header.has(flags::FINAL));
        assert_eq!(
            (f.pooled.header.width, f.pooled.header.pitch_x_um),
            (12, 2.0)
        );
        assert_eq!(json_of(&f.summary)["files"].as_array().unwrap().len(), 6);
        assert_eq!(json_of(&f.summary)["level_requested"], 2);
        let datum = surfstream_io::npy::read_npy_f64(dir.path().join("datum.npy")).unwrap();
        assert_eq!(datum.data[0], f64::from(datum_frame.heights[0]) + 100.0);
    }

    /// Whole datum and roughness maps as .npy + .png by the whole-map writer (what the node
    /// wrote before it streamed): the reference of the streamed files.
    fn write_pair(
        fw: &mut OutputWriter,
        datum: &[f32],
        roughness: &[f32],
        title: &str,
        h: &FrameHeader,
    ) -> Result<()> {
        let shape = Shape::new(h.height as usize, h.width as usize);
        for (name, values, npy, title) in [
            ("datum", datum, NpyHeights::Absolute, title),
            (
                "roughness",
                roughness,
                NpyHeights::RelativeF32,
                ROUGHNESS_TITLE,
            ),
        ] {
            fw.write_surface(&SurfaceOutput {
                name,
                heights: RasterView::new(values, shape)?,
                z_offset_um: h.z_offset_um,
                npy,
                title,
                x3p_pitch_um: None,
            })?;
        }
        Ok(())
    }

    /// A demo-size panorama (a 3x3 scan of 1024^2 tiles is ~2.8k px a side; this is a
    /// quarter of that area) with holes: rows at the top, middle and bottom, scattered pixels.
    fn demo_panorama(rows: u32, cols: u32) -> HeightMap {
        let mut pano = patch(0, 0, cols, rows, |x, y| {
            let (xf, yf) = (x as f32, y as f32);
            3.0 + 0.001 * xf - 0.0005 * yf
                + (0.01 * xf).sin()
                + 0.2 * (0.3 * yf).cos()
                + ((x * 7919 + y * 104_729) % 97) as f32 * 1e-3
        });
        pano.header.kind = FrameKind::Panorama as u32;
        pano.header.z_offset_um = 1234.5;
        let c = cols as usize;
        for r in [0usize, 1, rows as usize / 2, rows as usize - 1] {
            pano.heights[r * c..(r + 1) * c].fill(f32::NAN);
        }
        for i in (3..pano.heights.len()).step_by(1009) {
            pano.heights[i] = f32::NAN;
        }
        pano
    }

    #[test]
    fn streamed_final_files_are_byte_identical_to_the_in_memory_ones() {
        let (rows, cols) = (1401u32, 1400u32);
        let pano = demo_panorama(rows, cols);
        let mut s = settings();
        s.base = BaseChoice::Named(Wavelet::by_name("sym5").unwrap());
        s.level = LevelChoice::Default;
        assert!(final_pass_streams(&s));
        for mode in [Mode::Symmetric, Mode::Periodization] {
            s.mode = mode;
            let dir = tempfile::tempdir().unwrap();
            let (a, b) = (dir.path().join("streamed"), dir.path().join("reference"));
            std::fs::create_dir_all(&a).unwrap();
            std::fs::create_dir_all(&b).unwrap();
            let mut wa = OutputWriter::new(&a);
            let f = final_separation(&s, &pano, Some(&mut wa)).unwrap();
            assert_eq!(json_of(&f.summary)["streamed"], true);
            // What the node wrote before streaming: analyse(), then whole-map writers.
            let (r, c) = (rows as usize, cols as usize);
            let batch =
                analyse(&pano.heights, r, c, s.base, s.level, mode, 4, PoolOp::Max).unwrap();
            let mut wb = OutputWriter::new(&b);
            let level = batch.separation.level;
            write_pair(
                &mut wb,
                &batch.separation.datum,
                &batch.separation.roughness,
                &format!("datum, sym5 level {level} (um)"),
                &pano.header,
            )
            .unwrap();
            wb.write_surface(&SurfaceOutput {
                name: "pooled",
                heights: RasterView::new(
                    &batch.pooled.heights,
                    Shape::new(batch.pooled.rows, batch.pooled.cols),
                )
                .unwrap(),
                z_offset_um: pano.header.z_offset_um,
                npy: NpyHeights::Absolute,
                title: "pooled 4x4 (um)",
                x3p_pitch_um: None,
            })
            .unwrap();
            assert_eq!(wa.files(), wb.files());
            assert_eq!(wa.files().len(), 6);
            for name in wb.files() {
                let x = std::fs::read(a.join(name)).unwrap();
                let y = std::fs::read(b.join(name)).unwrap();
                assert!(x == y, "{mode}: {name} differs");
            }
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert!(bits(&f.datum.unwrap().heights) == bits(&batch.separation.datum));
            assert!(bits(&f.roughness.unwrap().heights) == bits(&batch.separation.roughness));
            // The summary: the same choices; the energy curve to round-off.
            let reference = serde_json::to_value(batch.summary()).unwrap();
            assert_eq!(
                json_of(&f.summary)["pooled_px"],
                json!([batch.pooled.cols, batch.pooled.rows])
            );
            for key in [
                "wavelet",
                "mode",
                "level",
                "level_min_energy",
                "pooling_bias",
            ] {
                assert_eq!(json_of(&f.summary)[key], reference[key], "{key}");
            }
            let fj = json_of(&f.summary);
            let (ea, eb) = (&fj["energy_curve"], &reference["energy_curve"]);
            assert_eq!(ea.as_array().unwrap().len(), eb.as_array().unwrap().len());
            for (p, q) in ea.as_array().unwrap().iter().zip(eb.as_array().unwrap()) {
                let (x, y) = (
                    p["approx_energy_fraction"].as_f64().unwrap(),
                    q["approx_energy_fraction"].as_f64().unwrap(),
                );
                assert!((x - y).abs() <= 1e-12 * x.abs(), "{x} vs {y}");
            }
        }
    }

    #[test]
    fn frames_only_when_asked_and_other_choices_stay_in_memory() {
        let pano = demo_panorama(120, 90);
        let dir = tempfile::tempdir().unwrap();
        let mut w = OutputWriter::new(dir.path());
        let f = final_separation_with(
            &settings(),
            pano.view(),
            FinalRequest {
                files: Some(&mut w),
                publish_datum: false,
                publish_roughness: true,
                stream: StreamOptions::default(),
            },
        )
        .unwrap();
        assert!(f.datum.is_none());
        assert_eq!(f.roughness.unwrap().heights.len(), 120 * 90);
        assert_eq!(json_of(&f.summary)["files"].as_array().unwrap().len(), 6);
        assert!(dir.path().join("datum.npy").exists());
        let mut s = settings();
        s.level = LevelChoice::MinEnergy;
        assert!(!final_pass_streams(&s));
        let f = final_separation(&s, &pano, None).unwrap();
        assert_eq!(json_of(&f.summary)["streamed"], false);
        s = settings();
        s.base = BaseChoice::MinRmse;
        assert!(!final_pass_streams(&s));
        s = settings();
        s.method = SeparationMethod::Gaussian { cutoff_um: 8.0 };
        assert!(!final_pass_streams(&s));
    }
}
