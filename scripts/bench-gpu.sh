#!/usr/bin/env bash
# CPU engine versus GPU engine on a machine with a real GPU (issue 13): prints the adapter
# and a per-stage table at 10^6 Gaussians x 10^4 segments and 10^7 x 10^5, in one run per
# size so that the ratio is fair. Needs a Vulkan, Metal or DX12 driver for the GPU; a
# software adapter (lavapipe, WARP, SwiftShader) is measured too, with a warning.
# Usage: scripts/bench-gpu.sh [extra `linegs-gpu bench` options, e.g. --profile reference]
# Pick an adapter with WGPU_ADAPTER_NAME=<part of its name> (see `vulkaninfo --summary`).
# LINEGS_GPU_BIN=<path> uses that binary instead of building one; BENCH_GPU_SIZES="G S
# LIMIT;..." replaces the two sizes (Gaussians, segments, time limit in seconds), as the
# smoke test in tests/cli.rs does. On a hardware adapter it fails (exit 1) when the GPU
# run's host seconds exceed BENCH_GPU_MAX_HOST_SHARE percent (default 10) of the CPU run's
# total: the host's share bounds what any GPU can gain (docs/benchmarks.md#host-share-of-the-gpu-engine).
# On a software adapter the share is checked only when BENCH_GPU_MAX_HOST_SHARE is set (run
# it with LINEGS_GPU_MEMBERS=device LINEGS_GPU_FIT=device LINEGS_GPU_UPLOADS=staged, the
# configuration a hardware adapter gets, for the share a real GPU would see).
set -euo pipefail
cd "$(dirname "$0")/.."
# The folder cargo builds into: CARGO_TARGET_DIR, a .cargo/config setting, or ./target.
target_dir() {
  cargo metadata --format-version 1 --no-deps | sed -n 's/.*"target_directory":"\([^"]*\)".*/\1/p'
}

if [ -n "${LINEGS_GPU_BIN:-}" ]; then
  bin=$LINEGS_GPU_BIN
else
  cargo build --release --quiet --bin linegs-gpu
  bin=$(target_dir)/release/linegs-gpu
fi

echo "== machine: $(nproc) CPU threads; $(uname -srm)"
if command -v nvidia-smi >/dev/null; then
  nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader || true
fi

# Each size in one process (CPU then GPU), each engine's fastest of two runs: the first
# engine in a process pays alone for the memory the process had not used before (on the
# development machine nearly half of the CPU run's index stage at 10^6, about an eighth of
# its total: docs/benchmarks.md#host-share-of-the-gpu-engine). A --repeat among the options
# replaces the two. The time limits keep the script under 5 minutes.
extra=("$@")
repeat=(--repeat 2)
for x in "${extra[@]}"; do
  case $x in --repeat | --repeat=*) repeat=() ;; esac
done
IFS=';' read -r -a sizes <<<"${BENCH_GPU_SIZES:-1000000 10000 60;10000000 100000 220}"
for size in "${sizes[@]}"; do
  read -r g s limit <<<"$size"
  args=(bench --num-gaussians "$g" --num-segments "$s" --backend cpu,gpu "${repeat[@]}" "${extra[@]}")
  echo "== linegs-gpu ${args[*]}"
  out=$(timeout "$limit" "$bin" "${args[@]}") || {
    echo "bench at $g x $s failed or ran past $limit s" >&2
    exit 1
  }
  echo "$out"
  # The adapter's own line ("  gpu: <adapter> (N_box ...)"), not the counters' lines below it.
  if echo "$out" | grep -E "^  gpu: .*\(N_box " | grep -qiE "llvmpipe|lavapipe|swiftshader|warp|software"; then
    echo "WARNING: the GPU engine ran on a software adapter; these are not real-GPU numbers" >&2
    [ -n "${BENCH_GPU_MAX_HOST_SHARE:-}" ] || continue
  fi
  # The last line of the host-share table: "total <host s> <share>%".
  share=$(echo "$out" | awk '/^gpu host share/ { t = 1 } t && $1 == "total" { s = $NF } END { sub("%", "", s); print s }')
  max=${BENCH_GPU_MAX_HOST_SHARE:-10}
  if [ -z "$share" ] || awk -v s="$share" -v m="$max" 'BEGIN { exit !(s > m) }'; then
    echo "FAILED: at $g x $s the GPU run's host seconds are ${share:-?} % of the CPU run's total (target <= $max %)" >&2
    exit 1
  fi
  echo "host share at $g x $s: $share % of the CPU run's total (target <= $max %)"

done
