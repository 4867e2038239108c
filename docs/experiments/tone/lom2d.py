"""Shared by the tone probes in this folder: a LOM scene's views enhanced as training enhances them (the
default Enhancer with the scene's hold-out weights, up to but not including the exposure curve), its
normal-light photos, and scores against them. Images sRGB [0, 1], channel-last."""

import json
from pathlib import Path

import kornia
import numpy as np
import torch

from naka_gs_plugin.data.images import read_rgb
from naka_gs_plugin.enhance.pipeline import EnhanceConfig, Enhancer
from naka_gs_plugin.metrics import psnr

LOM = Path("../shared/data/lom")


def names(scene: str, split: str) -> list:
    frames = json.loads((LOM / scene / f"transforms_{split}.json").read_text())["frames"]
    return [Path(f["file_path"]).name for f in frames]


def enhanced(scene: str, split: str) -> list:
    """The split's dark views through Naka, the hold-out network and capture chroma (no exposure curve)."""
    low = [torch.from_numpy(read_rgb(LOM / scene / "low" / n)) for n in names(scene, split)]
    config = EnhanceConfig(correction=f"outputs/correction-loo/{scene}/best.pt", exposure="none", use_cache=False)
    with torch.no_grad():
        return Enhancer(config).enhance_images(low, description=f"{scene} {split}")


def truths(scene: str) -> list:
    """The normal-light photos of the scene's test views."""
    return [torch.from_numpy(read_rgb(LOM / scene / "high" / n)) for n in names(scene, "test")]


def scores(images: list, photos: list) -> np.ndarray:
    """Mean PSNR and SSIM (11-px window) of ``images`` against ``photos``."""
    per_view = [
        (psnr(im, ph), float(kornia.metrics.ssim(im.permute(2, 0, 1)[None], ph.permute(2, 0, 1)[None], 11).mean()))
        for im, ph in zip(images, photos)
    ]
    return np.mean(per_view, 0)
