#!/usr/bin/env python3
"""Side by side: surfstream's error-bounded mesher vs pymeshlab screened Poisson / quadric
decimation, on the very height fields mesh_anchor.py meshed (its --save-inputs .npy files).

    python scripts/bench_mesh.py ANCHOR_JSON INPUT_DIR [--repeats 3] [--out FILE]

For each input in ANCHOR_JSON (the anchor's --out) and each Poisson depth there, meshes the same
.npy with epsilon = that Poisson mesh's achieved interior RMS vertical error, with
RAYON_NUM_THREADS=1 and with the default thread count, and prints a markdown table: time (wall
median and CPU), triangles, our max and RMS error over ALL samples (edges included) against
Poisson's and decimation's (interior and all-points) numbers. Needs the example binary:
cargo build --release -p surfstream-mesher --example bench_adaptive (CARGO_TARGET_DIR honoured).
"""
import argparse
import json
import os
import subprocess
import sys


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("anchor_json")
    ap.add_argument("input_dir")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default="bench-out/mesh_compare.json")
    a = ap.parse_args()
    target = os.environ.get("CARGO_TARGET_DIR", "target")
    exe = os.path.join(target, "release", "examples", "bench_adaptive")
    if not os.path.exists(exe):
        sys.exit(f"{exe} missing: cargo build --release -p surfstream-mesher --example bench_adaptive")
    res = json.load(open(a.anchor_json))
    rows, out = [], []
    for r in res["results"]:
        npy = os.path.join(a.input_dir, r["input"] + ".npy")
        if not os.path.exists(npy):
            print(f"skip {r['input']}: {npy} missing", file=sys.stderr)
            continue
        step = r["step_um"][0]
        for p in r["poisson"]:
            if p.get("threads") not in (1, "1"):
                continue  # the depth-8 reference run with MeshLab's default threads
            eps = p["deviation"]["interior"]["rms_um"]
            ours = {}
            for threads in ("1", None):
                env = dict(os.environ)
                if threads:
                    env["RAYON_NUM_THREADS"] = threads
                else:
                    env.pop("RAYON_NUM_THREADS", None)
                line = subprocess.run([exe, npy, str(step), repr(eps), str(a.repeats)], env=env,
                                      check=True, capture_output=True, text=True).stdout
                ours[threads or "default"] = json.loads(line)
                print(f"{r['input']} depth {p['depth']} threads {threads or 'default'}: "
                      f"{ours[threads or 'default']['median_s']:.3f} s", file=sys.stderr)
            o1, od = ours["1"], ours["default"]
            dall = p["deviation"].get("all", {})
            rows.append((r["input"], "x".join(map(str, r["shape"])), p["depth"], f"{eps:.4g}",
                         f"{p['time']['median_s']:.2f}", f"{p['cpu_time']['median_s']:.2f}",
                         f"{o1['median_s']:.3f}", f"{o1['cpu_median_s']:.2f}", f"{od['median_s']:.3f}",
                         f"{p['time']['median_s'] / o1['median_s']:.0f}x",
                         p["n_faces"], o1["triangles"],
                         f"{p['deviation']['interior']['max_abs_um']:.3g}",
                         f"{dall.get('max_abs_um', float('nan')):.3g}",
                         f"{o1['max_err_vs_f64_input_um']:.4g}", f"{o1['rms_err_vs_f64_input_um']:.4g}",
                         o1["bound_met"] and o1["max_err_vs_f64_input_um"] <= eps * (1 + 1e-6),
                         o1["watertight"]))
            out.append({"input": r["input"], "shape": r["shape"], "poisson": {
                k: p[k] for k in ("depth", "threads", "time", "cpu_time", "n_faces", "deviation")},
                "decimation": {k: r["decimation"][k] for k in ("time", "n_faces", "deviation")},
                "ours_threads_1": o1, "ours_threads_default": od})
    head = ["input", "shape", "Poisson depth", "epsilon um (= Poisson interior RMS)",
            "Poisson s", "Poisson CPU s", "ours s (1 thread)", "ours CPU s", "ours s (default threads)",
            "speed-up (wall, 1 thread)", "Poisson faces", "our triangles (solid)",
            "Poisson interior max um", "Poisson all-points max um", "our max um (all samples)",
            "our RMS um", "our max <= epsilon", "ours watertight"]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for row in rows:
        print("| " + " | ".join(str(x) for x in row) + " |")
    os.makedirs(os.path.dirname(a.out) or ".", exist_ok=True)
    json.dump({"anchor_env": res.get("env"), "rows": out}, open(a.out, "w"), indent=1)


if __name__ == "__main__":
    main()
