#!/usr/bin/env bash
# Byte identity and peak memory of `surfstream separate` between two binaries: every case is
# run with each, every output file compared with `cmp`, VmHWM taken from /usr/bin/time -v.
# Usage: scripts/compare_separate.sh BEFORE_BIN AFTER_BIN WORK_DIR PANORAMA.npy SPECIMENS_DIR MASKED.x3p
set -u
before=$1 after=$2 work=$3 pano=$4 spec=$5 masked=$6
cases=(
  "default|$pano"
  "level3|$pano --level 3"
  "db4-periodization|$spec/metropro-1.dat --wavelet db4 --mode periodization"
  "level-auto|$spec/sur-3.sur --level auto"
  "gaussian-250|$pano --method gaussian --cutoff-um 250"
  "masked|$masked --mask-exclude break-off"
  "wavelet-auto|$spec/x3p-2.x3p --wavelet auto"
  "robust-lambda-s|$spec/x3p-2.x3p --method robust-gaussian --cutoff-um 80 --lambda-s-um 2.5"
  "default-x3p2|$spec/x3p-2.x3p"
  "default-metropro|$spec/metropro-1.dat"
  "level-auto-pano|$pano --level auto"
)
printf '%-18s %-10s %-10s %s\n' case rss_before rss_after files
for c in "${cases[@]}"; do
  name=${c%%|*} args=${c#*|}
  for side in before after; do
    bin=$before; [ $side = after ] && bin=$after
    rm -rf "$work/$name.$side"
    # shellcheck disable=SC2086
    /usr/bin/time -v "$bin" separate $args -o "$work/$name.$side" \
      > "$work/$name.$side.out" 2> "$work/$name.$side.err"
    grep 'Maximum resident' "$work/$name.$side.err" | awk '{print $NF}' > "$work/$name.$side.rss"
  done
  verdict=""
  for f in $(cd "$work/$name.before" && ls); do
    if cmp -s "$work/$name.before/$f" "$work/$name.after/$f"; then verdict+="$f=; "; else verdict+="$f DIFFERS; "; fi
  done
  [ "$(cd "$work/$name.before" && ls)" = "$(cd "$work/$name.after" && ls)" ] || verdict+="(file lists differ)"
  printf '%-18s %-10s %-10s %s\n' "$name" "$(cat "$work/$name.before.rss")" "$(cat "$work/$name.after.rss")" "$verdict"
done
# Where separate.json differs: the same keys and values but for the energy curve's fractions
# (compared to 1e-12 relative) and an added equivalent_cutoff_y_um; anything else is printed.
python3 - "$work" <<'PY'
import json, os, sys
work = sys.argv[1]
for name in sorted(d[:-7] for d in os.listdir(work) if d.endswith('.before') and os.path.isdir(os.path.join(work, d))):
    a = json.load(open(os.path.join(work, name + '.before', 'separate.json')))
    b = json.load(open(os.path.join(work, name + '.after', 'separate.json')))
    if a == b:
        continue
    notes = []
    if 'equivalent_cutoff_y_um' in b and 'equivalent_cutoff_y_um' not in a:
        notes.append('+equivalent_cutoff_y_um %r (pitch %r)' % (b.pop('equivalent_cutoff_y_um'), b['pitch_um']))
    ea, eb = a.pop('energy_curve', None), b.pop('energy_curve', None)
    if ea is not None or eb is not None:
        worst = max(abs(p['approx_energy_fraction'] - q['approx_energy_fraction']) / abs(p['approx_energy_fraction'])
                    for p, q in zip(ea, eb))
        same_levels = [p['level'] for p in ea] == [q['level'] for q in eb]
        notes.append('energy_curve: %d points, levels %s, largest relative difference %.1e' % (len(ea), 'same' if same_levels else 'DIFFER', worst))
        if worst > 1e-12 or not same_levels:
            notes.append('ENERGY CURVE BEYOND ROUND-OFF')
    rest = 'rest identical' if a == b else 'REST DIFFERS: ' + str(sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k)))
    print('%-18s separate.json: %s; %s' % (name, '; '.join(notes), rest))
PY
