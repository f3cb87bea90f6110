#!/usr/bin/env python3
"""`surfstream separate` vs numpy + PyWavelets doing the same job on one map.

The job: load a .npy, sym5 level 8 (symmetric border) 2-D decomposition, datum = the
reconstruction from the approximation alone, roughness = map - datum, 4 x 4 max pooling, save
datum / roughness / pooled as .npy. Both sides are timed end to end (wall clock, best of
--repeat runs), surfstream as the CLI (process start included).

    python3 scripts/bench_separate_vs_pywt.py --size 4096 --bin target/release/surfstream
"""
import argparse
import os
import subprocess
import sys
import tempfile
import time

import numpy as np
import pywt


def python_job(src, out):
    z = np.load(src)
    coeffs = pywt.wavedec2(z, "sym5", mode="symmetric", level=8)
    coeffs = [coeffs[0]] + [tuple(np.zeros_like(d) for d in c) for c in coeffs[1:]]
    datum = pywt.waverec2(coeffs, "sym5", mode="symmetric")[: z.shape[0], : z.shape[1]]
    rough = (z - datum).astype(np.float32)
    r, c = z.shape[0] // 4 * 4, z.shape[1] // 4 * 4
    pooled = z[:r, :c].reshape(r // 4, 4, c // 4, 4).max(axis=(1, 3))
    np.save(os.path.join(out, "datum.npy"), datum)
    np.save(os.path.join(out, "roughness.npy"), rough)
    np.save(os.path.join(out, "pooled.npy"), pooled)
    return datum


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=4096)
    ap.add_argument("--bin", default="target/release/surfstream")
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    rng = np.random.default_rng(7)
    n = a.size
    y, x = np.mgrid[0:n, 0:n] / n
    z = np.sin(6 * x) + 0.5 * np.cos(9 * y) + 0.05 * rng.standard_normal((n, n))
    with tempfile.TemporaryDirectory() as d:
        src = os.path.join(d, "map.npy")
        np.save(src, z)
        py_out = os.path.join(d, "py")
        rs_out = os.path.join(d, "rs")
        os.makedirs(py_out)
        t_py = []
        for _ in range(a.repeat):
            t0 = time.perf_counter()
            datum_py = python_job(src, py_out)
            t_py.append(time.perf_counter() - t0)
        t_rs = []
        for _ in range(a.repeat):
            t0 = time.perf_counter()
            subprocess.run(
                [a.bin, "separate", src, "--wavelet", "sym5", "--level", "8", "--pool", "4",
                 "--pitch-um", "1", "-o", rs_out],
                check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            t_rs.append(time.perf_counter() - t0)
        datum_rs = np.load(os.path.join(rs_out, "datum.npy"))
        diff = float(np.max(np.abs(datum_rs - datum_py)))
    best_py, best_rs = min(t_py), min(t_rs)
    print(f"size {n} x {n}: numpy+PyWavelets {best_py:.3f} s, surfstream separate {best_rs:.3f} s, "
          f"ratio {best_py / best_rs:.2f}x; max |datum difference| {diff:.2e} um "
          f"(pywt {pywt.__version__}, numpy {np.__version__}, cpus {os.cpu_count()})")


if __name__ == "__main__":
    sys.exit(main())
