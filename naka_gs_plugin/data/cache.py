"""The plugin's on-disk cache: where it lives, the content key of a cached image, and its entries' checksums.

Writes into it go through :func:`naka_gs_plugin.data.safe_io.atomic_write` (a crash never leaves a
half-written entry under its final name). Each entry's checksum is recorded when it is written (:func:`seal`,
under ``<cache>/checksums/``, so that the entry folders hold entries only) and checked when it is read
(:func:`read_sealed`): an entry edited, zeroed or damaged since, one without a checksum (an older naka-gs
wrote it), or one that is not a regular file, is recomputed instead of being used. The checksum is a sha256 of
the entry's key (its path in the cache) and its bytes (:func:`entry_digest`): it proves the entry unchanged *and*
written under that key, so two entries swapped together with their checksum files are recomputed too.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Optional, Tuple

import numpy as np
from torch import Tensor

from naka_gs_plugin.data import safe_io
from naka_gs_plugin.data.safe_io import InputFileError, atomic_write_bytes, read_regular, usable_cache_dir

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


def entry_key(entry: Path) -> str:
    """The key a cache file is stored under: its path in the cache folder (``enhanced/<key>.npy``), or its name
    outside one. It stays the same when the whole cache folder is moved or copied."""
    entry = Path(entry)
    root = cache_root_of(entry)
    return entry.name if root is None else entry.absolute().relative_to(root).as_posix()


def entry_digest(entry: Path, data: bytes) -> str:
    """The checksum :func:`seal` records for the bytes ``data`` of the cache file ``entry``: the sha256 of its key
    (:func:`entry_key`) and its bytes. The key is in it so that an entry moved under another key (two entries swapped
    together with their checksum files) does not match: a checksum of the bytes alone proves them unchanged, not that
    they belong to the key they are read for."""
    digest = hashlib.sha256(f"naka-gs cache entry {entry_key(entry)}\n".encode())
    digest.update(data)
    return digest.hexdigest()


def seal(entry: Path) -> None:
    """Record the checksum (:func:`entry_digest`) of the cache file just written at ``entry`` (atomically), for
    :func:`read_sealed`. Raises OSError when it cannot be written (the entry is then unsealed: recomputed when next
    read)."""
    digest = entry_digest(entry, Path(entry).read_bytes())
    target = checksum_path(entry)
    target.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(target, digest.encode())


def read_sealed(entry: Path) -> Tuple[Optional[bytes], str]:
    """The bytes of the cache file ``entry`` and ``""`` when they match the checksum :func:`seal` recorded for its key;
    else ``None`` and why it cannot be used (``""`` for a missing entry: a plain miss). The caller recomputes it.
    Only regular files are read (a FIFO or a device put in the cache is recomputed, never waited on)."""
    try:
        data = read_regular(entry)
    except FileNotFoundError:
        return None, ""
    except InputFileError as err:
        return None, err.problem
    except OSError as err:
        return None, f"cannot be read ({err.strerror or err})"
    try:
        recorded = read_regular(checksum_path(entry)).decode("ascii").strip()
    except FileNotFoundError:
        return None, "has no checksum (an older naka-gs wrote it, or it was copied in)"
    except (OSError, ValueError):  # InputFileError and UnicodeDecodeError are ValueErrors
        return None, "has an unreadable checksum"
    # A checksum file of a naka-gs older than the key-bound checksums holds the sha256 of the bytes alone: it does not
    # match here, so such an entry is recomputed once (with this warning) and sealed the new way.
    if entry_digest(entry, data) != recorded:
        return None, "does not match its checksum (edited or damaged since it was written)"
    return data, ""
