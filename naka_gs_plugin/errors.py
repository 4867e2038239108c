"""The plugin's errors a user can fix, and the one line they end a command with.

A leaf module (it imports nothing of the plugin), so the data layer, the trainer and the console scripts can all
use it, and ``requirements.py`` before torch is imported.
"""

from __future__ import annotations

import errno
from typing import Optional


class UserError(Exception):
    """Base class of the plugin's exceptions for a problem the user can fix (a bad file, an option out of range):
    each message is one line naming the file or option and the fix. A command ends on one with the line
    ``naka-gs: <message>`` (exit status 1, no traceback); any other exception is a bug and keeps its traceback.
    Subclasses keep the builtin base that callers catch (``class ImageReadError(UserError, ValueError)``).
    tests/run/test_run_folder.py checks that every ``*Error`` class of the package is one, or a ``SystemExit``."""


def signal_exit_status(signum: int) -> int:
    """The exit status of a command that ``signum`` stopped: 128 + its number, as shells report a command the signal
    killed (130 for Ctrl-C, 143 for SIGTERM), also when the command cleaned up and exited by itself."""
    return 128 + int(signum)


def is_user_error(err: BaseException) -> bool:
    """Whether ``err`` is a :class:`UserError`."""
    return isinstance(err, UserError)


def user_error_exit(err: BaseException) -> Optional[SystemExit]:
    """``SystemExit("naka-gs: <message>")`` (exit status 1, no traceback) for a :class:`UserError`, else None: any
    other exception is a bug and keeps its traceback. A message of several lines (one per bad item) gets the prefix
    on each."""
    if not is_user_error(err):
        return None
    return SystemExit("\n".join(f"naka-gs: {line}" for line in (str(err) or type(err).__name__).splitlines()))


OS_ERROR_FIXES = {
    errno.ENOENT: "check the path (a missing input, or a folder that is not there)",
    errno.EACCES: "check its permissions, or choose a path you may use",
    errno.EPERM: "check its permissions, or choose a path you may use",
    errno.EROFS: "that file system is read-only: choose a writable place",
    errno.ENOSPC: "free disk space there, or choose a place with room",
    errno.EDQUOT: "free disk space there (your quota is used up), or choose a place with room",
    errno.ENOTDIR: "a part of the path is a file, not a folder: choose another path",
    errno.EEXIST: "something is in the way: move it, or choose another path",
    errno.EISDIR: "it is a folder: pass a file",
    errno.ENAMETOOLONG: "choose a shorter path",
    errno.ELOOP: "a symbolic link there leads back to itself: fix the link",
    errno.EIO: "free disk space there or choose a writable place, and check the disk",
}
"""What to do about an :class:`OSError` a command met, by its ``errno``."""


def os_error_exit(err: OSError) -> SystemExit:
    """The one line a command ends with when the operating system refused it a file: ``naka-gs: <path>: <reason> --
    <fix>`` (exit status 1), e.g. a missing input or an output where a file is in the way. Without a path (an
    ``OSError`` of a message only, the path in it) the message stands for both."""
    reason = err.strerror or str(err) or type(err).__name__
    fix = OS_ERROR_FIXES.get(err.errno) if err.errno is not None else None
    where = f"{err.filename}: " if err.filename is not None else ""
    line = f"naka-gs: {where}{reason}" + (f" -- {fix}" if fix and " -- " not in reason else "")
    return SystemExit(" ".join(line.split("\n")))
