#!/usr/bin/env bash
# Builds the Python wheel with maturin in a throwaway virtual environment, installs it and
# runs the pytest suite. Needs Python 3 with venv and pip (and network for maturin, numpy,
# pytest). Shares the workspace's target folder so the core crates compile once.
#
# usage: crates/mrfmap-py/build-and-test.sh [VENV_DIR]
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../.." && pwd)
venv=${1:-$(mktemp -d)/venv}
python3 -m venv "$venv"
"$venv/bin/pip" install -q --upgrade pip
"$venv/bin/pip" install -q "maturin>=1.5,<2" pytest numpy "rosbags==0.11.9" "dask[distributed]>=2024.1"
CARGO_TARGET_DIR="$root/target" "$venv/bin/maturin" build --release -q -m "$here/Cargo.toml" -o "$venv/wheels"
"$venv/bin/pip" install -q --force-reinstall "$venv"/wheels/mrfmap-*.whl
# Run from outside the source tree so `import mrfmap` finds the installed wheel.
# Dask is installed above: its tests must run here, not skip.
cd "$venv" && MRFMAP_REQUIRE_DASK=1 "$venv/bin/python" -m pytest -q "$here/tests"
