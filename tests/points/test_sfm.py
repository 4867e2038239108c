"""pycolmap wrappers: triangulation from known poses on a simulated dark capture of LOM sofa.

The simulator's ``capture`` source darkens real normal-light views (LOM ``high/``) whose poses are
known, so triangulated points can be checked against the scene's real surface: LOM's COLMAP cloud,
mapped into the transforms' frame by the sim3 between its camera centres and the transforms'.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch
from PIL import Image
from scipy.spatial import cKDTree

from naka_gs_plugin.enhance.pipeline import EnhanceConfig, Enhancer
from naka_gs_plugin.points.align import apply_sim3, match_names, umeyama
from naka_gs_plugin.points.sfm import SfMError, triangulate_known_poses
from tests.helpers import SHARED_DATA, dark_capture

SOFA = SHARED_DATA / "lom" / "sofa"
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


@pytest.fixture(scope="module")
def sofa_dark(tmp_path_factory) -> Path:
    return dark_capture(tmp_path_factory.mktemp("sfm"), n_train=12)


def surface_truth() -> np.ndarray:
    """LOM sofa's COLMAP points in the frame of its transforms json (its model has another frame)."""
    model = pycolmap.Reconstruction(SOFA / "colmap_sparse" / "0")
    frames = json.loads((SOFA / "transforms_train.json").read_text())["frames"]
    names = [im.name for im in model.images.values()]
    centres = np.array([im.projection_center() for im in model.images.values()])
    pairs = match_names(names, [f["file_path"] for f in frames])
    targets = np.array([frames[j]["transform_matrix"] for _, j in pairs])[:, :3, 3]
    s, r, t, rms = umeyama(centres[[i for i, _ in pairs]], targets)
    assert rms < 1e-6
    return apply_sim3(s, r, t, np.array([p.xyz for p in model.points3D.values()]))


def load_views(scene: Path, enhance: bool):
    meta = json.loads((scene / "transforms_train.json").read_text())
    images = [np.asarray(Image.open(scene / f["file_path"]).convert("RGB")) for f in meta["frames"]]
    if enhance:
        out = Enhancer(EnhanceConfig(use_cache=False, correction="none")).enhance_images(
            [torch.from_numpy(im.copy()) for im in images]
        )
        images = [(im.numpy() * 255.0 + 0.5).astype(np.uint8) for im in out]
    n = len(images)
    intrinsics = np.tile([meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"]], (n, 1))
    sizes = np.tile([meta["w"], meta["h"]], (n, 1))
    distortion = np.tile([meta[k] for k in ("k1", "k2", "p1", "p2")], (n, 1))
    c2w = np.array([f["transform_matrix"] for f in meta["frames"]]) @ GL_TO_CV
    names = [f["file_path"] for f in meta["frames"]]
    return images, names, intrinsics, sizes, c2w, distortion


def test_triangulation_from_known_poses_lands_on_the_surface(sofa_dark, tmp_path):
    images, names, intrinsics, sizes, c2w, distortion = load_views(sofa_dark, enhance=True)
    xyz, rgb, info = triangulate_known_poses(
        images, names, intrinsics, sizes, c2w, tmp_path / "work", distortion=distortion
    )
    assert xyz.shape == (info["points"], 3) and rgb.shape == (info["points"], 3) and rgb.dtype == np.uint8
    assert info["points"] >= 40
    assert set(info["seconds"]) == {"write", "extract", "match", "triangulate"}
    truth = surface_truth()
    extent = np.linalg.norm(np.percentile(truth, 95, axis=0) - np.percentile(truth, 5, axis=0))
    distance, _ = cKDTree(truth).query(xyz)
    assert np.median(distance) < 0.03 * extent, (np.median(distance), extent)
    # The poses were held fixed: the model's cameras are the given ones.
    model = pycolmap.Reconstruction(tmp_path / "work" / "triangulated")
    for image in model.images.values():
        i = image.image_id - 1
        np.testing.assert_allclose(image.cam_from_world().inverse().matrix(), c2w[i][:3], atol=1e-6)


def test_intrinsics_follow_a_downscaled_image(sofa_dark, tmp_path):
    images, names, intrinsics, sizes, c2w, distortion = load_views(sofa_dark, enhance=True)
    half = [np.asarray(Image.fromarray(im).resize((im.shape[1] // 2, im.shape[0] // 2), Image.BOX)) for im in images]
    xyz, _, info = triangulate_known_poses(half, names, intrinsics, sizes, c2w, tmp_path / "w", distortion=distortion)
    model = pycolmap.Reconstruction(tmp_path / "w" / "triangulated")
    camera = model.cameras[1]
    assert camera.width == half[0].shape[1]
    assert camera.focal_length_x == pytest.approx(intrinsics[0, 0] * half[0].shape[1] / sizes[0, 0])
    truth = surface_truth()
    extent = np.linalg.norm(np.percentile(truth, 95, axis=0) - np.percentile(truth, 5, axis=0))
    assert info["points"] >= 10 and np.median(cKDTree(truth).query(xyz)[0]) < 0.05 * extent


def test_nothing_to_triangulate_raises_a_clear_error(tmp_path):
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, (60, 80, 3), dtype=np.uint8) for _ in range(3)]
    c2w = np.stack([np.eye(4)] * 3)
    c2w[:, 0, 3] = [0.0, 0.1, 0.2]
    with pytest.raises(SfMError, match="triangulated no points from 3 views"):
        triangulate_known_poses(
            images, ["a", "b", "c"], np.tile([80.0, 80.0, 40.0, 30.0], (3, 1)), np.tile([80, 60], (3, 1)), c2w,
            tmp_path / "w",
        )  # fmt: skip


def test_inconsistent_inputs_are_rejected(tmp_path):
    image = np.zeros((8, 8, 3), np.uint8)
    with pytest.raises(ValueError, match="2 images but"):
        triangulate_known_poses([image, image], ["a"], np.ones((2, 4)), np.ones((2, 2)), np.eye(4)[None], tmp_path)
    with pytest.raises(ValueError, match="expected uint8"):
        triangulate_known_poses(
            [image.astype(np.float32)] * 2, ["a", "b"], np.ones((2, 4)), np.ones((2, 2)), np.stack([np.eye(4)] * 2),
            tmp_path,
        )  # fmt: skip


def test_compare_poses_removes_the_sim3_and_reports_a_camera_frame_offset():
    from scipy.spatial.transform import Rotation

    from naka_gs_plugin.points.sfm import compare_poses

    rng = np.random.default_rng(0)
    true = np.tile(np.eye(4), (10, 1, 1))
    true[:, :3, :3] = Rotation.random(10, random_state=1).as_matrix()
    true[:, :3, 3] = rng.normal(size=(10, 3))
    s, r, t = 2.0, Rotation.random(random_state=2).as_matrix(), np.array([1.0, 2.0, 3.0])
    offset = Rotation.from_rotvec([0.0, np.radians(2.0), 0.0]).as_matrix()  # e.g. a shifted principal point
    est = true.copy()
    est[:, :3, 3] = (true[:, :3, 3] - t) @ r / s
    est[:, :3, :3] = r.T @ true[:, :3, :3]
    exact = compare_poses(est, true)
    assert exact["rotation_deg"].max() < 1e-5 and exact["centre_error_pct"].max() < 1e-9
    assert exact["scale"] == pytest.approx(s)
    est[:, :3, :3] = est[:, :3, :3] @ offset
    shifted = compare_poses(est, true)
    np.testing.assert_allclose(shifted["rotation_deg"], 2.0, atol=1e-6)
    assert shifted["camera_offset_deg"] == pytest.approx(2.0) and shifted["rotation_deg_offset_removed"].max() < 1e-5
