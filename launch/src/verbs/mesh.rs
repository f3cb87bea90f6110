//! `surfstream mesh`: error-bounded triangle mesh of one height map, written as STL, with its
//! statistics in `OUT.json` beside it.

use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use clap::{Args, ValueEnum};
use surfstream_core::frame::to_frame_heights;
use surfstream_core::metrology::{self, Grid};
use surfstream_core::raster::Shape;
use surfstream_core::record::OutliersRecord;
use surfstream_core::units::height;
use surfstream_mesher::config::check_stl_path;
use surfstream_mesher::map::PreparedHeights;
use surfstream_mesher::outliers::OutlierPolicy;
use surfstream_mesher::tolerance::ModelMethod;
use surfstream_mesher::{
    mesh_surface, parse_choice, prepare_heights, DemEngine, Epsilon, LengthUnit, MeshKind,
    MeshMade, MeshMethod, MeshOutcome, MeshOutputs, MeshSettings, MesherConfig, MissingSamples,
    StlFormat, StreamedMesh, TargetMesh,
};

#[derive(Clone, Copy, ValueEnum)]
pub enum Units {
    M,
    Mm,
    Um,
}

#[derive(Args)]
pub struct MeshArgs {
    #[arg(help = super::file_help())]
    pub file: PathBuf,
    /// The model's tolerance per region, percent (default sa=1,sq=1,sz=3,res=20,max=50 when
    /// no epsilon is given, plus rough=5 with --roughness): the fewest triangles whose mesh,
    /// interpolated at every measured sample, keeps Sa, Sq and Sz within it in every window
    /// (docs/model.md); res bounds the pointwise residual RMS, max the largest pointwise
    /// error (% of Sq), rough the roughness the mesh carries (% of the measured one); `=off`
    /// drops a bound.
    #[arg(long, value_name = "sa=1,sq=1,sz=3", conflicts_with_all = ["epsilon_um", "epsilon_sq"])]
    pub tolerance: Option<surfstream_mesher::Tolerance>,
    /// Side of the windows the tolerance is judged in, samples (default: half the map's
    /// shorter side, 64 to 1024).
    #[arg(long, value_name = "PX")]
    pub region_px: Option<usize>,
    /// How the tolerance search's insertion order is made: "balanced" (default: greedy plus
    /// a per-block Sa/Sq balance) or "greedy" (the pointwise bound only); docs/model.md.
    #[arg(long, value_name = "balanced|greedy", default_value = "balanced",
          value_parser = |s: &str| parse_choice::<ModelMethod>("--model-method", s))]
    pub model_method: ModelMethod,
    /// The map's measured roughness (e.g. a run's roughness.npy, on the same grid): the
    /// tolerance then also judges the roughness the mesh carries (mesh minus datum) against it,
    /// within `rough` (default 5 %), as the graphs do (docs/model.md).
    #[arg(long, value_name = "FILE", conflicts_with_all = ["epsilon_um", "epsilon_sq"])]
    pub roughness: Option<PathBuf>,
    /// The fusion's tile placements for a panorama (a run's panorama.tiles.json; by default
    /// NAME.tiles.json beside NAME.npy when it exists): the tolerance then also judges every
    /// tile's footprint (Table 6's S1, S2, ...), as the graph's mesher does, and aims at all
    /// of the tolerance instead of 90 % of it.
    #[arg(long, value_name = "FILE", conflicts_with_all = ["epsilon_um", "epsilon_sq", "no_tiles"])]
    pub tiles: Option<PathBuf>,
    /// Do not read NAME.tiles.json beside the input: the windows alone, at 90 % of the
    /// tolerance (the margin for the tile regions not judged).
    #[arg(long)]
    pub no_tiles: bool,
    /// Only the tolerance search's own meshes: the fidelity-cost curve in OUT.json is then
    /// those (3 on the demo) instead of at least 6, so less time (the search's mesh is
    /// written; the curve's coarse points are not tried).
    #[arg(long, conflicts_with_all = ["epsilon_um", "epsilon_sq", "grid"])]
    pub no_curve: bool,
    /// Treat isolated spikes as not measured before meshing (ISO 25178-3 style outlier
    /// removal; they are always reported in OUT.json, and kept by default).
    #[arg(long)]
    pub remove_spikes: bool,
    /// Subtract the least-squares plane first, as `params --level` (the STL is of the levelled
    /// surface and the tolerance is judged on it); without it only the mean is removed, and a
    /// tilt then dominates Sq and hides the roughness from the tolerance.
    #[arg(long)]
    pub level: bool,
    /// A fixed bound instead of a tolerance: the largest vertical distance between any
    /// measured sample and the mesh, um.
    #[arg(long, conflicts_with = "epsilon_sq")]
    pub epsilon_um: Option<f64>,
    /// A fixed bound as a fraction of the map's Sq (about its least-squares plane).
    #[arg(long)]
    pub epsilon_sq: Option<f64>,
    /// Write what this DEM engine imports: liggghts (ASCII sheet in m, the model from the
    /// tolerance with no angle below 1 deg), mercurydpm (binary sheet in m on a regular grid),
    /// edem (binary solid in mm), yade (small ASCII sheet in m on a regular grid). Sets the
    /// format, kind, units, method and triangle budget; the target is recorded in OUT.json.
    #[arg(long, conflicts_with_all = ["solid", "sheet", "holes", "ascii", "units"])]
    pub target: Option<DemEngine>,
    /// With --target: the engine's regular grid (block means within its triangle budget)
    /// instead of the model from the tolerance.
    #[arg(long, requires = "target", conflicts_with_all = ["tolerance", "epsilon_um", "epsilon_sq"])]
    pub grid: bool,
    /// Stop refining at this many surface triangles (the bound may then not hold; OUT.json says);
    /// with a tolerance, the most the search may use.
    #[arg(long)]
    pub max_triangles: Option<usize>,
    /// A closed solid: surface, side walls and a flat base (default).
    #[arg(long, conflicts_with = "sheet")]
    pub solid: bool,
    /// The open surface alone (e.g. a wall); with --holes, missing samples stay holes.
    #[arg(long)]
    pub sheet: bool,
    /// Leave missing samples out as holes instead of filling them (needs --sheet).
    #[arg(long, requires = "sheet")]
    pub holes: bool,
    /// Write ASCII STL (LIGGGHTS) instead of binary (EDEM, Rocky, MercuryDPM).
    #[arg(long)]
    pub ascii: bool,
    /// Unit of the STL coordinates (mm when not given; the summary line names it).
    #[arg(long, value_enum)]
    pub units: Option<Units>,
    /// Base of the solid below the lowest sample, um (default: 10 % of the height range, >= 10).
    #[arg(long)]
    pub base_depth_um: Option<f64>,
    /// Pitch in um for a file that carries none (a .npy without its NAME.npy.json sidecar);
    /// refused when it disagrees with the file's own (the rule of every verb).
    #[arg(long)]
    pub pitch_um: Option<f64>,
    /// Output STL (missing folders are created); the statistics go to the same name with .json.
    #[arg(short = 'o', long, value_name = "OUT.stl")]
    pub out: PathBuf,
    #[command(flatten)]
    pub mask: super::MaskArgs,
}

pub fn run(a: MeshArgs) -> Result<()> {
    check_stl_name(&a.out)?;
    let settings = config(&a)
        .settings()
        .map_err(|e| anyhow!("{}: {e}", a.file.display()))?;
    let (surface, prepared) = prepared_heights(&a)?;
    let pitch = surfstream_core::Pitch::new(surface.pitch_x_um, surface.pitch_y_um)
        .map_err(|e| anyhow!("{}: {e}", a.file.display()))?;
    let roughness = match (&a.roughness, settings.tolerance) {
        (Some(path), Some(_)) => Some(roughness_reference(path, a.pitch_um, prepared.shape)?),
        _ => None,
    };
    let mut input = prepared.into_input(pitch);
    input.roughness_um = roughness.as_deref();
    if settings.tolerance.is_some() {
        input.footprints = tile_footprints_of(&a, input.shape, pitch)?;
    }
    let label = settings.map_stl_label();
    let outputs = MeshOutputs {
        stl: &a.out,
        resampled_npy: None,
        stl_label: &label,
    };
    if a.level {
        eprintln!(
            "mesh: levelled: the least-squares plane removed (as params --level); the mesh \
             and its tolerance are of the levelled surface"
        );
    }
    let mut outcome = mesh_surface(&settings, input, &outputs)
        .with_context(|| format!("{}", a.file.display()))?;
    say_spikes(&a, outcome.report.outliers.as_ref());
    outcome.report.input = Some(a.file.display().to_string());
    outcome.report.input_format = Some(surface.metadata.format.clone());
    let json_path = a.out.with_extension("json");
    let report = surfstream_core::record::to_value(&outcome.report)?;
    surfstream_core::fsutil::write_atomic(&json_path, |w| {
        serde_json::to_writer_pretty(w, &report)
            .map_err(|e| anyhow!("{}: {e}", json_path.display()))
    })?;
    match &outcome.made {
        MeshMade::Model(m) => say_result(&a, m, &outcome, &settings, &json_path),
        MeshMade::Grid(t) => say_grid(&a, t, &json_path),
        MeshMade::FullGrid(_) => {}
    }
    Ok(())
}

/// The tile footprints the tolerance judges too: from `--tiles`, or NAME.tiles.json beside
/// NAME.npy (the fusion writes panorama.tiles.json beside panorama.npy), said on stderr; none
/// with `--no-tiles` or without such a file. Errors: a file that is not the fusion's tile
/// placements, or (given with `--tiles`) one of another grid than the input's.
fn tile_footprints_of(
    a: &MeshArgs,
    shape: Shape,
    pitch: surfstream_core::Pitch,
) -> Result<Vec<surfstream_mesher::tolerance::Window>> {
    let beside = a.file.with_extension("tiles.json");
    let path = match (&a.tiles, a.no_tiles) {
        (Some(p), _) => p.clone(),
        (None, false) if beside.is_file() => beside,
        _ => return Ok(Vec::new()),
    };
    let text = std::fs::read_to_string(&path)
        .with_context(|| format!("{}: cannot read the tile placements", path.display()))?;
    let tiles: surfstream_core::record::PanoramaTiles =
        serde_json::from_str(&text).map_err(|e| {
            anyhow!(
                "{}: {e}: expected the fusion's tile placements (panorama.tiles.json; --no-tiles meshes without them)",
                path.display()
            )
        })?;
    let p = &tiles.panorama;
    // The .npy carries no origin: the panorama's, where its grid is the input's.
    let at = surfstream_mesher::ScanPlacement::new(pitch).with_origin(p.origin_x_um, p.origin_y_um);
    let footprints = surfstream_mesher::job::tile_footprints(&tiles, shape, &at);
    if footprints.is_empty() {
        let grid = format!(
            "{} x {} px at {} x {} um",
            p.height_px, p.width_px, p.pitch_x_um, p.pitch_y_um
        );
        if a.tiles.is_some() {
            bail!(
                "{}: the tile placements are of a {grid} panorama (rows x cols), {} is {} x {} px at {} x {} um: expected the placements of this map",
                path.display(),
                a.file.display(),
                shape.rows,
                shape.cols,
                pitch.x_um(),
                pitch.y_um()
            );
        }
        eprintln!(
            "mesh: note: {} is of another grid ({grid}): its tile footprints are not judged",
            path.display()
        );
        return Ok(Vec::new());
    }
    eprintln!(
        "mesh: judging the {} tile footprints of {} too (Table 6's regions): the search aims at all of the tolerance (--no-tiles: the windows alone, at 90 %)",
        footprints.len(),
        path.display()
    );
    Ok(footprints)
}

/// The mesher's config from the flags: the verb states the graph's parameters, typed, and
/// the mesher checks them ([`MesherConfig::settings`]).
pub fn config(a: &MeshArgs) -> MesherConfig {
    MesherConfig {
        units: match a.units.unwrap_or(Units::Mm) {
            Units::M => LengthUnit::M,
            Units::Mm => LengthUnit::Mm,
            Units::Um => LengthUnit::Um,
        },
        format: if a.ascii {
            StlFormat::Ascii
        } else {
            StlFormat::Binary
        },
        base_depth_um: a.base_depth_um,
        method: if a.grid {
            MeshMethod::Grid
        } else {
            MeshMethod::Adaptive
        },
        epsilon_um: a.epsilon_um,
        epsilon_sq_fraction: a.epsilon_sq,
        max_triangles: a.max_triangles,
        tolerance: a.tolerance,
        region_px: a.region_px,
        model_method: a.model_method,
        outliers: if a.remove_spikes {
            OutlierPolicy::Remove
        } else {
            OutlierPolicy::Keep
        },
        level: a.level,
        kind: if a.sheet {
            MeshKind::Sheet
        } else {
            MeshKind::Solid
        },
        missing: if a.holes {
            MissingSamples::Holes
        } else {
            MissingSamples::Fill
        },
        target: a.target,
        curve: !a.no_curve,
        ..MesherConfig::default()
    }
}

/// Below this share of the Sq with the mean removed, the Sq about the least-squares plane says
/// the surface is tilted (the verb then suggests --level).
const TILT_SQ_SHARE: f64 = 0.5;

/// The file read (its mask applied) and its heights prepared for the mesher
/// ([`prepare_heights`]); a tilt the mean does not remove is said.
fn prepared_heights(a: &MeshArgs) -> Result<(surfstream_io::formats::Surface, PreparedHeights)> {
    let mut surface = super::load_surface(&a.file, a.pitch_um, "mesh", true)?.surface;
    a.mask.apply(&a.file, &mut surface)?;
    if !a.level {
        say_tilt(&surface);
    }
    let shape = Shape::new(surface.height, surface.width);
    let prepared = prepare_heights(&surface.heights_um, shape)
        .with_context(|| format!("{}", a.file.display()))?;
    Ok((surface, prepared))
}

/// A tilt the mean does not remove: said, with what the tolerance and the STL do with it
/// (the tolerance is judged about the plane, the STL keeps it unless levelled).
fn say_tilt(surface: &surfstream_io::formats::Surface) {
    let grid = Grid::new(
        &surface.heights_um,
        surface.height,
        surface.width,
        surface.pitch_x_um,
        surface.pitch_y_um,
    );
    let Ok(Ok((a, b, c))) = grid.map(|g| metrology::fit_plane(&g)) else {
        return;
    };
    let (bx, by) = (b * surface.pitch_x_um, c * surface.pitch_y_um);
    let cols = surface.width.max(1);
    let measured = || {
        surface
            .heights_um
            .iter()
            .copied()
            .enumerate()
            .filter(|(_, z)| !z.is_nan())
    };
    let raw = sq_about_mean(|| measured().map(|(_, z)| z));
    let flat = sq_about_mean(|| {
        measured().map(|(k, z)| z - (a + by * (k / cols) as f64 + bx * (k % cols) as f64))
    });
    if flat < TILT_SQ_SHARE * raw {
        eprintln!(
            "mesh: note: the surface is tilted: Sq {} with the mean removed, {} about its \
             least-squares plane; the tolerance is judged about its least-squares plane (the \
             roughness's Sq, not the tilt's) and the STL keeps the tilt: --level removes the \
             plane from the STL too",
            height(raw),
            height(flat)
        );
    }
}

/// The Sq of `values()` about their mean: two passes over them, no copy.
fn sq_about_mean<I: Iterator<Item = f64>>(values: impl Fn() -> I) -> f64 {
    let (n, sum) = values().fold((0usize, 0.0), |(n, s), z| (n + 1, s + z));
    let mean = sum / n.max(1) as f64;
    (values().map(|z| (z - mean).powi(2)).sum::<f64>() / n.max(1) as f64).sqrt()
}

/// The spikes found, kept or removed.
fn say_spikes(a: &MeshArgs, spikes: Option<&OutliersRecord>) {
    let Some(spikes) = spikes.filter(|s| s.count > 0) else {
        return;
    };
    let Some(largest) = spikes.largest.first() else {
        return;
    };
    eprintln!(
        "mesh: {} spike(s) (largest {}{} at row {} col {}; they add {:+.2} % to Sz): {}",
        spikes.count,
        if largest.excess_um > 0.0 { "+" } else { "" },
        height(largest.excess_um),
        largest.row,
        largest.col,
        spikes.sz_effect_pct,
        if a.remove_spikes {
            "removed (--remove-spikes)"
        } else {
            "kept as measured (--remove-spikes to remove them)"
        }
    );
}

/// The lines the verb prints: the tolerance met (or not), the angles, the mesh.
fn say_result(
    a: &MeshArgs,
    m: &StreamedMesh,
    outcome: &MeshOutcome,
    settings: &MeshSettings,
    json_path: &Path,
) {
    let mesh_s = outcome.report.mesh_s.unwrap_or(0.0);
    let tolerance = outcome.tolerance.as_ref();
    let profile = settings.target;
    if let Some(r) = tolerance {
        let worst = r.region_fits.first();
        eprintln!(
            "mesh: tolerance {} {} at {} surface triangles ({:.3} per measured px, {} meshes \
             tried){}",
            r.tolerance,
            if r.met { "met" } else { "NOT met" },
            r.surface_triangles,
            r.triangles_per_measured_px,
            r.curve.len(),
            worst.map_or(String::new(), |w| format!(
                "; worst of {} regions{} {}: Sa {:+.2} %, Sq {:+.2} %, Sz {:+.2} %, residual {:.1} % \
                 of Sq, max error {} ({:.1} % of Sq)",
                r.regions,
                if r.judged_plane.is_some() {
                    " (less the least-squares plane)"
                } else {
                    ""
                },
                w.region,
                w.deviation_pct[0],
                w.deviation_pct[1],
                w.deviation_pct[2],
                w.residual_pct_of_sq,
                height(w.max_error_um),
                w.max_error_pct_of_sq,
            ))
        );
        if let Some(q) = &r.angles {
            eprintln!(
                "mesh: smallest angle {:.2} deg (bound {} deg; {:.3} deg before the refinement, \
                 which added {} triangles); {} below the bound",
                q.min_angle_deg,
                q.bound_deg,
                q.min_angle_before_deg,
                q.triangles.saturating_sub(q.triangles_before),
                q.below_bound
            );
        }
        if let Some(reason) = &r.reason {
            eprintln!("mesh: warning: {reason}");
        }
    }
    let (f, c) = (&m.fidelity, &m.counts);
    // The bound the mesh was made to: the search's choice with a tolerance (the flags' fixed
    // bound is not used then), else the fixed one.
    let epsilon = settings.adaptive.as_ref().map(|p| p.epsilon);
    let bound = match (tolerance, epsilon) {
        (Some(r), _) => {
            let chosen = r.curve.iter().find(|c| c.chosen);
            // Blocks whose regions all have a larger Sq take a coarser bound (issue 33): the
            // mesh's bound is then the coarsest block's, the search's the finest's.
            chosen.map_or(String::new(), |c| {
                let per_block = f.epsilon_um > c.epsilon_um * (1.0 + 1e-9);
                let finest = if per_block {
                    format!(
                        " where the regions' Sq is largest, {} um where it is smallest",
                        super::sig(c.epsilon_um, 4)
                    )
                } else {
                    String::new()
                };
                format!(
                    "{finest} = {} x Sq, the search's",
                    super::sig(c.epsilon_sq_fraction, 3)
                )
            })
        }
        (None, Some(Epsilon::SqFraction(q))) => format!(" = {q} x Sq"),
        (None, _) => String::new(),
    };
    eprintln!(
        "mesh: {} triangles ({} surface), {} vertices, STL in {}; max vertical error \
         {}, RMS {} (bound {}{bound}{}); {mesh_s:.2} s; wrote {} and {}",
        c.triangles,
        c.top_triangles,
        c.vertices,
        if a.units.is_none() && profile.is_none() {
            format!("{} (the default; --units m | mm | um)", c.units.symbol())
        } else {
            c.units.symbol().to_string()
        },
        height(f.error.max_um),
        height(f.error.rms_um),
        height(f.epsilon_um),
        if m.summary.record.budget_reached {
            ", triangle budget reached"
        } else {
            ""
        },
        a.out.display(),
        json_path.display()
    );
    if !f.bound_met {
        eprintln!(
            "mesh: warning: bound_met: false: the largest vertical error, {}, is beyond the \
             bound of {}{}",
            height(f.error.max_um),
            height(f.epsilon_um),
            if m.summary.record.budget_reached {
                " (the triangle budget stopped the refinement)"
            } else {
                ""
            }
        );
    }
}

/// The line for an engine's regular-grid sheet.
fn say_grid(a: &MeshArgs, t: &TargetMesh, json_path: &Path) {
    let profile = &t.profile;
    eprintln!(
        "mesh: {} triangles for {} ({} sheet in {}, {} x {} grid (rows x cols){}); smallest angle {:.1} deg; {} and {}",
        t.mesh.triangles.len(),
        profile.engine.name(),
        if profile.ascii { "ASCII" } else { "binary" },
        profile.units.symbol(),
        t.grid.rows,
        t.grid.cols,
        if t.stride > 1 {
            format!(", {0} x {0} samples averaged to fit {1} triangles", t.stride, profile.max_triangles)
        } else {
            String::new()
        },
        t.quality.min_angle_deg,
        a.out.display(),
        json_path.display()
    );
}

/// `mesh` writes STL: an output named otherwise (`-o k.obj`) is refused, not filled with STL
/// (the mesher's own rule, [`check_stl_path`]).
pub(super) fn check_stl_name(out: &Path) -> Result<()> {
    check_stl_path(out).map_err(|e| anyhow!(e))
}

/// The measured roughness that judges the roughness the mesh carries: the same grid as the
/// meshed map (its values relative to their mean, as the heights are).
fn roughness_reference(path: &Path, pitch_um: Option<f64>, shape: Shape) -> Result<Vec<f32>> {
    let r = super::load_surface(path, pitch_um, "mesh", true)?.surface;
    if (r.height, r.width) != (shape.rows, shape.cols) {
        bail!(
            "{}: --roughness is {} x {} px (rows x cols); the meshed map is {shape}: expected the \
             same grid",
            path.display(),
            r.height,
            r.width
        );
    }
    Ok(to_frame_heights(&r.heights_um).1)
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;
    use surfstream_core::raster::RasterView;
    use surfstream_mesher::{
        check_closed, mesh_height_field, mesh_to_tolerance, write_stl_ascii, write_stl_binary,
        ScanPlacement,
    };

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        mesh: MeshArgs,
    }

    fn args(npy: &Path, stl: &Path, extra: &[&str]) -> MeshArgs {
        let (npy, stl) = (npy.to_str().unwrap(), stl.to_str().unwrap());
        let mut all = vec!["mesh", npy, "-o", stl];
        all.extend_from_slice(extra);
        Cli::try_parse_from(all).unwrap().mesh
    }

    /// A wavy 90 x 120 map with a deterministic roughness, one sample not measured, 0.5 x
    /// 0.6 um pitch, about 40 um up (the verb meshes it about its mean).
    fn wavy_npy(dir: &Path) -> PathBuf {
        let (rows, cols) = (90, 120);
        let mut h: Vec<f64> = (0..rows * cols)
            .map(|k| {
                let (y, x) = ((k / cols) as f64, (k % cols) as f64);
                let noise = ((k * 7919 % 1009) as f64 / 1009.0 - 0.5) * 0.05;
                40.0 + (x / 9.0).sin() + 0.5 * (y / 13.0).cos() + noise
            })
            .collect();
        h[17 * cols + 33] = f64::NAN;
        let npy = dir.join("wavy.npy");
        surfstream_io::npy::write_npy_f64(&npy, &h, rows, cols).unwrap();
        let geometry = surfstream_io::sidecar::NpyGeometry {
            pitch_x_um: 0.5,
            pitch_y_um: 0.6,
            origin_um: None,
        };
        surfstream_io::sidecar::write_sidecar(&npy, &geometry).unwrap();
        npy
    }

    /// The fusion's tile placements beside NAME.npy (or given) put Table 6's tile regions
    /// among the regions the tolerance judges; `--no-tiles` leaves them out; placements of
    /// another grid are refused when given and passed over (said) when found beside.
    #[test]
    fn the_tile_placements_beside_a_panorama_are_judged_too() {
        let d = tempfile::tempdir().unwrap();
        let npy = wavy_npy(d.path());
        let placements = |width_px: usize| surfstream_core::record::PanoramaTiles {
            panorama: surfstream_core::record::PanoramaSummary {
                width_px,
                height_px: 90,
                origin_x_um: 10.0,
                origin_y_um: 20.0,
                pitch_x_um: 0.5,
                pitch_y_um: 0.6,
                z_offset_um: 0.0,
                invalid_px: 1,
            },
            tiles: [(0, 10.0), (1, 35.0)]
                .map(|(index, x_um)| surfstream_core::record::PlacedTile {
                    index,
                    x_um,
                    y_um: 20.0,
                    width_px: 70,
                    height_px: 90,
                })
                .to_vec(),
        };
        let write = |path: &Path, width_px: usize| {
            std::fs::write(path, serde_json::to_string(&placements(width_px)).unwrap()).unwrap()
        };
        let beside = d.path().join("wavy.tiles.json");
        write(&beside, 120);
        let stl = d.path().join("out/wall.stl");
        let pitch = surfstream_core::Pitch::new(0.5, 0.6).unwrap();
        let shape = Shape::new(90, 120);
        let found = tile_footprints_of(&args(&npy, &stl, &[]), shape, pitch).unwrap();
        let spans: Vec<(usize, usize)> = found.iter().map(|w| (w.col0, w.cols)).collect();
        assert_eq!(spans, [(0, 70), (50, 70)], "{found:?}");
        assert!(
            found.iter().all(|w| (w.row0, w.rows) == (0, 90)),
            "{found:?}"
        );
        let off = tile_footprints_of(&args(&npy, &stl, &["--no-tiles"]), shape, pitch).unwrap();
        assert!(off.is_empty());
        // The verb end to end: the record says how many footprints were judged.
        run(args(&npy, &stl, &["--tolerance", "sa=1,sq=1,sz=3"])).unwrap();
        let record: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(stl.with_extension("json")).unwrap())
                .unwrap();
        assert_eq!(
            record["tolerance"]["footprints"], 2,
            "{}",
            record["tolerance"]
        );
        // Another grid: refused when given, passed over when found beside.
        let other = d.path().join("other.tiles.json");
        write(&other, 121);
        let given = other.to_str().unwrap();
        let e = tile_footprints_of(&args(&npy, &stl, &["--tiles", given]), shape, pitch)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("other.tiles.json") && e.contains("expected the placements"),
            "{e}"
        );
        write(&beside, 121);
        assert!(tile_footprints_of(&args(&npy, &stl, &[]), shape, pitch)
            .unwrap()
            .is_empty());
    }

    /// The verb meshes through the streamed mesher; the in-memory mesher, run on the same
    /// prepared heights, is the oracle: the same STL bytes and the same statistics, and the
    /// spill file leaves nothing beside the STL.
    #[test]
    fn the_verb_writes_what_the_in_memory_mesher_writes() {
        let d = tempfile::tempdir().unwrap();
        let npy = wavy_npy(d.path());
        let cases: [&[&str]; 3] = [
            &[],
            &[
                "--epsilon-um",
                "0.05",
                "--sheet",
                "--ascii",
                "--units",
                "um",
            ],
            &[
                "--tolerance",
                "sa=0.5,sq=0.5,sz=2",
                "--model-method",
                "greedy",
            ],
        ];
        for (k, extra) in cases.into_iter().enumerate() {
            let out = d.path().join(format!("case{k}/wall.stl"));
            run(args(&npy, &out, extra)).unwrap();

            let a = args(&npy, &out, extra);
            let (surface, p) = prepared_heights(&a).unwrap();
            let heights = RasterView::new(&p.heights_um, p.shape).unwrap();
            let pitch =
                surfstream_core::Pitch::new(surface.pitch_x_um, surface.pitch_y_um).unwrap();
            let at = ScanPlacement::new(pitch).with_z_offset(p.z_offset_um);
            let settings = config(&a).settings().unwrap();
            let params = settings.adaptive.clone().unwrap();
            let m = match settings.tolerance {
                Some(s) => {
                    mesh_to_tolerance(heights, None, &at, &params, &s, &[])
                        .unwrap()
                        .0
                }
                None => mesh_height_field(heights, &at, &params).unwrap(),
            };
            let mut want = Vec::new();
            if a.ascii {
                write_stl_ascii(&mut want, &m.mesh, "surfstream mesh").unwrap();
            } else {
                write_stl_binary(&mut want, &m.mesh, "surfstream mesh").unwrap();
            }
            assert!(
                std::fs::read(&out).unwrap() == want,
                "case {extra:?}: STL bytes differ"
            );

            let json: serde_json::Value =
                serde_json::from_slice(&std::fs::read(out.with_extension("json")).unwrap())
                    .unwrap();
            let oracle = m.summary().unwrap();
            for key in [
                "triangles",
                "vertices",
                "surface_triangles",
                "fidelity",
                "offset_um",
            ] {
                assert_eq!(json[key], oracle[key], "case {extra:?}: {key}");
            }
            assert_eq!(json["watertight"], check_closed(&m.mesh).watertight);
            let mut files: Vec<String> = std::fs::read_dir(out.parent().unwrap())
                .unwrap()
                .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .collect();
            files.sort();
            assert_eq!(files, ["wall.json", "wall.stl"], "case {extra:?}");
        }
    }
}
