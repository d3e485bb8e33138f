#!/usr/bin/env bash
# The Python package's tests (docs/python.md), run by scripts/test.sh after the Rust tests:
# a virtual environment in py-venv of cargo's target folder (CARGO_TARGET_DIR honoured),
# `pip install .` (maturin builds python/ in that target folder and the release profile),
# then pytest, which compares `linegs` with the `linegs-gpu` binary of the test build
# (release/linegs-gpu there). Under CI=true a test that cannot find the binary fails.
#
# The binding and `cargo test --release` ask for the same dependency features (Cargo.toml,
# python/Cargo.toml), so after the test build `pip install .` compiles only pyo3 and the
# binding. If it recompiles the main crate, the feature sets have drifted apart (a new
# dependency or feature on one side): this script fails and says so.
set -euo pipefail
cd "$(dirname "$0")/.."
# The folder cargo builds into: CARGO_TARGET_DIR, a .cargo/config setting, or ./target.
target_dir() {
  cargo metadata --format-version 1 --no-deps | sed -n 's/.*"target_directory":"\([^"]*\)".*/\1/p'
}
target=$(target_dir)
[ -n "$target" ] || { echo "test-python: cargo metadata names no target folder" >&2; exit 1; }
venv=$target/py-venv
if [ ! -x "$venv/bin/python" ]; then
  if ! python3 -m venv "$venv" 2>/dev/null; then
    rm -rf "$venv"
    echo "test-python: installing python3-venv"
    SUDO=""
    if [ "$(id -u)" -ne 0 ]; then SUDO="sudo -n"; fi
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends python3-venv </dev/null
    python3 -m venv "$venv"
  fi
fi
py=$venv/bin/python
"$py" -m pip install -q --disable-pip-version-check numpy pytest "maturin>=1.5,<2"

# The binary the tests compare with: the test build's (same features as `cargo test`).
if [ ! -x "$target/release/linegs-gpu" ]; then
  cargo test --release --locked --no-run
fi

t=$SECONDS
log=$target/py-build.log
# --no-build-isolation: maturin from the venv, not a fresh download per run.
if ! PATH="$venv/bin:$PATH" "$py" -m pip install -v --no-build-isolation --disable-pip-version-check . >"$log" 2>&1; then
  tail -n 40 "$log"
  echo "test-python: pip install . failed (full log: $log)" >&2
  exit 1
fi
compiled=$(grep -Eo 'Compiling [A-Za-z0-9_-]+ v[^ ]+' "$log" | sort -u || true)
echo "test-python: pip install . took $((SECONDS - t)) s, compiled $(echo "$compiled" | grep -c . || true) crates"
if echo "$compiled" | grep -q '^Compiling linegs-gpu '; then
  echo "$compiled" | sed 's/^/  /'
  echo "test-python: pip install . recompiled the main crate: the binding's dependency features" \
    "no longer match the test build's (see docs/python.md, Build)" >&2
  exit 1
fi
LINEGS_GPU_BIN="$target/release/linegs-gpu" "$py" -m pytest -q python/tests
