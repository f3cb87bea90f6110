//! Closed solids from height fields: the regular-grid top surface ([`grid_solid`]) and the part
//! any top surface needs to become a watertight solid ([`close_top_surface`]: side walls and a
//! flat base), kept separate so that the adaptive mesher can reuse it.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::error::{MeshError, Result};
use surfstream_core::raster::RasterView;

use crate::field::{fill_missing, finite, positive_finite, validate, ScanPlacement};
use crate::geom;

/// Length unit of a mesh's coordinates. STL carries no unit, so the writers state it in the
/// header and the caller must tell the simulator (EDEM and LIGGGHTS both ask at import).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LengthUnit {
    /// Metres (SI; what LIGGGHTS and Yade scripts usually use).
    M,
    /// Millimetres (the default: what CAD and EDEM imports expect).
    #[default]
    Mm,
    /// Micrometres (the unit of the height maps themselves).
    Um,
}

impl LengthUnit {
    /// Micrometres in one of this unit: output = um / `um_per_unit()`.
    pub fn um_per_unit(self) -> f64 {
        match self {
            Self::M => 1e6,
            Self::Mm => 1e3,
            Self::Um => 1.0,
        }
    }

    /// The unit's symbol as written in STL headers and file names: "m", "mm", "um".
    pub fn symbol(self) -> &'static str {
        match self {
            Self::M => "m",
            Self::Mm => "mm",
            Self::Um => "um",
        }
    }
}

/// How a height field becomes a solid.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SolidParams {
    /// Unit of the output coordinates.
    pub units: LengthUnit,
    /// Distance of the flat base below the lowest (filled) sample, um. `None`:
    /// [`default_base_depth_um`] of the height range.
    pub base_depth_um: Option<f64>,
    /// Move the solid near the origin (see [`SolidMesh`]); the shift is kept in `offset_um`.
    pub recentre: bool,
}

impl Default for SolidParams {
    fn default() -> Self {
        Self {
            units: LengthUnit::Mm,
            base_depth_um: None,
            recentre: true,
        }
    }
}

impl SolidParams {
    /// Checks the parameters' domains.
    pub fn validate(&self) -> Result<()> {
        if let Some(depth_um) = self.base_depth_um {
            // Zero would make the walls under the lowest boundary sample degenerate.
            positive_finite("base_depth_um", depth_um)?;
        }
        Ok(())
    }
}

/// The default base depth: 10 % of the height range (max - min), at least 10 um, so the base
/// is clearly separate from the surface without dwarfing it.
pub fn default_base_depth_um(height_range_um: f64) -> f64 {
    (0.1 * height_range_um).max(10.0)
}

/// A closed triangle solid.
///
/// Coordinates are in `units`; scan coordinates in um are recovered exactly (up to f64
/// rounding) as `scan_um = vertex * units.um_per_unit() + offset_um`, see
/// [`SolidMesh::to_scan_um`].
///
/// With recentring (the default) the x, y centre of the grid is at (0, 0) and the base at
/// z = 0, so the whole solid has z >= 0 and sits on the x-y plane like a specimen on a table.
/// This matters because STL stores f32: a coordinate of 50 mm keeps only ~4 nm of resolution,
/// while one within a few mm of the origin keeps well under a nanometre. Without recentring
/// `offset_um` is zero and the vertices are the absolute scan coordinates.
///
/// Axes are those of the height map (DESIGN §2): x along columns, y along rows, z up; no flips.
/// Every triangle winds counter-clockwise seen from outside (right-handed outward normal).
#[derive(Debug, Clone, PartialEq)]
pub struct SolidMesh {
    /// Vertex positions in `units`.
    pub vertices: Vec<[f64; 3]>,
    /// Vertex indices, counter-clockwise seen from outside.
    pub triangles: Vec<[u32; 3]>,
    /// Scan position (um) of the output origin: `scan_um = vertex * um_per_unit + offset_um`.
    pub offset_um: [f64; 3],
    /// Unit of `vertices`.
    pub units: LengthUnit,
    /// How many missing (NaN) samples were filled before meshing.
    pub filled_samples: usize,
    /// The first `top_triangles` triangles are the measured surface; the rest are the side walls
    /// and the base, which a simulation may want to tag as a different wall.
    pub top_triangles: usize,
    /// Distance of the base below the lowest sample, um.
    pub base_depth_um: f64,
}

impl SolidMesh {
    /// A vertex (in `units`) in scan coordinates, um.
    pub fn to_scan_um(&self, vertex: [f64; 3]) -> [f64; 3] {
        let s = self.units.um_per_unit();
        [
            vertex[0] * s + self.offset_um[0],
            vertex[1] * s + self.offset_um[1],
            vertex[2] * s + self.offset_um[2],
        ]
    }

    /// The corner positions of triangle `t`. Panics if `t` or its indices are out of range;
    /// [`SolidMesh::validate`] checks the indices.
    pub fn triangle_corners(&self, t: usize) -> [[f64; 3]; 3] {
        let [a, b, c] = self.triangles[t];
        [
            self.vertices[a as usize],
            self.vertices[b as usize],
            self.vertices[c as usize],
        ]
    }

    /// Unit outward normal of triangle `t` (right-hand rule over its winding), computed in f64;
    /// zero for a degenerate triangle.
    pub fn face_normal(&self, t: usize) -> [f64; 3] {
        let [a, b, c] = self.triangle_corners(t);
        geom::unit_normal(a, b, c)
    }

    /// Checks that every index addresses a vertex, every coordinate is finite and the triangle
    /// count fits STL's 32-bit count, so writers never index out of bounds.
    pub fn validate(&self) -> Result<()> {
        let n = self.vertices.len();
        for (t, tri) in self.triangles.iter().enumerate() {
            if let Some(&v) = tri.iter().find(|&&v| v as usize >= n) {
                return Err(MeshError::InvalidMesh(format!(
                    "triangle {t} refers to vertex {v} but the mesh has {n} vertices"
                )));
            }
        }
        if let Some(k) = self
            .vertices
            .iter()
            .position(|v| !v.iter().all(|c| c.is_finite()))
        {
            return Err(MeshError::InvalidMesh(format!(
                "vertex {k} has a non-finite coordinate {:?}",
                self.vertices[k]
            )));
        }
        if self.triangles.len() > u32::MAX as usize {
            return Err(MeshError::TooLarge {
                what: "triangles",
                count: self.triangles.len(),
                limit: u32::MAX as usize,
            });
        }
        Ok(())
    }
}

/// Meshes a rows field into a closed, watertight solid on its regular grid.
///
/// - Missing (NaN) samples are filled first by [`fill_missing`]; the count is returned in
///   `filled_samples`. A field with no valid sample, a +/-infinite sample, fewer than 2 x 2
///   samples, a non-finite / non-positive pitch is an error.
/// - Top: one vertex per sample, `vertices[i * cols + j]` is sample (row i, column j); two
///   triangles per grid cell, split along the diagonal from (i, j) to (i + 1, j + 1):
///   `2 (cols - 1)(rows - 1)` triangles, first in `triangles`.
/// - Then [`close_top_surface`]: side walls down to a flat base `base_depth_um` below the lowest
///   sample and the base. With `B = 2 (cols - 1) + 2 (rows - 1)` boundary samples, the solid
///   has `cols * rows + B + 1` vertices and `2 (cols - 1)(rows - 1) + 3 B` triangles.
///
/// Runs in parallel over rows (rayon); `examples/bench_mesh.rs` times a 1024 x 1024 field.
pub fn grid_solid(
    heights: RasterView<'_, f32>,
    at: &ScanPlacement,
    params: &SolidParams,
) -> Result<SolidMesh> {
    validate(heights, at)?;
    params.validate()?;
    let cols = heights.cols();
    let (heights_um, filled_samples) = fill_missing(heights)?;

    let g = GridPlacement::new(&heights_um, at, params, heights.shape())?;
    let (top_vertices, vertex_count, top_triangles, triangle_count) = g.counts();
    let (offset_um, base_z_um, base_depth_um) = (g.offset_um, g.base_z_um, g.base_depth_um);
    let um_per_unit = params.units.um_per_unit();
    let place = |i: usize, j: usize, h_um: f32| g.place(i, j, h_um);

    let mut vertices: Vec<[f64; 3]> = Vec::with_capacity(vertex_count);
    vertices.resize(top_vertices, [0.0; 3]);
    vertices
        .par_chunks_mut(cols)
        .zip(heights_um.par_chunks(cols))
        .enumerate()
        .for_each(|(i, (row, h_row))| {
            for (j, (v, &h)) in row.iter_mut().zip(h_row).enumerate() {
                *v = place(i, j, h);
            }
        });

    let mut triangles: Vec<[u32; 3]> = Vec::with_capacity(triangle_count);
    triangles.resize(top_triangles, [0; 3]);
    let w32 = cols as u32; // fits: vertex_count <= u32::MAX was checked
    triangles
        .par_chunks_mut(2 * (cols - 1))
        .enumerate()
        .for_each(|(i, row)| {
            for (j, pair) in row.chunks_exact_mut(2).enumerate() {
                // x grows with j and y with i, so (i, j) -> (i, j+1) -> (i+1, j+1) turns
                // counter-clockwise seen from +z (right-handed): the normal points up. The
                // "image" winding (i, j) -> (i+1, j) -> (i+1, j+1), counter-clockwise on a
                // screen whose rows grow downwards, would point every top normal into the solid.
                let v00 = (i * cols + j) as u32;
                let v01 = v00 + 1;
                let v10 = v00 + w32;
                let v11 = v10 + 1;
                pair[0] = [v00, v01, v11];
                pair[1] = [v00, v11, v10];
            }
        });

    let boundary = g.boundary();
    close_top_surface(
        &mut vertices,
        &mut triangles,
        &boundary,
        base_z_um / um_per_unit,
    )?;
    debug_assert_eq!(vertices.len(), vertex_count);
    debug_assert_eq!(triangles.len(), triangle_count);

    Ok(SolidMesh {
        vertices,
        triangles,
        offset_um,
        units: params.units,
        filled_samples,
        top_triangles,
        base_depth_um,
    })
}

/// Where the vertices of the full-grid solid go ([`grid_solid`]; also the streamed grid,
/// module `stream`): one copy, so both place every vertex on the same f64.
#[derive(Debug, Clone, Copy)]
pub(crate) struct GridPlacement {
    at: ScanPlacement,
    rows: usize,
    cols: usize,
    centre_col: f64,
    centre_row: f64,
    min_um: f64,
    pub(crate) base_depth_um: f64,
    pub(crate) offset_um: [f64; 3],
    /// The base plane's z, um relative to the output origin.
    pub(crate) base_z_um: f64,
    um_per_unit: f64,
    recentre: bool,
}

impl GridPlacement {
    /// The placement for `heights_um` (filled, `shape`); errors when the solid would need more
    /// vertices or triangles than u32 indices address.
    pub(crate) fn new(
        heights_um: &[f32],
        at: &ScanPlacement,
        params: &SolidParams,
        shape: surfstream_core::raster::Shape,
    ) -> Result<Self> {
        let (rows, cols) = (shape.rows, shape.cols);
        let (min_um, max_um) = heights_um
            .par_iter()
            .fold(
                || (f32::INFINITY, f32::NEG_INFINITY),
                |(lo, hi), &h| (lo.min(h), hi.max(h)),
            )
            .reduce(
                || (f32::INFINITY, f32::NEG_INFINITY),
                |(a, b), (c, d)| (a.min(c), b.max(d)),
            );
        let (min_um, max_um) = (f64::from(min_um), f64::from(max_um));
        let base_depth_um = params
            .base_depth_um
            .unwrap_or_else(|| default_base_depth_um(max_um - min_um));
        let (px, py) = (at.pitch.x_um(), at.pitch.y_um());
        let centre_col = (cols - 1) as f64 / 2.0;
        let centre_row = (rows - 1) as f64 / 2.0;
        // Position of a sample relative to the output origin, um. Recentred coordinates are
        // formed from small numbers (index - centre, rows - min) rather than by subtracting
        // the offset from absolute positions, so no precision is lost to cancellation.
        let (offset_um, base_z_um) = if params.recentre {
            (
                [
                    at.origin_x_um + centre_col * px,
                    at.origin_y_um + centre_row * py,
                    at.z_offset_um + min_um - base_depth_um,
                ],
                0.0,
            )
        } else {
            ([0.0; 3], at.z_offset_um + (min_um - base_depth_um))
        };
        let g = Self {
            at: *at,
            rows,
            cols,
            centre_col,
            centre_row,
            min_um,
            base_depth_um,
            offset_um,
            base_z_um,
            um_per_unit: params.units.um_per_unit(),
            recentre: params.recentre,
        };
        let (_, vertex_count, _, triangle_count) = g.counts();
        // Indices are u32 (what every mesh consumer uses, and half the memory of usize).
        if vertex_count > u32::MAX as usize {
            return Err(MeshError::TooLarge {
                what: "vertices",
                count: vertex_count,
                limit: u32::MAX as usize,
            });
        }
        if triangle_count > u32::MAX as usize {
            return Err(MeshError::TooLarge {
                what: "triangles",
                count: triangle_count,
                limit: u32::MAX as usize,
            });
        }
        Ok(g)
    }

    /// (top vertices, vertices, top triangles, triangles) of the closed solid.
    pub(crate) fn counts(&self) -> (usize, usize, usize, usize) {
        let (rows, cols) = (self.rows, self.cols);
        let boundary_len = 2 * (cols - 1) + 2 * (rows - 1);
        let top_vertices = cols * rows;
        let top_triangles = 2 * (cols - 1) * (rows - 1);
        (
            top_vertices,
            top_vertices + boundary_len + 1,
            top_triangles,
            top_triangles + 3 * boundary_len,
        )
    }

    /// The vertex of sample (row `i`, column `j`) at height `h_um`, output units.
    #[inline]
    pub(crate) fn place(&self, i: usize, j: usize, h_um: f32) -> [f64; 3] {
        let at = &self.at;
        let (px, py) = (at.pitch.x_um(), at.pitch.y_um());
        let h_um = f64::from(h_um);
        let (x_um, y_um, z_um) = if self.recentre {
            (
                (j as f64 - self.centre_col) * px,
                (i as f64 - self.centre_row) * py,
                (h_um - self.min_um) + self.base_depth_um,
            )
        } else {
            (
                at.origin_x_um + j as f64 * px,
                at.origin_y_um + i as f64 * py,
                at.z_offset_um + h_um,
            )
        };
        let u = self.um_per_unit;
        [x_um / u, y_um / u, z_um / u]
    }

    /// The grid's rim as sample indices, counter-clockwise seen from +z: along y = min (+x),
    /// x = max (+y), y = max (-x), x = min (-y).
    pub(crate) fn boundary(&self) -> Vec<u32> {
        let (rows, cols) = (self.rows, self.cols);
        let idx = |i: usize, j: usize| (i * cols + j) as u32;
        let mut boundary = Vec::with_capacity(2 * (cols - 1) + 2 * (rows - 1));
        boundary.extend((0..cols - 1).map(|j| idx(0, j)));
        boundary.extend((0..rows - 1).map(|i| idx(i, cols - 1)));
        boundary.extend((1..cols).rev().map(|j| idx(rows - 1, j)));
        boundary.extend((1..rows).rev().map(|i| idx(i, 0)));
        boundary
    }
}

/// Closes an open top surface into a solid: a vertical wall under every boundary edge down to
/// the plane z = `base_z`, and a flat base.
///
/// Requirements (checked): the top triangles wind counter-clockwise seen from +z (normals up);
/// `boundary_ccw` lists the top surface's rim vertices once each, in order, counter-clockwise
/// seen from +z (so each top triangle traverses its rim edge in the same direction); the rim
/// is convex in x-y (collinear runs allowed, as on a grid's edge); `base_z` lies strictly below
/// every rim vertex.
///
/// Appends one base vertex under each rim vertex plus one at the rim's centroid, then two wall
/// triangles per rim edge and the base as a fan of one triangle per rim edge around the
/// centroid. The fan, rather than a fan from a corner, keeps every base triangle non-degenerate
/// even where many rim vertices are collinear.
pub fn close_top_surface(
    vertices: &mut Vec<[f64; 3]>,
    triangles: &mut Vec<[u32; 3]>,
    boundary_ccw: &[u32],
    base_z: f64,
) -> Result<()> {
    let n = boundary_ccw.len();
    if n < 3 {
        return Err(MeshError::InvalidMesh(format!(
            "a rim needs at least 3 vertices, got {n}"
        )));
    }
    finite("base_z", base_z)?;
    let first_base = vertices.len();
    let total = first_base + n + 1;
    if total > u32::MAX as usize {
        return Err(MeshError::TooLarge {
            what: "vertices",
            count: total,
            limit: u32::MAX as usize,
        });
    }
    let mut rim = Vec::with_capacity(n);
    for &b in boundary_ccw {
        let v = *vertices.get(b as usize).ok_or_else(|| {
            MeshError::InvalidMesh(format!(
                "rim vertex {b} is out of range ({first_base} vertices)"
            ))
        })?;
        // Written so that a NaN height also fails.
        if v[2].partial_cmp(&base_z) != Some(std::cmp::Ordering::Greater) {
            return Err(MeshError::InvalidMesh(format!(
                "base z = {base_z} is not below rim vertex {b} at z = {}",
                v[2]
            )));
        }
        rim.push(v);
    }
    // Shoelace area and per-corner turn: a clockwise or non-convex rim would give inward or
    // overlapping walls and base.
    let mut area2 = 0.0;
    for k in 0..n {
        let (a, b, c) = (rim[k], rim[(k + 1) % n], rim[(k + 2) % n]);
        area2 += a[0] * b[1] - b[0] * a[1];
        let (e1, e2) = ([b[0] - a[0], b[1] - a[1]], [c[0] - b[0], c[1] - b[1]]);
        let turn = e1[0] * e2[1] - e1[1] * e2[0];
        let scale = e1[0].hypot(e1[1]) * e2[0].hypot(e2[1]);
        if scale == 0.0 || turn < -1e-12 * scale {
            return Err(MeshError::InvalidMesh(format!(
                "rim is not convex and counter-clockwise at vertex {}",
                boundary_ccw[(k + 1) % n]
            )));
        }
    }
    if area2.is_nan() || area2 <= 0.0 {
        return Err(MeshError::InvalidMesh(
            "rim encloses no area counter-clockwise seen from +z".into(),
        ));
    }

    let (mut cx, mut cy) = (0.0, 0.0);
    for v in &rim {
        cx += v[0];
        cy += v[1];
        vertices.push([v[0], v[1], base_z]);
    }
    vertices.push([cx / n as f64, cy / n as f64, base_z]);
    let centre = (total - 1) as u32;
    let base = |k: usize| (first_base + k % n) as u32;

    triangles.reserve(3 * n);
    for k in 0..n {
        // The top surface traverses rim edge a -> b; the wall must traverse it b -> a. Seen from
        // outside (the rim runs counter-clockwise from above, so outside is to its right) the
        // quad b, a, a', b' is counter-clockwise.
        let (a, b) = (boundary_ccw[k], boundary_ccw[(k + 1) % n]);
        let (a_base, b_base) = (base(k), base(k + 1));
        triangles.push([b, a, a_base]);
        triangles.push([b, a_base, b_base]);
    }
    for k in 0..n {
        // Walls traverse the base edge a' -> b'; the base (normal -z, clockwise from above)
        // traverses it b' -> a'.
        triangles.push([centre, base(k + 1), base(k)]);
    }
    Ok(())
}
