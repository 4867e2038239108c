#!/usr/bin/env bash
# Set up (if needed) and run the whole test suite on CPU. Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
# torch.compile (nerfstudio's get_viewmat) costs ~20 s per process on CPU and buys nothing in tests.
export TORCHDYNAMO_DISABLE=1
exec .venv/bin/python -m pytest -q "$@"
