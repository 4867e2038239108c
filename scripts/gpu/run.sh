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
# gsplat's JIT build lives here, so it survives between calls while the machine stays warm.
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
  command -v ninja
}

step_build() {
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
}

step_parity() {
  local ckpt=()
  if [ -n "${NAKA_GS_PARITY_CKPT:-}" ]; then ckpt=(--checkpoint "$NAKA_GS_PARITY_CKPT" --max-gaussians 200000); fi
  # The saved reference (inputs + gsplat outputs) lets cpu-fast be compared on a CPU afterwards:
  # python -m naka_gs_plugin.scripts.cuda_parity --reference-file .../gsplat_reference.pt
  "$PY" -m naka_gs_plugin.scripts.cuda_parity --reference gsplat "${ckpt[@]}" \
    --out-dir "$OUT/parity" --save-reference "$OUT/parity/gsplat_reference.pt"
}

step_tests() {
  # --noconftest: tests/conftest.py imports the toy-scene writer (Pillow), which this file does not use.
  "$PY" -m pytest -q -rs --noconftest -p no:cacheprovider --junitxml "$OUT/tests.xml" tests/test_cuda_parity.py
}

step_timing() {
  "$PY" -m naka_gs_plugin.scripts.cuda_parity --mode timing --out-dir "$OUT/timing"
}

steps=("$@")
[ ${#steps[@]} -eq 0 ] && steps=(env install build parity tests timing)
failed=()
for step in "${steps[@]}"; do
  if ! declare -F "step_$step" >/dev/null; then echo "unknown step $step (env install build parity tests timing)"; exit 2; fi
  echo "=== $step"
  started=$SECONDS
  "step_$step" 2>&1 | tee "$OUT/$step.log"
  rc=${PIPESTATUS[0]}
  echo "=== $step: exit $rc after $((SECONDS - started)) s" | tee -a "$OUT/$step.log"
  [ "$rc" -eq 0 ] || failed+=("$step")
done
[ ${#failed[@]} -eq 0 ] || { echo "failed steps: ${failed[*]}"; exit 1; }
