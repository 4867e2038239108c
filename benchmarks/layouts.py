"""One scene in the three layouts ``ns-train naka-gs`` reads, trained and scored on the same normal-light truth.

A ``lowlight-data`` scene (e.g. LOM sofa) is written again as a ``nerfstudio-data`` scene (``transforms.json``,
``ply_file_path`` when the scene has points) and as a ``colmap`` scene (``images/`` + ``sparse/0`` in text
format): its training images (symbolic links, never copies) at the same poses, the scene's own points in the
transforms' world frame. Each layout is trained with ``ns-train`` (default options, the layout's subcommand),
one after the other, then every run renders the lowlight-data **test** poses, mapped into its own normalized frame
through its dataparser transform, and is scored against the same normal-light images (undistorted as ``ns-eval``
does) with the model's PSNR / SSIM / LPIPS. Printed: a Markdown table, one row per layout.

Run from the repository root (the scene is read in place; ``--out`` holds the layouts and the runs)::

    nice -n 5 python -m benchmarks.layouts --scene ../shared/data/lom/sofa --method naka-gs-fast \\
        --out outputs/layouts/sofa
"""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Literal, Optional, Tuple

import numpy as np
import torch
import tyro
from jaxtyping import Float
from torch import Tensor

from naka_gs_plugin.data.lowlight_dataparser import read_split
from naka_gs_plugin.points.seeding import TrainingFrame, align_cloud
from naka_gs_plugin.points.sources import find_scene_source, load_points, write_ply

Layout = Literal["lowlight-data", "nerfstudio-data", "colmap"]
LAYOUTS: Tuple[Layout, ...] = ("lowlight-data", "nerfstudio-data", "colmap")
CV_FROM_GL = np.diag([1.0, -1.0, -1.0, 1.0])
"""OpenGL camera axes (x right, y up, looking down -z) <-> OpenCV's (y down, looking down +z): its own inverse."""


def _image_names(images: List[Path]) -> List[str]:
    """The images' file names, each prefixed with its index where two share one (COLMAP keys images by name) or where
    name order is not the scene's view order (nerfstudio's parser sorts by name): every layout keeps the views in the
    scene's order, so that each run samples them alike."""
    names = [p.name for p in images]
    if len(set(names)) == len(names) and names == sorted(names):
        return names
    return [f"{i:04d}_{n}" for i, n in enumerate(names)]


def _link_images(images: List[Path], names: List[str], folder: Path) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for src, name in zip(images, names):
        link = folder / name
        if not link.is_symlink():
            link.symlink_to(Path(src).resolve())


def world_points(scene: Path) -> Optional[Tuple[np.ndarray, Optional[np.ndarray]]]:
    """The scene's own points (``auto``'s source) in the world frame of transforms_train.json, or None."""
    source = find_scene_source(scene)
    if source is None:
        return None
    cloud = load_points(source)
    xyz = align_cloud(cloud, TrainingFrame.from_scene(scene), "sim3")[0] if cloud.cameras else cloud.xyz
    return xyz, cloud.rgb


def _camera_params(intr: Tensor, dist: Tensor) -> Dict[str, float]:
    """json intrinsics of one frame; OpenCV distortion k1 k2 p1 p2 (nerfstudio order k1 k2 k3 k4 p1 p2)."""
    if float(dist[2].abs() + dist[3].abs()) > 0:
        raise ValueError("k3/k4 distortion: the converter writes COLMAP's OPENCV model (k1 k2 p1 p2) only")
    keys = ("fl_x", "fl_y", "cx", "cy", "w", "h")
    out = {k: float(v) for k, v in zip(keys, intr.tolist())}
    out.update(w=int(out["w"]), h=int(out["h"]), k1=float(dist[0]), k2=float(dist[1]), p1=float(dist[4]),
               p2=float(dist[5]))  # fmt: skip
    return out


def to_nerfstudio(scene: Path, out: Path) -> Path:
    """``out`` as a nerfstudio-data scene of ``scene``'s training views: transforms.json (OpenGL camera-to-world,
    per-frame OpenCV intrinsics), images/ (links), points.ply + ``ply_file_path`` when the scene has points."""
    train = read_split(scene, "transforms_train.json")
    names = _image_names(train.images)
    _link_images(train.images, names, out / "images")
    frames = [
        {"file_path": f"images/{name}", "transform_matrix": pose.tolist(), **_camera_params(intr, dist)}
        for name, pose, intr, dist in zip(names, train.poses, train.intrinsics, train.distortion)
    ]
    meta: Dict[str, object] = {"camera_model": "OPENCV", "frames": frames}
    points = world_points(scene)
    if points is not None:
        write_ply(out / "points.ply", *points)
        meta["ply_file_path"] = "points.ply"
    (out / "transforms.json").write_text(json.dumps(meta, indent=1))
    return out


def to_colmap(scene: Path, out: Path) -> Path:
    """``out`` as a colmap scene of ``scene``'s training views: images/ (links) and sparse/0 (text): one OPENCV
    camera per distinct intrinsics, world-to-camera poses (OpenCV axes) in the transforms' world frame, and the
    scene's points (no tracks) or none."""
    from nerfstudio.data.utils.colmap_parsing_utils import rotmat2qvec

    train = read_split(scene, "transforms_train.json")
    names = _image_names(train.images)
    _link_images(train.images, names, out / "images")
    model = out / "sparse" / "0"
    model.mkdir(parents=True, exist_ok=True)
    cameras: Dict[Tuple[float, ...], int] = {}
    images = []
    for i, (name, pose, intr, dist) in enumerate(zip(names, train.poses, train.intrinsics, train.distortion)):
        p = _camera_params(intr, dist)
        params = (p["w"], p["h"], p["fl_x"], p["fl_y"], p["cx"], p["cy"], p["k1"], p["k2"], p["p1"], p["p2"])
        cam = cameras.setdefault(params, len(cameras) + 1)
        w2c = np.linalg.inv(pose.numpy() @ CV_FROM_GL)
        q, t = rotmat2qvec(w2c[:3, :3]), w2c[:3, 3]
        images.append(f"{i + 1} {' '.join(f'{v:.17g}' for v in (*q, *t))} {cam} {name}\n\n")
    lines = [f"{cam} OPENCV {int(c[0])} {int(c[1])} {' '.join(f'{v:.17g}' for v in c[2:])}\n" for c, cam in
             cameras.items()]  # fmt: skip
    (model / "cameras.txt").write_text("".join(lines))
    (model / "images.txt").write_text("".join(images))
    points = world_points(scene)
    rows = []
    if points is not None:
        xyz, rgb = points
        rgb = np.full(xyz.shape, 128, np.uint8) if rgb is None else rgb
        rows = [f"{i + 1} {x:.9g} {y:.9g} {z:.9g} {r} {g} {b} 0\n" for i, ((x, y, z), (r, g, b)) in
                enumerate(zip(xyz.tolist(), rgb.tolist()))]  # fmt: skip
    (model / "points3D.txt").write_text("".join(rows))
    return out


def convert(scene: Path, out: Path, layout: Layout) -> Path:
    """``scene`` itself for lowlight-data, else its conversion into ``out``."""
    if layout == "lowlight-data":
        return scene
    return to_nerfstudio(scene, out) if layout == "nerfstudio-data" else to_colmap(scene, out)


def train_command(method: str, data: Path, layout: Layout, runs: Path, extra: List[str]) -> List[str]:
    """The ``ns-train`` command line of one layout (its subcommand last, as nerfstudio's methods take it)."""
    ns_train = str(Path(sys.executable).parent / "ns-train")
    return [ns_train, method, "--data", str(data), "--output-dir", str(runs), "--experiment-name", layout,
            "--timestamp", "run", "--vis", "tensorboard", "--viewer.quit-on-train-completion", "True",
            *extra, layout]  # fmt: skip


def map_poses(
    c2w: Float[Tensor, "N 3 4"], source: Tuple[Tensor, float], target: Tuple[Tensor, float]
) -> Float[Tensor, "N 3 4"]:
    """Camera-to-world matrices of one dataparser's normalized frame in another's. A frame is ``(transform [3, 4],
    scale)``: normalized = (R x + t) * scale, for world points x (the rotation also turns the camera axes)."""
    (a, sa), (b, sb) = source, target
    ra, ta, rb, tb = a[:, :3].double(), a[:, 3].double(), b[:, :3].double(), b[:, 3].double()
    rot = rb @ ra.T @ c2w[:, :, :3].double()
    centre_world = (c2w[:, :, 3].double() / sa - ta) @ ra  # R^T (y / s - t), row vectors
    centre = (centre_world @ rb.T + tb) * sb
    return torch.cat([rot, centre[:, :, None]], dim=2).float()


def _frame(pipeline) -> Tuple[Tensor, float]:
    outputs = pipeline.datamanager.train_dataparser_outputs
    return outputs.dataparser_transform, float(outputs.dataparser_scale)


def score(configs: Dict[str, Path]) -> Dict[str, Dict[str, float]]:
    """PSNR / SSIM / LPIPS of each run on the lowlight-data run's test views (the first of ``configs`` must be it):
    each renders those poses mapped into its frame, against the same truth images."""
    from nerfstudio.utils.eval_utils import eval_setup

    results: Dict[str, Dict[str, float]] = {}
    views = reference = None
    for layout, config in configs.items():
        _, pipeline, _, _ = eval_setup(config, test_mode="test")
        if views is None:
            views, reference = list(pipeline.datamanager.fixed_indices_eval_dataloader), _frame(pipeline)
        frame, scores = _frame(pipeline), []
        pipeline.eval()
        with torch.no_grad():
            for camera, batch in views:
                moved = camera.to(pipeline.device)
                if layout != "lowlight-data":
                    moved = type(camera)(**{**_camera_fields(camera), "camera_to_worlds": map_poses(
                        camera.camera_to_worlds, reference, frame)})  # fmt: skip
                outputs = pipeline.model.get_outputs_for_camera(moved)
                scores.append(pipeline.model.get_image_metrics_and_images(outputs, batch)[0])
        results[layout] = {k: float(np.mean([s[k] for s in scores])) for k in ("psnr", "ssim", "lpips")}
        results[layout]["gaussians"] = int(pipeline.model.num_points)
    return results


def _camera_fields(camera) -> Dict[str, object]:
    return {
        "camera_to_worlds": camera.camera_to_worlds,
        "fx": camera.fx,
        "fy": camera.fy,
        "cx": camera.cx,
        "cy": camera.cy,
        "width": camera.width,
        "height": camera.height,
        "distortion_params": camera.distortion_params,
        "camera_type": camera.camera_type,
        "metadata": camera.metadata,
    }


def table(results: Dict[str, Dict[str, float]], seconds: Dict[str, float]) -> str:
    base = results.get("lowlight-data", {}).get("psnr")
    rows = [
        "| layout | PSNR | dPSNR vs lowlight-data | SSIM | LPIPS | Gaussians | train s |",
        "|---|---|---|---|---|---|---|",
    ]
    for layout, r in results.items():
        delta = f"{r['psnr'] - base:+.2f}" if base is not None else "n/a"
        rows.append(f"| {layout} | {r['psnr']:.2f} | {delta} | {r['ssim']:.3f} | {r['lpips']:.3f} | "
                    f"{r['gaussians']} | {seconds.get(layout, float('nan')):.0f} |")  # fmt: skip
    return "\n".join(rows)


@dataclass
class Args:
    scene: Path = Path("../shared/data/lom/sofa")
    """A lowlight-data scene with normal-light test images (LOM)."""
    out: Path = Path("outputs/layouts/sofa")
    """Work folder: the converted layouts (links to the scene's images) and the runs."""
    method: str = "naka-gs-fast"
    """The preset every layout trains with."""
    layouts: Tuple[Layout, ...] = LAYOUTS
    """Layouts to run (lowlight-data first: the others are scored on its test views)."""
    train_options: str = ""
    """Extra ns-train options for every layout, one string given with ``=`` as it starts with ``--``
    (``--train-options="--max-num-iterations 300 --machine.seed 1"``)."""

    def main(self) -> Dict[str, Dict[str, float]]:
        if self.layouts[0] != "lowlight-data":
            raise SystemExit("benchmarks.layouts: --layouts must start with lowlight-data (the reference views)")
        configs: Dict[str, Path] = {}
        seconds: Dict[str, float] = {}
        for layout in self.layouts:
            data = convert(self.scene, self.out / layout, layout)
            cmd = train_command(self.method, data, layout, self.out / "runs", shlex.split(self.train_options))
            config = self.out / "runs" / layout / self.method / "run" / "config.yml"
            if not config.exists():
                print("+", " ".join(cmd), flush=True)
                t = time.perf_counter()
                subprocess.run(cmd, check=True, env=dict(os.environ))
                seconds[layout] = time.perf_counter() - t
            configs[layout] = config
        results = score(configs)
        print(table(results, seconds))
        (self.out / "results.json").write_text(json.dumps({"results": results, "train_seconds": seconds}, indent=1))
        return results


def entrypoint(args: Optional[List[str]] = None) -> None:
    tyro.cli(Args, args=args).main()


if __name__ == "__main__":
    entrypoint()
