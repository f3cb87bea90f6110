//! The mesher's job in a graph, without IPC: [`MeshJob`] keeps the final frame of every input
//! until each has ended its scan, then meshes the chosen surface ([`SurfaceChoice`]) once
//! through the mesher's one entry point ([`crate::map::mesh_surface`]): the STL, the mesh
//! re-sampled on the grid and the record for run.json. [`MeshJob::mesh`] is the same in
//! memory, the tests' oracle ([`MeshedSurface`]).
//!
//! Live frames are counted and skipped: a mesh is made once, from the exact final surface.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use surfstream_core::deviation::tile_regions;
use surfstream_core::frame::{flags, from_frame_heights, FrameHeader, FrameView, HeightMap};
use surfstream_core::raster::{Raster, RasterView, Shape};
use surfstream_core::record::{FormPlane, MeshReport, PanoramaTiles, RecordError, PANORAMA_TILES};

use crate::config::{MeshSettings, StlFormat, SurfaceChoice};
use crate::map::{mesh_surface, prepare_surface, tolerance_for, MeshInput, MeshOutputs};
use crate::outliers::OutlierReport;
use crate::report::{adaptive_method, mesh_report, MethodSummary, ReportContext};
use crate::target::block_values_on_grid;
use crate::tolerance::{mesh_to_tolerance, Window};
use crate::{
    check_closed, grid_sheet_for, grid_solid, mesh_height_field, stl, MeshCheck, MeshCounts,
    ScanPlacement, SolidMesh,
};

/// The label in the STL header of a graph's mesh (before the unit and offset).
pub const STL_LABEL: &str = "surfstream surface";

/// The surface, meshed in memory ([`MeshJob::mesh`], the tests' oracle).
pub struct MeshedSurface {
    pub solid: SolidMesh,
    pub check: MeshCheck,
    /// The adaptive mesh's or the engine grid sheet's own statistics (`None` for the grid
    /// solid).
    pub adaptive: Option<MethodSummary>,
    /// The mesh re-sampled on the meshed grid, absolute heights (um): for the grid mesh the
    /// samples themselves, for the adaptive one its interpolation (NaN where not covered). It
    /// is the "mesh" stage of the model-vs-measurement table (Table 6) in run.json.
    pub resampled_um: Raster<f64>,
    /// The header of the meshed surface's frame (grid, pitch, latency trace).
    pub header: FrameHeader,
    /// Where the grid was placed (from the header).
    pub at: ScanPlacement,
    /// The spikes found before meshing.
    pub outliers: OutlierReport,
    /// The plane removed before meshing (with `level`).
    pub form_plane: Option<FormPlane>,
}

impl MeshedSurface {
    /// Writes the solid as STL in `format`.
    pub fn write_stl(&self, w: &mut dyn std::io::Write, format: StlFormat) -> crate::Result<()> {
        let label = stl::stl_header(&self.solid, STL_LABEL);
        match format {
            StlFormat::Ascii => crate::write_stl_ascii(w, &self.solid, &label),
            StlFormat::Binary => crate::write_stl_binary(w, &self.solid, &label),
        }
    }

    /// The record for run.json (the caller adds files, wiring and times).
    pub fn summary(&self, settings: &MeshSettings) -> Result<MeshReport, RecordError> {
        let h = &self.header;
        let shape = Shape::new(h.height as usize, h.width as usize);
        let context = ReportContext {
            settings,
            shape,
            at: &self.at,
            t_acquired_ns: h.t_acquired_ns,
            surface: settings.surface.name(),
            outliers: &self.outliers,
            form_plane: self.form_plane,
        };
        mesh_report(
            &MeshCounts::of(&self.solid),
            &self.check,
            self.adaptive.as_ref(),
            &context,
        )
    }
}

/// What [`MeshJob::mesh_to_files`] wrote.
pub struct MeshFiles {
    /// The record for run.json (as [`MeshedSurface::summary`], with the time meshing took).
    pub summary: MeshReport,
    pub check: MeshCheck,
    /// True when the mesh went through the streaming mesher ([`crate::stream`]).
    pub streamed: bool,
}

/// Collects the final surface from the inputs and meshes it once every input has ended.
pub struct MeshJob {
    settings: MeshSettings,
    /// The final frame per input port, and the ports whose scan has ended.
    finals: BTreeMap<String, HeightMap>,
    ended: BTreeSet<String>,
    live_frames: u64,
    /// The measured roughness is wired: the tolerance judges the roughness the mesh carries.
    roughness_reference: bool,
    /// The fusion's tile placements ([`PANORAMA_TILES`]), read when the surface is meshed.
    tiles_file: Option<PathBuf>,
}

impl MeshJob {
    pub fn new(settings: MeshSettings) -> Self {
        Self {
            settings,
            finals: BTreeMap::new(),
            ended: BTreeSet::new(),
            live_frames: 0,
            roughness_reference: false,
            tiles_file: None,
        }
    }

    /// Judges Table 6's tile regions in the tolerance search too, from the fusion's tile
    /// placements at `path` ([`PANORAMA_TILES`] in the out dir; written before the final
    /// panorama is sent): when the file exists and the surface lies on the panorama's grid
    /// ([`tile_footprints`]). Without it, the windows alone.
    pub fn with_tile_footprints(mut self, path: PathBuf) -> Self {
        self.tiles_file = Some(path);
        self
    }

    /// The tile footprints on the surface's grid (empty: no file, no tolerance, another grid).
    fn footprints(&self, shape: Shape, at: &ScanPlacement) -> Result<Vec<Window>> {
        let path = match &self.tiles_file {
            Some(p) if self.settings.tolerance.is_some() && p.exists() => p,
            _ => return Ok(Vec::new()),
        };
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("mesher: {}: cannot read", path.display()))?;
        let tiles: PanoramaTiles = serde_json::from_str(&text).map_err(|e| {
            anyhow!(
                "mesher: {}: {e}: expected the fusion's tile placements ({PANORAMA_TILES})",
                path.display()
            )
        })?;
        Ok(tile_footprints(&tiles, shape, at))
    }

    /// Waits for the measured roughness on the input `roughness` too, and judges the
    /// roughness the mesh carries against it (surface = "panorama", a tolerance).
    pub fn with_roughness_reference(mut self) -> Self {
        self.roughness_reference = self.settings.surface == SurfaceChoice::Panorama;
        self
    }

    /// The input ports whose end of scan the job waits for.
    fn awaited_ports(&self) -> impl Iterator<Item = &'static str> + '_ {
        let reference: &[&str] = if self.roughness_reference {
            &["roughness"]
        } else {
            &[]
        };
        self.settings
            .surface
            .ports()
            .iter()
            .chain(reference)
            .copied()
    }

    pub fn settings(&self) -> &MeshSettings {
        &self.settings
    }

    /// Live (not final) frames seen and skipped.
    pub fn live_frames_skipped(&self) -> u64 {
        self.live_frames
    }

    /// Takes one frame from input `port`; true when it was the last end of scan the job waits
    /// for, so the surface is ready to mesh ([`MeshJob::mesh`]).
    pub fn accept(&mut self, port: &str, frame: FrameView<'_>) -> bool {
        if frame.header.has(flags::END_OF_SCAN) {
            self.ended.insert(port.to_owned());
            return self.awaited_ports().all(|p| self.ended.contains(p));
        }
        if frame.header.has(flags::FINAL) {
            self.finals.insert(port.to_owned(), frame.to_owned());
        } else {
            self.live_frames += 1;
        }
        false
    }

    /// The surface to mesh from the final frames: one input as is, or datum + roughness summed
    /// (the roughness is relative to the same z offset as the datum's frame, so the sum keeps
    /// the datum's offset).
    fn surface_to_mesh(&mut self) -> Result<HeightMap> {
        let mut take = |port: &str| {
            self.finals
                .remove(port)
                .ok_or_else(|| anyhow!("mesher: end of scan without a final '{port}' frame"))
        };
        match self.settings.surface {
            SurfaceChoice::Pooled | SurfaceChoice::Panorama => take("surface"),
            SurfaceChoice::Datum => take("datum"),
            SurfaceChoice::Roughness => take("roughness"),
            SurfaceChoice::DatumPlusRoughness => {
                let mut d = take("datum")?;
                let r = take("roughness")?;
                check_same_grid(("datum", &d), ("roughness", &r))?;
                for (z, &r) in d.heights.iter_mut().zip(&r.heights) {
                    *z += r;
                }
                Ok(d)
            }
        }
    }

    /// The measured roughness wired as the reference, on the surface's grid (takes its final
    /// frame); `None` when it is not wired.
    fn roughness_reference(&mut self, surface: &HeightMap) -> Result<Option<HeightMap>> {
        if !self.roughness_reference {
            return Ok(None);
        }
        let r = self
            .finals
            .remove("roughness")
            .ok_or_else(|| anyhow!("mesher: end of scan without a final 'roughness' frame"))?;
        check_same_grid(("panorama", surface), ("roughness", &r))?;
        Ok(Some(r))
    }

    /// Meshes the chosen surface (takes its final frames) in memory: the twin of
    /// [`MeshJob::mesh_to_files`], which the node runs. Only the tests call it, as the oracle
    /// the streamed files are compared with (the same STL bytes and record).
    pub fn mesh(&mut self) -> Result<MeshedSurface> {
        let mut s = self.surface_to_mesh()?;
        let reference = self.roughness_reference(&s)?;
        let h = s.header;
        let shape = Shape::new(h.height as usize, h.width as usize);
        let at = ScanPlacement::of_frame(&h).map_err(|e| anyhow!("mesher: {e}"))?;
        let (outliers, form_plane) = prepare_surface(&self.settings, &mut s.heights, shape, &at)?;
        let footprints = self.footprints(shape, &at)?;
        let heights = RasterView::new(&s.heights, shape).map_err(|e| anyhow!("mesher: {e}"))?;
        let (solid, adaptive, resampled) =
            match (&self.settings.adaptive, self.settings.grid_target()) {
                (_, Some(profile)) => {
                    let t = grid_sheet_for(heights, &at, &profile)?;
                    let on_grid = block_values_on_grid(t.block_means.view(), t.stride, shape);
                    let summary = MethodSummary::GridSheet(t.record());
                    (t.mesh, Some(summary), Some(on_grid.into_values()))
                }
                (None, None) => (grid_solid(heights, &at, &self.settings.solid)?, None, None),
                (Some(p), None) => {
                    let tolerance = tolerance_for(&self.settings, reference.is_some());
                    let (m, report) = match &tolerance {
                        Some(t) => {
                            let reference = reference.as_ref().map(|r| &r.heights[..]);
                            let (m, r) =
                                mesh_to_tolerance(heights, reference, &at, p, t, &footprints)?;
                            (m, Some(r))
                        }
                        None => (mesh_height_field(heights, &at, p)?, None),
                    };
                    let summary = adaptive_method(m.record()?, report.as_ref());
                    (m.mesh, Some(summary), Some(m.resampled_um))
                }
            };
        let resampled = resampled.as_deref().unwrap_or(&s.heights);
        let resampled_um = Raster::new(from_frame_heights(h.z_offset_um, resampled), shape)
            .map_err(|e| anyhow!("mesher: resampled mesh: {e}"))?;
        let check = check_closed(&solid);
        Ok(MeshedSurface {
            solid,
            check,
            adaptive,
            resampled_um,
            header: h,
            at,
            outliers,
            form_plane,
        })
    }

    /// Meshes the chosen surface (takes its final frames) through the one entry point
    /// ([`mesh_surface`]) and writes the STL to `stl` (atomically) and the mesh re-sampled on
    /// the grid (absolute um, f64) to `resampled_npy`: the same files and record as
    /// [`MeshJob::mesh`] followed by [`MeshedSurface::write_stl`], but the adaptive mesh is
    /// streamed ([`crate::stream`]): its triangles go through a spill file beside `stl`, so
    /// the memory held is a few bytes per sample whatever the triangle count.
    pub fn mesh_to_files(&mut self, stl: &Path, resampled_npy: &Path) -> Result<MeshFiles> {
        let s = self.surface_to_mesh()?;
        let reference = self.roughness_reference(&s)?;
        let h = s.header;
        let shape = Shape::new(h.height as usize, h.width as usize);
        let at = ScanPlacement::of_frame(&h).map_err(|e| anyhow!("mesher: {e}"))?;
        let input = MeshInput {
            heights_um: s.heights,
            shape,
            footprints: self.footprints(shape, &at)?,
            at,
            roughness_um: reference.as_ref().map(|r| &r.heights[..]),
            t_acquired_ns: h.t_acquired_ns,
            surface: self.settings.surface.name(),
        };
        let outputs = MeshOutputs {
            stl,
            resampled_npy: Some(resampled_npy),
            stl_label: STL_LABEL,
        };
        let outcome = mesh_surface(&self.settings, input, &outputs)?;
        Ok(MeshFiles {
            // The graph's engine grids are made in memory (their budgets bound them).
            streamed: !matches!(outcome.made, crate::map::MeshMade::Grid(_)),
            summary: outcome.report,
            check: outcome.check,
        })
    }
}

/// Table 6's tile regions (S1, S2, ..., [`tile_regions`]) as the tolerance search's regions,
/// when the surface (`shape`, `at`) lies on the grid of the panorama `tiles` describes; none
/// otherwise (a pooled map, or another panorama).
pub fn tile_footprints(tiles: &PanoramaTiles, shape: Shape, at: &ScanPlacement) -> Vec<Window> {
    let p = &tiles.panorama;
    let same_grid = (p.height_px, p.width_px) == (shape.rows, shape.cols)
        && p.pitch_x_um == at.pitch.x_um()
        && p.pitch_y_um == at.pitch.y_um()
        && p.origin_x_um == at.origin_x_um
        && p.origin_y_um == at.origin_y_um;
    if !same_grid {
        return Vec::new();
    }
    let placed = (tiles.tiles.iter()).map(|t| {
        let size = Shape::new(t.height_px, t.width_px);
        Some(((t.x_um, t.y_um), size))
    });
    let origin = (at.origin_x_um, at.origin_y_um);
    tile_regions(placed, origin, at.pitch, shape)
        .into_iter()
        .map(|r| Window {
            name: r.name,
            row0: r.row0,
            col0: r.col0,
            rows: r.rows,
            cols: r.cols,
        })
        .collect()
}

/// Two final frames must share one grid (size, pitch, origin) to be combined sample by sample.
fn check_same_grid((a_name, a): (&str, &HeightMap), (b_name, b): (&str, &HeightMap)) -> Result<()> {
    let (x, y) = (&a.header, &b.header);
    if (x.width, x.height) != (y.width, y.height)
        || x.pitch_x_um != y.pitch_x_um
        || x.pitch_y_um != y.pitch_y_um
        || x.origin_x_um != y.origin_x_um
        || x.origin_y_um != y.origin_y_um
        || a.heights.len() != b.heights.len()
    {
        bail!(
            "mesher: {a_name} ({} x {} px (rows x cols), pitch {} x {} um, origin {}, {} um) and \
             {b_name} ({} x {} px, pitch {} x {} um, origin {}, {} um) are not on the same grid",
            x.height,
            x.width,
            x.pitch_x_um,
            x.pitch_y_um,
            x.origin_x_um,
            x.origin_y_um,
            y.height,
            y.width,
            y.pitch_x_um,
            y.pitch_y_um,
            y.origin_x_um,
            y.origin_y_um
        );
    }
    Ok(())
}
