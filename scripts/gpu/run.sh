#!/usr/bin/env bash
# The CUDA checks of issue 19 on a GPU machine (Python 3.12, torch with CUDA and nvcc, numpy 2; no
# nerfstudio, no network). Run from anywhere; results go under $OUT (default ./gpu-out).
#   bash scripts/gpu/run.sh                 # all steps: env install build parity tests timing
#   bash scripts/gpu/run.sh install build   # only these (each step logs to $OUT/<step>.log)
# Needs .gpu-wheels/ (scripts/gpu/fetch_wheels.sh, on a machine with network). Optional:
# NAKA_GS_PARITY_CKPT=path/to/step-*.ckpt adds a trained scene to the parity table and tests.
set -uo pipefail
cd "$(dirname "$0")/../.."
ROOT=$PWD
OUT="${OUT:-$ROOT/gpu-out}"
PY="${PYTHON:-python3}"
SITE=$ROOT/.gpu-build/site
mkdir -p "$OUT" "$SITE"
# Wheels install into a private target dir put first on sys.path (no system or user site changes).
export PYTHONPATH="$SITE:$ROOT${PYTHONPATH:+:$PYTHONPATH}"
export PATH="$SITE/bin:$PATH"
# gsplat's JIT build lives here, so it survives between runs on the same machine.
export TORCH_EXTENSIONS_DIR=$ROOT/.gpu-build/torch_extensions
export MAX_JOBS="${MAX_JOBS:-$(nproc)}"
export TORCHDYNAMO_DISABLE=1

step_env() {
  nvidia-smi || true
  nvcc --version || true
  "$PY" - <<'PYEOF'
import sys, numpy, torch
print(sys.version, "| numpy", numpy.__version__, "| torch", torch.__version__, "cuda", torch.version.cuda)
print("CUDA available:", torch.cuda.is_available(), torch.cuda.get_device_name(0) if torch.cuda.is_available() else "")
PYEOF
  lscpu | head -20
}

step_install() {
  ls .gpu-wheels/*.whl >/dev/null || { echo "no .gpu-wheels/: run scripts/gpu/fetch_wheels.sh and carry .gpu-wheels"; return 1; }
  # --no-deps: the list is complete (torch and numpy are already there; a resolver would want them).
  "$PY" -m pip install --quiet --no-index --no-deps --upgrade --target "$SITE" .gpu-wheels/*.whl
  "$PY" -c "import gsplat, jaxtyping, tyro, rich, pytest; print('gsplat', gsplat.__version__)"
  if ls .gpu-wheels/train/*.whl >/dev/null 2>&1; then
    "$PY" -m pip install --quiet --no-index --no-deps --upgrade --target "$SITE" .gpu-wheels/train/*.whl
    "$PY" -c "import nerfstudio.engine.trainer, naka_gs_plugin.config; print('nerfstudio imports')"
  fi
  command -v ninja
}

step_build() {
  # A build made by an earlier call (carried as .gpu-build/prebuilt/gsplat_cuda.so.gz, see below)
  # is installed as gsplat's precompiled module, which gsplat imports before trying to build.
  if [ -f .gpu-build/prebuilt/gsplat_cuda.so.gz ]; then
    gunzip -c .gpu-build/prebuilt/gsplat_cuda.so.gz >"$SITE/gsplat/gsplat_cuda.so"
    # gsplat imports `gsplat.csrc`; the built module's init symbol is named gsplat_cuda.
    printf '%s\n' "import importlib.util, os, sys" \
      "_spec = importlib.util.spec_from_file_location('gsplat_cuda', os.path.join(os.path.dirname(__file__), 'gsplat_cuda.so'))" \
      "_mod = importlib.util.module_from_spec(_spec)" "_spec.loader.exec_module(_mod)" "sys.modules[__name__] = _mod" \
      >"$SITE/gsplat/csrc.py"
    "$PY" -c "from gsplat.cuda._backend import _C; assert _C is not None; print('gsplat: carried build loaded')"
    return
  fi
  # The same torch.utils.cpp_extension.load call as gsplat 1.4.0's cuda/_backend.py (name, sources,
  # flags, build dir), made here because ninja resumes it if a call times out, whereas gsplat's own
  # first import deletes a build directory that has no .so yet. Afterwards gsplat just loads it.
  if [ -z "${TORCH_CUDA_ARCH_LIST:-}" ]; then
    TORCH_CUDA_ARCH_LIST=$("$PY" -c "import torch; print('%d.%d' % torch.cuda.get_device_capability())")
    export TORCH_CUDA_ARCH_LIST
  fi
  echo "TORCH_CUDA_ARCH_LIST=$TORCH_CUDA_ARCH_LIST MAX_JOBS=$MAX_JOBS"
  "$PY" - <<'PYEOF'
import glob, os, time
from torch.utils.cpp_extension import _get_build_directory, load
import gsplat.cuda as pkg

path = os.path.dirname(os.path.abspath(pkg.__file__))
started = time.time()
load(
    name="gsplat_cuda",
    sources=list(glob.glob(os.path.join(path, "csrc/*.cu"))) + list(glob.glob(os.path.join(path, "csrc/*.cpp"))),
    extra_cflags=["-O3"],
    extra_cuda_cflags=["-O3"] if os.getenv("NO_FAST_MATH", "0") == "1" else ["-O3", "--use_fast_math"],
    extra_include_paths=[os.path.join(path, "csrc/"), os.path.join(path, "csrc", "third_party", "glm")],
    build_directory=_get_build_directory("gsplat_cuda", verbose=False),
    verbose=True,
)
from gsplat.cuda._backend import _C
assert _C is not None, "gsplat's CUDA extension did not load"
print(f"gsplat CUDA extension ready in {time.time() - started:.0f} s")
PYEOF
  # Sent back so that later calls (a fresh machine each) can carry it instead of building again.
  local so
  so=$("$PY" -c "from torch.utils.cpp_extension import _get_build_directory as d; print(d('gsplat_cuda', False))")/gsplat_cuda.so
  gzip -c "$so" >"$OUT/gsplat_cuda.so.gz" && ls -l "$so" "$OUT/gsplat_cuda.so.gz"
}

step_parity() {
  local ckpt=()
  if [ -n "${NAKA_GS_PARITY_CKPT:-}" ]; then ckpt=(--checkpoint "$NAKA_GS_PARITY_CKPT" --max-gaussians 200000); fi
  # The saved reference (inputs + gsplat outputs) lets cpu-fast be compared on a CPU afterwards:
  # python -m benchmarks.cuda_parity --reference-file .../gsplat_reference.pt
  "$PY" -m benchmarks.cuda_parity --reference gsplat "${ckpt[@]}" \
    --out-dir "$OUT/parity" --save-reference "$OUT/parity/gsplat_reference.pt"
}

step_tests() {
  # --noconftest: tests/conftest.py imports the toy-scene writer (Pillow), which this file does not use.
  "$PY" -m pytest -q -rs --noconftest -p no:cacheprovider --junitxml "$OUT/tests.xml" tests/benchmarks/test_cuda_parity.py
}

step_timing() {
  "$PY" -m benchmarks.cuda_parity --mode timing --out-dir "$OUT/timing"
}

step_train() {
  # nerfstudio's trainer with NakaGSModel on gsplat: the grid $GRID (default scripts/gpu/cuda-vs-cpu.yaml,
  # whose CPU side is the same command here). Needs .gpu-data/ (scripts/gpu/prepare_train.sh) and the
  # train wheels. $TRAIN_LIMIT_S (default 480) stops the grid in time for its results to come back.
  [ -d .gpu-data ] || { echo "no .gpu-data/: run scripts/gpu/prepare_train.sh here and carry .gpu-data"; return 1; }
  local grid=${GRID:-scripts/gpu/cuda-vs-cpu.yaml} rc=0
  local name
  name=$(basename "$grid" .yaml)
  if [ "${TRAIN_PARALLEL:-0}" = 1 ]; then
    # Every run of the grid at once, each its own grid process (own folder, CPU threads split between
    # them): small scenes leave the GPU mostly idle between one run's kernel launches. A run stopped by
    # the limit keeps its log, whose "[naka-gs bench] ... step N: PSNR" lines are its milestones so far.
    local ids id pids=()
    mapfile -t ids < <("$PY" -c "import sys; from pathlib import Path; from benchmarks.grid import grid_runs, load_grid; print('\n'.join(r['id'] for r in grid_runs(load_grid(Path(sys.argv[1])), Path('.'))))" "$grid")
    local threads=$(($(nproc) / ${#ids[@]})); [ "$threads" -ge 1 ] || threads=1
    for id in "${ids[@]}"; do
      PYTHONUNBUFFERED=1 OMP_NUM_THREADS=$threads NUMBA_NUM_THREADS=$threads MPLBACKEND=Agg timeout -k 10 "${TRAIN_LIMIT_S:-480}" \
        "$PY" -m benchmarks.grid "$grid" --only "$id" --out "$OUT/$name/${id//\//-}" >"$OUT/$name-${id//\//-}.log" 2>&1 &
      pids+=($!)
    done
    for i in "${!pids[@]}"; do wait "${pids[$i]}" || { echo "${ids[$i]}: exit $?"; rc=1; }; done
    grep -h "step [0-9]*: PSNR" "$OUT/$name"/*/logs/*/*/log.txt
    # Results, logs and configs only: a run stopped mid-save leaves a checkpoint being written, the runs'
    # other files (enhanced images, seed points) took the archive past the 16 MB a file may have to come
    # back from such a machine, and at most 8 files come back: everything else goes.
    (cd "$OUT" && find "$name" -type f \( -name '*.log' -o -name '*.txt' -o -name '*.json' -o -name '*.yml' -o -name '*.md' \) \
      -size -2M -print0 | tar czf "$name.tgz" --warning=no-file-changed --null -T - "$name"-*.log)
    rm -rf "${OUT:?}/$name" "$OUT/$name"-*.log
    return $rc
  fi
  MPLBACKEND=Agg timeout "${TRAIN_LIMIT_S:-480}" "$PY" -m benchmarks.grid "$grid" --out "$OUT/$name" || rc=$?
  # The grid records a failed run and carries on; here a failed run fails the step.
  "$PY" -c "import json, sys; r = json.load(open(sys.argv[1]))['runs']; bad = [k for k, v in r.items() if v['status'] != 'ok']; print('failed runs:', bad) if bad else None; sys.exit(bool(bad))" "$OUT/$name/results.json" || rc=1
  # The run folder as one archive (no checkpoint): one file to copy back.
  tar czf "$OUT/$name.tgz" --exclude '*.ckpt' --exclude cache -C "$OUT" "$name" && rm -rf "${OUT:?}/$name"
  return $rc
}

step_correction() {
  # The correction network's GPU recipe ($RECIPE, default naka_gs_plugin/configs/correction/gpu.yaml):
  # the shipped weights (all data) and the 4 leave-one-scene-out variants of the LOM protocol, trained
  # at once on the one GPU (CPU cores split between them for loading and augmentation). Data staged by
  # prepare_correction.sh in two parts, .gpu-corr-a and .gpu-corr-b. Epochs: the recipe's, lowered so that all five fit $CORRECTION_BUDGET_S seconds
  # (default 400) by a timed probe of training iterations. Results: $OUT/correction-<name>.pt (float16,
  # as shipped; provenance inside) and correction-runs.tgz (logs, history.json per run).
  local a=.gpu-corr-a b=.gpu-corr-b recipe=${RECIPE:-naka_gs_plugin/configs/correction/gpu.yaml}
  [ -d $a/lol/train/high ] || { echo "no $a/: carry it in a call just before this one (prepare_correction.sh)"; return 1; }
  [ -d $b/lol/train/low ] || { echo "no $b/: carry it (prepare_correction.sh)"; return 1; }
  "$PY" -c "import kornia, tyro" 2>/dev/null ||
    "$PY" -m pip install --quiet --no-index --no-deps --upgrade --target "$SITE" $b/wheels/*.whl || return 1
  local lol=$ROOT/.gpu-build/lol work=$ROOT/.gpu-build/correction
  rm -rf "$lol" "$work" && mkdir -p "$lol/train" "$work"
  ln -s "$ROOT/$a/lol/train/high" "$lol/train/high"
  ln -s "$ROOT/$b/lol/train/low" "$lol/train/low"
  ln -s "$ROOT/$a/lol/eval" "$lol/eval"
  local names=(all bike chair shrub sofa)
  local epochs
  local device=${CORRECTION_DEVICE:-cuda}  # cpu: a dry run of this step on any machine
  epochs=$("$PY" - "$recipe" "${CORRECTION_BUDGET_S:-400}" "${#names[@]}" "$device" <<'PYEOF'
import sys
from naka_gs_plugin.enhance.correction_train import config_from_yaml, iteration_seconds

config, budget, runs, device = config_from_yaml(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
per_it = iteration_seconds(config, device)
iters = (config.images_per_epoch or 1) // config.batch_size
# 1.3: validation, augmentation on the CPU and five processes sharing one GPU, from the probe alone.
epochs = max(1, min(config.epochs, int(budget / (runs * per_it * iters * 1.3))))
print(f"probe: {per_it * 1000:.1f} ms per iteration (batch {config.batch_size}, crop {config.crop}); "
      f"{runs} runs x {iters} iterations per epoch in {budget:.0f} s -> {epochs} epochs", file=sys.stderr)
print(epochs)
PYEOF
  ) || return 1
  echo "training ${#names[@]} networks for $epochs epochs"
  local threads=$(($(nproc) / ${#names[@]})); [ "$threads" -ge 1 ] || threads=1
  local pids=() n hold
  for n in "${names[@]}"; do
    hold=()
    [ "$n" = all ] || hold=(--hold-out "$n")
    timeout "$((${CORRECTION_BUDGET_S:-400} + 90))" "$PY" -m naka_gs_plugin.scripts.train_correction --config "$recipe" \
      --lol "$lol" --lom "$b"/lom/{bike,chair,shrub,sofa} "${hold[@]}" --epochs "$epochs" --device "$device" \
      --threads "$threads" --output-dir "$work/$n" --export-to "$OUT/correction-$n.pt" >"$work/$n.log" 2>&1 &
    pids+=($!)
  done
  local rc=0
  for i in "${!pids[@]}"; do wait "${pids[$i]}" || { echo "${names[$i]}: exit $?"; rc=1; }; done
  for n in "${names[@]}"; do
    tail -n 3 "$work/$n.log"
    # A run stopped by the timeout still sends back its best epoch so far.
    [ -f "$OUT/correction-$n.pt" ] || [ ! -f "$work/$n/best.pt" ] ||
      "$PY" -c "import sys; from pathlib import Path; from naka_gs_plugin.enhance.correction_train import export_weights; export_weights(Path(sys.argv[1]), Path(sys.argv[2]))" "$work/$n/best.pt" "$OUT/correction-$n.pt"
  done
  tar czf "$OUT/correction-runs.tgz" -C "$work" --exclude '*.pt' .
  return $rc
}

steps=("$@")
[ ${#steps[@]} -eq 0 ] && steps=(env install build parity tests timing)
failed=()
for step in "${steps[@]}"; do
  if ! declare -F "step_$step" >/dev/null; then echo "unknown step $step (env install build parity tests timing train correction)"; exit 2; fi
  echo "=== $step"
  started=$SECONDS
  "step_$step" 2>&1 | tee "$OUT/$step.log"
  rc=${PIPESTATUS[0]}
  echo "=== $step: exit $rc after $((SECONDS - started)) s" | tee -a "$OUT/$step.log"
  [ "$rc" -eq 0 ] || failed+=("$step")
done
[ ${#failed[@]} -eq 0 ] || { echo "failed steps: ${failed[*]}"; exit 1; }
