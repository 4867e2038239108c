#!/usr/bin/env bash
# A plain (non-editable) `pip install .` works: package data (configs, weights) and console scripts.
# Installs into a fresh venv that sees .venv's packages (nothing is downloaded), then runs the demo
# from a folder outside the repository, and the smoke grid of benchmarks/ against it. Under 2 minutes on 2 cores.
set -euo pipefail
cd "$(dirname "$0")/.."
repo=$PWD
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
python=$(.venv/bin/python -c 'import sys; print(sys._base_executable)')
"$python" -m venv --without-pip "$tmp/venv"
# .venv's site-packages as a plain path: its .pth files (the editable install's finder) stay inactive.
site=$(.venv/bin/python -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
echo "$site" > "$("$tmp/venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')/dotvenv.pth"
# A copy of the sources: setuptools builds in the source tree, and a stale build/ there would be installed.
mkdir "$tmp/src"
tar --exclude=__pycache__ -cf - pyproject.toml README.md naka_gs_plugin | tar -xf - -C "$tmp/src"
"$tmp/venv/bin/python" -m pip install -q --disable-pip-version-check --no-deps --no-build-isolation --no-index \
  "$tmp/src" > "$tmp/pip.log" 2>&1 || { tail -20 "$tmp/pip.log"; echo "[check-install] pip install . failed"; exit 1; }
mkdir "$tmp/work" && cd "$tmp/work"
"$tmp/venv/bin/python" -c "import naka_gs_plugin; assert 'site-packages' in naka_gs_plugin.__file__, naka_gs_plugin.__file__"
export TORCHDYNAMO_DISABLE=1 NAKA_GS_CACHE="$tmp/cache" NUMBA_CACHE_DIR="$tmp/numba"
"$tmp/venv/bin/naka-gs-demo" --steps 20 --out demo > demo.log 2>&1 || { tail -20 demo.log; echo "[check-install] naka-gs-demo failed"; exit 1; }
# The wheel holds no benchmark code; the benchmarks run from a clone (here a copy of benchmarks/ alone)
# against the installed package.
"$tmp/venv/bin/python" -c "import importlib.util as u, naka_gs_plugin, pathlib; assert u.find_spec('benchmarks') is None and not (pathlib.Path(naka_gs_plugin.__file__).parent / 'bench').exists(), 'benchmark code in the wheel'"
mkdir "$tmp/clone" && tar -C "$repo" --exclude=__pycache__ -cf - benchmarks | tar -xf - -C "$tmp/clone"
PYTHONPATH="$tmp/clone" "$tmp/venv/bin/python" -m benchmarks.grid benchmarks/configs/smoke.yaml --out bench > bench.log 2>&1 \
  || { tail -20 bench.log; echo "[check-install] python -m benchmarks.grid benchmarks/configs/smoke.yaml failed"; exit 1; }
"$tmp/venv/bin/python" -c "import json, sys; runs = json.load(open('bench/results.json'))['runs']; bad = [k for k, r in runs.items() if r['status'] != 'ok']; sys.exit(f'[check-install] smoke grid runs failed: {bad}' if bad or not runs else 0)"
echo "[check-install] pip install . (non-editable, no benchmark code in it): naka-gs-demo ran outside the repo, and the smoke grid of benchmarks/ on it"
