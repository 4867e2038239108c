"""A small ray-cast low-light scene with ground truth, generated in a second with no downloads.

The tests' fixture (the README demo uses the spec-driven simulator, :mod:`naka_gs_plugin.sim.generate`):
a textured sphere and box on a checkered floor with a striped backdrop, seen by an orbit of pinhole cameras. Images are exactly
3D-consistent (analytic ray casting), so Gaussians can be trained on them and SfM features match.

Effects, applied in linear light in this order and only these: exposure reduction (``exposure``),
Poisson-Gaussian sensor noise (``noise``), then sRGB encoding and 8-bit quantization. Test and
``train_gt`` images are the clean normal-light renders. It does not depend on the rasterizer, so the
data, enhancement and CLI tests stay independent of the model code.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from jaxtyping import Float
from PIL import Image

from naka_gs_plugin.sim.effects import linear_to_srgb
from naka_gs_plugin.sim.views import look_at


@dataclass
class ToySceneConfig:
    n_train: int = 12
    n_test: int = 3
    width: int = 96
    height: int = 72
    fov_deg: float = 55.0
    exposure: float = 0.008
    """Linear-light gain of the training images (gives mean sRGB pixel ~0.04, as real low-light scenes)."""
    noise: float = 0.0015
    """Gaussian read-noise std in linear [0,1] units; shot noise uses ``noise**2`` as gain."""
    seed: int = 0


def _shade(points: np.ndarray, normals: np.ndarray, albedo: np.ndarray) -> np.ndarray:
    light = np.array([0.4, -0.3, 0.85])
    light /= np.linalg.norm(light)
    lambert = np.clip((normals * light).sum(-1, keepdims=True), 0.0, 1.0)
    return albedo * (0.35 + 0.65 * lambert)


@np.errstate(invalid="ignore", divide="ignore")  # rays that miss a surface carry inf/nan until masked
def render_clean(c2w: np.ndarray, cfg: ToySceneConfig) -> Float[np.ndarray, "H W 3"]:
    """Linear-light RGB of the scene from one camera (values in [0, 1])."""
    h, w = cfg.height, cfg.width
    f = 0.5 * w / np.tan(0.5 * np.radians(cfg.fov_deg))
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    dirs_cam = np.stack([(xs - w / 2) / f, -(ys - h / 2) / f, -np.ones_like(xs)], -1)
    dirs = dirs_cam @ c2w[:3, :3].T
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    origin = c2w[:3, 3]
    depth = np.full((h, w), np.inf)
    color = np.zeros((h, w, 3))

    def hit(t: np.ndarray, rgb: np.ndarray) -> None:
        closer = (t > 1e-4) & (t < depth)
        depth[closer] = t[closer]
        color[closer] = rgb[closer]

    # Backdrop: a cylinder of radius 6 around z, with coloured vertical stripes.
    a = dirs[..., 0] ** 2 + dirs[..., 1] ** 2
    b = 2 * (origin[0] * dirs[..., 0] + origin[1] * dirs[..., 1])
    c = origin[0] ** 2 + origin[1] ** 2 - 36.0
    t = (-b + np.sqrt(np.maximum(b * b - 4 * a * c, 0))) / (2 * a + 1e-12)
    p = origin + t[..., None] * dirs
    ang = np.arctan2(p[..., 1], p[..., 0])
    stripe = (np.floor(ang * 12 / np.pi) % 3).astype(int)
    palette = np.array([[0.85, 0.25, 0.2], [0.2, 0.6, 0.85], [0.9, 0.8, 0.3]])
    band = 0.75 + 0.25 * np.sin(p[..., 2] * 3.0)[..., None]
    hit(t, palette[stripe] * band)

    # Floor z = 0: checkerboard.
    t = np.where(np.abs(dirs[..., 2]) > 1e-9, -origin[2] / np.where(dirs[..., 2] == 0, 1, dirs[..., 2]), np.inf)
    p = origin + t[..., None] * dirs
    check = ((np.floor(p[..., 0] * 2) + np.floor(p[..., 1] * 2)) % 2)[..., None]
    floor = np.where(check > 0, [0.9, 0.9, 0.85], [0.25, 0.35, 0.3])
    hit(t, _shade(p, np.broadcast_to([0.0, 0.0, 1.0], p.shape), floor))

    # Sphere at (0.6, 0, 0.7), radius 0.7, with latitude/longitude colour bands.
    centre, radius = np.array([0.6, 0.0, 0.7]), 0.7
    oc = origin - centre
    bq = (dirs * oc).sum(-1)
    disc = bq**2 - (oc @ oc - radius**2)
    t = np.where(disc > 0, -bq - np.sqrt(np.maximum(disc, 0)), np.inf)
    p = origin + t[..., None] * dirs
    n = (p - centre) / radius
    lon = np.arctan2(n[..., 1], n[..., 0])
    pattern = (np.floor(lon * 4 / np.pi) + np.floor(n[..., 2] * 3)) % 2
    sphere = np.where(pattern[..., None] > 0, [0.95, 0.55, 0.1], [0.3, 0.15, 0.7])
    hit(t, _shade(p, n, sphere))

    # Axis-aligned box [-1.4,-0.6] x [-0.5,0.7] x [0,0.9], green with a white grid.
    lo, hi = np.array([-1.4, -0.5, 0.0]), np.array([-0.6, 0.7, 0.9])
    inv = 1.0 / np.where(np.abs(dirs) < 1e-12, 1e-12, dirs)
    t0, t1 = (lo - origin) * inv, (hi - origin) * inv
    tnear, tfar = np.minimum(t0, t1).max(-1), np.maximum(t0, t1).min(-1)
    t = np.where((tnear < tfar) & (tnear > 0), tnear, np.inf)
    p = origin + t[..., None] * dirs
    axis = np.minimum(t0, t1).argmax(-1)
    normal = np.zeros_like(p)
    np.put_along_axis(normal, axis[..., None], -np.sign(np.take_along_axis(dirs, axis[..., None], -1)), -1)
    grid = ((np.abs(np.sin(p * 9.0)) < 0.15).any(-1))[..., None]
    box = np.where(grid, [0.95, 0.95, 0.95], [0.15, 0.65, 0.3])
    hit(t, _shade(p, normal, box))
    return np.clip(color, 0.0, 1.0)


def _camera_ring(n: int, phase: float) -> list:
    poses = []
    for i in range(n):
        ang = 2 * np.pi * (i + phase) / n
        eye = np.array([4.0 * np.cos(ang), 4.0 * np.sin(ang), 1.6 + 0.4 * np.sin(3 * ang)])
        poses.append(look_at(eye, np.array([0.0, 0.0, 0.5])))
    return poses


def write_toy_scene(out: Path, cfg: ToySceneConfig = ToySceneConfig()) -> Path:
    """Write a ``lowlight-data`` scene: ``train/`` (dark), ``train_gt/``, ``test/`` (clean), jsons."""
    rng = np.random.default_rng(cfg.seed)
    out = Path(out)
    f = 0.5 * cfg.width / np.tan(0.5 * np.radians(cfg.fov_deg))
    intr = {"fl_x": f, "fl_y": f, "cx": cfg.width / 2, "cy": cfg.height / 2, "w": cfg.width, "h": cfg.height}
    splits = {"train": _camera_ring(cfg.n_train, 0.0), "test": _camera_ring(cfg.n_test, 0.37)}
    for split, poses in splits.items():
        frames = []
        for i, c2w in enumerate(poses):
            clean = render_clean(c2w, cfg)
            name = f"{i:04d}.png"
            if split == "train":
                lin = clean * cfg.exposure
                # Poisson shot noise with gain noise**2 plus Gaussian read noise, in linear light.
                gain = max(cfg.noise**2, 1e-12)
                lin = rng.poisson(lin / gain) * gain + rng.normal(0.0, cfg.noise, lin.shape)
                _save(out / "train" / name, lin)
                _save(out / "train_gt" / name, clean)
            else:
                _save(out / "test" / name, clean)
            frames.append({"file_path": f"{split}/{name}", "transform_matrix": c2w.tolist()})
        (out / f"transforms_{split}.json").write_text(json.dumps({**intr, "frames": frames}, indent=1))
    (out / "toy_scene.json").write_text(json.dumps(asdict(cfg), indent=1))
    return out


def _save(path: Path, linear: np.ndarray) -> None:
    """Encode linear-light [0, 1] RGB as 8-bit sRGB PNG."""
    path.parent.mkdir(parents=True, exist_ok=True)
    srgb = linear_to_srgb(torch.from_numpy(np.clip(linear, 0.0, 1.0))).numpy()
    Image.fromarray((srgb * 255.0 + 0.5).astype(np.uint8)).save(path)
