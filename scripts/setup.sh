#!/usr/bin/env bash
# One-time set-up on a fresh Debian machine (Python 3.11, no GPU needed):
#   1. the system library open3d needs (libusb-1.0-0), via apt-get, only when missing;
#   2. a virtual environment in .venv;
#   3. this package, editable, with its dev extra (pytest), at the exact versions of scripts/constraints.txt
#      (the newest set measured; pyproject.toml states the supported ranges).
# Idempotent: a second run with unchanged pyproject.toml and constraints returns in about a second.
set -euo pipefail
cd "$(dirname "$0")/.."

if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  echo "[setup] installing libusb-1.0-0 (needed by open3d)"
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null
fi

PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  echo "[setup] creating .venv with $($PY --version)"
  "$PY" -m venv .venv
fi

stamp=.venv/.naka-gs-installed
want=$(cat pyproject.toml scripts/constraints.txt | sha1sum | cut -d' ' -f1)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  # The install needs ~8.5 GB; pip's own out-of-space error comes late and buries the cause.
  free_kb=$(df -Pk .venv | awk 'NR==2 {print $4}')
  if [ "$free_kb" -lt 9000000 ]; then
    echo "[setup] only $((free_kb / 1048576)) GB free on the disk of $(pwd)/.venv; the install needs ~9 GB: free some space and run again"
    exit 1
  fi
  echo "[setup] installing naka-gs and its dependencies into .venv (first time: ~2-3 min, ~8 GB)"
  start=$(date +%s)
  .venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip 2>&1 | grep -v "is ignored" || true
  # pip's own warnings about missing local index folders are noise on some machines: filter them.
  .venv/bin/python -m pip install -q --disable-pip-version-check -e ".[dev]" -c scripts/constraints.txt 2>&1 | grep -v "is ignored" || true
  .venv/bin/python -c "import naka_gs_plugin, nerfstudio, open3d, kornia" \
    || { echo "[setup] install failed: see the pip output above"; exit 1; }
  echo "$want" > "$stamp"
  echo "[setup] done in $(( $(date +%s) - start )) s; .venv is $(du -sh .venv | cut -f1)"
fi
