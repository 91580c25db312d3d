#!/usr/bin/env bash
# Create .venv and install torch==2.13.0 (CPU wheel) first, then the core and every distribution under
# adapters/, plugins/ and reference_models/ in editable mode. Safe to re-run: when no pyproject.toml changed since
# the last successful set-up, nothing is installed again.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
dists=(-e ".[test]")
for dir in adapters/* plugins/* reference_models/*; do
  if [ -f "$dir/pyproject.toml" ]; then dists+=(-e "$dir"); fi
done
stamp=.venv/.trafficrlhf-setup
wanted=$(cat pyproject.toml adapters/*/pyproject.toml plugins/*/pyproject.toml reference_models/*/pyproject.toml \
  | sha256sum | cut -d' ' -f1)
if [ -x .venv/bin/trafficrlhf ] && [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$wanted" ]; then
  echo "[setup] up to date: $(.venv/bin/trafficrlhf --version)"
  exit 0
fi
if [ ! -x .venv/bin/python ]; then
  echo "[setup] creating .venv with $($PYTHON --version)"
  "$PYTHON" -m venv .venv
fi
PIP=(.venv/bin/python -m pip install --disable-pip-version-check --progress-bar off)
# pip's exit status is kept; its "Collecting/Installing" lines show progress, the rest of its chatter is dropped
pip_install() {
  local rc
  set +e
  "${PIP[@]}" "$@" 2> >(grep -v "^WARNING: Location" >&2) \
    | { grep --line-buffered -E "^(Collecting|Installing|Successfully)" | sed -u 's/^/[setup]   /'; true; }
  rc=${PIPESTATUS[0]}
  set -e
  return "$rc"
}
echo "[setup] 1/2 torch==2.13.0 (CPU wheel; any other version pulls gigabytes of CUDA packages)"
pip_install "torch==2.13.0"
echo "[setup] 2/2 $(( ${#dists[@]} / 2 )) editable distributions and their dependencies (a few minutes the first time)"
pip_install "${dists[@]}"
.venv/bin/python -c "import torch, trafficrlhf_sdk; assert torch.__version__.startswith('2.13.0'), torch.__version__"
echo "$wanted" > "$stamp"
echo "[setup] done: $(.venv/bin/trafficrlhf --version)"
