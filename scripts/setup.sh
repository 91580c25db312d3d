#!/usr/bin/env bash
# Create .venv and install torch==2.13.0 (CPU wheel) first, then the core and every distribution under
# adapters/, plugins/ and reference_models/ in editable mode. Safe to re-run.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  echo "[setup] creating .venv with $($PYTHON --version)"
  "$PYTHON" -m venv .venv
fi
PIP=(.venv/bin/python -m pip install --quiet --disable-pip-version-check)
# pip's exit status is kept; only the noise about local index folders that do not exist is dropped
pip_install() { "${PIP[@]}" "$@" 2> >(grep -v "^WARNING: Location" >&2); }
# torch first: any other version pulls gigabytes of CUDA packages
pip_install "torch==2.13.0"
dists=(-e ".[test]")
for dir in reference_models adapters/* plugins/* reference_models/*; do
  if [ -f "$dir/pyproject.toml" ]; then dists+=(-e "$dir"); fi
done
echo "[setup] installing $(( ${#dists[@]} / 2 )) editable distributions: ${dists[*]}"
pip_install "${dists[@]}"
.venv/bin/python -c "import torch, trafficrlhf_sdk; assert torch.__version__.startswith('2.13.0'), torch.__version__"
echo "[setup] done: $(.venv/bin/trafficrlhf --version)"
