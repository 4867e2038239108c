#!/usr/bin/env bash
# naka-gs as a plugin for the nerfstudio a user already has, in the oldest environment we support: nerfstudio's
# install guide (torch 2.1.2 and torchvision 0.16.2 first, then nerfstudio 1.1.5; the pins of
# scripts/constraints-oldest.txt). Two cells of the version matrix (docs/install.md) in that one environment:
#   user:   the guide's environment as it was built (restored to its freeze first, so that every run resolves
#           afresh), then `pip install naka_gs-*.whl` with no constraints, as a user types it; checks: torch,
#           torchvision, numpy, nerfstudio and gsplat unchanged, `pip check` clean, naka-gs-sim writes a scene,
#           200 steps of `ns-train naka-gs` train on it and ns-eval scores the run;
#   pinned: then our other dependencies at their oldest supported versions (the whole set file as constraints);
#           checks: `pip check` clean, torch unchanged, the demo trains and ns-eval scores its run, the quick tests
#           pass against the wheel.
# The environment lives in .venv-oldest, kept between runs: ~8 GB, ~4 min to build the first time; each run 14 min on
# 2 busy cores (user 6, pinned 8). Needs .venv (scripts/setup.sh) for `python -m build`. Run by scripts/test.sh in CI,
# with a smoke subset of the quick tests in the pinned cell; arguments replace it (`-m "not slow" tests` runs them
# all). Another set:
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
pinned() { grep -E "^$1==" "$set_file" || { say "$(basename "$set_file") pins no $1"; exit 1; }; }
version() { "$env/bin/python" -c "import importlib.metadata as m; print(m.version('$1'))"; }
stack=(torch torchvision numpy nerfstudio gsplat)
stack_versions() { for p in "${stack[@]}"; do printf '%s ' "$p=$(version "$p" 2>/dev/null || echo none)"; done; }

if [ ! -x "$env/bin/python" ]; then
  "$base_python" -m venv "$env"
fi
# The guide's environment, as pip resolves it (no constraints beyond the guide's versions, and numpy < 2, which
# torch 2.1 was built against: torchvision alone would pull numpy 2); its freeze is the stamp.
guide=("$(pinned torch)" "$(pinned torchvision)" "$(pinned numpy)" "$(pinned nerfstudio)")
freeze=$env/.naka-gs-guide-freeze
if [ "$(head -1 "$freeze" 2>/dev/null)" != "# ${guide[*]}" ]; then
  say "building nerfstudio's guide environment (${guide[*]}) in $env (first time ~4 min, ~8 GB)"
  "$env/bin/pip" install "${pip_q[@]}" "${guide[@]:0:3}" 2>&1 | grep -v "is ignored" || true
  "$env/bin/pip" install "${pip_q[@]}" "${guide[3]}" 2>&1 | grep -v "is ignored" || true
  "$env/bin/python" -c "import nerfstudio, torch" || { say "the environment failed to install: see above"; exit 1; }
  { echo "# ${guide[*]}"; "$env/bin/pip" freeze --exclude-editable; } > "$freeze.new" && mv "$freeze.new" "$freeze"
fi

tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT

# A copy of the sources: setuptools builds in the source tree, and a stale build/ there would be packaged.
mkdir "$tmp/src"
tar --exclude=__pycache__ -cf - pyproject.toml README.md LICENSE naka_gs_plugin | tar -xf - -C "$tmp/src"
.venv/bin/python -m build --wheel --outdir "$tmp/dist" "$tmp/src" > "$tmp/build.log" 2>&1 \
  || { tail -20 "$tmp/build.log"; say "python -m build failed"; exit 1; }
wheel=$(ls "$tmp"/dist/naka_gs-*.whl)

SECONDS=0
# ---- user cell: the guide's environment exactly (what an earlier run added removed, what it changed put back).
"$env/bin/pip" freeze --exclude-editable | sed -E 's/ @ .*//; s/==.*//' | sort > "$tmp/now.txt"
grep -v '^#' "$freeze" | sed -E 's/ @ .*//; s/==.*//' | sort > "$tmp/guide.txt"
added=$(comm -23 "$tmp/now.txt" "$tmp/guide.txt")
[ -z "$added" ] || "$env/bin/pip" uninstall "${pip_q[@]}" -y $added > "$tmp/restore.log" 2>&1 \
  || { tail -20 "$tmp/restore.log"; say "could not restore the guide's environment"; exit 1; }
grep -v '^#' "$freeze" > "$tmp/guide-freeze.txt"
"$env/bin/pip" install "${pip_q[@]}" -r "$tmp/guide-freeze.txt" >> "$tmp/restore.log" 2>&1 \
  || { grep -v "is ignored" "$tmp/restore.log" | tail -20; say "could not restore the guide's environment"; exit 1; }
stack_before=$(stack_versions)
"$env/bin/pip" install "${pip_q[@]}" "$wheel" > "$tmp/pip-user.log" 2>&1 \
  || { grep -v "is ignored" "$tmp/pip-user.log" | tail -20; say "user: pip install of the wheel failed"; exit 1; }
stack_after=$(stack_versions)
[ "$stack_before" = "$stack_after" ] || { say "user: pip install changed $stack_before-> $stack_after"; exit 1; }
"$env/bin/pip" check > "$tmp/check.log" 2>&1 || { cat "$tmp/check.log"; say "user: pip check is not clean"; exit 1; }
resolved=$(for p in kornia numba pycolmap open3d opencv-python-headless imageio-ffmpeg; do printf '%s, ' "$p $(version $p)"; done)

mkdir "$tmp/work" && cd "$tmp/work"
export TORCHDYNAMO_DISABLE=1 NAKA_GS_CACHE="$tmp/cache" NUMBA_CACHE_DIR="$tmp/numba"
"$env/bin/naka-gs-sim" configs/scenes/dark-noisy.yaml --out scene > sim.log 2>&1 \
  || { tail -20 sim.log; say "user: naka-gs-sim failed"; exit 1; }
"$env/bin/ns-train" naka-gs --max-num-iterations 200 --vis tensorboard --viewer.quit-on-train-completion True \
  --output-dir user --timestamp run --data scene > train.log 2>&1 \
  || { tail -20 train.log; say "user: ns-train naka-gs failed"; exit 1; }
"$env/bin/ns-eval" --load-config user/scene/naka-gs/run/config.yml --output-path user-eval.json > user-eval.log 2>&1 \
  || { tail -20 user-eval.log; say "user: ns-eval failed"; exit 1; }
user_psnr=$("$env/bin/python" -c "import json; print(round(json.load(open('user-eval.json'))['results']['psnr'], 2))")
say "user: plain pip install beside ${guide[*]}: ${stack_after}kept; resolved ${resolved%, }; pip check clean;" \
  "naka-gs-sim scene, 200 steps of ns-train naka-gs, ns-eval PSNR $user_psnr dB (${SECONDS} s)"
SECONDS=0
cd "$repo"

# ---- pinned cell: the other dependencies at their oldest supported versions, in the same environment.
"$env/bin/pip" install "${pip_q[@]}" -c "$set_file" "$wheel" pytest websockets > "$tmp/pip.log" 2>&1 \
  || { grep -v "is ignored" "$tmp/pip.log" | tail -20; say "pinned: pip install of the wheel failed"; exit 1; }
"$env/bin/pip" check > "$tmp/check.log" 2>&1 || { cat "$tmp/check.log"; say "pinned: pip check is not clean"; exit 1; }
[ "$stack_before" = "$(stack_versions)" ] || { say "pinned: changed $stack_before-> $(stack_versions)"; exit 1; }

cd "$tmp/work"
"$env/bin/naka-gs-demo" --steps 20 --no-baseline --out demo > demo.log 2>&1 \
  || { tail -20 demo.log; say "pinned: naka-gs-demo failed"; exit 1; }
config=$(ls demo/run/*/naka-gs/*/config.yml | head -1)
"$env/bin/ns-eval" --load-config "$config" --output-path eval.json > eval.log 2>&1 \
  || { tail -20 eval.log; say "pinned: ns-eval failed"; exit 1; }
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
say "pinned: $(basename "$set_file"): Python $("$env/bin/python" -c 'import platform; print(platform.python_version())')," \
  "${stack_before}kept: pip check clean, demo trained, ns-eval PSNR $psnr dB, $(tail -1 "$tmp/pytest.log") (${SECONDS} s)"
