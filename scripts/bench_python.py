#!/usr/bin/env python3
"""The Python package in-process, beside what a Python user reaches for instead:

- ``Surface.params()`` (Sa Sq Sp Sv Sz Ssk Sku Sdq Sdr) vs surfalize 0.19.2's same nine, each
  on a fresh object (surfalize caches per object), on 2048^2 and 4096^2 maps;
- ``surfstream.read`` of a 4096^2 float64 .x3p vs ``surfalize.Surface.load`` of the same file;
- ``Surface.separate`` (sym5, symmetric, level 6: wavedec2 + approximation-only waverec2) vs
  PyWavelets 1.9.0 doing the same, on 2048^2 and 4096^2.

One run, the two side by side, interleaved per size so both see the same machine load; each
timing is the median of ``--reps`` repeats. The maps are ../shared/bench/benchkit.py's
synth_surface (self-affine, Sq 1 um, waviness and tilt). Prints a Markdown table and one JSON
line per measurement.

    .test-venv/bin/python scripts/bench_python.py [--sizes 2048 4096] [--reps 3]

Needs the package installed (pip install ./python) and surfalize, PyWavelets in the venv.
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

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
BENCH = os.environ.get("SURFSTREAM_BENCH_KIT", os.path.join(ROOT, "..", "shared", "bench"))
sys.path.insert(0, BENCH)

from benchkit import synth_surface  # noqa: E402

import surfstream as ss  # noqa: E402

NINE = ["Sa", "Sq", "Sp", "Sv", "Sz", "Ssk", "Sku", "Sdq", "Sdr"]


def timed(fn, reps):
    ts, out = [], None
    for _ in range(reps):
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts), out


def bench_params(z, pitch, reps):
    from surfalize import Surface as SfSurface

    s = ss.Surface(z, pitch)
    t_ours, ours = timed(s.params, reps)

    def sf():
        f = SfSurface(z, pitch, pitch)  # fresh: no cached values
        return {k: float(getattr(f, k)()) for k in NINE}

    t_sf, theirs = timed(sf, reps)
    worst = max(abs(ours[k] - theirs[k]) / max(abs(theirs[k]), 1e-300) for k in NINE)
    return t_ours, t_sf, worst


def bench_read(z, pitch, reps, tmp):
    from surfalize import Surface as SfSurface

    path = os.path.join(tmp, f"map_{z.shape[0]}.x3p")
    ss.Surface(z, pitch).write(path)
    t_ours, s = timed(lambda: ss.read(path), reps)
    t_sf, f = timed(lambda: SfSurface.load(path), reps)
    diff = float(np.nanmax(np.abs(np.asarray(f.data, dtype=np.float64) - s.heights)))
    return t_ours, t_sf, diff, os.path.getsize(path)


def bench_separate(z, pitch, reps, level):
    import pywt

    s = ss.Surface(z, pitch)

    def ours():
        return s.separate(wavelet="sym5", level=level, mode="symmetric")

    def theirs():
        c = pywt.wavedec2(z, "sym5", mode="symmetric", level=level)
        c = [c[0]] + [tuple(np.zeros_like(x) for x in d) for d in c[1:]]
        datum = pywt.waverec2(c, "sym5", mode="symmetric")[: z.shape[0], : z.shape[1]]
        return datum, z - datum

    t_ours, (d, _r) = timed(ours, reps)
    t_pw, (dp, _rp) = timed(theirs, reps)
    diff = float(np.max(np.abs(d.heights - dp)))
    return t_ours, t_pw, diff


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[2048, 4096])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--level", type=int, default=6)
    ap.add_argument("--pitch-um", type=float, default=0.5)
    a = ap.parse_args()
    warnings.simplefilter("ignore")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in a.sizes:
            z = synth_surface(n, step=a.pitch_um, seed=0)
            p = bench_params(z, a.pitch_um, a.reps)
            rows.append((f"params() 9 values, {n}^2", "surfalize", p[0], p[1], f"max rel diff {p[2]:.1e}"))
            if n == max(a.sizes):
                r = bench_read(z, a.pitch_um, a.reps, tmp)
                rows.append((f"read .x3p {n}^2 ({r[3] / 2**20:.0f} MiB)", "surfalize", r[0], r[1],
                             f"max abs diff {r[2]:.1e} um"))
            w = bench_separate(z, a.pitch_um, a.reps, a.level)
            rows.append((f"separate sym5 level {a.level}, {n}^2", "PyWavelets", w[0], w[1],
                         f"datum max abs diff {w[2]:.1e} um"))
            for r in rows[-(3 if n == max(a.sizes) else 2):]:
                print(json.dumps({"what": r[0], "ours_s": r[2], "other": r[1], "other_s": r[3], "note": r[4]}),
                      flush=True)
    print()
    print("| what | surfstream (s) | other | other (s) | speed-up | agreement |")
    print("|---|---|---|---|---|---|")
    for what, other, t_ours, t_other, note in rows:
        print(f"| {what} | {t_ours:.3f} | {other} | {t_other:.3f} | {t_other / t_ours:.1f}x | {note} |")
    print(f"\nmedian of {a.reps}; numpy {np.__version__}, {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
