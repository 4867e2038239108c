"""LPIPS (AlexNet, v0.1) that works offline: weights shipped with the package, kept out of checkpoints.

nerfstudio's splatfacto builds torchmetrics' LPIPS in ``populate_modules``; that downloads
torchvision's AlexNet weights (``URLError`` offline, killing ``ns-train``, ``ns-eval``, ``ns-viewer``
and ``ns-export`` alike) and puts 20 backbone tensors into every checkpoint. Here the same metric is
built from weights shipped in ``model/weights/lpips_alex.pt`` (AlexNet's convolutions and LPIPS
v0.1's linear layers, converted from the package index by ``scripts/convert_lpips_weights.py``;
licences in ``model/weights/LICENSE-lpips-alex.txt``), on first use and outside the module tree.

It is our own small module rather than torchmetrics' private ``_LPIPS`` because that class can only
take its backbone from torchvision's download; the arithmetic is the same (tested against it).
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path
from typing import Optional

import torch
import torchvision
from jaxtyping import Float
from torch import Tensor, nn

from naka_gs_plugin.errors import UserError

SHIPPED = Path(str(files("naka_gs_plugin.model") / "weights" / "lpips_alex.pt"))
"""AlexNet's five convolutions + LPIPS v0.1's linear layers, float32, ``torch.load(weights_only=True)``."""
CHANNELS = (64, 192, 384, 256, 256)
"""Channels of AlexNet's relu1..relu5, the layers LPIPS compares."""
RELU_ENDS = (2, 5, 8, 10, 12)
"""End indices (exclusive) of the slices of ``alexnet().features`` ending in relu1..relu5."""
CONVS = (0, 3, 6, 8, 10)
"""Indices of the convolutions in ``alexnet().features``."""


class LPIPSWeightsError(UserError, ValueError):
    """An LPIPS weights file (``--pipeline.model.lpips-weights``) that is missing, unreadable or not AlexNet's
    weights: one line naming the file and the fix."""


class LPIPS(nn.Module):
    """LPIPS v0.1 with the AlexNet backbone, as torchmetrics' ``normalize=True`` and nerfstudio use it.

    Images ``[B, 3, H, W]`` sRGB in [0, 1]; returns one distance per image pair (0 = identical).
    """

    def __init__(self) -> None:
        super().__init__()
        self.features = torchvision.models.alexnet(weights=None).features[: RELU_ENDS[-1]]
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in CHANNELS)
        # LPIPS's input scaling: its [-1, 1] images to ImageNet's mean and deviation.
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188])[None, :, None, None], persistent=False)
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450])[None, :, None, None], persistent=False)
        self.requires_grad_(False)
        self.eval()

    def _layers(self, x: Float[Tensor, "B 3 H W"]) -> list:
        out, start = [], 0
        for end in RELU_ENDS:
            x = self.features[start:end](x)
            out.append(x)
            start = end
        return out

    def forward(self, a: Float[Tensor, "B 3 H W"], b: Float[Tensor, "B 3 H W"]) -> Float[Tensor, " B"]:
        total = 0.0
        feats_a = self._layers(((2 * a - 1) - self.shift) / self.scale)
        feats_b = self._layers(((2 * b - 1) - self.shift) / self.scale)
        for lin, fa, fb in zip(self.lins, feats_a, feats_b):
            fa = fa / torch.sqrt(1e-8 + (fa**2).sum(1, keepdim=True))  # unit length over channels
            fb = fb / torch.sqrt(1e-8 + (fb**2).sum(1, keepdim=True))
            total = total + lin((fa - fb) ** 2).mean((2, 3))
        return total[:, 0]


def load_lpips(weights: Optional[Path] = None) -> LPIPS:
    """The metric with the shipped weights, or with the AlexNet backbone of ``weights``.

    ``weights``: our ``lpips_alex.pt`` format, or torchvision's ``alexnet-owt-7be5be79.pth`` (its
    ``features.*`` tensors; the linear layers then come from the shipped file). Raises
    :class:`LPIPSWeightsError` (a ``ValueError``) with one line naming the file when it is missing, unreadable
    or not AlexNet's weights. Leaves torch's random state as it found it (the layers' random initialisation is
    overwritten anyway), so that evaluating during training never changes the training that follows.
    """
    with torch.random.fork_rng(devices=[]):
        model = LPIPS()
    state = torch.load(SHIPPED, map_location="cpu", weights_only=True)
    if weights is not None:
        path = Path(weights)
        fix = "pass torchvision's alexnet-owt-7be5be79.pth or leave the option out (weights ship with naka-gs)"
        try:
            given = torch.load(path, map_location="cpu", weights_only=True)
        except FileNotFoundError:
            raise LPIPSWeightsError(f"{path}: LPIPS weights file not found -- {fix}") from None
        except Exception as err:  # truncated zip, pickle with code, not a torch file at all
            raise LPIPSWeightsError(
                f"{path}: not a readable torch weights file ({err.__class__.__name__}) -- {fix}"
            ) from None
        expected = {k: v.shape for k, v in model.state_dict().items()}
        backbone = [f"features.{i}.{p}" for i in CONVS for p in ("weight", "bias")]
        if not isinstance(given, dict) or not all(
            isinstance(given.get(k), Tensor) and given[k].shape == expected[k] for k in backbone
        ):
            raise LPIPSWeightsError(
                f"{path}: not AlexNet weights (no features.0-10 tensors of AlexNet's shapes) -- {fix}"
            )
        if not all(torch.isfinite(given[k]).all() for k in backbone):
            raise LPIPSWeightsError(f"{path}: AlexNet weights with NaN or infinite values -- {fix}")
        state.update({k: given[k].float() for k in backbone})
    model.load_state_dict(state)
    return model


class LazyLPIPS:
    """Callable ``(a, b) -> mean LPIPS`` of images ``[B, 3, H, W]`` in [0, 1], built on first use.

    Not an ``nn.Module``, so the backbone never enters a model's ``state_dict`` or checkpoint.
    """

    def __init__(self, weights: Optional[Path] = None) -> None:
        self.weights = weights
        self._metric: Optional[LPIPS] = None

    def __call__(self, a: Float[Tensor, "B 3 H W"], b: Float[Tensor, "B 3 H W"]) -> Tensor:
        if self._metric is None:
            self._metric = load_lpips(self.weights)
        self._metric = self._metric.to(a.device)
        with torch.no_grad():
            return self._metric(a.clamp(0, 1), b.clamp(0, 1)).mean()
