#!/usr/bin/env python3
"""Compares two out dirs of surfstream runs file by file (issue 24's byte-identity check).

    python3 scripts/compare_runs.py BEFORE AFTER

Every file must be byte-identical except the ones that carry times, which are compared as
JSON with the timing fields removed (listed in TIMING below):
  run.json, graph.resolved.json, nodes/<id>.json
                                        JSON without TIMING keys (any depth), key order kept,
                                        each run's out dir path written as OUT
  report.html                           not compared here: re-render it from BEFORE's run.json
  logs/*, recording.mcap                skipped (stderr text, recording times)
Exit status 0 when everything matches; every difference is printed.
"""
import json
import os
import re
import sys

# Keys whose values differ between two runs of the same command on the same commit (found by
# running each command twice): times, what the machine's load paces (coalesced live work,
# the live frames sent and the nodes' message traces), memory figures (peak RSS; the fusion's chunk budget is an eighth of
# MemAvailable without a memory_budget_gb; the memory plan's MemAvailable in graph.resolved.json)
# and the run's random scan id.
TIMING = {
    "scan_id", "chunk_budget_bytes", "available_bytes", "elapsed_s", "latency_ms", "peak_rss", "peak_rss_bytes",
    "t_acquired_ns", "t_written_ns", "t_finished_ns", "stats", "live_patches", "mesh_s",
    "live_frames_skipped", "messages",
}
SKIP_PREFIX = ("logs/",)
SKIP = {"recording.mcap", "report.html"}


def strip(v, root):
    """v without the TIMING keys, and with the run's own out dir (and its staging folder,
    named by the process id) written as OUT: two runs write to two folders."""
    if isinstance(v, dict):
        return {k: strip(x, root) for k, x in v.items() if k not in TIMING}
    if isinstance(v, list):
        return [strip(x, root) for x in v]
    if isinstance(v, str) and v.startswith(root):
        return re.sub(r"^OUT\.staging-\d+", "OUT.staging", "OUT" + v[len(root):])
    return v


def files(root):
    out = set()
    for d, _, names in os.walk(root):
        for n in names:
            out.add(os.path.relpath(os.path.join(d, n), root))
    return out


def main(a, b):
    fa, fb = files(a), files(b)
    bad = 0
    for f in sorted(fa ^ fb):
        print(f"only in {'BEFORE' if f in fa else 'AFTER'}: {f}")
        bad += 1
    same = 0
    for f in sorted(fa & fb):
        if f in SKIP or f.startswith(SKIP_PREFIX):
            continue
        pa, pb = os.path.join(a, f), os.path.join(b, f)
        if f in ("run.json", "graph.resolved.json") or (
            f.startswith("nodes/") and f.endswith(".json")
        ):
            # Python keeps the files' key order and tells 1 from 1.0: comparing the dumps
            # compares order, types and values at every depth.
            ja = strip(json.load(open(pa)), os.path.abspath(a))
            jb = strip(json.load(open(pb)), os.path.abspath(b))
            if json.dumps(ja, indent=1) != json.dumps(jb, indent=1):
                print(f"differs (timing fields removed): {f}")
                keys = ja.items() if isinstance(ja, dict) else enumerate(ja)
                for k, x in keys:
                    y = jb.get(k) if isinstance(jb, dict) else (jb[k] if k < len(jb) else None)
                    if json.dumps(x) != json.dumps(y):
                        print(f"   key {k}")
                bad += 1
            else:
                same += 1
            continue
        if open(pa, "rb").read() != open(pb, "rb").read():
            print(f"differs: {f}")
            bad += 1
        else:
            same += 1
    print(f"{same} files identical, {bad} differences")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], sys.argv[2]))
