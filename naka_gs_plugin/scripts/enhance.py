"""``naka-gs-enhance SCENE --out DIR``: the training-time enhancement, run outside training.

Loads a ``lowlight-data`` scene's training images through the low-light datamanager (same reader,
downscaling and undistortion as ``ns-train naka-gs``), enhances them with its
:class:`~naka_gs_plugin.enhance.pipeline.Enhancer` (same cache keys, including the correction network:
``--enhance.correction none|default|PATH --enhance.correction-mode MODE``), so a later ``ns-train`` with
the same options reads every image from the cache, and writes 8-bit PNGs plus an optional contact
sheet. Prints the throughput in images per second.

The output folder is built next to --out and moved into place when complete; --out may not be,
contain or lie inside a folder of input images, and an existing non-empty --out is replaced only
if it holds nothing but an earlier naka-gs-enhance output. Errors print one line (exit status 2).
"""

from __future__ import annotations

import dataclasses
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional, Sequence

import numpy as np
import torch
import tyro
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image

from naka_gs_plugin.data.images import ImageReadError
from naka_gs_plugin.data.lowlight_datamanager import LowLightDatamanagerConfig
from naka_gs_plugin.data.lowlight_dataparser import LowLightDataError, LowLightDataParserConfig, read_split
from naka_gs_plugin.data.safe_io import (
    UnsafeOutputError,
    check_not_input,
    check_replaceable,
    publish_dir,
    staging_dir,
)
from naka_gs_plugin.enhance.pipeline import EnhanceConfig, Enhancer
from naka_gs_plugin.sheet import contact_sheet


@dataclass
class Enhance:
    """Enhance a low-light scene's training images and write them as PNGs."""

    scene: tyro.conf.Positional[Path]
    """Scene folder (lowlight-data layout: transforms_train.json + images)."""
    out: Path = Path("outputs/enhanced")
    """Output folder for the enhanced PNGs and the sheet."""
    enhance: EnhanceConfig = field(default_factory=EnhanceConfig)
    downscale_factor: Optional[int] = None
    """Image downscale before enhancing (1 = full resolution; default: automatic, as ``ns-train``)."""
    sheet: bool = True
    """Also write before_after.png for up to ``sheet_views`` views (rows: input, enhanced; with the
    correction network: input, Naka only, corrected)."""
    sheet_views: int = 4

    def main(self) -> List[Path]:
        """Write the enhanced PNGs (and sheet) to ``out``; returns their final paths."""
        originals = read_split(self.scene, "transforms_train.json").images
        check_not_input(self.out, sorted({p.parent for p in originals}), "--out")
        check_replaceable(self.out, "--out", None)
        names = [f"{p.stem}.png" for p in originals]
        if len(set(names)) < len(names):
            dup = next(n for n in names if names.count(n) > 1)
            raise UnsafeOutputError(
                f"{self.scene}: two training images would both be written as --out/{dup} -- rename one"
            )
        datamanager = LowLightDatamanagerConfig(
            dataparser=LowLightDataParserConfig(data=self.scene, downscale_factor=self.downscale_factor),
            enhance=self.enhance,
        ).setup(device="cpu")
        # Quiet: nerfstudio logs its loading step, and a bad image must print one line, the error.
        quiet, CONSOLE.quiet = CONSOLE.quiet, True
        try:
            images = [data["image"] for data in datamanager.load_unenhanced_train()]
        finally:
            CONSOLE.quiet = quiet
        start = time.perf_counter()
        enhanced = datamanager.enhancer.enhance_images(images, description=f"Enhancing {self.scene.name}")
        seconds = time.perf_counter() - start
        out = self.out.resolve()
        stage = staging_dir(out)
        try:
            self._write(stage, names, images, enhanced, seconds)
            publish_dir(stage, out, "naka-gs-enhance", "--out", None)
        finally:
            shutil.rmtree(stage, ignore_errors=True)  # our own staging folder; gone already once published
        return [self.out / name for name in names]

    def _write(
        self, stage: Path, names: List[str], images: List[torch.Tensor], enhanced: List[torch.Tensor], seconds: float
    ) -> None:
        for name, image in zip(names, enhanced):
            Image.fromarray((image.numpy() * 255.0 + 0.5).astype(np.uint8)).save(stage / name)
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
                rows.append(
                    [im.numpy() for im in naka_only.enhance_images(images[:k], description="Naka only (sheet)")]
                )
            rows.append([im.numpy() for im in enhanced[:k]])
            sheet = contact_sheet(rows)
            Image.fromarray(sheet).save(stage / "before_after.png")
            CONSOLE.log(f"[naka-gs] sheet: {self.out / 'before_after.png'}", markup=False)


def entrypoint(args: Optional[Sequence[str]] = None) -> None:
    """Console script ``naka-gs-enhance``; bad input prints one line and exits with status 2."""
    cli = tyro.cli(Enhance, args=args)
    try:
        cli.main()
    except (UnsafeOutputError, LowLightDataError, ImageReadError, OSError) as err:  # OSError: e.g. missing weights
        CONSOLE.print(f"naka-gs-enhance: {err}", markup=False, soft_wrap=True)
        sys.exit(2)


if __name__ == "__main__":
    entrypoint()
