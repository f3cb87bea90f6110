#!/usr/bin/env python3
"""Side by side in ONE run: surfstream's error-bounded mesher vs pymeshlab screened Poisson
(depth 8 and 10) and quadric decimation, on the very height fields mesh_anchor.py meshes.

    python scripts/bench_mesh.py [--inputs NAMES] [--repeats 3] [--out-dir DIR]
    python scripts/bench_mesh.py --anchor-json FILE --input-dir DIR   # reuse an anchor run
    python scripts/bench_mesh.py FILE DIR                             # the same, older form

Run from the repository root with the bench venv (.bench-venv: pymeshlab, trimesh). By default
the anchor and ours are INTERLEAVED per input: `mesh_anchor.py --only NAME --save-inputs DIR`
(Poisson d8 + d10 with threads=1, decimation), then ours on the same .npy, then the next input,
so that both see the same machine load. For each Poisson depth, ours meshes with epsilon = that
Poisson mesh's achieved interior RMS vertical error, with RAYON_NUM_THREADS=1 and with the
default thread count; our solid is written as STL and checked by trimesh (is_watertight,
is_winding_consistent). Prints a markdown table (times are medians; CPU times beside wall
times because the machine is shared) and writes OUT_DIR/compare.json and compare.md.
Needs: cargo build --release -p surfstream-mesher --example bench_adaptive
(CARGO_TARGET_DIR honoured).
"""
import argparse
import json
import os
import subprocess
import sys

ALL = ["synthetic_256", "synthetic_1024_maxpool4", "metropro-1.dat_maxpool4",
       "x3p-2.x3p_maxpool4", "sur-uncompressed.sur_maxpool4", "synthetic_512", "synthetic_1024"]
ANCHOR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "shared", "bench",
                      "mesh_anchor.py")


def ours(exe, npy, step, eps, repeats, threads, stl):
    env = dict(os.environ)
    if threads:
        env["RAYON_NUM_THREADS"] = threads
    else:
        env.pop("RAYON_NUM_THREADS", None)
    line = subprocess.run([exe, npy, str(step), repr(eps), str(repeats), stl], env=env,
                          check=True, capture_output=True, text=True).stdout
    return json.loads(line)


def trimesh_check(stl):
    import trimesh
    m = trimesh.load(stl, process=True)
    return {"is_watertight": bool(m.is_watertight),
            "is_winding_consistent": bool(m.is_winding_consistent),
            "faces": int(len(m.faces))}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--inputs", default=",".join(ALL))
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out-dir", default="bench-out/mesh_compare")
    ap.add_argument("--anchor-json", help="use this mesh_anchor.py result instead of running it")
    ap.add_argument("--input-dir", help="with --anchor-json: its --save-inputs folder")
    ap.add_argument("--reuse-anchors", action="store_true",
                    help="use OUT_DIR/anchor_NAME.json where an earlier run left one (then the "
                         "anchor and ours are not interleaved for that input: say so)")
    ap.add_argument("positional", nargs="*", metavar="ANCHOR_JSON INPUT_DIR",
                    help="the older form: the same as --anchor-json ANCHOR_JSON --input-dir INPUT_DIR")
    a = ap.parse_args()
    if a.positional:
        if len(a.positional) != 2:
            sys.exit("give ANCHOR_JSON INPUT_DIR (or --anchor-json / --input-dir)")
        a.anchor_json, a.input_dir = a.positional
    target = os.environ.get("CARGO_TARGET_DIR", "target")
    exe = os.path.join(target, "release", "examples", "bench_adaptive")
    if not os.path.exists(exe):
        sys.exit(f"{exe} missing: cargo build --release -p surfstream-mesher --example bench_adaptive")
    os.makedirs(a.out_dir, exist_ok=True)
    input_dir = a.input_dir or os.path.join(a.out_dir, "inputs")
    reused = json.load(open(a.anchor_json))["results"] if a.anchor_json else None
    rows, out = [], []
    for name in a.inputs.split(","):
        if reused is not None:
            found = [r for r in reused if r["input"] == name]
            if not found:
                sys.exit(f"{name}: not in {a.anchor_json}")
            r = found[0]
        elif a.reuse_anchors and os.path.exists(os.path.join(a.out_dir, f"anchor_{name}.json")):
            r = json.load(open(os.path.join(a.out_dir, f"anchor_{name}.json")))["results"][0]
            print(f"anchor {name}: reusing this folder's earlier anchor run", file=sys.stderr)
        else:
            aj = os.path.join(a.out_dir, f"anchor_{name}.json")
            print(f"anchor {name} ...", file=sys.stderr, flush=True)
            subprocess.run([sys.executable, ANCHOR, "--only", name, "--save-inputs", input_dir,
                            "--out", aj, "--tmpdir", os.path.join(a.out_dir, "anchor_stl")],
                           check=True, stdout=subprocess.DEVNULL)
            r = json.load(open(aj))["results"][0]
        npy = os.path.join(input_dir, name + ".npy")
        if not os.path.exists(npy):
            sys.exit(f"{npy} missing (the anchor writes it with --save-inputs)")
        step = r["step_um"][0]
        dec = r["decimation"]
        for p in r["poisson"]:
            if p.get("threads") not in (1, "1"):
                continue
            eps = p["deviation"]["interior"]["rms_um"]
            stl = os.path.join(a.out_dir, f"ours_{name}_d{p['depth']}.stl")
            o1 = ours(exe, npy, step, eps, a.repeats, "1", stl)
            od = ours(exe, npy, step, eps, a.repeats, None, stl)
            tm = trimesh_check(stl)
            print(f"{name} depth {p['depth']}: Poisson {p['time']['median_s']:.2f} s, ours "
                  f"{o1['median_s']:.3f} s (1 thread) / {od['median_s']:.3f} s "
                  f"({od['rayon_threads']} threads)", file=sys.stderr, flush=True)
            dall = p["deviation"].get("all", {})
            rows.append((name, "x".join(map(str, r["shape"])), p["depth"], f"{eps:.4g}",
                         f"{p['time']['median_s']:.2f}", f"{p['cpu_time']['median_s']:.2f}",
                         f"{o1['median_s']:.3f}", f"{o1['cpu_median_s']:.2f}",
                         f"{od['median_s']:.3f}", f"{od['cpu_median_s']:.2f}",
                         f"{p['time']['median_s'] / o1['median_s']:.0f}x",
                         f"{p['cpu_time']['median_s'] / max(o1['cpu_median_s'], 0.01):.0f}x",
                         p["n_faces"], dec["n_faces"], o1["triangles"],
                         f"{p['deviation']['interior']['max_abs_um']:.3g}",
                         f"{dall.get('max_abs_um', float('nan')):.3g}",
                         f"{dec['deviation']['all']['max_abs_um']:.3g}",
                         f"{dec['deviation']['all']['rms_um']:.3g}",
                         f"{o1['max_err_vs_f64_input_um']:.4g}", f"{o1['rms_err_vs_f64_input_um']:.4g}",
                         o1["bound_met"] and o1["max_err_vs_f64_input_um"] <= eps * (1 + 1e-6),
                         f"{tm['is_watertight']}/{tm['is_winding_consistent']}"))
            out.append({"input": name, "shape": r["shape"], "epsilon_um": eps,
                        "poisson": {k: p[k] for k in ("depth", "threads", "time", "cpu_time",
                                                      "n_faces", "deviation")},
                        "decimation": {k: dec[k] for k in ("time", "n_faces", "deviation")},
                        "ours_threads_1": o1, "ours_threads_default": od, "ours_trimesh": tm,
                        "anchor_loadavg": [r.get("loadavg_1_5_15_at_end")]})
    head = ["input", "shape", "Poisson depth", "epsilon um (= Poisson interior RMS)",
            "Poisson s", "Poisson CPU s", "ours s (1 thread)", "ours CPU s (1 thread)",
            "ours s (default threads)", "ours CPU s (default)", "speed-up wall (1 thread)",
            "speed-up CPU", "Poisson faces", "decimation faces", "our triangles (solid)",
            "Poisson interior max um", "Poisson all-points max um", "decimation all-points max um",
            "decimation all-points RMS um", "our max um (all samples)", "our RMS um",
            "our max <= epsilon", "ours trimesh watertight/winding"]
    md = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    md += ["| " + " | ".join(str(x) for x in row) + " |" for row in rows]
    md.append("")
    md.append(f"load average at the end: {os.getloadavg()}")
    print("\n".join(md))
    open(os.path.join(a.out_dir, "compare.md"), "w").write("\n".join(md) + "\n")
    json.dump({"rows": out, "loadavg_at_end": os.getloadavg()},
              open(os.path.join(a.out_dir, "compare.json"), "w"), indent=1)


if __name__ == "__main__":
    main()
