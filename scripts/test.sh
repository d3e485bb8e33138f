#!/usr/bin/env bash
# The project's one test command (README, .ci/run). Installs what the tests need when it
# is missing — Mesa's software Vulkan driver (lavapipe) when no Vulkan driver at all is
# present, so the GPU tests really run on a machine without a GPU, and Chromium for the
# viewer test — then checks formatting and lints and runs every test: Rust, Python
# (scripts/test-python.sh) and Slurm (scripts/test-slurm.sh, which installs slurm-wlm
# and munge when missing). Without a Vulkan
# adapter the GPU tests fail, unless LINEGS_SKIP_GPU_TESTS=1 (then they print SKIPPED).
set -euo pipefail
cd "$(dirname "$0")/.."

# Any Vulkan driver will do (a real GPU's or lavapipe): lavapipe is installed only when
# the loader has no driver manifest at all and vulkaninfo (if present) sees no device.
have_vulkan() {
  local f
  for f in /usr/share/vulkan/icd.d/*.json /etc/vulkan/icd.d/*.json; do
    if [ -e "$f" ]; then return 0; fi
  done
  command -v vulkaninfo >/dev/null 2>&1 && vulkaninfo --summary 2>/dev/null | grep -q deviceName
}
chromium_on_path() {
  command -v chromium >/dev/null 2>&1 || command -v chromium-browser >/dev/null 2>&1 ||
    command -v google-chrome >/dev/null 2>&1
}

need=()
if ! have_vulkan; then
  need+=(mesa-vulkan-drivers libvulkan1)
fi
if ! chromium_on_path; then
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
if have_vulkan; then
  echo "Vulkan: driver found ($(ls /usr/share/vulkan/icd.d /etc/vulkan/icd.d 2>/dev/null | grep json | tr '\n' ' ' || true))"
else
  echo "Vulkan: no driver found; GPU tests will fail (LINEGS_SKIP_GPU_TESTS=1 skips them)"
fi

# Each phase says how long it took, so that a slow fresh clone shows where the time went.
phase() {
  local t=$SECONDS
  "$@"
  echo "test.sh: '$*' took $((SECONDS - t)) s"
}
phase cargo fmt --check
# --workspace: the Python binding too (its dependencies are the same check artefacts).
phase cargo clippy --workspace --all-targets --locked -- -D warnings
# The GPU tests start Mesa's drivers inside the test processes, where the binary's private
# XDG_RUNTIME_DIR (src/main.rs) does not reach: give them one too, or every GPU test prints
# Wayland's "error: XDG_RUNTIME_DIR is invalid or not set" into a passing run.
if [ ! -d "${XDG_RUNTIME_DIR:-}" ]; then
  XDG_RUNTIME_DIR="$(mktemp -d)" # mktemp -d creates it 0700, as the XDG spec requires
  export XDG_RUNTIME_DIR
  trap 'rm -rf "$XDG_RUNTIME_DIR"' EXIT
fi
# Release profile: the same build as `cargo run --release -- demo`. Debug assertions are
# off there, so the GPU engine's garbage-filled buffers are switched on by name.
export LINEGS_GPU_GARBAGE=1
phase cargo test --release --locked "$@"
# The Python package (`linegs`, docs/python.md): `pip install .` reuses the test build's
# dependency artefacts (the feature sets are unified), then pytest compares it with the
# binary. Then scripts/slurm-batch.sh on a one-node Slurm cluster (docs/cluster.md).
phase scripts/test-python.sh
phase scripts/test-slurm.sh
