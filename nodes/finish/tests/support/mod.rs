//! What the finishing tests against the real engine share: the engine, and Finnie's law
//! integrated analytically to check LIGGGHTS' wear against.

use surfstream_finish::engine::EngineCommand;
use surfstream_finish::setting::{effective_modulus_pa, Media, MediaPhysics, Workpiece};

pub fn engine() -> EngineCommand {
    EngineCommand::locate(1, None).unwrap_or_else(|e| {
        panic!("{e} (these tests need the real engine; scripts/test.sh installs it)")
    })
}

/// Finnie's angle function as LIGGGHTS codes it (mesh_module_stress.cpp), gamma from the plane.
pub fn finnie_f(gamma: f64) -> f64 {
    let (s, c) = gamma.sin_cos();
    if 3.0 * s > c {
        c * c / 3.0
    } else {
        2.0 * s * c - 3.0 * s * s
    }
}

/// Finnie volume of one frictionless, elastic (e = 1) Hertz impact of `media` on a rigid-ish
/// flat of `part` at normal speed `vn` and tangential speed `vt`: LIGGGHTS integrates
/// 2 k |v| |F| f(gamma) dt while the sphere approaches. With F = K d^1.5 (K = 4/3 E* sqrt R)
/// and energy conservation, vn(d)^2 = vn0^2 - 4 K d^2.5 / (5 m); dt = dd / vn; d = dmax sin(t)
/// removes the end-point singularity.
pub fn analytic_finnie_m3(media: &Media, part: &Workpiece, k: f64, vt: f64, vn0: f64) -> f64 {
    let m = media.mass_kg();
    let kk = 4.0 / 3.0 * effective_modulus_pa(media, part) * media.radius_m().sqrt();
    let dmax = (5.0 * m * vn0 * vn0 / (4.0 * kk)).powf(0.4);
    let n = 200_000;
    let mut v = 0.0;
    for i in 0..n {
        let th = (i as f64 + 0.5) / n as f64 * std::f64::consts::FRAC_PI_2;
        let d = dmax * th.sin();
        let dd = dmax * th.cos() * std::f64::consts::FRAC_PI_2 / n as f64;
        let vn = (vn0 * vn0 - 4.0 * kk / (5.0 * m) * d.powf(2.5))
            .max(1e-300)
            .sqrt();
        let f = kk * d.powf(1.5);
        let speed = vt.hypot(vn);
        v += 2.0 * k * speed * f * finnie_f(vn.atan2(vt)) * dd / vn;
    }
    v
}
