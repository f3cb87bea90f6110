#!/usr/bin/env python3
"""Stitch scan sets cut from the real specimens, as a user would, and print Table 6's verdict.

Each set is cut with make_tiles.py (2 x 3 tiles, 3 px stage error, piston, tilt, and per set
noise, dropouts and overlap), stitched with `surfstream stitch` at its defaults, and again with
`--tolerance rough=off` (the model judged on the heights only, as before the roughness
judgement): the triangles, the worst region of the roughness the mesh carries (Table 6's
"roughness (mesh - datum)" stage) and the verdict of both, side by side.

    .test-venv/bin/python scripts/bench_real_cuts.py --out /tmp/real-cuts \
        --kit ../shared/bench --specimens ../shared/specimens

Needs numpy and scipy (make_tiles.py) and a release build (target/release/surfstream).
"""
import argparse
import json
import subprocess
import sys
from pathlib import Path

# (name, specimen, make_tiles arguments): smooth and sparse real surfaces, clean and degraded.
SETS = [
    ("x3p-2 15 %", "x3p-2.x3p", "--tile 200 --overlap 0.15"),
    ("sur-uncompressed 20 %", "sur-uncompressed.sur", "--tile 160 --overlap 0.2"),
    ("metropro-1 10 % noisy", "metropro-1.dat", "--tile 200 --overlap 0.1 --noise-rel 0.03"),
    ("x3p-2 30 % noisy, dropouts", "x3p-2.x3p",
     "--tile 256 --overlap 0.3 --noise-rel 0.05 --dropout 0.02"),
    ("metropro-1 20 %", "metropro-1.dat", "--tile 200 --overlap 0.2"),
    ("metropro-1 30 % dropouts", "metropro-1.dat",
     "--tile 160 --overlap 0.3 --noise-rel 0.01 --dropout 0.01"),
    ("sur-3 20 % (89 % not measured)", "sur-3.sur",
     "--tile 150 --overlap 0.2 --dropout 0.01 --dropout-blobs 1"),
    ("sur-uncompressed 10 % noisy", "sur-uncompressed.sur",
     "--tile 128 --overlap 0.1 --noise-rel 0.05"),
]
COMMON = "--rows 2 --cols 3 --stage-sigma 3 --piston 0.05 --tilt-rel 0.5 --quiet"
ROUGHNESS_STAGE = "roughness (mesh - datum)"


def summarise(run_json: Path) -> str:
    r = json.loads(run_json.read_text())
    t = r["stages"]["mesher"]["tolerance"]
    stage = r["deviation"]["stages"][ROUGHNESS_STAGE]
    dev, par, region = max(
        (abs(v["deviation_pct"][q]), q, k)
        for k, v in stage["regions"].items()
        for q in ("Sa", "Sq", "Sz")
    )
    verdict = "PASS" if r["deviation"]["pass"] else "FAIL"
    return (f"{t['surface_triangles']} ({t['triangles_per_measured_px']:.3f}) | "
            f"{par} {dev:.1f} % in {region} | {verdict}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--kit", type=Path, default=Path("../shared/bench"))
    ap.add_argument("--specimens", type=Path, default=Path("../shared/specimens"))
    ap.add_argument("--cli", type=Path, default=Path("target/release/surfstream"))
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    print("| set | heights only: triangles (per measured px) | worst roughness | verdict "
          "| default: triangles (per measured px) | worst roughness | verdict |")
    print("|---|---|---|---|---|---|---|")
    for seed, (name, spec, args) in enumerate(SETS, start=1):
        d = a.out / f"set{seed}"
        cmd = [sys.executable, str(a.kit / "make_tiles.py"), str(a.specimens / spec), str(d),
               "--specimens", str(a.specimens), "--seed", str(seed)]
        subprocess.run(cmd + COMMON.split() + args.split(), check=True, capture_output=True)
        cells = []
        for label, extra in (("heights", ["--tolerance", "rough=off"]), ("default", [])):
            out = d / f"out-{label}"
            run = subprocess.run([str(a.cli), "stitch", str(d / "scan.toml"), "--out", str(out),
                                  "--force"] + extra, capture_output=True, text=True)
            if not (out / "run.json").exists():
                print(f"{name}: stitch failed: {run.stderr[-400:]}", file=sys.stderr)
                return 1
            cells.append(summarise(out / "run.json"))
        print(f"| {name} | {cells[0]} | {cells[1]} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
