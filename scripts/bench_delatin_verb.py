"""Usage: python scripts/bench_delatin_verb.py PANORAMA.npy ROUGHNESS.npy (the bench kit's venv
with pydelatin; the outputs of `surfstream launch launch/graphs/demo.toml`).

pydelatin held to the `mesh` verb's own criterion on the demo panorama: the whole map and
the verb's 17 windows (972 px at half steps), Sa/Sq/Sz, residual and roughness at 90 % of
the tolerance (the verb's share without footprints), the largest error at all of its limit,
every region less the least-squares plane (as the verb judges)."""
import json, sys
sys.path.insert(0, str(__import__('pathlib').Path(__file__).resolve().parent))
import numpy as np
import bench_model as bm
pano = np.load(sys.argv[1]).astype(np.float64)
rough = np.load(sys.argv[2]).astype(np.float64)
share = 0.9
bm.TOL = {k: v * share for k, v in bm.TOL.items()}
bm.POINTWISE = {"residual": 20.0 * share, "max_error": 50.0}
bm.ROUGHNESS_LIMIT = 5.0 * share
rows, cols = pano.shape
regions = [{"name": "whole", "row0": 0, "col0": 0, "rows": rows, "cols": cols}] + bm.mesher_windows(pano.shape, 972)
print(len(regions), "regions", file=sys.stderr)
r = bm.delatin_at_equal_fidelity(pano, regions, rough, bm.ls_plane(pano))
print(json.dumps({k: v for k, v in r.items() if k != "tried"}, default=float))
for t in r.get("tried", []):
    print(json.dumps({k: t[k] for k in ("bound_um", "triangles", "seconds", "pass")}))
