#!/usr/bin/env bash
# Two iceoryx2 roots on this machine joined by two zenoh tunnels (TCP over loopback), a
# publisher in root A and a subscriber in root B: prints the subscriber's JSON line per case.
#   cargo build --release --offline && bash run.sh
set -euo pipefail
cd "$(dirname "$0")"
bin=target/release/tunnel-bench
port=${PORT:-17447}
cleanup() { kill $(jobs -p) 2>/dev/null || true; }
trap cleanup EXIT
$bin tunnel rootA listen "tcp/127.0.0.1:$port" 2>/tmp/tunnelA.log &
sleep 1
$bin tunnel rootB connect "tcp/127.0.0.1:$port" 2>/tmp/tunnelB.log &
sleep 1
# case: FRAMES BYTES INTERVAL_MS: tile-sized patches at 10 per second, a burst of them, then
# larger frames up to a 6 x 6 scan's final panorama (127 MB)
cases=("50 4194304 100" "20 4194304 0" "5 16777216 1000" "5 33554432 1000" "3 127215792 1000")
for case in "${cases[@]}"; do
  set -- $case
  $bin sub rootB "$1" > /tmp/tunnel-sub.json &
  sub=$!
  $bin pub rootA "$1" "$2" "$3"
  wait $sub || true
  echo "{\"case\": \"$1 x $2 B every $3 ms\", \"result\": $(cat /tmp/tunnel-sub.json || echo null)}"
done
