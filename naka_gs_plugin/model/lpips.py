"""LPIPS that is built on first use, kept outside the module tree, and fails soft offline.

nerfstudio's splatfacto builds torchmetrics' LPIPS in ``populate_modules``; that downloads
torchvision's AlexNet weights and raises ``URLError`` on an offline machine, killing ``ns-train``,
``ns-eval``, ``ns-viewer`` and ``ns-export`` alike, and it puts 20 backbone tensors into every
checkpoint. Here the metric is constructed lazily; when the weights are neither in torch's hub
cache nor at a given local path and cannot be downloaded, it warns once and reports NaN, which the model then leaves out of its
metrics (NaN is not valid JSON).
"""

from __future__ import annotations

import math
import shutil
import tempfile
from pathlib import Path
from typing import Optional

import torch
from jaxtyping import Float
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor

ALEXNET_FILE = "alexnet-owt-7be5be79.pth"
"""torchvision's AlexNet ImageNet weights, the LPIPS backbone torchmetrics asks for."""


class LazyLPIPS:
    """Callable ``(a, b) -> LPIPS`` (NaN when unavailable); images ``[B, 3, H, W]`` in [0, 1] (normalize=True)."""

    def __init__(self, weights: Optional[Path] = None) -> None:
        self.weights = weights
        self._metric = None
        self._unavailable: Optional[str] = None

    def _build(self) -> None:
        from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

        if self.weights is None:
            self._metric = LearnedPerceptualImagePatchSimilarity(normalize=True)
            return
        if not Path(self.weights).is_file():
            raise FileNotFoundError(f"{self.weights}: LPIPS weights file not found")
        # torchvision only looks in torch.hub's directory: point it, for this one build, at a
        # temporary one holding the user's file under the expected name.
        previous = torch.hub.get_dir()
        with tempfile.TemporaryDirectory() as hub:
            (Path(hub) / "checkpoints").mkdir()
            shutil.copyfile(self.weights, Path(hub) / "checkpoints" / ALEXNET_FILE)
            torch.hub.set_dir(hub)
            try:
                self._metric = LearnedPerceptualImagePatchSimilarity(normalize=True)
            finally:
                torch.hub.set_dir(previous)

    def __call__(self, a: Float[Tensor, "B 3 H W"], b: Float[Tensor, "B 3 H W"]) -> float:
        if self._unavailable is not None:
            return math.nan
        if self._metric is None:
            try:
                self._build()
            except Exception as err:  # URLError offline, missing/corrupt file: the metric is optional
                self._unavailable = f"{err.__class__.__name__}: {err}"
                CONSOLE.print(
                    f"[naka-gs] LPIPS skipped: its AlexNet weights ({ALEXNET_FILE}) are not available "
                    f"({self._unavailable}). Put the file in {torch.hub.get_dir()}/checkpoints or pass "
                    "--pipeline.model.lpips-weights PATH.",
                    markup=False,
                    style="bold yellow",
                )
                return math.nan
        self._metric = self._metric.to(a.device)
        with torch.no_grad():
            return float(self._metric(a.clamp(0, 1), b.clamp(0, 1)))
