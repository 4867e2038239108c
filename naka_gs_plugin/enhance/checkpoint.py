"""Correction-network checkpoints: ours, the authors', and the shipped weights.

:func:`save_correction` / :func:`load_correction` read and write our format, a ``torch.save`` dict
``{"format": "naka-gs-correction", "config": ChromaGuidedConfig.to_dict(), "state_dict": {...}}``
(float16 weights are cast to float32 on load; extra keys such as an optimizer are ignored).
:func:`load_correction` also reads checkpoints written by the authors' ``naka_color_correction.py``
(``{"epoch", "model", "optimizer", "scheduler", "args", "best_psnr"}`` or a bare state dict),
through the explicit key table of :func:`authors_key_map`, including their older 3-channel
multiplicative head (its filters are averaged to one channel, as their loader does).
"""

from __future__ import annotations

import hashlib
from importlib.resources import files
from pathlib import Path
from typing import Dict, Optional, Union

import torch
from torch import Tensor

from naka_gs_plugin.enhance.correction_net import ChromaGuided, ChromaGuidedConfig
from naka_gs_plugin.errors import UserError

CHECKPOINT_FORMAT = "naka-gs-correction"
DEFAULT_WEIGHTS = Path(str(files("naka_gs_plugin.enhance") / "weights" / "chroma_guided_default.pt"))
"""The shipped weights (``EnhanceConfig.correction = "default"``)."""


class CorrectionWeightsError(UserError, ValueError):
    """A correction checkpoint that cannot be loaded (not a torch file, not this network's weights): a problem
    the user fixes by passing another file. The message is one line naming the file."""


class CorrectionWeightsNotFoundError(FileNotFoundError, CorrectionWeightsError):
    """A correction checkpoint path that names no file."""


def _conv_unit_keys(theirs: str, ours: str) -> Dict[str, str]:
    """Their ``ConvAct`` (``block.0`` conv without bias, ``block.1`` GroupNorm) -> our ``ConvUnit``."""
    return {
        f"{theirs}.block.0.weight": f"{ours}.conv.weight",
        f"{theirs}.block.1.weight": f"{ours}.norm.weight",
        f"{theirs}.block.1.bias": f"{ours}.norm.bias",
    }


def _res_block_keys(theirs: str, ours: str) -> Dict[str, str]:
    """Their ``ResidualBlock`` (``conv1``, ``conv2``) -> our ``ResBlock`` (``unit1``, ``unit2``)."""
    return {
        **_conv_unit_keys(f"{theirs}.conv1", f"{ours}.unit1"),
        **_conv_unit_keys(f"{theirs}.conv2", f"{ours}.unit2"),
    }


def _se_keys(theirs: str, ours: str) -> Dict[str, str]:
    """Their ``SEBlock`` (``fc.0``, ``fc.2`` 1x1 convs) -> our ``SqueezeExcite`` (``fc1``, ``fc2``)."""
    return {
        f"{theirs}.fc.0.weight": f"{ours}.fc1.weight",
        f"{theirs}.fc.0.bias": f"{ours}.fc1.bias",
        f"{theirs}.fc.2.weight": f"{ours}.fc2.weight",
        f"{theirs}.fc.2.bias": f"{ours}.fc2.bias",
    }


def authors_key_map(config: ChromaGuidedConfig) -> Dict[str, str]:
    """Every state-dict key of the authors' ``ChromaGuidedUNet`` -> our :class:`ChromaGuided` key.

    Their layout: ``stem``; ``down1..3`` = ``block`` (a Sequential: conv unit, residual blocks, SE)
    plus ``down``; ``bottleneck`` (Sequential: conv unit, 2 residual blocks, SE); ``up3..1`` =
    ``reduce`` plus ``block`` (2 residual blocks, SE); ``fuse`` (conv unit, residual block); heads.
    """
    table: Dict[str, str] = dict(_conv_unit_keys("stem", "stem"))
    for i, n_res in enumerate(config.enc_residual, start=1):
        table.update(_conv_unit_keys(f"down{i}.block.0", f"enc{i}.stage.conv_in"))
        for j in range(n_res):
            table.update(_res_block_keys(f"down{i}.block.{j + 1}", f"enc{i}.stage.res.{j}"))
        table.update(_se_keys(f"down{i}.block.{n_res + 1}", f"enc{i}.stage.se"))
        table.update(_conv_unit_keys(f"down{i}.down", f"enc{i}.down"))
    table.update(_conv_unit_keys("bottleneck.0", "bottleneck.conv_in"))
    for j in range(2):
        table.update(_res_block_keys(f"bottleneck.{j + 1}", f"bottleneck.res.{j}"))
    table.update(_se_keys("bottleneck.3", "bottleneck.se"))
    for i in (3, 2, 1):
        table.update(_conv_unit_keys(f"up{i}.reduce", f"dec{i}.stage.conv_in"))
        for j in range(2):
            table.update(_res_block_keys(f"up{i}.block.{j}", f"dec{i}.stage.res.{j}"))
        table.update(_se_keys(f"up{i}.block.2", f"dec{i}.stage.se"))
    table.update(_conv_unit_keys("fuse.0", "fuse.0"))
    table.update(_res_block_keys("fuse.1", "fuse.1"))
    for head in ("mul_head", "add_head"):
        table.update({f"{head}.weight": f"{head}.weight", f"{head}.bias": f"{head}.bias"})
    return table


def _authors_config(args: Optional[dict]) -> ChromaGuidedConfig:
    """Our config from their ``args`` dict (``base_ch``, ``mul_range``, ``add_range``, ``hf_*``)."""
    args = args or {}
    base = int(args.get("base_ch", 32))
    default = ChromaGuidedConfig()
    return ChromaGuidedConfig(
        widths=(base, 2 * base, 4 * base, 8 * base),
        enc_residual=(2, 2, 3),
        mul_range=float(args.get("mul_range", default.mul_range)),
        add_range=float(args.get("add_range", default.add_range)),
        lf_sigma=float(args.get("hf_sigma", default.lf_sigma)),
        lf_kernel=int(args.get("hf_kernel_size", default.lf_kernel)),
    )


def convert_authors_state_dict(state: Dict[str, Tensor], config: ChromaGuidedConfig) -> Dict[str, Tensor]:
    """Rename the authors' keys to ours; a 3-channel ``mul_head`` is averaged to one channel.

    Keys missing from the table are kept under their own name, so that ``load_state_dict`` reports
    them as unexpected instead of this function hiding them.
    """
    table = authors_key_map(config)
    out = {table.get(k, k): v for k, v in state.items()}
    for key in ("mul_head.weight", "mul_head.bias"):
        if key in out and out[key].shape[0] == 3:
            out[key] = out[key].mean(dim=0, keepdim=True)
    return out


def save_correction(net: ChromaGuided, path: Path, half: bool = True, extra: Optional[dict] = None) -> Path:
    """Write ``net`` in our checkpoint format (float16 weights by default, ~11 MB for the default net)."""
    state = {
        k: (v.detach().cpu().half() if half and v.is_floating_point() else v.detach().cpu())
        for k, v in net.state_dict().items()
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(
        {**(extra or {}), "format": CHECKPOINT_FORMAT, "config": net.config.to_dict(), "state_dict": state}, path
    )
    return path


def load_correction(path: Union[str, Path]) -> ChromaGuided:
    """A :class:`ChromaGuided` in eval mode, float32, from our checkpoint or the authors' (see module doc).

    Raises :class:`CorrectionWeightsNotFoundError` (a ``FileNotFoundError``) or :class:`CorrectionWeightsError`
    (a ``ValueError``) with a one-line message naming ``path``. Leaves torch's random state as it found it.
    """
    path = Path(path)
    if not path.is_file():
        raise CorrectionWeightsNotFoundError(f"correction checkpoint {path} not found: pass an existing .pt/.pth file")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # pickle/zip errors have many types; all mean "not a torch checkpoint"
        raise CorrectionWeightsError(
            f"{path} is not a readable torch checkpoint ({type(err).__name__}): re-save it with torch.save"
        ) from None
    if not isinstance(ckpt, dict):
        raise CorrectionWeightsError(
            f"{path} holds a {type(ckpt).__name__}, not a checkpoint dict: expected a naka-gs correction checkpoint"
        )
    state = ckpt.get("state_dict", ckpt.get("model", ckpt))
    if not isinstance(state, dict) or not all(isinstance(v, Tensor) for v in state.values()):
        raise CorrectionWeightsError(
            f"{path} has no state dict under 'state_dict' or 'model': expected a naka-gs correction checkpoint"
        )
    authors = "stem.block.0.weight" in state
    try:
        if authors:
            config = _authors_config(ckpt.get("args") if isinstance(ckpt.get("args"), dict) else None)
            state = convert_authors_state_dict(state, config)
        elif isinstance(ckpt.get("config"), dict):
            config = ChromaGuidedConfig.from_dict(ckpt["config"])
        else:
            raise ValueError("it has our key layout but no 'config' dict; save it with save_correction")
        # Its random initialisation is overwritten: leave torch's random state as it was, so that a run whose
        # enhancement is computed trains as one that finds it in the cache.
        with torch.random.fork_rng(devices=[]):
            net = ChromaGuided(config)
        incompatible = net.load_state_dict(
            {k: v.float() if v.is_floating_point() else v for k, v in state.items()}, strict=False
        )
    except (ValueError, TypeError, RuntimeError) as err:
        msg = " ".join(str(err).split())
        raise CorrectionWeightsError(f"{path} does not fit the correction network: {msg[:300]}") from None
    if incompatible.missing_keys or incompatible.unexpected_keys:
        raise CorrectionWeightsError(
            f"{path} does not fit the correction network ({'authors' if authors else 'naka-gs'} layout): "
            f"{len(incompatible.missing_keys)} missing keys (e.g. {incompatible.missing_keys[:2]}), "
            f"{len(incompatible.unexpected_keys)} unexpected (e.g. {incompatible.unexpected_keys[:2]}); "
            "expected a naka-gs or naka_color_correction.py checkpoint"
        )
    return net.eval()


def file_digest(path: Union[str, Path]) -> str:
    """SHA-1 of a file's bytes (the correction part of the enhancement cache key)."""
    h = hashlib.sha1()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()
