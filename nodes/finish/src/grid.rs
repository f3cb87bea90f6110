//! The patch of the model that is simulated, its mesh, and the way wear found on the mesh comes
//! back to the model's grid.
//!
//! The patch is a centred window of the model with a guard band of real neighbouring surface
//! around it; the guard band is meshed and worn like the rest, then cropped. Why not periodic
//! mirroring: a mirrored seam is an artificial ridge or valley that a millimetre medium would
//! sit on, and a 3 mm sphere spans the whole sub-millimetre patch, so periodic images of it
//! would touch the part at once; the band keeps the mesh's open edges (where LIGGGHTS' edge
//! contacts differ from a continuing surface) away from the evaluated patch.
//!
//! Wear to grid: LIGGGHTS reports each triangle's wear depth along its normal; depth x area is
//! the volume removed. Each triangle's volume goes in thirds to its three corners, which are
//! nodes of the (block-averaged) meshed grid; each node's volume is spread evenly over the
//! model samples of its block. Depth along z is volume / sample area, which is the normal wear
//! divided by cos(slope) on average over a triangle, and the total volume is kept exactly.

use anyhow::{bail, Result};
use surfstream_core::metrology::{level_plane, Grid};
use surfstream_core::raster::{RasterView, Shape};
use surfstream_core::{Pitch, Sampling};
use surfstream_mesher::{fill_missing, grid_sheet_for, EngineProfile, ScanPlacement, TargetMesh};

/// A rectangle of samples.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub struct Window {
    pub row0: usize,
    pub col0: usize,
    pub rows: usize,
    pub cols: usize,
}

/// The simulated area: the patch and its guard band, levelled, without missing samples.
#[derive(Debug, Clone)]
pub struct Patch {
    /// Heights of patch + guard band, um, row-major, sampled as `sampling` says.
    pub heights_um: Vec<f64>,
    /// The meshed area's shape and the model's pitch (origin 0: patch coordinates).
    pub sampling: Sampling,
    /// Where the meshed area sits in the model.
    pub in_model: Window,
    /// The evaluated patch inside the meshed area (the guard band cropped).
    pub crop: Window,
    /// Missing samples filled before meshing.
    pub filled_samples: usize,
}

impl Patch {
    /// Cuts the patch of `width_um x height_um` centred in the model (sampled as `model`
    /// says), with `guard_um` of neighbouring surface around it where the model has it,
    /// fills missing samples and levels the whole by its least-squares plane (the part's form
    /// tilt is not the media's business; the media act along the local normal).
    pub fn cut(
        model_um: &[f64],
        model: Sampling,
        width_um: f64,
        height_um: f64,
        guard_um: f64,
    ) -> Result<Patch> {
        let (rows, cols) = (model.rows(), model.cols());
        let (pitch_x_um, pitch_y_um) = (model.pitch_x_um(), model.pitch_y_um());
        if rows * cols != model_um.len() || rows < 4 || cols < 4 {
            bail!(
                "model of {} samples is not {rows} x {cols} (rows x cols, at least 4 x 4)",
                model_um.len()
            );
        }
        if !(width_um > 0.0 && height_um > 0.0 && guard_um >= 0.0) {
            bail!("patch {width_um} x {height_um} um, guard {guard_um} um: expected sizes > 0");
        }
        let pc = ((width_um / pitch_x_um).round() as usize).clamp(4, cols);
        let pr = ((height_um / pitch_y_um).round() as usize).clamp(4, rows);
        let gc = (guard_um / pitch_x_um).round() as usize;
        let gr = (guard_um / pitch_y_um).round() as usize;
        let c0 = (cols - pc) / 2;
        let r0 = (rows - pr) / 2;
        let mc0 = c0.saturating_sub(gc);
        let mr0 = r0.saturating_sub(gr);
        let mc1 = (c0 + pc + gc).min(cols);
        let mr1 = (r0 + pr + gr).min(rows);
        let (mrows, mcols) = (mr1 - mr0, mc1 - mc0);
        let mut h32 = Vec::with_capacity(mrows * mcols);
        for r in mr0..mr1 {
            for c in mc0..mc1 {
                h32.push(model_um[r * cols + c] as f32);
            }
        }
        let view = RasterView::new(&h32, Shape::new(mrows, mcols))?;
        let (filled, filled_samples) = fill_missing(view)?;
        let raw: Vec<f64> = filled.iter().map(|&h| f64::from(h)).collect();
        let sampling = Sampling::of(Shape::new(mrows, mcols), model.pitch());
        let g = Grid::of(&raw, sampling)?;
        let heights_um = level_plane(&g)?;
        Ok(Patch {
            heights_um,
            sampling,
            in_model: Window {
                row0: mr0,
                col0: mc0,
                rows: mrows,
                cols: mcols,
            },
            crop: Window {
                row0: r0 - mr0,
                col0: c0 - mc0,
                rows: pr,
                cols: pc,
            },
            filled_samples,
        })
    }

    /// The crop's samples: its shape at the patch's pitch.
    pub fn crop_sampling(&self) -> Sampling {
        self.sampling
            .with_shape(Shape::new(self.crop.rows, self.crop.cols))
    }

    /// The values of `field` (on the meshed area) inside the crop.
    pub fn cropped(&self, field: &[f64]) -> Vec<f64> {
        crop(field, self.sampling.cols(), self.crop)
    }
}

pub fn crop(field: &[f64], cols: usize, w: Window) -> Vec<f64> {
    let mut out = Vec::with_capacity(w.rows * w.cols);
    for r in w.row0..w.row0 + w.rows {
        out.extend_from_slice(&field[r * cols + w.col0..r * cols + w.col0 + w.cols]);
    }
    out
}

/// The patch's surface meshed for LIGGGHTS within `max_triangles`, and how its nodes sit on
/// the patch's grid.
pub struct PatchMesh {
    pub target: TargetMesh,
    pub map: NodeMap,
}

/// Grid geometry linking the mesh's nodes (block means) to the patch's samples.
#[derive(Debug, Clone, Copy)]
pub struct NodeMap {
    pub stride: usize,
    pub node_rows: usize,
    pub node_cols: usize,
    /// The patch's samples.
    pub sampling: Sampling,
    /// Mesh vertex (m) to patch position (um): um = m * 1e6 + offset.
    pub offset_um: [f64; 3],
}

/// Shift of the mesh in x and y, m (see [`mesh_patch`]).
pub const MESH_SHIFT_M: f64 = 1e-4;

pub fn mesh_patch(heights_um: &[f64], at: Sampling, max_triangles: usize) -> Result<PatchMesh> {
    let h32: Vec<f32> = heights_um.iter().map(|&h| h as f32).collect();
    let view = RasterView::new(&h32, at.shape())?;
    let profile =
        EngineProfile::with_budget(surfstream_mesher::DemEngine::Liggghts, Some(max_triangles));
    let mut target = grid_sheet_for(view, &ScanPlacement::new(at.pitch()), &profile)?;
    // LIGGGHTS refuses a mesh whose coordinates span less than 1e-4 m ("dimensions too
    // small", a round-off guard over all of x, y, z): a sub-100-um patch recentred on the
    // origin would. Moving it by +100 um in x and y makes the span at least 100 um.
    for v in &mut target.mesh.vertices {
        v[0] += MESH_SHIFT_M;
        v[1] += MESH_SHIFT_M;
    }
    target.mesh.offset_um[0] -= MESH_SHIFT_M * 1e6;
    target.mesh.offset_um[1] -= MESH_SHIFT_M * 1e6;
    let map = NodeMap {
        stride: target.stride,
        node_rows: target.grid.rows,
        node_cols: target.grid.cols,
        sampling: at,
        offset_um: target.mesh.offset_um,
    };
    Ok(PatchMesh { target, map })
}

impl NodeMap {
    /// Patch position (um) of mesh node (r, c): block means stand at their block's centre.
    fn node_position_um(&self, r: usize, c: usize) -> (f64, f64) {
        let half = (self.stride as f64 - 1.0) * 0.5;
        (
            (c as f64 * self.stride as f64 + half) * self.sampling.pitch_x_um(),
            (r as f64 * self.stride as f64 + half) * self.sampling.pitch_y_um(),
        )
    }

    /// Fractional node coordinates (row, col) of a point given in mesh units (m).
    fn node_coords(&self, x_m: f64, y_m: f64) -> (f64, f64) {
        let (x0, y0) = self.node_position_um(0, 0);
        let x_um = x_m * 1e6 + self.offset_um[0];
        let y_um = y_m * 1e6 + self.offset_um[1];
        (
            (y_um - y0) / (self.stride as f64 * self.sampling.pitch_y_um()),
            (x_um - x0) / (self.stride as f64 * self.sampling.pitch_x_um()),
        )
    }

    /// Nearest node of a mesh vertex (m), if it is on the grid (within a tenth of a cell).
    fn vertex_node(&self, v: [f64; 3]) -> Option<usize> {
        let (fr, fc) = self.node_coords(v[0], v[1]);
        let (r, c) = (fr.round(), fc.round());
        if (fr - r).abs() > 0.1 || (fc - c).abs() > 0.1 || r < 0.0 || c < 0.0 {
            return None;
        }
        let (r, c) = (r as usize, c as usize);
        (r < self.node_rows && c < self.node_cols).then_some(r * self.node_cols + c)
    }

    /// Node volumes (um^3) spread evenly over each node's block of samples: depth (um) along
    /// z per sample.
    pub fn nodes_to_samples(&self, node_volume_um3: &[f64]) -> Vec<f64> {
        let (rows, cols) = (self.sampling.rows(), self.sampling.cols());
        let mut depth = vec![0.0; rows * cols];
        let cell = self.sampling.pitch().cell_area_um2();
        for nr in 0..self.node_rows {
            let r0 = nr * self.stride;
            let r1 = (r0 + self.stride).min(rows);
            for nc in 0..self.node_cols {
                let c0 = nc * self.stride;
                let c1 = (c0 + self.stride).min(cols);
                let n = ((r1 - r0) * (c1 - c0)) as f64;
                let d = node_volume_um3[nr * self.node_cols + nc] / (n * cell);
                for r in r0..r1 {
                    for x in &mut depth[r * cols + c0..r * cols + c1] {
                        *x += d;
                    }
                }
            }
        }
        depth
    }

    /// Triangle volumes (m^3) to depth along z on the patch's samples (um). Returns the depth
    /// map and the volume of triangles whose corners are not on the grid (should be zero).
    pub fn triangle_volumes_to_depth(
        &self,
        triangles: &[[[f64; 3]; 3]],
        volume_m3: &[f64],
    ) -> (Vec<f64>, f64) {
        let mut node = vec![0.0; self.node_rows * self.node_cols];
        let mut unmapped = 0.0;
        for (t, &v) in triangles.iter().zip(volume_m3) {
            if v == 0.0 {
                continue;
            }
            let v_um3 = v * 1e18;
            let ids: Vec<Option<usize>> = t.iter().map(|&p| self.vertex_node(p)).collect();
            if ids.iter().all(Option::is_some) {
                for id in ids.into_iter().flatten() {
                    node[id] += v_um3 / 3.0;
                }
            } else {
                unmapped += v;
            }
        }
        (self.nodes_to_samples(&node), unmapped)
    }

    /// Point volumes (m^3 at x, y in m) to depth (um), each shared bilinearly among the four
    /// nodes around it (clamped at the edges), so the total is kept.
    pub fn point_volumes_to_depth(&self, points: &[(f64, f64, f64)]) -> Vec<f64> {
        let mut node = vec![0.0; self.node_rows * self.node_cols];
        let maxr = (self.node_rows - 1) as f64;
        let maxc = (self.node_cols - 1) as f64;
        for &(x, y, v) in points {
            if v == 0.0 {
                continue;
            }
            let (fr, fc) = self.node_coords(x, y);
            let (fr, fc) = (fr.clamp(0.0, maxr), fc.clamp(0.0, maxc));
            let (r0, c0) = (fr.floor() as usize, fc.floor() as usize);
            let (r1, c1) = (
                (r0 + 1).min(self.node_rows - 1),
                (c0 + 1).min(self.node_cols - 1),
            );
            let (tr, tc) = (fr - r0 as f64, fc - c0 as f64);
            let v = v * 1e18;
            node[r0 * self.node_cols + c0] += v * (1.0 - tr) * (1.0 - tc);
            node[r0 * self.node_cols + c1] += v * (1.0 - tr) * tc;
            node[r1 * self.node_cols + c0] += v * tr * (1.0 - tc);
            node[r1 * self.node_cols + c1] += v * tr * tc;
        }
        self.nodes_to_samples(&node)
    }
}

/// Triangle volumes (m^3) to depth along z on the samples of `sampling` (um), for a mesh whose
/// vertices are samples of that grid (the tolerance mesh, [`crate::passes`]): each triangle's
/// volume is spread evenly over the samples its footprint covers (corners and edges
/// included), so a large triangle's wear covers its area, not only its three corners, and the
/// total is kept exactly; a triangle whose footprint holds no sample gives its volume to the
/// sample nearest its centroid. `offset_um` turns a vertex (m) into patch coordinates (um):
/// um = m * 1e6 + offset.
pub fn triangle_volumes_to_samples(
    sampling: Sampling,
    offset_um: [f64; 3],
    triangles: &[[[f64; 3]; 3]],
    volume_m3: &[f64],
) -> SampleWear {
    let (rows, cols) = (sampling.rows(), sampling.cols());
    let (px, py) = (sampling.pitch_x_um(), sampling.pitch_y_um());
    let cell = sampling.pitch().cell_area_um2();
    let mut depth = vec![0.0; rows * cols];
    let mut unmapped = 0.0;
    let mut nearest = 0.0;
    let mut inside = Vec::new();
    for (t, &v) in triangles.iter().zip(volume_m3) {
        if v == 0.0 {
            continue;
        }
        // Corners in sample units (col, row).
        let q = t.map(|p| {
            (
                (p[0] * 1e6 + offset_um[0]) / px,
                (p[1] * 1e6 + offset_um[1]) / py,
            )
        });
        let det = (q[1].0 - q[0].0) * (q[2].1 - q[0].1) - (q[2].0 - q[0].0) * (q[1].1 - q[0].1);
        inside.clear();
        if det.abs() > 1e-12 {
            let lo_c = q.iter().map(|p| p.0).fold(f64::INFINITY, f64::min);
            let hi_c = q.iter().map(|p| p.0).fold(f64::NEG_INFINITY, f64::max);
            let lo_r = q.iter().map(|p| p.1).fold(f64::INFINITY, f64::min);
            let hi_r = q.iter().map(|p| p.1).fold(f64::NEG_INFINITY, f64::max);
            let c0 = (lo_c - 1e-6).ceil().max(0.0) as usize;
            let r0 = (lo_r - 1e-6).ceil().max(0.0) as usize;
            let c1 = ((hi_c + 1e-6).floor().max(-1.0) + 1.0) as usize;
            let r1 = ((hi_r + 1e-6).floor().max(-1.0) + 1.0) as usize;
            // Barycentric test with a tolerance of 1e-6 sample: corners and edges count.
            let eps = 1e-6 * det.abs();
            for r in r0..r1.min(rows) {
                for c in c0..c1.min(cols) {
                    let (x, y) = (c as f64, r as f64);
                    let w1 = (x - q[0].0) * (q[2].1 - q[0].1) - (q[2].0 - q[0].0) * (y - q[0].1);
                    let w2 = (q[1].0 - q[0].0) * (y - q[0].1) - (x - q[0].0) * (q[1].1 - q[0].1);
                    let (w1, w2) = (w1 * det.signum(), w2 * det.signum());
                    if w1 >= -eps && w2 >= -eps && w1 + w2 <= det.abs() + eps {
                        inside.push(r * cols + c);
                    }
                }
            }
        }
        if inside.is_empty() {
            // A triangle smaller than a sample spacing between samples (the angle-bounded
            // mesh of a worn surface inserts vertices off the grid): its volume goes to the
            // sample nearest its centroid, so the total is kept. Only one off the grid by more
            // than half a sample is unmapped.
            let (cc, cr) = (
                (q[0].0 + q[1].0 + q[2].0) / 3.0,
                (q[0].1 + q[1].1 + q[2].1) / 3.0,
            );
            let on_grid = |x: f64, n: usize| x > -0.5 && x < n as f64 - 0.5;
            if on_grid(cc, cols) && on_grid(cr, rows) {
                inside.push(cr.round() as usize * cols + cc.round() as usize);
                nearest += v;
            } else {
                unmapped += v;
                continue;
            }
        }
        let d = v * 1e18 / (inside.len() as f64 * cell);
        for &k in &inside {
            depth[k] += d;
        }
    }
    SampleWear {
        depth_um: depth,
        unmapped_m3: unmapped,
        to_nearest_sample_m3: nearest,
    }
}

/// Triangle wear on the samples ([`triangle_volumes_to_samples`]).
#[derive(Debug, Clone)]
pub struct SampleWear {
    /// Depth along z per sample, um.
    pub depth_um: Vec<f64>,
    /// Volume of triangles that cover no sample of the grid (off it: should be zero), m^3.
    pub unmapped_m3: f64,
    /// Volume of triangles between samples, given to the sample nearest their centroid, m^3
    /// (kept in the total; its place is within half a sample).
    pub to_nearest_sample_m3: f64,
}

/// Volume of a depth map (um) over samples of `pitch` (um^2 per sample), um^3.
pub fn volume_um3(depth_um: &[f64], pitch: Pitch) -> f64 {
    depth_um.iter().sum::<f64>() * pitch.x_um() * pitch.y_um()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bumpy(rows: usize, cols: usize) -> Vec<f64> {
        (0..rows * cols)
            .map(|k| ((k % cols) as f64 * 0.3).sin() + ((k / cols) as f64 * 0.2).cos())
            .collect()
    }

    #[test]
    fn the_patch_is_centred_with_its_guard_band_and_levelled() {
        let (rows, cols) = (60, 80);
        let mut z = bumpy(rows, cols);
        for (k, v) in z.iter_mut().enumerate() {
            *v += 0.05 * (k % cols) as f64; // a tilt the levelling removes
        }
        z[30 * cols + 40] = f64::NAN;
        let model = Sampling::square(Shape::new(rows, cols), 2.0).unwrap();
        let p = Patch::cut(&z, model, 40.0, 30.0, 10.0).unwrap();
        assert_eq!((p.crop.rows, p.crop.cols), (15, 20));
        assert_eq!((p.sampling.rows(), p.sampling.cols()), (25, 30));
        assert_eq!(p.sampling.pitch(), model.pitch());
        assert_eq!((p.crop.row0, p.crop.col0), (5, 5));
        assert_eq!((p.in_model.row0, p.in_model.col0), (17, 25));
        assert_eq!(p.filled_samples, 1);
        let mean = p.heights_um.iter().sum::<f64>() / p.heights_um.len() as f64;
        assert!(mean.abs() < 1e-9);
        assert_eq!(p.cropped(&p.heights_um).len(), 300);
        // A band that does not fit is cut at the model's edge.
        let p = Patch::cut(&z, model, 150.0, 100.0, 20.0).unwrap();
        assert_eq!((p.in_model.row0, p.in_model.col0), (0, 0));
        assert_eq!((p.sampling.rows(), p.sampling.cols()), (60, 80));
    }

    #[test]
    fn triangle_volumes_cover_their_footprint_and_keep_their_total() {
        // Two triangles over a 5 x 5 grid at 2 um (offset 3 um in x): the lower-right half
        // and the upper-left half of the square, sharing the diagonal.
        let at = Sampling::square(Shape::new(5, 5), 2.0).unwrap();
        let off = [3.0, 0.0, 0.0];
        let m = |c: f64, r: f64| [(c * 2.0 - 3.0) * 1e-6, r * 2.0 * 1e-6, 0.0];
        let tris = [
            [m(0.0, 0.0), m(4.0, 0.0), m(4.0, 4.0)],
            [m(0.0, 0.0), m(4.0, 4.0), m(0.0, 4.0)],
        ];
        let mapped = triangle_volumes_to_samples(at, off, &tris, &[1.5e-18, 0.0]);
        let (d, unmapped) = (mapped.depth_um, mapped.unmapped_m3);
        assert_eq!(unmapped, 0.0);
        assert_eq!(mapped.to_nearest_sample_m3, 0.0);
        // The first triangle covers the 15 samples with col >= row, evenly.
        let per = 1.5 / (15.0 * 4.0);
        for r in 0..5 {
            for c in 0..5 {
                let want = if c >= r { per } else { 0.0 };
                assert!(
                    (d[r * 5 + c] - want).abs() < 1e-15,
                    "({r}, {c}) {}",
                    d[r * 5 + c]
                );
            }
        }
        assert!((volume_um3(&d, at.pitch()) - 1.5).abs() < 1e-12);
        // A triangle off the grid is counted as unmapped.
        let far = [[m(10.0, 10.0), m(12.0, 10.0), m(12.0, 12.0)]];
        let unmapped = triangle_volumes_to_samples(at, off, &far, &[2e-18]).unmapped_m3;
        assert_eq!(unmapped, 2e-18);
        // A triangle between samples (vertices off the grid, no sample inside) gives its
        // volume to the sample nearest its centroid: (col 2, row 1).
        let small = [[m(1.6, 1.2), m(2.4, 1.2), m(2.0, 1.4)]];
        let mapped = triangle_volumes_to_samples(at, off, &small, &[0.8e-18]);
        let (d, unmapped) = (mapped.depth_um, mapped.unmapped_m3);
        assert_eq!(unmapped, 0.0);
        assert_eq!(
            mapped.to_nearest_sample_m3, 0.8e-18,
            "counted in the record"
        );
        assert!((d[5 + 2] - 0.8 / 4.0).abs() < 1e-15, "{d:?}");
        assert!((volume_um3(&d, at.pitch()) - 0.8).abs() < 1e-12);
    }

    #[test]
    fn triangle_and_point_volumes_keep_their_total() {
        let (rows, cols) = (21, 31);
        let z = bumpy(rows, cols);
        for budget in [2 * 20 * 30, 300] {
            let at = Sampling::square(Shape::new(rows, cols), 1.5).unwrap();
            let pm = mesh_patch(&z, at, budget).unwrap();
            let m = &pm.target.mesh;
            let tris: Vec<[[f64; 3]; 3]> = m
                .triangles
                .iter()
                .map(|t| t.map(|i| m.vertices[i as usize]))
                .collect();
            let vols: Vec<f64> = (0..tris.len()).map(|i| 1e-18 * (i % 7) as f64).collect();
            let (depth, unmapped) = pm.map.triangle_volumes_to_depth(&tris, &vols);
            assert_eq!(unmapped, 0.0, "stride {}", pm.map.stride);
            let total: f64 = vols.iter().sum::<f64>() * 1e18;
            let got = volume_um3(&depth, at.pitch());
            assert!((got / total - 1.0).abs() < 1e-12, "{got} vs {total}");
            // Points anywhere (even off the mesh) keep their volume too.
            let pts: Vec<(f64, f64, f64)> = tris
                .iter()
                .map(|t| (t[0][0] + 1e-7, t[0][1], 1e-18))
                .collect();
            let d = pm.map.point_volumes_to_depth(&pts);
            let got = volume_um3(&d, at.pitch());
            assert!((got / tris.len() as f64 - 1.0).abs() < 1e-12);
        }
    }
}
