"""2D colour levers on RealX3D BlueHawaii, scored against its 30 normal-light references.

Each lever re-takes the colour of the default enhancement's cached per-view output (Naka + shipped network +
capture chroma, before the exposure step), keeps each pixel's linear brightness (mean of the channels), then
applies the default exposure step and scores like ``naka-gs-enhance --reference``. Levers:

- ``decode G``: the capture decoded by a pure power law ``code ** G`` (a camera curve without sRGB's linear
  toe below code 10) instead of the sRGB curve before its chromaticity is taken;
- ``cbcr A``: the capture's JPEG chroma (Cb, Cr of its sRGB codes) scaled by ``A`` first (undoing a
  desaturation of the dark frame);
- ``eps E``: the neutral floor added to every channel before the ratio (default 1e-4, linear): a capture pixel
  near black gets a grey chromaticity;
- ``blur S``: the Gaussian low-pass on the capture, in pixels (default 3);
- ``wide S T``: below ``T`` codes of the 3 px filtered capture (linear, faded in from 0), the chromaticity of the
  capture filtered over ``S`` px in linear light instead (a luminance-weighted neighbourhood: a shadow takes the
  colour of the lit surfaces around it, where the capture recorded chroma above its quantisation);
- ``pedestal R G B``: per-channel offsets, in codes of sRGB's linear toe (``1 / (255 x 12.92)``), subtracted
  from the filtered linear capture before its chromaticity is taken;
- ``prepedestal R G B``: the same offsets subtracted from the capture before the whole enhancement (Naka, the
  network, capture chroma and tone see it; computed, not read from the cache);
- ``network``: the network's own colour (no capture chroma);
- ``oracle``: the default output with one per-scene white balance fitted to the references (diagnosis only: a
  ceiling for any scene-wide colour correction, never a method).

    .venv/bin/naka-gs-enhance ../shared/data/realx3d/BlueHawaii --out outputs/bluehawaii-2d-default  # fills the cache
    .venv/bin/python docs/experiments/realx3d_colour/levers_2d.py decode:2.2 cbcr:1.5 network oracle
"""

import sys
from pathlib import Path

import cv2
import kornia
import torch

from naka_gs_plugin.data.images import read_rgb
from naka_gs_plugin.data.lowlight_dataparser import LowLightDataParserConfig, read_split
from naka_gs_plugin.datamanager import LowLightDatamanagerConfig
from naka_gs_plugin.enhance.pipeline import EnhanceConfig
from naka_gs_plugin.enhance.stages import ExposureStage, to_float01
from naka_gs_plugin.scripts.enhance import score_against

torch.set_grad_enabled(False)
SCENE = Path("../shared/data/realx3d/BlueHawaii")


def linear(x):
    return kornia.color.rgb_to_linear_rgb(x.clamp(0, 1))


def with_chroma(image, chroma):
    """``image``'s linear brightness per pixel with the given linear chromaticity ``[3, H, W]``."""
    lum = linear(image.permute(2, 0, 1)).mean(0, keepdim=True)
    return kornia.color.linear_rgb_to_rgb((lum * chroma).clamp(0, 1)).permute(1, 2, 0)


def capture_chroma(low, decode="srgb", cbcr=1.0, blur=3.0, eps=1e-4, pedestal=None):
    """The blurred capture's linear chromaticity, as :func:`naka_gs_plugin.enhance.chroma.capture_chroma`
    takes it, with the lever's decode or chroma scale."""
    k = max(3, int(3 * blur) | 1)
    cap = kornia.filters.gaussian_blur2d(low.permute(2, 0, 1)[None], (k, k), (blur, blur), border_type="replicate")
    if cbcr != 1.0:
        ycc = kornia.color.rgb_to_ycbcr(cap)
        cap = kornia.color.ycbcr_to_rgb(torch.cat([ycc[:, :1], 0.5 + cbcr * (ycc[:, 1:] - 0.5)], 1))
    cap = cap[0].clamp(0, 1)
    lin, eps = (linear(cap), eps) if decode == "srgb" else (cap**decode, eps ** (decode / 2.4))
    if pedestal is not None:
        lin = (lin - torch.tensor(pedestal)[:, None, None] / (255 * 12.92)).clamp(min=0)
    return (lin + eps) / (lin.mean(0, keepdim=True) + eps)


def wide_chroma(low, sigma, codes, blur=3.0):
    """Capture chroma where the filtered capture is above ``codes`` 8-bit codes; below, blended (linearly in
    its brightness) toward the chromaticity of the linear capture low-passed over ``sigma`` px."""
    local = capture_chroma(low, blur=blur)
    lin = linear(low.permute(2, 0, 1)).permute(1, 2, 0).numpy()
    wide = torch.from_numpy(cv2.GaussianBlur(lin, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE)).permute(2, 0, 1)
    wide = (wide + 1e-6) / (wide.mean(0, keepdim=True) + 1e-6)
    k = max(3, int(3 * blur) | 1)
    cap = kornia.filters.gaussian_blur2d(low.permute(2, 0, 1)[None], (k, k), (blur, blur), border_type="replicate")
    level = linear(cap[0].clamp(0, 1)).mean(0, keepdim=True)
    w = (level / linear(torch.full((3, 1, 1), codes / 255.0))[0]).clamp(0, 1)
    return w * local + (1 - w) * wide


def main(levers):
    dm = LowLightDatamanagerConfig(
        dataparser=LowLightDataParserConfig(data=SCENE), enhance=EnhanceConfig(exposure="none")
    ).setup(device="cpu")
    lows = [to_float01(d["image"]) for d in dm.load_unenhanced_train()]
    cached = dm.enhancer.enhance_images(lows)
    names = [p.name for p in read_split(SCENE, "transforms_train.json").images]
    by_stem = {p.stem: p for p in read_split(SCENE, "transforms_reference.json").images}
    refs = [by_stem[Path(n).stem] for n in names]
    for lever in levers:
        kind, _, value = lever.partition(":")
        if kind == "decode":
            out = [with_chroma(i, capture_chroma(lo, decode=float(value))) for i, lo in zip(cached, lows)]
        elif kind == "cbcr":
            out = [with_chroma(i, capture_chroma(lo, cbcr=float(value))) for i, lo in zip(cached, lows)]
        elif kind == "eps":
            out = [with_chroma(i, capture_chroma(lo, eps=float(value))) for i, lo in zip(cached, lows)]
        elif kind == "pedestal":
            ped = [float(v) for v in value.split(":")]
            out = [with_chroma(i, capture_chroma(lo, pedestal=ped)) for i, lo in zip(cached, lows)]
        elif kind == "prepedestal":
            ped = torch.tensor([float(v) for v in value.split(":")]) / (255 * 12.92)
            out = dm.enhancer.enhance_images(
                [
                    kornia.color.linear_rgb_to_rgb(
                        (linear(lo.permute(2, 0, 1)) - ped[:, None, None]).clamp(min=0)
                    ).permute(1, 2, 0)
                    for lo in lows
                ]
            )
        elif kind == "blur":
            out = [with_chroma(i, capture_chroma(lo, blur=float(value))) for i, lo in zip(cached, lows)]
        elif kind == "wide":
            sigma, _, codes = value.partition(":")
            out = [with_chroma(i, wide_chroma(lo, float(sigma), float(codes))) for i, lo in zip(cached, lows)]
        elif kind == "network":
            naka, correction = dm.enhancer.view_stages[:2]
            naka.prepare(lows)
            out = [correction.apply(naka.apply(lo, lo), lo) for lo in lows]
        elif kind == "oracle":
            h, w = cached[0].shape[:2]
            truth = [torch.from_numpy(cv2.resize(read_rgb(p), (w, h), interpolation=cv2.INTER_AREA)) for p in refs]

            def mean_linear(images):
                return torch.stack([linear(i.permute(2, 0, 1)).mean((1, 2)) for i in images]).mean(0)

            gains = mean_linear(truth) / mean_linear(cached)
            print(f"oracle white balance (r, g, b gains, mean 1): {(gains / gains.mean()).tolist()}")
            out = []
            for image in cached:
                lin = linear(image.permute(2, 0, 1)) * gains[:, None, None]
                out.append(with_chroma(image, lin / lin.mean(0, keepdim=True).clamp(min=1e-8)))
        else:
            raise SystemExit(
                f"unknown lever {lever!r}: decode:G, cbcr:A, eps:E, blur:S, wide:S:T, pedestal:R:G:B, "
                "prepedestal:R:G:B, network or oracle"
            )
        print(f"BlueHawaii, {lever}:", flush=True)
        score_against(ExposureStage().apply_all(out), refs, names)


if __name__ == "__main__":
    main(sys.argv[1:] or ["decode:2.2", "cbcr:1.5", "network", "oracle"])
