#!/bin/bash
# The `mesh` verb before and after a change, byte for byte (docs/model.md, "The `mesh` verb
# streams"):
#   scripts/compare_mesh_verb.sh BEFORE_BIN AFTER_BIN OUT_DIR SPECIMENS_DIR DEMO_OUT_DIR
# SPECIMENS_DIR holds x3p-2.x3p, metropro-1.dat, sur-3.sur, sur-uncompressed.sur (real
# instrument files); DEMO_OUT_DIR a demo run's output (panorama.npy, roughness.npy). Each case
# runs under /usr/bin/time -v with both binaries; the STL is compared with cmp, OUT.json with
# diff without its "mesh_s" line (the time), and the peak RSS of both is printed.
set -u
B=$1 A=$2 O=$3 S=$4 D=$5
mkdir -p "$O/before" "$O/after"
cases=(
  "x3p-tol|$S/x3p-2.x3p"
  "x3p-liggghts|$S/x3p-2.x3p --target liggghts"
  "metro-sheet-eps|$S/metropro-1.dat --sheet --epsilon-um 0.01"
  "metro-maxtri-greedy|$S/metropro-1.dat --max-triangles 20000 --model-method greedy"
  "sur3-holes|$S/sur-3.sur --sheet --holes --epsilon-sq 0.1"
  "sur3-tol-sheet|$S/sur-3.sur --sheet"
  "suru-spikes-solid|$S/sur-uncompressed.sur --solid --remove-spikes --units um"
  "demo-rough|$D/panorama.npy --roughness $D/roughness.npy"
  "demo-ascii-eps|$D/panorama.npy --epsilon-sq 0.05 --ascii --units m"
  "demo-tol|$D/panorama.npy"
)
rss() { grep "Maximum resident" "$1" | awk '{print $NF}'; }
printf "%-22s %-5s %-5s %12s %12s\n" case stl json "before (KB)" "after (KB)"
for c in "${cases[@]}"; do
  name=${c%%|*} args=${c#*|}
  for w in before after; do
    bin=$B; [ "$w" = after ] && bin=$A
    # shellcheck disable=SC2086 # the case's arguments are words
    /usr/bin/time -v "$bin" mesh $args -o "$O/$w/$name.stl" >/dev/null 2>"$O/$w/$name.err" ||
      echo "$name: $w failed (see $O/$w/$name.err)"
  done
  stl=DIFF json=DIFF
  cmp -s "$O/before/$name.stl" "$O/after/$name.stl" && stl=same
  diff <(grep -v '"mesh_s"' "$O/before/$name.json") <(grep -v '"mesh_s"' "$O/after/$name.json") \
    >/dev/null && json=same
  printf "%-22s %-5s %-5s %12s %12s\n" "$name" $stl $json "$(rss "$O/before/$name.err")" \
    "$(rss "$O/after/$name.err")"
done
