#!/usr/bin/env python3
"""The model from a tolerance against the paper's path, over scan sets of several kinds.

For each scan set (cut with make_tiles.py from a specimen or a synthetic surface: a polished one
with scratches and spikes, a noisy one, one with missing points, measured specimens), runs
`surfstream stitch` at its defaults (the model from the default tolerance, Sa 1 %, Sq 1 %,
Sz 3 % per region) and reads run.json: the tolerance search's triangles and the Table 6 mesh
stage at the measured points (worst |deviation| of Sa, Sq, Sz over the tile regions, worst
pointwise residual in % of Sq). Beside it, the paper's path computed here from the same
panorama.npy: max pooling by p x p blocks and a grid mesh (two triangles per cell) interpolated
linearly at every measured pixel, judged in the same regions; p = 4 is the paper's, and the
largest p in 8, 4, 2, 1 that meets the tolerance gives the triangles that path needs for it.

    python scripts/bench_model.py --out /tmp/bench-model [--kit ../shared/bench]
        [--specimens ../shared/specimens] [--surfstream target/release/surfstream]
        [--set mesher.model_method='"greedy"' ...] [--label NAME] [--only noisy,missing]

`--set` is passed to every `surfstream stitch` (compare variants of the model: each run writes
OUT/stitch-LABEL/ and OUT/bench_model-LABEL.json); the tiles are cut once and reused.

Prints a Markdown table (and writes OUT/bench_model.json). Needs numpy and scipy (make_tiles);
surfalize for the .x3p / .sur specimens.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

TOL = {"Sa": 1.0, "Sq": 1.0, "Sz": 3.0}


def synthetic(kind: str, n: int = 900, seed: int = 5) -> np.ndarray:
    """A synthetic specimen (um) of `kind`: polished, noisy or missing."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:n, 0:n].astype(float)
    wav = 0.05 * np.sin(x / 90.0) * np.cos(y / 70.0)
    if kind == "polished":
        z = wav + 0.004 * rng.standard_normal((n, n))
        for k in range(6):  # scratches: 1-3 px wide grooves along random lines
            a, b = rng.uniform(-0.5, 0.5), rng.uniform(0, n)
            d = np.abs(y - (a * x + b)) / np.sqrt(1 + a * a)
            w = rng.uniform(0.6, 1.5)
            z -= rng.uniform(0.05, 0.3) * np.exp(-(d / w) ** 2)
        idx = rng.integers(0, n, size=(40, 2))  # single-pixel spikes
        z[idx[:, 0], idx[:, 1]] += rng.uniform(0.1, 0.5, size=40) * rng.choice([-1, 1], 40)
        return z
    if kind == "noisy":
        return 0.5 * np.sin(x / 40.0) * np.cos(y / 55.0) + 0.25 * rng.standard_normal((n, n))
    if kind == "missing":
        from scipy.ndimage import gaussian_filter

        z = gaussian_filter(rng.standard_normal((n, n)), 6) * 8 + wav
        z[rng.random((n, n)) < 0.03] = np.nan
        return z
    raise ValueError(kind)


def make_sets(out: Path, kit: Path, specimens: Path) -> list[tuple[str, Path]]:
    sets = []
    common = ["--overlap", "0.2", "--stage-sigma", "2", "--seed", "1"]
    jobs = [
        ("metropro-1 (measured)", "metropro-1.dat", ["--rows", "2", "--cols", "2", "--tile", "200", "--noise-rel", "0.02"]),
        ("sur-3 (measured)", "sur-3.sur", ["--rows", "2", "--cols", "2", "--tile", "256", "--noise-rel", "0.02"]),
    ]
    for kind, extra in [
        ("polished", ["--noise-rel", "0.01"]),
        ("noisy", ["--noise-rel", "0.05"]),
        ("missing", ["--noise-rel", "0.02", "--dropout", "0.01", "--dropout-blobs", "1.5"]),
    ]:
        spec = out / f"{kind}.npy"
        np.save(spec, synthetic(kind).astype(np.float32))
        jobs.append((f"synthetic {kind}", str(spec), ["--rows", "2", "--cols", "2", "--tile", "480", "--pitch", "0.5"] + extra))
    for name, spec, args in jobs:
        d = out / "tiles" / name.replace(" ", "_").replace("(", "").replace(")", "")
        if not (d / "scan.toml").exists():
            cmd = [sys.executable, str(kit / "make_tiles.py"), spec, str(d), "--specimens", str(specimens)] + common + args
            r = subprocess.run(cmd, capture_output=True, text=True)
            if r.returncode != 0:
                print(f"skip {name}: make_tiles failed: {r.stderr.strip()[-300:]}", file=sys.stderr)
                continue
        sets.append((name, d))
    return sets


def params(z: np.ndarray) -> np.ndarray:
    v = z[~np.isnan(z)]
    v = v - v.mean()
    return np.array([np.abs(v).mean(), np.sqrt((v * v).mean()), v.max() - v.min()])


def grid_mesh_at_pixels(pano: np.ndarray, p: int) -> tuple[np.ndarray, int]:
    """Max-pool by p x p and mesh the pooled grid (two triangles per cell, diagonal (0,0)-(1,1)),
    interpolated linearly at every panorama pixel; the triangle count."""
    r, c = pano.shape
    rp, cp = -(-r // p), -(-c // p)
    padded = np.full((rp * p, cp * p), np.nan, dtype=np.float64)
    padded[:r, :c] = pano
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            pooled = np.nanmax(padded.reshape(rp, p, cp, p), axis=(1, 3))
    if p == 1:
        return pooled[:r, :c], 2 * (r - 1) * (c - 1)
    yy, xx = np.mgrid[0:r, 0:c].astype(float)
    u = np.clip((xx - (p - 1) / 2) / p, 0, cp - 1 - 1e-9)
    v = np.clip((yy - (p - 1) / 2) / p, 0, rp - 1 - 1e-9)
    j0, i0 = np.floor(u).astype(int), np.floor(v).astype(int)
    fu, fv = u - j0, v - i0
    z00, z01 = pooled[i0, j0], pooled[i0, j0 + 1]
    z10, z11 = pooled[i0 + 1, j0], pooled[i0 + 1, j0 + 1]
    upper = fu >= fv
    m = np.where(upper, z00 + fu * (z01 - z00) + fv * (z11 - z01), z00 + fv * (z10 - z00) + fu * (z11 - z10))
    return m, 2 * (rp - 1) * (cp - 1)


def judge(pano: np.ndarray, model: np.ndarray, regions: list[dict]) -> dict:
    worst = {"Sa": 0.0, "Sq": 0.0, "Sz": 0.0, "residual": 0.0}
    for reg in regions:
        sl = (slice(reg["row0"], reg["row0"] + reg["rows"]), slice(reg["col0"], reg["col0"] + reg["cols"]))
        a, b = pano[sl].astype(float), model[sl].astype(float)
        ok = ~np.isnan(a) & ~np.isnan(b)
        a, b = np.where(ok, a, np.nan), np.where(ok, b, np.nan)
        pa, pb = params(a), params(b)
        for k, name in enumerate(["Sa", "Sq", "Sz"]):
            d = (pb[k] - pa[k]) / pa[k] * 100
            if abs(d) > abs(worst[name]):
                worst[name] = d
        ra = a[ok] - a[ok].mean()
        rb = b[ok] - b[ok].mean()
        worst["residual"] = max(worst["residual"], float(np.sqrt(((rb - ra) ** 2).mean()) / pa[1] * 100))
    return worst


def passes(w: dict) -> bool:
    return all(abs(w[k]) <= TOL[k] for k in TOL)


def main() -> int:
    here = Path(__file__).resolve().parent
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench-model"))
    ap.add_argument("--kit", type=Path, default=here.parent.parent / "shared" / "bench")
    ap.add_argument("--specimens", type=Path, default=here.parent.parent / "shared" / "specimens")
    ap.add_argument("--surfstream", type=Path, default=here.parent / "target" / "release" / "surfstream")
    ap.add_argument("--set", action="append", default=[], help="NODE.PARAM=VALUE passed to stitch")
    ap.add_argument("--label", default="", help="names this variant's outputs")
    ap.add_argument("--only", default="", help="comma-separated substrings of the set names to run")
    a = ap.parse_args()
    suffix = f"-{a.label}" if a.label else ""
    a.out.mkdir(parents=True, exist_ok=True)
    rows = []
    only = [w for w in a.only.split(",") if w]
    for name, d in make_sets(a.out, a.kit, a.specimens):
        if only and not any(w in name for w in only):
            continue
        o = a.out / f"stitch{suffix}" / d.name
        cmd = [str(a.surfstream), "stitch", str(d), "-o", str(o)]
        for kv in a.set:
            cmd += ["--set", kv]
        t0 = time.perf_counter()
        r = subprocess.run(cmd, capture_output=True, text=True)
        seconds = time.perf_counter() - t0
        if r.returncode != 0 or not (o / "run.json").exists():
            print(f"{name}: stitch failed: {r.stderr.strip()[-400:]}", file=sys.stderr)
            continue
        run = json.loads((o / "run.json").read_text())
        tol = run["stages"]["mesher"].get("tolerance", {})
        dev = run["deviation"]
        mesh = dev["stages"]["mesh"]
        ours = {"Sa": 0.0, "Sq": 0.0, "Sz": 0.0}
        for reg in mesh["regions"].values():
            for k in ours:
                d = reg["deviation_pct"][k]
                if d is not None and abs(d) > abs(ours[k]):
                    ours[k] = d
        pano = np.load(o / "panorama.npy").astype(np.float64)
        measured_px = int((~np.isnan(pano)).sum())
        regions = dev["regions"]
        paper = {}
        for p in [8, 4, 2, 1]:
            m, tri = grid_mesh_at_pixels(pano, p)
            paper[p] = (judge(pano, m, regions), tri)
        need = next(((p, paper[p][1]) for p in [8, 4, 2, 1] if passes(paper[p][0])), None)
        p4, p4_tri = paper[4]
        rows.append({
            "set": name,
            "panorama_px": list(pano.shape),
            "measured_px": measured_px,
            "ours": {**ours, "residual": mesh.get("worst_residual_rms_pct_of_sq"),
                     "surface_triangles": tol.get("surface_triangles"),
                     "triangles_per_measured_px": tol.get("triangles_per_measured_px"),
                     "met": tol.get("met"), "table6_mesh_pass": mesh.get("pass"),
                     "verdict_pass": dev.get("pass"), "stitch_seconds": seconds,
                     "checkpoints": len(tol.get("curve", []))},
            "paper_pool4": {**p4, "triangles": p4_tri, "triangles_per_measured_px": p4_tri / measured_px},
            "paper_needs": None if need is None else {"pool": need[0], "triangles": need[1],
                                                         "triangles_per_measured_px": need[1] / measured_px},
        })
    (a.out / f"bench_model{suffix}.json").write_text(json.dumps(rows, indent=1))
    print("| set | ours: worst Sa / Sq / Sz % | residual % of Sq | surface triangles (per measured px) | Table 6 mesh / verdict | paper 4x4 max pool + grid: worst Sa / Sq / Sz % | residual | triangles (per px) | paper's path at the tolerance needs | stitch s |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        o, p, n = r["ours"], r["paper_pool4"], r["paper_needs"]
        need = "not met even at p = 1" if n is None else f"pool {n['pool']}: {n['triangles']} ({n['triangles_per_measured_px']:.3f})"
        print(f"| {r['set']} | {o['Sa']:+.2f} / {o['Sq']:+.2f} / {o['Sz']:+.2f} | {o['residual'] or float('nan'):.1f} | "
              f"{o['surface_triangles']} ({o['triangles_per_measured_px'] or float('nan'):.3f}) | {'PASS' if o['table6_mesh_pass'] else 'FAIL'} / {'PASS' if o['verdict_pass'] else 'FAIL'} | "
              f"{p['Sa']:+.2f} / {p['Sq']:+.2f} / {p['Sz']:+.2f} | {p['residual']:.1f} | {p['triangles']} ({p['triangles_per_measured_px']:.3f}) | {need} | {o['stitch_seconds']:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
