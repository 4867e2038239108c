"""The plugin's on-disk cache: where it lives and the content key of a cached image.

Writes into it go through :func:`naka_gs_plugin.data.safe_io.atomic_write` (a crash never leaves a
half-written entry under its final name).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np
from torch import Tensor

from naka_gs_plugin.data.safe_io import usable_cache_dir


def default_cache_dir() -> Path:
    """``$NAKA_GS_CACHE``, else ``$XDG_CACHE_HOME/naka-gs``, else ``~/.cache/naka-gs``; when that
    cannot be written (read-only, a file, disk full) a private temporary folder, with one warning."""
    if os.environ.get("NAKA_GS_CACHE"):
        return usable_cache_dir(Path(os.environ["NAKA_GS_CACHE"]))
    return usable_cache_dir(Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "naka-gs")


def content_hash(image: Tensor) -> str:
    """SHA-1 of an image tensor's shape, dtype and bytes."""
    arr = np.ascontiguousarray(image.detach().cpu().numpy())
    h = hashlib.sha1(f"{arr.shape}{arr.dtype}".encode())
    h.update(arr.tobytes())
    return h.hexdigest()
