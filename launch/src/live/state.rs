//! What the live view knows of the run, and the one place it changes: the observer's messages
//! (tiles, registrations, preview patches), the node reports as each node finishes, and
//! run.json at the end. The page, `/state.json` and the Foxglove bridge all read snapshots of
//! it; nothing here waits on a reader.
//!
//! The numbers are the pipeline's own: registrations as the matcher sent them, latencies from
//! the frames' clock stamps, the pairs and the verdict from the same typed records report.html
//! and the CLI's verdict read (`surfstream_core::record`, [`crate::verdict`]).

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

use serde::Serialize;
use surfstream_core::frame::{flags, placed_by, FrameHeader, HeightMap, TileRegistration};
use surfstream_core::record::{
    FusionReport, MatcherPair, MatcherReport, MeshReport, NodeRecord, RunRecord, WaveletReport,
};

/// The preview canvas's longer side, cells: beyond it the canvas halves its resolution.
pub const CANVAS_MAX_SIDE: usize = 2048;

/// How a tile was placed, as the page colours it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Placement {
    /// By registration against its neighbours (or the first tile, the anchor).
    Registration,
    /// By registration through a link the matcher accepted below its NCC floor (a distinct
    /// peak on sparse texture): known from the matcher's pair log as it decides the pair,
    /// confirmed (or cleared, when the global solve dropped the link) by its report.
    WeakLink,
    /// Where the stage put it: no neighbour link held.
    StageFallback,
}

/// One tile as the page shows it.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct TileView {
    pub index: u32,
    pub row: Option<u32>,
    pub col: Option<u32>,
    /// The stage's planned (nominal) position of pixel (0, 0), um: the tile frame's origin.
    pub stage_x_um: Option<f64>,
    pub stage_y_um: Option<f64>,
    /// The field's size, um (from the tile frame).
    pub width_um: Option<f64>,
    pub height_um: Option<f64>,
    /// Where the matcher placed pixel (0, 0), um: the streaming registration, replaced by the
    /// end-of-scan solve's when it arrives (`final_solve`).
    pub x_um: Option<f64>,
    pub y_um: Option<f64>,
    pub placement: Option<Placement>,
    /// The best link's NCC (None before a link was tried).
    pub ncc: Option<f64>,
    pub links_tried: u32,
    pub links_accepted: u32,
    pub final_solve: bool,
    /// Acquisition of the tile -> its panorama preview patch sent by the fusion, ms.
    pub tile_to_panorama_ms: Option<f64>,
}

/// One neighbour pair: the matcher's streaming record from its pair log as it decides the
/// pair, replaced by the report's (after the global solve) when the matcher finishes.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PairView {
    pub a: u32,
    pub b: u32,
    pub direction: String,
    pub ncc: f64,
    pub accepted: bool,
    pub weak_link: bool,
    /// The offset disagrees with the layout's plan beyond the stage error (refused or
    /// flagged: `MatcherPair::layout_inconsistent`).
    pub layout_inconsistent: bool,
    pub kept_by_global_solve: Option<bool>,
    /// b's offset from a by the stage and by the registration, px.
    pub nominal_offset_px: [f64; 2],
    pub offset_px: Option<[f64; 2]>,
    /// |(p_b - p_a) - offset|, px: in the global solve's solution (the report's), or while
    /// streaming from the two tiles' registered positions as the view has them.
    pub residual_px: Option<f64>,
    /// Where `residual_px` comes from: "global_solve" or "streaming_placement".
    pub residual_of: Option<&'static str>,
    pub reason: Option<String>,
    /// The record is the report's (the global solve ran), not the streaming one.
    pub final_solve: bool,
}

/// One line of the running verdict: a stage that finished.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StageLine {
    pub stage: String,
    pub text: String,
    /// Whether the stage's own check passed (None: it has none).
    pub ok: Option<bool>,
}

/// The run's end.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FinalVerdict {
    /// "PASS" or "FAIL".
    pub verdict: &'static str,
    /// The CLI's verdict text (the same lines `surfstream` prints), or the run's error.
    pub text: String,
    pub failures: Vec<String>,
    /// report.html, served at /report.html, when the run wrote it.
    pub report: bool,
}

/// Messages the view could not show: it drops, the pipeline never waits.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Drops {
    /// Preview patches the latest-wins channel replaced before the view read them (gaps in
    /// the channel's sequence numbers).
    pub preview_patches_missed: u64,
    /// State updates a slow page skipped (it gets the newest one instead).
    pub page_updates_skipped: u64,
    /// Messages a slow Foxglove client skipped (it gets the newest one instead).
    pub foxglove_messages_skipped: u64,
}

/// Readers connected now.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Viewers {
    /// Pages with an open event stream.
    pub pages: u32,
    pub foxglove_clients: u32,
}

/// The growing panorama at preview resolution: each preview patch written where it lies,
/// halving the resolution whenever the canvas would pass [`CANVAS_MAX_SIDE`].
#[derive(Debug, Clone, Default)]
pub struct Canvas {
    /// Cell size, um (x, y); 0 before the first patch.
    pub cell_x_um: f64,
    pub cell_y_um: f64,
    /// Scan position of cell (0, 0), um.
    pub x0_um: f64,
    pub y0_um: f64,
    pub rows: usize,
    pub cols: usize,
    /// Heights relative to `z0_um` (NaN: nothing yet).
    pub heights: Vec<f32>,
    pub z0_um: f64,
}

impl Canvas {
    pub fn is_empty(&self) -> bool {
        self.heights.is_empty()
    }

    /// Writes one preview patch (a panorama region, heights relative to its `z_offset_um`).
    /// Frames without a usable sampling (markers, a zero pitch) are ignored.
    pub fn apply(&mut self, h: &FrameHeader, heights: &[f32]) {
        let (w, ht) = (h.width as usize, h.height as usize);
        let finite = |v: f64| v.is_finite();
        if w == 0
            || ht == 0
            || heights.len() != w * ht
            || !(h.pitch_x_um > 0.0 && h.pitch_y_um > 0.0)
            || !finite(h.origin_x_um + h.origin_y_um + h.z_offset_um)
        {
            return;
        }
        if self.is_empty() {
            self.cell_x_um = h.pitch_x_um;
            self.cell_y_um = h.pitch_y_um;
            self.x0_um = h.origin_x_um;
            self.y0_um = h.origin_y_um;
            self.z0_um = h.z_offset_um;
        }
        let (x1, y1) = (
            h.origin_x_um + w as f64 * h.pitch_x_um,
            h.origin_y_um + ht as f64 * h.pitch_y_um,
        );
        self.cover(h.origin_x_um, h.origin_y_um, x1, y1);
        let dz = (h.z_offset_um - self.z0_um) as f32;
        let c_lo = self.col_of(h.origin_x_um).max(0) as usize;
        let c_hi = (self.col_of(x1).max(0) as usize).min(self.cols);
        let r_lo = self.row_of(h.origin_y_um).max(0) as usize;
        let r_hi = (self.row_of(y1).max(0) as usize).min(self.rows);
        // Each covered cell takes the patch's pixel nearest its centre.
        for r in r_lo..r_hi {
            let y = self.y0_um + (r as f64 + 0.5) * self.cell_y_um;
            let pr = ((y - h.origin_y_um) / h.pitch_y_um).floor();
            let pr = pr.clamp(0.0, (ht - 1) as f64) as usize;
            for c in c_lo..c_hi {
                let x = self.x0_um + (c as f64 + 0.5) * self.cell_x_um;
                let pc = ((x - h.origin_x_um) / h.pitch_x_um).floor();
                let pc = pc.clamp(0.0, (w - 1) as f64) as usize;
                let v = heights[pr * w + pc];
                self.heights[r * self.cols + c] = v + dz;
            }
        }
    }

    fn col_of(&self, x_um: f64) -> i64 {
        ((x_um - self.x0_um) / self.cell_x_um).round() as i64
    }
    fn row_of(&self, y_um: f64) -> i64 {
        ((y_um - self.y0_um) / self.cell_y_um).round() as i64
    }

    /// Grows the canvas to cover [x0, x1) x [y0, y1) um, coarsening while it is too large.
    fn cover(&mut self, x0: f64, y0: f64, x1: f64, y1: f64) {
        loop {
            let (c_lo, c_hi) = (
                self.col_of(x0).min(0),
                self.col_of(x1).max(self.cols as i64),
            );
            let (r_lo, r_hi) = (
                self.row_of(y0).min(0),
                self.row_of(y1).max(self.rows as i64),
            );
            let (cols, rows) = ((c_hi - c_lo) as usize, (r_hi - r_lo) as usize);
            if cols.max(rows) > CANVAS_MAX_SIDE {
                self.halve();
                continue;
            }
            if c_lo == 0 && r_lo == 0 && cols == self.cols && rows == self.rows {
                return;
            }
            let mut grown = vec![f32::NAN; rows * cols];
            let (dc, dr) = ((-c_lo) as usize, (-r_lo) as usize);
            for r in 0..self.rows {
                let src = &self.heights[r * self.cols..(r + 1) * self.cols];
                let at = (r + dr) * cols + dc;
                grown[at..at + self.cols].copy_from_slice(src);
            }
            self.x0_um += c_lo as f64 * self.cell_x_um;
            self.y0_um += r_lo as f64 * self.cell_y_um;
            self.heights = grown;
            self.rows = rows;
            self.cols = cols;
            return;
        }
    }

    /// Halves the resolution: each new cell the NaN-aware mean of a 2 x 2 block.
    fn halve(&mut self) {
        let (rows, cols) = (self.rows.div_ceil(2), self.cols.div_ceil(2));
        let mut small = vec![f32::NAN; rows * cols];
        for r in 0..rows {
            for c in 0..cols {
                let (mut sum, mut n) = (0.0f32, 0u32);
                for (rr, cc) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
                    let (y, x) = (2 * r + rr, 2 * c + cc);
                    if y < self.rows && x < self.cols {
                        let v = self.heights[y * self.cols + x];
                        if v.is_finite() {
                            sum += v;
                            n += 1;
                        }
                    }
                }
                if n > 0 {
                    small[r * cols + c] = sum / n as f32;
                }
            }
        }
        self.heights = small;
        self.rows = rows;
        self.cols = cols;
        self.cell_x_um *= 2.0;
        self.cell_y_um *= 2.0;
    }
}

/// Everything the view shows.
#[derive(Debug, Clone)]
pub struct LiveState {
    pub graph: String,
    /// Tiles the source will send (None: it does not say before it runs, e.g. a recording).
    pub tiles_planned: Option<usize>,
    /// (row, col) by acquisition index, where the source says.
    pub grid: Vec<(usize, usize)>,
    pub tiles: BTreeMap<u32, TileView>,
    pub pairs: Vec<PairView>,
    pub stages: Vec<StageLine>,
    pub verdict: Option<FinalVerdict>,
    pub drops: Drops,
    pub viewers: Viewers,
    pub canvas: Canvas,
    /// The newest tile at full resolution (the page's crop, Foxglove's `/tiles`).
    pub newest_tile: Option<Arc<HeightMap>>,
    /// The newest preview patch (Foxglove's `/panorama/patches`).
    pub newest_patch: Option<Arc<HeightMap>>,
    /// Bumped on every change (readers compare it).
    pub version: u64,
    /// Bumped when the canvas, the newest tile, the tile boxes change.
    pub canvas_version: u64,
    pub tile_version: u64,
    pub boxes_version: u64,
    /// When the first and the latest tile registered.
    pub first_registered: Option<Instant>,
    pub last_registered: Option<Instant>,
    pub started: Instant,
    /// The scan ended (the matcher's end of scan) / the run ended (the verb returned).
    pub scan_ended: bool,
    pub run_ended: bool,
    pub stop_allowed: bool,
    last_preview_sequence: Option<u64>,
    /// Tiles at either end of an accepted weak link (streaming, then the report's).
    weak_tiles: std::collections::BTreeSet<u32>,
    /// The tiles' pitch (x, y), um, from the first tile frame: streaming residuals in px.
    pitch_um: Option<[f64; 2]>,
}

impl LiveState {
    pub fn new(graph: &str, grid: Vec<(usize, usize)>, stop_allowed: bool) -> Self {
        LiveState {
            graph: graph.into(),
            tiles_planned: (!grid.is_empty()).then_some(grid.len()),
            grid,
            tiles: BTreeMap::new(),
            pairs: Vec::new(),
            stages: Vec::new(),
            verdict: None,
            drops: Drops::default(),
            viewers: Viewers::default(),
            canvas: Canvas::default(),
            newest_tile: None,
            newest_patch: None,
            version: 0,
            canvas_version: 0,
            tile_version: 0,
            boxes_version: 0,
            first_registered: None,
            last_registered: None,
            started: Instant::now(),
            scan_ended: false,
            run_ended: false,
            stop_allowed,
            last_preview_sequence: None,
            weak_tiles: Default::default(),
            pitch_um: None,
        }
    }

    fn tile(&mut self, index: u32) -> &mut TileView {
        let grid = self.grid.get(index as usize).copied();
        self.tiles.entry(index).or_insert_with(|| TileView {
            index,
            row: grid.map(|g| g.0 as u32),
            col: grid.map(|g| g.1 as u32),
            ..TileView::default()
        })
    }

    /// A tile frame from the source: its planned position and size; kept as the newest tile.
    pub fn on_tile(&mut self, tile: HeightMap) {
        let h = tile.header;
        if h.has(flags::END_OF_SCAN) || h.width == 0 {
            return;
        }
        let t = self.tile(h.tile_index);
        t.row = Some(h.tile_row);
        t.col = Some(h.tile_col);
        t.stage_x_um = Some(h.origin_x_um);
        t.stage_y_um = Some(h.origin_y_um);
        t.width_um = Some(h.width as f64 * h.pitch_x_um);
        t.height_um = Some(h.height as f64 * h.pitch_y_um);
        self.pitch_um.get_or_insert([h.pitch_x_um, h.pitch_y_um]);
        self.newest_tile = Some(Arc::new(tile));
        self.tile_version += 1;
        self.boxes_version += 1;
        self.version += 1;
    }

    /// A registration from the matcher (streaming, or the end-of-scan solve's, `FINAL`).
    pub fn on_registration(&mut self, r: &TileRegistration, now: Instant) {
        if r.has(flags::END_OF_SCAN) {
            self.scan_ended = true;
            self.version += 1;
            return;
        }
        let is_final = r.has(flags::FINAL);
        let weak = self.weak_tiles.contains(&r.tile_index);
        let t = self.tile(r.tile_index);
        let first = t.x_um.is_none();
        if is_final || !t.final_solve {
            t.x_um = Some(r.x_um);
            t.y_um = Some(r.y_um);
            t.ncc = (r.links_tried > 0).then_some(r.quality);
            t.links_tried = r.links_tried;
            t.links_accepted = r.links_accepted;
            let by_stage = r.placed_by == placed_by::STAGE;
            t.placement = Some(match (by_stage, weak) {
                (true, _) => Placement::StageFallback,
                (false, true) => Placement::WeakLink,
                (false, false) => Placement::Registration,
            });
            t.final_solve = is_final;
        }
        if first && !is_final {
            self.first_registered.get_or_insert(now);
            self.last_registered = Some(now);
        }
        self.boxes_version += 1;
        self.version += 1;
    }

    /// A preview patch from the fusion (latest-wins: sequence gaps are patches missed).
    pub fn on_preview(&mut self, patch: HeightMap) {
        let h = patch.header;
        if h.has(flags::END_OF_SCAN) {
            return;
        }
        if let Some(prev) = self.last_preview_sequence {
            self.drops.preview_patches_missed += h.sequence.saturating_sub(prev + 1);
        }
        self.last_preview_sequence = Some(h.sequence);
        if h.t_sent_ns >= h.t_acquired_ns && h.t_acquired_ns > 0 {
            let ms = (h.t_sent_ns - h.t_acquired_ns) as f64 / 1e6;
            self.tile(h.tile_index).tile_to_panorama_ms = Some(ms);
        }
        self.canvas.apply(&h, &patch.heights);
        self.newest_patch = Some(Arc::new(patch));
        self.canvas_version += 1;
        self.version += 1;
    }

    /// Pairs the matcher decided while streaming (its pair log, [`surfstream_matcher::pair_log`]):
    /// shown at once, with their weak links; ignored once its report gave the final pairs.
    pub fn on_streaming_pairs(&mut self, pairs: &[MatcherPair]) {
        if pairs.is_empty() || self.pairs.iter().any(|p| p.final_solve) {
            return;
        }
        for p in pairs {
            if p.accepted && p.accepted_below_min_ncc {
                for i in [p.a, p.b] {
                    self.weak_tiles.insert(i);
                    if let Some(t) = self.tiles.get_mut(&i) {
                        if t.placement == Some(Placement::Registration) {
                            t.placement = Some(Placement::WeakLink);
                        }
                    }
                }
            }
            self.pairs.push(pair_view(p, false));
        }
        self.boxes_version += 1;
        self.version += 1;
    }

    /// The pairs with each streaming record's residual from the tiles' positions now.
    pub fn pair_views(&self) -> Vec<PairView> {
        let pos = |i: u32| {
            let t = self.tiles.get(&i)?;
            Some([t.x_um?, t.y_um?])
        };
        self.pairs
            .iter()
            .map(|p| {
                let mut v = p.clone();
                if !v.final_solve {
                    v.residual_px = (|| {
                        let (a, b, off, pitch) =
                            (pos(p.a)?, pos(p.b)?, p.offset_px?, self.pitch_um?);
                        let dx = (b[0] - a[0]) / pitch[0] - off[0];
                        let dy = (b[1] - a[1]) / pitch[1] - off[1];
                        Some(dx.hypot(dy))
                    })();
                    v.residual_of = v.residual_px.map(|_| "streaming_placement");
                }
                v
            })
            .collect()
    }

    /// A node's report (`nodes/<id>.json`), read as the typed record of its kind: a line of
    /// the running verdict; the matcher's also gives the pairs and the weak links.
    pub fn on_node_report(&mut self, node_id: &str, kind: &str, report: &serde_json::Value) {
        fn read<T: NodeRecord>(report: &serde_json::Value) -> Option<T> {
            <T as serde::Deserialize>::deserialize(report).ok()
        }
        let line = match kind {
            MatcherReport::NODE_KIND => {
                read::<MatcherReport>(report).map(|m| self.apply_matcher(&m))
            }
            FusionReport::NODE_KIND => read::<FusionReport>(report).map(|f| fusion_line(&f)),
            WaveletReport::NODE_KIND => read::<WaveletReport>(report).map(|w| wavelet_line(&w)),
            MeshReport::NODE_KIND => read::<MeshReport>(report).map(|m| mesh_line(&m)),
            _ => Some((format!("{kind} finished"), None)),
        };
        let (text, ok) = line.unwrap_or_else(|| {
            (
                format!("{kind} finished (its report does not read as a {kind} report)"),
                Some(false),
            )
        });
        self.stages.push(StageLine {
            stage: node_id.into(),
            text,
            ok,
        });
        self.version += 1;
    }

    fn apply_matcher(&mut self, m: &MatcherReport) -> (String, Option<bool>) {
        self.pairs = m.pairs.iter().map(|p| pair_view(p, true)).collect();
        let weak: Vec<(u32, u32)> = m
            .pairs
            .iter()
            .filter(|p| p.accepted_below_min_ncc && p.kept_by_global_solve != Some(false))
            .map(|p| (p.a, p.b))
            .collect();
        self.weak_tiles = weak.iter().flat_map(|&(a, b)| [a, b]).collect();
        for mt in &m.tiles {
            let by_stage = mt.placement.placed_by == "stage";
            let t = self.tile(mt.index);
            t.row = Some(mt.row);
            t.col = Some(mt.col);
            t.x_um = Some(mt.placement.x_um);
            t.y_um = Some(mt.placement.y_um);
            t.final_solve = true;
            t.placement = Some(if by_stage {
                Placement::StageFallback
            } else if weak.iter().any(|&(a, b)| a == mt.index || b == mt.index) {
                Placement::WeakLink
            } else {
                Placement::Registration
            });
        }
        self.boxes_version += 1;
        let fallback = m
            .tiles
            .iter()
            .filter(|t| t.placement.placed_by == "stage")
            .count();
        (
            format!(
                "matcher: {} tiles, {} by registration, {} by stage fallback; {} pairs, {} accepted, {} weak link(s)",
                m.tiles.len(),
                m.tiles.len() - fallback,
                fallback,
                m.pairs.len(),
                m.pairs.iter().filter(|p| p.accepted).count(),
                weak.len()
            ),
            Some(fallback == 0),
        )
    }

    /// run.json is written: the final verdict, the CLI's own.
    pub fn on_run_record(&mut self, run: &RunRecord, out: &Path) {
        if let Some(surfstream_core::record::DeviationRecord::Table(t)) = &run.deviation {
            self.stages.push(StageLine {
                stage: "table6".into(),
                text: format!(
                    "Table 6: every judged stage within {} % of the measured panorama: {}",
                    t.threshold_pct,
                    if t.pass { "yes" } else { "no" }
                ),
                ok: Some(t.pass),
            });
        }
        let v = crate::verdict::verdict(run, out, false);
        self.verdict = Some(FinalVerdict {
            verdict: if v.failures.is_empty() {
                "PASS"
            } else {
                "FAIL"
            },
            text: v.text,
            failures: v.failures,
            report: out.join("report.html").is_file(),
        });
        self.version += 1;
    }

    /// The run ended without a run record (an error, a stop).
    pub fn on_run_failed(&mut self, error: &str) {
        if self.verdict.is_none() {
            self.verdict = Some(FinalVerdict {
                verdict: "FAIL",
                text: format!("the run did not complete: {error}"),
                failures: vec![error.to_string()],
                report: false,
            });
        }
        self.version += 1;
    }

    pub fn tiles_registered(&self) -> usize {
        self.tiles.values().filter(|t| t.x_um.is_some()).count()
    }

    /// Fields per second between the first and the latest registration (None before two).
    pub fn fields_per_s(&self) -> Option<f64> {
        let (a, b) = (self.first_registered?, self.last_registered?);
        let n = self.tiles_registered();
        let dt = b.duration_since(a).as_secs_f64();
        (n >= 2 && dt > 0.0).then(|| (n - 1) as f64 / dt)
    }

    /// The time left at the pace so far, s.
    pub fn eta_s(&self) -> Option<f64> {
        let left = self.tiles_planned?.checked_sub(self.tiles_registered())?;
        if self.scan_ended {
            return Some(0.0);
        }
        self.fields_per_s().map(|f| left as f64 / f)
    }

    /// `/state.json`.
    pub fn snapshot(&self) -> StateJson<'_> {
        let lat: Vec<f64> = self
            .tiles
            .values()
            .filter_map(|t| t.tile_to_panorama_ms)
            .collect();
        let newest = self
            .tiles
            .values()
            .rev()
            .find_map(|t| t.tile_to_panorama_ms);
        let canvas = (!self.canvas.is_empty()).then_some(CanvasJson {
            x0_um: self.canvas.x0_um,
            y0_um: self.canvas.y0_um,
            width_um: self.canvas.cols as f64 * self.canvas.cell_x_um,
            height_um: self.canvas.rows as f64 * self.canvas.cell_y_um,
            cell_um: self.canvas.cell_x_um,
            version: self.canvas_version,
        });
        StateJson {
            graph: &self.graph,
            tiles_planned: self.tiles_planned,
            tiles_registered: self.tiles_registered(),
            tiles: self.tiles.values().collect(),
            pairs: self.pair_views(),
            stages: &self.stages,
            verdict: self.verdict.as_ref().map(|v| v.verdict),
            verdict_text: self.verdict.as_ref().map(|v| v.text.as_str()),
            failures: self.verdict.as_ref().map(|v| v.failures.as_slice()),
            report: self.verdict.as_ref().is_some_and(|v| v.report),
            progress: ProgressJson {
                elapsed_s: self.started.elapsed().as_secs_f64(),
                fields_per_s: self.fields_per_s(),
                eta_s: self.eta_s(),
                tile_to_panorama_ms: LatencyJson {
                    newest,
                    p50: percentile(&lat, 0.5),
                    max: lat.iter().copied().reduce(f64::max),
                    n: lat.len(),
                },
            },
            canvas,
            newest_tile: self.newest_tile.as_ref().map(|t| t.header.tile_index),
            scan_ended: self.scan_ended,
            run_ended: self.run_ended,
            stop_allowed: self.stop_allowed,
            drops: self.drops,
            viewers: self.viewers,
            version: self.version,
        }
    }

    /// `/state.json` as text (a typed record of string keys always serializes; `{}` if it
    /// ever did not, never a panic in the server).
    pub fn snapshot_text(&self) -> String {
        serde_json::to_string(&self.snapshot()).unwrap_or_else(|_| "{}".into())
    }
}

/// `/state.json`: what the page draws.
#[derive(Debug, Serialize)]
pub struct StateJson<'a> {
    pub graph: &'a str,
    pub tiles_planned: Option<usize>,
    pub tiles_registered: usize,
    pub tiles: Vec<&'a TileView>,
    pub pairs: Vec<PairView>,
    pub stages: &'a [StageLine],
    pub verdict: Option<&'static str>,
    pub verdict_text: Option<&'a str>,
    pub failures: Option<&'a [String]>,
    pub report: bool,
    pub progress: ProgressJson,
    pub canvas: Option<CanvasJson>,
    pub newest_tile: Option<u32>,
    pub scan_ended: bool,
    pub run_ended: bool,
    pub stop_allowed: bool,
    pub drops: Drops,
    pub viewers: Viewers,
    pub version: u64,
}

/// `/state.json` `progress`.
#[derive(Debug, Serialize)]
pub struct ProgressJson {
    pub elapsed_s: f64,
    pub fields_per_s: Option<f64>,
    pub eta_s: Option<f64>,
    pub tile_to_panorama_ms: LatencyJson,
}

/// Tile -> panorama latency over the tiles so far, ms.
#[derive(Debug, Serialize)]
pub struct LatencyJson {
    pub newest: Option<f64>,
    pub p50: Option<f64>,
    pub max: Option<f64>,
    pub n: usize,
}

/// `/state.json` `canvas`: where the preview sits, um, and its version.
#[derive(Debug, Serialize)]
pub struct CanvasJson {
    pub x0_um: f64,
    pub y0_um: f64,
    pub width_um: f64,
    pub height_um: f64,
    pub cell_um: f64,
    pub version: u64,
}

/// The page's view of a pair record: the streaming one (`final_solve` false) or the report's.
fn pair_view(p: &MatcherPair, final_solve: bool) -> PairView {
    let residual_px = p.residual_px.map(|[x, y]| x.hypot(y));
    PairView {
        a: p.a,
        b: p.b,
        direction: p.direction.clone(),
        ncc: p.ncc,
        accepted: p.accepted,
        weak_link: p.accepted_below_min_ncc,
        layout_inconsistent: p.layout_inconsistent.is_some(),
        kept_by_global_solve: p.kept_by_global_solve,
        nominal_offset_px: p.nominal_offset_px,
        offset_px: p.offset_px,
        residual_of: residual_px.map(|_| "global_solve"),
        residual_px,
        reason: p.reason.clone(),
        final_solve,
    }
}

/// The `q` quantile (nearest rank) of `v` (None when empty).
pub fn percentile(v: &[f64], q: f64) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    let k = ((q * s.len() as f64).ceil() as usize).clamp(1, s.len()) - 1;
    Some(s[k])
}

fn fusion_line(f: &FusionReport) -> (String, Option<bool>) {
    let ssim: Vec<f64> = f
        .fusion_pairs
        .iter()
        .map(|p| p.ssim_mean)
        .filter(|s| s.is_finite())
        .collect();
    let size = f
        .panorama
        .map(|p| format!("{} x {} px", p.height_px, p.width_px))
        .unwrap_or_else(|| "no panorama".into());
    let mean = (!ssim.is_empty()).then(|| ssim.iter().sum::<f64>() / ssim.len() as f64);
    (
        format!(
            "fusion ({}): panorama {size}; overlap SSIM mean {} over {} overlaps",
            f.method,
            mean.map_or("-".into(), |m| format!("{m:.3}")),
            ssim.len()
        ),
        None,
    )
}

fn wavelet_line(w: &WaveletReport) -> (String, Option<bool>) {
    match &w.final_pass {
        Some(f) => (
            format!(
                "wavelet: {}; panorama {} x {} px, pooled {} x {} px",
                f.separation.datum_title().trim_end_matches(" (um)"),
                f.panorama_px[0],
                f.panorama_px[1],
                f.pooled_px[0],
                f.pooled_px[1]
            ),
            None,
        ),
        None => ("wavelet: no final pass".into(), Some(false)),
    }
}

fn mesh_line(m: &MeshReport) -> (String, Option<bool>) {
    let met = m.tolerance.as_ref().map(|t| t.met);
    (
        format!(
            "mesher: {} triangles ({} on the surface) of the {}, {}{}",
            crate::verdict::count(m.triangles),
            crate::verdict::count(m.top_triangles),
            m.surface,
            m.file,
            match met {
                Some(true) => "; tolerance met",
                Some(false) => "; tolerance NOT met",
                None => "",
            }
        ),
        met,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn snap(s: &LiveState) -> serde_json::Value {
        serde_json::to_value(s.snapshot()).unwrap()
    }
    use surfstream_core::frame::FrameKind;

    fn patch(index: u32, seq: u64, x: f64, y: f64, w: u32, h: u32, value: f32) -> HeightMap {
        HeightMap {
            header: FrameHeader {
                kind: FrameKind::PanoramaPatch as u32,
                tile_index: index,
                sequence: seq,
                width: w,
                height: h,
                pitch_x_um: 2.0,
                pitch_y_um: 2.0,
                origin_x_um: x,
                origin_y_um: y,
                z_offset_um: 10.0,
                t_acquired_ns: 1_000_000,
                t_sent_ns: 5_000_000,
                ..FrameHeader::default()
            },
            heights: vec![value; (w * h) as usize],
        }
    }

    fn registration(index: u32, x: f64, by_stage: bool, flags: u32) -> TileRegistration {
        TileRegistration {
            tile_index: index,
            x_um: x,
            y_um: 0.0,
            placed_by: if by_stage {
                placed_by::STAGE
            } else {
                placed_by::REGISTRATION
            },
            links_tried: 1,
            links_accepted: u32::from(!by_stage),
            quality: 0.9,
            flags,
            ..TileRegistration::default()
        }
    }

    #[test]
    fn the_canvas_grows_in_every_direction_and_keeps_what_it_had() {
        let mut c = Canvas::default();
        c.apply(&patch(0, 0, 0.0, 0.0, 4, 3, 1.0).header, &[1.0; 12]);
        assert_eq!((c.rows, c.cols), (3, 4));
        // Left of and above the first patch: the canvas moves its origin.
        c.apply(&patch(1, 1, -4.0, -2.0, 2, 2, 2.0).header, &[2.0; 4]);
        assert_eq!((c.x0_um, c.y0_um), (-4.0, -2.0));
        assert_eq!((c.rows, c.cols), (4, 6));
        assert_eq!(c.heights[0], 2.0);
        // The first patch's cell (0, 0) is now cell (1, 2).
        assert_eq!(c.heights[c.cols + 2], 1.0);
        // Never covered: NaN.
        assert!(c.heights[3 * c.cols].is_nan());
    }

    #[test]
    fn a_canvas_beyond_its_largest_side_halves_its_resolution() {
        let mut c = Canvas::default();
        let w = CANVAS_MAX_SIDE as u32;
        c.apply(
            &patch(0, 0, 0.0, 0.0, w, 1, 3.0).header,
            &vec![3.0; w as usize],
        );
        assert_eq!(c.cols, CANVAS_MAX_SIDE);
        let x = w as f64 * 2.0;
        c.apply(&patch(1, 1, x, 0.0, 4, 1, 5.0).header, &[5.0; 4]);
        assert!(c.cols <= CANVAS_MAX_SIDE, "{}", c.cols);
        assert_eq!(c.cell_x_um, 4.0);
        assert_eq!(c.heights[0], 3.0);
        assert_eq!(c.heights[c.cols - 1], 5.0);
    }

    #[test]
    fn markers_and_bad_samplings_leave_the_canvas_alone() {
        let mut c = Canvas::default();
        let mut p = patch(0, 0, 0.0, 0.0, 2, 2, 1.0);
        p.header.pitch_x_um = 0.0;
        c.apply(&p.header, &p.heights);
        p.header.pitch_x_um = f64::NAN;
        c.apply(&p.header, &p.heights);
        assert!(c.is_empty());
        let p = patch(0, 0, f64::INFINITY, 0.0, 2, 2, 1.0);
        c.apply(&p.header, &p.heights);
        // Payload shorter than the header says.
        let p = patch(0, 0, 0.0, 0.0, 2, 2, 1.0);
        c.apply(&p.header, &p.heights[..3]);
        assert!(c.is_empty());
    }

    #[test]
    fn registrations_tiles_and_previews_make_the_state_json() {
        let mut s = LiveState::new("demo", vec![(0, 0), (0, 1), (1, 1)], false);
        let now = Instant::now();
        s.on_registration(&registration(0, 0.0, false, 0), now);
        s.on_registration(&registration(1, 90.0, true, 0), now);
        let mut tile = patch(1, 0, 100.0, 0.0, 50, 40, 0.0);
        tile.header.kind = FrameKind::Tile as u32;
        tile.header.tile_col = 1;
        s.on_tile(tile);
        s.on_preview(patch(0, 0, 0.0, 0.0, 4, 4, 1.0));
        // Sequence 3 after 0: two patches were replaced before the view read them.
        s.on_preview(patch(1, 3, 8.0, 0.0, 4, 4, 1.0));
        let j = snap(&s);
        assert_eq!(j["tiles_planned"], 3);
        assert_eq!(j["tiles_registered"], 2);
        assert_eq!(j["verdict"], serde_json::Value::Null);
        assert_eq!(j["drops"]["preview_patches_missed"], 2);
        let tiles = j["tiles"].as_array().unwrap();
        assert_eq!(tiles.len(), 2);
        assert_eq!(tiles[0]["placement"], "registration");
        assert_eq!(tiles[1]["placement"], "stage_fallback");
        assert_eq!(tiles[1]["stage_x_um"], 100.0);
        assert_eq!(tiles[1]["x_um"], 90.0);
        assert_eq!(tiles[1]["width_um"], 100.0);
        assert_eq!(
            (tiles[1]["row"].clone(), tiles[1]["col"].clone()),
            (0.into(), 1.into())
        );
        assert_eq!(tiles[0]["tile_to_panorama_ms"], 4.0);

        // The end-of-scan solve's placement replaces the streaming one, not the reverse.
        s.on_registration(&registration(1, 91.0, false, flags::FINAL), now);
        s.on_registration(&registration(1, 50.0, true, 0), now);
        let j = snap(&s);
        assert_eq!(j["tiles"][1]["x_um"], 91.0);
        assert_eq!(j["tiles"][1]["placement"], "registration");
        assert_eq!(j["tiles"][1]["final_solve"], true);

        s.on_run_failed("interrupted");
        assert_eq!(snap(&s)["verdict"], "FAIL");
    }

    #[test]
    fn a_matcher_report_gives_the_pairs_and_marks_weak_links() {
        let mut s = LiveState::new("demo", vec![(0, 0), (0, 1)], false);
        let report = serde_json::json!({
            "method": "phase",
            "tiles": [
                {"index": 0, "row": 0, "col": 0, "x_um": 0.0, "y_um": 0.0, "placed_by": "registration",
                 "links_accepted": 0, "links_tried": 0, "quality": 0.0, "piston_um": 0.0,
                 "tilt_x_um_per_px": 0.0, "tilt_y_um_per_px": 0.0,
                 "streaming": {"x_um": 0.0, "y_um": 0.0, "placed_by": "registration", "links_tried": 0,
                               "piston_um": 0.0, "tilt_x_um_per_px": 0.0, "tilt_y_um_per_px": 0.0}},
                {"index": 1, "row": 0, "col": 1, "x_um": 92.0, "y_um": 1.0, "placed_by": "registration",
                 "links_accepted": 1, "links_tried": 1, "quality": 0.4, "piston_um": 0.0,
                 "tilt_x_um_per_px": 0.0, "tilt_y_um_per_px": 0.0,
                 "streaming": {"x_um": 92.0, "y_um": 1.0, "placed_by": "registration", "links_tried": 1,
                               "piston_um": 0.0, "tilt_x_um_per_px": 0.0, "tilt_y_um_per_px": 0.0}}
            ],
            "pairs": [
                {"a": 0, "b": 1, "direction": "horizontal", "nominal_offset_px": [90.0, 0.0],
                 "offset_px": [92.0, 1.0], "ncc": 0.4, "peak_ratio": 3.0, "accepted": true,
                 "reason": null, "accepted_below_min_ncc": true, "residual_px": [0.3, 0.4]}
            ],
            "global": null
        });
        s.on_node_report("matcher", "matcher", &report);
        let j = snap(&s);
        assert_eq!(j["tiles"][0]["placement"], "weak_link");
        assert_eq!(j["tiles"][1]["placement"], "weak_link");
        assert_eq!(j["pairs"][0]["ncc"], 0.4);
        assert!((j["pairs"][0]["residual_px"].as_f64().unwrap() - 0.5).abs() < 1e-12);
        let line = j["stages"][0]["text"].as_str().unwrap();
        assert!(
            line.contains("2 by registration, 0 by stage fallback"),
            "{line}"
        );
        assert!(line.contains("1 weak link"), "{line}");
        // A report that does not read as its kind's is said, not hidden.
        s.on_node_report("fusion", "fusion", &serde_json::json!({"x": 1}));
        let j = snap(&s);
        assert_eq!(j["stages"][1]["ok"], false);
    }

    fn streaming_pair(a: u32, b: u32, offset_px: [f64; 2], weak: bool) -> MatcherPair {
        serde_json::from_value(serde_json::json!({
            "a": a, "b": b, "direction": "horizontal", "nominal_offset_px": [45.0, 0.0],
            "offset_px": offset_px, "ncc": 0.3, "peak_ratio": 4.0, "accepted": true,
            "reason": null, "accepted_below_min_ncc": weak
        }))
        .unwrap()
    }

    #[test]
    fn streaming_pairs_show_weak_links_and_residuals_before_the_report() {
        let mut s = LiveState::new("demo", vec![(0, 0), (0, 1), (0, 2)], false);
        let mut tile = patch(0, 0, 0.0, 0.0, 50, 40, 0.0);
        tile.header.kind = FrameKind::Tile as u32;
        s.on_tile(tile); // pitch 2 um
        let now = Instant::now();
        s.on_registration(&registration(0, 0.0, false, 0), now);
        // The pair arrives before tile 1's registration; a pair with tile 2, after it.
        s.on_streaming_pairs(&[streaming_pair(0, 1, [45.5, 0.0], true)]);
        let j = snap(&s);
        assert_eq!(j["tiles"][0]["placement"], "weak_link", "at once");
        assert_eq!(j["pairs"][0]["weak_link"], true);
        assert_eq!(j["pairs"][0]["final_solve"], false);
        assert_eq!(j["pairs"][0]["residual_px"], serde_json::Value::Null);
        s.on_registration(&registration(1, 92.0, false, 0), now);
        let j = snap(&s);
        assert_eq!(j["tiles"][1]["placement"], "weak_link");
        // (92 - 0) / 2 - 45.5 = 0.5 px, from the streaming placement.
        assert_eq!(j["pairs"][0]["residual_px"], 0.5);
        assert_eq!(j["pairs"][0]["residual_of"], "streaming_placement");
        s.on_registration(&registration(2, 180.0, true, 0), now);
        s.on_streaming_pairs(&[streaming_pair(1, 2, [44.0, 0.0], false)]);
        let j = snap(&s);
        assert_eq!(j["tiles"][2]["placement"], "stage_fallback");
        assert_eq!(j["pairs"].as_array().unwrap().len(), 2);
        assert_eq!(j["pairs"][1]["residual_px"], 0.0);
        // The report's pairs replace the streaming ones; later log lines change nothing.
        let mut final_pair = streaming_pair(0, 1, [45.5, 0.0], true);
        final_pair.kept_by_global_solve = Some(false);
        final_pair.residual_px = Some([0.3, 0.4]);
        let report = MatcherReport {
            method: "phase".into(),
            tiles: Vec::new(),
            pairs: vec![final_pair],
            global: None,
        };
        s.apply_matcher(&report);
        s.on_streaming_pairs(&[streaming_pair(1, 2, [44.0, 0.0], true)]);
        let j = snap(&s);
        assert_eq!(j["pairs"].as_array().unwrap().len(), 1);
        assert_eq!(j["pairs"][0]["final_solve"], true);
        assert_eq!(j["pairs"][0]["residual_of"], "global_solve");
        assert!((j["pairs"][0]["residual_px"].as_f64().unwrap() - 0.5).abs() < 1e-12);
        // The solve dropped the weak link: its tiles are no longer weak.
        s.on_registration(&registration(1, 91.0, false, flags::FINAL), now);
        assert_eq!(snap(&s)["tiles"][1]["placement"], "registration");
    }

    #[test]
    fn pace_and_eta_come_from_the_registrations() {
        let mut s = LiveState::new("demo", vec![(0, 0); 5], false);
        let t0 = Instant::now();
        s.on_registration(&registration(0, 0.0, false, 0), t0);
        assert_eq!(s.fields_per_s(), None);
        s.on_registration(
            &registration(1, 0.0, false, 0),
            t0 + std::time::Duration::from_secs(2),
        );
        assert_eq!(s.fields_per_s(), Some(0.5));
        assert_eq!(s.eta_s(), Some(6.0));
        assert_eq!(percentile(&[3.0, 1.0, 2.0], 0.5), Some(2.0));
        assert_eq!(percentile(&[], 0.5), None);
    }
}
