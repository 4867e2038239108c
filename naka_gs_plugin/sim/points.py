"""Dense "feed-forward-like" point cloud of a procedural scene, in a frame offset by a KNOWN sim3.

Points are drawn from the scene's surface samples (training frame = world frame of
``transforms_*.json``), jittered by ``noise_std``, plus uniform outliers in the samples'
bounding box and over-dense clusters, then mapped to the points' own frame by
``x' = scale * R @ x + translation``. Colours are the samples' shaded linear colours encoded to
sRGB uint8 (outliers: random). ``points.ply`` is binary little-endian PLY (float xyz, uchar rgb).
"""

from __future__ import annotations

from pathlib import Path
from typing import Dict, Tuple

import numpy as np
import torch
from jaxtyping import Float, UInt8

from naka_gs_plugin.sim.effects import linear_to_srgb
from naka_gs_plugin.sim.spec import PointCloudSpec, Sim3Spec


def sim3_matrix(sim3: Sim3Spec) -> Float[np.ndarray, "4 4"]:
    """4x4 matrix of ``x' = scale * Rz @ Ry @ Rx @ x + translation`` (angles in degrees)."""
    rx, ry, rz = np.radians(sim3.rotation_deg)
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    m = np.eye(4)
    m[:3, :3] = sim3.scale * (Rz @ Ry @ Rx)
    m[:3, 3] = sim3.translation
    return m


def apply_sim3(m: Float[np.ndarray, "4 4"], x: Float[np.ndarray, "N 3"]) -> Float[np.ndarray, "N 3"]:
    return x @ m[:3, :3].T + m[:3, 3]


def sample_point_cloud(
    spec: PointCloudSpec,
    surface: Float[np.ndarray, "S 3"],
    colors: Float[np.ndarray, "S 3"],
    rng: np.random.Generator,
) -> Tuple[Float[np.ndarray, "N 3"], UInt8[np.ndarray, "N 3"]]:
    """Noisy surface points + outliers + clusters, in the **training** frame; colours sRGB uint8."""
    idx = rng.integers(0, len(surface), spec.n_points)
    xyz = [surface[idx] + rng.normal(scale=spec.noise_std, size=(spec.n_points, 3))]
    rgb = [colors[idx]]
    n_out = int(round(spec.outlier_fraction * spec.n_points))
    lo, hi = surface.min(0), surface.max(0)
    xyz.append(rng.uniform(lo, hi, size=(n_out, 3)))
    rgb.append(rng.uniform(size=(n_out, 3)))
    for c in rng.integers(0, len(surface), spec.n_clusters):
        xyz.append(surface[c] + rng.normal(scale=spec.cluster_std, size=(spec.cluster_size, 3)))
        rgb.append(np.tile(colors[c], (spec.cluster_size, 1)))
    srgb = linear_to_srgb(torch.from_numpy(np.concatenate(rgb))[:, None, :].clip(0, 1))[:, 0].numpy()
    return np.concatenate(xyz), np.round(srgb * 255).astype(np.uint8)


def write_ply(path: Path, xyz: Float[np.ndarray, "N 3"], rgb: UInt8[np.ndarray, "N 3"]) -> None:
    """Binary little-endian PLY with float32 ``x y z`` and uchar ``red green blue``."""
    vertex = np.empty(len(xyz), dtype=[("xyz", "<f4", 3), ("rgb", "u1", 3)])
    vertex["xyz"], vertex["rgb"] = xyz, rgb
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(xyz)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    path.write_bytes(header.encode("ascii") + vertex.tobytes())


def camera_centres(m: Float[np.ndarray, "4 4"], names_c2w: Dict[str, np.ndarray]) -> Dict[str, list]:
    """Image file name -> camera centre in the point cloud's frame."""
    return {name: apply_sim3(m, c2w[None, :3, 3])[0].tolist() for name, c2w in names_c2w.items()}
