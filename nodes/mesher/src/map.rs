//! The mesher's one entry point: [`mesh_surface`] meshes one surface with the one
//! [`MeshSettings`] and writes its STL (and, for a graph, the mesh re-sampled on the grid),
//! returning the one record, [`MeshReport`]. The graph's node (`job::MeshJob`), the
//! `surfstream mesh` verb and the Python binding all call it, so none of them can drift.
//!
//! The steps, in order: the STL's name checked (`x.obj` is refused by every caller); the form
//! removed when the settings level ([`MeshSettings::level`], the least-squares plane as
//! `params --level`); spikes found (and removed on request); then the method: an engine's
//! regular grid, the full-grid solid, or the model (a fixed vertical bound or the fewest
//! triangles that meet the tolerance), the model streamed ([`crate::mesh_streaming`],
//! [`crate::mesh_streaming_to_tolerance`]: the triangles wait in a spill file in the STL's
//! folder).
//!
//! A caller with f64 heights (a file, a numpy array) turns them into the frame's f32 about
//! their mean with [`prepare_heights`] first.

use std::path::Path;
use std::time::Instant;

use anyhow::{anyhow, bail, Context, Result};
use rayon::prelude::*;
use surfstream_core::frame::to_frame_heights;
use surfstream_core::metrology;
use surfstream_core::raster::{RasterView, Shape};
use surfstream_core::record::{FormPlane, MeshReport};
use surfstream_core::Sampling;
use surfstream_io::npy::write_npy_abs;
use surfstream_io::sidecar::{write_sidecar, NpyGeometry};

use crate::config::{check_stl_path, MeshSettings, StlFormat};
use crate::outliers::{find_spikes, OutlierPolicy, OutlierReport};
use crate::report::{adaptive_method, mesh_report, MethodSummary, ReportContext};
use crate::target::block_values_on_grid;
use crate::tolerance::Window;
use crate::{
    grid_sheet_for, grid_streaming, mesh_streaming, mesh_streaming_to_tolerance, EngineProfile,
    MeshCheck, MeshCounts, MeshError, ScanPlacement, StreamedGrid, StreamedMesh, TargetMesh,
    ToleranceReport, ToleranceSettings,
};

/// f64 heights as the frame carries them: f32 about their mean (so that f32 keeps nanometres
/// however far up the z axis the part sits; the mean is the placement's z offset).
pub struct PreparedHeights {
    pub heights_um: Vec<f32>,
    pub z_offset_um: f64,
    pub shape: Shape,
}

/// `heights_um` (row-major, `shape`, NaN = not measured) as [`PreparedHeights`]. Errors: the
/// length is not the shape's, no measured sample, or an infinite sample
/// ([`MeshError::InfiniteSample`]: only NaN marks a missing sample).
pub fn prepare_heights(heights_um: &[f64], shape: Shape) -> Result<PreparedHeights> {
    if heights_um.len() != shape.rows * shape.cols {
        bail!(
            "the map holds {} heights, its shape says {shape}",
            heights_um.len()
        );
    }
    if !heights_um.iter().any(|h| h.is_finite()) {
        bail!("no measured sample (all NaN)");
    }
    // Refused before it enters the mean.
    if let Some(k) = heights_um.iter().position(|h| h.is_infinite()) {
        let cols = shape.cols.max(1);
        return Err(MeshError::InfiniteSample {
            row: k / cols,
            col: k % cols,
            value: heights_um[k] as f32,
        }
        .into());
    }
    let (z_offset_um, heights_um) = to_frame_heights(heights_um);
    Ok(PreparedHeights {
        heights_um,
        z_offset_um,
        shape,
    })
}

impl PreparedHeights {
    /// The surface to mesh at `pitch` (sample (0, 0) at the scan origin), without a roughness
    /// reference.
    pub fn into_input(self, pitch: surfstream_core::Pitch) -> MeshInput<'static> {
        MeshInput {
            heights_um: self.heights_um,
            shape: self.shape,
            at: ScanPlacement::new(pitch).with_z_offset(self.z_offset_um),
            roughness_um: None,
            footprints: Vec::new(),
            t_acquired_ns: 0,
            surface: "",
        }
    }
}

/// One surface to mesh.
pub struct MeshInput<'a> {
    /// Heights, um relative to `at.z_offset_um`, row-major `shape`, NaN = not measured.
    pub heights_um: Vec<f32>,
    pub shape: Shape,
    pub at: ScanPlacement,
    /// The measured roughness on the same grid (relative to its mean): the tolerance then
    /// also judges the roughness the mesh carries; `None`: that bound is not claimed.
    pub roughness_um: Option<&'a [f32]>,
    /// Table 6's tile regions on this grid (S1, S2, ...: `job::tile_footprints`),
    /// judged by the tolerance search beside its windows; empty: not known (a map from a
    /// file, Python), the windows alone.
    pub footprints: Vec<Window>,
    /// When the surface's frame was acquired (ns; 0: not from a frame).
    pub t_acquired_ns: u64,
    /// The surface's name in the report ("panorama", ...; empty: a map from a file).
    pub surface: &'static str,
}

/// Where [`mesh_surface`] writes.
pub struct MeshOutputs<'a> {
    /// The STL (its name must end in .stl); its folder is created and holds the spill file
    /// while the mesh is made.
    pub stl: &'a Path,
    /// The mesh re-sampled on the grid (absolute um, f64 .npy with its pitch sidecar), when
    /// wanted (a graph's Table 6 reads it).
    pub resampled_npy: Option<&'a Path>,
    /// The STL header's label (the writer adds the unit and the offset).
    pub stl_label: &'a str,
}

/// The mesh made, for the caller's own lines.
#[allow(clippy::large_enum_variant)]
pub enum MeshMade {
    /// The model (a fixed bound or the tolerance's), streamed.
    Model(StreamedMesh),
    /// An engine's regular-grid sheet.
    Grid(TargetMesh),
    /// Two triangles per grid cell, streamed.
    FullGrid(StreamedGrid),
}

/// What [`mesh_surface`] made.
pub struct MeshOutcome {
    /// The record (run.json's `stages.mesher`, the verb's OUT.json, Python's dict); `file`
    /// is the STL's file name.
    pub report: MeshReport,
    pub check: MeshCheck,
    pub made: MeshMade,
    /// The tolerance search's own report (the record holds it as `tolerance`).
    pub tolerance: Option<ToleranceReport>,
}

/// The heights the method meshes: levelled when the settings say so (the plane removed is
/// returned), spikes found (and removed on request). The in-memory oracle
/// (`job::MeshJob::mesh`) prepares the same way.
pub(crate) fn prepare_surface(
    settings: &MeshSettings,
    heights_um: &mut [f32],
    shape: Shape,
    at: &ScanPlacement,
) -> Result<(OutlierReport, Option<FormPlane>)> {
    if heights_um.len() != shape.rows * shape.cols {
        bail!(
            "the surface holds {} heights, its shape says {shape}",
            heights_um.len()
        );
    }
    let form_plane = if settings.level {
        Some(level_in_place(heights_um, shape, at)?)
    } else {
        None
    };
    let (report, spikes) = find_spikes(RasterView::new(heights_um, shape)?, settings.outliers);
    if settings.outliers == OutlierPolicy::Remove {
        for k in spikes {
            heights_um[k] = f32::NAN;
        }
    }
    Ok((report, form_plane))
}

/// Removes the least-squares plane from `heights_um` in place: the bits of
/// [`metrology::level_plane`] on an f64 copy rounded back to f32 (the plane fitted on the f32
/// heights themselves, [`metrology::fit_plane_f32`], is the one the widened copy gives, and
/// each sample is levelled by the same f64 expression), without the two f64 copies (16 B per
/// sample) that took. Returns the plane removed.
fn level_in_place(heights_um: &mut [f32], shape: Shape, at: &ScanPlacement) -> Result<FormPlane> {
    let sampling = Sampling::new(shape, at.pitch.x_um(), at.pitch.y_um())?;
    let (a, b, c) = metrology::fit_plane_f32(heights_um, sampling)
        .context("level (the least-squares plane)")?;
    let (bx, by) = (b * sampling.pitch_x_um(), c * sampling.pitch_y_um());
    heights_um
        .par_chunks_mut(shape.cols.max(1))
        .enumerate()
        .for_each(|(r, row)| {
            let base = a + by * r as f64;
            for (i, z) in row.iter_mut().enumerate() {
                *z = (f64::from(*z) - (base + bx * i as f64)) as f32;
            }
        });
    Ok(FormPlane {
        z_um: a + at.z_offset_um,
        slope_x_um_per_um: b,
        slope_y_um_per_um: c,
    })
}

/// The tolerance the search meets: without the measured roughness there is nothing to judge
/// the roughness against, and the report does not claim that bound.
pub(crate) fn tolerance_for(settings: &MeshSettings, roughness: bool) -> Option<ToleranceSettings> {
    let mut t = settings.tolerance?;
    if !roughness {
        t.tolerance.roughness_pct = None;
    }
    Some(t)
}

/// Meshes `input` as `settings` say, writes the STL (and the re-sampled mesh when asked) and
/// returns the record. The one entry point of the mesher (see the module's doc).
pub fn mesh_surface(
    settings: &MeshSettings,
    mut input: MeshInput<'_>,
    out: &MeshOutputs<'_>,
) -> Result<MeshOutcome> {
    check_stl_path(out.stl).map_err(MeshError::Incompatible)?;
    if let Some(r) = input.roughness_um {
        if r.len() != input.heights_um.len() {
            bail!(
                "the roughness holds {} values, the surface {}: expected the same grid",
                r.len(),
                input.heights_um.len()
            );
        }
    }
    let shape = input.shape;
    let (outliers, form_plane) =
        prepare_surface(settings, &mut input.heights_um, shape, &input.at)?;
    let heights = RasterView::new(&input.heights_um, shape)?;
    let at = &input.at;
    let spill_dir = match out.stl.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    std::fs::create_dir_all(spill_dir)
        .with_context(|| format!("{}: cannot create the folder", spill_dir.display()))?;
    let ascii = settings.format == StlFormat::Ascii;
    let context = ReportContext {
        settings,
        shape,
        at,
        t_acquired_ns: input.t_acquired_ns,
        surface: input.surface,
        outliers: &outliers,
        form_plane,
    };
    let t0 = Instant::now();
    let (made, check, method, tolerance) = match (&settings.adaptive, settings.grid_target()) {
        (_, Some(profile)) => grid_target(heights, at, &profile, out, ascii)?,
        (None, None) => {
            let g = grid_streaming(heights, at, &settings.solid)?;
            write_resampled(out, heights.values(), shape, at)?;
            let check = write_stl(out, |w| g.write_stl(w, ascii, out.stl_label, heights))?;
            (MeshMade::FullGrid(g), check, None, None)
        }
        (Some(params), None) => {
            let (mut m, report) = match tolerance_for(settings, input.roughness_um.is_some()) {
                Some(t) => {
                    let (m, r) = mesh_streaming_to_tolerance(
                        heights,
                        input.roughness_um,
                        at,
                        params,
                        &t,
                        &input.footprints,
                        spill_dir,
                    )?;
                    (m, Some(r))
                }
                None => (mesh_streaming(heights, at, params, spill_dir)?, None),
            };
            let method = adaptive_method(m.summary.clone(), report.as_ref());
            write_resampled(out, &m.resampled_um, shape, at)?;
            let check = write_stl(out, |w| m.write_stl(w, ascii, out.stl_label, heights))?;
            (MeshMade::Model(m), check, Some(method), report)
        }
    };
    let mesh_s = t0.elapsed().as_secs_f64();
    let counts = match &made {
        MeshMade::Model(m) => m.counts,
        MeshMade::Grid(t) => MeshCounts::of(&t.mesh),
        MeshMade::FullGrid(g) => g.counts,
    };
    let mut report = mesh_report(&counts, &check, method.as_ref(), &context)?;
    report.mesh_s = Some(mesh_s);
    report.file = out
        .stl
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    Ok(MeshOutcome {
        report,
        check,
        made,
        tolerance,
    })
}

/// An engine's regular-grid sheet: block-averaged to its triangle budget, elements checked
/// against its limits, made in memory (its budget bounds it).
fn grid_target(
    heights: RasterView<'_, f32>,
    at: &ScanPlacement,
    profile: &EngineProfile,
    out: &MeshOutputs<'_>,
    ascii: bool,
) -> Result<(
    MeshMade,
    MeshCheck,
    Option<MethodSummary>,
    Option<ToleranceReport>,
)> {
    let t = grid_sheet_for(heights, at, profile)?;
    if out.resampled_npy.is_some() {
        let on_grid = block_values_on_grid(t.block_means.view(), t.stride, heights.shape());
        write_resampled(out, on_grid.values(), heights.shape(), at)?;
    }
    let check = crate::check_closed(&t.mesh);
    surfstream_core::fsutil::write_atomic(out.stl, |w| {
        if ascii {
            crate::write_stl_ascii(w, &t.mesh, out.stl_label)?;
        } else {
            crate::write_stl_binary(w, &t.mesh, out.stl_label)?;
        }
        Ok(())
    })?;
    let method = MethodSummary::GridSheet(t.record());
    Ok((MeshMade::Grid(t), check, Some(method), None))
}

/// Writes the STL atomically with `write`, which returns the check of what it wrote.
fn write_stl(
    out: &MeshOutputs<'_>,
    write: impl FnOnce(&mut dyn std::io::Write) -> crate::Result<MeshCheck>,
) -> Result<MeshCheck> {
    let mut check = None;
    surfstream_core::fsutil::write_atomic(out.stl, |w| {
        check = Some(write(w)?);
        Ok(())
    })?;
    check.ok_or_else(|| anyhow!("{}: nothing written", out.stl.display()))
}

/// The mesh re-sampled on the grid (relative to the z offset), written absolute with its pitch
/// sidecar when the outputs ask for it.
fn write_resampled(
    out: &MeshOutputs<'_>,
    resampled_um: &[f32],
    shape: Shape,
    at: &ScanPlacement,
) -> Result<()> {
    let Some(path) = out.resampled_npy else {
        return Ok(());
    };
    write_npy_abs(path, resampled_um, shape.rows, shape.cols, at.z_offset_um)?;
    let geometry = NpyGeometry {
        pitch_x_um: at.pitch.x_um(),
        pitch_y_um: at.pitch.y_um(),
        origin_um: Some([at.origin_x_um, at.origin_y_um]),
    };
    write_sidecar(path, &geometry)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{
        check_closed, mesh_height_field, write_stl_binary, DemEngine, Epsilon, MesherConfig,
        TargetMethod,
    };
    use surfstream_core::Pitch;

    /// A tilted wavy 40 x 50 map about 30 um up, one sample not measured, one spike.
    fn map() -> (Vec<f64>, Shape) {
        let shape = Shape::new(40, 50);
        let mut h: Vec<f64> = (0..shape.rows * shape.cols)
            .map(|k| {
                let (y, x) = ((k / shape.cols) as f64, (k % shape.cols) as f64);
                30.0 + 0.01 * x + (x / 5.0).sin() + 0.3 * (y / 7.0).cos()
            })
            .collect();
        h[7 * shape.cols + 9] = f64::NAN;
        h[20 * shape.cols + 25] += 40.0;
        (h, shape)
    }

    fn outputs(stl: &Path) -> MeshOutputs<'_> {
        MeshOutputs {
            stl,
            resampled_npy: None,
            stl_label: "surfstream mesh",
        }
    }

    /// The streamed model written by `mesh_surface` is the in-memory mesher's (the oracle)
    /// byte for byte, its record carries the oracle's counts and checks, and the spill leaves
    /// nothing beside the STL.
    #[test]
    fn the_model_is_the_in_memory_meshers() {
        let d = tempfile::tempdir().unwrap();
        let (h, shape) = map();
        let pitch = Pitch::new(0.5, 0.7).unwrap();
        let settings = MesherConfig {
            epsilon_um: Some(0.02),
            ..MesherConfig::default()
        }
        .settings()
        .unwrap();
        let p = prepare_heights(&h, shape).unwrap();
        let (heights, z_offset_um) = (p.heights_um.clone(), p.z_offset_um);
        let stl = d.path().join("m/w.stl");
        let out = mesh_surface(&settings, p.into_input(pitch), &outputs(&stl)).unwrap();
        let at = ScanPlacement::new(pitch).with_z_offset(z_offset_um);
        let view = RasterView::new(&heights, shape).unwrap();
        let params = settings.adaptive.clone().unwrap();
        assert_eq!(params.epsilon, Epsilon::Um(0.02));
        let m = mesh_height_field(view, &at, &params).unwrap();
        let mut want = Vec::new();
        write_stl_binary(&mut want, &m.mesh, "surfstream mesh").unwrap();
        assert!(std::fs::read(&stl).unwrap() == want, "STL bytes differ");
        let json = surfstream_core::record::to_value(&out.report).unwrap();
        let oracle = m.summary().unwrap();
        for key in ["triangles", "vertices", "fidelity", "offset_um"] {
            assert_eq!(json[key], oracle[key], "{key}");
        }
        assert_eq!(json["watertight"], check_closed(&m.mesh).watertight);
        assert_eq!(json["outliers"]["count"], 1);
        assert_eq!(json["file"], "w.stl");
        assert_eq!(json["grid_px"], serde_json::json!([50, 40]));
        assert!(json.get("input").is_none() && json.get("form_removed").is_none());
        let files: Vec<_> = std::fs::read_dir(stl.parent().unwrap()).unwrap().collect();
        assert_eq!(files.len(), 1);
    }

    /// Levelled: the plane is gone from the meshed heights (the mesh of a tilted plane is two
    /// triangles flat at the mean) and the record says which form was removed.
    /// Levelling in place gives the bits the f64 copy and `level_plane` gave (rounded to
    /// f32), on a tilted wavy map with missing samples and a non-square pitch.
    #[test]
    fn level_in_place_is_level_plane_to_the_bit() {
        let shape = Shape::new(37, 53);
        let h: Vec<f32> = (0..shape.len())
            .map(|k| {
                let (i, j) = ((k / shape.cols) as f32, (k % shape.cols) as f32);
                if k % 97 == 5 {
                    f32::NAN
                } else {
                    12.5 + 0.31 * j - 0.17 * i + (0.7 * j).sin() * (0.3 * i).cos()
                }
            })
            .collect();
        let at = ScanPlacement::new(Pitch::new(0.8, 1.3).unwrap());
        let wide: Vec<f64> = h.iter().map(|&z| f64::from(z)).collect();
        let g = metrology::Grid::new(&wide, shape.rows, shape.cols, 0.8, 1.3).unwrap();
        let expected: Vec<f32> = metrology::level_plane(&g)
            .unwrap()
            .iter()
            .map(|&z| z as f32)
            .collect();
        let mut levelled = h.clone();
        level_in_place(&mut levelled, shape, &at).unwrap();
        assert!(levelled
            .iter()
            .zip(&expected)
            .all(|(a, b)| a.to_bits() == b.to_bits()));
        assert!(levelled.iter().zip(&h).any(|(a, b)| a != b));
    }

    #[test]
    fn level_removes_the_plane_before_meshing() {
        let d = tempfile::tempdir().unwrap();
        let shape = Shape::new(30, 40);
        let h: Vec<f64> = (0..shape.rows * shape.cols)
            .map(|k| 5.0 + 0.3 * (k % shape.cols) as f64 - 0.2 * (k / shape.cols) as f64)
            .collect();
        let pitch = Pitch::square(1.0).unwrap();
        let config = |level| MesherConfig {
            epsilon_um: Some(0.001),
            level,
            ..MesherConfig::default()
        };
        let run = |level: bool, name: &str| {
            let stl = d.path().join(name);
            let p = prepare_heights(&h, shape).unwrap();
            let settings = config(level).settings().unwrap();
            mesh_surface(&settings, p.into_input(pitch), &outputs(&stl)).unwrap()
        };
        let raw = run(false, "raw.stl");
        let flat = run(true, "flat.stl");
        assert_eq!(
            flat.report.form_removed.as_deref(),
            Some("least-squares plane")
        );
        assert!(raw.report.form_removed.is_none());
        // The plane removed is recorded (Table 6 levels the panorama by it): the map's own
        // slopes, 0.3 um per column and -0.2 per row at a 1 um pitch.
        assert!(raw.report.form_plane.is_none());
        let plane = flat.report.form_plane.expect("the plane removed");
        assert!((plane.slope_x_um_per_um - 0.3).abs() < 1e-6, "{plane:?}");
        assert!((plane.slope_y_um_per_um + 0.2).abs() < 1e-6, "{plane:?}");
        assert!((plane.z_um - 5.0).abs() < 1e-4, "{plane:?}");
        let z_range = |o: &MeshOutcome| match &o.made {
            MeshMade::Model(m) => {
                let r = &m.resampled_um;
                let (lo, hi) = r
                    .iter()
                    .fold((f32::MAX, f32::MIN), |(a, b), &z| (a.min(z), b.max(z)));
                hi - lo
            }
            _ => panic!("a model"),
        };
        assert!(z_range(&raw) > 10.0, "{}", z_range(&raw));
        assert!(z_range(&flat) < 1e-3, "{}", z_range(&flat));
        assert_eq!(flat.report.top_triangles, 2);
    }

    /// An engine's grid: the STL `grid_sheet_for` makes, its counts in the record; a fixed
    /// bound with an engine that bounds angles is refused; so are an STL named otherwise and
    /// an infinite sample.
    #[test]
    fn grid_targets_and_refusals() {
        let d = tempfile::tempdir().unwrap();
        let (h, shape) = map();
        let pitch = Pitch::square(1.0).unwrap();
        let settings = MesherConfig {
            target: Some(DemEngine::Yade),
            method: crate::MeshMethod::Grid,
            outliers: OutlierPolicy::Remove,
            ..MesherConfig::default()
        }
        .settings()
        .unwrap();
        let profile = settings.target.unwrap();
        assert_eq!(profile.method, TargetMethod::Grid);
        let stl = d.path().join("y.stl");
        let input = || prepare_heights(&h, shape).unwrap().into_input(pitch);
        let out = mesh_surface(&settings, input(), &outputs(&stl)).unwrap();
        let mut spikeless = input();
        prepare_surface(&settings, &mut spikeless.heights_um, shape, &spikeless.at).unwrap();
        assert!(spikeless.heights_um[20 * shape.cols + 25].is_nan());
        let view = RasterView::new(&spikeless.heights_um, shape).unwrap();
        let t = grid_sheet_for(view, &spikeless.at, &profile).unwrap();
        let json = surfstream_core::record::to_value(&out.report).unwrap();
        assert_eq!(json["triangles"], t.mesh.triangles.len());
        assert_eq!(json["method"], "grid");
        assert_eq!(json["outliers"]["removed"], 1);
        assert!(std::fs::metadata(&stl).unwrap().len() > 0);

        // An STL under another name is refused, as the verb refuses it, and nothing written.
        let obj = d.path().join("x.obj");
        let e = mesh_surface(&settings, input(), &outputs(&obj))
            .err()
            .unwrap();
        assert!(e.to_string().contains("x.obj: mesh writes STL"), "{e}");
        assert!(e.downcast_ref::<MeshError>().is_some(), "{e}");
        assert!(!obj.exists());

        let e = MesherConfig {
            target: Some(DemEngine::Liggghts),
            epsilon_um: Some(0.1),
            ..MesherConfig::default()
        }
        .settings()
        .unwrap_err();
        assert!(e.contains("needs the model from a tolerance"), "{e}");

        let mut inf = h.clone();
        inf[3] = f64::INFINITY;
        let e = prepare_heights(&inf, shape).err().unwrap();
        assert!(e.downcast_ref::<MeshError>().is_some(), "{e}");
        let nan = vec![f64::NAN; 6];
        assert!(prepare_heights(&nan, Shape::new(2, 3)).is_err());
    }
}
