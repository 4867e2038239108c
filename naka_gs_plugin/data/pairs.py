"""Dark/normal calibration pairs of one camera: found, read, checked and aligned before a profile is fitted.

Two layouts (``naka-gs-calibrate PAIRS``):

* a folder with ``low/`` and ``high/`` holding images of the same file names (LOL, LOM);
* a ``lowlight-data`` scene with ``transforms_reference.json`` (RealX3D's BlueHawaii): each training frame's
  image is paired with the reference frame of the same file stem.

Every check fails with one line naming the pair and the fix: fewer than :data:`MIN_PAIRS` pairs, sizes that
differ, a normal image no brighter than its dark one, a pair that does not align within :data:`MAX_SHIFT`
pixels (tripod pairs move a little: OpenCV's ECC finds the shift, and the normal image is moved onto the dark
one's grid), a reference that is mostly saturated. Images are sRGB [0, 1], channel-last, at the resolution
training uses (longer side at most 1600 px, :func:`~naka_gs_plugin.data.lowlight_dataparser.auto_downscale`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Tuple

import cv2
import numpy as np
from jaxtyping import Float

from naka_gs_plugin.data.images import IMAGE_SUFFIXES, read_rgb
from naka_gs_plugin.errors import UserError

MIN_PAIRS = 3
MAX_SHIFT = 4.0
"""Largest shift, in pixels at the training resolution, between a pair's images that is aligned; beyond it the
pair is refused (the camera moved between the shots)."""
MIN_CORRELATION = 0.6
"""Smallest ECC correlation of an aligned pair's brightness patterns (an unrelated pair scores near 0)."""
SATURATED = 250.0 / 255.0
MAX_SATURATED_FRACTION = 0.5
"""A reference with more than this fraction of pixels at or above :data:`SATURATED` in some channel is refused."""
ALIGN_LONG_SIDE = 512
"""The alignment runs on copies area-downscaled to this longer side (blurred noise; ECC in well under a second)."""


class PairsError(UserError, ValueError):
    """Calibration pairs that cannot be used; the message names the pair (or folder) and the fix."""


@dataclass
class Pair:
    """One dark/normal pair, read, aligned and downscaled to the training resolution."""

    name: str
    low_path: Path
    high_path: Path
    low: Optional[Float[np.ndarray, "H W 3"]] = None
    high: Optional[Float[np.ndarray, "H W 3"]] = None
    shift: Tuple[float, float] = (0.0, 0.0)
    """The normal image's shift onto the dark one, ``(x, y)`` pixels at the training resolution."""
    exposure_ratio: float = float("nan")
    """The normal image's linear light over the dark one's, where both recorded a level."""


def find_pairs(folder: Path) -> List[Pair]:
    """The pairs of ``folder`` in either layout (see the module docstring), sorted by name; not read yet."""
    folder = Path(folder)
    if (folder / "transforms_reference.json").is_file():
        from naka_gs_plugin.data.lowlight_dataparser import read_split  # here: nerfstudio only for this layout

        refs = {p.stem: p for p in read_split(folder, "transforms_reference.json").images}
        lows = read_split(folder, "transforms_train.json").images
        missing = [p.name for p in lows if p.stem not in refs]
        if missing:
            raise PairsError(
                f"{folder / 'transforms_reference.json'}: no reference for training view(s) {', '.join(missing[:3])}"
                " -- list a normal-light photo with the same file name for every training view"
            )
        return [Pair(p.name, p, refs[p.stem]) for p in lows]
    if not ((folder / "low").is_dir() and (folder / "high").is_dir()):
        raise PairsError(
            f"{folder}: not a folder of pairs -- give a folder with low/ and high/ (images of the same file names) "
            "or a lowlight-data scene with transforms_reference.json"
        )

    def images(sub: str) -> dict:
        return {p.name: p for p in sorted((folder / sub).iterdir()) if p.suffix.lower() in IMAGE_SUFFIXES}

    low, high = images("low"), images("high")
    alone = sorted(set(low) ^ set(high))
    if alone:
        side = "high" if alone[0] in low else "low"
        raise PairsError(
            f"{folder / ('low' if side == 'high' else 'high') / alone[0]}: no image of that name in {folder / side} "
            f"({len(alone)} without a partner) -- give each dark image a normal one of the same file name"
        )
    return [Pair(name, low[name], high[name]) for name in sorted(low)]


def _area(image: np.ndarray, factor: int) -> np.ndarray:
    if factor == 1:
        return image
    h, w = image.shape[:2]
    return cv2.resize(image, (w // factor, h // factor), interpolation=cv2.INTER_AREA)


def _pattern(image: np.ndarray, dark: bool) -> np.ndarray:
    """A grey copy for the alignment, downscaled, its tone evened out (the dark frame lifted by a Naka-like
    response at its own mean) so the two exposures show the same pattern."""
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    f = max(1, int(np.ceil(max(grey.shape) / ALIGN_LONG_SIDE)))
    grey = cv2.resize(grey, (grey.shape[1] // f, grey.shape[0] // f), interpolation=cv2.INTER_AREA)
    if dark:
        grey = grey / (grey + max(float(grey.mean()), 1e-3))
    return cv2.GaussianBlur(grey.astype(np.float32), (0, 0), 1.0)


def align(low: np.ndarray, high: np.ndarray) -> Tuple[Tuple[float, float], float]:
    """The translation ``(x, y)`` in pixels of ``low``'s grid that maps ``high`` onto ``low`` (OpenCV's ECC on
    downscaled brightness patterns), and the ECC correlation reached (``-1`` where ECC did not converge)."""
    a, b = _pattern(low, True), _pattern(high, False)
    scale = low.shape[1] / a.shape[1]
    warp = np.eye(2, 3, dtype=np.float32)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-5)
    try:
        corr, warp = cv2.findTransformECC(a, b, warp, cv2.MOTION_TRANSLATION, criteria, None, 5)
    except cv2.error:
        return (0.0, 0.0), -1.0
    return (float(warp[0, 2]) * scale, float(warp[1, 2]) * scale), float(corr)


def exposure_ratio(low: np.ndarray, high: np.ndarray) -> float:
    """Linear light of ``high`` over ``low`` (sRGB [0, 1]), summed over pixels where the dark frame recorded
    more than 2 codes and the normal one is not clipped, after a blur that averages the dark frame's noise."""
    import kornia
    import torch

    lo, hi = (cv2.GaussianBlur(x, (0, 0), 2.0) for x in (low, high))
    lin = [
        kornia.color.rgb_to_linear_rgb(torch.from_numpy(x).permute(2, 0, 1)).permute(1, 2, 0).numpy() for x in (lo, hi)
    ]
    ok = (lo.mean(axis=2) > 2 / 255) & (hi.max(axis=2) < SATURATED)
    if ok.sum() < 100:
        return float("nan")
    return float(lin[1][ok].sum() / max(lin[0][ok].sum(), 1e-12))


def load_pairs(pairs: List[Pair]) -> List[Pair]:
    """Read, check and align every pair (see the module docstring); the first problem raises :class:`PairsError`
    naming the pair and the fix, after listing every bad pair (one line each) when there are several."""
    from naka_gs_plugin.data.lowlight_dataparser import auto_downscale

    if len(pairs) < MIN_PAIRS:
        raise PairsError(
            f"{len(pairs)} calibration pair(s) ({', '.join(p.name for p in pairs) or 'none'}), at least {MIN_PAIRS} "
            "needed -- shoot more scenes twice (a short and a long shutter) and add them"
        )
    problems = []
    for pair in pairs:
        low, high = read_rgb(pair.low_path), read_rgb(pair.high_path)
        if low.shape != high.shape:
            problems.append(
                f"pair {pair.name}: {pair.low_path} is {low.shape[1]}x{low.shape[0]} but {pair.high_path} is "
                f"{high.shape[1]}x{high.shape[0]} -- pair images from one camera at one size"
            )
            continue
        factor = auto_downscale(low.shape[1], low.shape[0])
        low, high = _area(low, factor), _area(high, factor)
        if high.mean() <= low.mean():
            problems.append(
                f"pair {pair.name}: the normal image {pair.high_path} (mean {high.mean():.3f}) is no brighter than the "
                f"dark one {pair.low_path} (mean {low.mean():.3f}) -- swap them or remove the pair"
            )
            continue
        saturated = float((high.max(axis=2) >= SATURATED).mean())
        if saturated > MAX_SATURATED_FRACTION:
            problems.append(
                f"pair {pair.name}: {saturated:.0%} of {pair.high_path} is saturated -- shoot the normal image with a "
                "shorter shutter (it must keep the scene's colours), or remove the pair"
            )
            continue
        (dx, dy), corr = align(low, high)
        if corr < MIN_CORRELATION or max(abs(dx), abs(dy)) > MAX_SHIFT:
            moved = f"shifted by ({dx:+.1f}, {dy:+.1f}) px" if corr >= MIN_CORRELATION else "does not align"
            problems.append(
                f"pair {pair.name}: {pair.high_path} {moved} against {pair.low_path} (at most {MAX_SHIFT:g} px, "
                "ECC correlation {:.2f}) -- shoot the pair from a tripod without touching the camera, or remove it".format(
                    corr
                )
            )
            continue
        if abs(dx) > 0.05 or abs(dy) > 0.05:
            warp = np.array([[1, 0, dx], [0, 1, dy]], dtype=np.float32)
            high = cv2.warpAffine(
                high,
                warp,
                (high.shape[1], high.shape[0]),
                flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                borderMode=cv2.BORDER_REFLECT,
            )
        pair.low, pair.high, pair.shift = low, high, (dx, dy)
        pair.exposure_ratio = exposure_ratio(low, high)
    if problems:
        raise PairsError("\n".join(problems) if len(problems) > 1 else problems[0])
    return pairs
