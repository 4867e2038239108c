"""``naka-gs-enhance SCENE --out DIR``: the training-time enhancement, run outside training.

Loads a ``lowlight-data`` scene's training images through the low-light datamanager (same reader,
downscaling and undistortion as ``ns-train naka-gs``), enhances them with its
:class:`~naka_gs_plugin.enhance.pipeline.Enhancer` (same cache keys, including the correction network:
``--enhance.correction none|default|PATH --enhance.correction-mode MODE``), so a later ``ns-train`` with
the same options reads every image from the cache, and writes 8-bit PNGs plus an optional contact
sheet. Prints the throughput in images per second.

A scene with normal-light photos of its training views (``transforms_reference.json``, as RealX3D's
validation scene BlueHawaii has) is also scored against them (``--reference``): PSNR, SSIM and LPIPS
per view, and the colour error in linear light (:func:`naka_gs_plugin.metrics.colour_error`), written
to ``scores.json`` and printed.

The output folder is built next to --out and moved into place when complete; --out may not be,
contain or lie inside a folder of input images, and an existing non-empty --out is replaced only
if it holds nothing but an earlier naka-gs-enhance output. Ctrl-C or SIGTERM removes the unfinished output and
exits 130 / 143; errors print one line ``naka-gs: <message>`` (exit status 1).
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import numpy as np
import torch
import tyro
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image

from naka_gs_plugin.data.images import read_rgb
from naka_gs_plugin.data.lowlight_dataparser import LowLightDataError, LowLightDataParserConfig, read_split
from naka_gs_plugin.data.safe_io import UnsafeOutputError, staged_output
from naka_gs_plugin.datamanager import LowLightDatamanagerConfig
from naka_gs_plugin.enhance.pipeline import EnhanceConfig, Enhancer
from naka_gs_plugin.scripts import run
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
    reference: str = "auto"
    """Score the enhanced views against normal-light photos of the same views (matched by file name):
    ``auto`` = the scene's ``transforms_reference.json`` when it has one, ``none`` = never, or the name of
    another transforms json in the scene."""

    def main(self) -> List[Path]:
        """Write the enhanced PNGs (and sheet) to ``out``; returns their final paths."""
        originals = read_split(self.scene, "transforms_train.json").images
        inputs = sorted({p.parent for p in originals})
        with staged_output(self.out, tool="naka-gs-enhance", what="--out", inputs=inputs) as stage:
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
            references = self._references(originals)
            if references is not None:
                scores = score_against(enhanced, references, [p.name for p in originals])
                (stage / "scores.json").write_text(json.dumps(scores, indent=1))
            self._write(stage, names, images, enhanced, seconds)
        return [self.out / name for name in names]

    def _references(self, originals: List[Path]) -> Optional[List[Path]]:
        """The normal-light photo of each training view (same file stem), or None when not scoring."""
        name = "transforms_reference.json" if self.reference == "auto" else self.reference
        if self.reference == "none" or (self.reference == "auto" and not (self.scene / name).is_file()):
            return None
        by_stem = {p.stem: p for p in read_split(self.scene, name).images}
        missing = [p.name for p in originals if p.stem not in by_stem]
        if missing:
            raise LowLightDataError(
                f"{self.scene / name}: no reference for training view(s) {', '.join(missing[:3])} -- list a photo "
                "with the same file name for every training view, or pass --reference none"
            )
        return [by_stem[p.stem] for p in originals]

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
                naka_only = Enhancer(dataclasses.replace(self.enhance, correction="none", profile=None))
                rows.append(
                    [im.numpy() for im in naka_only.enhance_images(images[:k], description="Naka only (sheet)")]
                )
            rows.append([im.numpy() for im in enhanced[:k]])
            sheet = contact_sheet(rows)
            Image.fromarray(sheet).save(stage / "before_after.png")
            CONSOLE.log(f"[naka-gs] sheet: {self.out / 'before_after.png'}", markup=False)


def score_against(
    enhanced: Sequence[torch.Tensor], references: Sequence[Path], names: Sequence[str]
) -> Dict[str, object]:
    """PSNR, SSIM, LPIPS and colour error of each enhanced view (sRGB [0, 1], ``[H, W, 3]``) against its
    normal-light photo (resized to the view's size by area averaging, as the dataparser downscales), and
    their means; prints the means."""
    import cv2
    import kornia

    from naka_gs_plugin.metrics import colour_error, psnr
    from naka_gs_plugin.model.lpips import LazyLPIPS

    lpips = LazyLPIPS()
    rows = []
    for name, image, path in zip(names, enhanced, references):
        ref = read_rgb(path)
        h, w = image.shape[:2]
        if ref.shape[:2] != (h, w):
            ref = cv2.resize(ref, (w, h), interpolation=cv2.INTER_AREA)
        ref_t = torch.from_numpy(ref)
        a, b = image.permute(2, 0, 1)[None].clamp(0, 1), ref_t.permute(2, 0, 1)[None]
        rows.append(
            {
                "view": name,
                "psnr": psnr(a, b),
                "ssim": float(kornia.metrics.ssim(a, b, 11).mean()),
                "lpips": float(lpips(a, b)),
                **colour_error(image, ref_t),
            }
        )
    keys = [k for k in rows[0] if k != "view"]
    means = {k: float(np.mean([r[k] for r in rows])) for k in keys}
    CONSOLE.log(
        f"[naka-gs] against {len(rows)} normal-light references: PSNR {means['psnr']:.2f} dB, SSIM {means['ssim']:.3f}, "
        f"LPIPS {means['lpips']:.3f}, chromaticity L1 {means['chroma_l1']:.3f} (r {means['chroma_r']:+.3f}, "
        f"g {means['chroma_g']:+.3f}, b {means['chroma_b']:+.3f}), luminance x{means['luma_ratio']:.2f}",
        markup=False,
    )
    return {"n_views": len(rows), "means": means, "per_view": rows}


def entrypoint(args: Optional[Sequence[str]] = None) -> None:
    """Console script ``naka-gs-enhance`` (:func:`naka_gs_plugin.scripts.run`)."""
    run(Enhance.main, Enhance, args)


if __name__ == "__main__":
    entrypoint()
