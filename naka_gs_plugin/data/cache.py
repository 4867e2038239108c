"""The plugin's on-disk cache: where it lives, the content key of a cached image, and its entries' checksums.

Writes into it go through :func:`naka_gs_plugin.data.safe_io.atomic_write` (a crash never leaves a
half-written entry under its final name). Each entry's sha256 is recorded when it is written (:func:`seal`,
under ``<cache>/checksums/``, so that the entry folders hold entries only) and checked when it is read
(:func:`read_sealed`): an entry edited, zeroed or damaged since, or one without a checksum (an older naka-gs
wrote it), is recomputed instead of being used.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Optional, Tuple

import numpy as np
from torch import Tensor

from naka_gs_plugin.data import safe_io
from naka_gs_plugin.data.safe_io import atomic_write_bytes, usable_cache_dir

CHECKSUMS = "checksums"
"""The cache's folder of entry checksums: ``<cache>/checksums/<entry's path in the cache>.sha256``."""


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


def checksum_path(entry: Path) -> Path:
    """Where the checksum of the cache file ``entry`` is kept (beside it when it is not in a cache folder)."""
    entry = Path(entry)
    root = cache_root_of(entry)
    if root is None:
        return entry.with_name(entry.name + ".sha256")
    return root / CHECKSUMS / f"{entry.absolute().relative_to(root)}.sha256"


def seal(entry: Path) -> None:
    """Record the sha256 of the cache file just written at ``entry`` (atomically), for :func:`read_sealed`.
    Raises OSError when it cannot be written (the entry is then unsealed: recomputed when next read)."""
    digest = hashlib.sha256(Path(entry).read_bytes()).hexdigest()
    target = checksum_path(entry)
    target.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(target, digest.encode())


def read_sealed(entry: Path) -> Tuple[Optional[bytes], str]:
    """The bytes of the cache file ``entry`` and ``""`` when they match the checksum :func:`seal` recorded; else
    ``None`` and why it cannot be used (``""`` for a missing entry: a plain miss). The caller recomputes it."""
    try:
        data = Path(entry).read_bytes()
    except FileNotFoundError:
        return None, ""
    except OSError as err:
        return None, f"cannot be read ({err.strerror or err})"
    try:
        recorded = checksum_path(entry).read_text(encoding="ascii").strip()
    except FileNotFoundError:
        return None, "has no checksum (an older naka-gs wrote it, or it was copied in)"
    except (OSError, ValueError):
        return None, "has an unreadable checksum"
    if hashlib.sha256(data).hexdigest() != recorded:
        return None, "does not match its checksum (edited or damaged since it was written)"
    return data, ""
