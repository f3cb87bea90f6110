#!/usr/bin/env python3
"""``surfstream.read`` vs ``surfalize.Surface.load`` on every file of the given folders whose
format both read (issue 37: Python read >= surfalize on every format both read).

Each file: both readers once to warm the page cache, then ``--reps`` interleaved rounds
(ours, surfalize, ours, ...), in this process, imports done before; the medians, their ratio
(surfalize / ours: > 1 means ours is faster) and the largest height difference in um where
both give the same shape. Prints a Markdown table and one JSON line per file.

    .test-venv/bin/python scripts/bench_read_formats.py tests/data/specimens ../shared/specimens \\
        [--reps 7] [--x3p-size 4096]

--x3p-size N adds an N x N float64 .x3p written by surfstream (0: none).
"""

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
import warnings

import numpy as np
import surfstream as ss

# Extensions both read (surfalize 0.19.2's file handlers that surfstream also reads).
BOTH = {".x3p", ".sur", ".dat", ".plu", ".vk4", ".opd", ".zmg", ".nms", ".sdf", ".al3d", ".gwy", ".tmd"}


def med(fn, reps):
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts), ts


def one(path, reps):
    from surfalize import Surface as SfSurface

    def ours():
        return ss.read(path)

    def theirs():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return SfSurface.load(path)

    try:
        s, f = ours(), theirs()
    except Exception as e:  # a file one of them refuses: say so, no ratio
        return {"file": os.path.basename(path), "error": f"{type(e).__name__}: {e}"}
    t_ours, t_sf = [], []
    for _ in range(reps):
        t_ours.append(med(ours, 1)[0])
        t_sf.append(med(theirs, 1)[0])
    zo = np.asarray(s.heights, dtype=np.float64)
    zf = np.asarray(f.data, dtype=np.float64)
    diff = None
    if zo.shape == zf.shape:
        # Readers differ in conventions, not values: surfalize may put row 0 at the other edge
        # and may report heights about another origin; compare each about its mean, as read
        # and with the rows flipped, and keep the closer.
        for zc in (zf, zf[::-1]):
            both = np.isfinite(zo) & np.isfinite(zc)
            if both.any():
                a, b = zo[both] - zo[both].mean(), zc[both] - zc[both].mean()
                d = float(np.max(np.abs(a - b)))
                diff = d if diff is None else min(diff, d)
    mo, mf = statistics.median(t_ours), statistics.median(t_sf)
    return {
        "file": os.path.basename(path),
        "bytes": os.path.getsize(path),
        "rows_cols": list(zo.shape),
        "surfstream_s": round(mo, 5),
        "surfalize_s": round(mf, 5),
        "ratio": round(mf / mo, 2),
        "ratio_min": round(min(t_sf) / max(t_ours), 2),
        "ratio_max": round(max(t_sf) / min(t_ours), 2),
        "max_abs_diff_um": diff,
    }


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("dirs", nargs="+")
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--x3p-size", type=int, default=4096)
    a = ap.parse_args()
    paths = []
    for d in a.dirs:
        if os.path.isdir(d):
            paths += sorted(os.path.join(d, f) for f in os.listdir(d) if os.path.splitext(f)[1].lower() in BOTH)
    tmp = tempfile.mkdtemp(prefix="bench_read_")
    if a.x3p_size:
        n = a.x3p_size
        rng = np.random.default_rng(n)
        z = np.cumsum(rng.normal(size=(n, n)), axis=1) * 0.01
        p = os.path.join(tmp, f"map_{n}.x3p")
        ss.Surface(z, 0.8148).write(p)
        paths.append(p)
    load = os.getloadavg()[0]
    rows = [one(p, a.reps) for p in paths]
    for r in rows:
        print(json.dumps(r))
    print(f"\nload average {load:.2f} -> {os.getloadavg()[0]:.2f}, {a.reps} interleaved rounds per file\n")
    print("| file | size | surfstream.read | surfalize load | ratio (min-max) | max abs diff um (about the means) |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        if "error" in r:
            print(f"| {r['file']} | | | | {r['error']} | |")
            continue
        print(f"| {r['file']} | {r['rows_cols'][0]} x {r['rows_cols'][1]}, {r['bytes'] / 1e6:.2f} MB | "
              f"{r['surfstream_s'] * 1e3:.2f} ms | {r['surfalize_s'] * 1e3:.2f} ms | "
              f"{r['ratio']}x ({r['ratio_min']}-{r['ratio_max']}) | {r['max_abs_diff_um']} |")
    for f in os.listdir(tmp):
        os.remove(os.path.join(tmp, f))
    os.rmdir(tmp)


if __name__ == "__main__":
    sys.exit(main())
