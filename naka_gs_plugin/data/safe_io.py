"""Writing files without ever losing the user's: atomic writes, staged folders, ownership markers.

* Every file write goes to a unique temporary name in the target's folder (pid + random token, so
  concurrent runs never share one), is checked, and is published with :func:`os.replace`: a
  reader sees the old file or the complete new one, never a partial one.
* Every command's output (a folder, or a file) goes through :func:`staged_output`: refused when it equals,
  contains or lies inside an input, or would replace something we did not write; built in a hidden ``.partial``
  sibling folder; published by rename; the partial output removed on an exception, Ctrl-C or SIGTERM. Each
  folder we publish holds :data:`MARKER`, a json listing every file we wrote; a folder is only ever replaced when
  that marker exists and the folder holds nothing else.
* A cache directory that cannot be written falls back to a private temporary one, with one warning;
  it is removed when the process exits.
* Ctrl-C or SIGTERM while a staged output is built removes it, says so in one line (``naka-gs: Ctrl-C: stopped;
  ...`` on stderr) and exits 130 / 143 (:class:`RemovedOnStop`), even in the middle of a long native call.
* Every input file is read only when it is a regular file (:func:`regular_file`, :func:`open_regular`,
  :func:`read_regular`): a FIFO, a device or a socket (``file_path: /dev/zero``) is refused in one line before it is
  opened, so a read never blocks or runs forever; so is a path longer than the system allows.

Imports without nerfstudio (the image reader uses it on the GPU machine): its console is imported where it logs.
"""

from __future__ import annotations

import atexit
import contextlib
import errno
import json
import os
import secrets
import shutil
import signal
import stat
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import BinaryIO, Callable, Dict, Iterable, Iterator, List, NamedTuple, Optional, Union

from naka_gs_plugin.errors import UserError, signal_exit_status

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)

MARKER = ".naka-gs-output"
"""File naming the tool that wrote a folder and every file it wrote (paths relative to the folder)."""


class UnsafeOutputError(UserError, ValueError):
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
        meta = json.loads(read_regular(folder / MARKER))  # a FIFO there: no marker, never waited on
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


def check_parent_folder(out: Path, option: str) -> None:
    """Refuse ``out`` when the nearest existing path above it is not a folder (``notes.txt/out``): nothing can be
    made there."""
    for parent in out.parents:
        if parent.exists() or parent.is_symlink():
            if not parent.is_dir():
                raise UnsafeOutputError(f"{option} {out}: {parent} is not a folder -- choose another {option}")
            return


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


class RemovedOnStop:
    """While ``stage`` (the staging folder of ``out``, :func:`staged_output`) is built: Ctrl-C or SIGTERM removes it,
    prints one line ``naka-gs: <signal>: stopped; ...`` on stderr and exits 130 / 143 at once; ``out`` is left as it
    was.

    The work may sit in one native call for minutes (pycolmap's matching), and Python runs signal handlers only in
    the main thread, between bytecodes: a handler would run only once that call returned. So the signal is read from
    Python's wakeup file descriptor by a thread of ours, which does not wait for the main thread: it removes the stage
    and ends the process (``os._exit``). The main thread, should it run Python meanwhile, waits in its handler.
    :meth:`publishing` holds off the stop while ``out`` is replaced, so that ``out`` is complete or untouched. Outside
    the main thread (where no handler can be set) and for a signal ignored by the caller (``nohup``) it does nothing.
    """

    def __init__(self, stage: Path, out: Path) -> None:
        self.stage, self.out = stage, out
        self._existed = out.exists()
        self._lock = threading.Lock()
        self._publishing = False
        self._previous: Dict[int, object] = {}
        self._pipe: Optional[tuple] = None
        self._old_wakeup = -1
        self._thread: Optional[threading.Thread] = None

    def __enter__(self) -> "RemovedOnStop":
        if threading.current_thread() is not threading.main_thread():
            return self
        read, write = os.pipe()
        os.set_blocking(write, False)  # required of a wakeup fd
        self._pipe = (read, write)
        for signum in STOP_SIGNALS:
            if signal.getsignal(signum) != signal.SIG_IGN:
                self._previous[signum] = signal.signal(signum, self._hold)
        self._old_wakeup = signal.set_wakeup_fd(write, warn_on_full_buffer=False)
        self._thread = threading.Thread(target=self._watch, args=(read,), name="naka-gs-stop", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._pipe is None:
            return
        signal.set_wakeup_fd(self._old_wakeup)
        for signum, previous in self._previous.items():
            signal.signal(signum, previous if previous is not None else signal.SIG_DFL)  # type: ignore[arg-type]
        read, write = self._pipe
        os.close(write)  # the watcher reads end-of-file and returns
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        os.close(read)
        self._pipe, self._previous = None, {}

    @contextlib.contextmanager
    def publishing(self) -> Iterator[None]:
        """A stop that comes while the body runs waits for it to finish (``out`` is replaced then)."""
        with self._lock:
            self._publishing = True
            try:
                yield
            finally:
                self._publishing = False

    def _hold(self, signum: int, frame: object) -> None:
        # The watcher thread handles the stop; the main thread only stops doing work (unless it is publishing, which
        # the watcher waits for).
        if self._publishing:
            return
        while True:
            time.sleep(60.0)

    def _watch(self, read: int) -> None:
        while True:
            try:
                data = os.read(read, 64)
            except OSError:
                return
            if not data:
                return
            for signum in data:
                if signum in self._previous:
                    self._stop(signum)

    def _stop(self, signum: int) -> None:
        with self._lock:
            name = "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name
            if self.stage.exists():
                shutil.rmtree(self.stage, ignore_errors=True)
                kept = "was left as it was" if self._existed else "was not created"
                what = f"its unfinished output was removed and {self.out} {kept}; run it again to make it"
            else:
                what = f"{self.out} was complete already"
            line = f"naka-gs: {name}: stopped; {what}\n"
            try:
                # Not through the console: the main thread may be waiting in _hold holding its lock (a signal handler
                # runs between any two bytecodes). A progress bar hides the cursor on a terminal: show it again.
                with contextlib.suppress(Exception):
                    sys.stdout.flush()
                    if sys.stdout.isatty():
                        os.write(sys.stdout.fileno(), b"\x1b[?25h\n")
                os.write(sys.stderr.fileno(), line.encode())
            finally:
                os._exit(signal_exit_status(signum))


class OutputFile(NamedTuple):
    """An output that is one file, for :func:`staged_output`: what it is in words (``"a camera profile"``), and whether
    an existing file at its path is one (only then is it replaced)."""

    kind: str
    is_one: Callable[[Path], bool]


def _check_file_replaceable(out: Path, option: str, file: OutputFile) -> None:
    if (out.exists() or out.is_symlink()) and not (out.is_file() and file.is_one(out)):
        raise UnsafeOutputError(
            f"{option} {out} exists and is not {file.kind} -- choose another path (it is not replaced)"
        )


@contextlib.contextmanager
def staged_output(
    out: Path,
    *,
    tool: str,
    what: str = "--out",
    inputs: Iterable[Path] = (),
    overwrite: Optional[bool] = None,
    file: Optional[OutputFile] = None,
) -> Iterator[Path]:
    """Build a command's output ``out`` (its option ``what``) in a staging folder and publish it whole, or not at all.

    First ``out`` is checked: not equal to, inside or containing one of ``inputs`` (files or folders), not under a
    file, and replaceable: absent, an empty folder or a folder ``tool``-like commands wrote holding nothing else
    (:func:`check_replaceable` with ``overwrite``: None for commands without ``--overwrite``); with ``file``, absent or
    a file of that kind. Then it yields a new hidden sibling folder ``.<name>.partial-<pid>-<random>`` to write into:
    the folder ``out`` becomes, or with ``file`` one holding ``out.name`` and any files to publish beside it. When the
    body returns, the check is repeated and the output is published by rename (:func:`publish_dir`, which adds the
    :data:`MARKER`; files one by one, ``out`` last). An exception in the body, Ctrl-C or SIGTERM
    (:class:`RemovedOnStop`: one line, exit 130 / 143) removes the stage and leaves ``out`` as it was.
    """
    check_not_input(out, inputs, what)
    check_parent_folder(out, what)
    if file is None:
        check_replaceable(out, what, overwrite)
    else:
        _check_file_replaceable(out, what, file)
    target = out.resolve()
    target.parent.mkdir(parents=True, exist_ok=True)
    stage = unique_name(target, "partial")
    try:
        stage.mkdir()
    except OSError as err:  # the stage's hidden name means nothing to the user; the folder it is made in does
        raise type(err)(err.errno, err.strerror, str(target.parent)) from None
    try:
        with RemovedOnStop(stage, target) as stop:
            yield stage
            with stop.publishing():
                if file is None:
                    publish_dir(stage, target, tool, what, overwrite)
                else:
                    _check_file_replaceable(out, what, file)
                    for name in sorted((p.name for p in stage.iterdir()), key=lambda name: name == target.name):
                        os.replace(stage / name, target.parent / name)  # out last: the file a later run reads
    finally:
        shutil.rmtree(stage, ignore_errors=True)  # our own staging folder; gone already once published


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
        from nerfstudio.utils.rich_utils import CONSOLE  # here: this module imports without nerfstudio

        CONSOLE.log(
            f"[naka-gs] warning: cache {preferred} is not writable ({err.strerror or err}); using {fallback} for "
            "this run -- set NAKA_GS_CACHE to a writable folder to keep the cache between runs",
            markup=False,
        )
        return fallback


# --- inputs: regular files only ----------------------------------------------------------------------------------

PathLike = Union[str, "os.PathLike[str]"]

SHOWN_PATH_CHARS = 60
"""How much of a path too long for the system a message shows (the start: where it is)."""
MESSAGE_PATH_CHARS = 255
"""Longest path a message shows whole (a file name may be this long); a longer one is shortened (:func:`shown_path`)."""

_NONBLOCK = getattr(os, "O_NONBLOCK", 0)
"""Opening a FIFO with it returns at once (POSIX); the flag does nothing to a regular file."""

_KINDS = (
    (stat.S_ISDIR, "a folder"),
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


class InputFileError(UserError, ValueError):
    """An input that is not a regular file (a FIFO, a device, a socket, a folder), or a path longer than the system
    allows; one line ``[<what>: ]<path> <problem> -- <fix>``. ``problem`` alone (``is a FIFO (named pipe), not a
    regular file``) is kept for callers that report it their own way (the cache recomputes such an entry)."""

    def __init__(self, message: str, problem: str) -> None:
        super().__init__(message)
        self.problem = problem


def shown_path(path: PathLike, limit: int = MESSAGE_PATH_CHARS) -> str:
    """``path`` for a one-line message: whole up to ``limit`` characters, else its first :data:`SHOWN_PATH_CHARS`
    characters (where it is) and its length."""
    text = os.fspath(path)
    return text if len(text) <= limit else f"{text[:SHOWN_PATH_CHARS]}... ({len(text)} characters)"


def _refuse(path: PathLike, what: str, problem: str, fix: str, limit: int = MESSAGE_PATH_CHARS) -> InputFileError:
    """``[<what>: ]<path> <problem> -- <fix>``; a ``problem`` starting with ``:`` follows the path directly."""
    where = f"{what}: " if what else ""
    space = "" if problem.startswith(":") else " "
    return InputFileError(f"{where}{shown_path(path, limit)}{space}{problem} -- {fix}", problem.lstrip(": "))


def input_stat(path: PathLike, what: str = "") -> Optional[os.stat_result]:
    """``os.stat`` of an input (links followed), which opens nothing: None when it is missing (or a part of its path is
    a file); a path longer than the system allows, or a link loop, is an :class:`InputFileError` (``what`` names the
    input: ``"--data"``, ``"<json>: frame 3 file_path <name>"``). Any other ``OSError`` is raised as it is."""
    try:
        return os.stat(path)
    except (FileNotFoundError, NotADirectoryError):
        return None
    except OSError as err:
        if err.errno == errno.ENAMETOOLONG:
            raise _refuse(
                path,
                what,
                ": the path, or a name in it, is longer than the system allows",
                "use a shorter path (move the files to a folder nearer the root, or shorten their names)",
                limit=SHOWN_PATH_CHARS,
            ) from None
        if err.errno == errno.ELOOP:
            raise _refuse(
                path, what, "is a symbolic link that leads back to itself (a link loop)", "fix or replace the link"
            ) from None
        raise


def regular_file(path: PathLike, what: str = "", fix: str = "replace it with the file itself") -> bool:
    """Whether the input ``path`` is there: True for a regular file (links followed), False when it is missing; a FIFO,
    a device, a socket or a folder is an :class:`InputFileError` naming it and ``fix``, and so is a path too long
    (:func:`input_stat`). Nothing is opened, so nothing blocks: call it before every read of a user's file (opening a
    FIFO waits for a writer; ``/dev/zero`` never ends)."""
    st = input_stat(path, what)
    if st is None:
        return False
    _check_mode(st.st_mode, path, what, fix)
    return True


def _check_mode(mode: int, path: PathLike, what: str, fix: str) -> None:
    if stat.S_ISREG(mode):
        return
    kind = next((name for test, name in _KINDS if test(mode)), "a special file")
    raise _refuse(path, what, f"is {kind}, not a regular file", fix)


def open_regular(path: PathLike, what: str = "", fix: str = "replace it with the file itself") -> BinaryIO:
    """The input ``path`` opened for reading in binary, checked a regular file before it is opened
    (:func:`regular_file`) and again on the open descriptor (it may have been replaced between the two): opened with
    ``O_NONBLOCK``, so a FIFO put there meanwhile does not block the open either. A missing file raises
    ``FileNotFoundError``, other failures their ``OSError``."""
    regular_file(path, what, fix)
    fd = os.open(path, os.O_RDONLY | _NONBLOCK | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_BINARY", 0))
    try:
        _check_mode(os.fstat(fd).st_mode, path, what, fix)
        if _NONBLOCK:
            os.set_blocking(fd, True)  # no effect on a regular file's reads; as an ordinary open leaves it
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_regular(path: PathLike, what: str = "", fix: str = "replace it with the file itself") -> bytes:
    """The bytes of the input ``path``, read only when it is a regular file (:func:`open_regular`)."""
    with open_regular(path, what, fix) as stream:
        return stream.read()
