"""Where naka-gs reaches into nerfstudio: the only module that reads its stack frames, patches it or installs a hook.

nerfstudio (1.1.5) has no hook for what a naka-gs run needs at these points, so each is a workaround kept here, with
the upstream source it relies on pinned by sha256 beside it (:data:`UPSTREAM_SHA256`, checked by
``tests/run/test_nerfstudio_hooks.py``) and the hook we would propose upstream in a comment:

- ``eval_setup`` (ns-eval, ns-render, ns-export, ns-viewer) reads a run's config.yml and asks the config for its
  checkpoint folder; the config learns where the file lies only from eval_setup's frame
  (:func:`eval_setup_config_path`), so that a copied or moved run loads its own checkpoints;
- a config.yml that eval_setup cannot read fails before any of our code runs: a ``sys.excepthook`` makes it one line
  (:func:`activate`);
- ns-export makes its ``--output-dir`` before it loads the run: a failed load removes it again, and a file the export
  would replace is refused first (:func:`check_export_target`);
- splatfacto builds torchmetrics' LPIPS (which downloads AlexNet) inside ``populate_modules``
  (:func:`splatfacto_lpips_replaced`), and ``writer.setup_event_writer`` builds its tensorboard writer by name
  (:func:`tensorboard_writer_replaced`);
- torch >= 2.6 loads checkpoints with ``weights_only=True``, and nerfstudio writes numpy scalars into them
  (:func:`activate` registers them as safe).
- ns-render writes its videos with an ``ffmpeg`` it looks up on PATH (``check_ffmpeg_installed``, then mediapy):
  without a system one, imageio-ffmpeg's binary is put there (:func:`put_ffmpeg_on_path`).

Every hook is active only inside a naka-gs command or run: :func:`activate` is called by our console scripts, by
``ns-train naka-gs`` (the trainer config) and by ``eval_setup`` loading a naka-gs run (the config's
``get_checkpoint_dir``); at import only :func:`activate_for_command` runs, which activates nothing unless the command
line loads a naka-gs run's config.yml. ``ns-train splatfacto`` and every other method run exactly as without us.
"""

from __future__ import annotations

import atexit
import contextlib
import functools
import os
import shutil
import stat
import sys
import tempfile
import time
from pathlib import Path
from types import FrameType, TracebackType
from typing import Any, Callable, Dict, Iterator, List, Optional, Sequence, Tuple
from unittest import mock

import yaml

from naka_gs_plugin.data.safe_io import UnsafeOutputError, check_new_files
from naka_gs_plugin.errors import user_error_exit
from naka_gs_plugin.run.config_check import (
    config_file_problem,
    read_regular_text,
    refuse_code_in_config,
    unreadable_line,
    yaml_error_line,
)

UPSTREAM_SHA256: Dict[str, str] = {
    # eval_setup asks the config for its checkpoint folder with the file's path in its local ``config_path``, then
    # loads ``load_step``; it reads the file with ``yaml.load`` and asserts the result is a TrainerConfig.
    "nerfstudio.utils.eval_utils.eval_setup": "57bb85ad21bfef08f5032f01f441701226704a03a07aa2ef8675e76817089a6a",
    # eval_load_checkpoint names its file in the local ``load_path`` (checkpoint_mismatch_exit).
    "nerfstudio.utils.eval_utils.eval_load_checkpoint": (
        "673cc38af1137571b1dc5dc747d4e27a75d4b8ac8b76cb1abaa7733f531a6618"
    ),
    # ns-train calls set_timestamp, then save_config, before it launches the training.
    "nerfstudio.scripts.train.main": "eb5019ff18ee071d48486efc62a8c0e7d48788f9c33a0a32ff5b722a95723437",
    # The run folder's layout.
    "nerfstudio.configs.experiment_config.ExperimentConfig.get_base_dir": (
        "6da3d785c70b1a1d0e1081d3fea2f56b72fc45b17c9c5c75777b574b76c385f6"
    ),
    "nerfstudio.configs.experiment_config.ExperimentConfig.get_checkpoint_dir": (
        "e05da2c9dae431cd0664dd4bd1926ff3a9b663bdab57027a677388ac549230f5"
    ),
    "nerfstudio.configs.experiment_config.ExperimentConfig.save_config": (
        "b6c800ac503c45676a1b353091d3877ab79205019284b285acf1225344e93fd1"
    ),
    # ns-export makes its --output-dir before eval_setup, and its command object is ``self`` there.
    "nerfstudio.scripts.exporter.ExportGaussianSplat.main": (
        "00511077684e5547b24dfd7565f76552851c18e099afabbb081b46493d83db38"
    ),
    # Builds ``writer.TensorboardWriter`` by its module-level name.
    "nerfstudio.utils.writer.setup_event_writer": "e4ebc1768b0fe904ad1a607dab77dfdd18d0915272b3483c422162517a09d7d3",
    # Imports torchmetrics' LPIPS inside the method and builds it there.
    "nerfstudio.models.splatfacto.SplatfactoModel.populate_modules": (
        "be5dfb4957db9b7a5b3b0f82966ad9b26cf18f8761bd2cbe6245d3c4353f7277"
    ),
    # ns-render's video commands exit unless ``shutil.which("ffmpeg")`` finds one (put_ffmpeg_on_path).
    "nerfstudio.utils.install_checks.check_ffmpeg_installed": (
        "a0b8730f277ea0169cb311fc08d9435c28a7c92b5c59b95b5f5680608e96a661"
    ),
    # The files ns-export's cameras command writes (EXPORTED_FILES).
    "nerfstudio.scripts.exporter.ExportCameraPoses.main": (
        "946ce978d5e051aae7104458fb14d02cd8c4b3ab6a79a4c34495c196d3b627bf"
    ),
}
"""sha256 of the source of each upstream function these hooks rely on, by qualified name."""

METHOD_NAMES = ("naka-gs", "naka-gs-fast")
"""The presets' ``method_name``: a run folder ``<output-dir>/<experiment>/<method>/<timestamp>`` of ours."""

_IMPORTED_AT = time.time()
"""When this process imported the plugin: every ``ns-*`` command does so before it parses its options."""
_ACTIVE = False


def activate() -> None:
    """Turn on the hooks a naka-gs command or run needs in this process (once): the one-line end of a config.yml
    that ``eval_setup`` cannot read, and numpy's scalars as safe globals of ``torch.load``."""
    global _ACTIVE
    if _ACTIVE:
        return
    _ACTIVE = True
    _register_safe_globals()
    sys.excepthook = functools.partial(_excepthook, sys.excepthook)


def _register_safe_globals() -> None:
    """nerfstudio 1.1.5 writes ``np.float64`` learning rates into its checkpoints, and torch >= 2.6 loads with
    ``weights_only=True``: without these ``ns-eval``, ``ns-viewer`` and resume fail. Both names: a checkpoint
    written under numpy 1 says ``numpy.core...``, under numpy 2 ``numpy._core...``. Before torch 2.6 ``torch.load``
    defaults to ``weights_only=False`` (nothing to register), and before 2.5 it has no ``add_safe_globals`` with
    names."""
    import numpy as np
    import torch

    if torch.__version__ < "2.6":
        return
    try:  # numpy >= 1.26; ``numpy.core`` is a deprecated alias from numpy 2 on
        from numpy._core.multiarray import scalar
    except ImportError:
        from numpy.core.multiarray import scalar
    torch.serialization.add_safe_globals(
        [
            (scalar, "numpy.core.multiarray.scalar"),
            (scalar, "numpy._core.multiarray.scalar"),
            np.dtype,
            type(np.dtype(np.float64)),
        ]
    )


def loaded_config_path(argv: Sequence[str]) -> Optional[Path]:
    """The ``--load-config`` file of an ``ns-*`` command line that loads a run (ns-eval, ns-render, ns-export,
    ns-viewer), else None (ns-train reads its own ``--load-config`` through our config, which checks it)."""
    if not argv or Path(argv[0]).name in ("ns-train", "ns-train.exe"):
        return None
    for i, arg in enumerate(argv[1:], start=1):
        if arg == "--load-config" and i + 1 < len(argv):
            return Path(argv[i + 1])
        if arg.startswith("--load-config="):
            return Path(arg.partition("=")[2])
    return None


def is_naka_gs_run_config(path: Path) -> bool:
    """Whether ``path``, a config.yml that may be broken, is a naka-gs run's: it names our package, or it lies in a
    run folder of one of our presets (``.../<method>/<timestamp>/config.yml``). Only a regular file is read (a FIFO
    would block), and only its first megabyte."""
    if path.parent.parent.name in METHOD_NAMES:
        return True
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            return False
        with open(path, "rb") as fh:
            return b"naka_gs_plugin" in fh.read(1 << 20)
    except OSError:
        return False


def activate_for_command(argv: Optional[Sequence[str]] = None) -> None:
    """At the plugin's import (every ``ns-*`` command imports it, before it parses its options): when the command
    line loads a naka-gs run's config.yml, activate the hooks (so that one that is not YAML, empty or unreadable
    ends in one line) and refuse a file that would run code when eval_setup reads it with ``yaml.Loader``
    (:func:`~naka_gs_plugin.run.config_check.refuse_code_in_config`). Any other command (``ns-train splatfacto``,
    ``ns-eval`` of another method's run) is left exactly as it is without us."""
    path = loaded_config_path(sys.argv if argv is None else argv)
    if path is None or not is_naka_gs_run_config(path):
        return
    activate()
    try:
        text = read_regular_text(path)
    except (OSError, UnicodeDecodeError) as err:
        raise SystemExit(unreadable_line(path, err)) from None
    refuse_code_in_config(path, text)
    if Path((sys.argv if argv is None else argv)[0]).name == "ns-render":
        put_ffmpeg_on_path()


def put_ffmpeg_on_path() -> None:
    """Without an ``ffmpeg`` on PATH, put imageio-ffmpeg's binary there as ``ffmpeg`` (a link in a folder of this
    process, removed at its exit, at the end of PATH): nerfstudio's check, mediapy's video writer and the ffmpeg
    commands ns-render starts all find it. A platform imageio-ffmpeg has no binary for gets one line, and ns-render
    then its own "Could not find ffmpeg"."""
    if shutil.which("ffmpeg"):
        return
    try:
        import imageio_ffmpeg

        exe = imageio_ffmpeg.get_ffmpeg_exe()
    except (ImportError, RuntimeError) as err:
        print(f"naka-gs: imageio-ffmpeg gives no ffmpeg here ({err}): install ffmpeg to write videos", file=sys.stderr)
        return
    folder = tempfile.mkdtemp(prefix="naka-gs-ffmpeg-")
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    os.symlink(exe, os.path.join(folder, "ffmpeg"))
    os.environ["PATH"] = os.pathsep.join(filter(None, [os.environ.get("PATH"), folder]))


# ---------------------------------------------------------------------------------------------- eval_setup frames
# Proposed upstream: eval_setup passing ``config_path`` to the config (e.g. ``config.loaded_from(config_path)``) and
# to the pipeline's setup; with that, none of the frame reading below is needed.


def eval_setup_config_path(frame: Optional[FrameType]) -> Optional[Path]:
    """The config.yml that nerfstudio's ``eval_setup`` is loading when ``frame`` is that call, else None.

    ``eval_setup(config_path)`` is where ``ns-eval``, ``ns-render``, ``ns-export``, ``ns-viewer`` (and our
    demo and scene sheet) load a run, and it asks the config for its checkpoint folder right after reading
    it. The config's own location is known only there: ``eval_setup`` parses the file's text, so the YAML
    loader never sees the path, and ``--load-config`` on the command line is one spelling of it in four
    CLIs (and means something else to ``ns-train``)."""
    if frame is None or frame.f_code.co_name != "eval_setup":
        return None
    if frame.f_globals.get("__name__") != "nerfstudio.utils.eval_utils":
        return None
    path = frame.f_locals.get("config_path")
    return Path(path) if path is not None else None


def calling_eval_setup(depth: int = 1) -> Tuple[Optional[FrameType], Optional[Path]]:
    """For a method of ours called by upstream code (``depth`` calls above the caller of this function): the frame
    that called it and, when that frame is ``eval_setup``, the config.yml it loads."""
    frame = sys._getframe(depth + 1)
    return frame, eval_setup_config_path(frame)


def remove_new_empty_output_dir(eval_setup_frame: FrameType) -> None:
    """``ns-export`` makes its ``--output-dir`` before it loads the checkpoint; when that load fails, remove
    the folder again if it is empty and was made by this process (changed after the plugin was imported)."""
    caller = eval_setup_frame.f_back
    owner = caller.f_locals.get("self") if caller is not None else None
    out = getattr(owner, "output_dir", None)
    if type(owner).__module__ != "nerfstudio.scripts.exporter" or not isinstance(out, Path):
        return
    try:
        if out.is_dir() and not any(out.iterdir()) and out.stat().st_mtime >= _IMPORTED_AT - 1.0:
            out.rmdir()
    except OSError:
        pass


EXPORTED_FILES: Dict[str, Callable[[Any], List[str]]] = {
    "ExportGaussianSplat": lambda command: [command.output_filename],
    "ExportCameraPoses": lambda command: ["transforms_train.json", "transforms_eval.json"],
}
"""The files that ``ns-export``'s commands for a splat model write into ``--output-dir``, by command class."""


def check_export_target(eval_setup_frame: FrameType) -> None:
    """``ns-export`` writes into its ``--output-dir`` without looking: refuse, before the run is loaded, an
    ``--output-dir`` that is a file, or one that already holds a file the export would replace."""
    caller = eval_setup_frame.f_back
    owner = caller.f_locals.get("self") if caller is not None else None
    out = getattr(owner, "output_dir", None)
    if type(owner).__module__ != "nerfstudio.scripts.exporter" or not isinstance(out, Path):
        return
    names = EXPORTED_FILES.get(type(owner).__name__, lambda command: [])(owner)
    fix = "choose another --output-dir" + (" or --output-filename" if hasattr(owner, "output_filename") else "")
    try:
        check_new_files(out, names, "--output-dir", fix)
    except UnsafeOutputError as err:
        raise SystemExit(f"naka-gs: {err}") from None


def loading_error_exit(data: Optional[Path], err: BaseException) -> Optional[SystemExit]:
    """For the pipeline config's ``setup``: the one line to exit with when ``err``, a user error, was raised while
    nerfstudio's ``eval_setup`` (its caller) set up the pipeline of the run it loads, whose scene is ``data``; else
    None.

    A scene folder no longer where config.yml records it (moved or deleted after training) is named with the
    fix: config.yml is the only place ``ns-eval`` / ``ns-render`` / ``ns-export`` / ``ns-viewer`` learn the
    scene from. The output folder ``ns-export`` has just made is removed again."""
    frame, config_path = calling_eval_setup(2)  # the pipeline config's setup, then its caller
    exit_ = user_error_exit(err)
    if frame is None or config_path is None or exit_ is None:
        return None
    remove_new_empty_output_dir(frame)
    if data is None or Path(data).is_dir():
        return exit_
    where = f"{data}" if Path(data).is_absolute() else f"{data} (relative: looked for in {Path.cwd()})"
    return SystemExit(
        f"naka-gs: {config_path} records --data {where}, and no scene folder is there (moved or deleted since "
        "training): move the scene back there, or edit the data: path at the top of that config.yml"
    )


def checkpoint_mismatch_exit(problem: str) -> SystemExit:
    """For the pipeline's ``load_pipeline``: the one line for a checkpoint that does not fit the pipeline it is loaded
    into (``problem``), loaded by its caller, upstream's ``eval_load_checkpoint`` (``eval_setup``: ns-eval & co.) or
    ``Trainer._load_checkpoint`` (a resumed ns-train); each names the file in a local of its own."""
    loader = sys._getframe(2)
    path = loader.f_locals.get("load_path") or loader.f_locals.get("load_checkpoint") or "(unnamed)"
    config_path = eval_setup_config_path(loader.f_back)
    if config_path is not None and loader.f_back is not None:
        remove_new_empty_output_dir(loader.f_back)
        fix = f"point data: in {config_path} back at the scene this run was trained on"
    else:
        fix = "resume a run only with the --data it was trained on, or leave out --load-dir to train from scratch"
    return SystemExit(f"naka-gs: checkpoint {path}: {problem} -- {fix}")


# ------------------------------------------------------------------------------- a config.yml eval_setup cannot read
# Proposed upstream: eval_setup raising one error type for a config.yml it cannot read, naming the file.


def config_file_error(exc: BaseException) -> Optional[Tuple[str, FrameType]]:
    """The one line for ``exc``, and the ``eval_setup`` frame it passed, when it is upstream's ``eval_setup``
    (ns-eval, ns-render, ns-export, ns-viewer) failing to read its config.yml: an error of the file's reading or
    of its ``yaml.load``, or the ``assert`` after that of an empty file or one that holds no run configuration;
    else None."""
    tb: Optional[TracebackType] = exc.__traceback__
    while tb is not None:
        frame = tb.tb_frame
        if frame.f_code.co_name == "eval_setup" and frame.f_globals.get("__name__") == "nerfstudio.utils.eval_utils":
            break
        tb = tb.tb_next
    if tb is None or frame.f_locals.get("config_path") is None:
        return None
    path = Path(frame.f_locals["config_path"])
    line = None
    if tb.tb_next is not None and "config" not in frame.f_locals:  # raised inside the file's read or yaml.load
        if isinstance(exc, yaml.YAMLError):
            line = yaml_error_line(path, exc)
        elif isinstance(exc, (OSError, UnicodeDecodeError)):
            line = unreadable_line(path, exc)
    elif isinstance(exc, AssertionError) and tb.tb_next is None and "config" in frame.f_locals:
        try:
            line = config_file_problem(path, path.read_text(), frame.f_locals["config"])
        except (OSError, UnicodeDecodeError):
            return None
    return (line, frame) if line is not None else None


def _excepthook(previous, exc_type, exc, tb) -> None:
    found = config_file_error(exc) if exc is not None else None
    if found is None:
        previous(exc_type, exc, tb)
        return
    line, frame = found
    remove_new_empty_output_dir(frame)
    print(line, file=sys.stderr)  # the interpreter then exits with status 1, as for SystemExit(line)


# ------------------------------------------------------------------------------------------------ patched names
# Proposed upstream: a writer factory argument for setup_event_writer, and an ``lpips`` factory (or a config field for
# local weights) on SplatfactoModelConfig.


@contextlib.contextmanager
def tensorboard_writer_replaced(factory: Callable[..., Any]) -> Iterator[None]:
    """While inside: ``writer.setup_event_writer`` (the trainer's setup) builds its tensorboard writer with
    ``factory(log_dir=...)`` instead of ``writer.TensorboardWriter``."""
    from nerfstudio.utils import writer

    with mock.patch.object(writer, "TensorboardWriter", factory):
        yield


@contextlib.contextmanager
def splatfacto_lpips_replaced(factory: Callable[..., Any]) -> Iterator[None]:
    """While inside: splatfacto's ``populate_modules`` builds its LPIPS metric with ``factory(**kwargs)`` instead of
    torchmetrics' (which downloads AlexNet's weights on first use)."""
    with mock.patch("torchmetrics.image.lpip.LearnedPerceptualImagePatchSimilarity", factory):
        yield
