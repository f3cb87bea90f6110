//! Geometry for the tests that hand our STL to real DEM engines: read an ASCII STL, the
//! distance from a sphere centre to the mesh, and finding the engine on PATH.

use std::path::{Path, PathBuf};

use crate::{read_json, run, stderr, surfstream};

/// Meshes the specimen `x3p-2.x3p` with `mesh --target ENGINE --max-triangles BUDGET` into
/// `dir/wall.stl`; returns the mesh JSON (its target and format checked) and the triangles.
pub fn mesh_specimen_for(
    dir: &Path,
    engine: &str,
    max_triangles: usize,
) -> (serde_json::Value, Vec<Triangle>) {
    let specimen = crate::specimen("x3p-2.x3p");
    let stl = dir.join("wall.stl");
    let mut cmd = surfstream();
    cmd.arg("mesh")
        .arg(&specimen)
        .args(["--target", engine, "--max-triangles"])
        .arg(max_triangles.to_string())
        .arg("--out")
        .arg(&stl);
    let out = run(cmd);
    assert!(out.status.success(), "{}", stderr(&out));
    let report = read_json(&dir.join("wall.json"));
    assert_eq!(report["target"]["engine"], engine, "{report:#}");
    assert_eq!(report["format"], "ascii");
    assert_eq!(report["kind"], "sheet");
    assert_eq!(report["units"], "m");
    let mesh = read_ascii_stl(&stl);
    assert_eq!(Some(mesh.len() as u64), report["triangles"].as_u64());
    (report, mesh)
}

pub type Triangle = [[f64; 3]; 3];

/// Triangles of an ASCII STL, coordinates as written.
pub fn read_ascii_stl(path: &Path) -> Vec<Triangle> {
    let text = std::fs::read_to_string(path).expect("ASCII STL is UTF-8 text");
    assert!(text.starts_with("solid"), "not an ASCII STL");
    let vertices: Vec<[f64; 3]> = text
        .lines()
        .filter_map(|l| l.trim().strip_prefix("vertex "))
        .map(|v| {
            let c: Vec<f64> = v
                .split_whitespace()
                .map(|s| s.parse().expect("vertex coordinate"))
                .collect();
            [c[0], c[1], c[2]]
        })
        .collect();
    assert_eq!(vertices.len() % 3, 0);
    vertices.chunks(3).map(|t| [t[0], t[1], t[2]]).collect()
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Closest point of triangle `t` to `p` (Ericson, Real-Time Collision Detection, 5.1.5).
fn closest_on_triangle(p: [f64; 3], t: &Triangle) -> [f64; 3] {
    let [a, b, c] = *t;
    let (ab, ac, ap) = (sub(b, a), sub(c, a), sub(p, a));
    let (d1, d2) = (dot(ab, ap), dot(ac, ap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return a;
    }
    let bp = sub(p, b);
    let (d3, d4) = (dot(ab, bp), dot(ac, bp));
    if d3 >= 0.0 && d4 <= d3 {
        return b;
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        let v = d1 / (d1 - d3);
        return [a[0] + v * ab[0], a[1] + v * ab[1], a[2] + v * ab[2]];
    }
    let cp = sub(p, c);
    let (d5, d6) = (dot(ab, cp), dot(ac, cp));
    if d6 >= 0.0 && d5 <= d6 {
        return c;
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        let w = d2 / (d2 - d6);
        return [a[0] + w * ac[0], a[1] + w * ac[1], a[2] + w * ac[2]];
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        let bc = sub(c, b);
        return [b[0] + w * bc[0], b[1] + w * bc[1], b[2] + w * bc[2]];
    }
    let denom = 1.0 / (va + vb + vc);
    let (v, w) = (vb * denom, vc * denom);
    [
        a[0] + ab[0] * v + ac[0] * w,
        a[1] + ab[1] * v + ac[1] * w,
        a[2] + ab[2] * v + ac[2] * w,
    ]
}

/// Distance from `p` to the mesh, and whether `p` is above it (the nearest point's upward side).
pub fn distance_and_side(p: [f64; 3], mesh: &[Triangle]) -> (f64, bool) {
    let mut best = (f64::INFINITY, [0.0; 3]);
    for t in mesh {
        let q = closest_on_triangle(p, t);
        let d = sub(p, q);
        let d2 = dot(d, d);
        if d2 < best.0 {
            best = (d2, q);
        }
    }
    (best.0.sqrt(), p[2] >= best.1[2])
}

/// Asserts that spheres `[x, y, z, radius]` rest on `mesh`: every one above it and not sinking
/// more than 0.1 r into it, and nearly all (90 %; one may rest on another) within 1.02 r of it.
pub fn assert_spheres_rest_on(mesh: &[Triangle], spheres: &[[f64; 4]]) {
    let mut touching = 0;
    for s in spheres {
        let (d, above) = distance_and_side([s[0], s[1], s[2]], mesh);
        assert!(above, "sphere at {s:?} is below the wall");
        assert!(
            d > 0.9 * s[3],
            "sphere at {s:?} sinks {:.3} r into the wall",
            1.0 - d / s[3]
        );
        if d < 1.02 * s[3] {
            touching += 1;
        }
    }
    assert!(
        touching >= spheres.len() * 9 / 10,
        "{touching} of {} spheres touch the wall",
        spheres.len()
    );
}

/// The program `name` on PATH.
pub fn which(name: &str) -> Option<PathBuf> {
    std::env::var_os("PATH").and_then(|paths| {
        std::env::split_paths(&paths)
            .map(|p| p.join(name))
            .find(|p| p.is_file())
    })
}
