"""``naka-gs-eval-correction``: photometric quality of the correction network on paired held-out images.

For every validation pair (LOL-style ``<root>/eval/{low,high}``, LOM scenes' ``transforms_test.json``
views) it compares, against the normal-light ground truth: the low input, Naka, Naka + gray-world white
balance, and Naka + the network (one row per inference mode). Metrics: PSNR and SSIM overall and
inside two masks defined on the **ground truth** (so every method is scored on the same pixels):

* bright: GT luma >= its 0.85 quantile (the training loss takes the quantile of the prediction);
* edge: the training loss's gray-edge mask (``sqrt(|Laplacian(GT luma)| / max)``), used as soft weights.

PSNR = ``10 log10(1 / MSE)`` with the (mask-weighted) MSE over pixels and channels, per image, then
averaged; SSIM = kornia's map (Gaussian window 11, sigma 1.5), mask-weighted mean; LPIPS (AlexNet, v0.1,
:mod:`naka_gs_plugin.model.lpips`) over the whole image. Images sRGB [0, 1].
Prints one table per dataset and writes all numbers (per image too) as JSON.
"""

from __future__ import annotations

from typing import Dict

import kornia
import torch
from jaxtyping import Float
from rich.table import Table
from torch import Tensor

from naka_gs_plugin.enhance.correction_loss import gray_edge_mask, luminance
from naka_gs_plugin.metrics import psnr
from naka_gs_plugin.model.lpips import LazyLPIPS

LPIPS = LazyLPIPS()


def gray_world(image: Float[Tensor, "B 3 H W"]) -> Float[Tensor, "B 3 H W"]:
    """Gray-world white balance: scale each channel so its mean equals the mean over all channels; clip."""
    means = image.mean(dim=(2, 3), keepdim=True)
    gain = means.mean(dim=1, keepdim=True) / means.clamp(min=1e-6)
    return (image * gain).clamp(0.0, 1.0)


def masks(gt: Float[Tensor, "1 3 H W"], quantile: float = 0.85) -> Dict[str, Tensor]:
    """``{"all", "bright", "edge"}`` weight maps ``[1, 1, H, W]`` from the ground truth."""
    luma = luminance(gt)
    thresh = torch.quantile(luma.flatten(), quantile)
    return {"all": torch.ones_like(luma), "bright": (luma >= thresh).float(), "edge": gray_edge_mask(gt)}


def scores(pred: Tensor, gt: Tensor, weights: Dict[str, Tensor]) -> Dict[str, float]:
    """PSNR/SSIM of one image pair under each weight map, and LPIPS of the whole image (``lpips_all``)."""
    ssim_map = kornia.metrics.ssim(pred, gt, 11)
    out = {}
    for name, w in weights.items():
        out[f"psnr_{name}"] = psnr(pred, gt, w)
        out[f"ssim_{name}"] = float((ssim_map * w).sum() / (3 * w.sum().clamp(min=1e-12)))
    out["lpips_all"] = float(LPIPS(pred, gt))
    return out


def means_table(title: str, means: Dict[str, Dict[str, float]]) -> Table:
    table = Table(title=title)
    cols = ["psnr_all", "ssim_all", "lpips_all", "psnr_bright", "ssim_bright", "psnr_edge", "ssim_edge"]
    table.add_column("method")
    for c in cols:
        table.add_column(c.replace("_", " "), justify="right")
    for m, v in means.items():
        table.add_row(m, *(f"{v[c]:.2f}" if c.startswith("psnr") else f"{v[c]:.4f}" for c in cols))
    return table


def markdown(result: Dict[str, dict]) -> str:
    """The means as a Markdown table (for notes)."""
    cols = ["psnr_all", "ssim_all", "lpips_all", "psnr_bright", "ssim_bright", "psnr_edge", "ssim_edge"]
    lines = ["| dataset | method | " + " | ".join(cols) + " |", "|---" * (len(cols) + 2) + "|"]
    for dname, d in result["datasets"].items():
        for m, v in d["means"].items():
            vals = [f"{v[c]:.2f}" if c.startswith("psnr") else f"{v[c]:.4f}" for c in cols]
            lines.append(f"| {dname} | {m} | " + " | ".join(vals) + " |")
    return "\n".join(lines)
