"""Every console script, nerfstudio's convention: one module per script, a tyro dataclass with ``main()``
and a module-level ``entrypoint()``. ``naka-gs-<name>`` lives in ``scripts/<name>.py`` (dashes as
underscores) as the class ``<Name>`` in CamelCase (``naka-gs-process-data``: ``scripts/process_data.py``,
``ProcessData``); the library code a script calls stays in its package. Benchmarks and record tools are not
installed: they live in the repository's ``benchmarks/`` (``python -m benchmarks.<name>`` from a clone).

Every ``entrypoint()`` is :func:`run`, the one way out of a command:

- tyro parses the arguments; a usage error is tyro's message and exit status 2;
- ``main()`` runs; a problem the user can fix, a :class:`~naka_gs_plugin.errors.UserError`, ends it with the line
  ``naka-gs: <message>`` on stderr and exit status 1;
- so does an ``OSError`` (a missing input, an output where a file is in the way, a full disk): ``naka-gs: <path>:
  <reason> -- <fix>``;
- Ctrl-C and SIGTERM stop it with one line ``naka-gs: Ctrl-C: stopped...`` and exit status 130 / 143, its unfinished
  output removed (:func:`~naka_gs_plugin.data.safe_io.staged_output`);
- any other exception is a bug and keeps its traceback.

Light on purpose (no nerfstudio, no torch): ``naka-gs-train-correction`` runs where nerfstudio is not installed.
"""

from __future__ import annotations

import signal
import sys
import warnings
from typing import Any, Callable, List, Optional, Sequence, Type, TypeVar

from naka_gs_plugin.errors import UserError, os_error_exit, signal_exit_status, user_error_exit

T = TypeVar("T")

# Before a script imports nerfstudio: its cameras module calls torch.jit.script at import, which torch 2.14 deprecates
# with a warning on stderr that a user of a console script can do nothing about (scripts/constraints.txt pins both).
warnings.filterwarnings("ignore", message=r"`torch\.jit\.script` is deprecated", category=FutureWarning)


class Stopped(KeyboardInterrupt):
    """SIGTERM while a command runs, raised in the main thread as Ctrl-C's ``KeyboardInterrupt`` is, so that the
    same clean-up runs (``finally`` blocks, :func:`~naka_gs_plugin.data.safe_io.staged_output`)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def _raise_stopped(signum: int, frame: object) -> None:
    raise Stopped(signum)


def run(
    main: Callable[[T], object],
    config_cls: Type[T],
    args: Optional[Sequence[str]] = None,
    *,
    defaults: Optional[Callable[[List[str]], T]] = None,
    **tyro_kwargs: Any,
) -> None:
    """Parse ``args`` (default ``sys.argv[1:]``) into ``config_cls`` with tyro and call ``main`` on it, ending as the
    module docstring says. ``defaults(args)``, if given, makes the instance whose values tyro starts from (a recipe
    file named in the arguments); ``tyro_kwargs`` go to ``tyro.cli`` (``config=...``)."""
    import tyro  # here: importing the package stays light

    argv = list(sys.argv[1:] if args is None else args)
    previous = None
    try:  # SIGTERM as Ctrl-C, in the main thread; a signal the caller ignores (nohup) stays ignored
        if signal.getsignal(signal.SIGTERM) == signal.SIG_DFL:
            previous = signal.signal(signal.SIGTERM, _raise_stopped)
    except ValueError:  # not the main thread
        pass
    try:
        if defaults is not None:
            tyro_kwargs["default"] = defaults(argv)
        main(tyro.cli(config_cls, args=argv, **tyro_kwargs))
    except UserError as err:
        raise user_error_exit(err) from None  # type: ignore[misc]
    except OSError as err:
        raise os_error_exit(err) from None
    except KeyboardInterrupt as err:
        signum = getattr(err, "signum", signal.SIGINT)
        name = "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name
        sys.stdout.flush()
        print(f"naka-gs: {name}: stopped before it finished", file=sys.stderr, flush=True)
        raise SystemExit(signal_exit_status(signum)) from None
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
