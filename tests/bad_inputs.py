"""The machinery of the bad-input tables (tests/faults/): one row per case, its outcome, and every input it was
given byte-identical after.

A row is a ``make(env)`` that builds its inputs under ``env.tmp`` (copies of the toy scene or of a trained run;
nothing shared is modified) and returns the action plus the paths that must not change (files, or folders compared
by their whole tree), and the outcome it expects:

- :class:`Raises`: the exception type and a substring of its message, which is one line;
- :class:`Exits`: a console script's exit status and a substring of the one line it ends with (the ``SystemExit``
  message, else the last line it printed on stdout and stderr), which starts ``naka-gs:``, no traceback;
- :class:`Ok`: a check of the action's result.

:func:`check_case` runs one row; the outcome may also be given as a function of the :class:`Env` (a message that
names the row's own paths). The helpers below it build the inputs more than one table uses.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple, Union

import cv2
import pytest

from naka_gs_plugin.data.lowlight_dataparser import LowLightDataParserConfig
from naka_gs_plugin.enhance.pipeline import EnhanceConfig

Action = Callable[[], object]
"""What a row runs (and, for :class:`Ok`, whose result it checks)."""


@dataclass
class Raises:
    exc: type
    message: str
    after: Optional[Callable[["Env"], None]] = None
    """A further check once it has raised."""


@dataclass
class Exits:
    code: int
    message: str
    after: Optional[Callable[["Env"], None]] = None
    """A further check once it has exited."""
    prefix: str = "naka-gs: "
    """How the line starts: every naka-gs command's error line starts ``naka-gs:``; the benchmarks' their own."""


@dataclass
class Ok:
    check: Callable[["Env", object], None]


Outcome = Union[Raises, Exits, Ok]
Make = Callable[["Env"], Tuple[Action, List[Path]]]
"""A row's inputs: ``make(env)`` -> (the action, the paths that must not change)."""
Case = Tuple[Make, Union[Outcome, Callable[["Env"], Outcome]]]
"""One row of a table: its maker, and its outcome (or the outcome as a function of the row's :class:`Env`)."""


@dataclass
class Env:
    """What a row builds its inputs from: a private folder, the toy scene (read-only), pytest's monkeypatch and
    output capture, and a trained run (read-only; the tables that need one pass it)."""

    tmp: Path
    toy: Path
    monkeypatch: pytest.MonkeyPatch
    capsys: Optional[pytest.CaptureFixture] = None
    run: Optional[Path] = None

    def scene(self, name: str = "S", n_train: Optional[int] = None) -> Path:
        """A private copy of the toy scene (PNG captures, 8 training views), keeping only its first ``n_train``
        training views."""
        scene = Path(shutil.copytree(self.toy, self.tmp / name))
        if n_train is not None:
            path = scene / "transforms_train.json"
            meta = json.loads(path.read_text())
            meta["frames"] = meta["frames"][:n_train]
            path.write_text(json.dumps(meta))
        return scene

    def jpeg_scene(self, name: str = "S") -> Path:
        """The toy scene with its training captures as JPEGs (``train/*.jpg``)."""
        scene = self.scene(name)
        path = scene / "transforms_train.json"
        meta = json.loads(path.read_text())
        for frame in meta["frames"]:
            png = scene / frame["file_path"]
            cv2.imwrite(str(png.with_suffix(".jpg")), cv2.imread(str(png)), [cv2.IMWRITE_JPEG_QUALITY, 95])
            png.unlink()
            frame["file_path"] = str(Path(frame["file_path"]).with_suffix(".jpg"))
        path.write_text(json.dumps(meta))
        return scene

    def run_copy(self, name: str = "run", edit: Optional[Callable[[str], str]] = None) -> Path:
        """A private copy of the trained run; ``edit`` rewrites its config.yml's text as a user would."""
        assert self.run is not None, "this table has no trained run"
        run = Path(shutil.copytree(self.run, self.tmp / name))
        if edit is not None:
            (run / "config.yml").write_text(edit((run / "config.yml").read_text()))
        return run

    def log(self) -> str:
        """What the row has printed on stdout so far, its whitespace runs made single spaces."""
        return " ".join(self.capsys.readouterr().out.split())


def snapshot(paths: List[Path]) -> Dict[str, object]:
    """Every file and folder under ``paths`` (hidden ones included) by path: bytes, a link's target, or None for a
    folder."""
    state: Dict[str, object] = {}
    for root in paths:
        for item in [root, *(sorted(root.rglob("*")) if root.is_dir() else [])]:
            if item.is_symlink():
                state[str(item)] = ("link", os.readlink(item))
            else:
                state[str(item)] = None if item.is_dir() else item.read_bytes()
    return state


def check_case(env: Env, make: Make, expect: Union[Outcome, Callable[[Env], Outcome]]) -> None:
    """Run one row: build its inputs, run its action, check its outcome (and its ``after``), then that every
    protected path is as it was. An :class:`Exits` row's line, where it is printed rather than the ``SystemExit``
    message, is the last line of stdout and stderr together (after the run's own log lines)."""
    action, protected = make(env)
    if callable(expect):
        expect = expect(env)
    before = snapshot(protected)
    env.capsys.readouterr()
    if isinstance(expect, Raises):
        with pytest.raises(expect.exc) as err:
            action()
        message = str(err.value)
        assert expect.message in message and "\n" not in message, message
    elif isinstance(expect, Exits):
        with pytest.raises(SystemExit) as err:
            action()
        code = err.value.code
        out, errors = env.capsys.readouterr()
        assert "Traceback" not in out + errors, out + errors
        printed = code if isinstance(code, str) else (out + errors).strip().splitlines()[-1]
        assert (1 if isinstance(code, str) else code) == expect.code
        assert printed.startswith(expect.prefix) and expect.message in printed and "\n" not in printed, printed
    else:
        expect.check(env, action())
    if not isinstance(expect, Ok) and expect.after is not None:
        expect.after(env)
    assert snapshot(protected) == before


# --- inputs more than one table builds ------------------------------------------------------------------------

NAKA = EnhanceConfig(correction="none")
"""Naka-Rushton alone: enhancement without the correction network."""


def first_train_image(scene: Path) -> Path:
    return scene / json.loads((scene / "transforms_train.json").read_text())["frames"][0]["file_path"]


def edit_frame0(scene: Path, **values) -> Path:
    """Set keys of the first training frame (``transform_matrix`` included) in transforms_train.json."""
    path = scene / "transforms_train.json"
    meta = json.loads(path.read_text())
    meta["frames"][0].update(values)
    path.write_text(json.dumps(meta))
    return path


def parse(scene: Path, factor: int = 1) -> Action:
    """The dataparser's training outputs of ``scene``, at ``factor``."""
    config = LowLightDataParserConfig(data=scene, downscale_factor=factor)
    return lambda: config.setup().get_dataparser_outputs("train")


def run_console(env: Env, entrypoint: Callable[[], None], argv: List[str]) -> Action:
    """The console script ``argv[0]``'s entry point with ``sys.argv`` set to ``argv``."""

    def action():
        env.monkeypatch.setattr(sys, "argv", argv)
        entrypoint()

    return action
