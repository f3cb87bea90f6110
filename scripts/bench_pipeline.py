#!/usr/bin/env python3
"""Pipeline latency benchmark (a benchmark, not a test): runs real launches and reports
tile -> panorama patch latency at 10 % and 30 % overlap, and whether the work per tile grows
with the panorama (tile 50 vs tile 2 on a 10 x 5 scan).

    cargo build --release && python3 scripts/bench_pipeline.py [--field-time 0.6] [--skip-large]

Tiles are 1024 x 1024 at 0.8148 um; the stage is paced in real time (one field every
--field-time seconds) so the latencies are per tile, not queueing behind a burst.
"""
import argparse, json, os, statistics, subprocess, sys, tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BIN = os.path.join(ROOT, "target", "release", "surfstream")


def launch(out, sets):
    cmd = [BIN, "launch", os.path.join(ROOT, "launch/graphs/demo.toml"), "--out", out]
    for s in sets:
        cmd += ["--set", s]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        sys.exit(f"launch failed:\n{r.stderr}")
    return json.load(open(os.path.join(out, "run.json")))


def per_tile(out, node, port):
    rep = json.load(open(os.path.join(out, "nodes", f"{node}.json")))
    lat = {}
    for e in rep["stats"]["sent"].get(port, []):
        if e["flags"] & 3:  # FINAL or END_OF_SCAN
            continue
        lat.setdefault(e["tile_index"], (e["t_sent_ns"] - e["t_acquired_ns"]) / 1e6)
    return lat


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--field-time", type=float, default=0.6)
    ap.add_argument("--skip-large", action="store_true")
    a = ap.parse_args()
    tmp = tempfile.mkdtemp(prefix="surfstream-bench-")
    print(f"load average at start: {os.getloadavg()}")
    for ov in (0.10, 0.20, 0.30):
        out = os.path.join(tmp, f"ov{int(ov*100)}")
        run = launch(out, [f"stage.overlap={ov}", "stage.rows=3", "stage.cols=3", "stage.pacing=realtime",
                           f"stage.field_time_s={a.field_time}"])
        lat = run["latency_ms"]
        p, r = lat["tile_to_panorama"], lat["tile_to_registration"]
        print(f"3x3, overlap {ov:.0%}: tile->registration p50 {r['p50']:.1f} ms p95 {r['p95']:.1f} | "
              f"tile->panorama patch p50 {p['p50']:.1f} ms p95 {p['p95']:.1f} ms max {p['max']:.1f} | "
              f"tile->datum p50 {lat['tile_to_datum']['p50']:.1f} ms")
    if not a.skip_large:
        out = os.path.join(tmp, "10x5")
        run = launch(out, ["stage.rows=5", "stage.cols=10", "stage.overlap=0.1", "stage.pacing=realtime",
                           f"stage.field_time_s={a.field_time}", "recorder.path=recording.mcap"])
        pano = per_tile(out, "fusion", "panorama")
        reg = per_tile(out, "matcher", "registrations")
        datum = per_tile(out, "wavelet", "datum")
        early = [pano[i] for i in range(1, 4)]
        late = [pano[i] for i in range(46, 50)]
        print(f"10x5 at 10 %: tile 2 -> panorama {pano[2]:.1f} ms, tile 50 (index 49) {pano[49]:.1f} ms; "
              f"median of tiles 2-4 {statistics.median(early):.1f} ms vs tiles 47-50 {statistics.median(late):.1f} ms")
        print(f"   registration tile 2 {reg[2]:.1f} ms / tile 50 {reg[49]:.1f} ms; datum tile 2 {datum.get(2, float('nan')):.1f} ms / tile 50 {datum.get(49, float('nan')):.1f} ms")
        fl = run["latency_ms"]["final_frames"]
        print("   final: " + ", ".join(f"{k} {v['max']:.0f} ms" for k, v in fl.items()))
        print(f"   panorama {run['stages']['fusion']['panorama']['width_px']} x {run['stages']['fusion']['panorama']['height_px']} px; whole run {run['elapsed_s']:.1f} s")
    print(f"load average at end: {os.getloadavg()}; outputs in {tmp}")


if __name__ == "__main__":
    main()
