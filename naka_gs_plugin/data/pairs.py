"""Dark/normal calibration pairs of one camera: found, read, checked and aligned before a profile is fitted.

Two layouts (``naka-gs-calibrate PAIRS``):

* a folder with ``low/`` and ``high/`` holding images of the same file names (LOL, LOM);
* a ``lowlight-data`` scene with ``transforms_reference.json`` (RealX3D's BlueHawaii): each training frame's
  image is paired with the reference frame of the same file stem.

Alignment: tripod pairs move a little, and may turn or zoom a little. OpenCV's ECC finds an affine warp of the
normal image onto the dark one (a translation first, then rotation, scale and the rest: :func:`fit_warp`); the
normal image is warped onto the dark one's grid and both are cropped to where the warped image has data
(:attr:`Pair.box`). On BlueHawaii's 30 pairs with the normal images turned by 3 degrees it finds the turn to 0.004
degree and each warp within 0.02-0.07 px of the unturned pair's; the profile fitted on them scores as the one from
the unturned pairs (26.03 dB on the 30 views, against 24.75 with the shift alone).

Every check fails with one line naming the pair and the fix: fewer than :data:`MIN_PAIRS` pairs, sizes that
differ, a normal image no brighter than its dark one, a pair that moved more than a tripod pair does (its centre by
more than :data:`MAX_SHIFT` pixels, turned by more than :data:`MAX_ROTATION` degrees or zoomed by more than
:data:`MAX_SCALE`), a reference that is mostly saturated. A pair that does not align at all (ECC does not converge,
its correlation is below :data:`MIN_CORRELATION`, the warp skews the image, or it aligns far worse than the others:
:data:`FAR_BELOW`) is left out with one warning line naming it; fewer than :data:`MIN_PAIRS` left is an error.
Images are sRGB [0, 1], channel-last, at the resolution training uses (longer side at most 1600 px,
:func:`~naka_gs_plugin.data.lowlight_dataparser.auto_downscale`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, List, Optional, Tuple

import cv2
import numpy as np
from jaxtyping import Float

from naka_gs_plugin.data.images import IMAGE_SUFFIXES, read_rgb
from naka_gs_plugin.errors import UserError

MIN_PAIRS = 3
MAX_SHIFT = 4.0
"""Largest shift of the image centre, in pixels at the training resolution, between a pair's images that is aligned;
beyond it the pair is refused (the camera moved between the shots)."""
MAX_ROTATION = 10.0
"""Largest turn, in degrees, between a pair's images that is aligned; beyond it the pair is refused."""
MAX_SCALE = 0.1
"""Largest zoom between a pair's images that is aligned (a scale off 1 by more is refused)."""
MAX_SKEW = 0.02
"""Largest part of the warp that is neither a turn nor a zoom (shear, unequal scales), relative to its scale: no
camera makes one, so a warp with more did not align the pair."""
MIN_CORRELATION = 0.75
"""Smallest ECC correlation of an aligned pair's brightness patterns. Aligned pairs score 0.96-0.995 (BlueHawaii
0.993-0.995); a dark image against another scene's normal one 0.25-0.64, the patterns being smooth."""
FAR_BELOW = 5.0
"""A pair whose decorrelation (1 - ECC correlation) is more than this many times the pairs' median, and whose
correlation is below :data:`GOOD_CORRELATION`, aligns far worse than the others: it is left out."""
GOOD_CORRELATION = 0.98
"""A correlation at or above this is never far below the others."""
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
    """The normal image's shift onto the dark one at the image centre, ``(x, y)`` pixels at the training
    resolution."""
    rotation: float = 0.0
    """The normal image's turn against the dark one, degrees (positive: clockwise as the images are shown)."""
    scale: float = 1.0
    """The normal image's zoom against the dark one."""
    correlation: float = float("nan")
    """The ECC correlation of the aligned pair's brightness patterns."""
    box: Tuple[int, int, int, int] = (0, 0, 0, 0)
    """``(x0, y0, x1, y1)``: where the warped normal image has data (pixels of the training resolution, ends
    excluded); the profile is fitted and scored there. :attr:`low` is the whole dark image (as a run enhances it),
    :attr:`high` the whole warped normal one."""
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


def _to_grid(warp: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """An affine warp between pixel grids carried to grids ``sx`` (``sy``) times finer across (down), as an area
    downscale relates them (pixel centres: ``x_fine = sx * (x + 0.5) - 0.5``)."""
    grid = np.array([[sx, 0.0, (sx - 1) / 2], [0.0, sy, (sy - 1) / 2], [0.0, 0.0, 1.0]])
    return (grid @ np.vstack([warp.astype(np.float64), [0.0, 0.0, 1.0]]) @ np.linalg.inv(grid))[:2]


def fit_warp(low: np.ndarray, high: np.ndarray) -> Tuple[Optional[np.ndarray], float]:
    """The affine warp (2x3, pixels of ``low``'s grid to ``high``'s) that maps ``high`` onto ``low``, and the ECC
    correlation reached; ``(None, -1)`` where ECC did not converge.

    OpenCV's ECC on downscaled brightness patterns: a translation first (it reaches a shift of several pixels
    that the affine model, started from the identity, can miss), then MOTION_AFFINE from there (rotation, scale;
    on BlueHawaii's pairs as exact as MOTION_EUCLIDEAN, and it follows a zoom, which that cannot)."""
    a, b = _pattern(low, True), _pattern(high, False)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-5)
    warp = np.eye(2, 3, dtype=np.float32)
    try:
        _, warp = cv2.findTransformECC(a, b, warp, cv2.MOTION_TRANSLATION, criteria, None, 5)
    except cv2.error:
        warp = np.eye(2, 3, dtype=np.float32)
    try:
        corr, warp = cv2.findTransformECC(a, b, warp, cv2.MOTION_AFFINE, criteria, None, 5)
    except cv2.error:
        return None, -1.0
    if not np.isfinite(warp).all():
        return None, -1.0
    return _to_grid(warp, low.shape[1] / a.shape[1], low.shape[0] / a.shape[0]), float(corr)


def describe_warp(warp: np.ndarray, shape: Tuple[int, ...]) -> Tuple[Tuple[float, float], float, float, float]:
    """What ``warp`` (2x3, :func:`fit_warp`) does to an image of ``shape``: the centre's shift ``(x, y)`` in pixels,
    the turn in degrees (positive: clockwise as shown), the zoom, and the skew (the part that is no turn or zoom,
    relative to the zoom)."""
    h, w = shape[:2]
    m, centre = warp[:, :2], np.array([(w - 1) / 2, (h - 1) / 2])
    shift = m @ centre + warp[:, 2] - centre
    c, s = (m[0, 0] + m[1, 1]) / 2, (m[1, 0] - m[0, 1]) / 2
    scale = math.hypot(c, s)
    skew = float(np.abs(m - np.array([[c, -s], [s, c]])).max()) / max(scale, 1e-9)
    return (float(shift[0]), float(shift[1])), math.degrees(math.atan2(s, c)), float(scale), skew


def align(low: np.ndarray, high: np.ndarray) -> Tuple[Tuple[float, float], float]:
    """The shift ``(x, y)`` in pixels of ``low``'s grid of the image centre that maps ``high`` onto ``low``, and the
    ECC correlation reached (``-1`` where ECC did not converge): :func:`fit_warp`'s warp, told as a shift."""
    warp, corr = fit_warp(low, high)
    return ((0.0, 0.0), corr) if warp is None else (describe_warp(warp, low.shape)[0], corr)


def valid_box(warp: np.ndarray, shape: Tuple[int, ...]) -> Tuple[int, int, int, int]:
    """The largest box ``(x0, y0, x1, y1)`` of the image shrunk evenly about its centre whose corners ``warp``
    maps into the image (where the warped image has data)."""
    h, w = shape[:2]

    def box(t: float) -> Tuple[int, int, int, int]:
        return math.ceil(t * (w - 1)), math.ceil(t * (h - 1)), w - math.ceil(t * (w - 1)), h - math.ceil(t * (h - 1))

    def inside(b: Tuple[int, int, int, int]) -> bool:
        x0, y0, x1, y1 = b
        corners = np.array([[x0, x1 - 1, x0, x1 - 1], [y0, y0, y1 - 1, y1 - 1], [1, 1, 1, 1]], dtype=np.float64)
        xs, ys = warp @ corners
        tol = 1e-3
        return bool(
            (xs >= -tol).all() and (xs <= w - 1 + tol).all() and (ys >= -tol).all() and (ys <= h - 1 + tol).all()
        )

    if inside(box(0.0)):
        return box(0.0)
    lo, hi = 0.0, 0.5
    for _ in range(30):
        mid = (lo + hi) / 2
        lo, hi = (lo, mid) if inside(box(mid)) else (mid, hi)
    return box(hi)


def warp_onto(high: np.ndarray, warp: np.ndarray) -> np.ndarray:
    """``high`` resampled onto the dark image's grid by ``warp`` (bilinear; outside it, its mirror image, which
    :func:`valid_box` crops away)."""
    return cv2.warpAffine(
        high,
        warp.astype(np.float32),
        (high.shape[1], high.shape[0]),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REFLECT,
    )


def _turn(degrees: float) -> str:
    return f"{abs(degrees):.2f} deg " + ("clockwise" if degrees >= 0 else "anticlockwise")


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


def _warn(message: str) -> None:
    from nerfstudio.utils.rich_utils import CONSOLE  # here: the module imports without nerfstudio

    CONSOLE.log(f"[naka-gs] warning: {message}", markup=False)


def load_pairs(pairs: List[Pair], warn: Optional[Callable[[str], None]] = None) -> List[Pair]:
    """Read, check and align every pair (see the module docstring) and return those to fit on. A pair that does not
    align is left out with one line to ``warn`` (default: the console) naming it; the first other problem raises
    :class:`PairsError` naming the pair and the fix, after listing every bad pair (one line each) when there are
    several; so does having fewer than :data:`MIN_PAIRS` left."""
    from naka_gs_plugin.data.lowlight_dataparser import auto_downscale

    warn = warn or _warn
    if len(pairs) < MIN_PAIRS:
        raise PairsError(
            f"{len(pairs)} calibration pair(s) ({', '.join(p.name for p in pairs) or 'none'}), at least {MIN_PAIRS} "
            "needed -- shoot more scenes twice (a short and a long shutter) and add them"
        )
    problems = []
    fitted = []
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
        warp, corr = fit_warp(low, high)
        pair.low, pair.high, pair.correlation = low, high, corr
        fitted.append((pair, warp))
    # A pair aligns far worse than the others when its decorrelation is many times theirs (pairs differ in detail
    # and noise, so the level is the pairs' own).
    converged = [1.0 - p.correlation for p, w in fitted if w is not None and p.correlation >= MIN_CORRELATION]
    typical = float(np.median(converged)) if converged else float("nan")
    kept, left_out = [], []
    for pair, warp in fitted:
        why = _unaligned(pair, warp, typical)
        if why is not None:
            left_out.append(pair.name)
            warn(
                f"pair {pair.name}: {pair.high_path} does not align with {pair.low_path} ({why}) -- left out of the "
                "calibration; shoot it again from a tripod (only the shutter changes) or remove it"
            )
            pair.low = pair.high = None
            continue
        assert warp is not None and pair.low is not None and pair.high is not None
        shift, rotation, scale, _ = describe_warp(warp, pair.low.shape)
        if max(abs(shift[0]), abs(shift[1])) > MAX_SHIFT or abs(rotation) > MAX_ROTATION or abs(scale - 1) > MAX_SCALE:
            problems.append(
                f"pair {pair.name}: {pair.high_path} shifted by ({shift[0]:+.1f}, {shift[1]:+.1f}) px, turned "
                f"{_turn(rotation)}, zoomed x{scale:.3f} against {pair.low_path} (at most {MAX_SHIFT:g} px, "
                f"{MAX_ROTATION:g} deg, x{1 - MAX_SCALE:g}-x{1 + MAX_SCALE:g}; ECC correlation {pair.correlation:.2f}) "
                "-- shoot the pair from a tripod without touching the camera, or remove it"
            )
            continue
        h, w = pair.low.shape[:2]
        corners = np.array([[0, w - 1, 0, w - 1], [0, 0, h - 1, h - 1], [1, 1, 1, 1]], dtype=np.float64)
        if np.abs((warp - np.eye(2, 3)) @ corners).max() > 0.05:  # moved: resample; else leave the pixels be
            pair.high = warp_onto(pair.high, warp)
            pair.box = valid_box(warp, pair.low.shape)
        else:
            pair.box = (0, 0, w, h)
        pair.shift, pair.rotation, pair.scale = shift, rotation, scale
        x0, y0, x1, y1 = pair.box
        pair.exposure_ratio = exposure_ratio(pair.low[y0:y1, x0:x1], pair.high[y0:y1, x0:x1])
        kept.append(pair)
    if problems:
        raise PairsError("\n".join(problems) if len(problems) > 1 else problems[0])
    if len(kept) < MIN_PAIRS:
        raise PairsError(
            f"{len(kept)} of {len(pairs)} calibration pairs align ({', '.join(left_out)} did not), at least "
            f"{MIN_PAIRS} needed -- shoot those again from a tripod, or add more pairs"
        )
    return kept


def _unaligned(pair: Pair, warp: Optional[np.ndarray], typical: float) -> Optional[str]:
    """Why ``pair`` (its ECC ``warp``, None where ECC did not converge) does not align, or None where it does;
    ``typical``: the pairs' median decorrelation."""
    corr = pair.correlation
    if warp is None:
        return "ECC did not converge"
    if corr < MIN_CORRELATION:
        return f"ECC correlation {corr:.2f}, at least {MIN_CORRELATION:g} needed"
    assert pair.low is not None
    skew = describe_warp(warp, pair.low.shape)[3]
    if skew > MAX_SKEW:
        return f"the warp found skews the image by {skew:.1%}, which no camera does"
    if corr < GOOD_CORRELATION and np.isfinite(typical) and 1.0 - corr > FAR_BELOW * typical:
        return f"ECC correlation {corr:.3f}, far below the other pairs' {1.0 - typical:.3f}"
    return None
