#!/usr/bin/env bash
# Set up (if needed) and run the main job on the embedded default scene (generated, no downloads).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export TORCHDYNAMO_DISABLE=1
exec .venv/bin/naka-gs-demo "$@"
