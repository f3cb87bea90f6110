#!/usr/bin/env bash
# Tile -> panorama latency of the demo (2 x 2 fields of 1024 x 1024 px, one field per second)
# without the live view, with --view and no page open, and with a headless Chromium showing the
# page for the whole run (docs/live.md). Prints run.json's latency_ms.tile_to_panorama_patch
# per run. Usage: scripts/bench_live.sh [REPEATS] (default 3).
set -euo pipefail
cd "$(dirname "$0")/.."
repeats=${1:-3}
bin=target/release/surfstream
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
latency() {
    python3 -c 'import json,sys; l=json.load(open(sys.argv[1]))["latency_ms"]; k=[k for k in l if k.startswith("tile_to_panorama")][0]; p=l[k]; print(f"{k}: p50 {p[\"p50\"]:.1f} ms, p95 {p[\"p95\"]:.1f} ms, max {p[\"max\"]:.1f} ms (n {p[\"n\"]})")' "$1/run.json"
}
for i in $(seq "$repeats"); do
    for mode in none view browser; do
        out="$tmp/$mode-$i"
        case $mode in
            none) "$bin" launch launch/graphs/demo.toml -o "$out" >/dev/null 2>"$tmp/err" ;;
            view) "$bin" launch launch/graphs/demo.toml -o "$out" --view >/dev/null 2>"$tmp/err" ;;
            browser)
                "$bin" launch launch/graphs/demo.toml -o "$out" --view >/dev/null 2>"$tmp/err" &
                pid=$!
                until url=$(grep -o 'http://[0-9.:]*/' "$tmp/err" 2>/dev/null | head -1) && [ -n "$url" ]; do sleep 0.1; done
                /usr/bin/chromium --headless --no-sandbox --disable-gpu --disable-quic --no-first-run \
                    --disable-background-networking --disable-component-update --disable-sync \
                    --user-data-dir="$tmp/profile-$i" --timeout=60000 --screenshot="$tmp/shot.png" "$url" \
                    >/dev/null 2>&1 &
                browser=$!
                wait "$pid"
                kill "$browser" 2>/dev/null || true
                wait "$browser" 2>/dev/null || true
                ;;
        esac
        echo "run $i, $mode: $(latency "$out")"
    done
done
