"""A trained scene by eye: enhanced training view | render at that pose | render at a novel pose.

For scenes without ground truth (RealX3D) the sheet is the check: it shows whether the renders
reproduce the enhanced views the model trained on, and whether a pose between two training views
still looks like the scene. The novel pose is halfway between a training camera and the next one
(translation linear, rotation slerp). Brightnesses are means of sRGB [0, 1] over pixels and
channels, comparable with the normal-light mean of a paired data set.

Run from the directory ``ns-train`` ran in (the config's paths are relative to it, as for ``ns-eval``)::

    naka-gs-scene-sheet --load-config outputs/SCENE/naka-gs/TIMESTAMP/config.yml
"""

from __future__ import annotations

from typing import List, Sequence

import numpy as np
import torch
from jaxtyping import Float
from nerfstudio.cameras.camera_utils import quaternion_from_matrix, quaternion_matrix, quaternion_slerp
from nerfstudio.cameras.cameras import Cameras
from torch import Tensor

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
