//! The wavelet node's state and decisions, without IPC: what a panorama patch changes, what a
//! live pass publishes, what the final pass computes and writes.
//!
//! Live: [`LiveSeparation::apply_patch`] copies each arrived panorama patch into a mirror of
//! the panorama (a [`GrowingCanvas`], cheap), and [`LiveSeparation::live_pass`] separates once
//! over the region changed since the last pass plus a margin, at the level that window
//! supports, giving datum / roughness / pooled patches flagged PREVIEW. The work is bounded by
//! the window, not the panorama. A level-8 sym5 datum depends on ~2300 px around each pixel,
//! so live patches are approximations by construction.
//! Final: [`final_separation`] is the exact pass over the whole final panorama, identical to
//! the batch computation ([`crate::analyse`]), flagged FINAL and optionally written to files.

use anyhow::{anyhow, bail, Result};
use serde_json::json;
use surfstream_core::canvas::{GridRect, GrowingCanvas};
use surfstream_core::frame::{flags, FrameHeader, FrameKind, HeightMap};
use surfstream_core::raster::{RasterView, Shape};
use surfstream_io::output::{NpyHeights, OutputWriter, SurfaceOutput};

use surfstream_core::filter::Grid;

use crate::method::{equivalent_cutoff_um, filter_separation, level_lowered_warning};
use crate::{
    analyse, default_level, pool, pooling_bias, separate, BaseChoice, LevelChoice, Mode, PoolOp,
    SeparationMethod, Wavelet, DEFAULT_LEVEL,
};

/// Largest mirror the live pass keeps, px (as the fusion's canvas limit): a patch whose
/// position is absurd (a wrong unit) is refused instead of exhausting memory.
const MAX_MIRROR_PX: usize = 1 << 31;

/// How the panorama is separated and pooled.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SeparationSettings {
    /// Wavelet (base, level, mode below) or an ISO 16610 L-filter.
    pub method: SeparationMethod,
    /// S-filter cutoff, µm (filter methods only).
    pub lambda_s_um: Option<f64>,
    pub base: BaseChoice,
    pub level: LevelChoice,
    pub mode: Mode,
    /// Pooling block, px (>= 1).
    pub pool_block: usize,
    pub pool_op: PoolOp,
}

impl SeparationSettings {
    /// The base of live passes: the named one, sym5 when the final base is chosen by RMSE
    /// (ranking every base per live window would cost 23 separations).
    pub fn live_wavelet(&self) -> Result<Wavelet> {
        match self.base {
            BaseChoice::Named(w) => Ok(w),
            BaseChoice::MinRmse => Wavelet::by_name("sym5").ok_or_else(|| anyhow!("sym5 missing")),
        }
    }

    /// The level asked for, when it is a fixed one (live passes use it; the default otherwise).
    pub fn fixed_level(&self) -> Option<usize> {
        match self.level {
            LevelChoice::Fixed(l) => Some(l),
            _ => None,
        }
    }
}

/// The panorama as far as patches told it, on the grid of the first patch.
#[derive(Debug, Clone)]
struct PanoramaMirror {
    anchor_um: [f64; 2],
    pitch_um: [f64; 2],
    z_offset_um: f64,
    /// What patches have covered so far.
    extent: Option<GridRect>,
    heights: GrowingCanvas<f32>,
}

impl PanoramaMirror {
    fn new(h: &FrameHeader) -> Self {
        Self {
            anchor_um: [h.origin_x_um, h.origin_y_um],
            pitch_um: [h.pitch_x_um, h.pitch_y_um],
            z_offset_um: h.z_offset_um,
            extent: None,
            heights: GrowingCanvas::new(f32::NAN),
        }
    }

    /// Copies a patch in, growing the mirror as needed; returns the patch's grid rectangle.
    fn apply(&mut self, h: &FrameHeader, heights: &[f32]) -> Result<GridRect> {
        if (h.pitch_x_um - self.pitch_um[0]).abs() > 1e-9 * self.pitch_um[0]
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
            grid(h.origin_x_um, self.anchor_um[0], self.pitch_um[0]),
            grid(h.origin_y_um, self.anchor_um[1], self.pitch_um[1]),
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
        self.heights
            .write(r, heights)
            .map_err(|e| anyhow!("wavelet: panorama patch {}: {e}", h.sequence))?;
        self.extent = Some(extent);
        Ok(r)
    }

    /// A frame header for grid rectangle `r` of this panorama, pooled by `scale`.
    fn header_for(&self, r: GridRect, kind: FrameKind, scale: usize) -> FrameHeader {
        FrameHeader {
            kind: kind as u32,
            width: r.cols().div_ceil(scale) as u32,
            height: r.rows().div_ceil(scale) as u32,
            pitch_x_um: self.pitch_um[0] * scale as f64,
            pitch_y_um: self.pitch_um[1] * scale as f64,
            origin_x_um: self.anchor_um[0] + r.x0 as f64 * self.pitch_um[0],
            origin_y_um: self.anchor_um[1] + r.y0 as f64 * self.pitch_um[1],
            z_offset_um: self.z_offset_um,
            ..Default::default()
        }
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
#[derive(Debug, Clone)]
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
            dirty: None,
            trace: None,
        })
    }

    /// Folds a panorama patch into the mirror and marks its region changed.
    pub fn apply_patch(&mut self, header: &FrameHeader, heights: &[f32]) -> Result<()> {
        let m = self
            .mirror
            .get_or_insert_with(|| PanoramaMirror::new(header));
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
        let (Some(m), Some(dirty), Some((tile, t_acq))) =
            (&self.mirror, self.dirty.take(), self.trace.take())
        else {
            return Ok(None);
        };
        // A filter's datum depends on lambda_c around each point: take at least that much.
        let margin = match self.method.cutoff_um() {
            Some(lc) => {
                let reach = (lc / m.pitch_um[0].min(m.pitch_um[1])).ceil();
                self.margin_px.max(reach.min(1e6) as usize)
            }
            None => self.margin_px,
        };
        let Some(window) = m
            .extent
            .and_then(|e| dirty.expand(margin as i64).intersect(&e))
        else {
            return Ok(None);
        };
        let heights = m.heights.read(window);
        if heights.iter().all(|z| z.is_nan()) {
            return Ok(None);
        }
        let (rows, cols) = (window.rows(), window.cols());
        let sep = if self.method == SeparationMethod::Wavelet {
            let Ok(level) = default_level(rows, cols, &self.wavelet, self.level) else {
                return Ok(None);
            };
            let s = separate(&heights, rows, cols, &self.wavelet, self.mode, Some(level))?;
            (s.datum, s.roughness)
        } else {
            let grid = Grid {
                rows,
                cols,
                pitch_x_um: m.pitch_um[0],
                pitch_y_um: m.pitch_um[1],
            };
            let s = filter_separation(&heights, grid, self.method, self.lambda_s_um)
                .map_err(|e| anyhow!("wavelet: live {} separation: {e}", self.method.name()))?;
            (s.datum, s.roughness)
        };
        let crop = |v: &[f32]| -> Vec<f32> {
            let (dx, dy) = (
                (dirty.x0 - window.x0) as usize,
                (dirty.y0 - window.y0) as usize,
            );
            let w = dirty.cols();
            let mut c = Vec::with_capacity(w * dirty.rows());
            for row in 0..dirty.rows() {
                let at = (row + dy) * cols + dx;
                c.extend_from_slice(&v[at..at + w]);
            }
            c
        };
        let stamp = |mut h: FrameHeader| {
            h.flags |= flags::PREVIEW;
            h.tile_index = tile;
            h.t_acquired_ns = t_acq;
            h
        };
        let datum = HeightMap {
            header: stamp(m.header_for(dirty, FrameKind::Datum, 1)),
            heights: crop(&sep.0),
        };
        let roughness = HeightMap {
            header: stamp(m.header_for(dirty, FrameKind::Roughness, 1)),
            heights: crop(&sep.1),
        };
        // Pooled blocks stay aligned to the mirror's grid so live patches tile seamlessly.
        let pooled = match m
            .extent
            .and_then(|e| dirty.align_out(self.pool_block).intersect(&e))
        {
            Some(a) => {
                let p = pool(
                    &m.heights.read(a),
                    a.rows(),
                    a.cols(),
                    self.pool_block,
                    self.pool_op,
                )?;
                let mut h = stamp(m.header_for(a, FrameKind::Pooled, self.pool_block));
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

/// What the final pass publishes (flag FINAL) and reports.
#[derive(Debug, Clone)]
pub struct FinalSeparation {
    pub datum: HeightMap,
    pub roughness: HeightMap,
    pub pooled: HeightMap,
    /// The choices and the evidence ([`crate::Analysis::summary`]), the level asked for, the
    /// panorama's size and the files written.
    pub summary: serde_json::Value,
}

/// How run.json and `separate.json` define the wavelet's equivalent cutoff.
pub const CUTOFF_DEFINITION: &str = "wavelength at which the level's approximation passes 50 % amplitude: T(w) = prod_{k<level} |H(2^k w)|^2 / 2, H the decomposition low-pass, aliasing ignored (nodes/wavelet/src/method.rs)";

/// The exact separation of the final panorama; with a writer, also `datum`, `roughness` and
/// `pooled` as .npy + .png (datum and pooled absolute f64: they carry the panorama's offset;
/// roughness relative f32: it has none by nature).
pub fn final_separation(
    settings: &SeparationSettings,
    panorama: &HeightMap,
    files: Option<&mut OutputWriter>,
) -> Result<FinalSeparation> {
    let h = panorama.header;
    let (rows, cols) = (h.height as usize, h.width as usize);
    let (datum, roughness, pooled, mut summary, title) = match settings.method {
        SeparationMethod::Wavelet => {
            let analysis = analyse(
                &panorama.heights,
                rows,
                cols,
                settings.base,
                settings.level,
                settings.mode,
                settings.pool_block,
                settings.pool_op,
            )?;
            let mut summary = analysis.summary();
            let level = analysis.separation.level;
            let w = analysis.wavelet;
            if let Some(o) = summary.as_object_mut() {
                o.insert("method".into(), json!("wavelet"));
                o.insert(
                    "equivalent_cutoff_um".into(),
                    json!(equivalent_cutoff_um(&w, level, h.pitch_x_um)),
                );
                if h.pitch_y_um != h.pitch_x_um {
                    o.insert(
                        "equivalent_cutoff_y_um".into(),
                        json!(equivalent_cutoff_um(&w, level, h.pitch_y_um)),
                    );
                }
                o.insert(
                    "equivalent_cutoff_definition".into(),
                    json!(CUTOFF_DEFINITION),
                );
                let requested = match settings.level {
                    LevelChoice::Fixed(l) => Some(l),
                    LevelChoice::Default => Some(DEFAULT_LEVEL),
                    LevelChoice::MinEnergy => None,
                };
                if let Some(warning) =
                    requested.and_then(|r| level_lowered_warning(&w, r, level, h.pitch_x_um))
                {
                    eprintln!("wavelet: {warning}");
                    o.insert("warning".into(), json!(warning));
                }
            }
            let title = format!("datum, {} level {level} (um)", w.name());
            let sep = analysis.separation;
            (sep.datum, sep.roughness, analysis.pooled, summary, title)
        }
        method => {
            let grid = Grid {
                rows,
                cols,
                pitch_x_um: h.pitch_x_um,
                pitch_y_um: h.pitch_y_um,
            };
            let s = filter_separation(&panorama.heights, grid, method, settings.lambda_s_um)
                .map_err(|e| anyhow!("wavelet: {} separation: {e}", method.name()))?;
            let pooled = pool(
                &panorama.heights,
                rows,
                cols,
                settings.pool_block,
                settings.pool_op,
            )?;
            let cutoff = method.cutoff_um().unwrap_or(f64::NAN);
            let summary = json!({
                "method": method.name(),
                "cutoff_um": cutoff,
                "lambda_s_um": settings.lambda_s_um,
                "plane_removed_um": s.plane_um,
                "robust_iterations": s.robust_iterations.map(|r| r.0),
                "robust_converged": s.robust_iterations.map(|r| r.1),
                "pool": settings.pool_block,
                "pool_op": settings.pool_op.name(),
                "pooled_px": [pooled.cols, pooled.rows],
                "pooling_bias": pooling_bias(&panorama.heights, &pooled.heights),
            });
            let title = format!("datum, {} lambda_c {cutoff} um (um)", method.name());
            (s.datum, s.roughness, pooled, summary, title)
        }
    };
    let shape = Shape::new(rows, cols);
    let pooled_shape = Shape::new(pooled.rows, pooled.cols);
    let mut written = Vec::new();
    if let Some(w) = files {
        let block = settings.pool_block;
        for (name, values, shape, npy, title) in [
            (
                "datum",
                &datum,
                shape,
                NpyHeights::AbsoluteF64,
                title.clone(),
            ),
            (
                "roughness",
                &roughness,
                shape,
                NpyHeights::RelativeF32,
                "roughness (um)".to_string(),
            ),
            (
                "pooled",
                &pooled.heights,
                pooled_shape,
                NpyHeights::AbsoluteF64,
                format!("pooled {block}x{block} (um)"),
            ),
        ] {
            w.write_surface(&SurfaceOutput {
                name,
                heights: RasterView::new(values, shape)?,
                z_offset_um: h.z_offset_um,
                npy,
                title: &title,
                x3p_pitch_um: None,
            })?;
        }
        written = w.files().to_vec();
    }
    if let Some(o) = summary.as_object_mut() {
        o.insert("level_requested".into(), json!(settings.fixed_level()));
        o.insert("panorama_px".into(), json!([cols, rows]));
        o.insert("files".into(), json!(written));
    }
    let header = |kind: FrameKind| FrameHeader {
        kind: kind as u32,
        flags: flags::FINAL,
        ..h
    };
    let mut pooled_header = header(FrameKind::Pooled);
    pooled_header.width = pooled.cols as u32;
    pooled_header.height = pooled.rows as u32;
    pooled_header.pitch_x_um *= settings.pool_block as f64;
    pooled_header.pitch_y_um *= settings.pool_block as f64;
    Ok(FinalSeparation {
        datum: HeightMap {
            header: header(FrameKind::Datum),
            heights: datum,
        },
        roughness: HeightMap {
            header: header(FrameKind::Roughness),
            heights: roughness,
        },
        pooled: HeightMap {
            header: pooled_header,
            heights: pooled.heights,
        },
        summary,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

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

    #[test]
    fn mirror_grows_in_every_direction_and_keeps_content() {
        let first = patch(0, 0, 4, 3, |_, _| 1.0);
        let mut m = PanoramaMirror::new(&first.header);
        m.apply(&first.header, &first.heights).unwrap();
        for (x0, y0, v) in [(-5, 0, 2.0), (0, -4, 3.0), (6, 5, 4.0), (2, 1, 5.0)] {
            let p = patch(x0, y0, 4, 3, |_, _| v);
            let r = m.apply(&p.header, &p.heights).unwrap();
            assert_eq!(m.heights.read(r), p.heights);
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
        assert!(m.heights.rect().contains(&extent));
        assert_eq!(
            m.heights.read(GridRect {
                x0: 0,
                y0: 0,
                x1: 2,
                y1: 1
            }),
            vec![1.0, 1.0]
        );
        assert!(m.heights.read(GridRect {
            x0: 9,
            y0: -4,
            x1: 10,
            y1: -3
        })[0]
            .is_nan());
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
    }

    #[test]
    fn final_separation_by_a_filter_and_the_wavelet_cutoff_are_reported() {
        let mut pano = patch(0, 0, 48, 40, surface);
        pano.header.kind = FrameKind::Panorama as u32;
        let mut s = settings();
        s.method = SeparationMethod::Gaussian { cutoff_um: 8.0 };
        let f = final_separation(&s, &pano, None).unwrap();
        assert_eq!(f.summary["method"], "gaussian");
        assert_eq!(f.summary["cutoff_um"], 8.0);
        for ((d, r), h) in f
            .datum
            .heights
            .iter()
            .zip(&f.roughness.heights)
            .zip(&pano.heights)
        {
            assert!((d + r - h).abs() < 1e-5);
        }
        // The wavelet: db2 level 2 at 0.5 um is 8 pitches (4 um), reported with a warning
        // when the level asked for does not fit.
        let w = final_separation(&settings(), &pano, None).unwrap();
        let cutoff = w.summary["equivalent_cutoff_um"].as_f64().unwrap();
        assert!((cutoff - 4.0).abs() < 0.2, "{cutoff}");
        assert!(w.summary["warning"].is_null());
        s = settings();
        s.level = LevelChoice::Fixed(9);
        let lowered = final_separation(&s, &pano, None).unwrap();
        let text = lowered.summary["warning"].as_str().unwrap().to_string();
        assert!(text.contains("level 9 lowered to"), "{text}");
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
        assert_eq!(f.datum.heights, batch.separation.datum);
        assert_eq!(f.pooled.heights, batch.pooled.heights);
        assert!(f.datum.header.has(flags::FINAL));
        assert_eq!(
            (f.pooled.header.width, f.pooled.header.pitch_x_um),
            (12, 2.0)
        );
        assert_eq!(f.summary["files"].as_array().unwrap().len(), 6);
        assert_eq!(f.summary["level_requested"], 2);
        let datum = surfstream_io::npy::read_npy_f64(dir.path().join("datum.npy")).unwrap();
        assert_eq!(datum.data[0], f64::from(f.datum.heights[0]) + 100.0);
    }
}
