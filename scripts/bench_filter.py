#!/usr/bin/env python3
"""The ISO 16610-61 Gaussian filter on 4096^2: scipy.ndimage.gaussian_filter (what surfalize's
GaussianFilter calls, with sigma = alpha lambda_c / (sqrt(2 pi) pitch)) against ours
(nodes/wavelet/examples/bench_filter), interleaved round by round on the same array so both
see the same machine load; ours with RAYON_NUM_THREADS=1 and with rayon's default.

    python scripts/bench_filter.py [--size 4096] [--cutoffs 80,250] [--rounds 3] [--reps 3]

Run from the repository root with a Python that has numpy and scipy (the test venv). Needs
`cargo build --release -p surfstream-wavelet --example bench_filter` (CARGO_TARGET_DIR
honoured). scipy runs in float64 with its default truncation (4 sigma); ours reads the same
array as float32 and truncates at lambda_c (5.3 sigma), i.e. it does more work per point.
Prints one JSON line per measurement, then the medians and the ratios scipy / ours.
"""
import argparse
import json
import math
import os
import subprocess
import tempfile
import time

import numpy as np
import scipy.ndimage as nd

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ALPHA = math.sqrt(math.log(2) / math.pi)


def surface(n, seed=1):
    """Self-affine-like test map (um): filtered noise plus a long wave."""
    rng = np.random.default_rng(seed)
    f = np.fft.rfft2(rng.standard_normal((n, n)))
    ky = np.fft.fftfreq(n)[:, None]
    kx = np.fft.rfftfreq(n)[None, :]
    k = np.hypot(kx, ky)
    k[0, 0] = 1.0
    z = np.fft.irfft2(f * k ** -1.8, s=(n, n))
    z = z / z.std() * 1.3
    x = np.arange(n)
    return z + np.sin(2 * np.pi * x / 1500.0)[None, :]


def scipy_time(z, pitch, cutoff, reps):
    sigma = ALPHA * cutoff / (math.sqrt(2 * math.pi) * pitch)
    ts = []
    for i in range(reps + 1):
        t0 = time.perf_counter()
        nd.gaussian_filter(z, sigma)
        dt = time.perf_counter() - t0
        if i:
            ts.append(dt)
    return float(np.median(ts))


def ours_time(binary, path, pitch, cutoff, reps, threads):
    env = dict(os.environ)
    if threads is None:
        env.pop("RAYON_NUM_THREADS", None)
    else:
        env["RAYON_NUM_THREADS"] = str(threads)
    out = subprocess.run([binary, path, str(pitch), str(cutoff), str(reps)], env=env,
                         check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])["seconds"]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=4096)
    ap.add_argument("--pitch-um", type=float, default=0.8148)
    ap.add_argument("--cutoffs", default="80,250", help="lambda_c values in um")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--reps", type=int, default=3)
    a = ap.parse_args()
    target = os.environ.get("CARGO_TARGET_DIR", os.path.join(ROOT, "target"))
    binary = os.path.join(target, "release", "examples", "bench_filter")
    if not os.path.exists(binary):
        raise SystemExit(f"{binary} missing: cargo build --release -p surfstream-wavelet --example bench_filter")
    z = surface(a.size)
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, f"synth_{a.size}.npy")
        np.save(path, z)
        results = {}
        for cutoff in [float(c) for c in a.cutoffs.split(",")]:
            sigma = ALPHA * cutoff / (math.sqrt(2 * math.pi) * a.pitch_um)
            for r in range(a.rounds):
                for tool, f in [
                    ("scipy", lambda: scipy_time(z, a.pitch_um, cutoff, a.reps)),
                    ("ours_1thread", lambda: ours_time(binary, path, a.pitch_um, cutoff, a.reps, 1)),
                    ("ours_default", lambda: ours_time(binary, path, a.pitch_um, cutoff, a.reps, None)),
                ]:
                    s = f()
                    results.setdefault((cutoff, tool), []).append(s)
                    print(json.dumps({"round": r, "cutoff_um": cutoff, "sigma_px": round(sigma, 2),
                                      "tool": tool, "seconds": round(s, 4)}), flush=True)
    print(f"\n{a.size}^2, pitch {a.pitch_um} um, load average {os.getloadavg()[0]:.2f}, {os.cpu_count()} cpus")
    for cutoff in sorted({c for c, _ in results}):
        med = {t: float(np.median(results[(cutoff, t)])) for c, t in results if c == cutoff}
        print(f"lambda_c {cutoff:g} um: scipy {med['scipy']:.3f} s, ours 1 thread {med['ours_1thread']:.3f} s "
              f"({med['scipy'] / med['ours_1thread']:.1f}x), ours default {med['ours_default']:.3f} s "
              f"({med['scipy'] / med['ours_default']:.1f}x)")


if __name__ == "__main__":
    main()
