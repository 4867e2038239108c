#!/usr/bin/env bash
# naka-gs as a plugin for the nerfstudio a user already has, on the oldest set we support
# (scripts/constraints-oldest.txt: torch 2.1.2 as nerfstudio's install guide has it, numpy < 2, nerfstudio 1.1.5).
#   1. an environment built as nerfstudio's guide does: torch + torchvision first, then nerfstudio;
#   2. our wheel (python -m build), installed into it as a user would: `pip install naka_gs-*.whl`;
#   3. checks: pip would not change torch, torchvision, numpy or nerfstudio; `pip check` is clean; torch's
#      version is unchanged; the demo trains and ns-eval scores its run; the quick tests pass against the wheel.
# The environment lives in .venv-oldest, kept between runs: ~8 GB, ~4 min to build the first time. Needs .venv
# (scripts/setup.sh) for `python -m build`. Run by scripts/test.sh in CI, with a smoke subset of the quick tests;
# arguments replace it (`-m "not slow" tests` runs them all). Another cell of the version matrix (docs/install.md):
#   NAKA_GS_COMPAT_PYTHON=python3.12 NAKA_GS_COMPAT_SET=scripts/constraints.txt NAKA_GS_COMPAT_VENV=/tmp/py312 \
#     bash scripts/check_compat.sh
set -euo pipefail
cd "$(dirname "$0")/.."
repo=$PWD
env=${NAKA_GS_COMPAT_VENV:-$repo/.venv-oldest}
set_file=$(realpath "${NAKA_GS_COMPAT_SET:-scripts/constraints-oldest.txt}")
base_python=${NAKA_GS_COMPAT_PYTHON:-$(.venv/bin/python -c 'import sys; print(sys._base_executable)')}
smoke=(tests/leaf/test_cpu.py tests/run/test_torch_load.py tests/data/test_dataparser.py
  tests/enhance/test_naka.py tests/enhance/test_exposure.py tests/enhance/test_profile.py
  tests/model/test_rasterize.py tests/model/test_rasterize_cpu_fast.py tests/model/test_project_cpu_fast.py
  tests/model/test_composite.py tests/model/test_ssim.py tests/model/test_model.py tests/model/test_lpips.py)
tests=("$@")
[ ${#tests[@]} -gt 0 ] || tests=(-m "not slow" "${smoke[@]}")
pip_q=(-q --disable-pip-version-check)
say() { echo "[check-compat] $*"; }

if [ ! -x "$env/bin/python" ]; then
  "$base_python" -m venv "$env"
fi
stamp=$env/.naka-gs-set
if [ "$(cat "$stamp" 2>/dev/null)" != "$(sha1sum < "$set_file")" ]; then
  say "building the environment of $(basename "$set_file") in $env (first time ~4 min, ~8 GB)"
  # nerfstudio's guide: torch and torchvision first (its CUDA build), then nerfstudio into that environment.
  "$env/bin/pip" install "${pip_q[@]}" -c "$set_file" torch torchvision "numpy<2" 2>&1 | grep -v "is ignored" || true
  "$env/bin/pip" install "${pip_q[@]}" -c "$set_file" nerfstudio pytest websockets 2>&1 | grep -v "is ignored" || true
  "$env/bin/python" -c "import nerfstudio, torch" || { say "the environment failed to install: see above"; exit 1; }
  sha1sum < "$set_file" > "$stamp"
fi

tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
torch_before=$("$env/bin/python" -c 'import torch; print(torch.__version__)')

# A copy of the sources: setuptools builds in the source tree, and a stale build/ there would be packaged.
mkdir "$tmp/src"
tar --exclude=__pycache__ -cf - pyproject.toml README.md LICENSE naka_gs_plugin | tar -xf - -C "$tmp/src"
.venv/bin/python -m build --wheel --outdir "$tmp/dist" "$tmp/src" > "$tmp/build.log" 2>&1 \
  || { tail -20 "$tmp/build.log"; say "python -m build failed"; exit 1; }
wheel=$(ls "$tmp"/dist/naka_gs-*.whl)

# What a user's plain `pip install` would do to their environment (no constraints): it must keep their stack.
"$env/bin/pip" install "${pip_q[@]}" --dry-run --report "$tmp/plan.json" "$wheel" > "$tmp/plan.log" 2>&1 \
  || { tail -20 "$tmp/plan.log"; say "pip cannot install the wheel beside torch $torch_before"; exit 1; }
"$env/bin/python" - "$tmp/plan.json" <<'EOF'
import json, sys
changed = {i["metadata"]["name"].lower() for i in json.load(open(sys.argv[1]))["install"]}
kept = changed & {"torch", "torchvision", "numpy", "nerfstudio", "gsplat"}
sys.exit(f"[check-compat] pip install of the wheel would replace {sorted(kept)}" if kept else 0)
EOF
# The real install, with the other dependencies at their oldest supported versions.
"$env/bin/pip" install "${pip_q[@]}" --force-reinstall --no-deps "$wheel" > "$tmp/pip.log" 2>&1 \
  && "$env/bin/pip" install "${pip_q[@]}" -c "$set_file" "$wheel" >> "$tmp/pip.log" 2>&1 \
  || { grep -v "is ignored" "$tmp/pip.log" | tail -20; say "pip install of the wheel failed"; exit 1; }
"$env/bin/pip" check > "$tmp/check.log" 2>&1 || { cat "$tmp/check.log"; say "pip check is not clean"; exit 1; }
torch_after=$("$env/bin/python" -c 'import torch; print(torch.__version__)')
[ "$torch_before" = "$torch_after" ] || { say "torch changed: $torch_before -> $torch_after"; exit 1; }

mkdir "$tmp/work" && cd "$tmp/work"
export TORCHDYNAMO_DISABLE=1 NAKA_GS_CACHE="$tmp/cache" NUMBA_CACHE_DIR="$tmp/numba"
"$env/bin/naka-gs-demo" --steps 20 --no-baseline --out demo > demo.log 2>&1 \
  || { tail -20 demo.log; say "naka-gs-demo failed"; exit 1; }
config=$(ls demo/run/*/naka-gs/*/config.yml | head -1)
"$env/bin/ns-eval" --load-config "$config" --output-path eval.json > eval.log 2>&1 \
  || { tail -20 eval.log; say "ns-eval failed"; exit 1; }
psnr=$("$env/bin/python" -c "import json; print(round(json.load(open('eval.json'))['results']['psnr'], 2))")

# The tests against the installed wheel: a copy of the repository without the package's sources, run by the
# environment's pytest script (which, unlike `python -m pytest`, puts no working folder on the path).
mkdir "$tmp/clone" && tar -C "$repo" --exclude=__pycache__ -cf - pyproject.toml README.md LICENSE docs tests \
  benchmarks scripts | tar -xf - -C "$tmp/clone"
# The real scenes some tests read lie beside a clone, and the shipped specs name them relative to it.
[ -d "$repo/../shared" ] && ln -s "$(realpath "$repo/../shared")" "$tmp/shared"
cd "$tmp/clone"
[ -z "${PYTHONPATH:-}" ] || { say "PYTHONPATH is set: unset it, the tests must import the installed wheel"; exit 1; }
"$env/bin/pytest" -q -p no:cacheprovider --rootdir "$tmp/clone" -c "$tmp/clone/pyproject.toml" \
  "${tests[@]/#tests/$tmp/clone/tests}" > "$tmp/pytest.log" 2>&1 \
  || { grep -E "^(FAILED|ERROR)|^E " "$tmp/pytest.log" | head -40; tail -3 "$tmp/pytest.log"; say "tests failed on this set"; exit 1; }
say "$(basename "$set_file"): Python $("$env/bin/python" -c 'import platform; print(platform.python_version())'), torch $torch_after (kept)," \
  "nerfstudio $("$env/bin/python" -c 'import nerfstudio, importlib.metadata as m; print(m.version("nerfstudio"))'): pip check clean," \
  "demo trained, ns-eval PSNR $psnr dB, $(tail -1 "$tmp/pytest.log")"
