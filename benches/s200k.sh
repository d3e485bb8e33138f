#!/usr/bin/env bash
# The whole process on a scene the size of the authors' s200k test scene (200,000
# Gaussians, 318 Line3D++ segments): the first 318 segments of the real Line3D++ output in
# tests/data, Gaussians sampled around them (`synth around`, seed 1), then
# `refine --backend cpu --report` (both evaluations, the edge fit), run RUNS times (default
# 5); prints each run's wall time and the median, and the report's stage times of the
# last run. A binary other than target/release/linegs-gpu: BIN=path.
#
#   bash benches/s200k.sh [RUNS]
set -euo pipefail
repo=$(cd "$(dirname "$0")/.." && pwd)
bin=${BIN:-$repo/target/release/linegs-gpu}
runs=${1:-5}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
obj=$repo/tests/data/line3dpp/line3dpp_optimized.obj
awk '/^v / && ++v <= 636; /^l / && ++l <= 318' "$obj" >"$work/lines.obj"
"$bin" synth around --lines "$work/lines.obj" -o "$work/g.ply" -n 200000 --seed 1 >/dev/null
times=()
for _ in $(seq "$runs"); do
  start=$(date +%s.%N)
  "$bin" refine --backend cpu -g "$work/g.ply" -l "$work/lines.obj" -o "$work/out.obj" \
    --report "$work/r.json" >/dev/null
  end=$(date +%s.%N)
  times+=("$(echo "$end - $start" | bc -l)")
done
printf 'run %s s\n' "${times[@]}"
printf '%s\n' "${times[@]}" | sort -g | awk '{a[NR]=$1} END {printf "median %.3f s of %d runs\n", a[int((NR+1)/2)], NR}'
python3 -c '
import json, sys
r = json.load(open(sys.argv[1]))
print("segments", r["input"].get("segments_read"), "n_box", r["input"].get("n_box"))
print(" ".join("%s %.4f" % (s["name"], s["seconds"]) for s in r["stages"]))
' "$work/r.json"
