#!/usr/bin/env bash
# Set up (if needed) and run the whole test suite on CPU; extra arguments go to pytest. The full run
# (no arguments, as CI) then checks a non-editable install (scripts/check_install.sh, < 2 min) and the wheel in
# nerfstudio's guide environment, as a user's plain `pip install` and at our oldest pins (scripts/check_compat.sh:
# ~14 min on 2 busy cores; ~4 min more and ~8 GB to build that environment the first time).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
# Style first (seconds): the formatter and the linter as configured in pyproject.toml.
.venv/bin/ruff format --check --quiet .
.venv/bin/ruff check --quiet .
# torch.compile (nerfstudio's get_viewmat) costs ~20 s per process on CPU and buys nothing in tests.
export TORCHDYNAMO_DISABLE=1
.venv/bin/python -m pytest -q "$@"
if [ $# -eq 0 ]; then
  bash scripts/check_install.sh
  bash scripts/check_compat.sh
fi
