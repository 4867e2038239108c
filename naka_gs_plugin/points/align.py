"""Closed-form point-set alignment (Umeyama 1991) and image-name correspondence matching.

Transforms map source to destination: ``dst ~= s * R @ src + t`` (points as rows, so
``apply_sim3`` computes ``s * xyz @ R.T + t``). Units are whatever the inputs use.
"""

from __future__ import annotations

import re
from pathlib import PurePath
from typing import Callable, Dict, List, Literal, Optional, Sequence, Tuple

import numpy as np
from jaxtyping import Float

from naka_gs_plugin.errors import UserError

_SUFFIX = re.compile(r"(_enhanced|_image|_img)$", re.IGNORECASE)
_LAST_INT = re.compile(r"(\d+)(?!.*\d)")


class AlignmentError(UserError, ValueError):
    """Correspondences cannot determine the requested transform."""


def umeyama(
    src: Float[np.ndarray, "N 3"], dst: Float[np.ndarray, "N 3"], mode: Literal["sim3", "rigid"] = "sim3"
) -> Tuple[float, Float[np.ndarray, "3 3"], Float[np.ndarray, "3"], float]:
    """Least-squares ``(s, R, t)`` with ``dst ~= s * R @ src + t`` and the residual RMS (dst units).

    ``R`` is a proper rotation (reflection fixed via the sign of ``det``); ``s = 1`` for ``rigid``.
    Raises ``AlignmentError`` for < 3 pairs, coincident or collinear points.
    """
    if mode not in ("sim3", "rigid"):
        raise AlignmentError(f"mode must be 'sim3' or 'rigid', got {mode!r}")
    src = np.asarray(src, dtype=np.float64).reshape(-1, 3)
    dst = np.asarray(dst, dtype=np.float64).reshape(-1, 3)
    if src.shape != dst.shape:
        raise AlignmentError(f"src has {len(src)} points but dst has {len(dst)}")
    n = src.shape[0]
    if n < 3:
        raise AlignmentError(f"{mode} alignment needs >= 3 correspondences, got {n}")
    if not (np.isfinite(src).all() and np.isfinite(dst).all()):
        raise AlignmentError("correspondences contain non-finite coordinates")
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    xs, xd = src - mu_s, dst - mu_d
    for name, pts, x in (("source", src, xs), ("destination", dst, xd)):
        sv = np.linalg.svd(x, compute_uv=False)
        if sv[0] <= 1e-12 * max(1.0, float(np.abs(pts).max())) * np.sqrt(n):
            raise AlignmentError(f"{name} points are coincident (zero variance)")
        if sv[1] <= 1e-9 * sv[0]:
            raise AlignmentError(f"{name} points are collinear (rank < 2)")
    cov = xd.T @ xs / n
    u, d, vt = np.linalg.svd(cov)
    sign = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2] = -1.0
    r = (u * sign) @ vt
    s = float((d * sign).sum() / (xs * xs).sum() * n) if mode == "sim3" else 1.0
    t = mu_d - s * r @ mu_s
    rms = float(np.sqrt(((apply_sim3(s, r, t, src) - dst) ** 2).sum(axis=1).mean()))
    return s, r, t, rms


def apply_sim3(
    s: float, R: Float[np.ndarray, "3 3"], t: Float[np.ndarray, "3"], xyz: Float[np.ndarray, "N 3"]
) -> Float[np.ndarray, "N 3"]:
    """``s * R @ p + t`` for every row ``p`` of ``xyz``."""
    return s * np.asarray(xyz, dtype=np.float64) @ np.asarray(R).T + np.asarray(t)


def _key_exact(name: str) -> Optional[str]:
    return PurePath(name).name.lower()


def _key_stem(name: str) -> Optional[str]:
    return _SUFFIX.sub("", PurePath(name).stem.lower())


def _key_int(name: str) -> Optional[str]:
    m = _LAST_INT.search(PurePath(name).stem)
    return str(int(m.group(1))) if m else None


def _unique_index(names: Sequence[str], rule: Callable[[str], Optional[str]], free: set) -> Dict[str, int]:
    """Key -> index over the indices in ``free``, keeping only keys produced by exactly one of them."""
    seen: Dict[str, List[int]] = {}
    for i in sorted(free):
        k = rule(names[i])
        if k is not None:
            seen.setdefault(k, []).append(i)
    return {k: v[0] for k, v in seen.items() if len(v) == 1}


def match_names(src_names: Sequence[str], dst_names: Sequence[str]) -> List[Tuple[int, int]]:
    """Pair names ``(i, j)`` by rule priority: case-insensitive file name, then stem without an
    ``_enhanced``/``_image``/``_img`` suffix, then the last integer in the stem. A rule uses only
    keys unique on both sides among still-unmatched names; each name is matched at most once.
    """
    free_s, free_d = set(range(len(src_names))), set(range(len(dst_names)))
    pairs: List[Tuple[int, int]] = []
    for rule in (_key_exact, _key_stem, _key_int):
        ks = _unique_index(src_names, rule, free_s)
        kd = _unique_index(dst_names, rule, free_d)
        for k, i in ks.items():
            j = kd.get(k)
            if j is not None:
                pairs.append((i, j))
                free_s.discard(i)
                free_d.discard(j)
    return sorted(pairs)
