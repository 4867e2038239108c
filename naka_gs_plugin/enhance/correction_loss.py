"""Mask-guided training loss of the correction network (paper Sec. 3.1; reference:
``NakaCorrectionLoss`` + ``NakaCorrectionLossWithMasks``, weights as the reference's ``train()``).

``L = L_base + 1.0 * L_gray + 0.8 * L_bright`` with
``L_base = 1.0 L_rgb + 0.5 L_chroma + 0.3 L_ssim + 0.2 L_edge + 0.15 L_feat + 0.02 L_reg``
(the reference's MSE term has weight 0 and is left out). Every term is returned separately for logging.

Images are sRGB-encoded float in [0, 1], channel-first ``[B, 3, H, W]``.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Optional

import kornia
import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor, nn

from naka_gs_plugin.errors import UserError

LUMA = (0.299, 0.587, 0.114)
"""BT.601 luma weights (the reference's gray image for both masks)."""

GRAY_LAPLACIAN = torch.tensor([[2.0, 0.0, 2.0], [0.0, -8.0, 0.0], [2.0, 0.0, 2.0]])
"""OpenCV's ``cv2.Laplacian(ksize=3)`` kernel (the reference's aperture-3 call). kornia's ``laplacian(3)``
is the 4-neighbour-free ``[[1,1,1],[1,-8,1],[1,1,1]]`` kernel, a different operator, so the explicit
kernel goes through ``kornia.filters.filter2d`` instead."""

VGG_LAYERS = (3, 8, 17, 26)
"""torchvision VGG19 ``features`` indices: relu1_2, relu2_2, relu3_4, relu4_4 (reference)."""


def luminance(image: Float[Tensor, "B 3 H W"]) -> Float[Tensor, "B 1 H W"]:
    """BT.601 luma ``.299 R + .587 G + .114 B`` of sRGB values."""
    r, g, b = image[:, 0:1], image[:, 1:2], image[:, 2:3]
    return LUMA[0] * r + LUMA[1] * g + LUMA[2] * b


@torch.no_grad()
def gray_edge_mask(gt: Float[Tensor, "B 3 H W"]) -> Float[Tensor, "B 1 H W"]:
    """``sqrt(|Lap(gray(gt))| / (max + 1e-8))`` per image, in [0, 1]; no gradient.

    Border handling is torch's ``'reflect'`` (mirror without repeating the edge pixel), which is OpenCV's
    default ``BORDER_REFLECT_101`` used by the reference's ``cv2.Laplacian``. Needs H, W >= 2.
    """
    kernel = GRAY_LAPLACIAN.to(gt)[None]
    lap = kornia.filters.filter2d(luminance(gt), kernel, border_type="reflect").abs()
    peak = lap.flatten(1).amax(dim=1)[:, None, None, None]
    return (lap / (peak + 1e-8)).sqrt()


@torch.no_grad()
def bright_mask(pred: Float[Tensor, "B 3 H W"], quantile: float = 0.85) -> Float[Tensor, "B 1 H W"]:
    """1 where the prediction's luma is >= its per-sample ``quantile`` (linear interpolation), else 0."""
    gray = luminance(pred)
    thresh = torch.quantile(gray.flatten(1).float(), quantile, dim=1, interpolation="linear")
    return (gray >= thresh.to(gray.dtype)[:, None, None, None]).to(pred.dtype)


def charbonnier(pred: Tensor, target: Tensor, eps: float = 1e-3) -> Tensor:
    return torch.sqrt((pred - target) ** 2 + eps * eps).mean()


def ssim_loss(pred: Float[Tensor, "B 3 H W"], target: Float[Tensor, "B 3 H W"]) -> Tensor:
    """``1 - mean SSIM`` (Gaussian window 11, sigma 1.5, C1 = 0.01^2, C2 = 0.03^2, +1e-8 denominator).

    The reference convolves with zero padding; kornia's ``padding='same'`` reflects instead. Zero-padding
    both images by 5 and using kornia's ``'valid'`` mode gives exactly the reference's same-size map.
    """
    p = 11 // 2
    ssim_map = kornia.metrics.ssim(
        F.pad(pred, (p, p, p, p)), F.pad(target, (p, p, p, p)), 11, eps=1e-8, padding="valid"
    )
    return 1.0 - ssim_map.mean()


def sobel_magnitude(image: Float[Tensor, "B C H W"]) -> Float[Tensor, "B C H W"]:
    """Per-channel ``sqrt(gx^2 + gy^2 + 1e-6)`` of the raw 3x3 Sobel responses, zero padding (reference).

    kornia's ``sobel`` always replicates the border, so its kernels go through ``filter2d`` with zero padding.
    """
    k = kornia.filters.get_sobel_kernel2d(device=image.device, dtype=image.dtype)
    gx = kornia.filters.filter2d(image, k[0:1], border_type="constant")
    gy = kornia.filters.filter2d(image, k[1:2], border_type="constant")
    return torch.sqrt(gx * gx + gy * gy + 1e-6)


def total_variation(x: Tensor) -> Tensor:
    """Mean absolute horizontal difference + mean absolute vertical difference (0 on 1-pixel axes)."""
    tv = x.new_zeros(())
    if x.shape[-1] > 1:
        tv = tv + (x[..., :, 1:] - x[..., :, :-1]).abs().mean()
    if x.shape[-2] > 1:
        tv = tv + (x[..., 1:, :] - x[..., :-1, :]).abs().mean()
    return tv


class VGGWeightsError(UserError, ValueError):
    """``--vgg-weights`` names a file that is not torchvision's VGG19 state dict; one line."""


class VGGFeatures(nn.Module):
    """Frozen torchvision VGG19 up to relu4_4, on ImageNet-normalised input; returns 4 feature maps."""

    def __init__(self, weights: Path) -> None:
        super().__init__()
        import torchvision

        vgg = torchvision.models.vgg19(weights=None)
        try:
            state = torch.load(weights, map_location="cpu", weights_only=True)
        except (OSError, RuntimeError) as err:
            raise VGGWeightsError(
                f"cannot read VGG19 weights {weights}: {err}; pass torchvision's vgg19-dcbb9e9d.pth"
            ) from err
        try:
            vgg.load_state_dict(state)
        except RuntimeError as err:
            raise VGGWeightsError(f"{weights} is not a torchvision VGG19 state dict; pass vgg19-dcbb9e9d.pth") from err
        self.features = vgg.features[: max(VGG_LAYERS) + 1].eval()
        for p in self.features.parameters():
            p.requires_grad_(False)
        self.register_buffer("mean", torch.tensor([0.485, 0.456, 0.406])[None, :, None, None])
        self.register_buffer("std", torch.tensor([0.229, 0.224, 0.225])[None, :, None, None])

    def forward(self, x: Float[Tensor, "B 3 H W"]) -> list:
        x = (x - self.mean) / self.std
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in VGG_LAYERS:
                out.append(x)
        return out


@dataclass
class LossWeights:
    """Term weights (reference ``train()`` values)."""

    rgb: float = 1.0
    chroma: float = 0.5
    ssim: float = 0.3
    edge: float = 0.2
    feat: float = 0.15
    reg: float = 0.02
    gray: float = 1.0
    bright: float = 0.8
    bright_quantile: float = 0.85


class CorrectionLoss(nn.Module):
    """Base + gray-edge + bright-region loss; ``forward`` returns a dict with every term and ``total``."""

    def __init__(self, weights: Optional[LossWeights] = None, vgg_weights: Optional[Path] = None) -> None:
        super().__init__()
        self.w = weights or LossWeights()
        self.vgg: Optional[VGGFeatures] = None
        if vgg_weights is not None:
            if not Path(vgg_weights).is_file():
                raise FileNotFoundError(f"VGG19 weights {vgg_weights} not found; pass an existing vgg19-dcbb9e9d.pth")
            self.vgg = VGGFeatures(Path(vgg_weights))
        elif self.w.feat > 0:
            # The reference silently falls back to random VGG weights; a random network is no perceptual loss.
            warnings.warn(
                "VGG perceptual term disabled: no VGG19 ImageNet weights given (vgg_weights); "
                "training without L_feat (reference weight 0.15)",
                stacklevel=2,
            )

    def forward(
        self,
        pred: Float[Tensor, "B 3 H W"],
        gt: Float[Tensor, "B 3 H W"],
        naka: Float[Tensor, "B 3 H W"],
        mul: Float[Tensor, "B 1 H W"],
        add: Float[Tensor, "B 3 H W"],
    ) -> Dict[str, Tensor]:
        """All terms (already-unweighted values) plus ``base`` and ``total`` (weighted sums)."""
        w = self.w
        terms: Dict[str, Tensor] = {}
        terms["rgb"] = charbonnier(pred, gt) + 0.5 * (pred - gt).abs().mean()
        # kornia's YCbCr is BT.601 full range with +0.5 chroma offsets; its Cb/Cr factors 0.564/0.713 are the
        # rounded 0.5/(1-.114) = 0.56433 and 0.5/(1-.299) = 0.71327 (chroma differs from exact by < 4e-4).
        ycc_p, ycc_g = kornia.color.rgb_to_ycbcr(pred), kornia.color.rgb_to_ycbcr(gt)
        terms["chroma"] = (ycc_p[:, 1:] - ycc_g[:, 1:]).abs().mean() + 0.2 * (ycc_p[:, :1] - ycc_g[:, :1]).abs().mean()
        terms["ssim"] = ssim_loss(pred, gt)
        terms["edge"] = (sobel_magnitude(pred) - sobel_magnitude(gt)).abs().mean()
        if self.vgg is not None:
            fp, fg = self.vgg(pred), self.vgg(gt)
            terms["feat"] = torch.stack([(a - b).abs().mean() for a, b in zip(fp, fg)]).mean()
        hinge = F.relu((pred - gt).abs().mean() - (naka - gt).abs().mean())
        terms["reg"] = (
            (mul - 1.0).abs().mean()
            + add.abs().mean()
            + 0.5 * (total_variation(mul) + total_variation(add))
            + 0.1 * hinge
        )
        base = sum(getattr(w, k) * v for k, v in terms.items())
        err = (pred - gt).abs()
        terms["gray"] = (gray_edge_mask(gt) * err).mean()
        terms["bright"] = (bright_mask(pred, w.bright_quantile) * err).mean()
        terms["base"] = base
        terms["total"] = base + w.gray * terms["gray"] + w.bright * terms["bright"]
        return terms
