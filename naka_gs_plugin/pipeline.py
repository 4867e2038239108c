"""NakaGSPipeline: nerfstudio's VanillaPipeline, seeding the model from ``--pipeline.model.init``.

The seed points need what only the datamanager has (the scene's training cameras and dataparser
normalization; for the triangulation fallback, the *enhanced* training images), and they must
exist before the model is built. VanillaPipeline builds the model right after the datamanager,
seeding it only from ``dataparser_outputs.metadata["points3D_xyz"]``, so ``__init__`` is the one
method replaced; everything else is inherited.

Pipelines that load a checkpoint (``ns-eval``, ``ns-viewer``, ``ns-export``: ``test_mode`` other
than ``val``) never compute seed points: they read the cached cloud if there is one, else start
from random Gaussians, which the checkpoint then replaces (splatfacto resizes its parameters on
load).
"""

from __future__ import annotations

import tempfile
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Literal, Optional, Tuple, Type

import numpy as np
import torch
import torch.distributed as dist
from nerfstudio.models.base_model import Model
from nerfstudio.pipelines.base_pipeline import Pipeline, VanillaPipeline, VanillaPipelineConfig
from torch.cuda.amp.grad_scaler import GradScaler
from torch.nn.parallel import DistributedDataParallel as DDP

from naka_gs_plugin.data.lowlight_datamanager import LowLightDatamanager, LowLightDatamanagerConfig
from naka_gs_plugin.data.lowlight_dataparser import read_split
from naka_gs_plugin.enhance.pipeline import content_hash
from naka_gs_plugin.model.naka_gs_model import NakaGSModelConfig
from naka_gs_plugin.points.seeding import SeedResult, TrainingFrame, log_points, resolve_seed_points


@dataclass
class NakaGSPipelineConfig(VanillaPipelineConfig):
    """VanillaPipeline + seed points from ``--pipeline.model.init`` (source, alignment, PPM)."""

    _target: Type = field(default_factory=lambda: NakaGSPipeline)
    datamanager: LowLightDatamanagerConfig = field(default_factory=LowLightDatamanagerConfig)
    model: NakaGSModelConfig = field(default_factory=NakaGSModelConfig)


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
        Pipeline.__init__(self)  # VanillaPipeline.__init__, with the seed points resolved in between
        self.config = config
        self.test_mode = test_mode
        self.datamanager = config.datamanager.setup(
            device=device, test_mode=test_mode, world_size=world_size, local_rank=local_rank
        )
        self.seeding = self._resolve_seed(compute=test_mode == "val")
        seed_pts = None
        if self.seeding.xyz is not None:
            rgb = self.seeding.rgb if self.seeding.rgb is not None else np.zeros((0, 3), np.uint8)
            seed_pts = (torch.from_numpy(self.seeding.xyz).float(), torch.from_numpy(np.ascontiguousarray(rgb)))
        self.datamanager.to(device)
        assert self.datamanager.train_dataset is not None, "Missing input dataset"
        self._model = config.model.setup(
            scene_box=self.datamanager.train_dataset.scene_box,
            num_train_data=len(self.datamanager.train_dataset),
            metadata=self.datamanager.train_dataset.metadata,
            device=device,
            grad_scaler=grad_scaler,
            seed_points=seed_pts,
        )
        self.model.to(device)
        self.world_size = world_size
        if world_size > 1:
            self._model = typing.cast(Model, DDP(self._model, device_ids=[local_rank], find_unused_parameters=True))
            dist.barrier(device_ids=[local_rank])

    # ---------------------------------------------------------------------------------- seeding
    def _resolve_seed(self, compute: bool) -> SeedResult:
        init = self.config.model.init
        if self.config.model.random_init:
            log_points("seed points: random init (--pipeline.model.random-init True overrides --pipeline.model.init)")
            return SeedResult(None, None, {"source": "random", "reason": "random_init"})
        outputs = self.datamanager.train_dataparser_outputs
        scene = Path(self.datamanager.config.dataparser.data)
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
