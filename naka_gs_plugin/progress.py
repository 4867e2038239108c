"""The one progress display of the plugin's long stages (enhancement, correction training, mapping).

A rich progress bar on a terminal; where stdout is not one (a log file, CI, ``nohup``) the bar
cannot redraw, so the same progress is also printed as plain lines -- the first item, then at most
every ``log_every`` seconds, and the last -- each with the rate and the time left.
"""

from __future__ import annotations

import contextlib
import threading
import time
from typing import Callable, Dict, Iterator, Optional

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TaskID,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)


class StageProgress(Progress):
    """``rich.progress.Progress`` with the plugin's columns and plain log lines off a terminal."""

    def __init__(self, console: Optional[Console] = None, log_every: float = 30.0) -> None:
        """``console``: default nerfstudio's, so that the bar and nerfstudio's log lines do not garble each other."""
        if console is None:
            from nerfstudio.utils.rich_utils import CONSOLE  # lazy: callers with their own console need no nerfstudio

            console = CONSOLE
        super().__init__(
            TextColumn("[progress.description]{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            TimeRemainingColumn(),
            console=console,
            transient=False,
        )
        self.log_every = log_every
        self._logged: Dict[TaskID, float] = {}

    def update(self, task_id: TaskID, **kwargs) -> None:
        super().update(task_id, **kwargs)
        self._log(task_id)

    def advance(self, task_id: TaskID, advance: float = 1) -> None:
        super().advance(task_id, advance)
        self._log(task_id)

    def _log(self, task_id: TaskID) -> None:
        if self.console.is_terminal:
            return
        with self._lock:
            task = self._tasks[task_id]
            done, total, elapsed = task.completed, task.total, task.elapsed or 0.0
        now = time.monotonic()
        first = task_id not in self._logged
        finished = total is not None and done >= total
        if not (first or finished or now - self._logged[task_id] >= self.log_every) or done <= 0:
            return
        self._logged[task_id] = now
        rate = done / elapsed if elapsed > 0 else float("inf")
        left = f", {(total - done) / rate:.0f} s left" if total is not None and 0 < rate < float("inf") else ""
        of = f"/{total:.0f}" if total is not None else ""
        self.console.print(
            f"{task.description}: {done:.0f}{of} in {elapsed:.0f} s ({rate:.3g}/s{left})", markup=False, highlight=False
        )


@contextlib.contextmanager
def progress_from(progress: Progress, task: TaskID, read: Callable[[], int], every: float = 0.5) -> Iterator[None]:
    """Show ``read()`` (items done so far) as ``task``'s progress every ``every`` seconds while the body runs: for a
    long call that reports nothing itself but whose progress can be read from elsewhere (pycolmap's feature
    extraction and matching, from its database). A ``read`` that fails is skipped until the next poll."""
    done = threading.Event()

    def poll() -> None:
        while not done.wait(every):
            try:
                progress.update(task, completed=read())
            except Exception:  # noqa: BLE001 -- progress is a display: a failed read must never stop the work
                pass

    thread = threading.Thread(target=poll, name="naka-gs-progress", daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join()
    try:
        progress.update(task, completed=read())
    except Exception:  # noqa: BLE001
        pass
