"""Reference values of the FRT / MNT / Nanoscope specimens from SurfaceTopography (MIT), printed in
surfstream's convention: heights in um, our row r / column c (row-major, first stored row =
row 0). Run: python st_reference.py FILE... (needs `pip install SurfaceTopography`)."""
import sys

import numpy as np
import SurfaceTopography
from SurfaceTopography import open_topography

print("SurfaceTopography", SurfaceTopography.__version__)
for path in sys.argv[1:]:
    reader = open_topography(path)
    t = reader.topography()
    to_um = {"m": 1e6, "mm": 1e3, "µm": 1.0, "nm": 1e-3}[t.unit]  # channel 0 (its default)
    h = np.ma.filled(np.ma.masked_array(t.heights()).astype(float), np.nan) * to_um  # (nx, ny)
    nx, ny = t.nb_grid_pts
    # SurfaceTopography 1.27 flips FRT and Nanoscope rows to image orientation; surfstream keeps
    # the stored order.
    flipped = type(reader).__name__ in ("FRTReader", "DIReader")
    ours = h.T[::-1] if flipped else h.T  # (rows, cols)
    v = ours[np.isfinite(ours)]
    c = v - v.mean()
    sx, sy = t.physical_sizes
    print(f"{path}: {type(reader).__name__}, unit {t.unit}, cols x rows {nx} x {ny}")
    print(f"  pitch_x_um {sx / nx * to_um!r} pitch_y_um {sy / ny * to_um!r}")
    print(f"  not measured {int(np.isnan(ours).sum())}")
    print(f"  mean_um {v.mean()!r} sq_um {np.sqrt((c * c).mean())!r} min_um {v.min()!r} max_um {v.max()!r}")
    print(f"  rms_height_from_area (ST, its unit) {t.rms_height_from_area()!r}")
    rows, cols = ours.shape
    for r, col in [(0, 0), (0, 1), (1, 0), (rows // 3, cols // 2), (rows // 2, cols // 3), (rows - 1, cols - 1)]:
        print(f"  h[row {r}, col {col}] = {ours[r, col]!r}")
