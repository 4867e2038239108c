#!/usr/bin/env bash
# Here (with the dev venv and ../shared/data): fill the git-ignored .gpu-data/ for `run.sh train`:
#   bash scripts/gpu/prepare_train.sh [scene ...]     (default: sofa)
# Per LOM scene:
#   - .gpu-data/lom/<scene>: the transforms files and only the images they name (low-light training
#     views, normal-light test and val views), with the COLMAP model turned into points.ply +
#     points_cameras.json (the same points, colours and camera centres, float32): the model is read
#     with pycolmap, whose 38 MB wheel does not fit a 64 MiB transfer;
#   - .gpu-data/correction-<scene>.pt: its leave-one-out correction weights
#     (outputs/correction-loo/<scene>/best.pt) in float16, as the shipped weights are stored.
# The images and the weights are separate paths so that they can travel in separate transfers.
# Run the same grid here for the CPU side: both then train on identical inputs.
set -euo pipefail
cd "$(dirname "$0")/../.."
PY="${PYTHON:-.venv/bin/python}"
[ $# -gt 0 ] || set -- sofa
DEST=.gpu-data
rm -rf "$DEST"
mkdir -p "$DEST/lom"
"$PY" - "$@" <<'PYEOF'
import json, shutil, sys
from pathlib import Path
import torch
from naka_gs_plugin.points.sources import CAMERAS_JSON, load_colmap, write_ply

for scene in sys.argv[1:]:
    src, root = Path("../shared/data/lom") / scene, Path(".gpu-data/lom") / scene
    weights = Path(f"outputs/correction-loo/{scene}/best.pt")
    if not weights.is_file():
        sys.exit(f"{weights}: missing -- train it first: naka-gs-train-correction --hold-out {scene}")
    for split in sorted(src.glob("transforms_*.json")):
        (root / split.name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(split, root / split.name)
        for frame in json.loads(split.read_text())["frames"]:
            (root / frame["file_path"]).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src / frame["file_path"], root / frame["file_path"])
    cloud = load_colmap(src / "colmap_sparse" / "0")
    write_ply(root / "points.ply", cloud.xyz, cloud.rgb)
    (root / CAMERAS_JSON).write_text(json.dumps({k: v.tolist() for k, v in cloud.cameras.items()}))
    ckpt = torch.load(weights, map_location="cpu", weights_only=True)
    ckpt["state_dict"] = {k: v.half() for k, v in ckpt["state_dict"].items()}
    torch.save({k: ckpt[k] for k in ("format", "config", "state_dict")}, f".gpu-data/correction-{scene}.pt")
    print(f"{scene}: {len(cloud)} points, {len(cloud.cameras)} camera centres -> points.ply")
PYEOF
du -sh "$DEST"/lom/* "$DEST"/*.pt
