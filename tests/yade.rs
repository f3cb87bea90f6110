//! The STL made for Yade is imported by the real engine (Debian package `yade`;
//! scripts/test.sh installs it): a measured specimen meshed with `--target yade` is loaded with
//! `ymport.stl` as fixed facets, and 30 spheres dropped on it must come to rest on it, every one
//! touching the mesh and none below it.

use std::process::Command;

use surfstream_e2e::dem::{assert_spheres_rest_on, mesh_specimen_for, which};
use surfstream_e2e::read_json;

const SPHERES: usize = 30;

/// Yade script: facets from the STL, spheres placed without overlap above the highest vertex,
/// soft linear Cundall-Strack contacts with damping, 6 ms of settling, final positions to
/// JSON.
const SETTLE_PY: &str = r#"
import json, random
from yade import ymport
r = 3e-6
O.materials.append(FrictMat(young=1e5, poisson=0.3, density=2500, frictionAngle=0.5, label='m'))
facets = ymport.stl('wall.stl', material='m')
O.bodies.append(facets)
xs, ys, zs = [], [], []
for f in facets:
    for v in f.shape.vertices:
        p = f.state.pos + f.state.ori * v
        xs.append(p[0]); ys.append(p[1]); zs.append(p[2])
x0, x1, y0, y1, zmax = min(xs), max(xs), min(ys), max(ys), max(zs)
random.seed(1)
placed, ids = [], []
while len(ids) < SPHERES:
    p = (random.uniform(x0 + 2*r, x1 - 2*r), random.uniform(y0 + 2*r, y1 - 2*r),
         random.uniform(zmax + 1.5*r, zmax + 7*r))
    if all(sum((a - b)**2 for a, b in zip(p, q)) > (2.2*r)**2 for q in placed):
        placed.append(p)
        ids.append(O.bodies.append(sphere(p, r, material='m')))
O.engines = [
    ForceResetter(),
    InsertionSortCollider([Bo1_Sphere_Aabb(), Bo1_Facet_Aabb()]),
    InteractionLoop([Ig2_Sphere_Sphere_ScGeom(), Ig2_Facet_Sphere_ScGeom()],
                    [Ip2_FrictMat_FrictMat_FrictPhys()],
                    [Law2_ScGeom_FrictPhys_CundallStrack()]),
    NewtonIntegrator(gravity=(0, 0, -9.81), damping=0.4),
]
O.dt = 0.5 * PWaveTimeStep()
O.run(int(6e-3 / O.dt), True)
json.dump({'facets': len(facets), 'spheres': [list(O.bodies[i].state.pos) + [r] for i in ids]},
          open('final.json', 'w'))
"#;

#[test]
fn yade_imports_the_wall_and_spheres_settle_on_it() {
    let yade = which("yade").unwrap_or_else(|| {
        panic!(
            "Yade is not installed: this test needs the Debian package `yade` \
             (scripts/test.sh installs it with apt-get)"
        )
    });
    let dir = tempfile::tempdir().expect("tempdir");
    // ymport.stl welds vertices in O(V^2): 20k triangles (the target's budget) take ~2 min
    // here, 4k take seconds and import the same way.
    let (_, mesh) = mesh_specimen_for(dir.path(), "yade", 4000);

    let script = SETTLE_PY.replace("SPHERES", &SPHERES.to_string());
    std::fs::write(dir.path().join("settle.py"), script).expect("write script");
    let run_out = Command::new(yade)
        .args(["-n", "-x", "settle.py"])
        .current_dir(dir.path())
        .output()
        .expect("start yade");
    assert!(
        run_out.status.success(),
        "Yade failed ({:?}):\n{}\n{}",
        run_out.status,
        String::from_utf8_lossy(&run_out.stdout),
        String::from_utf8_lossy(&run_out.stderr)
    );
    let result = read_json(&dir.path().join("final.json"));
    assert_eq!(
        result["facets"].as_u64(),
        Some(mesh.len() as u64),
        "every triangle imported"
    );
    let spheres = result["spheres"].as_array().expect("spheres");
    assert_eq!(spheres.len(), SPHERES);
    let spheres: Vec<[f64; 4]> = spheres
        .iter()
        .map(|s| std::array::from_fn(|k| s[k].as_f64().expect("number")))
        .collect();
    assert_spheres_rest_on(&mesh, &spheres);
}
