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
rm -rf "$DEST"
mkdir -p "$DEST"
"$PY" -m pip download --quiet --no-deps --only-binary=:all: \
  --python-version 3.12 --implementation cp --abi cp312 \
  --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform manylinux_2_5_x86_64 \
  -d "$DEST" "${WHEELS[@]}"
ls -l "$DEST"
du -sh "$DEST"
