"""``NakaGSTrainer``: nerfstudio's ``Trainer`` with training state that survives Ctrl-C, kills and bad files.

- Ctrl-C finishes the running step, saves it and exits 130; a second Ctrl-C exits 130 at once.
- A checkpoint is written to a temporary file in its folder and published with ``os.replace``, so a
  write cut short (full disk, kill) never replaces or poses as a valid ``step-*.ckpt``.
- ``--load-dir`` / ``--load-checkpoint`` skip a corrupt or truncated checkpoint for the newest valid
  older one, and fail with one line naming the folder when none is valid.
- SIGTERM is handled as Ctrl-C; either one before the first training step has finished (while the
  training images load and are enhanced, which can take minutes) stops at once, nothing to save.
- With ``--vis tensorboard``, the scalars nerfstudio records at every step (iteration time, ETA, rays per second,
  learning rates) are written at the steps it logs the losses at (:class:`LoggedStepsTensorboardWriter`).
- One of the plugin's own errors for a problem the user can fix (:data:`~naka_gs_plugin.errors.USER_ERRORS`: a bad scene file,
  image, point source) ends ``ns-train`` with the one line ``naka-gs: <message>`` (exit status 1)
  instead of nerfstudio's traceback; any other exception is a bug and keeps its traceback.

``NakaGSTrainerConfig`` makes the run folder trustworthy: ``ns-train`` refuses a run folder that already
holds another run, a missing ``--data`` or an unwritable ``--output-dir`` is one line and leaves no
folder, and ``ns-eval`` / ``ns-render`` / ``ns-export`` / ``ns-viewer`` load the newest valid checkpoint
of the folder their config.yml is in (a copied or moved run loads its own checkpoints); a scene that is
no longer where config.yml says is one line there too (:func:`loading_error_exit`). A config.yml or option that
nerfstudio would misread (an unknown key, a value of the wrong type or out of range) is one line before anything
runs (:mod:`naka_gs_plugin.config_check`), as is a checkpoint of a scene with another number of views, and
``ns-export`` never replaces a file already in its ``--output-dir``.

Only the hooks are overridden; loading the chosen file is still upstream's code. The upstream methods
whose behaviour this relies on are pinned by source hash in ``tests/test_trainer_safety.py`` and
``tests/test_run_folder.py``.
"""

from __future__ import annotations

import os
import re
import secrets
import signal
import sys
import threading
import time
import zipfile
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from types import FrameType
from typing import List, Literal, NoReturn, Optional, Sequence, Type, Union
from unittest import mock

import torch
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.engine.trainer import Trainer, TrainerConfig
from nerfstudio.utils import writer
from nerfstudio.utils.decorators import check_main_thread
from nerfstudio.utils.misc import step_check
from nerfstudio.utils.rich_utils import CONSOLE

from naka_gs_plugin.config_check import check_config_file, check_run_config, install_excepthook
from naka_gs_plugin.data.safe_io import UnsafeOutputError, check_new_files
from naka_gs_plugin.errors import user_error_exit

INTERRUPTED_EXIT_CODE = 130  # 128 + SIGINT, what shells report for a Ctrl-C'd command; SIGTERM exits with it too
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
CHECKPOINT_NAME = re.compile(r"step-(\d+)\.ckpt")
# Upstream's ns-eval/ns-viewer/ns-export parse every name in the checkpoint folder as int(name[first "-" + 1 :
# first "."]) and take the largest (eval_utils.eval_load_checkpoint). A temporary file left by a kill
# therefore has to parse, and to step 0, so that it never outranks a real checkpoint.
PARTIAL_PREFIX = "tmp-0."
PER_STEP_SCALARS = frozenset(
    event.value
    for event in (writer.EventName.ITER_TRAIN_TIME, writer.EventName.ETA, writer.EventName.TRAIN_RAYS_PER_SEC)
)
"""Scalars nerfstudio's training loop records at every step, besides each optimizer group's ``learning_rate/<group>``."""


def checkpoint_step(path: Path) -> Optional[int]:
    """The step of a ``step-<N>.ckpt`` name, else None."""
    match = CHECKPOINT_NAME.fullmatch(path.name)
    return int(match.group(1)) if match else None


def is_valid_checkpoint(path: Path) -> bool:
    """Whether ``path`` is a complete ``torch.save`` archive whose every record matches its CRC-32.

    ``torch.save`` writes a zip with a CRC per record; a truncated file lacks the central directory
    and a damaged one fails a CRC, both without unpickling anything."""
    try:
        with zipfile.ZipFile(path) as archive:
            return archive.testzip() is None
    except (OSError, EOFError, zipfile.BadZipFile):
        return False


def checkpoints_newest_first(folder: Path, up_to: Optional[int] = None) -> List[Path]:
    """The ``step-*.ckpt`` files in ``folder`` (none if it is missing), largest step first; only steps
    <= ``up_to`` when given."""
    found = [p for p in folder.glob("step-*.ckpt") if checkpoint_step(p) is not None] if folder.is_dir() else []
    found = [p for p in found if up_to is None or checkpoint_step(p) <= up_to]  # type: ignore[operator]
    return sorted(found, key=checkpoint_step, reverse=True)  # type: ignore[arg-type]


def newest_checkpoint(folder: Path) -> Optional[Path]:
    """The ``step-*.ckpt`` in ``folder`` with the largest step, if any."""
    return next(iter(checkpoints_newest_first(folder)), None)


def first_valid_checkpoint(candidates: Sequence[Path], folder: Path, verb: str) -> Optional[Path]:
    """The first valid checkpoint of ``candidates`` (newest first), else None; when it is not the first,
    one line names the ones skipped and what ``verb`` ("resuming from", "loading") now uses."""
    for i, path in enumerate(candidates):
        if is_valid_checkpoint(path):
            if i:
                skipped = ", ".join(p.name for p in candidates[:i])
                CONSOLE.print(
                    f"naka-gs: skipping corrupt or truncated {skipped} in {folder}; {verb} {path.name}",
                    markup=False,
                    soft_wrap=True,
                )
            return path
    return None


def _fsync_dir(folder: Path) -> None:
    # Makes the rename durable before older checkpoints are deleted; directories cannot be opened on Windows.
    if hasattr(os, "O_DIRECTORY"):
        fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


class LoggedStepsTensorboardWriter(writer.TensorboardWriter):
    """nerfstudio's tensorboard writer, writing the scalars the training loop records at every step (the iteration
    time and rays per second, both running averages over the last steps, the ETA and each group's learning rate)
    only at the steps it logs the losses at: every ``every`` steps from step 0 (``--logging.steps-per-log``). Every
    other event is written as upstream writes it. Why: nerfstudio pins protobuf <= 3.20.3, which has no compiled
    module for Python 3.11, so tensorboard serialises each scalar in pure Python: the ten or so of every step were a
    measurable share of a CPU training step (docs/cpu.md)."""

    def __init__(self, log_dir: Path, every: int) -> None:
        super().__init__(log_dir=log_dir)
        self.every = every

    def write_scalar(self, name: str, scalar: Union[float, torch.Tensor], step: int) -> None:
        per_step = name in PER_STEP_SCALARS or name.startswith("learning_rate/")
        if per_step and not step_check(step, self.every, run_at_zero=True):
            return
        super().write_scalar(name, scalar, step)


class NakaGSTrainer(Trainer):
    """nerfstudio's ``Trainer`` with atomic checkpoints, Ctrl-C / SIGTERM saving and corrupt-checkpoint fallback."""

    def setup(self, test_mode: Literal["test", "val", "inference"] = "val") -> None:
        """Upstream's setup, plus a callback that records the last fully completed step. A setup that fails
        removes the run folder ``save_config`` has just made (nothing was trained into it); a user error
        (:data:`~naka_gs_plugin.errors.USER_ERRORS`: an empty ``--data`` folder, a truncated COLMAP model...) is then one line."""
        self._stop_step: Optional[int] = None  # the step running when the first Ctrl-C / SIGTERM came
        self._stop_name = "interrupted"  # "Ctrl-C" or "SIGTERM" once one came
        self._done_step: Optional[int] = None  # the last step whose iteration and callbacks finished
        self._previous_handlers: dict = {}  # the signal handlers _on_stop_signal replaced (restored after)
        self._catch_stop_signals()
        tensorboard = partial(LoggedStepsTensorboardWriter, every=self.config.logging.steps_per_log)
        try:
            with mock.patch.object(writer, "TensorboardWriter", tensorboard):  # writer.setup_event_writer makes it
                super().setup(test_mode=test_mode)
        except KeyboardInterrupt:
            self._discard_new_run_folder()
            self._exit_interrupted(f"{self._stop_name} during setup, before any training step; {self._newest_note()}")
        except BaseException as err:
            self._discard_new_run_folder()
            exit_ = user_error_exit(err)
            if exit_ is not None:
                raise exit_ from None
            raise
        finally:
            self._release_stop_signals()
        self.callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self._step_done))

    def train(self) -> None:
        """Upstream's training loop with Ctrl-C / SIGTERM deferred to the end of the running step.

        Stopping between steps matters: an interrupt inside densification or an optimizer step would
        save parameters and optimizer state that no longer match. Before the first step has finished
        (the training images load and are enhanced inside it) there is nothing to save: it stops at once.
        A user error (:data:`~naka_gs_plugin.errors.USER_ERRORS`: an unreadable training image, a diverged loss) is one line."""
        self._catch_stop_signals()
        try:
            super().train()
        except KeyboardInterrupt:
            if self.training_state == "completed" and not self._previous_handlers:
                raise  # upstream's "Ctrl-C to quit" the viewer after a finished training: keep its behaviour
            if self._done_step is None:
                self._exit_interrupted(
                    f"{self._stop_name} before the first training step finished, nothing to save (enhanced "
                    f"images already cached are kept); {self._newest_note()}"
                )
            self._exit_interrupted(f"interrupted again during step {self.step}, not saved; {self._newest_note()}")
        except Exception as err:
            exit_ = user_error_exit(err)
            if exit_ is None:
                raise
            raise exit_ from None
        finally:
            self._release_stop_signals()

    def _catch_stop_signals(self) -> None:
        # Handlers can only be set in the main thread; an ignored signal (nohup, `cmd &` in a script) stays ignored.
        if threading.current_thread() is not threading.main_thread():
            return
        for signum in STOP_SIGNALS:
            if signal.getsignal(signum) != signal.SIG_IGN:
                self._previous_handlers[signum] = signal.signal(signum, self._on_stop_signal)

    def _on_stop_signal(self, signum, frame) -> None:
        self._stop_name = "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name
        if self._stop_step is not None or self._done_step is None:
            raise KeyboardInterrupt  # a second one, or nothing trained yet: stop now
        self._stop_step = self.step
        self.stop_training = True  # also ends upstream's pause loop; _step_done re-sets it if train() resets it
        CONSOLE.print(
            f"naka-gs: {self._stop_name}: finishing step {self.step}, then saving a checkpoint "
            f"({self._stop_name} again: quit without saving)",
            markup=False,
            soft_wrap=True,
        )

    def _step_done(self, step: int) -> None:
        self._done_step = step
        if self._stop_step is not None:
            self.stop_training = True

    def _release_stop_signals(self) -> None:
        for signum, previous in self._previous_handlers.items():
            signal.signal(signum, previous or signal.SIG_DFL)  # None: a handler set outside Python
        self._previous_handlers = {}

    def _after_train(self) -> None:
        """On Ctrl-C / SIGTERM: save the last completed step and exit 130; otherwise upstream's end of training."""
        if self._stop_step is None:
            return super()._after_train()
        assert self._done_step is not None  # _on_stop_signal stops at once before the first step finished
        self.save_checkpoint(self._done_step)
        path = self.checkpoint_dir / f"step-{self._done_step:09d}.ckpt"
        self._exit_interrupted(
            f"interrupted; step {self._done_step} saved to {path} (resume with --load-dir {self.checkpoint_dir})"
        )

    def _train_complete_viewer(self) -> None:
        """Upstream waits here for Ctrl-C after a finished training; let that Ctrl-C through as before."""
        self._release_stop_signals()
        super()._train_complete_viewer()

    def _newest_note(self) -> str:
        newest = newest_checkpoint(self.checkpoint_dir)
        return f"newest checkpoint of this run: {newest}" if newest else "this run saved no checkpoint"

    def _discard_new_run_folder(self) -> None:
        """Remove the config.yml and the folders that ``NakaGSTrainerConfig.save_config`` created for this
        run; a folder that holds anything else (another process's run) stays."""
        created = getattr(self.config, "_created_folders", None)
        if not created:
            return
        (self.base_dir / "config.yml").unlink(missing_ok=True)
        for folder in created:  # deepest first
            try:
                folder.rmdir()
            except OSError:
                return

    def _exit_interrupted(self, what: str) -> NoReturn:
        CONSOLE.print(f"naka-gs: {what}", markup=False, soft_wrap=True)
        raise SystemExit(INTERRUPTED_EXIT_CODE)

    @check_main_thread
    def save_checkpoint(self, step: int) -> None:
        """Upstream's checkpoint, written to ``tmp-0.<pid>-<random>.<name>.partial`` and published with
        ``os.replace``; older checkpoints are deleted (when only the latest is kept) only after that."""
        self.checkpoint_dir.mkdir(parents=True, exist_ok=True)
        path = self.checkpoint_dir / f"step-{step:09d}.ckpt"
        partial = self.checkpoint_dir / f"{PARTIAL_PREFIX}{os.getpid()}-{secrets.token_hex(4)}.{path.name}.partial"
        # The same dict as upstream's save_checkpoint (pinned by source hash in the tests).
        state = {
            "step": step,
            "pipeline": self.pipeline.module.state_dict()  # type: ignore
            if hasattr(self.pipeline, "module")
            else self.pipeline.state_dict(),
            "optimizers": {k: v.state_dict() for (k, v) in self.optimizers.optimizers.items()},
            "schedulers": {k: v.state_dict() for (k, v) in self.optimizers.schedulers.items()},
            "scalers": self.grad_scaler.state_dict(),
        }
        try:
            with open(partial, "wb") as fh:
                torch.save(state, fh)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(partial, path)
        except Exception as err:
            partial.unlink(missing_ok=True)
            raise SystemExit(
                f"naka-gs: checkpoint {path} not written ({err}); the checkpoints already in {self.checkpoint_dir} "
                f"are intact: free disk space, then resume with --load-dir {self.checkpoint_dir}"
            ) from None
        except BaseException:  # a second Ctrl-C mid-write: leave no partial file behind
            partial.unlink(missing_ok=True)
            raise
        _fsync_dir(self.checkpoint_dir)
        if self.config.save_only_latest_checkpoint:
            for old in self.checkpoint_dir.glob("*.ckpt"):
                if old != path:
                    old.unlink()

    def _load_checkpoint(self) -> None:
        """Upstream's loading of the newest valid checkpoint that ``--load-dir`` / ``--load-checkpoint`` allow."""
        chosen = self.checkpoint_to_resume()
        if chosen is None:
            super()._load_checkpoint()
        else:
            # Upstream's --load-checkpoint branch loads exactly one file; point it at the chosen one for the call.
            config = self.config
            saved = config.load_dir, config.load_checkpoint
            config.load_dir, config.load_checkpoint = None, chosen
            try:
                super()._load_checkpoint()
            finally:
                config.load_dir, config.load_checkpoint = saved
        self._rebind_optimizers()

    def _rebind_optimizers(self) -> None:
        """Point every optimizer at the pipeline's current parameters, moving their loaded state along.

        Splatfacto's ``load_state_dict`` replaces each Gaussian parameter with a new ``Parameter`` of the
        checkpoint's size, after the optimizers were built on the old (seed-sized) ones; upstream leaves them
        there, so a resumed run stepped tensors the model no longer uses and its Gaussians stayed frozen
        (until a densification step rebound them, with fresh Adam moments). Parameters are matched by
        group name and position; their loaded Adam state moves with them.
        """
        groups = self.pipeline.get_param_groups()
        for name, optimizer in self.optimizers.optimizers.items():
            current = groups.get(name)
            if current is None or len(optimizer.param_groups) != 1:
                continue
            group = optimizer.param_groups[0]
            if len(group["params"]) != len(current):
                continue
            for old, new in zip(group["params"], current):
                if old is not new and old in optimizer.state:
                    optimizer.state[new] = optimizer.state.pop(old)
            group["params"] = list(current)
            self.optimizers.parameters[name] = current

    def checkpoint_to_resume(self) -> Optional[Path]:
        """The checkpoint to resume from: the requested one (the newest in ``--load-dir`` unless ``--load-step``
        names one, or ``--load-checkpoint``), else the newest valid older ``step-*.ckpt`` in its folder; None
        when no resume was asked for. Exits with one line when there is nothing valid to resume from."""
        config = self.config
        if config.load_dir is not None:
            flag, folder, newest = "--load-dir", Path(config.load_dir), config.load_step
            if newest is not None and not (folder / f"step-{newest:09d}.ckpt").is_file():
                raise SystemExit(
                    f"naka-gs: --load-step {newest}: {folder} has no step-{newest:09d}.ckpt; pick a step it holds"
                )
        elif config.load_checkpoint is not None:
            requested = Path(config.load_checkpoint)
            flag, folder, newest = "--load-checkpoint", requested.parent, checkpoint_step(requested)
            if not requested.is_file():
                raise SystemExit(f"naka-gs: --load-checkpoint {requested} does not exist; pass a step-*.ckpt file")
        else:
            return None
        if config.load_dir is None and newest is None:
            candidates = [requested]  # a custom file name: nothing in its folder is known to be older
        else:
            candidates = checkpoints_newest_first(folder, up_to=newest)
        if not candidates:
            raise SystemExit(
                f"naka-gs: {flag} {folder}: no step-*.ckpt checkpoint there; "
                "point it at a run's nerfstudio_models folder"
            )
        chosen = first_valid_checkpoint(candidates, folder, "resuming from")
        if chosen is not None:
            return chosen
        raise SystemExit(
            f"naka-gs: {flag} {folder}: every checkpoint there is corrupt or truncated "
            f"({', '.join(p.name for p in candidates)}); resume from another run's nerfstudio_models folder, "
            f"or train from scratch without {flag}"
        )


_IMPORTED_AT = time.time()
"""When this process imported the plugin: every ``ns-*`` command does so before it parses its options."""


def _eval_setup_config_path(frame: Optional[FrameType]) -> Optional[Path]:
    """The config.yml that nerfstudio's ``eval_setup`` is loading when ``frame`` is that call, else None.

    ``eval_setup(config_path)`` is where ``ns-eval``, ``ns-render``, ``ns-export``, ``ns-viewer`` (and our
    demo and scene sheet) load a run, and it asks the config for its checkpoint folder right after reading
    it. The config's own location is known only there: ``eval_setup`` parses the file's text, so the YAML
    loader never sees the path, and ``--load-config`` on the command line is one spelling of it in four
    CLIs (and means something else to ``ns-train``). Reading eval_setup's argument from the calling frame
    is exact for every caller; the upstream function is pinned by source hash in tests/test_run_folder.py."""
    if frame is None or frame.f_code.co_name != "eval_setup":
        return None
    if frame.f_globals.get("__name__") != "nerfstudio.utils.eval_utils":
        return None
    path = frame.f_locals.get("config_path")
    return Path(path) if path is not None else None


def _remove_new_empty_output_dir(eval_setup_frame: FrameType) -> None:
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


EXPORTED_FILES = {
    "ExportGaussianSplat": lambda command: [command.output_filename],
    "ExportCameraPoses": lambda command: ["transforms_train.json", "transforms_eval.json"],
}
"""The files that ``ns-export``'s commands for a splat model write into ``--output-dir``, by command class."""


def _check_export_target(eval_setup_frame: FrameType) -> None:
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


install_excepthook(_remove_new_empty_output_dir)  # a config.yml eval_setup cannot read: one line


def loading_error_exit(frame: Optional[FrameType], data: Optional[Path], err: BaseException) -> Optional[SystemExit]:
    """The one line to exit with when ``err``, a user error (:data:`~naka_gs_plugin.errors.USER_ERRORS`), was raised while nerfstudio's
    ``eval_setup`` (``frame``) set up the pipeline of the run it loads, whose scene is ``data``; else None.

    A scene folder no longer where config.yml records it (moved or deleted after training) is named with the
    fix: config.yml is the only place ``ns-eval`` / ``ns-render`` / ``ns-export`` / ``ns-viewer`` learn the
    scene from. The output folder ``ns-export`` has just made is removed again."""
    config_path = _eval_setup_config_path(frame)
    exit_ = user_error_exit(err)
    if frame is None or config_path is None or exit_ is None:
        return None
    _remove_new_empty_output_dir(frame)
    if data is None or Path(data).is_dir():
        return exit_
    where = f"{data}" if Path(data).is_absolute() else f"{data} (relative: looked for in {Path.cwd()})"
    return SystemExit(
        f"naka-gs: {config_path} records --data {where}, and no scene folder is there (moved or deleted since "
        "training): move the scene back there, or edit the data: path at the top of that config.yml"
    )


def checkpoint_mismatch_exit(loader: FrameType, problem: str) -> SystemExit:
    """The one line for a checkpoint that does not fit the pipeline it is loaded into (``problem``), loaded by
    ``loader``: upstream's ``eval_load_checkpoint`` (``eval_setup``: ns-eval & co.) or ``Trainer._load_checkpoint``
    (a resumed ns-train); each names the file in a local of its own (pinned by source hash in the tests)."""
    path = loader.f_locals.get("load_path") or loader.f_locals.get("load_checkpoint") or "(unnamed)"
    config_path = _eval_setup_config_path(loader.f_back)
    if config_path is not None:
        _remove_new_empty_output_dir(loader.f_back)
        fix = f"point data: in {config_path} back at the scene this run was trained on"
    else:
        fix = "resume a run only with the --data it was trained on, or leave out --load-dir to train from scratch"
    return SystemExit(f"naka-gs: checkpoint {path}: {problem} -- {fix}")


@dataclass
class NakaGSTrainerConfig(TrainerConfig):
    """nerfstudio's ``TrainerConfig`` for :class:`NakaGSTrainer`, with a run folder that can be trusted.

    Training: a run folder that already holds a run is refused (``--load-dir`` into it resumes it); a missing
    ``--data`` or an unwritable ``--output-dir`` is one line, before any folder is made. Loading
    (``eval_setup``): the run folder is the one config.yml is in, not the output path it records, so a
    copied or moved run loads its own checkpoints; of those, the newest valid one."""

    _target: Type = field(default_factory=lambda: NakaGSTrainer)

    def __post_init__(self) -> None:
        """``ns-train naka-gs --load-config FILE`` takes every option from FILE: check it (YAML, a run's
        configuration, known keys, values of their type and range) before nerfstudio reads it."""
        if self.load_config is not None:
            check_config_file(self.load_config)

    def set_timestamp(self) -> None:
        """Upstream's timestamp, then refuse a run folder that already holds a run, unless this run resumes
        it (``--load-dir`` / ``--load-checkpoint`` inside it). ``ns-train`` calls this just before it writes
        config.yml; programs that manage their own run folders (benchmarks.grid) call ``save_config`` only.
        ``ns-train --load-config <a run's config.yml>`` ends here too: its file fixes the run folder, so the
        refusal also says what to change in the file. Values out of range are refused first (one line)."""
        check_run_config(self, None)
        super().set_timestamp()
        run = self.get_base_dir()
        if not (run / "config.yml").exists():
            return
        models = (run / self.relative_model_dir).resolve()
        resumed = [Path(self.load_dir)] if self.load_dir is not None else []
        resumed += [Path(self.load_checkpoint).parent] if self.load_checkpoint is not None else []
        if any(folder.resolve() == models for folder in resumed):
            return
        # With --load-config, ns-train takes every option from that file and ignores the command line's, so
        # the flags that would help need their counterparts in the file.
        model_dir = run / self.relative_model_dir
        raise SystemExit(
            f"naka-gs: {run} already holds a run (its config.yml); resume it with --load-dir {model_dir} or pick "
            "another --timestamp -- with --load-config these flags are ignored (every option comes from the file): "
            f"set load_dir: {model_dir} in that file to resume, or change the timestamp: line in a copy for a new run"
        )

    def save_config(self) -> None:
        """Upstream's config.yml, after checking ``--data`` exists; a folder that cannot be made or written is
        one line. Records the folders it creates, which a failed ``NakaGSTrainer.setup`` removes again."""
        data = self.pipeline.datamanager.data or self.pipeline.datamanager.dataparser.data
        if data is not None and not Path(data).exists():
            raise SystemExit(
                f"naka-gs: --data {data}: no such scene folder; pass --data <folder with transforms_train.json>"
            )
        run = self.get_base_dir()
        created = [folder for folder in (run, *run.parents) if not folder.exists()]  # deepest first
        try:
            super().save_config()
        except OSError as err:
            raise SystemExit(
                f"naka-gs: cannot write the run folder {run} ({err.strerror or err}); pick a writable --output-dir"
            ) from None
        self._created_folders = created  # set after the YAML dump: not a field, never in config.yml

    def get_base_dir(self) -> Path:
        """The folder config.yml was loaded from, once ``eval_setup`` has loaded it; else upstream's
        ``<output_dir>/<experiment_name>/<method_name>/<timestamp>``."""
        loaded_from = getattr(self, "_loaded_from", None)
        return loaded_from if loaded_from is not None else super().get_base_dir()

    def get_checkpoint_dir(self) -> Path:
        """Upstream's checkpoint folder; when ``eval_setup`` asks, that of the folder config.yml is in, with
        ``load_step`` set to its newest valid checkpoint (one line names any skipped)."""
        frame = sys._getframe(1)
        config_path = _eval_setup_config_path(frame)
        if config_path is None:
            return super().get_checkpoint_dir()
        try:
            check_run_config(self, config_path)
        except SystemExit:
            _remove_new_empty_output_dir(frame)
            raise
        _check_export_target(frame)
        here = config_path.absolute().parent
        recorded = super().get_base_dir()
        if recorded.resolve() != here.resolve():
            CONSOLE.print(
                f"naka-gs: {config_path} records its run folder as {recorded}; using the folder it is in, {here} "
                "(a copied or moved run loads its own checkpoints)",
                markup=False,
                soft_wrap=True,
            )
        self._loaded_from = here
        folder = super().get_checkpoint_dir()
        # A load_step in config.yml next to a load_dir is the step that run resumed from, in another folder.
        up_to = self.load_step if self.load_dir is None else None
        candidates = checkpoints_newest_first(folder, up_to=up_to)
        chosen = first_valid_checkpoint(candidates, folder, "loading")
        if chosen is None:
            _remove_new_empty_output_dir(frame)
            if not candidates:
                raise SystemExit(
                    f"naka-gs: {folder}: no step-*.ckpt checkpoint there"
                    + (f" at or before step {up_to}" if up_to is not None else "")
                    + "; train this run first, or load the config.yml of a run that saved one"
                )
            raise SystemExit(
                f"naka-gs: {folder}: every checkpoint there is corrupt or truncated "
                f"({', '.join(p.name for p in candidates)}); nothing to load: train this run again"
            )
        self.load_step = checkpoint_step(chosen)
        return folder
