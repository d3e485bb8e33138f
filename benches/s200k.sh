#!/usr/bin/env bash
# The whole process on the box scene of the authors' s200k shape (`synth s200k`: 200,000
# Gaussians, 318 segments with every defect planted): the scene written once, then
# `refine --backend cpu --report` (reading, both evaluations, the edge fit with its move
# gate, writing) run RUNS times (default 7) as new processes; prints each run's wall time,
# the median, and the report's stage times of the last run. BIN=path times another binary
# (default: target/release/linegs-gpu, or $CARGO_TARGET_DIR/release/linegs-gpu); OTHER=path
# times a second binary interleaved run by run (same minutes, same load) and prints the
# ratio of the medians. SEED=n picks the scene (default 1). The load average is printed
# before and after: other work on the machine slows every run.
#
#   bash benches/s200k.sh [RUNS]
set -euo pipefail
repo=$(cd "$(dirname "$0")/.." && pwd)
bin=${BIN:-${CARGO_TARGET_DIR:-$repo/target}/release/linegs-gpu}
other=${OTHER:-}
runs=${1:-7}
seed=${SEED:-1}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
"$bin" synth s200k --seed "$seed" -o "$work/g.ply" --lines-out "$work/lines.obj" >/dev/null
# Wall seconds of one whole run of binary $1.
one() {
  local start end
  start=$(date +%s.%N)
  "$1" refine --backend cpu -g "$work/g.ply" -l "$work/lines.obj" -o "$work/out.obj" \
    --report "$work/r.json" >/dev/null
  end=$(date +%s.%N)
  echo "$end - $start" | bc -l
}
median() { sort -g | awk '{a[NR]=$1} END {printf "%.4f", a[int((NR+1)/2)]}'; }
echo "load average before: $(cut -d' ' -f1-3 /proc/loadavg)"
times=() others=()
for _ in $(seq "$runs"); do
  times+=("$(one "$bin")")
  if [[ -n $other ]]; then others+=("$(one "$other")"); fi
done
echo "load average after:  $(cut -d' ' -f1-3 /proc/loadavg)"
m=$(printf '%s\n' "${times[@]}" | median)
printf 'run %.4f s\n' "${times[@]}"
echo "median $m s of $runs runs: $bin refine --backend cpu -g g.ply -l lines.obj -o out.obj --report r.json (scene: synth s200k --seed $seed)"
if [[ -n $other ]]; then
  o=$(printf '%s\n' "${others[@]}" | median)
  echo "other  $o s of $runs runs (interleaved): $other"
  echo "ratio $(echo "$m / $o" | bc -l | cut -c1-5) (this / other)"
fi
python3 -c '
import json, sys
r = json.load(open(sys.argv[1]))
print("segments", r["input"].get("segments_read"), "n_box", r["input"].get("n_box"), "out", r["after"]["segments"])
print(" ".join("%s %.4f" % (s["name"], s["seconds"]) for s in r["stages"]))
' "$work/r.json"
