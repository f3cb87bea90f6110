#!/usr/bin/env python3
"""The mesh job, whole processes, files in and out: `surfstream mesh` against pydelatin at a
bound given, in interleaved rounds (so that both see the same machine load).

    python scripts/bench_mesh_job.py OUT_DIR --bound-um 0.8621 [--rounds 5]
        [--surfstream target/release/surfstream] [--work DIR] [-- MESH_ARGS...]

OUT_DIR is a run's out dir (`surfstream launch launch/graphs/demo.toml -o OUT_DIR`): its
panorama.npy (and roughness.npy, passed to the verb). The pydelatin job is this script run
as `--delatin-job NPY BOUND STL` in its own process: read the .npy, fill the missing pixels
(bench_model's `filled`), `Delatin` at the bound, write a binary STL. The bound is the one
pydelatin needs for the fidelity compared (`scripts/bench_delatin_verb.py` for the verb's
own criterion, `bench_model.py` for the graph's). MESH_ARGS go to the verb (`--no-tiles`).
Each process is timed by `/usr/bin/time` (wall and peak RSS); writes nothing outside --work
(default: a new temporary directory).
"""
import argparse
import json
import os
import re
import statistics
import struct
import subprocess
import sys
import tempfile


def delatin_job(npy: str, bound: float, stl: str) -> None:
    import numpy as np
    from pydelatin import Delatin

    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from bench_model import filled

    z = filled(np.load(npy).astype(np.float64))
    rows, cols = z.shape
    tin = Delatin(z, width=cols, height=rows, max_error=bound)
    v = np.asarray(tin.vertices, dtype=np.float32)
    f = np.asarray(tin.triangles, dtype=np.int64)
    tri = v[f]  # (n, 3, 3)
    with open(stl, "wb") as out:
        out.write(b"\0" * 80 + struct.pack("<I", len(f)))
        rec = np.zeros(len(f), dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])
        rec["v"] = tri
        out.write(rec.tobytes())
    print(json.dumps({"triangles": int(len(f))}))


def timed(cmd: list[str]) -> tuple[float, int, str]:
    """Wall seconds, peak RSS in MB and stderr+stdout of `cmd` under /usr/bin/time."""
    p = subprocess.run(["/usr/bin/time", "-f", "TIME %e %M"] + cmd, capture_output=True, text=True)
    if p.returncode != 0:
        sys.exit(f"bench_mesh_job: {' '.join(cmd)} failed:\n{p.stderr[-2000:]}")
    m = re.findall(r"TIME ([0-9.]+) ([0-9]+)", p.stderr)[-1]
    return float(m[0]), int(m[1]) // 1024, p.stdout + p.stderr


def main() -> None:
    if len(sys.argv) == 5 and sys.argv[1] == "--delatin-job":
        delatin_job(sys.argv[2], float(sys.argv[3]), sys.argv[4])
        return
    argv, mesh_args = sys.argv[1:], []
    if "--" in argv:
        k = argv.index("--")
        argv, mesh_args = argv[:k], argv[k + 1:]
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out_dir")
    ap.add_argument("--bound-um", type=float, required=True)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--surfstream", default="target/release/surfstream")
    ap.add_argument("--work")
    a = ap.parse_args(argv)
    work = a.work or tempfile.mkdtemp(prefix="bench-mesh-job-")
    os.makedirs(work, exist_ok=True)
    pano = os.path.join(a.out_dir, "panorama.npy")
    rough = os.path.join(a.out_dir, "roughness.npy")
    rows = []
    for r in range(a.rounds):
        dl_stl = os.path.join(work, f"delatin-{r}.stl")
        dl = timed([sys.executable, os.path.abspath(__file__), "--delatin-job", pano, repr(a.bound_um), dl_stl])
        ours_stl = os.path.join(work, f"ours-{r}.stl")
        cmd = [a.surfstream, "mesh", pano, "-o", ours_stl] + (["--roughness", rough] if os.path.exists(rough) else []) + mesh_args
        us = timed(cmd)
        tri = re.search(r"met at ([0-9]+) surface triangles", us[2]) or re.search(r"\(([0-9]+) surface\)", us[2])
        row = {"round": r + 1, "load": os.getloadavg()[0],
               "delatin_s": dl[0], "delatin_mb": dl[1], "delatin_triangles": json.loads(dl[2].splitlines()[0])["triangles"],
               "ours_s": us[0], "ours_mb": us[1], "ours_surface_triangles": int(tri.group(1)) if tri else None}
        row["ratio"] = row["delatin_s"] / row["ours_s"]
        rows.append(row)
        print(json.dumps(row), flush=True)
    med = lambda k: statistics.median(r[k] for r in rows)
    print(f"pydelatin median {med('delatin_s'):.2f} s ({min(r['delatin_s'] for r in rows):.2f}-"
          f"{max(r['delatin_s'] for r in rows):.2f}), {rows[0]['delatin_triangles']} tri, {med('delatin_mb'):.0f} MB; "
          f"ours median {med('ours_s'):.2f} s ({min(r['ours_s'] for r in rows):.2f}-{max(r['ours_s'] for r in rows):.2f}), "
          f"{rows[0]['ours_surface_triangles']} surface tri, {med('ours_mb'):.0f} MB; "
          f"per-round pydelatin/ours median {med('ratio'):.2f} ({min(r['ratio'] for r in rows):.2f}-"
          f"{max(r['ratio'] for r in rows):.2f}); work dir {work}")


if __name__ == "__main__":
    main()
