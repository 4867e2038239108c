"""A run's checkpoints: which files are checkpoints, whether one is whole, and the random state a resume needs.

``torch.save`` writes a zip archive; a checkpoint cut short (a kill, a full disk) lacks its central directory and a
damaged one fails a record's CRC, both found without unpickling anything (:func:`is_valid_checkpoint`).
"""

from __future__ import annotations

import os
import random
import re
import zipfile
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

import numpy as np
import torch
from nerfstudio.utils.rich_utils import CONSOLE

CHECKPOINT_NAME = re.compile(r"step-(\d+)\.ckpt")
# Upstream's ns-eval/ns-viewer/ns-export parse every name in the checkpoint folder as int(name[first "-" + 1 :
# first "."]) and take the largest (eval_utils.eval_load_checkpoint). A temporary file left by a kill
# therefore has to parse, and to step 0, so that it never outranks a real checkpoint.
PARTIAL_PREFIX = "tmp-0."
RESUME_STATE = "naka_gs_resume"
"""The checkpoint's entry for what an exact continuation needs besides upstream's model, optimizers, schedulers and
gradient scaler: the random generators, the datamanager's place in its view order, the model's densification
statistics. ``ns-eval`` & co. read only ``pipeline``; checkpoints of older versions have no such entry."""
RESUMED_PARTS = {"random": "random state", "datamanager": "view order", "model": "densification statistics"}


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


def random_state() -> Dict[str, Any]:
    """The global random generators' states: Python's, numpy's, torch's CPU one and, once CUDA is in use, its
    devices'. Plain values and tensors, which ``torch.load(weights_only=True)`` reads."""
    numpy = np.random.get_state(legacy=False)
    state: Dict[str, Any] = {
        "python": random.getstate(),
        "numpy": {
            "key": numpy["state"]["key"].tolist(),
            "pos": int(numpy["state"]["pos"]),
            "has_gauss": int(numpy["has_gauss"]),
            "gauss": float(numpy["gauss"]),
        },
        "torch": torch.get_rng_state(),
    }
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_random_state(state: Dict[str, Any]) -> bool:
    """Put back :func:`random_state`'s generators (CUDA's where this machine has as many devices); False, changing
    nothing, when ``state`` is not such a state."""
    # Each state is checked on a generator of its own before any global one changes.
    python, numpy, torch_cpu = random.Random(), np.random.RandomState(), torch.Generator()
    try:
        python.setstate(state["python"])
        saved = state["numpy"]
        key = np.array(saved["key"], dtype=np.uint32)
        numpy.set_state({"bit_generator": "MT19937", "state": {"key": key, "pos": saved["pos"]},
                         "has_gauss": saved["has_gauss"], "gauss": saved["gauss"]})  # fmt: skip
        torch_cpu.set_state(state["torch"])
    except (KeyError, TypeError, ValueError, RuntimeError):
        return False
    random.setstate(python.getstate())
    np.random.set_state(numpy.get_state())
    torch.set_rng_state(torch_cpu.get_state())
    cuda = state.get("cuda")
    if cuda is not None and torch.cuda.is_available() and len(cuda) == torch.cuda.device_count():
        torch.cuda.set_rng_state_all(cuda)
    return True


def fsync_dir(folder: Path) -> None:
    # Makes the rename durable before older checkpoints are deleted; directories cannot be opened on Windows.
    if hasattr(os, "O_DIRECTORY"):
        fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
