//! The adaptive mesher in bounded memory (issue 17): the same mesh, STL bytes and statistics
//! as [`crate::mesh_height_field`] followed by [`crate::write_stl_binary`] /
//! [`crate::write_stl_ascii`] and [`crate::check_closed`], without ever holding the whole
//! triangle list, the vertex list or an f64 copy of the mesh on the grid.
//!
//! Two passes ([`mesh_streaming`], then [`StreamedMesh::write_stl`]):
//! 1. The blocks of the triangulation ([`crate::tin`]: shared sides simplified first, so every
//!    block meshes on its own) are meshed a few rows of blocks at a time, in parallel. Each
//!    block's kept triangles (three grid sample indices, 12 bytes) go to an unnamed spill file;
//!    the rows of blocks are painted onto the f32 mesh-on-grid raster (the error and Table 6);
//!    the used vertices are marked in a bitset (1 bit per sample) and their height range kept,
//!    which is all the vertex placement needs; and the edges are checked (below).
//! 2. Once the height range is known (the re-centring offset and the base depend on it), the
//!    spill file is read back in order and every triangle written with its vertices placed
//!    exactly as the in-memory mesher places them, then the walls and the base.
//!
//! The closed-solid check is done as triangles pass, exactly: an edge can only belong to the
//! triangles of blocks that hold both its ends. An edge that does not lie along a side of its
//! block belongs to that block alone, so each block settles its own edges; an edge along a side
//! is kept pending until every block (or wall) that can use it has been seen: the side between
//! two blocks of a band once the band is done, the row between two bands once the upper band
//! is done, the grid's rim once the walls are added. The pending edges are O(rows + cols).
//! Duplicate triangles across blocks would need three collinear corners on a shared side and
//! are checked among such triangles; coincident f32 vertices by the monotonic argument in
//! [`coincident_vertices`].
//!
//! What stays per sample: the input (4 B), the f32 mesh-on-grid raster (4 B), one bit, and
//! while the blocks are meshed the plan's filled copy when samples are missing (4 B); the
//! field's plane is fitted on the f32 field and the areal parameters are computed by rows
//! ([`crate::fidelity`]). A mesh keeps no filled copy: the writer fills the field again
//! ([`fill_missing`], the same bits as the plan's), so the meshes the tolerance search holds
//! (the best and the last failing one) hold nothing per sample but their raster, which the
//! search parks in a spill file ([`StreamedMesh::park`]).

use std::collections::HashSet;
use std::io::Write;
use std::path::Path;

use rayon::prelude::*;
use surfstream_core::raster::{RasterView, Shape};
use surfstream_core::store::{AppendLog, SpillFile};

use crate::adaptive::{adaptive_summary, Fidelity, MeshCounts, VertexPlacement};
use crate::check::MeshCheck;
use crate::error::{MeshError, Result};
use crate::fidelity::{level_field, FieldLevel};
use crate::field::fill_missing;
use crate::field::{validate, ScanPlacement};
use crate::geom;
use crate::solid::{close_top_surface, GridPlacement, SolidParams};
use crate::stl::StlSink;
use crate::tin::{grid_rim, on_row, paint_band, BlockPlan, BlockTin, ErrorStats, MissingSamples};
use crate::{MeshKind, MeshParams};

/// Rows of blocks meshed (in parallel) and painted (in parallel) at a time. Two keep both
/// cores busy; more only holds more triangles.
const BANDS_AT_ONCE: usize = 2;

/// Triangles read back from the spill file per step of the second pass.
const READ_TRIANGLES: usize = 1 << 15;

/// Sample indices (three per triangle) written to the spill file at a time: 1 MiB.
const SPILL_BATCH_VALUES: usize = 1 << 18;

/// The second pass's reads of `triangles` spilled triangles: (byte offset, triangles), in
/// order, [`READ_TRIANGLES`] at a time.
fn spill_steps(triangles: usize) -> impl Iterator<Item = (u64, usize)> {
    (0..triangles).step_by(READ_TRIANGLES).map(move |t| {
        let n = READ_TRIANGLES.min(triangles - t);
        ((t * 12) as u64, n)
    })
}

/// An edge as its two vertex keys (low, high) packed in a u128, and whether a triangle
/// traverses it low -> high. Top vertices are keyed by their grid sample, the walls' base
/// vertices by `BASE_KEY + k`.
type Edge = (u128, bool);
const BASE_KEY: u64 = 1 << 32;

/// The first pass of the streaming mesher: everything but the STL itself (see the module
/// docs).
pub struct StreamedMesh {
    /// The sizes run.json reports.
    pub counts: MeshCounts,
    /// The mesh re-sampled on the grid, um relative to the field's z offset (NaN: not covered):
    /// what [`crate::AdaptiveMesh::resampled_um`] holds.
    pub resampled_um: Vec<f32>,
    /// `resampled_um` while it waits in a spill file ([`StreamedMesh::park`]): its length.
    parked: Option<(SpillFile, usize)>,
    /// The statistics [`crate::AdaptiveMesh::record`] gives.
    pub summary: crate::adaptive::AdaptiveSummary,
    pub fidelity: Fidelity,
    /// The kept top triangles, three grid sample indices each, in order from offset 0.
    spill: AppendLog<u32>,
    place: VertexPlacement,
    /// The walls and base in local indices: the first `rim.len()` vertices are the rim's top
    /// vertices (grid samples `rim`), then its base vertices and the base's centre.
    walls: Option<Walls>,
    /// Edge and triangle checks settled in the first pass.
    topology: Topology,
    top_z_positive: bool,
}

/// The heights the full grid's vertices take (the input, with missing samples filled).
enum Filled {
    /// Nothing was missing: the input is borrowed again at write time (passed back in).
    Input,
    Owned(Vec<f32>),
}

struct Walls {
    rim: Vec<u32>,
    vertices: Vec<[f64; 3]>,
    triangles: Vec<[u32; 3]>,
}

#[derive(Default)]
struct Topology {
    boundary_edges: usize,
    non_manifold_edges: usize,
    misoriented_edges: usize,
    duplicate_triangles: usize,
    /// Edges along block sides not yet settled.
    pending: Vec<Edge>,
    /// Triangles with all three corners on one line of the grid (degenerate ones, which alone
    /// could repeat in two blocks), sorted corners.
    collinear: Vec<[u64; 3]>,
}

impl Topology {
    /// Counts every run of equal edges in `edges` (sorted) that `settled` accepts; the others
    /// are returned.
    fn settle(&mut self, edges: &mut Vec<Edge>, settled: impl Fn(u128) -> bool) {
        edges.par_sort_unstable();
        let mut keep = Vec::new();
        for run in edges.chunk_by(|x, y| x.0 == y.0) {
            if !settled(run[0].0) {
                keep.extend_from_slice(run);
                continue;
            }
            let c = classify(run);
            self.boundary_edges += c[0];
            self.non_manifold_edges += c[1];
            self.misoriented_edges += c[2];
        }
        *edges = keep;
    }
}

/// [boundary, non-manifold, misoriented] of one edge from all its uses (as
/// [`crate::check_closed`] counts them).
fn classify(run: &[Edge]) -> [usize; 3] {
    let forward = run.iter().filter(|e| e.1).count();
    let backward = run.len() - forward;
    [
        usize::from(run.len() == 1),
        usize::from(run.len() > 2),
        usize::from(forward > 1 || backward > 1),
    ]
}

fn edge(a: u64, b: u64) -> Option<Edge> {
    (a != b).then(|| {
        let (lo, hi) = (a.min(b), a.max(b));
        ((u128::from(lo) << 64) | u128::from(hi), a < b)
    })
}

fn ends(key: u128) -> (u64, u64) {
    ((key >> 64) as u64, key as u64)
}

/// What one block contributes, computed on the block's own thread.
struct BlockPart {
    triangles: Vec<[u32; 3]>,
    budget_reached: bool,
    all_kept: bool,
    /// [boundary, non-manifold, misoriented] of the edges inside the block.
    inner: [usize; 3],
    side_edges: Vec<Edge>,
    duplicates: usize,
    collinear: Vec<[u64; 3]>,
}

/// One bit per grid sample.
struct Bits(Vec<u64>);

impl Bits {
    fn new(n: usize) -> Self {
        Self(vec![0; n.div_ceil(64)])
    }
    fn set(&mut self, k: usize) {
        self.0[k / 64] |= 1 << (k % 64);
    }
    fn get(&self, k: usize) -> bool {
        self.0[k / 64] >> (k % 64) & 1 == 1
    }
    fn count(&self) -> usize {
        self.0.iter().map(|w| w.count_ones() as usize).sum()
    }
}

/// The first pass: meshes `heights` as [`crate::mesh_height_field`] does (same checks, same
/// errors), spilling the triangles to an unnamed file in `spill_dir`. Then write the STL with
/// [`StreamedMesh::write_stl`], passing the same `heights`.
pub fn mesh_streaming(
    heights: RasterView<'_, f32>,
    at: &ScanPlacement,
    params: &MeshParams,
    spill_dir: &Path,
) -> Result<StreamedMesh> {
    mesh_streaming_with(heights, at, params, spill_dir, false)
}

/// [`mesh_streaming`], optionally with every block's peak and valley kept as vertices
/// ([`TinParams::keep_extremes`]).
pub(crate) fn mesh_streaming_with(
    heights: RasterView<'_, f32>,
    at: &ScanPlacement,
    params: &MeshParams,
    spill_dir: &Path,
    keep_extremes: bool,
) -> Result<StreamedMesh> {
    crate::adaptive::check_adaptive(heights, at, params)?;
    // The field's plane and parameters, once (the in-memory mesher computes them twice, the
    // same way), by rows.
    let level = level_field(heights, at.pitch);
    let epsilon_um = params.epsilon_um(|| level.and_then(|l| l.params).map_or(0.0, |p| p.sq_um))?;
    let plan = BlockPlan::new(heights, &params.tin_params(epsilon_um, keep_extremes))?;
    stream_blocks(
        heights,
        at,
        params,
        spill_dir,
        &plan,
        level,
        epsilon_um,
        true,
        &|k| Ok(plan.mesh(k)),
    )
}

/// The level of the field, for [`stream_blocks`] (fitted on the f32 field, by rows).
pub(crate) fn field_level(heights: RasterView<'_, f32>, at: &ScanPlacement) -> Option<FieldLevel> {
    level_field(heights, at.pitch)
}

/// The first pass of the streaming mesher over the blocks of `plan`, each triangulated by
/// `mesh_block(k)` (the plan's own greedy insertion, or a snapshot of a block refined step by
/// step); `epsilon_um` is the bound they were made at, `level` the field's
/// ([`field_level`]). Without `mesh_fidelity` the mesh's areal parameters are left out
/// (`fidelity.mesh` is `None` until [`StreamedMesh::measure_mesh`]): the tolerance search
/// judges its checkpoints by regions and needs them only for the mesh it keeps (two passes over
/// the grid by rows).
#[allow(clippy::too_many_arguments)]
pub(crate) fn stream_blocks(
    heights: RasterView<'_, f32>,
    at: &ScanPlacement,
    params: &MeshParams,
    spill_dir: &Path,
    plan: &BlockPlan<'_>,
    level: Option<FieldLevel>,
    epsilon_um: f64,
    mesh_fidelity: bool,
    mesh_block: &(dyn Fn(usize) -> Result<BlockTin> + Sync),
) -> Result<StreamedMesh> {
    let shape = heights.shape();
    let (rows, cols) = (shape.rows, shape.cols);
    let (nbx, nby) = plan.blocks_x_y();
    let valid = plan.valid.as_deref();
    let filled: &[f32] = &plan.filled;
    let measured = heights.values();

    // Triangles go to the log in batches of about a megabyte (one write each).
    let mut spill = AppendLog::<u32>::new(Some(spill_dir.to_path_buf()));
    let mut batch: Vec<u32> = Vec::with_capacity(SPILL_BATCH_VALUES);
    let mut resampled_um = vec![f32::NAN; rows * cols];
    let mut used = Bits::new(rows * cols);
    let (mut min_um, mut max_um) = (f64::INFINITY, f64::NEG_INFINITY);
    let mut topology = Topology::default();
    let (mut top_triangles, mut all_kept, mut budget_reached) = (0usize, true, false);
    let mut band_errors = Vec::with_capacity(nby);
    // The triangles of the band below that touch its top row (painted first on that row).
    let mut below: Vec<[u32; 3]> = Vec::new();
    let mut rest: &mut [f32] = &mut resampled_um;
    for j0 in (0..nby).step_by(BANDS_AT_ONCE) {
        surfstream_core::liveness::beat();
        let j1 = (j0 + BANDS_AT_ONCE).min(nby);
        let parts: Vec<BlockPart> = (j0 * nbx..j1 * nbx)
            .into_par_iter()
            .map(|k| Ok(block_part(plan, k, mesh_block(k)?, valid)))
            .collect::<Result<_>>()?;
        // Bands in order: their triangles (block order) and rows.
        let mut bands = Vec::with_capacity(j1 - j0);
        let mut parts = parts.into_iter();
        for j in j0..j1 {
            let mut own = Vec::new();
            for mut p in parts.by_ref().take(nbx) {
                budget_reached |= p.budget_reached;
                all_kept &= p.all_kept;
                topology.boundary_edges += p.inner[0];
                topology.non_manifold_edges += p.inner[1];
                topology.misoriented_edges += p.inner[2];
                topology.duplicate_triangles += p.duplicates;
                topology.pending.extend_from_slice(&p.side_edges);
                topology.collinear.extend_from_slice(&p.collinear);
                for t in &p.triangles {
                    for &s in t {
                        let s = s as usize;
                        used.set(s);
                        let h = f64::from(filled[s]);
                        min_um = min_um.min(h);
                        max_um = max_um.max(h);
                    }
                    batch.extend_from_slice(t);
                    if batch.len() >= SPILL_BATCH_VALUES {
                        spill.append(&batch)?;
                        batch.clear();
                    }
                }
                top_triangles += p.triangles.len();
                own.append(&mut p.triangles);
            }
            let y0 = plan.ys[j];
            let end = if j + 1 == nby { rows } else { plan.ys[j + 1] };
            let (this, next) = std::mem::take(&mut rest).split_at_mut((end - y0) * cols);
            rest = next;
            bands.push((y0, own, this));
        }
        // Each band paints on top of what the band below left on their shared row.
        let mut belows = Vec::with_capacity(bands.len());
        belows.push(std::mem::take(&mut below));
        for b in 1..bands.len() {
            belows.push(on_row(&bands[b - 1].1, bands[b].0, cols));
        }
        let errors: Vec<ErrorStats> = bands
            .par_iter_mut()
            .zip(belows.par_iter())
            .map(|((y0, own, out), below)| paint_band(filled, measured, cols, *y0, below, own, out))
            .collect();
        band_errors.extend(errors);
        if let Some((_, own, _)) = bands.last() {
            if j1 < nby {
                below = on_row(own, plan.ys[j1], cols);
            }
        }
        // The side edges of these bands are settled unless they lie on the row the next band
        // shares or on the grid's rim (the walls come last).
        let open_row = (j1 < nby).then(|| plan.ys[j1]);
        let mut pending = std::mem::take(&mut topology.pending);
        topology.settle(&mut pending, |key| {
            !on_rim(key, shape) && open_row.is_none_or(|y| !on_grid_row(key, y, cols))
        });
        topology.pending = pending;
    }
    let error = ErrorStats::combine(&band_errors);
    if !batch.is_empty() {
        spill.append(&batch)?;
    }
    drop(batch);

    if top_triangles == 0 {
        return Err(MeshError::Incompatible(
            "no triangle has three measured corners: nothing to mesh".into(),
        ));
    }
    let place = VertexPlacement::new(params, at, shape, min_um, max_um);
    let walls = if params.kind == MeshKind::Solid {
        Some(solid_walls(all_kept, &used, shape, &place, filled)?)
    } else {
        None
    };
    // The walls settle the rim; everything still pending is final now.
    let mut pending = std::mem::take(&mut topology.pending);
    if let Some(w) = &walls {
        add_walls(w, &mut pending, &mut topology);
    }
    topology.settle(&mut pending, |_| true);
    let mut collinear = std::mem::take(&mut topology.collinear);
    collinear.sort_unstable();
    topology.duplicate_triangles += collinear.windows(2).filter(|p| p[0] == p[1]).count();

    let wall_vertices = walls.as_ref().map_or(0, |w| w.vertices.len());
    let counts = MeshCounts {
        units: params.solid.units,
        offset_um: place.offset_um(),
        triangles: top_triangles + walls.as_ref().map_or(0, |w| w.triangles.len()),
        top_triangles,
        vertices: used.count() + wall_vertices - walls.as_ref().map_or(0, |w| w.rim.len()),
        filled_samples: if params.missing == MissingSamples::Fill {
            plan.missing_samples
        } else {
            0
        },
        base_depth_um: place.base_depth_um,
    };
    if counts.triangles > u32::MAX as usize {
        return Err(MeshError::TooLarge {
            what: "triangles",
            count: counts.triangles,
            limit: u32::MAX as usize,
        });
    }
    let fidelity = Fidelity {
        epsilon_um,
        error,
        bound_met: error.max_um <= epsilon_um,
        field: level.and_then(|l| l.params),
        mesh: level
            .filter(|_| mesh_fidelity)
            .and_then(|l| l.mesh_params_at_measured(&resampled_um, heights.values())),
    };
    let summary = adaptive_summary(
        params.kind,
        &counts,
        plan.missing_samples,
        params.missing,
        budget_reached,
        &fidelity,
    )?;
    let top_z_positive = place.vertex(0, min_um as f32)[2] as f32 > place.base_z() as f32;
    // Only the used samples' bits were needed; the spill and the walls carry the rest.
    drop(used);
    Ok(StreamedMesh {
        counts,
        resampled_um,
        parked: None,
        summary,
        fidelity,
        spill,
        place,
        walls,
        topology,
        top_z_positive,
    })
}

/// The side walls and base that close the top surface into a solid, along the rim of the
/// samples the top uses; refused when the top does not reach the whole rim (`all_kept`).
fn solid_walls(
    all_kept: bool,
    used: &Bits,
    shape: Shape,
    place: &VertexPlacement,
    filled: &[f32],
) -> Result<Walls> {
    if !all_kept {
        return Err(MeshError::Incompatible(
            "the mesh's top does not reach the whole rim of the grid; cannot close it".into(),
        ));
    }
    let rim = grid_rim(|s| used.get(s), shape);
    let mut vertices: Vec<[f64; 3]> = rim
        .iter()
        .map(|&s| place.vertex(s as usize, filled[s as usize]))
        .collect();
    let boundary: Vec<u32> = (0..rim.len() as u32).collect();
    let mut triangles = Vec::new();
    close_top_surface(&mut vertices, &mut triangles, &boundary, place.base_z())?;
    Ok(Walls {
        rim,
        vertices,
        triangles,
    })
}

/// Meshes block `k` and settles what it can on its own thread.
fn block_part(plan: &BlockPlan<'_>, k: usize, bt: BlockTin, valid: Option<&[bool]>) -> BlockPart {
    let kept = bt.kept(valid);
    let (block, _) = plan.block(k);
    let cols = plan.cols;
    let side = |s: u64| {
        let (x, y) = ((s as usize) % cols, (s as usize) / cols);
        [
            (y == block.y0) as u8,
            (x == block.x1) as u8,
            (y == block.y1) as u8,
            (x == block.x0) as u8,
        ]
    };
    let along_side = |a: u64, b: u64| {
        let (sa, sb) = (side(a), side(b));
        (0..4).any(|i| sa[i] == 1 && sb[i] == 1)
    };
    let mut edges: Vec<Edge> = kept
        .triangles
        .iter()
        .flat_map(|t| (0..3).filter_map(move |k| edge(u64::from(t[k]), u64::from(t[(k + 1) % 3]))))
        .collect();
    edges.sort_unstable();
    let (mut inner, mut side_edges) = ([0usize; 3], Vec::new());
    for run in edges.chunk_by(|x, y| x.0 == y.0) {
        let (a, b) = ends(run[0].0);
        if along_side(a, b) {
            side_edges.extend_from_slice(run);
        } else {
            let c = classify(run);
            for i in 0..3 {
                inner[i] += c[i];
            }
        }
    }
    let mut sorted: Vec<[u64; 3]> = kept
        .triangles
        .iter()
        .map(|t| {
            let mut s = t.map(u64::from);
            s.sort_unstable();
            s
        })
        .collect();
    sorted.sort_unstable();
    let duplicates = sorted.windows(2).filter(|p| p[0] == p[1]).count();
    let mut collinear: Vec<[u64; 3]> = sorted
        .into_iter()
        .filter(|s| {
            let c = s.map(|v| ((v as usize % cols) as i64, (v as usize / cols) as i64));
            (c[1].0 - c[0].0) * (c[2].1 - c[0].1) == (c[1].1 - c[0].1) * (c[2].0 - c[0].0)
        })
        .collect();
    // Repeats inside the block are counted above; across blocks they are counted once more.
    collinear.dedup();
    BlockPart {
        triangles: kept.triangles,
        budget_reached: bt.budget_reached,
        all_kept: kept.all_kept,
        inner,
        side_edges,
        duplicates,
        collinear,
    }
}

/// Both ends of the edge on the same side of the grid's rectangle.
fn on_rim(key: u128, shape: Shape) -> bool {
    let (a, b) = ends(key);
    if a >= BASE_KEY || b >= BASE_KEY {
        return true;
    }
    let c = shape.cols as u64;
    let (xa, ya, xb, yb) = (a % c, a / c, b % c, b / c);
    let (w, h) = (c - 1, shape.rows as u64 - 1);
    (ya == yb && (ya == 0 || ya == h)) || (xa == xb && (xa == 0 || xa == w))
}

/// Both ends of the edge on grid row `y`.
fn on_grid_row(key: u128, y: usize, cols: usize) -> bool {
    let (a, b) = ends(key);
    let c = cols as u64;
    a / c == y as u64 && b / c == y as u64
}

impl StreamedMesh {
    /// Moves the mesh on the grid (4 B per sample) to an unnamed spill file in `spill_dir`
    /// and frees it: the tolerance search keeps its best mesh while it makes the next one.
    /// [`StreamedMesh::unpark`] reads it back, the same bits.
    pub(crate) fn park(&mut self, spill_dir: &Path) -> Result<()> {
        if self.parked.is_some() {
            return Ok(());
        }
        let mut file = SpillFile::new(Some(spill_dir.to_path_buf()));
        for (k, part) in self.resampled_um.chunks(SPILL_BATCH_VALUES).enumerate() {
            // GBs to a busy disk at 20 x 20: alive between batches.
            surfstream_core::liveness::beat();
            let at = (k * SPILL_BATCH_VALUES * 4) as u64;
            file.write_at(at, &surfstream_core::store::encode(part))?;
        }
        self.parked = Some((file, self.resampled_um.len()));
        self.resampled_um = Vec::new();
        Ok(())
    }

    /// The mesh on the grid back in memory after [`StreamedMesh::park`].
    pub(crate) fn unpark(&mut self) -> Result<()> {
        let Some((file, len)) = self.parked.take() else {
            return Ok(());
        };
        let mut values = Vec::with_capacity(len);
        for at in (0..len).step_by(SPILL_BATCH_VALUES) {
            surfstream_core::liveness::beat();
            let n = SPILL_BATCH_VALUES.min(len - at);
            values.extend(file.read_values::<f32>((at * 4) as u64, n)?);
        }
        self.resampled_um = values;
        Ok(())
    }

    /// The mesh's areal parameters at the measured samples of `measured` (the field), levelled
    /// by the field's plane `level`, when [`stream_blocks`] left them out.
    pub(crate) fn measure_mesh(&mut self, level: Option<FieldLevel>, measured: &[f32]) {
        self.fidelity.mesh =
            level.and_then(|l| l.mesh_params_at_measured(&self.resampled_um, measured));
        self.summary.record.fidelity = (&self.fidelity).into();
    }

    /// The second pass: writes the STL (binary or `ascii`) from the spill file, the same bytes
    /// as the in-memory writers give for [`crate::mesh_height_field`]'s mesh, and returns the
    /// closed-solid check of what was written. `heights` must be the field given to
    /// [`mesh_streaming`].
    pub fn write_stl(
        &mut self,
        w: &mut dyn Write,
        ascii: bool,
        header_text: &str,
        heights: RasterView<'_, f32>,
    ) -> Result<MeshCheck> {
        // The heights the vertices take, filled again as the plan filled them (the same
        // samples, the same bits): a mesh does not keep a filled copy of the field while the
        // tolerance search holds it (two of them, beside the search's own).
        let (filled, _) = fill_missing(heights)?;
        same_samples(&filled, self.resampled_um.len())?;
        let filled: &[f32] = &filled;
        let place = &self.place;
        let spill = &self.spill;
        let mut steps = spill_steps(self.counts.top_triangles);
        let (degenerate, volume6) = write_solid(
            w,
            ascii,
            header_text,
            &self.counts,
            || {
                let Some((offset, n)) = steps.next() else {
                    return Ok(None);
                };
                let samples = spill.read(offset, 3 * n)?;
                Ok(Some(
                    samples
                        .par_chunks_exact(3)
                        .map(|r| {
                            let t = [r[0], r[1], r[2]];
                            (t.map(|s| place.vertex(s as usize, filled[s as usize])), t)
                        })
                        .collect(),
                ))
            },
            self.walls.as_ref(),
        )?;
        let coincident = self.coincident_vertices(heights.shape(), filled);
        Ok(self.topology.check(degenerate, volume6, coincident))
    }

    /// Vertices equal once rounded to f32: see the free function [`coincident_vertices`].
    fn coincident_vertices(&self, shape: Shape, filled: &[f32]) -> usize {
        let base: Vec<[f64; 3]> = self
            .walls
            .as_ref()
            .map_or(Vec::new(), |w| w.vertices[w.rim.len()..].to_vec());
        coincident_vertices(
            shape,
            |s| self.place.vertex(s, 0.0),
            self.top_z_positive,
            &base,
            |visit| {
                // Every used vertex: the samples the spill file names.
                let mut seen: HashSet<u32> = HashSet::new();
                for (offset, n) in spill_steps(self.counts.top_triangles) {
                    let Ok(samples) = self.spill.read(offset, 3 * n) else {
                        break;
                    };
                    for s in samples {
                        if seen.insert(s) {
                            visit(self.place.vertex(s as usize, filled[s as usize]));
                        }
                    }
                }
            },
        )
    }
}

/// Vertices equal once rounded to f32 (as [`crate::check_closed`] counts them). Rounding is
/// monotonic and a top vertex's x depends on its column alone, y on its row (`at_height_0` of
/// sample s): when the columns' f32 x are all distinct and so are the rows' f32 y, no two top
/// vertices coincide; when the lowest top vertex is above the base also in f32
/// (`top_z_positive`), no top vertex meets a base vertex, so only the base's own vertices
/// remain to compare. Otherwise (far from the origin without re-centring) every top vertex is
/// hashed (`each_top` visits them once each), which costs memory per vertex.
fn coincident_vertices(
    shape: Shape,
    at_height_0: impl Fn(usize) -> [f64; 3],
    top_z_positive: bool,
    base: &[[f64; 3]],
    each_top: impl FnOnce(&mut dyn FnMut([f64; 3])),
) -> usize {
    let key = |v: [f64; 3]| v.map(|c| (c as f32 + 0.0).to_bits());
    let distinct = |values: Vec<u32>| values.windows(2).all(|p| p[0] != p[1]);
    let xs = (0..shape.cols).map(|j| key(at_height_0(j))[0]).collect();
    let ys = (0..shape.rows)
        .map(|i| key(at_height_0(i * shape.cols))[1])
        .collect();
    let mut set: HashSet<[u32; 3]> = base.iter().map(|&v| key(v)).collect();
    let mut count = base.len();
    if !(distinct(xs) && distinct(ys) && top_z_positive) {
        each_top(&mut |v| {
            count += 1;
            set.insert(key(v));
        });
    }
    count - set.len()
}

/// The full-grid solid ([`crate::grid_solid`]) streamed: the same STL bytes and check, with
/// nothing per sample held but the input (and its filled copy when samples are missing). The
/// triangles are generated again while writing; the check runs in groups of cell rows (edges
/// along the row a group shares with the next, and along the rim, wait).
pub struct StreamedGrid {
    pub counts: MeshCounts,
    place: GridPlacement,
    filled: Filled,
    walls: Walls,
    topology: Topology,
    shape: Shape,
    top_z_positive: bool,
}

/// Cells per group of cell rows in the grid's edge check (about 25 MB of edges).
const GRID_CHECK_CELLS: usize = 1 << 18;

/// The two triangles of cell (row `i`, column `j`) as sample indices, as [`crate::grid_solid`]
/// makes them.
#[inline]
fn cell_triangles(i: usize, j: usize, cols: usize) -> [[u32; 3]; 2] {
    let v00 = (i * cols + j) as u32;
    let (v01, v10) = (v00 + 1, v00 + cols as u32);
    let v11 = v10 + 1;
    [[v00, v01, v11], [v00, v11, v10]]
}

/// The first pass of the streamed grid solid: counts, placement, walls and the edge check
/// (errors as [`crate::grid_solid`]). Then [`StreamedGrid::write_stl`] with the same heights.
pub fn grid_streaming(
    heights: RasterView<'_, f32>,
    at: &ScanPlacement,
    params: &SolidParams,
) -> Result<StreamedGrid> {
    validate(heights, at)?;
    params.validate()?;
    let shape = heights.shape();
    let (rows, cols) = (shape.rows, shape.cols);
    let (filled, filled_samples) = fill_missing(heights)?;
    let place = GridPlacement::new(&filled, at, params, shape)?;
    let (_, vertex_count, top_triangles, triangle_count) = place.counts();
    let rim = place.boundary();
    let mut vertices: Vec<[f64; 3]> = rim
        .iter()
        .map(|&s| {
            let s = s as usize;
            place.place(s / cols, s % cols, filled[s])
        })
        .collect();
    let local: Vec<u32> = (0..rim.len() as u32).collect();
    let mut triangles = Vec::new();
    close_top_surface(
        &mut vertices,
        &mut triangles,
        &local,
        place.base_z_um / params.units.um_per_unit(),
    )?;
    let walls = Walls {
        rim,
        vertices,
        triangles,
    };

    let mut topology = Topology::default();
    let group = (GRID_CHECK_CELLS / cols).max(1);
    for r0 in (0..rows - 1).step_by(group) {
        surfstream_core::liveness::beat();
        let r1 = (r0 + group).min(rows - 1);
        let mut edges: Vec<Edge> = std::mem::take(&mut topology.pending);
        let mut sorted = Vec::with_capacity((r1 - r0) * (cols - 1) * 2);
        for i in r0..r1 {
            for j in 0..cols - 1 {
                for t in cell_triangles(i, j, cols) {
                    for k in 0..3 {
                        edges.extend(edge(u64::from(t[k]), u64::from(t[(k + 1) % 3])));
                    }
                    let mut s = t;
                    s.sort_unstable();
                    sorted.push(s);
                }
            }
        }
        // A triangle spans two rows of samples, so it repeats only inside its own group.
        sorted.par_sort_unstable();
        topology.duplicate_triangles += sorted.windows(2).filter(|p| p[0] == p[1]).count();
        let open_row = (r1 < rows - 1).then_some(r1);
        topology.settle(&mut edges, |key| {
            !on_rim(key, shape) && open_row.is_none_or(|y| !on_grid_row(key, y, cols))
        });
        topology.pending = edges;
    }
    let mut pending = std::mem::take(&mut topology.pending);
    add_walls(&walls, &mut pending, &mut topology);
    topology.settle(&mut pending, |_| true);

    let counts = MeshCounts {
        units: params.units,
        offset_um: place.offset_um,
        triangles: triangle_count,
        top_triangles,
        vertices: vertex_count,
        filled_samples,
        base_depth_um: place.base_depth_um,
    };
    let lowest = place.place(0, 0, place_min(&filled))[2] as f32;
    let top_z_positive = lowest > (place.base_z_um / params.units.um_per_unit()) as f32;
    let filled = match filled {
        std::borrow::Cow::Borrowed(_) => Filled::Input,
        std::borrow::Cow::Owned(v) => Filled::Owned(v),
    };
    Ok(StreamedGrid {
        counts,
        place,
        filled,
        walls,
        topology,
        shape,
        top_z_positive,
    })
}

/// The lowest height (um) of the filled samples.
fn place_min(filled: &[f32]) -> f32 {
    filled
        .par_iter()
        .copied()
        .reduce(|| f32::INFINITY, f32::min)
}

/// The walls' edges (keyed as the top's) into `pending`, their duplicates into `topology`.
fn add_walls(w: &Walls, pending: &mut Vec<Edge>, topology: &mut Topology) {
    let n = w.rim.len();
    let key = |v: u32| -> u64 {
        let v = v as usize;
        if v < n {
            u64::from(w.rim[v])
        } else {
            BASE_KEY + (v - n) as u64
        }
    };
    let mut sorted = Vec::with_capacity(w.triangles.len());
    for t in &w.triangles {
        for k in 0..3 {
            pending.extend(edge(key(t[k]), key(t[(k + 1) % 3])));
        }
        let mut s = t.map(key);
        s.sort_unstable();
        sorted.push(s);
    }
    sorted.sort_unstable();
    topology.duplicate_triangles += sorted.windows(2).filter(|p| p[0] == p[1]).count();
}

impl Topology {
    fn check(&self, degenerate: usize, volume6: f64, coincident: usize) -> MeshCheck {
        let edges_ok =
            self.boundary_edges == 0 && self.non_manifold_edges == 0 && self.misoriented_edges == 0;
        MeshCheck {
            watertight: edges_ok,
            consistently_oriented: self.misoriented_edges == 0,
            signed_volume: volume6 / 6.0,
            degenerate_triangles: degenerate,
            duplicate_triangles: self.duplicate_triangles,
            boundary_edges: self.boundary_edges,
            non_manifold_edges: self.non_manifold_edges,
            misoriented_edges: self.misoriented_edges,
            coincident_vertices_f32: coincident,
        }
    }
}

impl StreamedGrid {
    /// Writes the STL (binary or `ascii`): the same bytes as the in-memory writers give for
    /// [`crate::grid_solid`]'s mesh; returns the check. `heights` must be the field given to
    /// [`grid_streaming`].
    pub fn write_stl(
        &self,
        w: &mut dyn Write,
        ascii: bool,
        header_text: &str,
        heights: RasterView<'_, f32>,
    ) -> Result<MeshCheck> {
        let (rows, cols) = (self.shape.rows, self.shape.cols);
        let filled = self.filled.heights(heights, rows * cols)?;
        let g = &self.place;
        let vertex = |s: u32| {
            let s = s as usize;
            g.place(s / cols, s % cols, filled[s])
        };
        let mut cell_rows = 0..rows - 1;
        let (degenerate, volume6) = write_solid(
            w,
            ascii,
            header_text,
            &self.counts,
            || {
                Ok(cell_rows.next().map(|i| {
                    (0..cols - 1)
                        .into_par_iter()
                        .flat_map_iter(|j| cell_triangles(i, j, cols).map(|t| (t.map(vertex), t)))
                        .collect()
                }))
            },
            Some(&self.walls),
        )?;
        let base = &self.walls.vertices[self.walls.rim.len()..];
        let coincident = coincident_vertices(
            self.shape,
            |s| g.place(s / cols, s % cols, 0.0),
            self.top_z_positive,
            base,
            |visit| {
                for (s, &h) in filled.iter().enumerate() {
                    visit(g.place(s / cols, s % cols, h));
                }
            },
        );
        Ok(self.topology.check(degenerate, volume6, coincident))
    }
}

impl Filled {
    /// The heights the vertices take, given the input `heights` passed back to the writer;
    /// refused when their count is not the `samples` the mesh was made from.
    fn heights<'a>(&'a self, heights: RasterView<'a, f32>, samples: usize) -> Result<&'a [f32]> {
        let filled: &[f32] = match self {
            Filled::Input => heights.values(),
            Filled::Owned(v) => v,
        };
        same_samples(filled, samples)?;
        Ok(filled)
    }
}

/// Refuses a height field handed to a writer whose sample count is not the `samples` the
/// mesh was made from.
fn same_samples(filled: &[f32], samples: usize) -> Result<()> {
    if filled.len() != samples {
        return Err(MeshError::Incompatible(format!(
            "write_stl: the height field has {} samples, the mesh was made from {samples}",
            filled.len()
        )));
    }
    Ok(())
}

/// One streamed solid's top triangles in groups: placed corners and sample indices.
type PlacedTriangles = Vec<([[f64; 3]; 3], [u32; 3])>;

/// The second pass of both streamed solids: the STL (binary or `ascii`) of the top's triangles
/// as `next_top` hands them over, group by group, then the walls and the base; returns the
/// degenerate triangles and six times the signed volume (as [`crate::check_closed`] counts
/// them).
fn write_solid(
    w: &mut dyn Write,
    ascii: bool,
    header_text: &str,
    counts: &MeshCounts,
    mut next_top: impl FnMut() -> Result<Option<PlacedTriangles>>,
    walls: Option<&Walls>,
) -> Result<(usize, f64)> {
    let mut out = StlSink::new(
        w,
        ascii,
        counts.units,
        counts.offset_um,
        header_text,
        counts.triangles as u32,
    )?;
    let (mut degenerate, mut volume6) = (0usize, 0.0f64);
    let mut write = |corners: &PlacedTriangles| -> Result<()> {
        let (d, v) = shape_terms(corners);
        degenerate += d;
        volume6 += v;
        for (c, _) in corners {
            out.push(*c)?;
        }
        Ok(())
    };
    while let Some(corners) = next_top()? {
        surfstream_core::liveness::beat();
        write(&corners)?;
    }
    if let Some(walls) = walls {
        let corners: PlacedTriangles = walls
            .triangles
            .iter()
            .map(|t| (t.map(|v| walls.vertices[v as usize]), *t))
            .collect();
        write(&corners)?;
    }
    out.finish()?;
    Ok((degenerate, volume6))
}

/// Degenerate triangles and six times the signed volume of `triangles` (as
/// [`crate::check_closed`] computes them).
fn shape_terms(triangles: &[([[f64; 3]; 3], [u32; 3])]) -> (usize, f64) {
    let per: Vec<(usize, f64)> = triangles
        .par_iter()
        .map(|([a, b, c], t)| {
            if t[0] == t[1] || t[1] == t[2] || t[0] == t[2] {
                return (1, 0.0);
            }
            let area2 = geom::area_vector2(*a, *b, *c);
            let longest2 = [geom::sub(*b, *a), geom::sub(*c, *b), geom::sub(*a, *c)]
                .iter()
                .map(|e| geom::dot(*e, *e))
                .fold(0.0, f64::max);
            let degenerate = geom::dot(area2, area2).sqrt() <= 1e-12 * longest2;
            (usize::from(degenerate), geom::dot(*a, geom::cross(*b, *c)))
        })
        .collect();
    per.iter()
        .fold((0, 0.0), |acc, p| (acc.0 + p.0, acc.1 + p.1))
}
