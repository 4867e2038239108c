"""The scene sheet: pose interpolation, and one sheet from a tiny ``naka-gs`` training of the toy scene."""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest
import torch
from PIL import Image

from benchmarks.scene_sheet import SceneSheet, entrypoint, interpolate_pose, sheet_views


def _rotation(axis, degrees: float) -> torch.Tensor:
    """Rodrigues: rotation by ``degrees`` about ``axis``."""
    x, y, z = (np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)).tolist()
    cross = torch.tensor([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]], dtype=torch.float64)
    a = math.radians(degrees)
    return torch.eye(3, dtype=torch.float64) + math.sin(a) * cross + (1 - math.cos(a)) * cross @ cross


def _angle(r_a: torch.Tensor, r_b: torch.Tensor) -> float:
    """Geodesic angle between two rotations, degrees."""
    cos = ((r_a.T @ r_b).trace() - 1) / 2
    return math.degrees(math.acos(float(cos.clamp(-1, 1))))


def _pose(rot: torch.Tensor, t) -> torch.Tensor:
    return torch.cat([rot, torch.tensor(t, dtype=torch.float64)[:, None]], dim=1)


def test_interpolate_pose_endpoints_and_midpoint():
    a = _pose(_rotation([0.3, 1.0, 0.2], 20.0), [1.0, 2.0, 3.0])
    b = _pose(_rotation([-0.5, 0.4, 1.0], 70.0), [-1.0, 0.0, 5.0])
    assert torch.allclose(interpolate_pose(a, b, 0.0), a, atol=1e-9)
    assert torch.allclose(interpolate_pose(a, b, 1.0), b, atol=1e-9)

    mid = interpolate_pose(a, b, 0.5)
    rot = mid[:, :3]
    assert torch.allclose(rot @ rot.T, torch.eye(3, dtype=torch.float64), atol=1e-9)
    assert torch.det(rot).item() == pytest.approx(1.0, abs=1e-9)
    total = _angle(a[:, :3], b[:, :3])
    assert total > 30.0  # a real rotation between the endpoints, so "halfway" means something
    assert _angle(a[:, :3], rot) == pytest.approx(total / 2, abs=1e-6)
    assert _angle(rot, b[:, :3]) == pytest.approx(total / 2, abs=1e-6)
    assert torch.allclose(mid[:, 3], torch.tensor([0.0, 1.0, 4.0], dtype=torch.float64))
    assert mid.dtype == a.dtype


def test_sheet_views_evenly_spaced():
    assert sheet_views(8, 3) == [0, 4, 7]  # 3.5 rounds to even
    assert sheet_views(8, 1) == [0]
    assert sheet_views(2, 5) == [0, 1]


@pytest.mark.parametrize(
    "args, message",
    [
        (["--load-config", "no/such/config.yml"], "--load-config no/such/config.yml is not a file"),
        (["--load-config", "{config}", "--views", "0"], "--views must be >= 1, got 0"),
    ],
)
def test_bad_input_is_one_line(tmp_path, args, message):
    config = tmp_path / "config.yml"
    config.write_text("")
    with pytest.raises(SystemExit) as exit_info:
        entrypoint([a.format(config=config) for a in args])
    text = str(exit_info.value.code)
    assert message in text and "\n" not in text


def test_sheet_from_a_tiny_training(toy_scene, tmp_path):
    from nerfstudio.scripts.train import main as train_main

    from naka_gs_plugin.config import naka_gs_method

    config = copy.deepcopy(naka_gs_method.config)
    config.data = toy_scene
    config.output_dir = tmp_path / "outputs"
    config.experiment_name = "toy"
    config.timestamp = "run"
    config.max_num_iterations = config.steps_per_save = 20
    config.vis = "tensorboard"
    config.viewer.quit_on_train_completion = True
    config.pipeline.init.triangulate = False  # random init: SfM on 8 tiny views is not under test
    config.pipeline.model.num_random = 2000
    config.pipeline.datamanager.enhance.correction = "none"
    train_main(config)

    out = tmp_path / "sheet.png"
    report = SceneSheet(load_config=config.get_base_dir() / "config.yml", views=3, output=out).main()

    assert [r["view"] for r in report["rows"]] == [0, 4, 7]
    assert [r["novel_towards_view"] for r in report["rows"]] == [1, 5, 6]
    assert report["train_views"] == 8 and report["step"] == 19
    sheet = np.asarray(Image.open(out))
    assert sheet.shape == (3 * 48, 3 * 64, 3)
    keys = ("enhanced_mean_all_views", "enhanced_mean", "render_mean", "novel_render_mean")
    assert all(0.0 < report[k] < 1.0 for k in keys), report
    # Naka lifts the dark toy views (mean sRGB ~0.04) well above their capture.
    assert report["enhanced_mean_all_views"] > 0.15
    assert isinstance(report["exposure_gain"], float) and report["exposure_gain"] >= 1.0
    assert json.loads(out.with_suffix(".json").read_text()) == report
