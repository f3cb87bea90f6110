#!/usr/bin/env bash
# Fault injection.
#
# Part 1 (issue 15): N launches of a small demo graph, each hit by one fault at a random
# moment (SIGKILL of a node, SIGSTOP of a node, SIGKILL of the launcher, SIGSTOP of the launcher
# for 2 s, in rotation; the node and the moment drawn from SEED), each followed by a clean launch
# into the same out dir. After every run it asserts: the out dir holds one run (complete, FAILED,
# or the earlier run untouched), no process outlived the launcher, a stopped node was named as
# stalled, and the next launch left /dev/shm, the iceoryx2 node records and folders, staging
# folders and .partial files at zero. The suite runs 4 of these (tests/faults.rs).
#
# Part 2 (issue 27): stop signals. N runs of `run`, `stitch` and `launch` in rotation, each sent
# SIGINT, SIGTERM or SIGHUP (in rotation) in one phase (in rotation): "startup" (0.05-0.5 s after
# the start, before the first tile), "scan" (after the first tile's progress line), "end" (after
# the last tile's line: final passes, run.json, the commit), and "twice" (two SIGINTs mid-scan:
# the second forces). After each: exit status 1 naming the signal (0 if the run had completed,
# 130/143/129 for "twice"), never 101 or a panic; the out dir FAILED naming the signal, complete,
# or never created; no staging folder, no lock, no process of the run, no /dev/shm file of its
# domain. One line per run and a table at the end (docs/reliability.md).
#
# Part 3 (issue 27): a second user. As root, a throwaway user (useradd) tries to read and block
# the launcher's slots and shared memory while root launches, then launches itself. Skipped
# (said so) when not root.
#
# Part 4 (issue 36): a loaded machine. LOAD_LOOPS busy loops (default 8) pinned to CPU 0 with
# `taskset -c 0`, and every command of this part pinned there too, LOAD_RUNS times (default 1):
# the demo graph under `launch` (must complete), the full-disk test (the record must keep the
# OS's reason), the stopped-receiver test (a SIGSTOPped node must still be named within its
# stall time) and a lock planted as a symbolic link (refused, its target untouched). Prints
# tried / held / failed per check (the table in docs/reliability.md).
#
#   bash scripts/fault_inject.sh             # 10 + 10 runs, seed from the clock (printed)
#   bash scripts/fault_inject.sh 40 12345    # 40 + 40 runs, reproducible kills
#   SKIP_KILLS=1 bash scripts/fault_inject.sh 24   # only parts 2, 3 and 4
#   ONLY_LOAD=1 LOAD_RUNS=2 bash scripts/fault_inject.sh   # only part 4, twice
set -euo pipefail
cd "$(dirname "$0")/.."
N="${1:-10}"
SEED="${2:-$(date +%s)}"
[ -n "${NO_BUILD:-}" ] || cargo build --release --workspace --bins
BIN="$PWD/target/release/surfstream"

if [ -z "${SKIP_KILLS:-}" ] && [ -z "${ONLY_LOAD:-}" ] && [ -z "${ONLY_FINISH:-}" ]; then
  SURFSTREAM_FAULT_RUNS="$N" SURFSTREAM_FAULT_SEED="$SEED" \
    timeout $((N * 60 + 120)) \
    cargo test --release -p surfstream-e2e --test faults -- --nocapture --test-threads 1 \
    faults_leave_one_run
fi

# ---- part 5: the finish engine (issue 36) ----
# FINISH_RUNS (default 1) rounds of: SIGKILL and SIGINT to `surfstream finish` while its
# LIGGGHTS runs (a 50 x 60 px rough patch, --no-macro --cycles 1, a few seconds of engine);
# an engine that exits 1 (a stand-in on SURFSTREAM_LIGGGHTS); an engine that sleeps (silent:
# SURFSTREAM_ENGINE_STALL_S=3 must kill and name it); and the demo under `launch` with as many
# busy loops as cores (not pinned; LOADED_DEMO_ARGS, default tiles of 256 px, fast pacing).
# After each: no engine process of the run left, OUT either FAILED with logs/ or a complete
# (possibly partial) finish.json, never neither (for SIGKILL, which nothing can record, OUT is
# left as it was and no engine survives). ONLY_FINISH=1 runs only this part.
FINISH_RUNS="${FINISH_RUNS:-1}"
if [ "$FINISH_RUNS" -gt 0 ] && [ -z "${ONLY_LOAD:-}" ]; then
  FW="$(mktemp -d /tmp/ss-finish.XXXXXX)"
  python3 - "$FW/rough.npy" <<'PY'
import sys, struct, random
random.seed(5)
rows, cols = 50, 60
hdr = "{'descr': '<f8', 'fortran_order': False, 'shape': (%d, %d), }" % (rows, cols)
hdr += " " * (118 - len(hdr)) + "\n"
with open(sys.argv[1], "wb") as f:
    f.write(b"\x93NUMPY\x01\x00" + struct.pack("<H", len(hdr)) + hdr.encode())
    f.write(struct.pack("<%dd" % (rows * cols), *[random.gauss(0, 1) for _ in range(rows * cols)]))
PY
  declare -A ftried fheld
  fcheck() { # fcheck NAME FUNCTION: the function must succeed
    local name="$1"; shift
    ftried[$name]=$(( ${ftried[$name]:-0} + 1 ))
    local t0=$SECONDS
    if "$@" >"$FW/$name.log" 2>&1; then
      fheld[$name]=$(( ${fheld[$name]:-0} + 1 )); echo "finish: $name: held ($((SECONDS - t0)) s)"
    else echo "finish: $name: FAILED ($((SECONDS - t0)) s):"; tail -8 "$FW/$name.log"; fi
  }
  FIN_ARGS=(--no-macro --pitch-um 3 --patch-um 90 --cycles 1 --passes 150 --calibrate 1.272,0.565)
  # The engine processes working in this run's folder (their cwd under DIR; to detect, not to
  # kill: other users' engines on the machine are not ours).
  engines_of() { pgrep -x liggghts | while read -r p; do
    case "$(readlink "/proc/$p/cwd" 2>/dev/null)" in "$1"/*) echo "$p" ;; esac; done; true; }
  out_ok() { # FAILED with logs/, or a complete finish.json
    local o="$1"
    if [ -f "$o/FAILED" ]; then [ -d "$o/logs" ] && ls "$o/logs" | grep -q liggghts; return; fi
    [ -f "$o/finish.json" ] && python3 -c "import json,sys; json.load(open(sys.argv[1]))" "$o/finish.json"
  }
  signal_mid_engine() { # signal_mid_engine SIG
    local sig="$1" o; o="$(mktemp -d "$FW/sig.XXXXXX")/out"
    "$BIN" finish "$FW/rough.npy" "${FIN_ARGS[@]}" -o "$o" 2>"$o.err" & local pid=$!
    local k
    for ((k = 0; k < 600; k++)); do # the engine started: a liggghts child of the run
      [ -n "$(engines_of "$(dirname "$o")")" ] && break; sleep 0.1; done
    [ -n "$(engines_of "$(dirname "$o")")" ] || { echo "the engine never started"; cat "$o.err"; kill -KILL $pid; return 1; }
    sleep 1; kill -"$sig" $pid
    local rc=0; wait $pid || rc=$?
    sleep 3
    local left; left="$(engines_of "$(dirname "$o")")"
    echo "exit $rc; engines left: '${left}'; out: $(ls "$o" 2>/dev/null | tr '\n' ' ')"
    [ -z "$left" ] || return 1
    [ "$rc" -ne 0 ] || return 1
    if [ "$sig" != KILL ]; then out_ok "$o"; return; fi
    # Nothing can record a SIGKILL: OUT is left as it was (here: never created); what is left
    # beside it is said, and the next finish into OUT must clear it and complete.
    echo "beside OUT after SIGKILL: $(ls -a "$(dirname "$o")" | grep -v '^\.*$' | tr '\n' ' ')"
    [ ! -e "$o/finish.json" ] || out_ok "$o" || return 1
    "$BIN" finish "$FW/rough.npy" "${FIN_ARGS[@]}" -o "$o" 2>>"$o.err" || { tail -3 "$o.err"; return 1; }
    echo "the next finish into OUT: exit 0; beside OUT: $(ls -a "$(dirname "$o")" | grep -v '^\.*$' | tr '\n' ' ')"
    out_ok "$o" && ! ls -d "$o".staging-* "$o.lock" 2>/dev/null
  }
  fake_engine() { # fake_engine exit1|sleep
    local d; d="$(mktemp -d "$FW/fake.XXXXXX")"
    if [ "$1" = exit1 ]; then
      printf '#!/bin/sh\necho "ERROR: Lost atoms: original 1 current 0" > "$4"\ncat "$4"\nexit 1\n' > "$d/liggghts"
    else
      printf '#!/bin/sh\nexec sleep 600\n' > "$d/liggghts"
    fi
    chmod 755 "$d/liggghts"
    local rc=0
    PATH="$d:$PATH" SURFSTREAM_ENGINE_STALL_S=3 timeout 120 \
      "$BIN" finish "$FW/rough.npy" "${FIN_ARGS[@]}" -o "$d/out" 2>"$d/err" || rc=$?
    sleep 1
    local left; left="$(pgrep -f -- "sleep 600" | while read -r p; do
      grep -qa "$d" "/proc/$p/environ" 2>/dev/null && echo "$p"; done; true)"
    echo "exit $rc; sleeping engines left: '$left'"; tail -3 "$d/err"
    [ "$rc" -ne 0 ] && [ "$rc" -ne 124 ] && [ -z "$left" ] && [ -f "$d/out/FAILED" ] && out_ok "$d/out"
  }
  loaded_demo() {
    local n; n="$(nproc)"; local lp=()
    for ((i = 0; i < n; i++)); do sh -c 'while :; do :; done' & lp+=($!); done
    local rc=0
    "$BIN" launch launch/graphs/demo.toml ${LOADED_DEMO_ARGS:---set stage.tile_px=256 --set stage.pacing=fast} -o "$FW/demo" || rc=$?
    kill "${lp[@]}"
    [ "$rc" -eq 0 ] && [ -f "$FW/demo/run.json" ]
  }
  for ((k = 0; k < FINISH_RUNS; k++)); do
    fcheck sigkill-mid-engine signal_mid_engine KILL
    fcheck sigint-mid-engine signal_mid_engine INT
    fcheck engine-exits-1 fake_engine exit1
    fcheck engine-sleeps fake_engine sleep
    fcheck loaded-demo loaded_demo
  done
  echo
  echo "| check ($(date -u +%Y-%m-%dT%H:%MZ), load average $(cut -d' ' -f1-3 /proc/loadavg)) | tried | held | failed |"
  echo "|---|---|---|---|"
  ff=0
  for name in sigkill-mid-engine sigint-mid-engine engine-exits-1 engine-sleeps loaded-demo; do
    t=${ftried[$name]:-0}; h=${fheld[$name]:-0}; ff=$((ff + t - h))
    echo "| $name | $t | $h | $((t - h)) |"
  done
  [ -z "${FINISH_LOGS:-}" ] || cp "$FW"/*.log "$FINISH_LOGS"/
  rm -rf "$FW"
  if [ -n "${ONLY_FINISH:-}" ]; then [ $ff -eq 0 ]; exit; fi
fi

# ---- part 4: a loaded machine (issue 36) ----
LOAD_RUNS="${LOAD_RUNS:-1}"
LOAD_LOOPS="${LOAD_LOOPS:-8}"
if [ "$LOAD_RUNS" -gt 0 ]; then
  LW="$(mktemp -d /tmp/ss-load.XXXXXX)"
  loadpids=()
  for ((i = 0; i < LOAD_LOOPS; i++)); do taskset -c 0 sh -c 'while :; do :; done' & loadpids+=($!); done
  stop_load() { kill "${loadpids[@]}" 2>/dev/null || true; rm -rf "$LW"; }
  trap stop_load EXIT
  echo "load: $LOAD_LOOPS busy loops pinned to CPU 0 (pids ${loadpids[*]}); every command below pinned there too"
  all_cpus="$(taskset -pc $$ | sed 's/.*: //')"
  taskset -pc 0 $$ >/dev/null # this shell, so every command it starts
  declare -A tried held
  check() { # check NAME CMD...: the command must succeed
    local name="$1"; shift
    tried[$name]=$(( ${tried[$name]:-0} + 1 ))
    local t0=$SECONDS
    if "$@" >"$LW/$name.log" 2>&1; then
      held[$name]=$(( ${held[$name]:-0} + 1 )); echo "load: $name: held ($((SECONDS - t0)) s)"
    else echo "load: $name: FAILED ($((SECONDS - t0)) s):"; tail -5 "$LW/$name.log"; fi
  }
  planted_lock() {
    local d; d="$(mktemp -d "$LW/lock.XXXXXX")"
    echo "years of work" > "$d/precious.txt"; ln -s "$d/precious.txt" "$d/out.lock"
    ! "$BIN" run launch/graphs/demo.toml -o "$d/out" 2>"$d/err" && grep -q "symbolic link" "$d/err" \
      && [ "$(cat "$d/precious.txt")" = "years of work" ]
  }
  for ((k = 0; k < LOAD_RUNS; k++)); do
    check demo-launch "$BIN" launch launch/graphs/demo.toml -o "$LW/demo-$k"
    check full-disk cargo test --release -p surfstream-e2e --test faults -- --exact a_full_disk_fails_the_run_and_keeps_the_os_reason
    check stopped-node cargo test --release -p surfstream-e2e --test faults -- --exact a_stopped_receiver_is_named_as_stalled
    check planted-lock planted_lock
  done
  echo
  echo "| check (loaded: $LOAD_LOOPS busy loops on CPU 0) | tried | held | failed |"
  echo "|---|---|---|---|"
  lf=0
  for name in demo-launch full-disk stopped-node planted-lock; do
    t=${tried[$name]:-0}; h=${held[$name]:-0}; lf=$((lf + t - h))
    echo "| $name | $t | $h | $((t - h)) |"
  done
  stop_load; trap - EXIT
  taskset -pc "$all_cpus" $$ >/dev/null
  if [ -n "${ONLY_LOAD:-}" ]; then [ $lf -eq 0 ]; exit; fi
fi

# ---- part 2: stop signals at every phase of run, stitch and launch ----
WORK="$(mktemp -d /tmp/ss-signals.XXXXXX)"
chmod 755 "$WORK"
trap 'rm -rf "$WORK"' EXIT
GRAPH="$WORK/demo.toml"
sed 's/^name = "demo"$/name = "demo"\nstall_timeout_s = 20/' launch/graphs/demo.toml > "$GRAPH"
SCAN="$WORK/scan"
# A 2 x 2 scan directory of 256 px tiles, from a `run` of the simulated stage's recording.
"$BIN" run "$GRAPH" --set stage.tile_px=256 --set 'stage.pacing="fast"' -o "$WORK/seed" >/dev/null 2>&1
SCAN="$WORK/seed/recording.mcap"
[ -f "$SCAN" ] || { echo "no seed recording"; exit 1; }

verbs=(run stitch launch)
sigs=(INT TERM HUP)
phases=(startup scan end twice)
declare -A tally
fails=0
wait_for() { # wait_for FILE TEXT PID: until FILE contains TEXT (0) or PID ended (1)
  local t=0
  while ! grep -qF -- "$2" "$1" 2>/dev/null; do
    kill -0 "$3" 2>/dev/null || return 1
    sleep 0.02; t=$((t + 1)); [ $t -lt 6000 ] || return 1
  done
}
for ((k = 0; k < N; k++)); do
  verb=${verbs[$((k % 3))]}
  sig=${sigs[$(((k / 3) % 3))]}
  phase=${phases[$(((k / 9) % 4))]}
  [ "$phase" = twice ] && sig=INT
  d="$WORK/r$k"; mkdir -p "$d"; out="$d/out"; log="$d/stderr"
  case $verb in
    run|launch) args=("$verb" "$GRAPH" --set stage.tile_px=256 --set stage.field_time_s=0.7 --set 'stage.pacing="realtime"' -o "$out") ;;
    stitch) args=(stitch "$SCAN" --set 'stage.pacing="realtime"' -o "$out") ;;
  esac
  "$BIN" "${args[@]}" >/dev/null 2>"$log" &
  pid=$!
  applied=1
  case $phase in
    startup) sleep "0.$((5 + RANDOM % 45))" ;;
    scan|twice) wait_for "$log" "(1 done)" $pid || applied=0 ;;
    end) wait_for "$log" "(4 done)" $pid || applied=0; sleep "0.$((RANDOM % 99))" ;;
  esac
  kill -s "$sig" $pid 2>/dev/null || applied=0
  if [ "$phase" = twice ]; then sleep 0.05; kill -s INT $pid 2>/dev/null || true; fi
  set +e; wait $pid; code=$?; set -e
  err="$(cat "$log")"
  bad=""
  [ $code -ne 101 ] || bad="exit 101"
  ! grep -q panicked "$log" || bad="$bad panic"
  if [ -e "$out/FAILED" ]; then state=FAILED; grep -q "SIG$sig" "$out/FAILED" || bad="$bad FAILED-without-signal"
  elif [ -e "$out/run.json" ]; then state=complete
  elif [ -e "$out" ]; then state=other; bad="$bad out-half-written"
  else state=none; fi
  case "$code:$phase" in
    0:*) [ "$state" = complete ] || bad="$bad exit0-not-complete" ;;
    1:*) grep -q "interrupted by SIG$sig" "$log" || bad="$bad error-without-signal" ;;
    130:twice) grep -q "second stop signal" "$log" || bad="$bad no-force-note" ;;
    *) bad="$bad exit$code" ;;
  esac
  left="$(ls -a "$d" | grep -E '^out\.(staging|lock)' || true)"
  [ -z "$left" ] || { [ "$code" = 130 ] || bad="$bad left:$left"; }
  sleep 0.3
  pgrep -f -- "$d/" >/dev/null && bad="$bad orphans"
  dom="$(grep -o 'domain ss[0-9]*_[0-9a-f]*_' "$log" | head -1 | cut -d' ' -f2 || true)"
  if [ -n "$dom" ] && [ "$code" != 130 ] && ls /dev/shm | grep -q "^$dom"; then bad="$bad shm-left"; fi
  [ -n "$bad" ] && fails=$((fails + 1))
  key="$verb SIG$sig $phase"
  printf 'signal run %2d: %-6s SIG%-4s %-7s -> exit %3s, out %-8s %s\n' "$k" "$verb" "$sig" "$phase" "$code" "$state" "${bad:-ok}$([ $applied = 1 ] || echo ' (signal after the end)')"
  tally["$verb $phase exit$code $state${bad:+ BAD}"]=$(( ${tally["$verb $phase exit$code $state${bad:+ BAD}"]:-0} + 1 ))
done
echo
echo "| verb | phase | exit | out dir | runs |"
echo "|---|---|---|---|---|"
for key in "${!tally[@]}"; do
  read -r v p e s rest <<<"$key"
  echo "| $v | $p | ${e#exit} | $s${rest:+ $rest} | ${tally[$key]} |"
done | sort
echo "signal runs: $N, failures: $fails"

# ---- part 3: a second user ----
if [ "$(id -u)" != 0 ]; then
  echo "second user: SKIPPED (needs root to create a throwaway user)"
  [ $fails -eq 0 ]; exit
fi
U=ssneighbour
unset XDG_RUNTIME_DIR # root's slots in /tmp/surfstream-0, which the neighbour can see exists
id "$U" >/dev/null 2>&1 || useradd --no-create-home --shell /usr/sbin/nologin "$U"
as_u() { runuser -u "$U" -- "$@"; }
# Root launches (slow pacing) while the neighbour tries everything.
"$BIN" launch "$GRAPH" --set stage.tile_px=256 --set stage.field_time_s=1.0 --set 'stage.pacing="realtime"' \
  -o "$WORK/root-out" >/dev/null 2>"$WORK/root.stderr" &
rpid=$!
wait_for "$WORK/root.stderr" "scan started" $rpid || true
dom="$(grep -o 'domain ss[0-9]*_[0-9a-f]*_' "$WORK/root.stderr" | head -1 | cut -d' ' -f2)"
sb=0
attempt() { # attempt DESCRIPTION CMD...: the neighbour must fail
  if as_u "$@" >/dev/null 2>&1; then echo "second user: $1: SUCCEEDED (bad)"; sb=$((sb + 1))
  else echo "second user: refused: $*"; fi
}
attempt ls /tmp/surfstream-0
attempt sh -c 'flock -n /tmp/surfstream-0/slot-0.lock true'
attempt sh -c "cat /dev/shm/${dom}* | head -c1 | grep -q ."
mgmt="$(ls /dev/shm/${dom}*global_mgmt)"
stat -c "second user: root's management segment $mgmt: mode %a, owner %U" "$mgmt"
attempt sh -c "printf 0123456789abcdef 1<> $mgmt"
attempt ls /tmp/surfstream-0/iceoryx2
# The neighbour plants what it can where root would look, then root's launch still completes.
as_u sh -c 'mkdir -p /tmp/surfstream-slots && for k in $(seq 0 31); do : > /tmp/surfstream-slots/slot-$k.lock; done' || true
as_u flock /tmp/surfstream-slots/slot-0.lock sleep 20 &
npid=$!
set +e; wait $rpid; rc=$?; set -e
echo "second user: root's launch during the attempts -> exit $rc"
[ $rc -eq 0 ] || sb=$((sb + 1))
"$BIN" launch "$GRAPH" --set stage.tile_px=256 --set 'stage.pacing="fast"' -o "$WORK/root-out2" >/dev/null 2>"$WORK/root2.stderr" \
  && echo "second user: root's next launch -> ok" || { echo "root's next launch failed"; sb=$((sb + 1)); }
for f in "$WORK"/root*.stderr; do
  d2="$(grep -o 'domain ss[0-9]*_[0-9a-f]*_' "$f" | head -1 | cut -d' ' -f2)"
  if ls /dev/shm | grep -q "^$d2"; then echo "second user: root's domain $d2 left files in /dev/shm"; sb=$((sb + 1));
  else echo "second user: root's domain $d2: nothing left in /dev/shm"; fi
done
# And the neighbour can launch too (its own slots), after root did.
mkdir -p "$WORK/u" && chown "$U" "$WORK/u"
if as_u env -u XDG_RUNTIME_DIR HOME="$WORK/u" "$BIN" launch "$GRAPH" --set stage.tile_px=256 --set 'stage.pacing="fast"' -o "$WORK/u/out" >/dev/null 2>"$WORK/u.stderr"; then
  echo "second user: its own launch after root's -> ok ($(grep -o 'domain [^ ]*' "$WORK/u.stderr"))"
else echo "second user: its own launch FAILED:"; tail -3 "$WORK/u.stderr"; sb=$((sb + 1)); fi
kill "$npid" 2>/dev/null || true
echo "second user: $sb failure(s)"
[ $fails -eq 0 ] && [ $sb -eq 0 ]
