"""Camera views shared by the sources, camera conventions and the 3D lamps of ``light_sources``.

Poses are camera-to-world in the **OpenGL** convention (x right, y up, looking down -z), as in
``transforms_*.json``; the rasterizer and the lamp projection use **OpenCV** world-to-camera
``viewmat = inverse(c2w @ diag(1, -1, -1, 1))``. Intrinsics are pixels, pixel centres at +0.5.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor

LAMP_COLOR = (1.0, 0.85, 0.6)
"""Warm-white lamp colour (linear RGB, scaled by the lamp intensity)."""


@dataclass(frozen=True)
class View:
    """One camera of a split."""

    split: str  # "train" or "test"
    index: int
    name: str  # output file stem, e.g. "0003"
    c2w: Float[np.ndarray, "4 4"]  # OpenGL camera-to-world
    K: Float[np.ndarray, "3 3"]  # pixels
    width: int
    height: int
    origin: str = ""  # where the clean image came from (capture source), else ""


def opencv_viewmat(c2w: Float[np.ndarray, "4 4"]) -> Float[np.ndarray, "4 4"]:
    """OpenGL camera-to-world -> OpenCV world-to-camera."""
    return np.linalg.inv(c2w @ np.diag([1.0, -1.0, -1.0, 1.0]))


def look_at(eye: np.ndarray, target: np.ndarray) -> Float[np.ndarray, "4 4"]:
    """OpenGL camera-to-world at ``eye`` looking at ``target``, world up = +z."""
    back = (eye - target) / np.linalg.norm(eye - target)
    right = np.cross([0.0, 0.0, 1.0], back)
    right /= np.linalg.norm(right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, np.cross(back, right), back, eye
    return c2w


def place_lamps(rng: np.random.Generator, count: int, center: np.ndarray, radius: float) -> Float[np.ndarray, "L 3"]:
    """``count`` lamp positions uniform in the ball of ``radius`` around ``center`` (world units)."""
    direction = rng.normal(size=(count, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True).clip(min=1e-12)
    return center + direction * radius * rng.uniform(size=(count, 1)) ** (1.0 / 3.0)


def lamp_image(view: View, lamps: Float[np.ndarray, "L 3"], intensity: float, radius: float) -> Float[Tensor, "H W 3"]:
    """Linear radiance of the lamps seen by ``view``: Gaussian cores of world ``radius``, no occlusion."""
    ys, xs = np.mgrid[0 : view.height, 0 : view.width] + 0.5
    out = np.zeros((view.height, view.width))
    w2c = opencv_viewmat(view.c2w)
    for p in lamps:
        x, y, z = w2c[:3, :3] @ p + w2c[:3, 3]
        if z <= 1e-3:
            continue
        u, v = view.K[0, 0] * x / z + view.K[0, 2], view.K[1, 1] * y / z + view.K[1, 2]
        sigma = max(view.K[0, 0] * radius / z, 0.5)
        out += intensity * np.exp(-((xs - u) ** 2 + (ys - v) ** 2) / (2 * sigma**2))
    return torch.from_numpy(out[..., None] * np.asarray(LAMP_COLOR))
