#!/usr/bin/env bash
# Here (with the dev venv and ../shared/data): fill the git-ignored .gpu-data/ for `run.sh train`, the
# CUDA-vs-CPU training comparison on one LOM scene (default sofa), scripts/gpu/cuda-vs-cpu.yaml:
#   - the scene, copied (the GPU machine sees only the repository), with its COLMAP model turned into
#     points.ply + points_cameras.json (the same points, colours and camera centres, float32): the
#     model is read with pycolmap, whose 38 MB wheel does not fit a 64 MiB transfer;
#   - its leave-one-out correction weights (outputs/correction-loo/<scene>/best.pt) in float16, as
#     the shipped weights are stored (21 MB in float32).
# Run the same grid here for the CPU side: both then train on identical inputs.
set -euo pipefail
cd "$(dirname "$0")/../.."
PY="${PYTHON:-.venv/bin/python}"
SCENE="${1:-sofa}"
DEST=.gpu-data
rm -rf "$DEST"
mkdir -p "$DEST/lom"
cp -a "../shared/data/lom/$SCENE" "$DEST/lom/$SCENE"
"$PY" - "$SCENE" <<'PYEOF'
import json, shutil, sys
from pathlib import Path
import torch
from naka_gs_plugin.points.sources import CAMERAS_JSON, load_colmap, write_ply

scene = sys.argv[1]
root = Path(".gpu-data/lom") / scene
cloud = load_colmap(root / "colmap_sparse" / "0")
write_ply(root / "points.ply", cloud.xyz, cloud.rgb)
(root / CAMERAS_JSON).write_text(json.dumps({k: v.tolist() for k, v in cloud.cameras.items()}))
shutil.rmtree(root / "colmap_sparse")
print(f"{scene}: {len(cloud)} points, {len(cloud.cameras)} camera centres -> points.ply")
ckpt = torch.load(f"outputs/correction-loo/{scene}/best.pt", map_location="cpu", weights_only=True)
ckpt["state_dict"] = {k: v.half() for k, v in ckpt["state_dict"].items()}
torch.save({k: ckpt[k] for k in ("format", "config", "state_dict")}, f".gpu-data/correction-{scene}.pt")
PYEOF
du -sh "$DEST"
