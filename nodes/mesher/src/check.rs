//! Topology and geometry checks of a triangle mesh: is it a closed, consistently oriented solid
//! whose normals point outwards, and does it survive STL's f32 coordinates?

use std::collections::HashSet;

use rayon::prelude::*;

use crate::geom;
use crate::solid::SolidMesh;

/// What [`check_closed`] found.
#[derive(Debug, Clone, PartialEq)]
pub struct MeshCheck {
    /// Every edge is shared by exactly two triangles that traverse it in opposite directions:
    /// the mesh bounds a volume with no holes, flaps or flipped faces.
    pub watertight: bool,
    /// No edge is traversed twice in the same direction: neighbouring triangles agree on which
    /// side is outside (true for an open surface too).
    pub consistently_oriented: bool,
    /// Enclosed volume in cubic output units by the divergence theorem; positive when the
    /// normals point outwards, negative when the whole mesh is inside out.
    pub signed_volume: f64,
    /// Triangles with a repeated or out-of-range vertex index, or an area that is zero to f64
    /// precision (twice the area below 1e-12 of the squared longest edge).
    pub degenerate_triangles: usize,
    /// Triangles over the same three vertices as an earlier one (in any order).
    pub duplicate_triangles: usize,
    /// Edges used by only one triangle (the rim of a hole).
    pub boundary_edges: usize,
    /// Edges used by three or more triangles.
    pub non_manifold_edges: usize,
    /// Edges traversed twice in the same direction (a flipped neighbour).
    pub misoriented_edges: usize,
    /// Vertices whose position, rounded to f32 as STL stores it, equals that of another vertex:
    /// a reader that welds vertices by position would merge them and tear the topology. Non-zero
    /// when coordinates far from the origin lose precision (see `SolidParams::recentre`).
    pub coincident_vertices_f32: usize,
}

/// Checks that `mesh` is a closed solid with outward normals (see [`MeshCheck`]). Never panics,
/// whatever the indices; costs a sort of all edges, so it is meant for tests and diagnostics.
pub fn check_closed(mesh: &SolidMesh) -> MeshCheck {
    let vertices = &mesh.vertices;
    let n = vertices.len();
    let in_range = |t: &[u32; 3]| t.iter().all(|&v| (v as usize) < n);

    let (degenerate_triangles, signed_volume6) = mesh
        .triangles
        .par_iter()
        .map(|t| {
            if !in_range(t) || t[0] == t[1] || t[1] == t[2] || t[0] == t[2] {
                return (1usize, 0.0f64);
            }
            let [a, b, c] = t.map(|v| vertices[v as usize]);
            let area2 = geom::area_vector2(a, b, c);
            let longest2 = [geom::sub(b, a), geom::sub(c, b), geom::sub(a, c)]
                .iter()
                .map(|e| geom::dot(*e, *e))
                .fold(0.0, f64::max);
            let degenerate = geom::dot(area2, area2).sqrt() <= 1e-12 * longest2;
            (usize::from(degenerate), geom::dot(a, geom::cross(b, c)))
        })
        .reduce(|| (0, 0.0), |x, y| (x.0 + y.0, x.1 + y.1));

    // Directed edges keyed by their undirected (min, max) pair; `true` when traversed min -> max.
    let mut edges: Vec<(u64, bool)> = mesh
        .triangles
        .par_iter()
        .filter(|t| in_range(t))
        .flat_map_iter(|t| {
            (0..3).filter_map(move |k| {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                (a != b).then(|| {
                    let (lo, hi) = (a.min(b), a.max(b));
                    ((u64::from(lo) << 32) | u64::from(hi), a < b)
                })
            })
        })
        .collect();
    edges.par_sort_unstable();

    let (mut boundary_edges, mut non_manifold_edges, mut misoriented_edges) = (0, 0, 0);
    for run in edges.chunk_by(|x, y| x.0 == y.0) {
        let forward = run.iter().filter(|e| e.1).count();
        let backward = run.len() - forward;
        match run.len() {
            1 => boundary_edges += 1,
            2 => {}
            _ => non_manifold_edges += 1,
        }
        if forward > 1 || backward > 1 {
            misoriented_edges += 1;
        }
    }

    let mut sorted: Vec<[u32; 3]> = mesh
        .triangles
        .par_iter()
        .map(|t| {
            let mut s = *t;
            s.sort_unstable();
            s
        })
        .collect();
    sorted.par_sort_unstable();
    let duplicate_triangles = sorted.windows(2).filter(|w| w[0] == w[1]).count();

    // `+ 0.0` turns -0.0 into +0.0 so both zeros weld, as they would in a reader.
    let positions: HashSet<[u32; 3]> = vertices
        .iter()
        .map(|v| v.map(|c| (c as f32 + 0.0).to_bits()))
        .collect();
    let coincident_vertices_f32 = n - positions.len();

    let edges_ok = boundary_edges == 0 && non_manifold_edges == 0 && misoriented_edges == 0;
    MeshCheck {
        watertight: edges_ok && !mesh.triangles.iter().any(|t| !in_range(t)),
        consistently_oriented: misoriented_edges == 0,
        signed_volume: signed_volume6 / 6.0,
        degenerate_triangles,
        duplicate_triangles,
        boundary_edges,
        non_manifold_edges,
        misoriented_edges,
        coincident_vertices_f32,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solid::{close_top_surface, LengthUnit};

    #[test]
    fn rejects_a_clockwise_rim() {
        let mut v = vec![
            [0.0, 0.0, 1.0],
            [1.0, 0.0, 1.0],
            [1.0, 1.0, 1.0],
            [0.0, 1.0, 1.0],
        ];
        let mut t = vec![[0, 1, 2], [0, 2, 3]];
        assert!(close_top_surface(&mut v.clone(), &mut t.clone(), &[0, 3, 2, 1], 0.0).is_err());
        assert!(close_top_surface(&mut v.clone(), &mut t.clone(), &[0, 1, 2, 3], 1.0).is_err());
        assert!(close_top_surface(&mut v.clone(), &mut t.clone(), &[0, 1, 2, 9], 0.0).is_err());
        close_top_surface(&mut v, &mut t, &[0, 1, 2, 3], 0.0).unwrap();
        assert_eq!((v.len(), t.len()), (9, 2 + 12));
        let check = check_closed(&SolidMesh {
            vertices: v,
            triangles: t,
            offset_um: [0.0; 3],
            units: LengthUnit::Um,
            filled_samples: 0,
            top_triangles: 2,
            base_depth_um: 1.0,
        });
        assert!(check.watertight && check.consistently_oriented);
        assert!((check.signed_volume - 1.0).abs() < 1e-12);
    }
}
