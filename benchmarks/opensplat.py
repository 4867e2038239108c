"""naka-gs against an independent CPU trainer, OpenSplat, on the same machine, images and steps.

OpenSplat (C++/libtorch, built outside this repository: ``../shared/tools/anchors/opensplat/README.md``)
and ``ns-train naka-gs`` train on the same LOM scene's training views (its ``high/`` normal-light images by
default, so neither needs an enhancement; ``--images low`` for the dark ones, enhancement off for both), at
full size from the first step (no coarse-to-fine schedule: OpenSplat ``--num-downscales 0``, naka-gs
``--pipeline.model.num-downscales 0``), from the same seed points (the scene's COLMAP model restricted to the
training views), with the same thread count (``OMP_NUM_THREADS`` and ``NUMBA_NUM_THREADS``) and no evaluation
during training. Each trainer runs twice, ``--short-steps`` and ``--steps`` steps, and the time per step is the
difference of the two walls over the difference of the steps (start-up, loading and saving cancel out). Printed
per trainer: seconds per step, the Gaussians at the end, peak RSS (``/usr/bin/time``), as a Markdown table.

Run from the repository root (the scene folder and the OpenSplat binary are read in place; the work folder
holds symlinks, the restricted COLMAP model and both trainers' outputs):

    python -m benchmarks.opensplat --opensplat /path/to/opensplat --scene ../shared/data/lom/sofa
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional

import tyro

from benchmarks.harness import timed
from benchmarks.machine import describe_cpu


@dataclass
class Args:
    opensplat: Path
    """The OpenSplat binary (built for the CPU)."""
    scene: Path = Path("../shared/data/lom/sofa")
    """A LOM scene: transforms_train.json, low/ and high/ images, colmap_sparse/0."""
    images: Literal["high", "low"] = "high"
    """Which of the scene's images both train on."""
    steps: int = 600
    short_steps: int = 50
    threads: int = 1
    work: Optional[Path] = None
    """Work folder (default: a new temporary one)."""


def prepare(scene: Path, images: str, work: Path) -> tuple[Path, Path]:
    """A COLMAP project for OpenSplat and a lowlight-data scene for naka-gs, both on ``scene``'s training views
    (``images`` folder) and its COLMAP model restricted to them. Returns (project, naka-gs scene)."""
    import pycolmap

    frames = json.loads((scene / "transforms_train.json").read_text(encoding="utf-8-sig"))
    train = {Path(f["file_path"]).name for f in frames["frames"]}
    model = pycolmap.Reconstruction(str(scene / "colmap_sparse" / "0"))
    for image in list(model.images.values()):
        if image.name not in train:
            model.deregister_frame(image.frame_id)
    project = work / "colmap"
    (project / "sparse" / "0").mkdir(parents=True, exist_ok=True)
    (project / "images").mkdir(exist_ok=True)
    model.write(str(project / "sparse" / "0"))
    for name in train:
        link = project / "images" / name
        if not link.exists():
            link.symlink_to((scene / images / name).resolve())
    ours = work / "scene"
    ours.mkdir(exist_ok=True)
    for split in ("train", "test", "val"):
        path = scene / f"transforms_{split}.json"
        if path.is_file():
            data = json.loads(path.read_text(encoding="utf-8-sig"))
            if split == "train":
                for frame in data["frames"]:
                    frame["file_path"] = f"{images}/{Path(frame['file_path']).name}"
            (ours / path.name).write_text(json.dumps(data))
    for name, target in ((images, scene / images), ("high", scene / "high"), ("colmap_sparse", project / "sparse")):
        if not (ours / name).exists():
            (ours / name).symlink_to(target.resolve())
    return project, ours


def ply_vertices(path: Path) -> int:
    with open(path, "rb") as fh:
        for line in fh:
            if line.startswith(b"element vertex"):
                return int(line.split()[-1])
            if line.strip() == b"end_header":
                break
    raise ValueError(f"{path}: no vertex count in its header")


def run_opensplat(args: Args, project: Path, work: Path, env: dict, steps: int) -> tuple[float, float, int]:
    out = work / f"opensplat-{steps}.ply"
    cmd = [
        str(args.opensplat),
        str(project),
        "--cpu",
        "-n",
        str(steps),
        "-d",
        "1",
        "--num-downscales",
        "0",
        "-o",
        str(out),
    ]
    wall, rss = timed(cmd, env, work / f"opensplat-{steps}.log")
    return wall, rss, ply_vertices(out)


def run_naka_gs(scene: Path, work: Path, env: dict, steps: int) -> tuple[float, float, int]:
    import torch

    ns_train = Path(sys.executable).parent / "ns-train"
    out = work / "ns"
    never = str(steps + 1)
    cmd = [
        str(ns_train), "naka-gs", "--data", str(scene), "--output-dir", str(out), "--timestamp", f"steps-{steps}",
        "--max-num-iterations", str(steps), "--steps-per-save", str(steps), "--steps-per-eval-image", never,
        "--steps-per-eval-all-images", never, "--vis", "tensorboard", "--viewer.quit-on-train-completion", "True",
        "--pipeline.model.num-downscales", "0", "--pipeline.datamanager.enhance.method", "none",
    ]  # fmt: skip
    wall, rss = timed(cmd, env, work / f"naka-gs-{steps}.log")
    ckpt = max((out / scene.name / "naka-gs" / f"steps-{steps}" / "nerfstudio_models").glob("step-*.ckpt"))
    state = torch.load(ckpt, map_location="cpu", weights_only=False)["pipeline"]
    return wall, rss, int(state["_model.gauss_params.means"].shape[0])


def main(args: Args) -> None:
    print(describe_cpu())
    work = args.work or Path(tempfile.mkdtemp(prefix="naka-gs-opensplat-"))
    work.mkdir(parents=True, exist_ok=True)
    project, scene = prepare(args.scene, args.images, work)
    env = dict(os.environ, OMP_NUM_THREADS=str(args.threads), NUMBA_NUM_THREADS=str(args.threads))
    env.setdefault("TORCHDYNAMO_DISABLE", "1")
    print(f"scene {args.scene} ({args.images}/ images), {args.steps} vs {args.short_steps} steps, "
          f"{args.threads} thread(s), work folder {work}")  # fmt: skip
    rows = []
    for name, run in (
        ("OpenSplat", lambda steps: run_opensplat(args, project, work, env, steps)),
        ("naka-gs", lambda steps: run_naka_gs(scene, work, env, steps)),
    ):
        short_wall, _, _ = run(args.short_steps)
        wall, rss, gaussians = run(args.steps)
        per_step = (wall - short_wall) / (args.steps - args.short_steps)
        rows.append((name, per_step, gaussians, rss, wall))
        print(f"  {name}: {short_wall:.1f} s for {args.short_steps} steps, {wall:.1f} s for {args.steps}", flush=True)
    print(f"\n| trainer | s per step | Gaussians at step {args.steps} | peak RSS GB | wall of {args.steps} steps, s |")
    print("|---|---|---|---|---|")
    for name, per_step, gaussians, rss, wall in rows:
        print(f"| {name} | {per_step:.3f} | {gaussians:,} | {rss:.2f} | {wall:.1f} |")


def entrypoint() -> None:
    main(tyro.cli(Args))


if __name__ == "__main__":
    entrypoint()
