#!/usr/bin/env python3
"""`surfstream separate` vs numpy + PyWavelets doing the same job on one map.

The job: load a .npy, sym5 level 8 (symmetric border) 2-D decomposition, datum = the
reconstruction from the approximation alone, roughness = map - datum, 4 x 4 max pooling, save
datum / roughness / pooled as .npy. Both sides are whole processes timed end to end (wall
clock, interpreter / process start and imports included), files in and out, run as
interleaved pairs (anchor, surfstream, anchor, ...) so both see the same machine load; the
medians and the min-max of the per-pair ratios are printed with the load average.

    python3 scripts/bench_separate_vs_pywt.py --size 4096 --bin target/release/surfstream \
        --pairs 7 [--no-sync]

Run with a Python that has numpy and PyWavelets (the bench kit's venv:
bash ../shared/bench/setup.sh .bench-venv). surfstream's outputs are synced to the disk
(its default) unless --no-sync is given; np.save does not sync.
"""
import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np
import pywt

PY_JOB = r"""
import os, sys
import numpy as np, pywt
src, out = sys.argv[1], sys.argv[2]
z = np.load(src)
coeffs = pywt.wavedec2(z, "sym5", mode="symmetric", level=8)
coeffs = [coeffs[0]] + [tuple(np.zeros_like(d) for d in c) for c in coeffs[1:]]
datum = pywt.waverec2(coeffs, "sym5", mode="symmetric")[: z.shape[0], : z.shape[1]]
rough = (z - datum).astype(np.float32)
r, c = z.shape[0] // 4 * 4, z.shape[1] // 4 * 4
pooled = z[:r, :c].reshape(r // 4, 4, c // 4, 4).max(axis=(1, 3))
os.makedirs(out, exist_ok=True)
np.save(os.path.join(out, "datum.npy"), datum)
np.save(os.path.join(out, "roughness.npy"), rough)
np.save(os.path.join(out, "pooled.npy"), pooled)
"""


def timed(cmd):
    """Wall seconds and peak RSS (MiB) of one child process, the RSS from GNU time (a
    child's own rusage would count the pages of the Python process it was forked from)."""
    t0 = time.perf_counter()
    p = subprocess.run(["/usr/bin/time", "-f", "MAXRSS_KB %M"] + cmd, stdout=subprocess.DEVNULL,
                       stderr=subprocess.PIPE, text=True)
    dt = time.perf_counter() - t0
    if p.returncode != 0:
        raise SystemExit(f"{cmd[0]} failed ({p.returncode}): {p.stderr}")
    kb = [l for l in p.stderr.splitlines() if l.startswith("MAXRSS_KB ")][-1].split()[1]
    return dt, int(kb) / 1024.0


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=4096)
    ap.add_argument("--bin", default="target/release/surfstream")
    ap.add_argument("--pairs", type=int, default=7)
    ap.add_argument("--no-sync", action="store_true", help="pass --no-sync to surfstream")
    ap.add_argument("--dir", default=None, help="work folder (default: a temporary one)")
    a = ap.parse_args()
    rng = np.random.default_rng(7)
    n = a.size
    y, x = np.mgrid[0:n, 0:n] / n
    z = np.sin(6 * x) + 0.5 * np.cos(9 * y) + 0.05 * rng.standard_normal((n, n))
    with tempfile.TemporaryDirectory(dir=a.dir) as d:
        src = os.path.join(d, "map.npy")
        np.save(src, z)
        del z, x, y
        py_out, rs_out = os.path.join(d, "py"), os.path.join(d, "rs")
        rs_cmd = [a.bin, "separate", src, "--wavelet", "sym5", "--level", "8", "--pool", "4",
                  "--pitch-um", "1", "-o", rs_out] + (["--no-sync"] if a.no_sync else [])
        py_cmd = [sys.executable, "-c", PY_JOB, src, py_out]
        load0 = os.getloadavg()
        rows = []
        for i in range(a.pairs + 1):  # pair 0 warms the page cache and is not counted
            shutil.rmtree(py_out, ignore_errors=True)
            shutil.rmtree(rs_out, ignore_errors=True)
            t_py, m_py = timed(py_cmd)
            t_rs, m_rs = timed(rs_cmd)
            if i:
                rows.append((t_py, m_py, t_rs, m_rs))
                print(json.dumps({"pair": i, "numpy_pywt_s": round(t_py, 3), "numpy_pywt_mib": round(m_py),
                                  "surfstream_s": round(t_rs, 3), "surfstream_mib": round(m_rs),
                                  "ratio": round(t_py / t_rs, 2), "load1": os.getloadavg()[0]}), flush=True)
        load1 = os.getloadavg()
        datum_py = np.load(os.path.join(py_out, "datum.npy"))
        datum_rs = np.load(os.path.join(rs_out, "datum.npy"))
        rough_py = np.load(os.path.join(py_out, "roughness.npy"))
        rough_rs = np.load(os.path.join(rs_out, "roughness.npy"))
        diff_p = float(np.max(np.abs(np.load(os.path.join(py_out, "pooled.npy"))
                                     - np.load(os.path.join(rs_out, "pooled.npy")))))
        diff = float(np.max(np.abs(datum_rs - datum_py)))
        diff_r = float(np.max(np.abs(rough_rs.astype(np.float64) - rough_py.astype(np.float64))))
    med = lambda k: statistics.median(r[k] for r in rows)
    ratios = [r[0] / r[2] for r in rows]
    print(f"\n{n} x {n}, {a.pairs} interleaved pairs, load average {load0[0]:.2f} -> {load1[0]:.2f}, "
          f"{os.cpu_count()} cpus (pywt {pywt.__version__}, numpy {np.__version__})")
    print(f"numpy+PyWavelets {med(0):.3f} s, {med(1):.0f} MiB; surfstream separate{' --no-sync' if a.no_sync else ''} "
          f"{med(2):.3f} s, {med(3):.0f} MiB; ratio (anchor / surfstream) median {statistics.median(ratios):.2f}x "
          f"(min {min(ratios):.2f}, max {max(ratios):.2f})")
    print(f"max |datum difference| {diff:.2e} um, max |roughness difference| {diff_r:.2e} um, "
          f"max |pooled difference| {diff_p:.2e} um (surfstream separates f32 heights about their mean)")


if __name__ == "__main__":
    sys.exit(main())
