"""``python -m benchmarks.correction_eval``: photometric quality of the correction network on paired held-out images.

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

Run from the repository root: ``python -m benchmarks.correction_eval --help``.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import kornia
import numpy as np
import torch
import tyro
from jaxtyping import Float
from nerfstudio.utils.rich_utils import CONSOLE
from rich.table import Table
from torch import Tensor

from naka_gs_plugin.data.images import read_rgb
from naka_gs_plugin.enhance.checkpoint import DEFAULT_WEIGHTS, load_correction
from naka_gs_plugin.enhance.correction import MODES, CorrectionRunner
from naka_gs_plugin.enhance.correction_loss import gray_edge_mask, luminance
from naka_gs_plugin.enhance.correction_train import Pair, lol_pairs, lom_pairs, with_naka
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


@dataclass
class EvalCorrection:
    """Score input / Naka / Naka + gray world / Naka + network on held-out pairs."""

    lol: Tuple[Path, ...] = ()
    """LOL-style roots (their ``eval/{low,high}`` pairs are scored)."""
    lom: Tuple[Path, ...] = ()
    """lowlight-data scenes with low/ + high/ (their ``transforms_test.json`` views are scored)."""
    weights: Path = DEFAULT_WEIGHTS
    """Correction checkpoint (default: the shipped weights)."""
    modes: Tuple[str, ...] = ("exact",)
    """Network inference modes to score (``auto`` or naka_gs_plugin.enhance.correction.MODES)."""
    output: Path = Path("outputs/correction_eval.json")
    """JSON with the per-dataset means and the per-image numbers."""

    def main(self) -> Dict[str, dict]:
        unknown = [m for m in self.modes if m != "auto" and m not in MODES]
        if unknown:
            raise ValueError(f"unknown modes {unknown}; choose auto or one of {sorted(MODES)}")
        datasets: Dict[str, List[Pair]] = {}
        for root in self.lol:
            datasets[f"LOL {root.name} eval"] = lol_pairs(root, "eval")
        if self.lom:
            datasets["LOM test views"] = [p for scene in self.lom for p in lom_pairs(scene, "test")]
        if not datasets:
            raise ValueError("nothing to score: pass --lol and/or --lom")
        net = load_correction(self.weights)
        runners = {m: CorrectionRunner(net, m) for m in self.modes}
        methods = ["input", "naka", "naka+grayworld"] + [f"naka+net ({m})" for m in self.modes]
        result: Dict[str, dict] = {"weights": str(self.weights), "datasets": {}}
        for dname, pairs in datasets.items():
            per_image: Dict[str, List[dict]] = {m: [] for m in methods}
            seconds: Dict[str, List[float]] = {m: [] for m in self.modes}
            for pair in pairs:
                low_hw3 = torch.from_numpy(read_rgb(pair.low))[None]
                gt = torch.from_numpy(read_rgb(pair.high)).permute(2, 0, 1)[None]
                low = low_hw3.permute(0, 3, 1, 2).contiguous()
                naka = with_naka(low_hw3)
                preds = {"input": low, "naka": naka, "naka+grayworld": gray_world(naka)}
                for m, runner in runners.items():
                    t0 = time.perf_counter()
                    preds[f"naka+net ({m})"] = runner(low, naka)["enhanced"]
                    seconds[m].append(time.perf_counter() - t0)
                w = masks(gt)
                for m in methods:
                    per_image[m].append({"image": str(pair.low), **scores(preds[m], gt, w)})
            means = {
                m: {k: float(np.mean([r[k] for r in rows])) for k in rows[0] if k != "image"}
                for m, rows in per_image.items()
            }
            result["datasets"][dname] = {
                "n_images": len(pairs),
                "means": means,
                "seconds_per_image": {m: float(np.mean(s)) for m, s in seconds.items()},
                "per_image": per_image,
            }
            CONSOLE.print(means_table(f"{dname} ({len(pairs)} images)", means))
        self.output.parent.mkdir(parents=True, exist_ok=True)
        self.output.write_text(json.dumps(result, indent=1))
        CONSOLE.log(f"[naka-gs] correction evaluation written to {self.output}", markup=False)
        return result


def entrypoint(args: Optional[Sequence[str]] = None) -> None:
    """``python -m benchmarks.correction_eval``; bad input prints one line."""
    config = tyro.cli(EvalCorrection, args=args)
    try:
        result = config.main()
    except (FileNotFoundError, ValueError) as err:
        raise SystemExit(f"python -m benchmarks.correction_eval: {err}") from None
    CONSOLE.print(markdown(result), markup=False, soft_wrap=True)


if __name__ == "__main__":
    entrypoint()
