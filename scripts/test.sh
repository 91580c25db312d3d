#!/usr/bin/env bash
# Set everything up, then run the whole test suite (slow end-to-end tests included, in their small CI form).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
# Debian's chromium for the annotation app's real-browser test (skipped, with its reason, if this fails)
bash scripts/install_browser.sh || echo "[browser] chromium could not be installed: the browser test will skip"
# lint first (ruff pinned in the test extra, rules in pyproject.toml): a few seconds
.venv/bin/ruff check .
# the documentation site builds without a warning (API reference generated from the docstrings); the warnings
# print, and --strict fails the build on any, broken links and anchors included (validation in mkdocs.yml)
NO_MKDOCS_2_WARNING=1 .venv/bin/mkdocs build --strict -d "$(mktemp -d)"
exec .venv/bin/python -m pytest -q -p no:cacheprovider -n 2 "$@"
