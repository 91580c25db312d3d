#!/usr/bin/env bash
# Install Debian's Chromium for the annotation app's real-browser test (plugins/annotation_web/tests).
# Idempotent: does nothing when /usr/bin/chromium exists. Needs root (or sudo) and the Debian package archive.
# The test drives this browser with the Python `playwright` package and `executable_path=/usr/bin/chromium`;
# it never runs `playwright install` (which would download a browser build of its own).
set -euo pipefail
if command -v chromium >/dev/null 2>&1; then
  echo "[browser] chromium present: $(chromium --version 2>/dev/null || echo unknown version)"
  exit 0
fi
SUDO=""
if [ "$(id -u)" -ne 0 ]; then
  if command -v sudo >/dev/null 2>&1; then SUDO="sudo"; else
    echo "[browser] not root and no sudo: install Debian's 'chromium' package yourself" >&2; exit 1
  fi
fi
echo "[browser] installing Debian's chromium"
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
$SUDO apt-get install -y -qq --no-install-recommends chromium fonts-dejavu-core >/dev/null
echo "[browser] installed: $(chromium --version 2>/dev/null || echo unknown version)"
