"""Low-light datamanager: nerfstudio's FullImageDatamanager plus train-only enhancement.

Training images are enhanced once, after loading and undistortion, by the configured
:class:`~naka_gs_plugin.enhance.pipeline.Enhancer` (disk-cached); eval images are never touched,
so metrics compare renders against the real normal-light ground truth. Scenes without
ground-truth eval images (RealX3D) train without evaluation, and anything asking for eval images
gets a one-line :class:`MissingGroundTruthError` (an exit, not a traceback).

Eval images that are dark captures (``metadata["eval_truth"] == "dark"``: the nerfstudio-data and colmap layouts,
a naka-gs-process-data scene) are no truth either: where they are the training views themselves (the default) training
evaluates nothing; held-out ones are scored during training, the pipeline labelling those metrics ``vs_dark_*``;
``ns-eval`` gets the one line saying there is no normal-light truth.

Commands that load a trained run (``ns-eval``, ``ns-render dataset``, ``ns-viewer``: a datamanager built
with ``test_mode`` other than ``val``) read images after ``eval_setup``, outside ns-train's conversion of
user errors: an image found unreadable there is the same one ``naka-gs:`` line (:attr:`LowLightDataset.loads_a_run`).
"""

from __future__ import annotations

import random
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Literal, Tuple, Type, Union

import cv2
import numpy as np
import torch
from jaxtyping import Float
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanager, FullImageDatamanagerConfig
from nerfstudio.data.datasets.base_dataset import InputDataset
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor

from naka_gs_plugin.cpu import keep_freed_memory
from naka_gs_plugin.data.images import read_raw, read_rgb
from naka_gs_plugin.data.layouts import LayoutConfig
from naka_gs_plugin.data.lowlight_dataparser import LowLightDataError, LowLightDataParserConfig
from naka_gs_plugin.enhance.pipeline import EnhanceConfig, Enhancer
from naka_gs_plugin.errors import user_error_exit

FLAT_RANGE = 0.25 / 255.0
"""Least contrast of a training image (its 0.1-99.9 % pixel range, sRGB [0, 1]): a quarter of an 8-bit level.

Measured: the flattest real captures in ../shared/data (LOL low) still have a pixel std of 2.3 8-bit
levels; the darkest simulator preset (configs/scenes/dark.yaml, linear 16-bit) spans 2.6 levels. An
all-black or all-white capture spans 0: lens cap, wrong folder or a blown-out exposure."""


class MissingGroundTruthError(SystemExit):
    """Raised when an operation needs eval images that the scene does not have: a ``SystemExit`` whose
    message is the one line ``ns-eval`` prints (exit status 1), with no traceback."""


class LowLightDataset(InputDataset):
    """An InputDataset that knows whether its split has ground-truth images.

    nerfstudio's trainer evaluates only ``if datamanager.eval_dataset:``; a split whose images are
    missing is therefore falsy. Its cameras still load, and ``ns-render dataset --split test
    --rendered-output-names rgb`` renders the test views (e.g. a RealX3D challenge submission):
    there, each missing image is a black placeholder, announced once.
    """

    _warned = False
    evaluated = True
    """False where the eval views are the dark training captures themselves: nothing to evaluate (falsy)."""
    loads_a_run = False
    """Set by a datamanager built to load a trained run (``ns-eval``, ``ns-render dataset``...): a user error
    reading an image (a :class:`~naka_gs_plugin.errors.UserError`) is then the one line ``naka-gs: <message>``
    (exit status 1). Under training the trainer converts them itself; other callers get the exception."""

    @property
    def has_ground_truth(self) -> bool:
        return bool(self._dataparser_outputs.metadata.get("has_ground_truth", True))

    @property
    def eval_truth(self) -> str:
        """``normal-light`` (the images are the truth renders are scored against) or ``dark`` (dark captures)."""
        return str(self._dataparser_outputs.metadata.get("eval_truth", "normal-light"))

    def __bool__(self) -> bool:
        return self.has_ground_truth and self.evaluated and len(self) > 0

    def get_numpy_image(self, image_idx: int) -> np.ndarray:
        """nerfstudio's 8-bit PIL read (``cache_images_type uint8``), after a full check of the file
        (PIL may be set to pad truncated images; a broken file gets one line naming it)."""
        path = self._dataparser_outputs.image_filenames[image_idx]
        read_raw(path)
        try:
            return super().get_numpy_image(image_idx)
        except OSError:  # a file PIL cannot open but the reader can (float32 RGB TIFF): rounded to 8 bit
            image = self.get_image_float32(image_idx).numpy()
            return np.round(image * 255.0).astype(np.uint8)

    def get_image_float32(self, image_idx: int) -> Float[Tensor, "H W 3"]:
        """The image at full bit depth (16-bit captures keep their dark detail), float32 sRGB [0, 1]."""
        path = self._dataparser_outputs.image_filenames[image_idx]
        image = read_rgb(path)
        if self.scale_factor != 1.0:
            size = (int(image.shape[1] * self.scale_factor), int(image.shape[0] * self.scale_factor))
            image = cv2.resize(image, size, interpolation=cv2.INTER_LINEAR)
        return torch.from_numpy(np.ascontiguousarray(image))

    def get_data(self, image_idx: int, image_type: Literal["uint8", "float32"] = "float32") -> Dict:
        try:
            return self._get_data(image_idx, image_type)
        except Exception as err:
            exit_ = user_error_exit(err) if self.loads_a_run else None
            if exit_ is None:
                raise
            raise exit_ from None

    def _get_data(self, image_idx: int, image_type: Literal["uint8", "float32"]) -> Dict:
        if self.has_ground_truth:
            return super().get_data(image_idx, image_type)
        if not LowLightDataset._warned:
            CONSOLE.print(
                "[naka-gs] this split has no ground-truth images: gt-* outputs are black placeholders",
                markup=False,
                style="bold yellow",
            )
            LowLightDataset._warned = True
        camera = self.cameras[image_idx]
        shape = (int(camera.height.item()), int(camera.width.item()), 3)
        dtype = torch.uint8 if image_type == "uint8" else torch.float32
        return {"image_idx": image_idx, "image": torch.zeros(shape, dtype=dtype)}


@dataclass
class LowLightDatamanagerConfig(FullImageDatamanagerConfig):
    """FullImageDatamanager whose training images pass through the enhancement pipeline."""

    _target: Type = field(default_factory=lambda: LowLightDatamanager)
    dataparser: LayoutConfig = field(default_factory=LowLightDataParserConfig)
    """The scene layout: lowlight-data (default), nerfstudio-data or colmap (``naka_gs_plugin.data.layouts``)."""
    enhance: EnhanceConfig = field(default_factory=EnhanceConfig)
    """Enhancement applied to training images only (``--pipeline.datamanager.enhance.sigma`` ...)."""
    cache_images_type: Literal["uint8", "float32"] = "float32"
    """float32 keeps the enhanced images' precision; uint8 quarters the memory (rounds after enhancing)."""


class LowLightDatamanager(FullImageDatamanager[LowLightDataset]):
    """See the module docstring."""

    config: LowLightDatamanagerConfig

    def __init__(
        self,
        config: LowLightDatamanagerConfig,
        device: Union[torch.device, str] = "cpu",
        test_mode: Literal["test", "val", "inference"] = "val",
        world_size: int = 1,
        local_rank: int = 0,
        **kwargs,
    ):
        super().__init__(config, device, test_mode, world_size, local_rank, **kwargs)
        if torch.device(device).type != "cuda" and self.config.cache_images == "cpu":
            # "cpu" pins memory, which needs an NVIDIA driver; "gpu" means "this datamanager's device".
            self.config.cache_images = "gpu"
        self.enhancer = Enhancer(self.config.enhance, device=device)
        for dataset in (self.train_dataset, self.eval_dataset):
            dataset.loads_a_run = test_mode != "val"
        self.has_ground_truth = bool(self.eval_dataset)
        self.against_dark = self.has_ground_truth and self.eval_dataset.eval_truth == "dark"
        """Whether the eval images are dark captures: metrics against them are labelled, ns-eval refuses them."""
        if self.against_dark and self._eval_views_train():
            self.eval_dataset.evaluated = False
        if not self.eval_dataset:
            self.eval_unseen_cameras = []

    def _eval_views_train(self) -> bool:
        """Whether every eval image is a training image (``--eval-mode all``, naka-gs-process-data's default)."""

        def files(outputs) -> set:
            return {str(p) for p in outputs.metadata.get("source_images", outputs.image_filenames)}

        return files(self.eval_dataset._dataparser_outputs) <= files(self.train_dataparser_outputs)

    def resume_state(self) -> Dict[str, Any]:
        """Where training is in its view order, which nerfstudio keeps outside any ``state_dict``: the training views
        still to serve this round, what picks the next round (the shuffling generator with ``random`` sampling, the
        views' unsampled-round counts with ``fps``) and the test views not yet evaluated this round. Plain lists and
        tuples, which ``torch.load(weights_only=True)`` reads (:meth:`load_resume_state` puts them back)."""
        state: Dict[str, Any] = {
            "train_unseen_cameras": [int(i) for i in self.train_unseen_cameras],
            "eval_unseen_cameras": [int(i) for i in self.eval_unseen_cameras],
        }
        if hasattr(self, "random_generator"):
            state["random_generator"] = self.random_generator.getstate()
        if hasattr(self, "train_unsampled_epoch_count"):
            state["train_unsampled_epoch_count"] = self.train_unsampled_epoch_count.tolist()
        return state

    def load_resume_state(self, state: Dict[str, Any]) -> bool:
        """Continue the view order :meth:`resume_state` saved; False, changing nothing, when it does not fit this
        scene's views or this sampling strategy."""
        n_train, n_eval = len(self.train_dataset), len(self.eval_dataset)

        def views(key: str, n: int) -> bool:
            indices = state.get(key)
            return isinstance(indices, list) and all(type(i) is int and 0 <= i < n for i in indices)

        if not (
            views("train_unseen_cameras", n_train)
            and state["train_unseen_cameras"]
            and views("eval_unseen_cameras", n_eval)
        ):
            return False
        if self.config.train_cameras_sampling_strategy == "random":
            generator = random.Random()
            try:
                generator.setstate(state["random_generator"])
            except (KeyError, TypeError, ValueError):
                return False
            self.random_generator = generator
        else:
            counts = state.get("train_unsampled_epoch_count")
            if not isinstance(counts, list) or len(counts) != n_train:
                return False
            self.train_unsampled_epoch_count = np.array(counts, dtype=np.float64)
        self.train_unseen_cameras = list(state["train_unseen_cameras"])
        self.eval_unseen_cameras = list(state["eval_unseen_cameras"])
        return True

    def load_unenhanced_train(self) -> List[Dict[str, torch.Tensor]]:
        """The training images as training loads them, before enhancement: full bit depth, downscaled,
        undistorted (``naka-gs-enhance`` enhances these, so training then finds them in the cache).
        Once per datamanager: undistortion updates the cameras' intrinsics in place."""
        return self._check_contrast(super()._load_images("train", self.config.cache_images))

    def _check_contrast(self, cached: List[Dict[str, torch.Tensor]]) -> List[Dict[str, torch.Tensor]]:
        """Refuse training images that are all flat (all black, all white: nothing to reconstruct) in one
        line; warn once when only some are (see :data:`FLAT_RANGE`)."""
        outputs = self.train_dataparser_outputs
        names = outputs.metadata.get("source_images", outputs.image_filenames)
        flat = []
        for i, data in enumerate(cached):
            image = data["image"]
            sample = image[:: max(1, image.shape[0] // 256), :: max(1, image.shape[1] // 256)].float().flatten()
            lo, hi = torch.quantile(sample.cpu(), torch.tensor([0.001, 0.999])).tolist()
            if image.dtype == torch.uint8:
                lo, hi = lo / 255.0, hi / 255.0
            if hi - lo < FLAT_RANGE:
                flat.append((names[i], lo, hi))
        if not flat:
            return cached
        kind = (
            "black" if all(hi < 0.5 for _, _, hi in flat) else "white" if all(lo > 0.5 for _, lo, _ in flat) else "flat"
        )
        first, lo, hi = flat[0]
        what = f"{kind} (no contrast: {Path(first).name} spans {lo:.4f}-{hi:.4f})"
        if len(flat) == len(cached):
            raise LowLightDataError(
                f"{self.config.dataparser.data}: all {len(cached)} training images are {what} -- nothing to "
                "reconstruct: check the captures (lens cap? wrong folder? overexposed?)"
            )
        CONSOLE.log(
            f"[naka-gs] warning: {len(flat)} of {len(cached)} training images are {what}"
            f"{', and ' + ', '.join(Path(n).name for n, _, _ in flat[1:3]) if len(flat) > 1 else ''}"
            f"{' ...' if len(flat) > 3 else ''}: each teaches a blank view -- remove them from transforms_train.json",
            markup=False,
        )
        return cached

    def _load_images(
        self, split: Literal["train", "eval"], cache_images_device: Literal["cpu", "gpu"]
    ) -> List[Dict[str, torch.Tensor]]:
        if split == "eval" and not self.has_ground_truth:
            raise MissingGroundTruthError(self._no_gt_message())
        cached = super()._load_images(split, cache_images_device)
        if split == "train":
            self._check_contrast(cached)
            # The enhancer takes CPU images (only its correction network may run on the GPU), also where
            # nerfstudio caches the images on the GPU; each result goes back to its image's device.
            enhanced = self.enhancer.enhance_images(
                [d["image"].cpu() for d in cached], description="Enhancing train images"
            )
            for data, image in zip(cached, enhanced):
                image = image.to(data["image"].device)
                data["image"] = (image * 255.0).round().to(torch.uint8) if data["image"].dtype == torch.uint8 else image
            keep_freed_memory()  # training starts next: the same heap thresholds whether or not the correction ran
        return cached

    def _no_gt_message(self) -> str:
        return (
            f"naka-gs: {self.config.dataparser.data}: the '{self.test_split}' split has no ground-truth images "
            "(its transforms json points at missing files), so there is nothing to evaluate against -- "
            "use a scene with test images (e.g. LOM, or a naka-gs-sim scene) for metrics"
        )

    def _dark_message(self) -> str:
        note = self.eval_dataset._dataparser_outputs.metadata.get("truth_note", "its eval images are dark captures")
        return (
            f"naka-gs: {self.config.dataparser.data}: no normal-light truth ({note}) -- nothing to score renders "
            "against: render the views with ns-render, or use a lowlight-data scene with normal-light test images "
            "(e.g. LOM) for metrics"
        )

    def _check_truth(self) -> None:
        """One line where there is nothing to evaluate against: no images, or dark captures outside training's
        labelled metrics (``ns-eval`` loads a run with ``test_mode`` test)."""
        if not self.has_ground_truth:
            raise MissingGroundTruthError(self._no_gt_message())
        if self.against_dark and (self.test_mode != "val" or not self.eval_dataset):
            raise MissingGroundTruthError(self._dark_message())

    @property
    def fixed_indices_eval_dataloader(self) -> List[Tuple[Cameras, Dict]]:
        self._check_truth()
        return super().fixed_indices_eval_dataloader

    def next_eval_image(self, step: int) -> Tuple[Cameras, Dict]:
        self._check_truth()
        return super().next_eval_image(step)

    def next_eval(self, step: int) -> Tuple[Cameras, Dict]:
        self._check_truth()
        return super().next_eval(step)
