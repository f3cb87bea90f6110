#!/usr/bin/env python3
"""Runs the real LIGGGHTS binary on an ASCII STL sheet (in m) made by `surfstream mesh --target
liggghts`: imports it as a `mesh/surface` wall, drops a lattice of spheres onto it at 0.05 m/s
and runs STEPS steps. Prints the import line, the wall's triangles and the loop time per step.

    python3 scripts/liggghts_sheet.py SHEET.stl [--steps 1000] [--diameter-um 30] [--keep DIR]

Exits non-zero when LIGGGHTS fails (e.g. "Bad mesh" on slivers). Standard library only.
"""
import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile


def bounds(stl):
    lo, hi = [float("inf")] * 3, [float("-inf")] * 3
    n = 0
    with open(stl) as f:
        for line in f:
            s = line.split()
            if s and s[0] == "vertex":
                n += 1
                for k in range(3):
                    v = float(s[k + 1])
                    lo[k], hi[k] = min(lo[k], v), max(hi[k], v)
    return lo, hi, n // 3


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("stl")
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--diameter-um", type=float, default=30.0)
    ap.add_argument("--keep", help="folder to keep the input and log in")
    a = ap.parse_args()
    lo, hi, triangles = bounds(a.stl)
    d = a.diameter_um * 1e-6
    span = [hi[k] - lo[k] for k in range(3)]
    # Spheres on a lattice of 4/3 diameters over the inner 80 % of the sheet, starting one
    # diameter above its highest point, moving down into contact.
    margin = [0.1 * span[0], 0.1 * span[1]]
    spacing = 4.0 / 3.0 * d
    z0 = hi[2] + d
    z1 = z0 + 4 * spacing
    text = f"""atom_style granular
atom_modify map array
boundary f f f
newton off
communicate single vel yes
units si
region domain block {lo[0] - 2 * d:e} {hi[0] + 2 * d:e} {lo[1] - 2 * d:e} {hi[1] + 2 * d:e} {lo[2] - 4 * d:e} {z1 + 4 * d:e} units box
create_box 1 domain
neighbor {d / 3:e} bin
neigh_modify delay 0
fix m1 all property/global youngsModulus peratomtype 5e6
fix m2 all property/global poissonsRatio peratomtype 0.45
fix m3 all property/global coefficientRestitution peratomtypepair 1 0.3
fix m4 all property/global coefficientFriction peratomtypepair 1 0.5
pair_style gran model hertz tangential history
pair_coeff * *
timestep 1e-7
fix gravi all gravity 9.81 vector 0.0 0.0 -1.0
fix cad all mesh/surface file wall.stl type 1
fix walls all wall/gran model hertz tangential history mesh n_meshes 1 meshes cad
region pr block {lo[0] + margin[0]:e} {hi[0] - margin[0]:e} {lo[1] + margin[1]:e} {hi[1] - margin[1]:e} {z0:e} {z1:e} units box
lattice sc {spacing:e}
create_atoms 1 region pr
set group all density 2500 diameter {d:e}
velocity all set 0 0 -0.05 units box
fix integr all nve/sphere
thermo_modify lost ignore norm no
thermo {max(a.steps // 5, 1)}
run {a.steps}
"""
    work = a.keep or tempfile.mkdtemp(prefix="liggghts-sheet-")
    os.makedirs(work, exist_ok=True)
    shutil.copyfile(a.stl, os.path.join(work, "wall.stl"))
    with open(os.path.join(work, "in.sheet"), "w") as f:
        f.write(text)
    exe = shutil.which("liggghts")
    if not exe:
        sys.exit("liggghts is not on PATH (Debian package liggghts)")
    r = subprocess.run([exe, "-in", "in.sheet"], cwd=work, capture_output=True, text=True)
    log = r.stdout + r.stderr
    with open(os.path.join(work, "log.txt"), "w") as f:
        f.write(log)
    imported = re.search(r"Import and parallelization of mesh \S+ containing (\d+) triangle", log)
    loop = re.search(r"Loop time of ([0-9.eE+-]+) on (\d+) procs for (\d+) steps with (\d+) atoms", log)
    aspect = re.findall(r"(\d+) elements have high aspect ratio", log)
    if r.returncode != 0 or "ERROR" in log or not loop:
        tail = "\n".join(log.splitlines()[-25:])
        sys.exit(f"LIGGGHTS failed (exit {r.returncode}) on {a.stl}:\n{tail}")
    t, procs, steps, atoms = float(loop[1]), int(loop[2]), int(loop[3]), int(loop[4])
    print(f"{a.stl}: {triangles} triangles in the STL; LIGGGHTS imported "
          f"{imported[1] if imported else '?'}; high-aspect-ratio warnings: "
          f"{aspect[0] if aspect else 0}; {atoms} spheres of {a.diameter_um} um, {steps} steps "
          f"in {t:.3f} s on {procs} proc(s): {t / steps * 1e3:.3f} ms per step")
    if not a.keep:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
