#!/usr/bin/env bash
# Here (with the dev venv, ../shared/data and PyPI): stage the correction network's training data for
# `run.sh correction` (the GPU recipe, naka_gs_plugin/configs/correction/gpu.yaml). LOL + LOM are
# 112 MB, split in two parts of under 64 MiB each with the repository (15 MB), for transfers limited
# to that size (copy both along with the repository; run.sh correction reads both):
#   .gpu-corr-a/ (~50 MB): LOL train/high + eval
#   .gpu-corr-b/ (~51 MB): LOL train/low, the train + test views of the 4 LOM scenes (low/, high/,
#                                  transforms_{train,test}.json), and the wheels the GPU image lacks
# JPEGs are re-packed with `jpegtran -optimize -progressive` (lossless: the same DCT coefficients, so the
# same decoded pixels, which the check below asserts with OpenCV, the trainer's reader), 6 % smaller.
set -euo pipefail
cd "$(dirname "$0")/../.."
PY="${PYTHON:-.venv/bin/python}"
DATA="${DATA:-../shared/data}"
command -v jpegtran >/dev/null || { echo "jpegtran not found: apt-get install libjpeg-turbo-progs"; exit 1; }
rm -rf .gpu-corr-a .gpu-corr-b
pack() {  # pack SRC_DIR DEST_DIR [NAME...]: JPEGs losslessly re-packed, anything else copied
  local src=$1 dest=$2
  shift 2
  mkdir -p "$dest"
  local names=("$@")
  [ ${#names[@]} -gt 0 ] || mapfile -t names < <(ls "$src")
  for n in "${names[@]}"; do
    case "${n,,}" in
      *.jpg | *.jpeg) jpegtran -copy none -optimize -progressive -outfile "$dest/$n" "$src/$n" ;;
      *) cp "$src/$n" "$dest/$n" ;;
    esac
  done
}
pack "$DATA/lol/train/high" .gpu-corr-a/lol/train/high
pack "$DATA/lol/eval/high" .gpu-corr-a/lol/eval/high
pack "$DATA/lol/eval/low" .gpu-corr-a/lol/eval/low
pack "$DATA/lol/train/low" .gpu-corr-b/lol/train/low
for scene in bike chair shrub sofa; do
  src="$DATA/lom/$scene"
  mapfile -t frames < <("$PY" -c "import json, sys, pathlib; print('\n'.join(sorted({pathlib.Path(f['file_path']).name for s in ('train', 'test') for f in json.load(open(f'{sys.argv[1]}/transforms_{s}.json'))['frames']})))" "$src")
  pack "$src/low" ".gpu-corr-b/lom/$scene/low" "${frames[@]}"
  pack "$src/high" ".gpu-corr-b/lom/$scene/high" "${frames[@]}"
  cp "$src/transforms_train.json" "$src/transforms_test.json" ".gpu-corr-b/lom/$scene/"
done
# The GPU image has torch, numpy, OpenCV, PyYAML, rich and jaxtyping; these it lacks (dev venv versions).
"$PY" -m pip download --quiet --no-deps --only-binary=:all: --python-version 3.12 --implementation cp --abi cp312 \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
  -d .gpu-corr-b/wheels tyro==1.0.17 docstring-parser==0.18.0 typeguard==4.6.0 kornia==0.9.0 kornia_rs==0.2.0
"$PY" - "$DATA" <<'PYEOF'
import sys
from pathlib import Path
import numpy as np
from naka_gs_plugin.data.images import read_stored

data = Path(sys.argv[1])
staged = [p for root in (Path(".gpu-corr-a"), Path(".gpu-corr-b")) for p in root.rglob("*") if p.suffix.lower() in (".jpg", ".jpeg")]
for p in staged:
    rel = p.relative_to(p.parts[0])
    if not np.array_equal(read_stored(p), read_stored(data / rel)):
        raise SystemExit(f"{p} decodes differently from {data / rel}")
print(f"{len(staged)} staged JPEGs decode to the same pixels as the originals")
PYEOF
tracked=$(git ls-files -z | du -cb --files0-from=- | tail -1 | cut -f1)
for part in .gpu-corr-a .gpu-corr-b; do
  size=$(du -sb "$part" | cut -f1)
  echo "$part: $((size / 1000000)) MB + the repository $((tracked / 1000000)) MB = $(((size + tracked) / 1000000)) MB of the 67 MB (64 MiB) a call carries"
  [ $((size + tracked)) -lt 67108864 ] || { echo "$part is over 64 MiB with the repository"; exit 1; }
done
