"""``NakaGSTrainer``: nerfstudio's ``Trainer`` with training state that survives Ctrl-C, kills and bad files.

- Ctrl-C finishes the running step, saves it and exits 130; a second Ctrl-C exits 130 at once.
- A checkpoint is written to a temporary file in its folder and published with ``os.replace``, so a
  write cut short (full disk, kill) never replaces or poses as a valid ``step-*.ckpt``.
- ``--load-dir`` / ``--load-checkpoint`` skip a corrupt or truncated checkpoint for the newest valid
  older one, and fail with one line naming the folder when none is valid.

Only the hooks are overridden; loading the chosen file is still upstream's code. The upstream methods
whose behaviour this relies on are pinned by source hash in ``tests/test_trainer_safety.py``.
"""

from __future__ import annotations

import os
import re
import secrets
import signal
import threading
import zipfile
from pathlib import Path
from typing import Literal, NoReturn, Optional

import torch
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.engine.trainer import Trainer
from nerfstudio.utils.decorators import check_main_thread
from nerfstudio.utils.rich_utils import CONSOLE

INTERRUPTED_EXIT_CODE = 130  # 128 + SIGINT, what shells report for a Ctrl-C'd command
CHECKPOINT_NAME = re.compile(r"step-(\d+)\.ckpt")
# Upstream's ns-eval/ns-viewer/ns-export parse every name in the checkpoint folder as int(name[first "-" + 1 :
# first "."]) and take the largest (eval_utils.eval_load_checkpoint). A temporary file left by a kill
# therefore has to parse, and to step 0, so that it never outranks a real checkpoint.
PARTIAL_PREFIX = "tmp-0."


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


def newest_checkpoint(folder: Path) -> Optional[Path]:
    """The ``step-*.ckpt`` in ``folder`` with the largest step, if any."""
    found = [p for p in folder.glob("step-*.ckpt") if checkpoint_step(p) is not None] if folder.is_dir() else []
    return max(found, key=checkpoint_step, default=None)  # type: ignore[arg-type]


def _fsync_dir(folder: Path) -> None:
    # Makes the rename durable before older checkpoints are deleted; directories cannot be opened on Windows.
    if hasattr(os, "O_DIRECTORY"):
        fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


class NakaGSTrainer(Trainer):
    """nerfstudio's ``Trainer`` with atomic checkpoints, Ctrl-C saving and corrupt-checkpoint fallback."""

    def setup(self, test_mode: Literal["test", "val", "inference"] = "val") -> None:
        """Upstream's setup, plus a callback that records the last fully completed step."""
        self._sigint_step: Optional[int] = None  # the step running when the first Ctrl-C came
        self._done_step: Optional[int] = None  # the last step whose iteration and callbacks finished
        self._deferring_sigint = False  # whether _on_sigint is installed (then _previous_sigint is restored)
        self._previous_sigint = None
        try:
            super().setup(test_mode=test_mode)
        except KeyboardInterrupt:
            self._exit_interrupted(f"interrupted during setup, before any training step; {self._newest_note()}")
        self.callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self._step_done))

    def train(self) -> None:
        """Upstream's training loop with Ctrl-C deferred to the end of the running step.

        Stopping between steps matters: an interrupt inside densification or an optimizer step would
        save parameters and optimizer state that no longer match."""
        # Handlers can only be set in the main thread; an ignored SIGINT (nohup, `cmd &` in a script) stays ignored.
        if threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGINT) != signal.SIG_IGN:
            self._previous_sigint = signal.signal(signal.SIGINT, self._on_sigint)
            self._deferring_sigint = True
        try:
            super().train()
        except KeyboardInterrupt:
            if self.training_state == "completed" and not self._deferring_sigint:
                raise  # upstream's "Ctrl-C to quit" the viewer after a finished training: keep its behaviour
            self._exit_interrupted(f"interrupted again during step {self.step}, not saved; {self._newest_note()}")
        finally:
            self._release_sigint()

    def _on_sigint(self, signum, frame) -> None:
        if self._sigint_step is not None:
            raise KeyboardInterrupt
        self._sigint_step = self.step
        self.stop_training = True  # also ends upstream's pause loop; _step_done re-sets it if train() resets it
        CONSOLE.print(
            f"naka-gs: Ctrl-C: finishing step {self.step}, then saving a checkpoint "
            "(Ctrl-C again: quit without saving)",
            markup=False,
            soft_wrap=True,
        )

    def _step_done(self, step: int) -> None:
        self._done_step = step
        if self._sigint_step is not None:
            self.stop_training = True

    def _release_sigint(self) -> None:
        if self._deferring_sigint:
            signal.signal(signal.SIGINT, self._previous_sigint or signal.SIG_DFL)  # None: a handler set outside Python
            self._deferring_sigint = False

    def _after_train(self) -> None:
        """On Ctrl-C: save the last completed step and exit 130; otherwise upstream's end of training."""
        if self._sigint_step is None:
            return super()._after_train()
        if self._done_step is None:
            self._exit_interrupted(f"interrupted before the first step finished; {self._newest_note()}")
        self.save_checkpoint(self._done_step)
        path = self.checkpoint_dir / f"step-{self._done_step:09d}.ckpt"
        self._exit_interrupted(
            f"interrupted; step {self._done_step} saved to {path} (resume with --load-dir {self.checkpoint_dir})"
        )

    def _train_complete_viewer(self) -> None:
        """Upstream waits here for Ctrl-C after a finished training; let that Ctrl-C through as before."""
        self._release_sigint()
        super()._train_complete_viewer()

    def _newest_note(self) -> str:
        newest = newest_checkpoint(self.checkpoint_dir)
        return f"newest checkpoint of this run: {newest}" if newest else "this run saved no checkpoint"

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
            return super()._load_checkpoint()
        # Upstream's --load-checkpoint branch loads exactly one file; point it at the chosen one for the call.
        config = self.config
        saved = config.load_dir, config.load_checkpoint
        config.load_dir, config.load_checkpoint = None, chosen
        try:
            super()._load_checkpoint()
        finally:
            config.load_dir, config.load_checkpoint = saved

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
            found = [p for p in folder.glob("step-*.ckpt") if checkpoint_step(p) is not None] if folder.is_dir() else []
            candidates = sorted(
                (p for p in found if newest is None or checkpoint_step(p) <= newest),  # type: ignore[operator]
                key=checkpoint_step,  # type: ignore[arg-type]
                reverse=True,
            )
        if not candidates:
            raise SystemExit(
                f"naka-gs: {flag} {folder}: no step-*.ckpt checkpoint there; "
                "point it at a run's nerfstudio_models folder"
            )
        for i, path in enumerate(candidates):
            if is_valid_checkpoint(path):
                if i:
                    skipped = ", ".join(p.name for p in candidates[:i])
                    CONSOLE.print(
                        f"naka-gs: skipping corrupt or truncated {skipped} in {folder}; resuming from {path.name}",
                        markup=False,
                        soft_wrap=True,
                    )
                return path
        raise SystemExit(
            f"naka-gs: {flag} {folder}: every checkpoint there is corrupt or truncated "
            f"({', '.join(p.name for p in candidates)}); resume from another run's nerfstudio_models folder, "
            f"or train from scratch without {flag}"
        )
