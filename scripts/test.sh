#!/usr/bin/env bash
# The project's one test command (README, .ci/run). Installs what the tests need when it
# is missing — Mesa's software Vulkan driver (lavapipe), so the GPU tests really run on a
# machine without a GPU, and Chromium for the viewer test — then checks formatting and
# lints and runs every test. Without a Vulkan adapter the GPU tests fail, unless
# LINEGS_SKIP_GPU_TESTS=1 (then they print SKIPPED).
set -euo pipefail
cd "$(dirname "$0")/.."

need=()
if ! ls /usr/share/vulkan/icd.d/lvp_icd.*.json >/dev/null 2>&1; then
  need+=(mesa-vulkan-drivers libvulkan1)
fi
if ! command -v chromium >/dev/null 2>&1; then
  need+=(chromium)
fi
if [ ${#need[@]} -gt 0 ]; then
  echo "installing: ${need[*]}"
  SUDO=""
  if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
  export DEBIAN_FRONTEND=noninteractive
  for attempt in 1 2 3; do
    if $SUDO apt-get update -qq && $SUDO apt-get install -y -qq --no-install-recommends "${need[@]}"; then
      break
    fi
    echo "apt-get failed (attempt $attempt); retrying in 10 s"
    sleep 10
  done
fi
if ls /usr/share/vulkan/icd.d/lvp_icd.*.json >/dev/null 2>&1; then
  echo "Vulkan: lavapipe installed"
else
  echo "Vulkan: no lavapipe ICD found; GPU tests will fail (LINEGS_SKIP_GPU_TESTS=1 skips them)"
fi

cargo fmt --check
cargo clippy --all-targets --locked -- -D warnings
# Release profile: the same build as `cargo run --release -- demo`. Debug assertions are
# off there, so the GPU engine's garbage-filled buffers are switched on by name.
export LINEGS_GPU_GARBAGE=1
cargo test --release --locked "$@"
# The Python package (`linegs`): opt in with LINEGS_TEST_PYTHON=1. pyo3's macros enable
# syn and once_cell features that the main build does not use, so today the binding
# recompiles most dependencies once more (see README, Python); too slow for every run.
if [ "${LINEGS_TEST_PYTHON:-0}" = 1 ]; then
  scripts/test-python.sh
fi
