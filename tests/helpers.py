"""Shared test helpers: builders of test inputs and the reduced training loop (test modules import only these)."""

from __future__ import annotations

import copy
import hashlib
import inspect
from pathlib import Path
from typing import Callable, Dict, Optional, Sequence

import torch
import yaml

from naka_gs_plugin.config import FusedAdamConfig, naka_gs_method

SHARED = Path(__file__).resolve().parents[2] / "shared"
"""The shared folder beside the clone."""
SHARED_DATA = SHARED / "data"
"""The real scenes (LOM, LOL, RealX3D), read in place."""
SHARED_REFERENCE = SHARED / "reference"
"""Reference material (the LPIPS example pair)."""
TINY_VIEWS = {"n_train": 3, "n_test": 1, "width": 48, "height": 36, "spacing": 0.3}
"""A simulator scene's views small enough for unit tests."""
F32, F64 = torch.float32, torch.float64


def upstream_sha256(function) -> str:
    """sha256 of an upstream function's source, for the tests that pin the upstream code our hooks rely on; of the
    function itself where nerfstudio's ``check_main_thread`` or ``check_viewer_enabled`` wraps it (they keep no
    ``__wrapped__``, and the wrapper's source is the same for every function they wrap)."""
    if function.__code__.co_name == "wrapper" and function.__closure__:
        function = function.__closure__[0].cell_contents
    return hashlib.sha256(inspect.getsource(function).encode()).hexdigest()


def train_steps(
    model,
    cameras,
    images: Sequence[torch.Tensor],
    steps: int,
    after_step: Optional[Callable[[int], None]] = None,
    lrs: Optional[Dict[str, float]] = None,
) -> torch.Tensor:
    """The training loop of nerfstudio's trainer, reduced: one Adam per parameter group as naka-gs configures
    them (:class:`~naka_gs_plugin.config.FusedAdamConfig`; lr 1e-3 or ``lrs[group]``),
    views in turn with their index in ``metadata["cam_idx"]`` as the datamanager sets it,
    ``step_post_backward`` (densification) after every step. Returns the last step's main loss;
    ``after_step(step)`` runs after each step."""
    lrs = lrs or {}
    opts = {k: FusedAdamConfig(lr=lrs.get(k, 1e-3)).setup(p) for k, p in model.get_param_groups().items() if p}
    model.train()
    for step in range(steps):
        model.step, model.optimizers = step, opts
        i = step % len(images)
        camera = cameras[i : i + 1]
        camera.metadata = {"cam_idx": i}
        outputs = model.get_outputs(camera)
        loss = model.get_loss_dict(outputs, {"image": images[i]})["main_loss"]
        loss.backward()
        for opt in opts.values():
            opt.step()
            opt.zero_grad()
        model.step_post_backward(step)
        if after_step is not None:
            after_step(step)
    return loss


def write_spec(tmp_path: Path, effects: list, name: str = "s", source: dict | None = None, **top) -> Path:
    source = source or {"procedural": {**TINY_VIEWS, "points": {"n_points": 500, "n_clusters": 1, "cluster_size": 50}}}
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump({"name": name, "source": source, "effects": effects, **top}))
    return path


def dark_capture(out: Path, n_train: int, downscale: int = 2, scene: str = "sofa") -> Path:
    """LOM ``scene`` views darkened like a real low-light capture (8-bit sRGB JPEG, noise)."""
    from naka_gs_plugin.sim.generate import generate
    from naka_gs_plugin.sim.spec import parse_spec

    path = SHARED_DATA / "lom" / scene
    spec = {
        "name": f"{scene}-dark",
        "source": {"capture": {"path": str(path), "n_train": n_train, "n_test": 2, "downscale": downscale}},
        "effects": [
            {"exposure": {"factor": 0.012}},
            {"noise": {"shot_gain": 5e-5, "read_std": 4e-4}},
            {"response": {"curve": "srgb"}},
            {"quantize": {}},
            {"jpeg": {"quality": 90}},
        ],
    }
    return generate(parse_spec(spec, out / "spec.yaml"), out / "scene", seed=0)


def make_scene(n, width, height, n_cams=2, sh_degree=3, seed=0, dtype=F32, scale=0.06, hard=False):
    """Random Gaussians in front of ``n_cams`` nearby OpenCV cameras; rasterization's inputs.

    ``hard`` adds the stability cases to the first 12 Gaussians: collapsed (1e-12) and huge (1e3)
    scales, saturated opacities (logits +-30), zero quaternions, a needle, and Gaussians behind
    the camera and inside the near plane.
    """
    gen = torch.Generator().manual_seed(seed)
    focal = 0.8 * width
    z = 2.0 + 4.0 * torch.rand(n, generator=gen, dtype=F64)
    x = (torch.rand(n, generator=gen, dtype=F64) - 0.5) * 1.2 * width / focal * z
    y = (torch.rand(n, generator=gen, dtype=F64) - 0.5) * 1.2 * height / focal * z
    means = torch.stack([x, y, z], dim=1)
    scales = scale * torch.exp(0.5 * torch.randn(n, 3, generator=gen, dtype=F64))
    quats = torch.randn(n, 4, generator=gen, dtype=F64)
    logits = 2.0 * torch.randn(n, generator=gen, dtype=F64)
    if hard:
        scales[0] = 1e-12
        scales[1] = 1e3
        means[:2, :2] = 0.0
        logits[[0, 2, 3]] = 30.0
        logits[[4, 5]] = -30.0
        scales[2] = 5 * scale
        quats[6:8] = 0.0
        scales[8] = torch.tensor([3.0, 1e-4, 1e-4], dtype=F64) * scale  # needle
        means[9, 2] = -1.0  # behind the camera
        means[10, 2] = 0.005  # inside the near plane
        means[11, 2] = 0.3  # close: large on screen
        logits[1] = 0.0  # the huge one is half transparent: the others stay visible
    viewmats = torch.eye(4, dtype=F64).repeat(n_cams, 1, 1)
    viewmats[1:, :3, 3] = 0.1 * torch.randn(n_cams - 1, 3, generator=gen, dtype=F64)
    k = torch.tensor([[focal, 0, 0.5 * width], [0, focal, 0.5 * height], [0, 0, 1]], dtype=F64)
    scene = dict(
        means=means,
        quats=quats,
        scales=scales,
        opacities=torch.sigmoid(logits),
        colors=0.4 * torch.randn(n, (sh_degree + 1) ** 2, 3, generator=gen, dtype=F64),
        viewmats=viewmats,
        Ks=k.repeat(n_cams, 1, 1),
    )
    scene = {key: value.to(dtype) for key, value in scene.items()}
    return dict(scene, width=width, height=height, sh_degree=sh_degree)


def tiny_run_config(scene: Path, out: Path, steps: int, **overrides):
    """The naka-gs config as ns-train builds it, tiny: 2000 random Gaussians, Naka only, no evaluation, the run
    folder ``<out>/<scene>/naka-gs/run``. ``overrides``: dotted field names (``pipeline.model.sh_degree``) -> values."""
    config = copy.deepcopy(naka_gs_method.config)
    config.data = scene
    config.output_dir = out
    config.timestamp = "run"
    config.max_num_iterations = steps
    config.save_only_latest_checkpoint = False
    config.steps_per_eval_image = config.steps_per_eval_all_images = 10**6
    config.vis = "tensorboard"
    config.viewer.quit_on_train_completion = True
    config.pipeline.init.triangulate = False
    config.pipeline.model.num_random = 2000
    config.pipeline.datamanager.enhance.correction = "none"
    for dotted, value in overrides.items():
        *parents, name = dotted.split(".")
        target = config
        for parent in parents:
            target = getattr(target, parent)
        setattr(target, name, value)
    return config
