#!/usr/bin/env bash
# Set everything up, then run the whole test suite (slow end-to-end tests included, in their small CI form).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/python -m pytest -q -p no:cacheprovider -n 2 "$@"
