#!/usr/bin/env bash
# Fill .gpu-wheels/ (git-ignored) with the wheels the GPU machine lacks, for CPython 3.12 on
# x86-64 Linux: gsplat 1.4.0 (pure Python; compiles its CUDA kernels on first use) and the small
# pure dependencies of gsplat, the parity harness (tyro) and pytest. torch and numpy are already
# there, so every wheel is fetched with --no-deps from this explicit list (a resolver would pull
# torch). Versions are those of the development venv. Needs network access to PyPI.
set -euo pipefail
cd "$(dirname "$0")/../.."
PY="${PYTHON:-.venv/bin/python}"
DEST=.gpu-wheels
WHEELS=(
  gsplat==1.4.0 ninja==1.13.2
  jaxtyping==0.3.11 wadler-lindig==0.1.8
  rich==15.0.0 markdown-it-py==4.3.0 mdurl==0.1.2 pygments==2.21.0
  tyro==1.0.17 docstring-parser==0.18.0 typeguard==4.6.0 typing-extensions==4.16.0
  pytest==9.2.0 pluggy==1.7.0 iniconfig==2.3.1 packaging==26.3
)
# `run.sh train` (nerfstudio's trainer on the GPU): nerfstudio and what its import path and ours need
# beyond the GPU image's packages (found by tracing the imports of a python -m benchmarks.grid run), except
# pycolmap (38 MB: prepare_train.sh turns the COLMAP model into a PLY instead).
TRAIN_WHEELS=(
  nerfstudio==1.1.5 viser==0.2.7 nerfacc==0.5.2 rawpy==0.28.0 msgspec==0.22.0 pyquaternion==0.9.9
  pytorch_msssim==1.0.0 splines==0.3.0 tensorly==0.10.0 appdirs==1.4.4 defusedxml==0.7.1 dill==0.4.1
  PySocks==1.7.1 websockets==17.4 torch-fidelity==0.4.0 kornia==0.9.0 kornia_rs==0.2.0 cffi==2.1.1
  pycparser==3.12 plyfile==1.1.3
  fpsample==0.3.3  # the dev venv's 1.0.2 has no cp312 manylinux wheel; nerfstudio imports it, sofa does not use it
)
fetch() {
  "$PY" -m pip download --quiet --no-deps --only-binary=:all: \
    --python-version 3.12 --implementation cp --abi cp312 \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
    --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform manylinux_2_5_x86_64 \
    --platform manylinux1_x86_64 -d "$@"
}
rm -rf "$DEST"
mkdir -p "$DEST/train"
fetch "$DEST" "${WHEELS[@]}"
fetch "$DEST/train" "${TRAIN_WHEELS[@]}"
ls -l "$DEST" "$DEST/train"
du -sh "$DEST" "$DEST/train"
