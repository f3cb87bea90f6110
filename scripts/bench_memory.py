#!/usr/bin/env python3
"""Peak resident memory of a demo scan, per panorama pixel (issue 17). A benchmark, not a test.

Runs `surfstream run|launch launch/graphs/demo.toml --set stage.pacing=fast --set
stage.rows=R --set stage.cols=C --out OUT` under /usr/bin/time -v and samples /proc every
50 ms meanwhile: the peak of the summed VmRSS of the whole process tree (under `launch` every
node is its own process, so this is what the machine has to hold at once; shared-memory frames
count in every process that maps them) and of its summed PSS (each shared page counted once) and each process's
VmHWM (its own peak) by name. Prints one JSON line: the panorama size, the peaks, bytes per
panorama pixel, wall time, the throughput of the scan (fields per second through the fusion),
the time from the last tile to the final mesh, and the load average before and after (the
machine is shared: read every figure beside it).

    python3 scripts/bench_memory.py --rows 6 --cols 6 --mode run --out /tmp/m6
    python3 scripts/bench_memory.py --rows 6 --cols 6 --mode launch --bin target/release
    python3 scripts/bench_memory.py --rows 12 --cols 12 --set graph.memory_budget_gb=2
"""

import argparse
import json
import os
import subprocess
import sys
import time


def children_of(root):
    """Pids of the process tree under `root` (itself included)."""
    parent = {}
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat") as f:
                s = f.read()
            # comm may contain spaces: the ppid is the second field after the last ')'.
            parent[int(d)] = int(s[s.rindex(")") + 2 :].split()[1])
        except (OSError, ValueError):
            pass
    tree, frontier = {root}, [root]
    while frontier:
        p = frontier.pop()
        for c, pp in parent.items():
            if pp == p and c not in tree:
                tree.add(c)
                frontier.append(c)
    return tree


def status_kb(pid):
    out = {}
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                k, _, v = line.partition(":")
                if k in ("Name", "VmRSS", "VmHWM"):
                    out[k] = v.split()[0] if k != "Name" else v.strip()
    except OSError:
        return None
    return out


def pss_kb(pid):
    """Proportional set size: shared pages (the iceoryx2 frames every subscriber maps) are
    split among the processes that map them, so the sum over the tree counts them once."""
    try:
        with open(f"/proc/{pid}/smaps_rollup") as f:
            for line in f:
                if line.startswith("Pss:"):
                    return int(line.split()[1])
    except OSError:
        pass
    return 0


def loadavg():
    with open("/proc/loadavg") as f:
        return " ".join(f.read().split()[:3])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=6)
    ap.add_argument("--cols", type=int, default=None)
    ap.add_argument("--mode", choices=["run", "launch"], default="run")
    ap.add_argument("--bin", default="target/release", help="folder holding surfstream*")
    ap.add_argument("--graph", default="launch/graphs/demo.toml")
    ap.add_argument("--out", default=None)
    ap.add_argument("--set", action="append", default=[], help="extra --set NODE.PARAM=VALUE")
    a = ap.parse_args()
    cols = a.cols or a.rows
    out = a.out or f"/tmp/bench_memory_{a.mode}_{a.rows}x{cols}"
    cmd = ["/usr/bin/time", "-v", os.path.join(a.bin, "surfstream"), a.mode, a.graph,
           "--set", "stage.pacing=fast", "--set", f"stage.rows={a.rows}",
           "--set", f"stage.cols={cols}", "--out", out]
    for s in a.set:
        cmd += ["--set", s]
    load_before = loadavg()
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    peak_tree_kb, peak_pss_kb, hwm = 0, 0, {}
    while proc.poll() is None:
        total, total_pss = 0, 0
        for pid in children_of(proc.pid):
            s = status_kb(pid)
            if not s or "VmRSS" not in s:
                continue
            total += int(s["VmRSS"])
            total_pss += pss_kb(pid)
            name = s["Name"]
            hwm[name] = max(hwm.get(name, 0), int(s.get("VmHWM", 0)))
        peak_tree_kb = max(peak_tree_kb, total)
        peak_pss_kb = max(peak_pss_kb, total_pss)
        time.sleep(0.05)
    wall = time.monotonic() - t0
    err = proc.stderr.read()
    max_rss = [l for l in err.splitlines() if "Maximum resident" in l]
    if proc.returncode != 0:
        sys.stderr.write(err[-3000:])
        sys.exit(f"bench_memory: the run failed ({proc.returncode})")
    with open(os.path.join(out, "run.json")) as f:
        run = json.load(f)
    pano = run["stages"]["fusion"]["panorama"]
    px = pano["width_px"] * pano["height_px"]
    tiles = run.get("tiles", [])
    rec = {
        "scan": f"{a.rows}x{cols}", "mode": a.mode, "sets": a.set,
        "panorama_px": px, "panorama": f'{pano["width_px"]}x{pano["height_px"]}',
        "peak_tree_rss_mb": round(peak_tree_kb / 1024, 1),
        "peak_tree_bytes_per_px": round(peak_tree_kb * 1024 / px, 2),
        "peak_tree_pss_mb": round(peak_pss_kb / 1024, 1),
        "peak_tree_pss_bytes_per_px": round(peak_pss_kb * 1024 / px, 2),
        "time_v_max_rss_mb": round(int(max_rss[0].split()[-1]) / 1024, 1) if max_rss else None,
        "process_hwm_mb": {k: round(v / 1024, 1) for k, v in sorted(hwm.items())},
        "run_json_peak_rss": run.get("peak_rss"),
        "wall_s": round(wall, 2), "tiles": len(tiles),
        "load_before": load_before, "load_after": loadavg(),
    }
    final = run.get("latency_ms", {}).get("final_frames", {})
    to_mesh_s = final.get("last_tile_to_mesh", {}).get("max", 0.0) / 1e3
    to_pano_s = final.get("last_tile_to_final_panorama", {}).get("max", 0.0) / 1e3
    rec["last_tile_to_final_panorama_s"] = round(to_pano_s, 2)
    rec["last_tile_to_mesh_s"] = round(to_mesh_s, 2)
    # Fields per second through the scan: every field in, until the last one was acquired.
    scan_s = run["elapsed_s"] - to_mesh_s
    rec["fields_per_s"] = round(len(tiles) / scan_s, 2) if scan_s > 0 else None
    rec["p95_tile_to_panorama_ms"] = run.get("latency_ms", {}).get("tile_to_panorama", {}).get("p95")
    print(json.dumps(rec))


if __name__ == "__main__":
    main()
