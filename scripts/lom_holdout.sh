#!/usr/bin/env bash
# The real-scene protocol (docs/real-scenes.md): leave-one-scene-out over the LOM scenes.
#   1. for each scene X without them, the correction weights of the shipped recipe with --hold-out X
#      (outputs/correction-loo/X/best.pt; ~17 min each on an idle 2-core CPU);
#   2. the 2D score of those weights on X's test views (python -m benchmarks.correction_eval, low -> enhanced vs
#      normal light): outputs/correction-loo/X/eval_2d.json;
#   3. the 3D grid (default: benchmarks/configs/lom-holdout.yaml): ns-train naka-gs on X, scored on X's test
#      views at each milestone; table and plots in outputs/bench/<grid name>/.
# Resumable: finished weights, 2D scores and grid runs are kept. Usage:
#   bash scripts/lom_holdout.sh [--grid FILE] [--scenes "bike sofa"] [recipe flags for naka-gs-train-correction ...]
set -euo pipefail
cd "$(dirname "$0")/.."
grid=benchmarks/configs/lom-holdout.yaml
scenes="bike chair shrub sofa"
recipe=()
while [ $# -gt 0 ]; do
  case "$1" in
    --grid) grid=$2; shift 2 ;;
    --scenes) scenes=$2; shift 2 ;;
    *) recipe+=("$1"); shift ;;
  esac
done
bash scripts/setup.sh
for scene in $scenes; do
  weights=outputs/correction-loo/$scene
  if [ ! -f "$weights/best.pt" ]; then
    .venv/bin/naka-gs-train-correction --config naka_gs_plugin/configs/correction/default.yaml --hold-out "$scene" \
      --output-dir "$weights" "${recipe[@]}"
  fi
  if [ ! -f "$weights/eval_2d.json" ]; then
    .venv/bin/python -m benchmarks.correction_eval --lom "../shared/data/lom/$scene" --weights "$weights/best.pt" \
      --modes auto --output "$weights/eval_2d.json"
  fi
done
.venv/bin/python -m benchmarks.grid "$grid"
