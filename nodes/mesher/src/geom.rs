//! Small f64 vector helpers shared by the mesh builder, the checker and the STL writers.

#[inline]
pub(crate) fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

#[inline]
pub(crate) fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

#[inline]
pub(crate) fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Twice the area vector of triangle (a, b, c): its direction is the right-handed normal of the
/// winding a -> b -> c.
#[inline]
pub(crate) fn area_vector2(a: [f64; 3], b: [f64; 3], c: [f64; 3]) -> [f64; 3] {
    cross(sub(b, a), sub(c, a))
}

/// Unit normal of triangle (a, b, c) by the right-hand rule, computed in f64 so that the
/// micrometre-sized facets of a fine grid keep a precise direction; zero for a degenerate one.
#[inline]
pub(crate) fn unit_normal(a: [f64; 3], b: [f64; 3], c: [f64; 3]) -> [f64; 3] {
    let n = area_vector2(a, b, c);
    let len = dot(n, n).sqrt();
    if len > 0.0 && len.is_finite() {
        [n[0] / len, n[1] / len, n[2] / len]
    } else {
        [0.0; 3]
    }
}

/// The smallest interior angle of triangle `p`, degrees (0 for a degenerate one): what the DEM
/// engines check at import (module `target`).
pub(crate) fn min_angle_deg(p: [[f64; 3]; 3]) -> f64 {
    let mut min = f64::INFINITY;
    for k in 0..3 {
        let (u, v) = (sub(p[(k + 1) % 3], p[k]), sub(p[(k + 2) % 3], p[k]));
        let c = cross(u, v);
        min = min.min(dot(c, c).sqrt().atan2(dot(u, v)).to_degrees());
    }
    if min.is_finite() {
        min
    } else {
        0.0
    }
}
