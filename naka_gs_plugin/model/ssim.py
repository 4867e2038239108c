"""Splatfacto's SSIM (loss and eval metric), with compiled kernels for CPU images.

Splatfacto scores every training step with ``pytorch_msssim.SSIM(data_range=1, channel=3)``: an 11-tap
Gaussian window (sigma 1.5) over the valid region (no padding), ``K = (0.01, 0.03)``, the mean of the SSIM
map over batch, channels and pixels. On a CPU that module is five grouped ``conv2d`` pairs forward and as
many in autograd's backward, plus a dozen full-size temporaries: at 500x375 it costs as much as the
rasterizer does at a few hundred Gaussians. :class:`SSIMLoss` is that module (same constructor and attributes)
whose ``forward`` runs :mod:`.ssim_cpu_fast` for float32 RGB CPU images of at least the window's size in both
dimensions with splatfacto's 11-tap window, and ``pytorch_msssim`` itself for anything else (CUDA, float64, smaller
images, other windows or channel counts): that is also the
readable reference the tests compare the kernels with. Inputs are NCHW in [0, 1], any strides (splatfacto passes
permuted HWC images); whichever of the two inputs requires a gradient gets it.

Splatfacto's training loss adds an L1 term to it, ``(1 - lambda) * mean|X - Y| + lambda * (1 - SSIM)``, and logs the
step's PSNR: as PyTorch operations, half a dozen full-size passes forward and backward for the L1 term and three for
PSNR's squared error. :meth:`SSIMLoss.l1_ssim_loss` is that loss with the L1 term inside the SSIM's node (one more
read of the images forward, a term of the SSIM's backward kernel), :func:`squared_error_sum` PSNR's sum in one pass.
"""

from __future__ import annotations

from typing import Optional

import torch
from jaxtyping import Float
from pytorch_msssim import SSIM
from torch import Tensor

from naka_gs_plugin.cpu import numba_fast_path

FAST_TAPS = 11
"""The window length the compiled kernels take (splatfacto's); a compile-time constant of theirs."""
FAST_CHANNELS = 3
"""The channel count the compiled kernels take (RGB); a compile-time constant of theirs."""


def _fast_path(name: str = "ssim_cpu_fast"):
    """A function of :mod:`.ssim_cpu_fast` (by default :func:`.ssim_cpu_fast.ssim_cpu_fast`), or None where numba
    does not import."""
    return numba_fast_path("naka_gs_plugin.model.ssim_cpu_fast", name)


def squared_error_sum(a: Float[Tensor, "*shape"], b: Float[Tensor, "*shape"]) -> Optional[float]:
    """The sum of (a - b)^2 from the compiled kernel, one pass, for float32 CPU tensors of one shape; None for
    anything else (the caller's reference then computes it)."""
    if not (
        a.shape == b.shape
        and a.dim() > 0
        and a.device.type == b.device.type == "cpu"
        and a.dtype == b.dtype == torch.float32
        and _fast_path() is not None
    ):
        return None
    return _fast_path("error_sums")(a, b)[1]


class SSIMLoss(SSIM):
    """``pytorch_msssim.SSIM`` whose forward runs the compiled kernels where they apply (module docstring)."""

    def forward(self, X: Float[Tensor, "N C H W"], Y: Float[Tensor, "N C H W"]) -> Tensor:
        if not self._fused_applies(X, Y):
            return super().forward(X, Y)
        window, c1, c2 = self._constants()
        return _fast_path()(X, Y, window, c1, c2)

    def l1_ssim_loss(self, X: Float[Tensor, "N C H W"], Y: Float[Tensor, "N C H W"], ssim_lambda: float) -> Tensor:
        """Splatfacto's training loss, ``(1 - ssim_lambda) * mean|X - Y| + ssim_lambda * (1 - SSIM(X, Y))`` (its
        ``get_loss_dict``'s main loss without a mask): where the kernels apply, one node whose backward adds the L1
        term's gradient inside the SSIM's kernel, instead of autograd's half a dozen full-size operations for it."""
        if not self._fused_applies(X, Y):
            return (1 - ssim_lambda) * torch.abs(X - Y).mean() + ssim_lambda * (1 - super().forward(X, Y))
        return _fast_path("l1_ssim_loss_cpu_fast")(X, Y, *self._constants(), ssim_lambda)

    def _constants(self) -> tuple:
        """The kernels' window (the one pytorch_msssim convolves with, as NumPy, made once), C1 and C2."""
        if getattr(self, "_window", None) is None:
            self._window = self.win[0].flatten().to(torch.float32).numpy()
        k1, k2 = self.K
        return self._window, (k1 * self.data_range) ** 2, (k2 * self.data_range) ** 2

    def _fused_applies(self, X: Tensor, Y: Tensor) -> bool:
        return (
            X.dim() == 4
            and X.shape == Y.shape
            and X.device.type == "cpu"
            and Y.device.type == "cpu"
            and X.dtype == Y.dtype == torch.float32
            and X.shape[1] == FAST_CHANNELS
            and self.win_size == FAST_TAPS
            and min(X.shape[2:]) >= self.win_size
            and self.size_average
            and not self.nonnegative_ssim
            and _fast_path() is not None
        )
