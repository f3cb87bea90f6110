#!/usr/bin/env bash
# Tile -> panorama latency of the demo (2 x 2 fields of 1024 x 1024 px, one field per second)
# without the live view, with --view and no page open, and with a headless Chromium showing the
# page for the whole run (docs/live.md). Prints run.json's latency per hop (tile ->
# registration, registration -> panorama patch, tile -> panorama patch) per run. Usage: scripts/bench_live.sh [REPEATS] (default 3).
set -euo pipefail
cd "$(dirname "$0")/.."
repeats=${1:-3}
bin=target/release/surfstream
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
latency() {
    python3 - "$1/run.json" <<'PY'
import json, sys
lat = json.load(open(sys.argv[1]))["latency_ms"]
hops = [("tile_to_registration", lat["tile_to_registration"]),
        ("registration_to_panorama", lat["hops"]["registration_to_panorama"]),
        ("tile_to_panorama", lat["tile_to_panorama"])]
print("; ".join("%s p50 %.1f max %.1f ms (n %d)" % (k, p["p50"], p["max"], p["n"]) for k, p in hops))
PY
}
for i in $(seq "$repeats"); do
    for mode in none view browser; do
        out="$tmp/$mode-$i"
        case $mode in
            none) "$bin" launch launch/graphs/demo.toml -o "$out" >/dev/null 2>"$tmp/err-$mode-$i" ;;
            view) "$bin" launch launch/graphs/demo.toml -o "$out" --view >/dev/null 2>"$tmp/err-$mode-$i" ;;
            browser)
                "$bin" launch launch/graphs/demo.toml -o "$out" --view >/dev/null 2>"$tmp/err-$mode-$i" &
                pid=$!
                until url=$(grep -o 'http://[0-9.:]*/' "$tmp/err-$mode-$i" 2>/dev/null | head -1) && [ -n "$url" ]; do sleep 0.1; done
                /usr/bin/chromium --headless --no-sandbox --disable-gpu --disable-quic --no-first-run \
                    --disable-background-networking --disable-component-update --disable-sync \
                    --user-data-dir="$tmp/profile-$i" --remote-debugging-port=0 "$url" \
                    >/dev/null 2>&1 &
                browser=$!
                # The page is connected while the scan runs (the state's viewers.pages).
                pages=0
                while kill -0 "$pid" 2>/dev/null; do
                    n=$(curl -s --max-time 2 "${url}state.json" | python3 -c 'import json,sys; print(json.load(sys.stdin)["viewers"]["pages"])' 2>/dev/null || echo 0)
                    [ "$n" -gt "$pages" ] && pages=$n
                    sleep 1
                done
                wait "$pid"
                mode="browser (pages connected: $pages)"
                kill "$browser" 2>/dev/null || true
                wait "$browser" 2>/dev/null || true
                ;;
        esac
        echo "run $i, $mode: $(latency "$out")"
    done
done
