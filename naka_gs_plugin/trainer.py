"""``NakaGSTrainer``: nerfstudio's ``Trainer`` with training state that survives Ctrl-C, kills and bad files.

- Ctrl-C finishes the running step, saves it and exits 130; a second Ctrl-C exits 130 at once.
- A checkpoint is written to a temporary file in its folder and published with ``os.replace``, so a
  write cut short (full disk, kill) never replaces or poses as a valid ``step-*.ckpt``.
- ``--load-dir`` / ``--load-checkpoint`` skip a corrupt or truncated checkpoint for the newest valid
  older one, and fail with one line naming the folder when none is valid.
- A checkpoint also holds what upstream's leaves out of a run's state (:data:`RESUME_STATE`: the random generators,
  the datamanager's place in its view order, the densification statistics), so a run resumed from it, after a
  ``kill -9`` too, continues as it would have uninterrupted: on a CPU it ends with the same model bit for bit. A
  checkpoint without them (an older version's) resumes with one line saying that the continuation is not exact.
- SIGTERM is handled as Ctrl-C, exiting 143 (128 + the signal, the shells' convention); either one before the first
  training step has finished (while the
  training images load and are enhanced, which can take minutes) stops at once, nothing to save.
- With ``--vis tensorboard``, the scalars nerfstudio records at every step (iteration time, ETA, rays per second,
  learning rates) are written at the steps it logs the losses at (:class:`LoggedStepsTensorboardWriter`).
- One of the plugin's own errors for a problem the user can fix (:class:`~naka_gs_plugin.errors.UserError`: a bad scene file,
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
whose behaviour this relies on are pinned by source hash in ``tests/run/test_trainer_safety.py`` and
``tests/run/test_run_folder.py``.
"""

from __future__ import annotations

import os
import secrets
import signal
import threading
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, Dict, Literal, NoReturn, Optional, Type, Union

import torch
import tyro
from nerfstudio.configs.base_config import MachineConfig
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.engine.trainer import Trainer, TrainerConfig
from nerfstudio.utils import writer
from nerfstudio.utils.decorators import check_main_thread
from nerfstudio.utils.misc import step_check
from nerfstudio.utils.rich_utils import CONSOLE

from naka_gs_plugin.errors import OS_ERROR_FIXES, os_error_exit, signal_exit_status, user_error_exit
from naka_gs_plugin.run import nerfstudio_hooks as hooks
from naka_gs_plugin.run.checkpoints import (
    PARTIAL_PREFIX,
    RESUME_STATE,
    RESUMED_PARTS,
    checkpoint_step,
    checkpoints_newest_first,
    first_valid_checkpoint,
    fsync_dir,
    newest_checkpoint,
    random_state,
    set_random_state,
)
from naka_gs_plugin.run.claim import claim_run_folder, give_up_run_folder
from naka_gs_plugin.run.config_check import check_config_file, check_run_config

INTERRUPTED_EXIT_CODE = signal_exit_status(signal.SIGINT)  # 130, what shells report for a Ctrl-C'd command
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
PER_STEP_SCALARS = frozenset(
    event.value
    for event in (writer.EventName.ITER_TRAIN_TIME, writer.EventName.ETA, writer.EventName.TRAIN_RAYS_PER_SEC)
)
"""Scalars nerfstudio's training loop records at every step, besides each optimizer group's ``learning_rate/<group>``."""


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

    def __init__(self, config: TrainerConfig, local_rank: int = 0, world_size: int = 1) -> None:
        hooks.activate()  # a naka-gs run: its checkpoints load with numpy's scalars as safe globals
        if isinstance(config, NakaGSTrainerConfig):
            config.resolve_device()  # upstream picks the device from the config here
        super().__init__(config, local_rank, world_size)

    def setup(self, test_mode: Literal["test", "val", "inference"] = "val") -> None:
        """Upstream's setup, plus a callback that records the last fully completed step. A setup that fails
        removes the run folder ``save_config`` has just made (nothing was trained into it); a user error
        (:class:`~naka_gs_plugin.errors.UserError`: an empty ``--data`` folder, a truncated COLMAP model...) is then one line."""
        self._stop_step: Optional[int] = None  # the step running when the first Ctrl-C / SIGTERM came
        self._stop_name = "interrupted"  # "Ctrl-C" or "SIGTERM" once one came
        self._stop_signum = signal.SIGINT  # the signal that stops the run (a KeyboardInterrupt of its own: Ctrl-C)
        self._done_step: Optional[int] = None  # the last step whose iteration and callbacks finished
        self._previous_handlers: dict = {}  # the signal handlers _on_stop_signal replaced (restored after)
        self._catch_stop_signals()
        tensorboard = partial(LoggedStepsTensorboardWriter, every=self.config.logging.steps_per_log)
        try:
            with hooks.tensorboard_writer_replaced(tensorboard):
                super().setup(test_mode=test_mode)
        except KeyboardInterrupt:
            self._discard_new_run_folder()
            self._exit_interrupted(f"{self._stop_name} during setup, before any training step; {self._newest_note()}")
        except BaseException as err:
            self._discard_new_run_folder()
            exit_ = user_error_exit(err)
            if exit_ is None and isinstance(err, OSError) and err.errno in OS_ERROR_FIXES:
                exit_ = os_error_exit(err)  # a path too long, a full disk...: the user's to fix
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
        A user error (:class:`~naka_gs_plugin.errors.UserError`: an unreadable training image, a diverged loss) is one line."""
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
            if isinstance(self.config, NakaGSTrainerConfig):
                self.config.release_run_folder()

    def _catch_stop_signals(self) -> None:
        # Handlers can only be set in the main thread; an ignored signal (nohup, `cmd &` in a script) stays ignored.
        if threading.current_thread() is not threading.main_thread():
            return
        for signum in STOP_SIGNALS:
            if signal.getsignal(signum) != signal.SIG_IGN:
                self._previous_handlers[signum] = signal.signal(signum, self._on_stop_signal)

    def _on_stop_signal(self, signum, frame) -> None:
        self._stop_name = "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name
        self._stop_signum = signum
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
        """On Ctrl-C / SIGTERM: save the last completed step and exit 130 / 143; otherwise upstream's end of training."""
        if self._stop_step is None:
            return super()._after_train()
        assert self._done_step is not None  # _on_stop_signal stops at once before the first step finished
        self.save_checkpoint(self._done_step)
        path = self.checkpoint_dir / f"step-{self._done_step:09d}.ckpt"
        self._exit_interrupted(
            f"interrupted; step {self._done_step} saved to {path} ({self._resume_hint(self._done_step)})"
        )

    def _resume_hint(self, saved_step: int) -> str:
        """How to resume from ``saved_step`` and end where this run would have: upstream's ``--max-num-iterations``
        counts the steps a run trains after its checkpoint, so the same command would train them all again."""
        left = self._start_step + self.config.max_num_iterations - 1 - saved_step
        return f"resume with --load-dir {self.checkpoint_dir} --max-num-iterations {left} to end at the same step"

    def _train_complete_viewer(self) -> None:
        """Upstream waits here for Ctrl-C after a finished training; let that Ctrl-C through as before."""
        self._release_stop_signals()
        super()._train_complete_viewer()

    def _newest_note(self) -> str:
        newest = newest_checkpoint(self.checkpoint_dir)
        return f"newest checkpoint of this run: {newest}" if newest else "this run saved no checkpoint"

    def _discard_new_run_folder(self) -> None:
        """Remove the config.yml, the claim and the folders that ``NakaGSTrainerConfig.save_config`` created for this
        run; a folder that holds anything else (another process's run) stays."""
        if isinstance(self.config, NakaGSTrainerConfig):
            self.config.release_run_folder(remove_created=True)

    def _exit_interrupted(self, what: str) -> NoReturn:
        CONSOLE.print(f"naka-gs: {what}", markup=False, soft_wrap=True)
        raise SystemExit(signal_exit_status(self._stop_signum))

    @check_main_thread
    def save_checkpoint(self, step: int) -> None:
        """Upstream's checkpoint plus :data:`RESUME_STATE`, written to ``tmp-0.<pid>-<random>.<name>.partial`` and
        published with ``os.replace``; older checkpoints are deleted (when only the latest is kept) only after that."""
        self.checkpoint_dir.mkdir(parents=True, exist_ok=True)
        path = self.checkpoint_dir / f"step-{step:09d}.ckpt"
        partial = self.checkpoint_dir / f"{PARTIAL_PREFIX}{os.getpid()}-{secrets.token_hex(4)}.{path.name}.partial"
        # Upstream's save_checkpoint dict (pinned by source hash in the tests), plus our entry.
        state = {
            "step": step,
            "pipeline": self.pipeline.module.state_dict()  # type: ignore
            if hasattr(self.pipeline, "module")
            else self.pipeline.state_dict(),
            "optimizers": {k: v.state_dict() for (k, v) in self.optimizers.optimizers.items()},
            "schedulers": {k: v.state_dict() for (k, v) in self.optimizers.schedulers.items()},
            "scalers": self.grad_scaler.state_dict(),
            RESUME_STATE: self._resume_state(),
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
        fsync_dir(self.checkpoint_dir)
        if self.config.save_only_latest_checkpoint:
            for old in self.checkpoint_dir.glob("*.ckpt"):
                if old != path:
                    old.unlink()

    def _resume_state(self) -> Dict[str, Any]:
        """:data:`RESUME_STATE`: the random generators, and each part of the pipeline's own (``resume_state()``)."""
        state: Dict[str, Any] = {"random": random_state()}
        for name in ("datamanager", "model"):
            part = getattr(self.pipeline, name, None)
            if hasattr(part, "resume_state"):
                state[name] = part.resume_state()
        return state

    def _load_checkpoint(self) -> None:
        """Upstream's loading of the newest valid checkpoint that ``--load-dir`` / ``--load-checkpoint`` allow, then
        what continues the run exactly (:data:`RESUME_STATE`)."""
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
        if chosen is not None:
            self._restore_resume_state(chosen)

    def _restore_resume_state(self, path: Path) -> None:
        """Put back the random generators, the view order and the densification statistics ``path`` holds, so that
        the run continues as it would have uninterrupted; one line names what it lacks (an older checkpoint)."""
        # Upstream has just loaded the file and keeps none of it; mapped, only the pickled entries are read again.
        saved = torch.load(str(path), map_location="cpu", mmap=True).get(RESUME_STATE)
        saved = saved if isinstance(saved, dict) else {}
        restorers = {"random": set_random_state}
        for name in ("datamanager", "model"):
            part = getattr(self.pipeline, name, None)
            if hasattr(part, "load_resume_state"):
                restorers[name] = part.load_resume_state
        lacking = [
            RESUMED_PARTS[name]
            for name, restore in restorers.items()
            if not (isinstance(saved.get(name), dict) and restore(saved[name]))
        ]
        if lacking:
            CONSOLE.print(
                f"naka-gs: {path} holds no {', '.join(lacking)} (saved by an older naka-gs): training resumes from "
                f"step {self._start_step}, but does not continue exactly as the interrupted run would have",
                markup=False,
                soft_wrap=True,
            )

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


RUN_FILE_ROOM = 100
"""Characters a run folder's path leaves for what a run writes in it: tensorboard's
``events.out.tfevents.<time>.<host>.<pid>.<n>`` (written from a thread, whose error would be a traceback) and
``nerfstudio_models/step-<9 digits>.ckpt``, with room for a long host name."""


def _path_max(folder: str) -> int:
    """The longest path the system takes (4,096 on Linux), asked of ``folder``'s nearest existing parent."""
    probe = folder
    while not os.path.exists(probe) and os.path.dirname(probe) != probe:
        probe = os.path.dirname(probe)
    try:
        return os.pathconf(probe, "PC_PATH_MAX")
    except (OSError, ValueError, AttributeError):
        return 4096


@dataclass
class NakaGSMachineConfig(MachineConfig):
    """nerfstudio's machine options, with a device that defaults to the machine's own."""

    device_type: Literal["auto", "cpu", "cuda", "mps"] = "auto"
    """auto: cuda where this machine has it, else cpu (nerfstudio's default, cuda, dies without one). The naka-gs
    preset's schedule follows it: see ``ns-train naka-gs --help``'s description."""


@dataclass
class NakaGSTrainerConfig(TrainerConfig):
    """nerfstudio's ``TrainerConfig`` for :class:`NakaGSTrainer`, with a run folder that can be trusted.

    Training: a run folder that already holds a run is refused (``--load-dir`` into it resumes it); a missing
    ``--data`` or an unwritable ``--output-dir`` is one line, before any folder is made. Loading
    (``eval_setup``): the run folder is the one config.yml is in, not the output path it records, so a
    copied or moved run loads its own checkpoints; of those, the newest valid one."""

    _target: Type = field(default_factory=lambda: NakaGSTrainer)
    machine: NakaGSMachineConfig = field(default_factory=NakaGSMachineConfig)
    steps_per_eval_image: Optional[int] = 500
    """Steps between evaluations of one test view during training; None: by device (the preset's ``by_device``)."""
    steps_per_eval_all_images: Optional[int] = 25000
    """Steps between evaluations of all test views during training; None: by device (the preset's ``by_device``)."""
    by_device: tyro.conf.Suppress[Dict[str, Dict[str, Any]]] = field(default_factory=dict)
    """What the run takes by device (``cpu`` / ``cuda``): dotted option -> value, set where the option is None once
    the run's device is known (:meth:`resolve_device`), then emptied. Filled by the presets, not a command-line
    option."""

    def resolve_device(self) -> None:
        """Settle ``--machine.device-type auto`` (CUDA where this machine has it, else the CPU), then set every option
        left to the device: the :attr:`by_device` entries for it and the model's schedule. Idempotent; called before
        the run's config.yml is written and before it trains."""
        if self.machine.device_type == "auto":
            self.machine.device_type = "cuda" if torch.cuda.is_available() else "cpu"
        device = "cuda" if self.machine.device_type == "cuda" else "cpu"
        for dotted, value in (getattr(self, "by_device", None) or {}).get(device, {}).items():
            *parents, name = dotted.split(".")
            owner: Any = self
            for part in parents:
                owner = owner[part] if isinstance(owner, dict) else getattr(owner, part)
            if owner is not None and getattr(owner, name, None) is None:
                setattr(owner, name, value)
        self.by_device = {}
        resolve = getattr(self.pipeline.model, "resolve_schedule", None)
        if resolve is not None:
            resolve(device)

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
        refusal also says what to change in the file. Values out of range are refused first (one line). The run's
        device settles here (:meth:`resolve_device`), and the naka-gs hooks turn on."""
        hooks.activate()
        self.resolve_device()
        check_run_config(self, None)
        super().set_timestamp()
        self._refuse_a_run_folder_outside_output_dir()
        self._refuse_a_run_folder_in_use()

    def _refuse_a_run_folder_outside_output_dir(self) -> None:
        """Exit with one line when ``--experiment-name``, ``--method-name`` or ``--timestamp`` would put the run
        folder outside ``--output-dir`` (``..``, an absolute path): a run stays in the folder it was asked into."""
        out = os.path.normpath(os.path.abspath(self.output_dir))
        for flag, value in (
            ("--experiment-name", self.experiment_name),
            ("--method-name", self.method_name),
            ("--timestamp", self.timestamp),
        ):
            if value is None:
                continue
            inside = os.path.normpath(os.path.join(out, str(value)))
            if os.path.isabs(str(value)) or ".." in Path(str(value)).parts or os.path.commonpath([out, inside]) != out:
                raise SystemExit(
                    f"naka-gs: {flag} {value}: the run folder would lie outside --output-dir {self.output_dir} -- "
                    f"give {flag} a plain name (no '..', not an absolute path), or choose another --output-dir"
                )
        run = os.path.abspath(self.get_base_dir())
        limit = _path_max(out) - RUN_FILE_ROOM
        if len(run) > limit:
            raise SystemExit(
                f"naka-gs: --output-dir {str(self.output_dir)[:60]}...: the run folder's path is {len(run)} characters, "
                f"and the files a run writes in it need it under {limit} (the system allows {limit + RUN_FILE_ROOM}) "
                "-- choose a shorter --output-dir"
            )

    def _refuse_a_run_folder_in_use(self) -> None:
        """Exit with one line when the run folder holds a run's config.yml that this run does not resume."""
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
        hooks.activate()
        self.resolve_device()
        data = self.pipeline.datamanager.data or self.pipeline.datamanager.dataparser.data
        if data is not None and not Path(data).exists():
            raise SystemExit(
                f"naka-gs: --data {data}: no such scene folder; pass --data <folder with transforms_train.json>"
            )
        run = self.get_base_dir()
        created = [folder for folder in (run, *run.parents) if not folder.exists()]  # deepest first
        token = None
        try:
            run.mkdir(parents=True, exist_ok=True)
            token = claim_run_folder(run)
            # Checked again now that the folder is ours: a run that got there between set_timestamp and the claim.
            self._refuse_a_run_folder_in_use()
            super().save_config()
        except BaseException as err:
            # Refused by another run's claim: the folders are that run's, whoever made them.
            give_up_run_folder(run, token, created if token is not None or isinstance(err, OSError) else [])
            if isinstance(err, OSError):
                raise SystemExit(
                    f"naka-gs: cannot write the run folder {run} ({err.strerror or err}); pick a writable --output-dir"
                ) from None
            raise
        # Set after the YAML dump: not fields, never in config.yml.
        self._created_folders, self._run_claim = created, token

    def release_run_folder(self, remove_created: bool = False) -> None:
        """Give up this run's claim of its folder (:func:`claim_run_folder`); with ``remove_created`` (a setup that
        failed), also remove the config.yml and the folders :meth:`save_config` created, unless one holds anything
        else (another process's run)."""
        created = self.__dict__.pop("_created_folders", None) or []
        give_up_run_folder(
            self.get_base_dir(), self.__dict__.pop("_run_claim", None), created if remove_created else []
        )

    def get_base_dir(self) -> Path:
        """The folder config.yml was loaded from, once ``eval_setup`` has loaded it; else upstream's
        ``<output_dir>/<experiment_name>/<method_name>/<timestamp>``."""
        loaded_from = getattr(self, "_loaded_from", None)
        return loaded_from if loaded_from is not None else super().get_base_dir()

    def get_checkpoint_dir(self) -> Path:
        """Upstream's checkpoint folder; when ``eval_setup`` asks, that of the folder config.yml is in, with
        ``load_step`` set to its newest valid checkpoint (one line names any skipped)."""
        frame, config_path = hooks.calling_eval_setup()
        if frame is None or config_path is None:
            return super().get_checkpoint_dir()
        hooks.activate()  # eval_setup is loading a naka-gs run
        try:
            check_run_config(self, config_path)
        except SystemExit:
            hooks.remove_new_empty_output_dir(frame)
            raise
        hooks.check_export_target(frame)
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
            hooks.remove_new_empty_output_dir(frame)
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
