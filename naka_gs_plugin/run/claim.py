"""A run folder's claim: one ``ns-train`` writes a run folder, and two started together never share one.

The claim is a small JSON file (:data:`RUN_CLAIM`: pid, host, a random token) created exclusively before anything else
is written to the folder and removed when the training ends; one left by a process that no longer exists is taken
over with one line.
"""

from __future__ import annotations

import atexit
import json
import os
import secrets
import socket
import stat
import time
from pathlib import Path
from typing import Optional, Sequence, Set

from nerfstudio.utils.rich_utils import CONSOLE

RUN_CLAIM = ".naka-gs-run"
"""A run folder's claim: made with an exclusive create before anything else is written to the folder, holding the
pid, host and a random token of the ns-train that writes it; removed when that training ends."""
_LIVE_CLAIMS: Set[str] = set()
"""Tokens of the claims this process holds (a claim copied along with a run folder is not one of them)."""


KINDS = {stat.S_IFDIR: "a folder", stat.S_IFIFO: "a FIFO", stat.S_IFSOCK: "a socket", stat.S_IFCHR: "a device",
         stat.S_IFBLK: "a device", stat.S_IFLNK: "a symbolic link"}  # fmt: skip


def _not_a_claim_file(claim: Path) -> Optional[str]:
    """What ``claim`` is when it exists and is not a regular file (we only ever write regular files), else None."""
    try:
        mode = os.lstat(claim).st_mode
    except OSError:
        return None
    return None if stat.S_ISREG(mode) else KINDS.get(stat.S_IFMT(mode), "not a regular file")


def _claim_holder(claim: Path) -> Optional[dict]:
    """The claim's record, or None when it is not one (unreadable, or cut short by a crash mid-write). Opened
    without blocking and read only as a regular file: a FIFO in its place would block the training forever."""
    try:
        fd = os.open(claim, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOFOLLOW", 0))
        with os.fdopen(fd, "rb") as fh:
            if not stat.S_ISREG(os.fstat(fh.fileno()).st_mode):
                return None
            record = json.loads(fh.read(1 << 16).decode("utf-8"))
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) else None


def _claim_is_live(record: Optional[dict]) -> bool:
    """Whether the process that wrote ``record`` may still be writing the folder: on this host, a process with its
    pid exists (its own token, for this process); on another host, always (its processes cannot be seen)."""
    if record is None:
        return False
    if record.get("host") != socket.gethostname():
        return True
    pid = record.get("pid")
    if not isinstance(pid, int) or pid <= 0:
        return False
    if pid == os.getpid():
        return record.get("token") in _LIVE_CLAIMS
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # exists, owned by another user
        return True
    return True


def _publish_exclusive(path: Path, text: str) -> None:
    """Create ``path`` holding ``text``, or raise FileExistsError when it exists: written under a unique name and
    hard-linked into place, so that no reader ever sees it empty or half written."""
    tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}-{secrets.token_hex(4)}")
    tmp.write_text(text, encoding="utf-8")
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise
    except OSError:  # a file system without hard links: an exclusive create, then the write
        with open(path, "x", encoding="utf-8") as fh:
            fh.write(text)
    finally:
        tmp.unlink(missing_ok=True)


def claim_run_folder(run: Path) -> str:
    """Claim the existing folder ``run`` for this process with an exclusive create of its :data:`RUN_CLAIM`; returns
    the claim's token. The check that a folder is free and taking it are one step, so of two ``ns-train`` started
    together into one folder exactly one gets it; the other ends with one line. A claim left by a run that died
    without releasing it (a crash, ``kill -9``; its pid no longer exists on this host) is taken over, with one line.
    Removed by :func:`release_run_folder` (at the latest when this process exits)."""
    claim = run / RUN_CLAIM
    token = secrets.token_hex(8)
    record = {"pid": os.getpid(), "host": socket.gethostname(), "token": token, "started": time.time()}
    for _ in range(3):  # a stale claim moved aside can be taken by another process first: look again
        try:
            _publish_exclusive(claim, json.dumps(record))
        except FileExistsError:
            kind = _not_a_claim_file(claim)
            if kind is not None:
                raise SystemExit(
                    f"naka-gs: {claim} is {kind}, not a run claim (naka-gs only ever writes a small file there) -- "
                    "move it out of the run folder, or pick another --timestamp or --output-dir"
                ) from None
            held = _claim_holder(claim)
            if _claim_is_live(held):
                pid, host = held.get("pid"), held.get("host")  # type: ignore[union-attr]
                raise SystemExit(
                    f"naka-gs: {run} is claimed by another training (pid {pid} on {host}, its {RUN_CLAIM}); pick "
                    f"another --timestamp or --output-dir -- if no ns-train is writing there any more, delete {claim}"
                ) from None
            _take_over(claim, held)
            continue
        _LIVE_CLAIMS.add(token)
        atexit.register(release_run_folder, claim, token)
        return token
    raise SystemExit(f"naka-gs: {run}: other trainings keep claiming it; pick another --timestamp or --output-dir")


def _take_over(claim: Path, held: Optional[dict]) -> None:
    """Remove a stale claim, with one line; moved aside first, so that of two processes taking it over one does."""
    aside = claim.with_name(f"{RUN_CLAIM}.stale-{os.getpid()}-{secrets.token_hex(4)}")
    try:
        os.rename(claim, aside)
    except FileNotFoundError:
        return  # another process took it over first
    if _claim_is_live(_claim_holder(aside)):  # a fresh claim replaced the stale one meanwhile: give it back
        try:
            os.link(aside, claim)
        except FileExistsError:
            pass
        aside.unlink(missing_ok=True)
        return
    aside.unlink(missing_ok=True)
    who = f"pid {held.get('pid')}, no longer running" if held is not None else "its claim file was unreadable"
    CONSOLE.print(
        f"naka-gs: {claim.parent}: taking over the claim of a training that ended without releasing it ({who})",
        markup=False,
        soft_wrap=True,
    )


def give_up_run_folder(run: Path, token: Optional[str], created: Sequence[Path]) -> None:
    """Release the claim ``token`` of ``run`` (if any); when this run created the folder (``created``, deepest first),
    remove the config.yml it wrote (only while it held the claim) and those folders again, unless one holds anything
    else."""
    if created and token is not None:
        (run / "config.yml").unlink(missing_ok=True)
    if token is not None:
        release_run_folder(run / RUN_CLAIM, token)
    for folder in created:
        try:
            folder.rmdir()
        except OSError:
            return


def release_run_folder(claim: Path, token: str) -> None:
    """Remove ``claim`` if it is still the one this process made with ``token``."""
    if token not in _LIVE_CLAIMS:
        return
    _LIVE_CLAIMS.discard(token)
    held = _claim_holder(claim)
    if held is not None and held.get("token") == token:
        claim.unlink(missing_ok=True)
