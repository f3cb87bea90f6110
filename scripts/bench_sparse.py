#!/usr/bin/env python3
"""Registration on sparse texture: tile sets cut from sparse surfaces, stitched, scored.

    python3 scripts/bench_sparse.py [--quick] [--label NAME] [--bin target/release/surfstream]

1. Specimens (written once to bench-out/sparse/specimens/, seeded):
   - dots:       a near-flat plane (long-wave waviness 5 nm) with white noise 2 nm and a few
                 isolated bumps and pits (radius 2-6 px, 0.2-1 um), about one per 70 x 70 px;
   - dots_rare:  the same, one feature per 130 x 130 px (a 10 % strip holds 0-2);
   - scratches:  polished lay (10 nm, correlated along x over ~200 px, across y over ~2 px) with
                 20 straight scratches (1-3 px wide, 0.05-0.3 um deep) and a few pits;
   - metropro:   ../shared/specimens/metropro-1.dat levelled by a 2nd-order polynomial (a
                 polished part: Sq 4 nm after levelling, a few defects);
   - pills:      ../shared/specimens/sur-uncompressed.sur (isolated pill-shaped features on a
                 plane).
2. Tile sets (bench-out/sparse/sets/): ../shared/bench/make_tiles.py, 3 x 3 grids, 10 % and
   20 % overlap, seeds 1..4 (2 with --quick), the stitch anchors' "noisy" condition: stage error
   3 px (sigma), per-tile piston 1 Sq and tilt 0.5 Sq, white noise 0.05 Sq, 0.5 % dropouts and
   1.5 NaN blobs per tile.
3. Each set stitched with `BIN stitch SET/scan.toml -o SET/out-LABEL` and scored with
   ../shared/bench/score_registration.py (pairs within 0.5 px, global RMS of the tile
   positions after removing the common translation).

Prints a markdown table per specimen and overlap, and writes bench-out/sparse/LABEL.json.
Needs numpy and scipy (and surfalize for the .sur specimen): the .test-venv of scripts/test.sh.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BENCH = os.path.join(REPO, "..", "shared", "bench")
SPECIMENS = os.path.join(REPO, "..", "shared", "specimens")

NOISY = ["--stage-sigma", "3", "--piston-rel", "1.0", "--tilt-rel", "0.5", "--noise-rel", "0.05",
         "--dropout", "0.005", "--dropout-blobs", "1.5", "--blob-radius", "2", "8"]


def bump(z, rng, n, radius, height):
    """Adds n Gaussian bumps / pits at random places."""
    h, w = z.shape
    yy, xx = np.mgrid[0:h, 0:w]
    for _ in range(n):
        cy, cx = rng.uniform(0, h), rng.uniform(0, w)
        r = rng.uniform(*radius)
        a = rng.uniform(*height) * rng.choice([-1.0, 1.0])
        y0, y1 = int(max(0, cy - 4 * r)), int(min(h, cy + 4 * r + 1))
        x0, x1 = int(max(0, cx - 4 * r)), int(min(w, cx + 4 * r + 1))
        d2 = (yy[y0:y1, x0:x1] - cy) ** 2 + (xx[y0:y1, x0:x1] - cx) ** 2
        z[y0:y1, x0:x1] += a * np.exp(-d2 / (2 * r * r))


def smooth_noise(rng, shape, sigma_yx, amp):
    """White noise low-passed by an anisotropic Gaussian (FFT), scaled to rms amp."""
    from scipy import ndimage
    n = ndimage.gaussian_filter(rng.standard_normal(shape), sigma_yx, mode="wrap")
    return n * (amp / n.std())


def make_dots(rng, size, per_px2):
    z = smooth_noise(rng, (size, size), (150, 150), 0.005)
    z += rng.standard_normal((size, size)) * 0.002
    bump(z, rng, int(size * size / per_px2), (2.0, 6.0), (0.2, 1.0))
    return z


def make_scratches(rng, size):
    z = smooth_noise(rng, (size, size), (2, 200), 0.01)
    z += rng.standard_normal((size, size)) * 0.002
    yy, xx = np.mgrid[0:size, 0:size].astype(float)
    for _ in range(20):
        # mostly along the lay (x), some across
        ang = rng.normal(0, 0.35) if rng.uniform() < 0.7 else rng.uniform(0, math.pi)
        cy, cx = rng.uniform(0, size, 2)
        length = rng.uniform(0.2, 1.0) * size
        width = rng.uniform(0.5, 1.5)
        depth = rng.uniform(0.05, 0.3)
        ux, uy = math.cos(ang), math.sin(ang)
        along = (xx - cx) * ux + (yy - cy) * uy
        across = -(xx - cx) * uy + (yy - cy) * ux
        inside = np.abs(along) < length / 2
        z -= depth * np.exp(-across ** 2 / (2 * width ** 2)) * inside
    bump(z, rng, 12, (1.0, 3.0), (0.05, 0.3))
    return z


def specimens(root):
    """name -> (path, extra make_tiles args, tile px)."""
    os.makedirs(root, exist_ok=True)
    out = {}
    rng = np.random.default_rng(20261127)
    synth = {
        "dots": lambda: make_dots(rng, 900, 70 * 70),
        "dots_rare": lambda: make_dots(rng, 900, 130 * 130),
        "scratches": lambda: make_scratches(rng, 900),
    }
    for name, make in synth.items():
        path = os.path.join(root, f"{name}.npy")
        z = make()  # always drawn, so each specimen is the same whatever exists on disk
        if not os.path.exists(path):
            np.save(path, z.astype(np.float64))
        out[name] = (path, ["--pitch", "1.0"], 256)
    out["metropro"] = (os.path.join(SPECIMENS, "metropro-1.dat"), ["--level", "poly2"], 160)
    out["pills"] = (os.path.join(SPECIMENS, "sur-uncompressed.sur"), [], 160)
    return out


def generate(root, seeds, python):
    sets = []
    for name, (path, extra, tile) in specimens(os.path.join(root, "specimens")).items():
        for ov in (0.1, 0.2):
            for seed in seeds:
                d = os.path.join(root, "sets", f"{name}_ov{int(ov * 100)}_s{seed}")
                if not os.path.exists(os.path.join(d, "ground_truth.json")):
                    cmd = [python, os.path.join(BENCH, "make_tiles.py"), path, d, "--rows", "3",
                           "--cols", "3", "--tile", str(tile), "--overlap", str(ov),
                           "--seed", str(seed), "--quiet"] + extra + NOISY
                    subprocess.run(cmd, check=True)
                sets.append((name, ov, seed, d))
    return sets


def score(python, d, out):
    r = subprocess.run([python, os.path.join(BENCH, "score_registration.py"),
                        os.path.join(d, "ground_truth.json"), os.path.join(out, "run.json"),
                        "--json"], capture_output=True, text=True, check=True)
    return json.loads(r.stdout)


def pair_errors(d, out):
    """Per pair: (a, b, error px, accepted by the matcher, reason)."""
    gt = json.load(open(os.path.join(d, "ground_truth.json")))
    run = json.load(open(os.path.join(out, "run.json")))
    px, py = gt["pixel_pitch_um"]["x"], gt["pixel_pitch_um"]["y"]
    pos = {t["index"]: (t["x_um"] / px, t["y_um"] / py) for t in run["tiles"]}
    reg = {(p["a"], p["b"]): p for p in run.get("pairs", [])}
    rows = []
    for p in gt["pairs"]:
        a, b = p["a"], p["b"]
        ex = pos[b][0] - pos[a][0] - p["true_offset_px"][0]
        ey = pos[b][1] - pos[a][1] - p["true_offset_px"][1]
        r = reg.get((a, b)) or reg.get((b, a)) or {}
        rows.append((a, b, math.hypot(ex, ey), bool(r.get("accepted")), r.get("reason")))
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="bench-out/sparse")
    ap.add_argument("--bin", default="target/release/surfstream")
    ap.add_argument("--label", default="current")
    ap.add_argument("--quick", action="store_true", help="seeds 1-2 only")
    ap.add_argument("--only", default=None, help="comma-separated specimen names")
    ap.add_argument("--pairs", action="store_true", help="print every pair beyond 0.5 px")
    a = ap.parse_args()
    python = sys.executable
    seeds = [1, 2] if a.quick else [1, 2, 3, 4]
    sets = generate(a.out, seeds, python)
    if a.only:
        keep = set(a.only.split(","))
        sets = [s for s in sets if s[0] in keep]
    groups = {}
    t0 = time.time()
    for name, ov, seed, d in sets:
        out = os.path.join(d, f"out-{a.label}")
        if os.path.exists(os.path.join(out, "run.json")):
            os.remove(os.path.join(out, "run.json"))
        r = subprocess.run([a.bin, "stitch", os.path.join(d, "scan.toml"), "-o", out],
                           capture_output=True, text=True)
        if not os.path.exists(os.path.join(out, "run.json")):
            print(f"{name} ov{ov} s{seed}: no run.json: {r.stderr[-400:]}", file=sys.stderr)
            continue
        pe = pair_errors(d, out)
        s = score(python, d, out)
        g = groups.setdefault((name, ov), {"errs": [], "rms": [], "stage": 0, "rejected": 0,
                                           "tiles": 0, "partial": 0, "directional": 0})
        g["errs"] += [e for _, _, e, _, _ in pe]
        g["rms"].append(s["global_rms_px"])
        run = json.load(open(os.path.join(out, "run.json")))
        g["stage"] += sum(1 for t in run["tiles"] if t.get("placed_by") != "registration")
        # Tiles placed along one direction by links and along the other by the stage.
        g["partial"] += sum(1 for t in run["tiles"] if t.get("registered_directions") == 1)
        # Refused pairs given to the global solve as one-direction (ridge) constraints.
        g["directional"] += sum(1 for p in run.get("pairs", [])
                                if (p.get("directional") or {}).get("kept_by_global_solve"))
        g["tiles"] += 9
        g["rejected"] += sum(1 for *_, acc, _ in pe if not acc)
        if a.pairs:
            for pa, pb, e, acc, why in pe:
                if e > 0.5:
                    print(f"  {name} ov{int(ov * 100)} s{seed} pair {pa}-{pb}: {e:.2f} px, "
                          f"accepted={acc} {why or ''}")
    rows = []
    print(f"\n{a.label}: {len(sets)} sets in {time.time() - t0:.0f} s\n")
    print("| specimen | overlap | pairs | within 0.5 px | max pair error px | global RMS px "
          "(mean over sets) | worst set RMS px | pairs rejected | one-direction links kept | "
          "tiles placed by stage (of which one direction) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    all_errs, all_rms = [], []
    for (name, ov), g in groups.items():
        e = np.array(g["errs"])
        within = float((e <= 0.5).mean() * 100)
        rms = float(np.mean(g["rms"]))
        rows.append({"specimen": name, "overlap": ov, "pairs": len(e), "within_0p5_pct": within,
                     "max_pair_px": float(e.max()), "global_rms_px_mean": rms,
                     "global_rms_px_max": float(np.max(g["rms"])), "rejected": g["rejected"],
                     "stage_placed": g["stage"], "tiles": g["tiles"],
                     "one_direction_by_stage": g["partial"], "directional_kept": g["directional"]})
        all_errs += list(e)
        all_rms += g["rms"]
        print(f"| {name} | {int(ov * 100)} % | {len(e)} | {within:.0f} % | {e.max():.2f} | "
              f"{rms:.3f} | {np.max(g['rms']):.3f} | {g['rejected']} | {g['directional']} | "
              f"{g['stage']}/{g['tiles']} ({g['partial']}) |")
    e = np.array(all_errs)
    if len(e):
        print(f"| **all** | | {len(e)} | {(e <= 0.5).mean() * 100:.1f} % | {e.max():.2f} | "
              f"{np.mean(all_rms):.3f} | {np.max(all_rms):.3f} | "
              f"{sum(r['rejected'] for r in rows)} | {sum(r['directional_kept'] for r in rows)} | "
              f"{sum(r['stage_placed'] for r in rows)}/{sum(r['tiles'] for r in rows)} "
              f"({sum(r['one_direction_by_stage'] for r in rows)}) |")
    os.makedirs(a.out, exist_ok=True)
    with open(os.path.join(a.out, f"{a.label}.json"), "w") as f:
        json.dump({"label": a.label, "bin": a.bin, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
