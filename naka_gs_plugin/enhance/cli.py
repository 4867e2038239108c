"""``naka-gs-enhance SCENE --out DIR``: the training-time enhancement, run outside training.

Reads a ``lowlight-data`` scene's training images, enhances them exactly as the datamanager
does (same :class:`~naka_gs_plugin.enhance.pipeline.Enhancer`, same cache, including the
correction network: ``--enhance.correction none|default|PATH --enhance.correction-mode MODE``), and
writes 8-bit PNGs plus an optional contact sheet. Prints the throughput in images per second.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional, Sequence

import numpy as np
import torch
import tyro
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image

from naka_gs_plugin.data.lowlight_dataparser import LowLightDataParserConfig
from naka_gs_plugin.enhance.pipeline import EnhanceConfig, Enhancer


def load_rgb(path: Path) -> torch.Tensor:
    """An image file as ``uint8 [H, W, 3]`` sRGB (16-bit PNGs are reduced to 8 bit, alpha dropped)."""
    with Image.open(path) as im:
        return torch.from_numpy(np.array(im.convert("RGB")))


def contact_sheet(rows: Sequence[Sequence[np.ndarray]], max_width: int = 384) -> np.ndarray:
    """Tile images (float [0,1] or uint8, ``[H, W, 3]``) into a grid, each resized to one tile size."""
    first = rows[0][0]
    scale = min(1.0, max_width / first.shape[1])
    size = (max(1, int(first.shape[1] * scale)), max(1, int(first.shape[0] * scale)))

    def tile(img: np.ndarray) -> np.ndarray:
        arr = img if img.dtype == np.uint8 else (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)
        return np.asarray(Image.fromarray(arr).resize(size, Image.Resampling.BILINEAR))

    return np.concatenate([np.concatenate([tile(im) for im in row], axis=1) for row in rows], axis=0)


@dataclass
class EnhanceCLI:
    """Enhance a low-light scene's training images and write them as PNGs."""

    scene: tyro.conf.Positional[Path]
    """Scene folder (lowlight-data layout: transforms_train.json + images)."""
    out: Path = Path("outputs/enhanced")
    """Output folder for the enhanced PNGs and the sheet."""
    enhance: EnhanceConfig = field(default_factory=EnhanceConfig)
    downscale_factor: int = 1
    """Image downscale before enhancing (1 = full resolution)."""
    sheet: bool = True
    """Also write before_after.png for up to ``sheet_views`` views (rows: input, enhanced; with the
    correction network: input, Naka only, corrected)."""
    sheet_views: int = 4

    def main(self) -> List[Path]:
        outputs = LowLightDataParserConfig(data=self.scene, downscale_factor=self.downscale_factor).setup()
        paths = outputs.get_dataparser_outputs("train").image_filenames
        images = [load_rgb(p) for p in paths]
        start = time.perf_counter()
        enhanced = Enhancer(self.enhance).enhance_images(images, description=f"Enhancing {self.scene.name}")
        seconds = time.perf_counter() - start
        self.out.mkdir(parents=True, exist_ok=True)
        written = []
        for path, image in zip(paths, enhanced):
            dst = self.out / f"{path.stem}.png"
            Image.fromarray((image.numpy() * 255.0 + 0.5).astype(np.uint8)).save(dst)
            written.append(dst)
        h, w = images[0].shape[:2]
        CONSOLE.log(
            f"[naka-gs] {len(images)} images of {w}x{h} in {seconds:.2f} s: {len(images) / seconds:.2f} images/s",
            markup=False,
        )
        if self.sheet:
            k = min(self.sheet_views, len(images))
            rows = [[im.numpy() for im in images[:k]]]
            if self.enhance.method == "naka" and self.enhance.correction != "none":
                naka_only = Enhancer(dataclasses.replace(self.enhance, correction="none"))
                rows.append([im.numpy() for im in naka_only.enhance_images(images[:k], description="Naka only (sheet)")])
            rows.append([im.numpy() for im in enhanced[:k]])
            sheet = contact_sheet(rows)
            Image.fromarray(sheet).save(self.out / "before_after.png")
            CONSOLE.log(f"[naka-gs] wrote {self.out / 'before_after.png'}", markup=False)
        return written


def entrypoint(args: Optional[Sequence[str]] = None) -> None:
    tyro.cli(EnhanceCLI, args=args).main()
