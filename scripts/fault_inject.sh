#!/usr/bin/env bash
# Fault injection (issue 15): N launches of a small demo graph, each hit by one fault at a random
# moment (SIGKILL of a node, SIGSTOP of a node, SIGKILL of the launcher, SIGSTOP of the launcher
# for 2 s, in rotation; the node and the moment drawn from SEED), each followed by a clean launch
# into the same out dir. After every run it asserts: the out dir holds one run (complete, FAILED,
# or the earlier run untouched), no process outlived the launcher, a stopped node was named as
# stalled, and the next launch left /dev/shm, the iceoryx2 node records and folders, staging
# folders and .partial files at zero. The suite runs 4 of these (tests/faults.rs); this is the
# larger campaign. About 15-25 s per run on a loaded 2-core machine.
#
#   bash scripts/fault_inject.sh            # 10 runs, seed from the clock (printed)
#   bash scripts/fault_inject.sh 40 12345   # 40 runs, reproducible
set -euo pipefail
cd "$(dirname "$0")/.."
N="${1:-10}"
SEED="${2:-$(date +%s)}"
cargo build --release --workspace --bins
SURFSTREAM_FAULT_RUNS="$N" SURFSTREAM_FAULT_SEED="$SEED" \
  timeout $((N * 60 + 120)) \
  cargo test --release -p surfstream-e2e --test faults -- --nocapture --test-threads 1
