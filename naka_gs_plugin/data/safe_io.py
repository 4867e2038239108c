"""Writing files without ever losing the user's: atomic writes, staged folders, ownership markers.

* Every file write goes to a unique temporary name in the target's folder (pid + random token, so
  concurrent runs never share one), is checked, and is published with :func:`os.replace`: a
  reader sees the old file or the complete new one, never a partial one.
* Output folders are built in a hidden sibling staging folder and published by rename. Each
  folder we publish holds :data:`MARKER`, a json listing every file we wrote; a folder is only
  ever replaced when that marker exists and the folder holds nothing else.
* Output folders are refused when they equal, contain or lie inside an input.
* A cache directory that cannot be written falls back to a private temporary one, with one warning;
  it is removed when the process exits.
"""

from __future__ import annotations

import atexit
import json
import os
import secrets
import shutil
import tempfile
from pathlib import Path
from typing import Callable, Dict, Iterable, List, Optional

from nerfstudio.utils.rich_utils import CONSOLE

MARKER = ".naka-gs-output"
"""File naming the tool that wrote a folder and every file it wrote (paths relative to the folder)."""


class UnsafeOutputError(ValueError):
    """An output location that would overwrite or delete something we did not write; one line."""


def unique_name(path: Path, tag: str) -> Path:
    """A hidden sibling of ``path`` no other process picks: ``.NAME.TAG-PID-RANDOM``."""
    return path.parent / f".{path.name}.{tag}-{os.getpid()}-{secrets.token_hex(4)}"


def atomic_write(path: Path, write: Callable[[Path], object]) -> Path:
    """Publish ``path`` by writing a unique temporary sibling with ``write(tmp)`` and renaming it.

    ``write`` may return ``False`` (as ``cv2.imwrite`` does) to report failure; that, an exception,
    or an empty result raises :class:`OSError` and leaves ``path`` untouched.
    """
    # Same folder (rename stays atomic); the real suffix last, since it picks the encoder (cv2, np.save).
    tmp = path.parent / f".{path.stem}.tmp-{os.getpid()}-{secrets.token_hex(4)}{path.suffix}"
    try:
        ok = write(tmp)
        if ok is False or not tmp.is_file() or tmp.stat().st_size == 0:
            raise OSError(f"{path}: write failed (disk full or not writable?)")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def atomic_write_bytes(path: Path, data: bytes) -> Path:
    """:func:`atomic_write` of a byte string."""
    return atomic_write(path, lambda tmp: tmp.write_bytes(data))


def _is_within(inner: Path, outer: Path) -> bool:
    return inner == outer or outer in inner.parents


def check_not_input(out: Path, inputs: Iterable[Path], option: str) -> None:
    """Refuse an output folder equal to, inside, or a parent of any input (files or folders)."""
    out_r = out.resolve()
    for item in inputs:
        item_r = item.resolve()
        if _is_within(out_r, item_r) or _is_within(item_r, out_r):
            relation = "is" if out_r == item_r else ("is inside" if _is_within(out_r, item_r) else "contains")
            raise UnsafeOutputError(
                f"{option} {out}: {relation} the input {item} -- choose an output folder outside the input"
            )


def written_files(folder: Path) -> Optional[List[str]]:
    """Files our marker in ``folder`` lists (relative paths), or None when there is no valid marker."""
    try:
        meta = json.loads((folder / MARKER).read_text())
        files = meta["files"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return [str(f) for f in files] if isinstance(files, list) else None


def foreign_files(folder: Path) -> List[str]:
    """Files (and empty folders) under ``folder`` that our marker does not list; all of them without one."""
    ours = set(written_files(folder) or [])
    found = []
    for path in sorted(folder.rglob("*")):
        rel = path.relative_to(folder).as_posix()
        if rel == MARKER or rel in ours:
            continue
        if path.is_dir() and not path.is_symlink():
            if any(path.iterdir()):
                continue  # judged by its contents
        found.append(rel)
    return found


def check_replaceable(out: Path, option: str, overwrite: Optional[bool]) -> None:
    """Refuse ``out`` unless it is absent, empty, or (``overwrite`` True or None = no flag) ours alone.

    ``overwrite=None`` is for commands without ``--overwrite``: they replace their own earlier
    output silently but nothing else. The message names the first foreign file.
    """
    if not out.exists() and not out.is_symlink():
        return
    if not out.is_dir() or out.is_symlink():
        raise UnsafeOutputError(f"{option} {out}: exists and is not a folder -- choose another {option}")
    if not any(out.iterdir()):
        return
    if overwrite is False:
        raise UnsafeOutputError(
            f"{option} {out}: already exists and is not empty -- choose another {option} or --overwrite"
        )
    if written_files(out) is None:
        raise UnsafeOutputError(
            f"{option} {out}: not empty and not written by naka-gs (no {MARKER} marker), so it is never "
            f"replaced -- choose a new or empty {option}"
        )
    extra = foreign_files(out)
    if extra:
        raise UnsafeOutputError(
            f"{option} {out}: holds {extra[0]}"
            + (f" and {len(extra) - 1} more" if len(extra) > 1 else "")
            + f", which naka-gs did not write -- move it out or choose another {option}"
        )


def check_new_files(folder: Path, names: Iterable[str], option: str, fix: str) -> None:
    """Refuse ``folder`` when it is a file, or holds one of ``names``: for a program that writes those files into
    it without a check of its own (nerfstudio's ``ns-export``). ``fix`` names the other choices."""
    if folder.exists() and not folder.is_dir():
        raise UnsafeOutputError(f"{option} {folder}: exists and is not a folder -- choose another {option}")
    for name in names:
        if (folder / name).exists() or (folder / name).is_symlink():
            raise UnsafeOutputError(
                f"{option} {folder}: already holds {name}, which would be replaced -- move it away, or {fix}"
            )


def staging_dir(out: Path) -> Path:
    """A new, empty hidden sibling of ``out`` to build it in (see :func:`publish_dir`)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    stage = unique_name(out, "partial")
    stage.mkdir()
    return stage


def write_marker(folder: Path, tool: str, extra: Optional[Dict[str, object]] = None) -> None:
    """Record ``tool`` and every file now under ``folder`` in its :data:`MARKER`."""
    files = sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file() and p.name != MARKER)
    atomic_write_bytes(folder / MARKER, json.dumps({"tool": tool, "files": files, **(extra or {})}, indent=1).encode())


def publish_dir(stage: Path, out: Path, tool: str, option: str, overwrite: Optional[bool]) -> None:
    """Move the finished ``stage`` to ``out``, replacing an old ``out`` only if it is ours alone.

    The check is repeated here (the folder may have changed while we worked). The old folder is
    renamed aside first and put back if the final rename fails.
    """
    write_marker(stage, tool)
    check_replaceable(out, option, overwrite)
    trash = None
    if out.exists():
        trash = unique_name(out, "old")
        os.replace(out, trash)
    try:
        os.replace(stage, out)
    except OSError:
        if trash is not None:
            os.replace(trash, out)
        raise
    if trash is not None:
        shutil.rmtree(trash, ignore_errors=True)


_fallback: Dict[Path, Path] = {}


def _remove_fallback(folder: Path, pid: int) -> None:
    """Remove a fallback cache when the process that made it exits (not a forked child of it)."""
    if os.getpid() == pid:
        shutil.rmtree(folder, ignore_errors=True)


def usable_cache_dir(preferred: Path) -> Path:
    """``preferred`` if a file can be created in it, else a private temporary folder (warned once).

    Covers a read-only cache, a full disk and ``$NAKA_GS_CACHE`` naming a file.
    """
    if preferred in _fallback:
        return _fallback[preferred]
    try:
        preferred.mkdir(parents=True, exist_ok=True)
        probe = unique_name(preferred / "probe", "tmp")
        probe.write_bytes(b"ok")
        probe.unlink()
        return preferred
    except OSError as err:
        fallback = Path(tempfile.mkdtemp(prefix="naka-gs-cache-"))
        _fallback[preferred] = fallback
        atexit.register(_remove_fallback, fallback, os.getpid())
        CONSOLE.log(
            f"[naka-gs] warning: cache {preferred} is not writable ({err.strerror or err}); using {fallback} for "
            "this run -- set NAKA_GS_CACHE to a writable folder to keep the cache between runs",
            markup=False,
        )
        return fallback
