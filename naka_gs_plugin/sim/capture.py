"""The ``capture`` source: a real clean multi-view capture whose normal-light images are the truth.

Reads a ``lowlight-data`` scene with normal-light images, e.g. LOM: ``transforms_train.json``
frames point at ``low/<n>.JPG``; the clean image of that view is ``high/<n>.JPG`` (any
``low/`` path component is replaced by ``high/``; other paths are used as they are).
``transforms_test.json`` frames give the test views (normal light already). ``n_train`` /
``n_test`` views are taken evenly spaced along each json's frame list. Images are sRGB JPEGs,
box-downscaled by ``downscale`` (size floored; ``fl_x fl_y cx cy`` divided by it, the OpenCV
distortion ``k1 k2 p1 p2`` kept) and decoded to **linear** light.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Dict, List, Tuple

import cv2
import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor

from naka_gs_plugin.data.images import read_rgb
from naka_gs_plugin.sim.effects import srgb_to_linear
from naka_gs_plugin.sim.spec import CaptureSource, SimSpecError
from naka_gs_plugin.sim.views import View

_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")


def clean_image_path(scene: Path, file_path: str) -> Path:
    """The normal-light image of a frame: ``low/`` -> ``high/`` (LOM), otherwise the frame's own file."""
    parts = Path(file_path).parts
    return scene.joinpath(*["high" if p == "low" else p for p in parts])


def _axes_centre(c2ws: np.ndarray) -> Tuple[np.ndarray, float]:
    """Least-squares point closest to all optical axes, and 0.25 x the median camera distance to it."""
    a, b = np.zeros((3, 3)), np.zeros(3)
    for c2w in c2ws:
        d = -c2w[:3, 2]  # OpenGL cameras look down -z
        proj = np.eye(3) - np.outer(d, d)
        a += proj
        b += proj @ c2w[:3, 3]
    centre = np.linalg.lstsq(a, b, rcond=None)[0]
    return centre, 0.25 * float(np.median(np.linalg.norm(c2ws[:, :3, 3] - centre, axis=1)))


class CaptureScene:
    """Views and clean linear images of a capture; same interface as ``ProceduralScene``."""

    def __init__(self, source: CaptureSource, spec_path: Path):
        self.source = source
        self.scene = source.path
        self.meta = json.loads((self.scene / "transforms_train.json").read_text(encoding="utf-8-sig"))
        self.views: List[View] = []
        for split, n in (("train", source.n_train), ("test", source.n_test)):
            frames = json.loads((self.scene / f"transforms_{split}.json").read_text(encoding="utf-8-sig"))["frames"]
            if n > len(frames):
                raise SimSpecError(
                    f"{spec_path}: field 'source.capture.n_{split}': {n} views asked, "
                    f"{self.scene / f'transforms_{split}.json'} has {len(frames)}"
                )
            picks = np.round(np.linspace(0, len(frames) - 1, n)).astype(int) if n > 1 else np.arange(n)
            for i, k in enumerate(picks):
                path = clean_image_path(self.scene, frames[k]["file_path"])
                if not path.is_file():
                    raise SimSpecError(f"{spec_path}: field 'source.capture.path': clean image {path} not found")
                c2w = np.asarray(frames[k]["transform_matrix"], dtype=np.float64)
                self.views.append(View(split, i, f"{i:04d}", c2w, self._K(), *self._size(), origin=str(path)))
        train = np.stack([v.c2w for v in self.views if v.split == "train"])
        self.lamp_region = _axes_centre(train)

    def _size(self) -> Tuple[int, int]:
        d = self.source.downscale
        return int(float(self.meta["w"]) / d), int(float(self.meta["h"]) / d)

    def _K(self) -> np.ndarray:
        d, m = self.source.downscale, self.meta
        return np.array([[m["fl_x"] / d, 0, m["cx"] / d], [0, m["fl_y"] / d, m["cy"] / d], [0, 0, 1.0]])

    def intrinsics(self) -> Dict[str, float]:
        K, (w, h) = self._K(), self._size()
        out = {"fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "w": w, "h": h}
        out.update({k: float(self.meta[k]) for k in _DISTORTION_KEYS if k in self.meta})
        return out

    def clean(self, view: View) -> Float[Tensor, "H W 3"]:
        """The view's real normal-light image, downscaled (area filter) and decoded to linear [0, 1], float64."""
        full = read_rgb(Path(view.origin), np.float64)
        small = cv2.resize(full, (view.width, view.height), interpolation=cv2.INTER_AREA)
        return srgb_to_linear(torch.from_numpy(small))
