"""NakaGSPipeline: nerfstudio's VanillaPipeline, seeding the model from ``--pipeline.init``.

The seed points need what only the datamanager has (the scene's training cameras and dataparser
normalization; for the triangulation fallback, the *enhanced* training images), and they must
exist before the model is built. VanillaPipeline builds the model right after the datamanager,
seeding it from the train dataparser outputs' ``metadata["points3D_xyz"]``/``["points3D_rgb"]``:
the datamanager is built through :meth:`NakaGSPipeline._datamanager_with_seed`, which resolves the
seed points and puts them there; everything else is VanillaPipeline's.

Pipelines that load a checkpoint (``ns-eval``, ``ns-viewer``, ``ns-export``: ``test_mode`` other
than ``val``) never compute seed points: they read the cached cloud if there is one, else start
from random Gaussians, which the checkpoint then replaces (splatfacto resizes its parameters on
load).
"""

from __future__ import annotations

import tempfile
from contextlib import nullcontext
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, Callable, Dict, Literal, Optional, Tuple, Type

import numpy as np
import torch
from nerfstudio.pipelines.base_pipeline import VanillaPipeline, VanillaPipelineConfig
from torch.cuda.amp.grad_scaler import GradScaler

from naka_gs_plugin.data.cache import content_hash
from naka_gs_plugin.data.lowlight_dataparser import read_split
from naka_gs_plugin.datamanager import LowLightDatamanager, LowLightDatamanagerConfig
from naka_gs_plugin.model.naka_gs_model import NakaGSModelConfig, resolve_rasterizer
from naka_gs_plugin.points.seeding import (
    PointInitConfig,
    SeedResult,
    TrainingFrame,
    log_points,
    resolve_seed_points,
)
from naka_gs_plugin.run import nerfstudio_hooks as hooks


@dataclass
class NakaGSPipelineConfig(VanillaPipelineConfig):
    """VanillaPipeline + seed points from ``--pipeline.init`` (source, alignment, PPM)."""

    _target: Type = field(default_factory=lambda: NakaGSPipeline)
    datamanager: LowLightDatamanagerConfig = field(default_factory=LowLightDatamanagerConfig)
    model: NakaGSModelConfig = field(default_factory=NakaGSModelConfig)
    init: PointInitConfig = field(default_factory=PointInitConfig)
    """Seed points of the Gaussians (source, alignment, PPM)."""

    def setup(self, **kwargs: Any) -> Any:
        """The pipeline, as upstream builds it. When ``eval_setup`` builds it for ``ns-eval``, ``ns-render``,
        ``ns-export`` or ``ns-viewer``, a user error (a scene moved away since training, a bad scene file) is
        one line naming the scene config.yml records (``run.nerfstudio_hooks.loading_error_exit``)."""
        try:
            return super().setup(**kwargs)
        except Exception as err:
            data = self.datamanager.data or self.datamanager.dataparser.data
            exit_ = hooks.loading_error_exit(data, err)
            if exit_ is None:
                raise
            raise exit_ from None

    def __setstate__(self, state: Dict[str, Any]) -> None:
        """Load ``config.yml`` files of runs trained before ``init`` moved here from the model config
        (``ns-eval``/``ns-viewer``/``ns-export`` on an older run): take it from the model."""
        if "init" not in state:
            model_state = getattr(state.get("model"), "__dict__", {})
            state["init"] = model_state.pop("init", None) or PointInitConfig()
        self.__dict__.update(state)


class NakaGSPipeline(VanillaPipeline):
    """See the module docstring."""

    config: NakaGSPipelineConfig
    datamanager: LowLightDatamanager

    def __init__(
        self,
        config: NakaGSPipelineConfig,
        device: str,
        test_mode: Literal["test", "val", "inference"] = "val",
        world_size: int = 1,
        local_rank: int = 0,
        grad_scaler: Optional[GradScaler] = None,
    ):
        background = nullcontext()
        if (
            torch.device(device).type == "cpu"
            and resolve_rasterizer(config.model.rasterizer, torch.device(device)) == "cpu-fast"
        ):
            # The kernels compile in a child process while the datamanager enhances the training images.
            from naka_gs_plugin.model.rasterize_cpu_fast import compiling_in_background

            background = compiling_in_background()
        # The config is handed back unchanged (it is saved and reloaded by ns-eval, ns-viewer...).
        build = config.datamanager._target
        config.datamanager._target = partial(self._datamanager_with_seed, build, test_mode == "val")
        try:
            with background:
                super().__init__(config, device, test_mode, world_size, local_rank, grad_scaler)
        finally:
            config.datamanager._target = build

    def _datamanager_with_seed(
        self, build: Callable[..., LowLightDatamanager], compute: bool, config: LowLightDatamanagerConfig, **kwargs
    ) -> LowLightDatamanager:
        """The datamanager, its train dataparser outputs' metadata holding the seed points (if any) as
        VanillaPipeline reads them: ``points3D_xyz`` float32 ``[N, 3]``, ``points3D_rgb`` uint8 ``[N, 3]``
        (``[0, 3]`` without colours)."""
        self.datamanager = build(config, **kwargs)
        self.seeding = self._resolve_seed(compute=compute)
        if self.seeding.xyz is not None:
            rgb = self.seeding.rgb if self.seeding.rgb is not None else np.zeros((0, 3), np.uint8)
            self.datamanager.train_dataparser_outputs.metadata.update(
                points3D_xyz=torch.from_numpy(self.seeding.xyz).float(),
                points3D_rgb=torch.from_numpy(np.ascontiguousarray(rgb)),
            )
        return self.datamanager

    def load_pipeline(self, loaded_state: Dict[str, Any], step: int) -> None:
        """Upstream's, after checking that the checkpoint fits this model: its per-view parameters (appearance,
        bilateral grids, camera adjustments) have one row per training view, so a checkpoint of a scene with
        another number of views (``--load-dir`` of another scene's run, or ``data:`` in config.yml pointed at
        another scene) is one line naming the checkpoint, instead of torch's size-mismatch traceback."""
        problem = self._checkpoint_mismatch(loaded_state, self.datamanager.config.dataparser.data)
        if problem is None:
            return super().load_pipeline(loaded_state, step)
        raise hooks.checkpoint_mismatch_exit(problem)

    def _checkpoint_mismatch(self, loaded_state: Dict[str, Any], data: Path) -> Optional[str]:
        """How ``loaded_state`` does not fit this pipeline's parameters (but the Gaussians', which loading resizes)
        of the scene ``data``; None when it fits."""
        current = self.state_dict()
        views = self.model.num_train_data
        for key, value in loaded_state.items():
            key = key[len("module.") :] if key.startswith("module.") else key
            here = current.get(key)
            if key.startswith("_model.gauss_params.") or here is None or not hasattr(value, "shape"):
                continue
            if tuple(value.shape) == tuple(here.shape):
                continue
            if here.dim() == value.dim() and here.shape[0] == views:
                return f"was trained on a scene with {value.shape[0]} training views, and {data} has {views}"
            return f"its {key} is {tuple(value.shape)}, where the model for {data} has {tuple(here.shape)}"
        return None

    # ---------------------------------------------------------------------------------- eval labels
    def get_eval_image_metrics_and_images(self, step: int) -> Tuple[Dict[str, float], Dict[str, torch.Tensor]]:
        metrics, images = super().get_eval_image_metrics_and_images(step)
        return self._labelled(metrics), images

    def get_average_eval_image_metrics(self, *args: Any, **kwargs: Any) -> Dict[str, float]:
        return self._labelled(super().get_average_eval_image_metrics(*args, **kwargs))

    def _labelled(self, metrics: Dict[str, Any]) -> Dict[str, Any]:
        """Metrics scored against dark captures (a held-out view of a nerfstudio-data or colmap scene) are
        ``vs_dark_psnr`` ..., never read as quality; timings (``num_rays*``, ``fps``) keep their names."""
        if not self.datamanager.against_dark:
            return metrics
        return {k if k.startswith(("num_rays", "fps")) else f"vs_dark_{k}": v for k, v in metrics.items()}

    # ---------------------------------------------------------------------------------- seeding
    def _resolve_seed(self, compute: bool) -> SeedResult:
        init = self.config.init
        if self.config.model.random_init:
            log_points("seed points: random init (--pipeline.model.random-init True overrides --pipeline.init)")
            return SeedResult(None, None, {"source": "random", "reason": "random_init"})
        outputs = self.datamanager.train_dataparser_outputs
        scene = Path(self.datamanager.config.dataparser.data)
        layout = outputs.metadata.get("seed_frame")
        if layout is not None:  # nerfstudio-data, colmap: the frame of their own points
            frame = TrainingFrame.from_layout(scene, layout)
        else:  # lowlight-data: the world frame of transforms_train.json
            train = read_split(scene, "transforms_train.json")
            frame = TrainingFrame.from_split(scene, train, outputs.dataparser_transform, outputs.dataparser_scale)
        return resolve_seed_points(init, frame, self._triangulate, self._triangulation_key, compute=compute)

    def _triangulation_key(self) -> Dict[str, Any]:
        """What the triangulated cloud depends on: the enhanced, undistorted training images and their intrinsics."""
        cams = self.datamanager.train_dataset.cameras
        return {
            "images": [content_hash(d["image"]) for d in self.datamanager.cached_train],
            "intrinsics": torch.cat([cams.fx, cams.fy, cams.cx, cams.cy], dim=1).tolist(),
        }

    def _triangulate(self) -> Tuple[np.ndarray, np.ndarray, Dict[str, Any]]:
        """Triangulate the enhanced, undistorted training views at their known poses (normalized frame).

        Returns no points (and the reason in ``info["error"]``) when pycolmap triangulates nothing.
        """
        from naka_gs_plugin.points.sfm import SfMError, triangulate_known_poses

        cached = self.datamanager.cached_train  # loads, undistorts and enhances (kept for training)
        cams = self.datamanager.train_dataset.cameras  # intrinsics updated by the undistortion
        images = [_to_uint8(d["image"]) for d in cached]
        names = [
            f"{i:04d}_{Path(p).stem}.png"
            for i, p in enumerate(self.datamanager.train_dataparser_outputs.image_filenames)
        ]
        c2w = torch.eye(4, dtype=torch.float64).repeat(len(images), 1, 1)
        c2w[:, :3, :4] = cams.camera_to_worlds.double()
        c2w = c2w @ torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))  # OpenGL -> OpenCV axes
        intrinsics = torch.cat([cams.fx, cams.fy, cams.cx, cams.cy], dim=1).double().numpy()
        sizes = torch.cat([cams.width, cams.height], dim=1).double().numpy()
        with tempfile.TemporaryDirectory(prefix="naka-gs-triangulate-") as work:
            try:
                return triangulate_known_poses(images, names, intrinsics, sizes, c2w.numpy(), Path(work))
            except SfMError as err:
                return np.zeros((0, 3)), np.zeros((0, 3), np.uint8), {"error": str(err)}


def _to_uint8(image: torch.Tensor) -> np.ndarray:
    image = image[..., :3].detach().cpu()
    if image.dtype != torch.uint8:
        image = (image.clamp(0, 1) * 255.0).round().to(torch.uint8)
    return image.numpy()
