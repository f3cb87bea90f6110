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
# The model's default pointwise bounds (% of the region's Sq): residual RMS and largest error.
POINTWISE = {"residual": 20.0, "max_error": 50.0}


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
    if kind == "tilt":
        # A plane tilted by 2 um over the field (0.5 um pitch: 450 um) carrying a fine
        # roughness of Sq ~0.05 um: the tilt dominates Sa about the mean.
        return 2.0 * (x + 0.6 * y) / n + 0.05 * np.sin(x / 9.0) * np.cos(y / 7.0) + 0.02 * rng.standard_normal((n, n))
    if kind == "form":
        # A cylinder's crown (radius 2 mm at 0.5 um pitch: 6 um of sag over the field) with
        # waviness and roughness on it.
        r_um, xc = 2000.0, 0.5 * (x - n / 2)
        return (-(xc ** 2) / (2 * r_um) + 0.1 * np.sin(x / 30.0) * np.cos(y / 25.0)
                + 0.03 * rng.standard_normal((n, n)))
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
        ("tilt", ["--noise-rel", "0.01", "--level", "none"]),
        ("form", ["--noise-rel", "0.01", "--level", "none"]),
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


def ls_plane(pano: np.ndarray) -> np.ndarray:
    """The least-squares plane of the measured pixels, on the grid (the form the mesher's
    tolerance judges every region without: run.json's `tolerance.judged_plane`)."""
    rows, cols = pano.shape
    y, x = np.mgrid[0:rows, 0:cols].astype(np.float64)
    ok = ~np.isnan(pano)
    a = np.column_stack([np.ones(ok.sum()), x[ok], y[ok]])
    c, *_ = np.linalg.lstsq(a, pano[ok].astype(np.float64), rcond=None)
    return c[0] + c[1] * x + c[2] * y


def judge(pano: np.ndarray, model: np.ndarray, regions: list[dict], plane: np.ndarray | None = None) -> dict:
    """Worst Sa / Sq / Sz deviation (%), residual RMS and largest pointwise error (% of the
    region's Sq; `max_error_um` in um) over the regions, both means removed per region (and
    with `plane`, both less that plane first)."""
    if plane is not None:
        pano, model = pano - plane, model - plane
    worst = {"Sa": 0.0, "Sq": 0.0, "Sz": 0.0, "residual": 0.0, "max_error": 0.0, "max_error_um": 0.0}
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
        e = float(np.abs(rb - ra).max())
        if e / pa[1] * 100 > worst["max_error"]:
            worst["max_error"], worst["max_error_um"] = e / pa[1] * 100, e
    return worst


def passes(w: dict) -> bool:
    return all(abs(w[k]) <= TOL[k] for k in TOL)


def passes_pointwise(w: dict) -> bool:
    """The default tolerance: Sa, Sq, Sz and both pointwise bounds."""
    return passes(w) and all(w[k] <= POINTWISE[k] for k in POINTWISE)


def top_of_stl(stl: Path, pitch: tuple[float, float], um_per_unit: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The top surface of one of our STLs (a solid or a sheet) as (vertex x, y in panorama
    pixels, z in um, faces): a solid's walls and base are left out (triangles with a vertex
    on the base, or with no area in projection); column 0 / row 0 are the smallest x / y of the
    top (the mesher places sample (i, j) at x = j * pitch_x, y = i * pitch_y)."""
    import trimesh

    m = trimesh.load(str(stl), process=True, force="mesh")
    v, f = np.asarray(m.vertices, dtype=np.float64) * um_per_unit, np.asarray(m.faces)
    if m.is_watertight:
        # A solid: its base is the plane of the lowest vertices; drop it and the walls down to it.
        base = v[:, 2] <= v[:, 2].min() + 1e-9 * max(1.0, float(np.abs(v[:, 2]).max()))
        f = f[~base[f].any(axis=1)]
    used = np.unique(f)
    x0, y0 = v[used, 0].min(), v[used, 1].min()
    xy = np.column_stack([(v[:, 0] - x0) / pitch[0], (v[:, 1] - y0) / pitch[1]])
    # Every vertex of ours is a grid sample; the STL's float32 coordinates are not exact.
    return np.round(xy), v[:, 2], f


def judge_stl(stl: Path, pano: np.ndarray, pitch: tuple[float, float], um_per_unit: float,
              regions: list[dict], plane: np.ndarray | None = None) -> dict:
    """Our STL judged independently of the mesher: its top triangles interpolated at every
    measured pixel (as a DEM engine sees the wall), in the Table 6 regions."""
    xy, z, f = top_of_stl(stl, pitch, um_per_unit)
    model = rasterize(xy, z, f, pano.shape)
    w = judge(pano, model, regions, plane)
    w["uncovered_px"] = int((np.isnan(model) & ~np.isnan(pano)).sum())
    w["surface_triangles"] = int(len(f))
    return w


def delatin(pano: np.ndarray, regions: list[dict], plane: np.ndarray | None = None) -> dict:
    """pydelatin (greedy TIN, the sample farthest from the mesh first) at one uniform bound of
    0.5 x the smallest region Sq (the pointwise bound every region asks for, as the issue
    measured it), on the panorama with its missing pixels filled; judged like ours."""
    from pydelatin import Delatin

    lev = pano if plane is None else pano - plane
    sq = min(params(lev[r["row0"]:r["row0"] + r["rows"], r["col0"]:r["col0"] + r["cols"]])[1] for r in regions)
    z = filled(pano)
    rows, cols = z.shape
    t0 = time.perf_counter()
    tin = Delatin(z, width=cols, height=rows, max_error=0.5 * sq * POINTWISE["max_error"] / 50.0)
    seconds = time.perf_counter() - t0
    v, f = np.asarray(tin.vertices, dtype=np.float64), np.asarray(tin.triangles)
    v[:, 1] = rows - 1 - v[:, 1]  # pydelatin's y runs up from the last row
    model = rasterize(v[:, :2], v[:, 2], f, z.shape)
    w = judge(pano, model, regions, plane)
    return {"triangles": int(len(f)), "max_error_um": 0.5 * sq, "seconds": seconds, "worst": w,
            "pass": passes_pointwise(w)}


def delatin_at_equal_fidelity(pano: np.ndarray, regions: list[dict], roughness: np.ndarray | None = None,
                              plane: np.ndarray | None = None) -> dict:
    """The fewest triangles pydelatin needs to meet the whole default tolerance (Sa/Sq 1 %,
    Sz 3 %, residual 20 %, max error 50 % of Sq), judged like ours: its one uniform bound
    searched from 0.5 x the smallest region Sq (x 0.8 down to the first passing bound, or
    x 1.25 up to the first failing one), then bisected geometrically six times between the
    last failing and the first passing bound. With `roughness` (the run's roughness.npy) the
    roughness the mesh carries (roughness + mesh - panorama) must also keep Sa, Sq and Sz
    within 5 % in every region, as the default holds ours to. `search_seconds` is every
    Delatin call of the search (what a user who must find the bound pays), `seconds` the
    passing mesh's alone."""
    from pydelatin import Delatin

    lev = pano if plane is None else pano - plane
    sq = min(params(lev[r["row0"]:r["row0"] + r["rows"], r["col0"]:r["col0"] + r["cols"]])[1] for r in regions)
    z = filled(pano)
    rows, cols = z.shape
    spent = 0.0
    tried = []

    def at(bound: float) -> dict:
        nonlocal spent
        t0 = time.perf_counter()
        tin = Delatin(z, width=cols, height=rows, max_error=bound)
        seconds = time.perf_counter() - t0
        spent += seconds
        v, f = np.asarray(tin.vertices, dtype=np.float64), np.asarray(tin.triangles)
        v[:, 1] = rows - 1 - v[:, 1]  # pydelatin's y runs up from the last row
        model = rasterize(v[:, :2], v[:, 2], f, z.shape)
        w = judge(pano, model, regions, plane)
        ok = passes_pointwise(w)
        if roughness is not None:
            rw = judge(roughness, roughness + model - pano, regions)
            w["roughness"] = max((rw[k] for k in ("Sa", "Sq", "Sz")), key=abs)
            ok = ok and abs(w["roughness"]) <= ROUGHNESS_LIMIT
        w = {k: float(v) for k, v in w.items()}
        r = {"bound_um": float(bound), "triangles": int(len(f)), "seconds": seconds, "worst": w, "pass": bool(ok)}
        tried.append(r)
        return r

    def pointwise_step(r: dict) -> float | None:
        """Just below the bound where a mesh failing only its pointwise bounds (they follow
        the bound) would meet them, as our search steps there (tolerance.rs `pointwise_step`):
        a near miss by the regions' means then costs pydelatin no 0.8 step either."""
        w = r["worst"]
        if r["pass"] or not passes(w) or abs(w.get("roughness", 0.0)) > ROUGHNESS_LIMIT:
            return None
        ratio = min(POINTWISE[k] / w[k] for k in POINTWISE if w[k] > POINTWISE[k])
        return r["bound_um"] * ratio * 0.998

    b0 = 0.5 * sq * POINTWISE["max_error"] / 50.0
    first = at(b0)
    fail, ok = (None, first) if first["pass"] else (first, None)
    near = pointwise_step(first)
    if near is not None:
        r = at(near)
        fail, ok = (fail, r) if r["pass"] else (r, ok)
    step = 1.25 if first["pass"] else 0.8
    b = b0
    for _ in range(25):
        if (ok is not None and fail is not None) or b < 0.004 * b0:
            break
        b *= step
        r = at(b)
        if r["pass"]:
            ok = r if ok is None or r["bound_um"] > ok["bound_um"] else ok
        else:
            fail = r if fail is None or r["bound_um"] < fail["bound_um"] else fail
    if ok is None:
        return {"met": False, "tried": tried, "search_seconds": spent}
    for _ in range(6 if fail is not None else 0):
        r = at(float(np.sqrt(ok["bound_um"] * fail["bound_um"])))
        if r["pass"]:
            ok = r
        else:
            fail = r
    best = min((r for r in tried if r["pass"]), key=lambda r: r["triangles"])
    return {"met": True, **best, "search_seconds": spent, "meshes": len(tried), "tried": tried}


RESIDUAL_LIMIT = 50.0  # the residual bound (% of Sq) the quadric search was measured at (session 3)


def mesher_windows(shape: tuple[int, int], region_px: int) -> list[dict]:
    """The mesher's judged windows (nodes/mesher/src/tolerance.rs `windows`): squares of
    `region_px` at half steps, the last flush with the far edge; the whole map is judged as
    Table 6's "panorama" already."""
    side = max(region_px, 2)
    rows, cols = shape
    if rows <= side and cols <= side:
        return []

    def starts(n: int) -> list[int]:
        if n <= side:
            return [0]
        step = max(side // 2, 1)
        v = []
        k = 0
        while k * step + side < n:
            v.append(k * step)
            k += 1
        if not v or v[-1] != n - side:
            v.append(n - side)
        return v

    rs, cs = starts(rows), starts(cols)
    return [{"name": f"W{i + 1}.{j + 1}", "row0": r0, "col0": c0, "rows": min(side, rows), "cols": min(side, cols)}
            for i, r0 in enumerate(rs) for j, c0 in enumerate(cs)]


def filled(pano: np.ndarray) -> np.ndarray:
    """The panorama with its missing pixels filled smoothly (normalized convolution at growing
    widths), so that a full-grid mesh covers every pixel; the fill is never judged."""
    from scipy.ndimage import gaussian_filter

    z = pano.copy()
    for sigma in (2, 8, 32, 128, 512):
        miss = np.isnan(z)
        if not miss.any():
            break
        w = gaussian_filter((~miss).astype(float), sigma)
        v = gaussian_filter(np.where(miss, 0.0, z), sigma)
        with np.errstate(invalid="ignore", divide="ignore"):
            z = np.where(miss & (w > 1e-6), v / w, z)
    return np.where(np.isnan(z), np.nanmean(pano), z)


def rasterize(xy_px: np.ndarray, z: np.ndarray, faces: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A triangle mesh interpolated linearly at every pixel (vertex x, y in pixels): NaN where no
    triangle covers; where triangles overlap in projection (a fold), the last one wins."""
    rows, cols = shape
    out = np.full(rows * cols, np.nan)
    for start in range(0, len(faces), 200_000):
        f = faces[start:start + 200_000]
        p, h = xy_px[f], z[f]
        x0 = np.clip(np.ceil(p[:, :, 0].min(1) - 1e-9), 0, cols - 1).astype(np.int64)
        x1 = np.clip(np.floor(p[:, :, 0].max(1) + 1e-9), 0, cols - 1).astype(np.int64)
        y0 = np.clip(np.ceil(p[:, :, 1].min(1) - 1e-9), 0, rows - 1).astype(np.int64)
        y1 = np.clip(np.floor(p[:, :, 1].max(1) + 1e-9), 0, rows - 1).astype(np.int64)
        w, hh = np.maximum(x1 - x0 + 1, 0), np.maximum(y1 - y0 + 1, 0)
        n = w * hh
        t = np.repeat(np.arange(len(f)), n)
        k = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
        px = (x0[t] + k % w[t]).astype(float)
        py = (y0[t] + k // w[t]).astype(float)
        a, b, c = p[t, 0], p[t, 1], p[t, 2]
        det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
        with np.errstate(invalid="ignore", divide="ignore"):
            l1 = ((px - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (py - a[:, 1])) / det
            l2 = ((b[:, 0] - a[:, 0]) * (py - a[:, 1]) - (px - a[:, 0]) * (b[:, 1] - a[:, 1])) / det
        l0 = 1 - l1 - l2
        eps = 1e-9
        inside = (det != 0) & (l0 >= -eps) & (l1 >= -eps) & (l2 >= -eps)
        zz = l0 * h[t, 0] + l1 * h[t, 1] + l2 * h[t, 2]
        idx = (py * cols + px).astype(np.int64)
        out[idx[inside]] = zz[inside]
    return out.reshape(rows, cols)


def full_grid(pano: np.ndarray, pitch: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """The full-grid mesh of the panorama (x, y in um, missing pixels filled smoothly, two
    triangles per pixel): vertices and faces."""
    rows, cols = pano.shape
    z = filled(pano)
    yy, xx = np.mgrid[0:rows, 0:cols]
    verts = np.column_stack([xx.ravel() * pitch[0], yy.ravel() * pitch[1], z.ravel()]).astype(np.float64)
    i = (yy[:-1, :-1] * cols + xx[:-1, :-1]).ravel()
    faces = np.concatenate([np.column_stack([i, i + 1, i + cols + 1]), np.column_stack([i, i + cols + 1, i + cols])]).astype(np.int32)
    return verts, faces


def decimate(verts: np.ndarray, faces: np.ndarray, n: int, optimal_placement: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """Quadric edge collapse (pymeshlab) of a mesh to `n` faces: vertices, faces, seconds."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=verts, face_matrix=faces))
    t0 = time.perf_counter()
    ms.meshing_decimation_quadric_edge_collapse(targetfacenum=n, preserveboundary=True, boundaryweight=1.0,
                                                preservenormal=True, preservetopology=True, planarquadric=True,
                                                optimalplacement=optimal_placement)
    secs = time.perf_counter() - t0
    m = ms.current_mesh()
    return m.vertex_matrix(), m.face_matrix(), secs


ROUGHNESS_LIMIT = 5.0  # the model's default bound on the roughness the mesh carries (%)


def judge_mesh(pano: np.ndarray, pitch: tuple[float, float], regions: list[dict], v: np.ndarray, f: np.ndarray,
               roughness: np.ndarray | None = None) -> dict:
    """A decimated mesh judged like the others (interpolated at every measured pixel, Table 6
    regions, the residual bound; every measured pixel must be covered). With `roughness` (the
    run's roughness.npy) also the roughness the mesh carries (roughness + mesh - panorama)
    against it, Sa, Sq, Sz within ROUGHNESS_LIMIT, as the model's default tolerance asks."""
    rows, cols = pano.shape
    xy = np.column_stack([v[:, 0] / pitch[0], v[:, 1] / pitch[1]])
    model = rasterize(xy, v[:, 2], f, (rows, cols))
    w = judge(pano, model, regions)
    ok = passes(w) and w["residual"] <= RESIDUAL_LIMIT
    if roughness is not None:
        r = judge(roughness, roughness + model - pano, regions)
        w["roughness"] = max((r[k] for k in ("Sa", "Sq", "Sz")), key=abs)
        ok = ok and abs(w["roughness"]) <= ROUGHNESS_LIMIT
    uncovered = int((np.isnan(model) & ~np.isnan(pano)).sum())
    return {"faces": int(len(f)), "pass": bool(ok and uncovered == 0), "worst": w, "uncovered_px": uncovered}


def quadric_search(pano: np.ndarray, pitch: tuple[float, float], regions: list[dict], start_faces: int,
                   optimal_placement: bool = True, progressive: bool = False,
                   roughness: np.ndarray | None = None) -> dict:
    """Quadric edge-collapse decimation (Garland-Heckbert; pymeshlab's
    meshing_decimation_quadric_edge_collapse, boundary preserved) of the full-grid mesh of the
    panorama (missing pixels filled), judged like the others: the fewest faces found that meet
    the tolerance and the residual bound. Target counts: from `start_faces`, doubled or halved
    until the result changes, then bisected (geometric) to within 10 %. `optimal_placement`
    False keeps every vertex on a measured sample (collapse to an end point).

    `progressive`: every target below a passing one is decimated from the smallest passing
    mesh found so far instead of from the full grid (a 1.5 M-face grid takes minutes per
    decimation; a decimated mesh of a few hundred thousand faces seconds). Only the first
    decimation (at 8 x `start_faces`, halved from there), and any target above every passing
    one, starts from the full grid.
    `--quadric-check` measures what this changes against the direct decimation."""
    verts, faces = full_grid(pano, pitch)
    full = len(faces)
    tried = {}
    passing: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # target -> mesh, kept when progressive

    def trial(n: int) -> bool:
        n = int(min(max(n, 2), full))
        if n in tried:
            return tried[n]["pass"]
        src_n = min((k for k in passing if k > n), default=None) if progressive else None
        sv, sf = passing[src_n] if src_n is not None else (verts, faces)
        v, f, secs = decimate(sv, sf, n, optimal_placement)
        j = judge_mesh(pano, pitch, regions, v, f, roughness)
        tried[n] = {"target": n, **j, "decimation_s": secs, "from_faces": int(len(sf))}
        if progressive and j["pass"]:
            passing[n] = (v, f)
        w = j["worst"]
        print(f"    quadric {n} (from {len(sf)}) -> {len(f)} faces: Sa {w['Sa']:+.2f} Sq {w['Sq']:+.2f} Sz {w['Sz']:+.2f} "
              f"res {w['residual']:.1f} rough {w.get('roughness', float('nan')):+.2f} {'pass' if j['pass'] else 'fail'} ({secs:.1f} s)",
              file=sys.stderr)
        return j["pass"]

    # Progressive: start well above (a passing mesh is the source of every smaller target).
    n = max(start_faces, 64) if not progressive else min(8 * max(start_faces, 64), full // 2)
    lo, hi = None, None  # largest failing, smallest passing
    for _ in range(8):
        if trial(n):
            hi = n
            if lo is not None:
                break
            n //= 2
        else:
            lo = n
            if hi is not None or n >= full:
                break
            n *= 2
    while lo is not None and hi is not None and hi > 1.1 * lo:
        mid = int(np.sqrt(lo * hi))
        if trial(mid):
            hi = mid
        else:
            lo = mid
    best = tried.get(hi) if hi is not None else None
    return {"full_grid_faces": full, "progressive": progressive,
            "tried": sorted(tried.values(), key=lambda t: t["target"]), "fewest_passing": best}


def quadric_check(pano: np.ndarray, pitch: tuple[float, float], regions: list[dict], direct: dict,
                  optimal_placement: bool) -> list[dict]:
    """The targets a direct search tried, decimated progressively instead (largest from the
    full grid, each next one from the previous result), judged the same way: what the
    progressive search changes, side by side."""
    verts, faces = full_grid(pano, pitch)
    out = []
    src = (verts, faces)
    for t in sorted(direct["tried"], key=lambda t: -t["target"]):
        v, f, secs = decimate(src[0], src[1], t["target"], optimal_placement)
        j = judge_mesh(pano, pitch, regions, v, f)
        out.append({"target": t["target"], "direct": {k: t[k] for k in ("faces", "pass", "worst")},
                    "progressive": {**j, "from_faces": int(len(src[1])), "decimation_s": secs},
                    "direct_s": t.get("decimation_s")})
        w, d = j["worst"], t["worst"]
        print(f"    {t['target']}: direct {t['faces']} {'pass' if t['pass'] else 'fail'} Sa {d['Sa']:+.2f} Sq {d['Sq']:+.2f} "
              f"Sz {d['Sz']:+.2f} res {d['residual']:.1f} ({t.get('decimation_s', 0):.1f} s) | progressive from {len(src[1])}: "
              f"{len(f)} {'pass' if j['pass'] else 'fail'} Sa {w['Sa']:+.2f} Sq {w['Sq']:+.2f} Sz {w['Sz']:+.2f} "
              f"res {w['residual']:.1f} ({secs:.1f} s)", file=sys.stderr)
        src = (v, f)
    return out


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
    ap.add_argument("--quadric", action="store_true",
                    help="also search the fewest faces that quadric edge-collapse decimation (pymeshlab) needs")
    ap.add_argument("--quadric-again", action="store_true", help="redo the quadric searches kept in OUT")
    ap.add_argument("--quadric-on-samples", action="store_true",
                    help="quadric collapses to an end point (vertices stay on measured samples) instead of the optimal placement")
    ap.add_argument("--quadric-progressive", action="store_true",
                    help="decimate each target below a passing one from that passing mesh, not from the full grid")
    ap.add_argument("--quadric-rough", action="store_true",
                    help="quadric must also keep the roughness it carries within 5 %% (the model's default), judged against roughness.npy")
    ap.add_argument("--quadric-check", action="store_true",
                    help="decimate the targets of the kept direct search progressively and print both")
    ap.add_argument("--delatin", action="store_true",
                    help="also mesh each panorama with pydelatin at 0.5 x the smallest region Sq (pip install pydelatin)")
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
        # The form the tolerance judged its regions without (run.json states it): every
        # mesh here is judged without the same plane, ours and the others alike.
        plane = ls_plane(pano) if tol.get("judged_plane") else None
        paper = {}
        for p in [8, 4, 2, 1]:
            m, tri = grid_mesh_at_pixels(pano, p)
            paper[p] = (judge(pano, m, regions, plane), tri)
        need = next(((p, paper[p][1]) for p in [8, 4, 2, 1] if passes(paper[p][0])), None)
        quadric = None
        if a.quadric:
            # Kept per set (the decimations take minutes on a full grid); --quadric-again redoes.
            variant = (("-samples" if a.quadric_on_samples else "") + ("-progressive" if a.quadric_progressive else "")
                       + ("-rough" if a.quadric_rough else ""))
            cache = a.out / f"quadric{variant}-{o.name}.json"
            pitch = run["stages"]["mesher"].get("pitch_um", [1.0, 1.0])
            if a.quadric_check:
                direct = a.out / f"quadric{'-samples' if a.quadric_on_samples else ''}-{o.name}.json"
                if not direct.exists():
                    print(f"{name}: --quadric-check needs the direct search kept in {direct}", file=sys.stderr)
                else:
                    print(f"{name}: direct against progressive decimation", file=sys.stderr)
                    check = quadric_check(pano, (float(pitch[0]), float(pitch[1])), regions,
                                          json.loads(direct.read_text()), not a.quadric_on_samples)
                    (a.out / f"quadric-check{'-samples' if a.quadric_on_samples else ''}-{o.name}.json").write_text(
                        json.dumps(check, indent=1))
            if cache.exists() and not a.quadric_again:
                quadric = json.loads(cache.read_text())
            else:
                print(f"{name}: quadric decimation of the full grid", file=sys.stderr)
                quadric = quadric_search(pano, (float(pitch[0]), float(pitch[1])), regions,
                                         int(tol.get("surface_triangles") or 1000),
                                         optimal_placement=not a.quadric_on_samples,
                                         progressive=a.quadric_progressive,
                                         roughness=np.load(o / "roughness.npy").astype(np.float64) if a.quadric_rough else None)
                cache.write_text(json.dumps(quadric, indent=1))
        mesher = run["stages"]["mesher"]
        pitch = mesher.get("pitch_um", [1.0, 1.0])
        pitch = (float(pitch[0]), float(pitch[1]))
        um_per_unit = {"m": 1e6, "mm": 1e3, "um": 1.0}[mesher.get("units", "mm")]
        stl_judge = judge_stl(o / "surface.stl", pano, pitch, um_per_unit, regions, plane)
        delatin_row = delatin(pano, regions, plane) if a.delatin else None
        rough_path = o / "roughness.npy"
        rough = np.load(rough_path).astype(np.float64) if rough_path.exists() else None
        delatin_equal = delatin_at_equal_fidelity(pano, regions, rough, plane) if a.delatin else None
        # The regions ours is held to (the issue's "every tile footprint and every mesher
        # window"): Table 6's and the mesher's windows; pydelatin held to the same ones.
        ours_regions = regions + (mesher_windows(pano.shape, int(tol["region_px"])) if tol.get("region_px") else [])
        stl_judge_ours = judge_stl(o / "surface.stl", pano, pitch, um_per_unit, ours_regions, plane)
        delatin_same = (delatin_at_equal_fidelity(pano, ours_regions, rough, plane)
                        if a.delatin and len(ours_regions) > len(regions) else None)
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
            "quadric": quadric,
            "stl_judge": stl_judge,
            "delatin": delatin_row,
            "delatin_equal_fidelity": delatin_equal,
            "regions_ours_meets": len(ours_regions),
            "judged_without_plane": plane is not None,
            "stl_judge_ours_regions": stl_judge_ours,
            "delatin_equal_fidelity_ours_regions": delatin_same,
            "mesh_seconds": mesher.get("mesh_s"),
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
    print()
    print("The STL judged independently (its top triangles interpolated at every measured pixel, tile footprints "
          "and the whole panorama, means removed per region), beside pydelatin at 0.5 x the smallest region Sq:")
    print()
    print("| set | ours: worst Sa / Sq / Sz % | residual % of Sq | max error % of Sq (um) | surface tri (per measured px) | "
          "meets the default (Sa/Sq 1, Sz 3, res 20, max 50) | pydelatin tri (per px) | pydelatin worst Sa / Sq / Sz %, residual, max error % of Sq | pydelatin meets it | pydelatin s | our mesher s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        j, d, mp = r["stl_judge"], r["delatin"], r["measured_px"]
        dtext = ("| - | - | - | - " if d is None else
                 f"| {d['triangles']} ({d['triangles'] / mp:.3f}) | {d['worst']['Sa']:+.2f} / {d['worst']['Sq']:+.2f} / "
                 f"{d['worst']['Sz']:+.2f}, {d['worst']['residual']:.1f}, {d['worst']['max_error']:.1f} | "
                 f"{'yes' if d['pass'] else 'no'} | {d['seconds']:.2f} ")
        print(f"| {r['set']} | {j['Sa']:+.2f} / {j['Sq']:+.2f} / {j['Sz']:+.2f} | {j['residual']:.1f} | "
              f"{j['max_error']:.1f} ({j['max_error_um']:.4g}) | {j['surface_triangles']} ({j['surface_triangles'] / mp:.3f}) | "
              f"{'yes' if passes_pointwise(j) and j['uncovered_px'] == 0 else 'no'} {dtext}| "
              f"{r['mesh_seconds'] if r['mesh_seconds'] is not None else float('nan'):.2f} |")
    if any(r["delatin_equal_fidelity"] for r in rows):
        print()
        print("At equal fidelity: the fewest triangles pydelatin needs to meet the same default tolerance on the same "
              "regions, the roughness it carries within 5 % included (its one bound searched: delatin_at_equal_fidelity), beside ours:")
        print()
        print("| set | ours: surface tri (per measured px) | pydelatin at equal fidelity: tri (per px), bound um | ours / pydelatin triangles | "
              "our mesher s | pydelatin s: the passing mesh / the whole search (meshes) |")
        print("|---|---|---|---|---|---|")
        for r in rows:
            j, e, mp = r["stl_judge"], r["delatin_equal_fidelity"], r["measured_px"]
            ms = r["mesh_seconds"] if r["mesh_seconds"] is not None else float("nan")
            if not e["met"]:
                print(f"| {r['set']} | {j['surface_triangles']} ({j['surface_triangles'] / mp:.3f}) | not met down to "
                      f"{min(t['bound_um'] for t in e['tried']):.4g} um | - | {ms:.2f} | - / {e['search_seconds']:.2f} |")
                continue
            print(f"| {r['set']} | {j['surface_triangles']} ({j['surface_triangles'] / mp:.3f}) | {e['triangles']} "
                  f"({e['triangles'] / mp:.3f}), {e['bound_um']:.4g} | {j['surface_triangles'] / e['triangles']:.2f} | "
                  f"{ms:.2f} | {e['seconds']:.2f} / {e['search_seconds']:.2f} ({e['meshes']}) |")
    if any(r["delatin_equal_fidelity_ours_regions"] for r in rows):
        print()
        print("The same, on the regions ours is held to (Table 6's tile footprints and the whole panorama, and the "
              "mesher's windows): ours judged independently there, pydelatin's bound searched until it meets them all:")
        print()
        print("| set | regions | ours meets them (independent judge): worst max error % of Sq, residual | ours: surface tri (per px) | "
              "pydelatin at equal fidelity there: tri (per px), bound um | ours / pydelatin triangles |")
        print("|---|---|---|---|---|---|")
        for r in rows:
            j, e, mp = r["stl_judge_ours_regions"], r["delatin_equal_fidelity_ours_regions"], r["measured_px"]
            if e is None:
                continue
            meets = "yes" if passes_pointwise(j) and j["uncovered_px"] == 0 else "no"
            dtext = (f"not met down to {min(t['bound_um'] for t in e['tried']):.4g} um | -" if not e["met"] else
                     f"{e['triangles']} ({e['triangles'] / mp:.3f}), {e['bound_um']:.4g} | "
                     f"{j['surface_triangles'] / e['triangles']:.2f}")
            print(f"| {r['set']} | {r['regions_ours_meets']} | {meets}: {j['max_error']:.1f}, {j['residual']:.1f} | "
                  f"{j['surface_triangles']} ({j['surface_triangles'] / mp:.3f}) | {dtext} |")
    if any(r["quadric"] for r in rows):
        print()
        print("Surface triangles per measured px at the tolerance (Sa 1 %, Sq 1 %, Sz 3 %, residual <= 50 % of Sq for ours and quadric):")
        print()
        print("| set | ours (balanced) | quadric edge collapse (pymeshlab), fewest passing | quadric: worst Sa / Sq / Sz %, residual | paper's path (max pool + grid) |")
        print("|---|---|---|---|---|")
        for r in rows:
            o, q, n, mp = r["ours"], r["quadric"], r["paper_needs"], r["measured_px"]
            best = q and q["fewest_passing"]
            qtext = "not met" if not best else f"{best['faces']} ({best['faces'] / mp:.3f})"
            wtext = "" if not best else (f"{best['worst']['Sa']:+.2f} / {best['worst']['Sq']:+.2f} / "
                                         f"{best['worst']['Sz']:+.2f}, {best['worst']['residual']:.1f}"
                                         + (f", roughness {best['worst']['roughness']:+.2f}" if "roughness" in best["worst"] else ""))
            ntext = "not met" if n is None else f"pool {n['pool']}: {n['triangles']} ({n['triangles_per_measured_px']:.3f})"
            print(f"| {r['set']} | {o['surface_triangles']} ({o['triangles_per_measured_px'] or float('nan'):.3f}) | "
                  f"{qtext} | {wtext} | {ntext} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
