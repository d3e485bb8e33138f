#!/usr/bin/env bash
# The Python package's tests: a fresh virtual environment in target/py-venv, `pip install .`
# (maturin builds python/ in the project's target folder and release profile), then pytest,
# which compares `linegs.refine` with the `linegs-gpu` binary of target/release.
set -euo pipefail
cd "$(dirname "$0")/.."
venv=target/py-venv
if [ ! -x "$venv/bin/python" ]; then
  python3 -m venv "$venv"
fi
"$venv/bin/python" -m pip install -q --upgrade pip
"$venv/bin/python" -m pip install -q numpy pytest
"$venv/bin/python" -m pip install -q .
cargo build --release --locked --bin linegs-gpu
LINEGS_GPU_BIN="$PWD/target/release/linegs-gpu" "$venv/bin/python" -m pytest -q python/tests
