"""The plugin's on-disk cache: where it lives and the content key of a cached image.

Writes into it go through :func:`naka_gs_plugin.data.safe_io.atomic_write` (a crash never leaves a
half-written entry under its final name).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Optional

import numpy as np
from torch import Tensor

from naka_gs_plugin.data import safe_io
from naka_gs_plugin.data.safe_io import usable_cache_dir


def preferred_cache_dir() -> Path:
    """``$NAKA_GS_CACHE``, else ``$XDG_CACHE_HOME/naka-gs``, else ``~/.cache/naka-gs`` (not checked)."""
    if os.environ.get("NAKA_GS_CACHE"):
        return Path(os.environ["NAKA_GS_CACHE"])
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "naka-gs"


def default_cache_dir() -> Path:
    """:func:`preferred_cache_dir`; when that cannot be written (read-only, a file, disk full) a
    private temporary folder, with one warning."""
    return usable_cache_dir(preferred_cache_dir())


def cache_root_of(path: Path) -> Optional[Path]:
    """The cache folder (preferred or this run's fallback) holding ``path``, or None: a file of ours,
    not the user's. Creates and probes nothing."""
    target = Path(path).absolute()
    for root in (preferred_cache_dir(), *safe_io._fallback.values()):
        root = root.absolute()
        if root == target or root in target.parents:
            return root
    return None


def content_hash(image: Tensor) -> str:
    """SHA-1 of an image tensor's shape, dtype and bytes."""
    arr = np.ascontiguousarray(image.detach().cpu().numpy())
    h = hashlib.sha1(f"{arr.shape}{arr.dtype}".encode())
    h.update(arr.tobytes())
    return h.hexdigest()
