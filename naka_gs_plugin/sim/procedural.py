"""The ``procedural`` source: textured objects made of small opaque Gaussians, rendered by our rasterizer.

World frame: z up, metres-like units; objects sit on the floor ``z = 0`` near the origin:
two spheres and two boxes, a floor disk (radius 5) and a cylindrical backdrop (radius 5.5,
height 3.5), all coloured by seeded procedural textures (checkers, stripes, bands, colour
noise: rich in SfM features and colour) with baked Lambert shading. Colours are **linear** RGB
in [0, 1]. Each surface sample becomes one flat Gaussian (in-plane sigma ``0.4 * spacing``,
``0.05 * spacing`` along the normal, opacity 0.98). Cameras are an ``orbit`` ring or a
``forward``-facing sweep; poses are OpenGL camera-to-world (see :mod:`naka_gs_plugin.sim.views`).
"""

from __future__ import annotations

from typing import Dict, List, Tuple

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor

from naka_gs_plugin.model.rasterize import rasterization
from naka_gs_plugin.sim.spec import ProceduralSource
from naka_gs_plugin.sim.views import View, look_at, opencv_viewmat

BACKGROUND = (0.55, 0.6, 0.7)
"""Linear sky colour behind everything (seen above the backdrop)."""
LIGHT_DIR = np.array([0.4, -0.3, 0.85]) / np.linalg.norm([0.4, -0.3, 0.85])
LAMP_REGION = (np.array([0.0, 0.0, 0.8]), 1.6)
"""Centre and radius of the ball where ``light_sources`` lamps are placed."""

Samples = Tuple[Float[np.ndarray, "N 3"], Float[np.ndarray, "N 3"], Float[np.ndarray, "N 3"]]
"""Surface samples: points, unit normals, linear albedo."""


def _palette(t: np.ndarray, phase: np.ndarray) -> np.ndarray:
    """Cosine colour palette: saturated hues cycling with ``t`` (linear RGB in [0.05, 0.95])."""
    return 0.5 + 0.45 * np.cos(2 * np.pi * (t[..., None] + phase))


class _Texture:
    """Seeded colour noise: sums of random sinusoids of the 3D position."""

    def __init__(self, rng: np.random.Generator):
        self.freq = rng.normal(scale=3.0, size=(4, 3))
        self.offset = rng.uniform(0, 2 * np.pi, size=4)
        self.phase = rng.uniform(0, 1, size=(3, 3))

    def noise(self, p: np.ndarray) -> np.ndarray:
        return np.sin(p @ self.freq.T + self.offset).mean(-1)

    def hue(self, t: np.ndarray, k: int) -> np.ndarray:
        return _palette(t, self.phase[k])


def _grid(a: np.ndarray, b: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    u, v = np.meshgrid(a, b, indexing="ij")
    return u.ravel(), v.ravel()


def _floor(s: float, tex: _Texture) -> Samples:
    x, y = _grid(np.arange(-5, 5, s) + s / 2, np.arange(-5, 5, s) + s / 2)
    keep = x**2 + y**2 < 25
    p = np.stack([x[keep], y[keep], np.zeros(keep.sum())], -1)
    check = (np.floor(p[:, 0] * 2) + np.floor(p[:, 1] * 2)) % 2
    colour = np.where(check[:, None] > 0, tex.hue(0.08 * p[:, 0] + 0.3 * tex.noise(p), 0), [0.12, 0.12, 0.1])
    return p, np.tile([0.0, 0.0, 1.0], (len(p), 1)), colour


def _backdrop(s: float, tex: _Texture) -> Samples:
    r = 5.5
    ang, z = _grid(np.arange(0, 2 * np.pi, s / r), np.arange(0, 3.5, s) + s / 2)
    p = np.stack([r * np.cos(ang), r * np.sin(ang), z], -1)
    stripe = np.floor(ang * 24 / (2 * np.pi))
    band = 0.7 + 0.3 * np.sin(z * 4.0 + 2 * tex.noise(p))
    colour = tex.hue(stripe / 7.0 + 0.1 * z, 1) * band[:, None]
    return p, -p * np.array([1.0, 1.0, 0.0]) / r, colour


def _sphere(centre: np.ndarray, radius: float, s: float, tex: _Texture, k: int) -> Samples:
    n = max(int(4 * np.pi * radius**2 / s**2), 16)
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    ang = np.pi * (1 + 5**0.5) * i
    normal = np.stack([np.sqrt(1 - z**2) * np.cos(ang), np.sqrt(1 - z**2) * np.sin(ang), z], -1)
    p = centre + radius * normal
    lon = np.arctan2(normal[:, 1], normal[:, 0])
    pattern = (np.floor(lon * 4 / np.pi) + np.floor(normal[:, 2] * 3)) % 2
    colour = np.where(pattern[:, None] > 0, tex.hue(lon / (2 * np.pi), k), tex.hue(normal[:, 2] * 0.5 + 0.5, 2) * 0.4)
    keep = p[:, 2] > s / 2  # drop the part below the floor
    return p[keep], normal[keep], colour[keep]


def _box(lo: np.ndarray, hi: np.ndarray, s: float, tex: _Texture, k: int) -> Samples:
    points, normals = [], []
    for axis in range(3):
        for side, value in ((-1.0, lo[axis]), (1.0, hi[axis])):
            if axis == 2 and side < 0:
                continue  # bottom face rests on the floor
            a, b = [ax for ax in range(3) if ax != axis]
            u, v = _grid(np.arange(lo[a], hi[a], s) + s / 2, np.arange(lo[b], hi[b], s) + s / 2)
            p = np.zeros((len(u), 3))
            p[:, axis], p[:, a], p[:, b] = value, u, v
            nrm = np.zeros_like(p)
            nrm[:, axis] = side
            points.append(p)
            normals.append(nrm)
    p, nrm = np.concatenate(points), np.concatenate(normals)
    grid = ((np.abs(np.sin(p * 9.0)) < 0.2) & (nrm == 0)).any(-1)  # lines on the face's own axes
    colour = np.where(grid[:, None], [0.9, 0.9, 0.88], tex.hue(0.5 * tex.noise(p) + 0.15 * p[:, 2], k))
    return p, nrm, colour


def surface_samples(source: ProceduralSource, scene_seed: int) -> Samples:
    """All surface samples of the scene (points, normals, **shaded** linear colours)."""
    tex = _Texture(np.random.default_rng(scene_seed))
    s = source.spacing
    parts = [
        _floor(s, tex),
        _backdrop(s, tex),
        _sphere(np.array([0.6, 0.0, 0.7]), 0.7, s, tex, 0),
        _sphere(np.array([-0.4, 1.3, 0.45]), 0.45, s, tex, 1),
        _box(np.array([-1.4, -0.5, 0.0]), np.array([-0.6, 0.7, 0.9]), s, tex, 2),
        _box(np.array([0.4, -1.7, 0.0]), np.array([1.2, -1.0, 0.55]), s, tex, 0),
    ]
    p, n, albedo = (np.concatenate([part[i] for part in parts]) for i in range(3))
    lambert = np.clip(n @ LIGHT_DIR, 0.0, 1.0)[:, None]
    return p, n, np.clip(albedo * (0.35 + 0.65 * lambert), 0.0, 1.0)


def _normal_quats(n: np.ndarray) -> np.ndarray:
    """wxyz quaternions rotating +z onto the unit normals ``n``."""
    q = np.stack([1.0 + n[:, 2], -n[:, 1], n[:, 0], np.zeros(len(n))], -1)
    q[1.0 + n[:, 2] < 1e-6] = [0.0, 1.0, 0.0, 0.0]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def camera_rig(source: ProceduralSource) -> List[View]:
    """Train then test views; test cameras sit between the training ones."""
    f = 0.5 * source.width / np.tan(0.5 * np.radians(source.fov_deg))
    K = np.array([[f, 0, source.width / 2], [0, f, source.height / 2], [0, 0, 1.0]])
    target = np.array([0.0, 0.0, 0.5])
    views = []
    for split, n, phase in (("train", source.n_train, 0.0), ("test", source.n_test, 0.5)):
        for i in range(n):
            t = (i + phase) / n
            if source.layout == "orbit":
                ang = 2 * np.pi * t
                eye = np.array([3.6 * np.cos(ang), 3.6 * np.sin(ang), 1.5 + 0.3 * np.sin(3 * ang)])
                c2w = look_at(eye, target)
            else:
                eye = np.array([-1.2 + 2.4 * t, -3.8, 1.4 + 0.3 * np.sin(4 * np.pi * t)])
                c2w = look_at(eye, target + np.array([0.3 * eye[0], 0.0, 0.0]))
            views.append(View(split, i, f"{i:04d}", c2w, K, source.width, source.height))
    return views


class ProceduralScene:
    """The Gaussians of a procedural scene and its views; :meth:`clean` renders one view (linear)."""

    lamp_region = LAMP_REGION

    def __init__(self, source: ProceduralSource, scene_seed: int):
        self.source = source
        self.points, self.normals, self.colors = surface_samples(source, scene_seed)
        n = len(self.points)
        sigma = source.spacing * np.array([0.4, 0.4, 0.05])
        self.gaussians: Dict[str, Tensor] = {
            "means": torch.from_numpy(self.points).float(),
            "quats": torch.from_numpy(_normal_quats(self.normals)).float(),
            "scales": torch.from_numpy(np.tile(sigma, (n, 1))).float(),
            "opacities": torch.full((n,), 0.98),
            "colors": torch.from_numpy(self.colors).float(),
        }
        self.views = camera_rig(source)

    def intrinsics(self) -> Dict[str, float]:
        K = self.views[0].K
        return {
            "fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2], "cy": K[1, 2],
            "w": self.source.width, "h": self.source.height,
        }  # fmt: skip

    @torch.no_grad()
    def clean(self, view: View) -> Float[Tensor, "H W 3"]:
        """Linear-light render of ``view`` in [0, 1], float64."""
        g = self.gaussians
        colors, _, _ = rasterization(
            g["means"], g["quats"], g["scales"], g["opacities"], g["colors"],
            torch.from_numpy(opencv_viewmat(view.c2w)).float()[None],
            torch.from_numpy(view.K).float()[None],
            view.width, view.height,
            backgrounds=torch.tensor([BACKGROUND]),
        )  # fmt: skip
        return colors[0].double().clamp(0.0, 1.0)
