#!/usr/bin/env bash
# Wavelet round trip and 4x4 max pooling: PyWavelets / numpy and surfstream, interleaved in one
# run on the anchors' own arrays (wavelet_anchor.py --save-inputs), two rounds.
#
#   bash scripts/bench_wavelet.sh [INPUTS_DIR]     default bench-out/wavelet-inputs
#
# Needs the bench venv (bash ../shared/bench/setup.sh .bench-venv) and a release build of the
# wavelet example (cargo build --release -p surfstream-wavelet --examples).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
IN="${1:-bench-out/wavelet-inputs}"
PY=.bench-venv/bin/python
BENCH="${CARGO_TARGET_DIR:-target}/release/examples/bench_wavelet"
[ -f "$IN/synth_4096.npy" ] || "$PY" ../shared/bench/wavelet_anchor.py --quick --skip-timing --save-inputs "$IN" >/dev/null
anchor() {
    "$PY" -W ignore - "$IN" <<'PYEOF'
# The anchors' headline calls: pywt sym5 level 8 symmetric f64 wavedec2 + waverec2 (median of
# 5, 3 at 4096^2) and numpy's reshape max pooling (pooling_anchor.py's max_reshape4d, median of 7).
import sys, time, statistics, numpy as np, pywt
d = sys.argv[1]
for n in (1024, 2048, 4096):
    x = np.load(f"{d}/synth_{n}.npy"); ts = []
    for _ in range(5 if n < 4096 else 3):
        t = time.perf_counter()
        pywt.waverec2(pywt.wavedec2(x, "sym5", mode="symmetric", level=8), "sym5", mode="symmetric")
        ts.append(time.perf_counter() - t)
    print(f"PyWavelets round trip {n}^2: median {statistics.median(ts) * 1e3:.1f} ms")
x = np.load(f"{d}/synth_4096.npy"); ts = []
for _ in range(7):
    t = time.perf_counter(); x.reshape(1024, 4, 1024, 4).max(axis=(1, 3)); ts.append(time.perf_counter() - t)
print(f"numpy 4x4 max pooling 4096^2 f64: median {statistics.median(ts) * 1e3:.1f} ms")
PYEOF
}
for round in 1 2; do
    echo "== round $round, load $(cut -d' ' -f1 /proc/loadavg)"
    anchor
    RAYON_NUM_THREADS=1 "$BENCH" --inputs "$IN" --only rt 1024 2048 4096
    RAYON_NUM_THREADS=1 "$BENCH" --inputs "$IN" --only pool 4096
done
echo "== surfstream, default threads"
"$BENCH" --inputs "$IN" --only rt 1024 2048 4096
