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

use crate::{
    analyse, default_level, pool, separate, BaseChoice, LevelChoice, Mode, PoolOp, Wavelet,
};

/// Largest mirror the live pass keeps, px (as the fusion's canvas limit): a patch whose
/// position is absurd (a wrong unit) is refused instead of exhausting memory.
const MAX_MIRROR_PX: usize = 1 << 31;

/// How the panorama is separated and pooled.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SeparationSettings {
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
        let Some(window) = m
            .extent
            .and_then(|e| dirty.expand(self.margin_px as i64).intersect(&e))
        else {
            return Ok(None);
        };
        let heights = m.heights.read(window);
        if heights.iter().all(|z| z.is_nan()) {
            return Ok(None);
        }
        let (rows, cols) = (window.rows(), window.cols());
        let Ok(level) = default_level(rows, cols, &self.wavelet, self.level) else {
            return Ok(None);
        };
        let sep = separate(&heights, rows, cols, &self.wavelet, self.mode, Some(level))?;
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
            heights: crop(&sep.datum),
        };
        let roughness = HeightMap {
            header: stamp(m.header_for(dirty, FrameKind::Roughness, 1)),
            heights: crop(&sep.roughness),
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
    let (sep, pooled) = (analysis.separation, analysis.pooled);
    let shape = Shape::new(rows, cols);
    let pooled_shape = Shape::new(pooled.rows, pooled.cols);
    let mut written = Vec::new();
    if let Some(w) = files {
        let block = settings.pool_block;
        for (name, values, shape, npy, title) in [
            (
                "datum",
                &sep.datum,
                shape,
                NpyHeights::AbsoluteF64,
                format!(
                    "datum, {} level {} (um)",
                    analysis.wavelet.name(),
                    sep.level
                ),
            ),
            (
                "roughness",
                &sep.roughness,
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
            heights: sep.datum,
        },
        roughness: HeightMap {
            header: header(FrameKind::Roughness),
            heights: sep.roughness,
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
