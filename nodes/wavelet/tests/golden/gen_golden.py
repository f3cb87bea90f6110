#!/usr/bin/env python3
"""Write the PyWavelets parity data that tests/pywt_parity.rs checks against.

    python3 -m venv /tmp/pywt-venv && /tmp/pywt-venv/bin/pip install PyWavelets==1.9.0 numpy
    /tmp/pywt-venv/bin/python nodes/wavelet/tests/golden/gen_golden.py

Writes, beside this script:
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
n is pywt.dwt_max_level of the smaller side, at least 1, and 2 for the tiny cases whose max
level is 0, to cover the border extension of signals shorter than the filter (PyWavelets
allows levels past the maximum with a warning). The inputs `<rows>x<cols>/x` are float32
values held as float64, so the separation test can feed the same data as f32.
"""
import os
import warnings

import numpy as np
import pywt

HERE = os.path.dirname(os.path.abspath(__file__))
WAVELETS = ["db1", "db4", "sym5", "coif2"]
# (size, wavelets): every wavelet on an odd and an even size; the pipeline's sym5 also on a
# larger odd x even size; sym5 on maps shorter than its 10 taps (repeated reflection / wrap).
CASES = ([((17, 23), w) for w in WAVELETS] + [((24, 24), w) for w in WAVELETS]
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
    arrays = []        # (key, 2-D array)
    levels = []        # (case, n)

    def put(key, a):
        a = np.ascontiguousarray(np.asarray(a, dtype=np.float64))
        assert a.ndim == 2
        arrays.append((key, a))

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
    with open(os.path.join(HERE, "golden.bin"), "wb") as fb, \
            open(os.path.join(HERE, "index.txt"), "w") as fi:
        from importlib.metadata import version
        fi.write(f"# PyWavelets {version('PyWavelets')}, numpy {np.__version__}: "
                 "written by gen_golden.py, do not edit\n")
        for case, n in levels:
            fi.write(f"level {case} {n}\n")
        for key, a in arrays:
            fb.write(a.astype("<f8").tobytes())
            fi.write(f"{key} {a.shape[0]} {a.shape[1]} {offset}\n")
            offset += a.size
    print(f"{len(arrays)} arrays, {offset * 8 / 1024:.0f} KiB")


if __name__ == "__main__":
    main()
