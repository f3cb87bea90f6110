#!/usr/bin/env python3
"""Write the PyWavelets parity data that nodes/wavelet/tests/pywt_parity.rs checks against.

    .test-venv/bin/python scripts/gen_wavelet_golden.py target/wavelet-golden
    SURFSTREAM_WAVELET_GOLDEN=target/wavelet-golden cargo test --release -p surfstream-wavelet

scripts/test.sh runs it with the test venv's PyWavelets (pinned in scripts/test-requirements.txt)
before `cargo test`, so the check runs in CI against the real library. ~6 MB, under a second.

Writes into the directory given (created if needed):
  golden.bin   every array, float64 little-endian, row-major, back to back;
  index.txt    one line per array: `key rows cols offset` (offset in values, not bytes),
               plus `level <case> <n>` lines giving each case's decomposition depth.

For every input size, wavelet and mode (a "case", key prefix `<rows>x<cols>/<wavelet>/<mode>`):
  cA<n>, cH<l>, cV<l>, cD<l>   wavedec2(x, level=n), l = n..1 (a decomposition of depth l < n
                               has the same details for levels 1..l, and its cA_l feeds
                               level l+1, so the test checks every depth against these);
  perm                         waverec2 of those coefficients with each level's details
                               rotated (cH, cV, cD) -> (cD, cH, cV): inconsistent coefficients,
                               so it tests the inverse as a linear map, not only as an inverse;
  datum<n>                     waverec2([cA_n, zeros, ...]), uncropped: the separation's datum
                               (sym5 cases only).
Plus `filter/<wavelet>/dec_lo`, `dec_hi`, `rec_lo`, `rec_hi` (1 x L): the filter values
PyWavelets uses, which our table must equal bit for bit.
n is pywt.dwt_max_level of the smaller side, at least 1, and 2 for the tiny cases whose max
level is 0, to cover the border extension of signals shorter than the filter (PyWavelets
allows levels past the maximum with a warning). The inputs `<rows>x<cols>/x` are float32
values held as float64, so the separation test can feed the same data as f32.
"""
import os
import warnings

import numpy as np
import pywt

import sys

WAVELETS = ([f"db{i}" for i in range(1, 11)] + [f"sym{i}" for i in range(2, 11)]
            + [f"coif{i}" for i in range(1, 6)])
# (size, wavelets): every wavelet on an odd x odd, an even x even and a larger even x odd size
# (the latter reaches level 2..6 for every base); the pipeline's sym5 also on odd x even; sym5
# on maps shorter than its 10 taps (repeated reflection / wrap).
CASES = ([((17, 23), w) for w in WAVELETS] + [((24, 24), w) for w in WAVELETS]
         + [((64, 57), w) for w in WAVELETS]
         + [((45, 36), "sym5"), ((5, 7), "sym5"), ((3, 40), "sym5")])
DATUM_WAVELETS = {"sym5"}   # datum golden only for the pipeline's wavelet (keeps the files small)
MODES = ["symmetric", "periodization"]


def surface(rows, cols, seed):
    """A smooth form plus texture plus noise, rounded to float32."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:rows, 0:cols].astype(np.float64)
    z = (0.02 * x * y / max(rows, cols) + np.sin(0.31 * x) * np.cos(0.17 * y)
         + 0.3 * rng.standard_normal((rows, cols)) + 5.0)
    return z.astype(np.float32).astype(np.float64)


def main():
    if len(sys.argv) != 2:
        sys.exit(f"usage: {sys.argv[0]} OUT_DIR")
    out_dir = sys.argv[1]
    os.makedirs(out_dir, exist_ok=True)
    arrays = []        # (key, 2-D array)
    levels = []        # (case, n)

    def put(key, a):
        a = np.ascontiguousarray(np.asarray(a, dtype=np.float64))
        assert a.ndim == 2
        arrays.append((key, a))

    for wname in WAVELETS:
        w = pywt.Wavelet(wname)
        for band in ("dec_lo", "dec_hi", "rec_lo", "rec_hi"):
            put(f"filter/{wname}/{band}", np.asarray(getattr(w, band))[None, :])

    for (rows, cols), wname in CASES:
        size = f"{rows}x{cols}"
        if not any(k == f"{size}/x" for k, _ in arrays):
            x = surface(rows, cols, seed=rows * 1000 + cols)
            put(f"{size}/x", x)
        x = next(a for k, a in arrays if k == f"{size}/x")
        w = pywt.Wavelet(wname)
        n = pywt.dwt_max_level(min(rows, cols), w.dec_len)
        n = n if n >= 1 else 2
        for mode in MODES:
            case = f"{size}/{wname}/{mode}"
            levels.append((case, n))
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")   # levels past the max for the tiny cases
                c = pywt.wavedec2(x, w, mode=mode, level=n)
                put(f"{case}/cA{n}", c[0])
                for lev, (cH, cV, cD) in zip(range(n, 0, -1), c[1:]):
                    put(f"{case}/cH{lev}", cH)
                    put(f"{case}/cV{lev}", cV)
                    put(f"{case}/cD{lev}", cD)
                rot = [c[0]] + [(d[2], d[0], d[1]) for d in c[1:]]
                put(f"{case}/perm", pywt.waverec2(rot, w, mode=mode))
                if wname in DATUM_WAVELETS:
                    z = [c[0]] + [tuple(np.zeros_like(d) for d in lv) for lv in c[1:]]
                    put(f"{case}/datum{n}", pywt.waverec2(z, w, mode=mode))

    offset = 0
    # Written under temporary names and renamed, so a failed run leaves no half a golden set.
    bin_path, idx_path = os.path.join(out_dir, "golden.bin"), os.path.join(out_dir, "index.txt")
    with open(bin_path + ".partial", "wb") as fb, open(idx_path + ".partial", "w") as fi:
        from importlib.metadata import version
        fi.write(f"# PyWavelets {version('PyWavelets')}, numpy {np.__version__}: "
                 "written by scripts/gen_wavelet_golden.py, do not edit\n")
        for case, n in levels:
            fi.write(f"level {case} {n}\n")
        for key, a in arrays:
            fb.write(a.astype("<f8").tobytes())
            fi.write(f"{key} {a.shape[0]} {a.shape[1]} {offset}\n")
            offset += a.size
    os.replace(bin_path + ".partial", bin_path)
    os.replace(idx_path + ".partial", idx_path)
    print(f"gen_wavelet_golden: {len(arrays)} arrays, {offset * 8 / 1024:.0f} KiB in {out_dir}")


if __name__ == "__main__":
    main()
