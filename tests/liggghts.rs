//! The STL made for LIGGGHTS is imported by the real engine (LIGGGHTS-PUBLIC, Debian package
//! `liggghts`; scripts/test.sh installs it): a measured specimen is meshed with
//! `--target liggghts`, used as a `mesh/surface` wall with `wall/gran`, and 30 spheres dropped on
//! it must come to rest on it: every sphere touches the mesh (centre one radius from the nearest
//! triangle) and none is below it.

use std::process::Command;

use surfstream_e2e::dem::{assert_spheres_rest_on, mesh_specimen_for, read_ascii_stl, which};
use surfstream_e2e::{read_json, run, stderr, surfstream};

/// Sphere radius, m: a few times the specimen's pitch, a tenth of its width.
const RADIUS_M: f64 = 3e-6;
const PARTICLES: usize = 30;

fn liggghts_input(bounds: [[f64; 2]; 3]) -> String {
    let [[x0, x1], [y0, y1], [z0, z1]] = bounds;
    let r = RADIUS_M;
    format!(
        "# {PARTICLES} spheres settling on a measured surface: mesh/surface + wall/gran
atom_style granular
atom_modify map array
boundary f f f
newton off
communicate single vel yes
units si
region domain block {dx0:e} {dx1:e} {dy0:e} {dy1:e} {dz0:e} {dz1:e} units box
create_box 1 domain
neighbor {skin:e} bin
neigh_modify delay 0
fix m1 all property/global youngsModulus peratomtype 5.e6
fix m2 all property/global poissonsRatio peratomtype 0.3
fix m3 all property/global coefficientRestitution peratomtypepair 1 0.1
fix m4 all property/global coefficientFriction peratomtypepair 1 0.5
pair_style gran model hertz tangential history
pair_coeff * *
timestep 5e-8
fix gravity all gravity 9.81 vector 0.0 0.0 -1.0
fix wall all mesh/surface file wall.stl type 1 verbose yes
fix walls all wall/gran model hertz tangential history mesh n_meshes 1 meshes wall
region drop block {ix0:e} {ix1:e} {iy0:e} {iy1:e} {iz0:e} {iz1:e} units box volume_limit 1e-20
fix template all particletemplate/sphere 15485863 atom_type 1 density constant 2500 radius constant {r:e} volume_limit 1e-20
fix distribution all particledistribution/discrete 32452843 1 template 1.0
fix insert all insert/pack seed 32452867 distributiontemplate distribution vel constant 0. 0. 0. insert_every once overlapcheck yes all_in yes particles_in_region {PARTICLES} region drop
fix integrate all nve/sphere
thermo_style custom step atoms ke
thermo 10000
thermo_modify lost ignore norm no
run 60000
write_dump all custom final.txt id x y z radius
",
        dx0 = x0 - 4.0 * r,
        dx1 = x1 + 4.0 * r,
        dy0 = y0 - 4.0 * r,
        dy1 = y1 + 4.0 * r,
        // Room below the lowest point: a sphere that fell through would leave the box.
        dz0 = z0 - 4.0 * r,
        dz1 = z1 + 12.0 * r,
        skin = 0.5 * r,
        ix0 = x0 + 2.0 * r,
        ix1 = x1 - 2.0 * r,
        iy0 = y0 + 2.0 * r,
        iy1 = y1 - 2.0 * r,
        iz0 = z1 + 1.5 * r,
        iz1 = z1 + 7.0 * r,
    )
}

#[test]
fn liggghts_imports_the_wall_and_spheres_settle_on_it() {
    let liggghts = which("liggghts").unwrap_or_else(|| {
        panic!(
            "LIGGGHTS is not installed: this test needs the Debian package `liggghts` \
             (scripts/test.sh installs it with apt-get)"
        )
    });
    let dir = tempfile::tempdir().expect("tempdir");
    // A budget that keeps the simulation short; the default (400k) imports the same way.
    let (report, mesh) = mesh_specimen_for(dir.path(), "liggghts", 30_000);
    assert!(
        report["element_quality"]["min_angle_deg"]
            .as_f64()
            .unwrap_or(0.0)
            > 1.0
    );
    let triangles = mesh.len();
    let mut bounds = [[f64::INFINITY, f64::NEG_INFINITY]; 3];
    for t in &mesh {
        for v in t {
            for (axis, b) in bounds.iter_mut().enumerate() {
                b[0] = b[0].min(v[axis]);
                b[1] = b[1].max(v[axis]);
            }
        }
    }
    // The specimen is 83 um x 204 um: in metres, as LIGGGHTS' `units si` reads it.
    assert!(
        (bounds[0][1] - bounds[0][0] - 82.8e-6).abs() < 1e-6,
        "{bounds:?}"
    );
    assert!(
        (bounds[1][1] - bounds[1][0] - 204.2e-6).abs() < 1e-6,
        "{bounds:?}"
    );

    std::fs::write(dir.path().join("in.settle"), liggghts_input(bounds)).expect("write input");
    let run_out = Command::new(liggghts)
        .args(["-in", "in.settle"])
        .current_dir(dir.path())
        .output()
        .expect("start liggghts");
    let log = String::from_utf8_lossy(&run_out.stdout).to_string();
    assert!(
        run_out.status.success() && !log.contains("ERROR"),
        "LIGGGHTS failed ({:?}):\n{}\n{}",
        run_out.status,
        &log[log.len().saturating_sub(3000)..],
        String::from_utf8_lossy(&run_out.stderr)
    );
    let imported = format!(
        "Import and parallelization of mesh wall containing {triangles} triangle(s) successful"
    );
    assert!(log.contains(&imported), "mesh not imported:\n{log}");
    assert!(
        !log.contains("high aspect ratio"),
        "LIGGGHTS warns about element quality:\n{log}"
    );

    // Final positions: every sphere kept (none left the box by falling through), every sphere
    // above the wall and touching it.
    let dump = std::fs::read_to_string(dir.path().join("final.txt")).expect("final.txt");
    let atoms: Vec<[f64; 4]> = dump
        .lines()
        .skip_while(|l| !l.starts_with("ITEM: ATOMS"))
        .skip(1)
        .map(|l| {
            let c: Vec<f64> = l
                .split_whitespace()
                .map(|s| s.parse().expect("number"))
                .collect();
            [c[1], c[2], c[3], c[4]]
        })
        .collect();
    assert_eq!(
        atoms.len(),
        PARTICLES,
        "spheres lost (fell through or flew off)"
    );
    assert_spheres_rest_on(&mesh, &atoms);
}

/// The graph parameter does what the flag does: `--set mesher.target=liggghts` on the demo
/// writes an ASCII sheet in metres on a regular grid and records the target in run.json.
#[test]
fn graph_parameter_target_liggghts_writes_an_ascii_sheet() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out_dir = dir.path().join("out");
    let mut cmd = surfstream();
    cmd.args([
        "run",
        "launch/graphs/demo.toml",
        "--set",
        "stage.pacing=fast",
    ])
    .args(["--set", "mesher.target=liggghts", "--out"])
    .arg(&out_dir);
    let out = run(cmd);
    assert!(out.status.success(), "{}", stderr(&out));
    let mesh = &read_json(&out_dir.join("run.json"))["stages"]["mesher"];
    assert_eq!(mesh["target"]["engine"], "liggghts", "{mesh:#}");
    assert_eq!(mesh["format"], "ascii");
    assert_eq!(mesh["units"], "m");
    assert_eq!(mesh["method"], "grid");
    assert_eq!(mesh["kind"], "sheet");
    assert!(
        mesh["element_quality"]["min_angle_deg"]
            .as_f64()
            .unwrap_or(0.0)
            > 1.0
    );
    let stl = read_ascii_stl(&out_dir.join("surface.stl"));
    assert_eq!(stl.len() as u64, mesh["triangles"].as_u64().unwrap_or(0));
    assert!(stl.len() <= 400_000);
}
