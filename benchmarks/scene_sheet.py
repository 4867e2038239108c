"""A trained scene by eye: enhanced training view | render at that pose | render at a novel pose.

For scenes without ground truth (RealX3D) the sheet is the check: it shows whether the renders
reproduce the enhanced views the model trained on, and whether a pose between two training views
still looks like the scene. The novel pose is halfway between a training camera and the next one
(translation linear, rotation slerp). Brightnesses are means of sRGB [0, 1] over pixels and
channels, comparable with the normal-light mean of a paired data set.

Run from the directory ``ns-train`` ran in (the config's paths are relative to it, as for ``ns-eval``)::

    python -m benchmarks.scene_sheet --load-config outputs/SCENE/naka-gs/TIMESTAMP/config.yml

Run from the repository root: ``python -m benchmarks.scene_sheet --help``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import numpy as np
import torch
import tyro
from jaxtyping import Float
from nerfstudio.cameras.camera_utils import quaternion_from_matrix, quaternion_matrix, quaternion_slerp
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image
from torch import Tensor

from naka_gs_plugin.enhance.stages import to_float01
from naka_gs_plugin.sheet import contact_sheet

COLUMNS = ("enhanced training view", "render at that pose", "render halfway to the next view")


def interpolate_pose(c2w_a: Float[Tensor, "3 4"], c2w_b: Float[Tensor, "3 4"], t: float) -> Float[Tensor, "3 4"]:
    """Camera-to-world at fraction ``t`` from ``a`` (0) to ``b`` (1): translation linear, rotation by
    slerp (shortest arc). Works for OpenGL or OpenCV poses alike (both inputs in the same one)."""
    a, b = c2w_a.detach().cpu().double().numpy(), c2w_b.detach().cpu().double().numpy()
    quat = quaternion_slerp(quaternion_from_matrix(a[:3, :3]), quaternion_from_matrix(b[:3, :3]), t)
    pose = np.concatenate([quaternion_matrix(quat)[:3, :3], ((1.0 - t) * a[:3, 3] + t * b[:3, 3])[:, None]], axis=1)
    return torch.from_numpy(pose).to(c2w_a)


def sheet_views(num_views: int, k: int) -> List[int]:
    """``k`` training-view indices evenly spaced over ``0 .. num_views - 1`` (fewer if ``k > num_views``)."""
    return sorted({int(i) for i in np.linspace(0, num_views - 1, k).round()})


def mean_brightness(images: Sequence[Float[Tensor, "H W 3"]]) -> float:
    """Mean sRGB value over the images' pixels and channels (images may differ in size)."""
    return float(np.mean([float(im.mean()) for im in images]))


def trained_pose(model, cameras: Cameras, idx: int) -> Float[Tensor, "3 4"]:
    """Training camera ``idx``'s OpenGL camera-to-world with the camera optimizer's correction (if
    training refined poses, the model fits the refined ones)."""
    camera = cameras[idx : idx + 1].to(model.device)
    camera.metadata = {"cam_idx": idx}
    with torch.no_grad():
        return model.camera_optimizer.apply_to_camera(camera)[0]


def render_at(model, cameras: Cameras, idx: int, c2w: Float[Tensor, "3 4"]) -> Float[Tensor, "H W 3"]:
    """sRGB [0, 1] render with camera ``idx``'s intrinsics at pose ``c2w`` (OpenGL camera-to-world)."""
    cam = cameras[idx : idx + 1]
    camera = Cameras(
        camera_to_worlds=c2w[None].to(cam.camera_to_worlds),
        fx=cam.fx,
        fy=cam.fy,
        cx=cam.cx,
        cy=cam.cy,
        width=cam.width,
        height=cam.height,
        camera_type=cam.camera_type,
    )
    return model.get_outputs_for_camera(camera)["rgb"].cpu()


@dataclass
class SceneSheet:
    """Sheet and brightness JSON of a trained ``naka-gs`` run (see the module docstring)."""

    load_config: Path
    """The run's config.yml, as written by ``ns-train naka-gs``."""
    views: int = 3
    """Rows: training views, evenly spaced over the training set."""
    output: Optional[Path] = None
    """Sheet PNG; the JSON goes beside it with suffix .json. Default: scene_sheet.png in the run folder."""
    tile_width: int = 384
    """Width in pixels of each picture on the sheet (never enlarged)."""

    def main(self) -> Dict:
        """Write the sheet and the JSON; return the JSON's contents."""
        if not self.load_config.is_file():
            raise FileNotFoundError(
                f"--load-config {self.load_config} is not a file -- pass the config.yml that ns-train wrote "
                "(outputs/SCENE/naka-gs/TIMESTAMP/config.yml)"
            )
        if self.views < 1:
            raise ValueError(f"--views must be >= 1, got {self.views} -- use e.g. --views 3")
        # Heavy: nerfstudio's method registry imports every model.
        from nerfstudio.utils.eval_utils import eval_setup

        _, pipeline, _, step = eval_setup(self.load_config, test_mode="test")
        datamanager, model = pipeline.datamanager, pipeline.model
        # Loading the training images enhances them (from the cache when ns-train filled it) and, for
        # distorted captures, rewrites the cameras' intrinsics to the undistorted images': load first.
        train = [to_float01(data["image"]).cpu() for data in datamanager.cached_train]
        cameras = datamanager.train_dataset.cameras
        if len(train) < 2:
            raise ValueError(
                f"--load-config {self.load_config}: the scene has {len(train)} training view(s), "
                "a novel pose between two needs at least 2 -- train on a scene with more views"
            )

        rows, records = [], []
        for i in sheet_views(len(train), self.views):
            j = i + 1 if i + 1 < len(train) else i - 1
            c2w_i, c2w_j = trained_pose(model, cameras, i), trained_pose(model, cameras, j)
            render = render_at(model, cameras, i, c2w_i)
            novel = render_at(model, cameras, i, interpolate_pose(c2w_i, c2w_j, 0.5))
            rows.append([train[i].numpy(), render.numpy(), novel.numpy()])
            records.append(
                {
                    "view": i,
                    "image": datamanager.train_dataset.image_filenames[i].name,
                    "novel_towards_view": j,
                    "enhanced_mean": mean_brightness([train[i]]),
                    "render_mean": mean_brightness([render]),
                    "novel_render_mean": mean_brightness([novel]),
                }
            )

        output = self.output or self.load_config.parent / "scene_sheet.png"
        output.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(contact_sheet(rows, max_width=self.tile_width)).save(output)
        report = {
            "config": str(self.load_config),
            "step": step,
            "train_views": len(train),
            "enhanced_mean_all_views": mean_brightness(train),
            "exposure_gain": datamanager.enhancer.last_run.get("exposure_gain"),
            "enhanced_mean": float(np.mean([r["enhanced_mean"] for r in records])),
            "render_mean": float(np.mean([r["render_mean"] for r in records])),
            "novel_render_mean": float(np.mean([r["novel_render_mean"] for r in records])),
            "columns": list(COLUMNS),
            "rows": records,
            "sheet": str(output),
        }
        output.with_suffix(".json").write_text(json.dumps(report, indent=1))
        value = report["exposure_gain"]
        CONSOLE.print(
            f"[naka-gs scene-sheet] {len(train)} training views, enhanced mean {report['enhanced_mean_all_views']:.3f}"
            + (f" (exposure gain {value:.3f})" if value is not None else "")
            + f"; sheet views: enhanced {report['enhanced_mean']:.3f}, render {report['render_mean']:.3f}, "
            f"novel render {report['novel_render_mean']:.3f}; wrote {output} (columns: {' | '.join(COLUMNS)}) "
            f"and {output.with_suffix('.json')}",
            markup=False,
        )
        return report


def entrypoint(args: Optional[Sequence[str]] = None) -> None:
    """``python -m benchmarks.scene_sheet``; bad input prints one line."""
    sheet = tyro.cli(SceneSheet, args=args)
    try:
        sheet.main()
    except (FileNotFoundError, ValueError) as err:
        raise SystemExit(f"python -m benchmarks.scene_sheet: {err}") from None


if __name__ == "__main__":
    entrypoint()
