"""``naka-gs-demo``: the README's main job on the embedded default scene (no downloads).

Generates the toy low-light scene (:mod:`naka_gs_plugin.sim.toy_scene`), enhances its training
views with the same pipeline as ``ns-train naka-gs``, scores input and enhanced images against
the known normal-light truth (PSNR, dB), and writes a before/after/truth contact sheet.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch
import tyro
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image

from naka_gs_plugin.enhance.cli import contact_sheet, load_rgb
from naka_gs_plugin.enhance.pipeline import EnhanceConfig, Enhancer
from naka_gs_plugin.sim.toy_scene import ToySceneConfig, write_toy_scene


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    """PSNR in dB between two float images in [0, 1]."""
    return float(-10.0 * torch.log10(((a - b) ** 2).mean().clamp(min=1e-12)))


@dataclass
class Demo:
    """Generate the toy low-light scene, enhance it, report PSNR against the truth."""

    out: Path = Path("outputs/demo")
    scene: ToySceneConfig = field(default_factory=lambda: ToySceneConfig(width=240, height=180))
    enhance: EnhanceConfig = field(default_factory=EnhanceConfig)

    def main(self) -> dict:
        scene_dir = write_toy_scene(self.out / "scene", self.scene)
        names = sorted(p.name for p in (scene_dir / "train").glob("*.png"))
        low = [load_rgb(scene_dir / "train" / n) for n in names]
        truth = [load_rgb(scene_dir / "train_gt" / n).float() / 255.0 for n in names]
        enhanced = Enhancer(self.enhance).enhance_images(low, description="Enhancing toy scene")
        report = {
            "views": len(names),
            "mean_input_brightness": float(np.mean([im.float().mean() / 255.0 for im in low])),
            "psnr_input_db": float(np.mean([psnr(lo.float() / 255.0, t) for lo, t in zip(low, truth)])),
            "psnr_enhanced_db": float(np.mean([psnr(e, t) for e, t in zip(enhanced, truth)])),
        }
        k = min(4, len(names))
        sheet = contact_sheet(
            [[im.numpy() for im in low[:k]], [im.numpy() for im in enhanced[:k]], [t.numpy() for t in truth[:k]]]
        )
        Image.fromarray(sheet).save(self.out / "before_after.png")
        (self.out / "report.json").write_text(json.dumps(report, indent=1))
        CONSOLE.print(
            f"[naka-gs demo] {report['views']} views, input mean {report['mean_input_brightness']:.3f}: "
            f"PSNR vs truth {report['psnr_input_db']:.2f} dB (input) -> {report['psnr_enhanced_db']:.2f} dB (Naka)",
            markup=False,
        )
        CONSOLE.print(
            f"[naka-gs demo] wrote {self.out / 'before_after.png'} (rows: input, enhanced, truth) and report.json",
            markup=False,
        )
        return report


def entrypoint(args: Optional[Sequence[str]] = None) -> None:
    tyro.cli(Demo, args=args).main()
