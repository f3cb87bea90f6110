#!/usr/bin/env python3
"""ISO 25178 parameters on 4096^2, surfalize beside ours, interleaved round by round on the
same array, so both see the same machine load.

    python scripts/bench_params.py --all [--rounds 3] [--input bench-out/inputs/synth_4096.npy]
    python scripts/bench_params.py [--rounds 3] [--reps 3] [--input ...]

--all: every parameter both compute (height, hybrid, Sal Str Std, the Sk family, Sxp, the four
volumes, Smr(c), Smc(mr), Spd Spc S5p S5v S10z): `surfstream params FILE --all --jsonl` (the
whole process: reading the .npy, all 35 parameters, printing) against the same parameters from
one fresh surfalize Surface (its caches shared between parameters, as a user gets them), one
repeat per round each; medians over the rounds, the ratio (and its min-max over the rounds),
our process's peak RSS (GNU /usr/bin/time) against the input array's size, and the largest
relative difference of each value. Needs `cargo build --release -p surfstream`.

Without --all: the nine height and hybrid parameters (../shared/bench/params_anchor.py's own
timing function) against common/examples/metrology_bench.

Run from the repository root with the bench venv (.bench-venv/bin/python: surfalize). Needs
`cargo build --release -p surfstream-io --example metrology_bench` (CARGO_TARGET_DIR
honoured). The input is params_anchor.py's timing array (`--save-inputs`); it is written here
when missing. Prints one JSON line per measurement and a summary with medians and ratios,
ours with RAYON_NUM_THREADS=1 and with rayon's default thread count.
"""
import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
BENCH = os.environ.get("SURFSTREAM_BENCH_KIT", os.path.join(ROOT, "..", "shared", "bench"))  # the anchor kit
sys.path.insert(0, BENCH)

import params_anchor  # noqa: E402  (the anchor's own parameter set and timing)
from benchkit import synth_surface  # noqa: E402


def surfalize_all9(z, reps):
    from surfalize import Surface
    ts = []
    for i in range(reps + 1):
        s = Surface(z.copy(), 1.0, 1.0)  # fresh object: surfalize caches per object
        t0 = time.perf_counter()
        p = params_anchor.surfalize_params(s)
        dt = time.perf_counter() - t0
        if i:
            ts.append(dt)
    return float(np.median(ts)), p


def ours(binary, path, reps, threads):
    env = dict(os.environ)
    if threads is None:
        env.pop("RAYON_NUM_THREADS", None)
    else:
        env["RAYON_NUM_THREADS"] = str(threads)
    out = subprocess.run([binary, "params", path, str(reps)], env=env, check=True,
                         capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


SHARED = ["Sa", "Sq", "Sp", "Sv", "Sz", "Ssk", "Sku", "Sdq", "Sdr", "Sal", "Str", "Std",
          "Sk", "Spk", "Svk", "Smr1", "Smr2", "Spkx", "Svkx", "Sxp", "Vmp", "Vmc", "Vvv", "Vvc",
          "Spd", "Spc", "S5p", "S5v", "S10z"]


def surfalize_all(z):
    import warnings
    from surfalize import Surface
    warnings.simplefilter("ignore")
    s = Surface(z.copy(), 1.0, 1.0)
    t0 = time.perf_counter()
    p = {k: float(getattr(s, k)()) for k in SHARED}
    m = float(z.mean())
    p["Smr(c=0um)"] = float(s.Smr(m))
    p["Smc(mr=10%)"] = float(s.Smc(10)) - m
    return time.perf_counter() - t0, p


def ours_all(binary, path):
    """Wall time, the values, and the process's peak RSS in bytes, from GNU time's %M: a
    child's own ru_maxrss would count this Python process's pages (fork's copy of the page
    tables, kept in the high-water mark across exec)."""
    t0 = time.perf_counter()
    p = subprocess.run(["/usr/bin/time", "-f", "%M", binary, "params", path, "--all", "--pitch-um", "1",
                        "--jsonl"], check=True, capture_output=True, text=True)
    dt = time.perf_counter() - t0
    rss = int(p.stderr.strip().splitlines()[-1]) * 1024
    return dt, json.loads(p.stdout.strip().splitlines()[-1]), rss


def main_all(a, target):
    binary = os.path.join(target, "release", "surfstream")
    if not os.path.exists(binary):
        sys.exit(f"{binary} missing: cargo build --release -p surfstream")
    z = np.load(a.input)
    ts = {"surfalize": [], "ours": []}
    rss_all = []
    worst = {}
    for r in range(a.rounds):
        t, theirs = surfalize_all(z)
        ts["surfalize"].append(t)
        print(json.dumps({"round": r, "what": "surfalize", "s": t, "load": os.getloadavg()}), flush=True)
        t, o, rss = ours_all(binary, a.input)
        ts["ours"].append(t)
        rss_all.append(rss)
        print(json.dumps({"round": r, "what": "ours params --all", "s": t, "peak_rss_mib": rss / 2**20,
                          "load": os.getloadavg()}), flush=True)
        for k, v in theirs.items():
            w = o.get(k)
            if k == "Std":  # surfalize measures towards -y (row 0 on top): 180 - ours
                v = (180.0 - v) % 180.0
            if w is None or v != v:
                worst[k] = "both undefined" if (w is None and v != v) else f"ours {w}, surfalize {v}"
                continue
            worst[k] = max(worst.get(k, 0.0) if isinstance(worst.get(k), float) else 0.0,
                           abs(w - v) / max(abs(v), 1e-300))
    med = {k: float(np.median(v)) for k, v in ts.items()}
    print(f"\n{z.shape[0]} x {z.shape[1]}, {len(SHARED) + 2} shared parameters, median of {a.rounds} rounds, interleaved:")
    print(f"  surfalize {med['surfalize']:.2f} s, ours (params --all, whole process) {med['ours']:.2f} s:"
          f" ours {med['surfalize'] / med['ours']:.1f}x faster")
    ratios = [s / o for s, o in zip(ts["surfalize"], ts["ours"])]
    print(f"  ratio per round: min {min(ratios):.1f}x, max {max(ratios):.1f}x")
    print(f"  ours peak RSS {max(rss_all) / 2**20:.0f} MiB = {max(rss_all) / z.nbytes:.2f}x the input's"
          f" {z.nbytes / 2**20:.0f} MiB (float64 array)")
    print("  largest relative difference per parameter: " +
          ", ".join(f"{k} {v:.1e}" if isinstance(v, float) else f"{k} {v}" for k, v in worst.items()))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--all", action="store_true", help="every parameter both compute, via params --all")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--input", default="bench-out/inputs/synth_4096.npy")
    a = ap.parse_args()
    target = os.environ.get("CARGO_TARGET_DIR", os.path.join(ROOT, "target"))
    if not os.path.exists(a.input):
        os.makedirs(os.path.dirname(a.input) or ".", exist_ok=True)
        np.save(a.input, synth_surface(4096, seed=4096))
    if a.all:
        return main_all(a, target)
    binary = os.path.join(target, "release", "examples", "metrology_bench")
    if not os.path.exists(binary):
        sys.exit(f"{binary} missing: cargo build --release -p surfstream-io --example metrology_bench")
    if not os.path.exists(a.input):
        os.makedirs(os.path.dirname(a.input) or ".", exist_ok=True)
        np.save(a.input, synth_surface(4096, seed=4096))
    z = np.load(a.input)
    rows = {"surfalize": [], "ours_1_thread": [], "ours_default_threads": []}
    default_threads = None
    worst_rel = 0.0
    for r in range(a.rounds):
        t, theirs = surfalize_all9(z, a.reps)
        rows["surfalize"].append(t)
        print(json.dumps({"round": r, "what": "surfalize all 9", "median_s": t, "load": os.getloadavg()}))
        for key, threads in (("ours_1_thread", 1), ("ours_default_threads", None)):
            o = ours(binary, a.input, a.reps, threads)
            rows[key].append(o["all_9_params"]["median_s"])
            if threads is None:
                default_threads = o["rayon_threads"]
            for k, v in theirs.items():
                worst_rel = max(worst_rel, abs(o["params"][k] - v) / abs(v))
            print(json.dumps({"round": r, "what": key, "rayon_threads": o["rayon_threads"],
                              "median_s": o["all_9_params"]["median_s"], "load": os.getloadavg()}))
    med = {k: float(np.median(v)) for k, v in rows.items()}
    print(f"\n4096^2, nine parameters, median of {a.rounds} rounds (each a median of {a.reps}), interleaved:")
    print(f"  surfalize: {med['surfalize'] * 1e3:.1f} ms")
    for key, label in (("ours_1_thread", "1 thread"), ("ours_default_threads", f"{default_threads} threads")):
        print(f"  ours, {label}: {med[key] * 1e3:.1f} ms = {med['surfalize'] / med[key]:.1f}x faster")
    print(f"  largest relative difference of the nine values to surfalize's: {worst_rel:.2e}")


if __name__ == "__main__":
    main()
