"""Shared by test_coverage.py and cull_unseen.py: a trained run's test views and training cameras, and how
many training images a world point falls into."""

from pathlib import Path

import torch
from nerfstudio.utils.eval_utils import eval_setup

from naka_gs_plugin.enhance.pipeline import to_float01
from naka_gs_plugin.model.naka_gs_model import viewmat_from_c2w


def load_run(config: Path):
    """(model, test cameras, test photos sRGB [0, 1], their file names, training cameras) of a run, undistorted (loading the
    cached images undistorts them and updates the cameras in place, so it comes first)."""
    _, pipeline, _, _ = eval_setup(config, test_mode="test")
    datamanager = pipeline.datamanager
    truths = [to_float01(data["image"]) for data in datamanager.cached_eval]
    datamanager.cached_train
    names = [Path(f).name for f in datamanager.eval_dataset.image_filenames]
    return pipeline.model, datamanager.eval_dataset.cameras, truths, names, datamanager.train_dataset.cameras


def seen_by(points: torch.Tensor, train) -> torch.Tensor:
    """For world points [N, 3], how many training images (Cameras ``train``) each falls into, in front of
    the camera (OpenCV projection of the OpenGL poses)."""
    views = viewmat_from_c2w(train.camera_to_worlds.float())
    ks = train.get_intrinsics_matrices().float()
    count = torch.zeros(len(points))
    for t in range(len(train)):
        cam = points @ views[t, :3, :3].T + views[t, :3, 3]
        uv = cam[:, :2] / cam[:, 2:].clamp_min(1e-6) @ ks[t, :2, :2].T + ks[t, :2, 2]
        w, h = float(train.width[t]), float(train.height[t])
        count += ((cam[:, 2] > 0.01) & (uv[:, 0] > 0) & (uv[:, 0] < w) & (uv[:, 1] > 0) & (uv[:, 1] < h)).float()
    return count
