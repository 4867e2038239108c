"""``naka-gs-train-correction``: train the chroma-correction network on paired low/normal-light images.

Paired sources (all images sRGB-encoded, 8- or 16-bit; pairs matched by file name):

* LOL-style roots: ``<root>/train/{low,high}/`` for training, ``<root>/eval/{low,high}/`` for validation;
* ``lowlight-data`` scenes with ``low/`` + ``high/`` (LOM): ``transforms_train.json`` frames (``low/<n>``)
  train, ``transforms_test.json`` frames (``high/<n>``) validate; each frame's partner has the same name
  in the other folder;
* simulator scenes (``naka-gs-sim``): ``train/<n>`` + ``train_gt/<n>.png`` (training only).

Recipe (reference ``train()``): AdamW (lr 2e-4, wd 1e-4), cosine schedule stepped per epoch, batch 8,
random rescale 0.7-1.4 (bilinear, each side floored at the crop), random crop, h/v flips and a 90 degree
rotation (p = 0.5 each), Naka computed on the augmented crop (per-crop min-max), grad-norm clip 1.0,
mask-guided loss (:mod:`naka_gs_plugin.enhance.correction_loss`). Validation: full-resolution PSNR
``10 log10(1 / (MSE + 1e-8))`` averaged per image, every epoch (epoch 0 = before training).
Checkpoints ``latest.pt`` (every epoch) and ``best.pt`` (best validation PSNR) are
:func:`~naka_gs_plugin.enhance.checkpoint.save_correction` files (float32) plus the optimizer,
scheduler, epoch, history and this config, so :func:`~naka_gs_plugin.enhance.checkpoint.load_correction`
reads them directly.

A YAML recipe sets the defaults: ``naka-gs-train-correction --config configs/correction/default.yaml``
(flags after it override single values).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import cv2
import numpy as np
import torch
import torch.nn.functional as F
import yaml
from jaxtyping import Float
from rich.console import Console
from torch import Tensor

from naka_gs_plugin.cpu import fit_threads
from naka_gs_plugin.data.images import IMAGE_SUFFIXES, as_float, read_stored
from naka_gs_plugin.enhance.checkpoint import load_correction, save_correction
from naka_gs_plugin.enhance.correction import MODES, CorrectionRunner
from naka_gs_plugin.enhance.correction_loss import CorrectionLoss
from naka_gs_plugin.enhance.correction_net import ChromaGuided, ChromaGuidedConfig, apply_maps
from naka_gs_plugin.enhance.naka import naka_enhance
from naka_gs_plugin.errors import UserError
from naka_gs_plugin.metrics import psnr
from naka_gs_plugin.progress import StageProgress
from naka_gs_plugin.shipped import config_file

CONSOLE = Console(width=120)
"""The trainer's console (rich's, as nerfstudio's: this module imports without nerfstudio)."""


class CorrectionTrainingError(UserError, ValueError):
    """A training option, recipe or data source the correction trainer cannot use; one line naming it."""


@dataclass
class TrainConfig:
    """Training of the correction network (defaults: the reference recipe, 200 epochs)."""

    config: Optional[Path] = None
    """YAML recipe whose keys (this dataclass's field names) set the defaults; flags override them."""
    output_dir: Path = Path("outputs/correction")
    """Where latest.pt, best.pt and history.json are written."""
    model: ChromaGuidedConfig = field(default_factory=ChromaGuidedConfig)
    """Network architecture (default: the reference's, 5.44 M parameters); stored in every checkpoint."""
    neutral_init: bool = False
    """Zero the two output heads so training starts from neutral maps (output = the Naka image) instead of
    PyTorch's default initialisation (the reference's); helps short CPU budgets."""
    lol: Tuple[Path, ...] = ()
    """LOL-style roots: <root>/train/{low,high} train, <root>/eval/{low,high} validate."""
    lom: Tuple[Path, ...] = ()
    """lowlight-data scenes with low/ + high/: transforms_train.json frames train, transforms_test.json validate."""
    sim: Tuple[Path, ...] = ()
    """Simulator scenes: train/<n> + train_gt/<n>.png (training only)."""
    hold_out: Tuple[str, ...] = ()
    """Folder names of ``--lom``/``--sim`` scenes to leave out entirely, training and validation (the
    leave-one-scene-out weights of the real-scene protocol: ``--hold-out sofa``). Each must name one."""
    lol_weight: float = 1.0
    """Relative sampling weight of each LOL pair (1 for every source = uniform over all pairs)."""
    lom_weight: float = 1.0
    """Relative sampling weight of each LOM-scene pair."""
    sim_weight: float = 1.0
    """Relative sampling weight of each simulator pair."""
    epochs: int = 200
    batch_size: int = 8
    crop: int = 256
    """Square training crop, pixels."""
    images_per_epoch: Optional[int] = None
    """Crops per epoch (one per drawn pair); default: every training pair once. Iterations = this // batch."""
    lr: float = 2e-4
    weight_decay: float = 1e-4
    grad_clip: float = 1.0
    scale_range: Tuple[float, float] = (0.7, 1.4)
    """Uniform random rescale factor of each pair before cropping."""
    min_edge_correlation: float = 0.3
    """Pairs whose Naka(low) vs high gradient-magnitude correlation is below this are dropped as misaligned.
    On LOL train + LOM the aligned pairs score >= 0.62 and the one misaligned pair (LOL 648, shifted ~60 px)
    0.06."""
    vgg_weights: Optional[Path] = None
    """torchvision VGG19 ImageNet state dict (vgg19-dcbb9e9d.pth) for the perceptual term; none: term off."""
    bf16: bool = False
    """bfloat16 autocast of the network's forward pass (loss in float32)."""
    device: str = "auto"
    """Where the network trains and validates: ``auto`` (CUDA when available, else the CPU), ``cpu``,
    ``cuda`` or ``cuda:N``. Data loading and augmentation stay on the CPU."""
    threads: Optional[int] = None
    """torch CPU threads (default: torch's choice)."""
    seed: int = 42
    resume: Optional[Path] = None
    """Continue from this checkpoint (e.g. <output_dir>/latest.pt): weights, optimizer, scheduler, epoch."""
    export_to: Optional[Path] = None
    """After training, write best.pt here as shippable float16 weights (:func:`export_weights`)."""
    log_every: int = 10
    """Log a training-loss line every this many iterations (for log files, where no bar is drawn)."""
    val_mode: str = "exact"
    """Validation forward: an inference mode (naka_gs_plugin.enhance.correction.MODES; ``exact``: the plain
    float32 forward), or ``half``: ``exact`` with the maps predicted at half resolution and upsampled
    bilinearly (about 4x cheaper; selects checkpoints, it is no inference mode: it loses SSIM). PSNR is
    always computed at full resolution."""


@dataclass
class Pair:
    """One low/normal-light image pair; ``source`` is ``lol``, ``lom`` or ``sim``."""

    low: Path
    high: Path
    source: str

    @property
    def name(self) -> str:
        return f"{self.low.parent.parent.name}/{self.low.name}"


def _images(folder: Path) -> Dict[str, Path]:
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder} is not a folder: expected paired low/high image folders")
    return {p.name: p for p in sorted(folder.iterdir()) if p.suffix.lower() in IMAGE_SUFFIXES}


def lol_pairs(root: Path, split: str) -> List[Pair]:
    """``<root>/<split>/low/<n>`` with ``<root>/<split>/high/<n>``."""
    low, high = _images(root / split / "low"), _images(root / split / "high")
    missing = sorted(set(low) - set(high))
    if missing:
        raise FileNotFoundError(
            f"{root / split / 'high' / missing[0]} missing ({len(missing)} low images without a partner)"
        )
    if not low:
        raise FileNotFoundError(f"{root / split / 'low'} holds no images")
    return [Pair(low[n], high[n], "lol") for n in sorted(low)]


def lom_pairs(scene: Path, split: str) -> List[Pair]:
    """Frames of ``transforms_<split>.json``; each frame's file name is looked up in ``low/`` and ``high/``."""
    meta = scene / f"transforms_{split}.json"
    if not meta.is_file():
        raise FileNotFoundError(f"{meta} not found: expected a lowlight-data scene with low/ and high/")
    pairs = []
    for frame in json.loads(meta.read_text(encoding="utf-8-sig"))["frames"]:
        name = Path(frame["file_path"]).name
        low, high = scene / "low" / name, scene / "high" / name
        for p in (low, high):
            if not p.is_file():
                raise FileNotFoundError(f"{p} not found (frame {frame['file_path']} of {meta}): needs low/ and high/")
        pairs.append(Pair(low, high, "lom"))
    return pairs


def sim_pairs(scene: Path) -> List[Pair]:
    """Simulator ``train/<stem>.*`` with ``train_gt/<stem>.png``."""
    low, gt = _images(scene / "train"), _images(scene / "train_gt")
    gt_by_stem = {Path(n).stem: p for n, p in gt.items()}
    pairs = []
    for name, p in low.items():
        if Path(name).stem not in gt_by_stem:
            raise FileNotFoundError(f"{scene / 'train_gt' / (Path(name).stem + '.png')} missing for {p}")
        pairs.append(Pair(p, gt_by_stem[Path(name).stem], "sim"))
    return pairs


def naka_np(image: Float[np.ndarray, "H W 3"]) -> Float[np.ndarray, "H W 3"]:
    """The reference Naka pre-enhancement (per-image statistics) of one float image."""
    return naka_enhance(torch.from_numpy(image)).numpy()


def edge_correlation(low: np.ndarray, high: np.ndarray) -> float:
    """Pearson correlation of the gradient magnitudes of Naka(low) and high (luma, half resolution, blur 1 px).

    Gradients ignore the tone differences between a Naka image and the normal-light one (plain luma
    correlation is as low for well-aligned pairs with different lighting), but drop sharply with any shift.
    """
    mags = []
    for img in (naka_np(as_float(low)), as_float(high)):
        luma = img @ np.array([0.299, 0.587, 0.114], np.float32)
        luma = cv2.GaussianBlur(cv2.resize(luma, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA), (0, 0), 1.0)
        gx, gy = cv2.Sobel(luma, cv2.CV_32F, 1, 0), cv2.Sobel(luma, cv2.CV_32F, 0, 1)
        mags.append(np.sqrt(gx * gx + gy * gy).ravel())
    if mags[0].std() < 1e-8 or mags[1].std() < 1e-8:
        return 0.0
    return float(np.corrcoef(mags[0], mags[1])[0, 1])


class PairSet:
    """Pairs decoded into memory (uint8/uint16) once."""

    def __init__(self, pairs: Sequence[Pair], description: str) -> None:
        self.pairs = list(pairs)
        self.low: List[np.ndarray] = []
        self.high: List[np.ndarray] = []
        with StageProgress(CONSOLE) as progress:
            task = progress.add_task(description, total=len(self.pairs))
            for p in self.pairs:
                low, high = read_stored(p.low), read_stored(p.high)
                if low.shape != high.shape:
                    raise CorrectionTrainingError(
                        f"{p.low} is {low.shape[1]}x{low.shape[0]} but {p.high} is {high.shape[1]}x{high.shape[0]}"
                    )
                self.low.append(low)
                self.high.append(high)
                progress.advance(task)

    def __len__(self) -> int:
        return len(self.pairs)

    def drop_misaligned(self, threshold: float) -> List[Tuple[str, float]]:
        """Remove pairs with :func:`edge_correlation` < threshold; returns their names and scores."""
        scores = [edge_correlation(lo, hi) for lo, hi in zip(self.low, self.high)]
        keep = [i for i, s in enumerate(scores) if s >= threshold]
        dropped = [(str(self.pairs[i].low), scores[i]) for i in range(len(scores)) if scores[i] < threshold]
        self.pairs = [self.pairs[i] for i in keep]
        self.low = [self.low[i] for i in keep]
        self.high = [self.high[i] for i in keep]
        return dropped


def augment(
    low: np.ndarray, high: np.ndarray, crop: int, rng: np.random.Generator, scale_range: Tuple[float, float]
) -> Tuple[np.ndarray, np.ndarray]:
    """Reference augmentation of one pair -> two float32 ``[crop, crop, 3]`` arrays in [0, 1]."""
    h, w = low.shape[:2]
    s = rng.uniform(*scale_range)
    size = (max(crop, int(round(w * s))), max(crop, int(round(h * s))))
    low = cv2.resize(as_float(low), size, interpolation=cv2.INTER_LINEAR)
    high = cv2.resize(as_float(high), size, interpolation=cv2.INTER_LINEAR)
    y, x = rng.integers(0, size[1] - crop + 1), rng.integers(0, size[0] - crop + 1)
    low, high = low[y : y + crop, x : x + crop], high[y : y + crop, x : x + crop]
    if rng.random() < 0.5:
        low, high = low[:, ::-1], high[:, ::-1]
    if rng.random() < 0.5:
        low, high = low[::-1], high[::-1]
    if rng.random() < 0.5:
        low, high = np.rot90(low), np.rot90(high)
    return np.ascontiguousarray(low), np.ascontiguousarray(high)


def with_naka(low: Float[Tensor, "B H W 3"]) -> Float[Tensor, "B 3 H W"]:
    """Naka with per-image (here: per-crop) statistics, channel-first."""
    return naka_enhance(low).permute(0, 3, 1, 2).contiguous()


VAL_MODES = ("half", *sorted(MODES))
"""``--val-mode`` choices (see :attr:`TrainConfig.val_mode`)."""


def half_resolution_maps(
    runner: CorrectionRunner, low: Float[Tensor, "B 3 H W"], naka: Float[Tensor, "B 3 H W"]
) -> Float[Tensor, "B 3 H W"]:
    """The corrected image with the maps predicted on the pair at half size (area filter) and
    upsampled bilinearly to full size, where they are applied to ``naka``."""
    h, w = low.shape[-2:]
    half = (max(1, round(h / 2)), max(1, round(w / 2)))
    mul, add = runner.predict_maps(*(F.interpolate(t, size=half, mode="area") for t in (low, naka)))
    mul, add = (F.interpolate(m, size=(h, w), mode="bilinear", align_corners=False) for m in (mul, add))
    return apply_maps(naka, mul, add, runner.net.config.lf_kernel, runner.net.config.lf_sigma)


@torch.no_grad()
def validate(net: ChromaGuided, val: PairSet, mode: str = "exact") -> Dict[str, float]:
    """Full-resolution PSNR per image (network run in ``mode``, one of :data:`VAL_MODES`, on the
    network's device), averaged overall and per source."""
    runner = CorrectionRunner(net, "exact" if mode == "half" else mode)
    device = next(net.parameters()).device
    scores: Dict[str, List[float]] = {}
    for pair, lo, hi in zip(val.pairs, val.low, val.high):
        low = torch.from_numpy(as_float(lo))[None]
        gt = torch.from_numpy(as_float(hi)).permute(2, 0, 1)[None].to(device)
        low, naka = low.permute(0, 3, 1, 2).contiguous().to(device), with_naka(low).to(device)
        out = half_resolution_maps(runner, low, naka) if mode == "half" else runner(low, naka)["enhanced"]
        scores.setdefault(pair.source, []).append(psnr(out, gt, eps=1e-8))
    result = {f"psnr_{k}": float(np.mean(v)) for k, v in scores.items()}
    result["psnr"] = float(np.mean([s for v in scores.values() for s in v]))
    return result


def _jsonable(config: TrainConfig) -> dict:
    def conv(v):
        if isinstance(v, Path):
            return str(v)
        if isinstance(v, (tuple, list)):
            return [conv(x) for x in v]
        return v

    return {k: conv(v) for k, v in asdict(config).items()}


def config_from_yaml(path: Path) -> TrainConfig:
    """A :class:`TrainConfig` whose fields are set from a YAML mapping of field names (``configs/correction/...``:
    the shipped recipe if there is no such file)."""
    path = config_file(path)
    if not path.is_file():
        raise FileNotFoundError(f"recipe {path} not found: pass an existing YAML file to --config")
    data = yaml.safe_load(path.read_text()) or {}
    types = {f.name: f.type for f in fields(TrainConfig)}
    unknown = sorted(set(data) - set(types))
    if unknown:
        raise CorrectionTrainingError(f"{path}: unknown keys {unknown}; use TrainConfig field names (see --help)")
    values = {}
    for k, v in data.items():
        t = str(types[k])
        if k == "model":
            v = ChromaGuidedConfig.from_dict(v or {})
        elif "Tuple[Path" in t:
            v = tuple(Path(x) for x in v)
        elif "Path" in t and v is not None:
            v = Path(v)
        elif t.startswith("Tuple") and v is not None:
            v = tuple(v)
        values[k] = v
    return TrainConfig(config=path, **values)


def optimizer_step(net: torch.nn.Module, opt: torch.optim.Optimizer, loss: torch.Tensor, grad_clip: float) -> bool:
    """Backward, clip the gradient norm, step; False (and no step) when the gradient is not finite.

    GroupNorm amplifies the gradient by up to 1/sqrt(eps) per layer where a whole group's
    activations are exactly constant, as for an exactly constant (all-black) crop: ~1e36 after the
    bottleneck, which overflows float32. Such a step is skipped rather than writing NaN into the weights.
    """
    opt.zero_grad(set_to_none=True)
    loss.backward()
    norm = torch.nn.utils.clip_grad_norm_(net.parameters(), grad_clip)
    if not torch.isfinite(norm):
        opt.zero_grad(set_to_none=True)
        return False
    opt.step()
    return True


def train_step(
    net: ChromaGuided,
    loss_fn: CorrectionLoss,
    opt: torch.optim.Optimizer,
    low: Float[Tensor, "B H W 3"],
    gt: Float[Tensor, "B 3 H W"],
    config: TrainConfig,
) -> Tuple[Dict[str, Tensor], bool]:
    """One training iteration on CPU crops (sRGB, [0, 1]), run on the network's device: Naka, forward,
    loss, backward and step. Returns the loss terms and whether the step was taken (:func:`optimizer_step`)."""
    device = next(net.parameters()).device
    naka = with_naka(low).to(device)
    with torch.autocast(device.type, dtype=torch.bfloat16, enabled=config.bf16):
        o = net(low.permute(0, 3, 1, 2).contiguous().to(device), naka)
    terms = loss_fn(o["enhanced"].float(), gt.to(device), naka, o["mul_map"].float(), o["add_map"].float())
    return terms, optimizer_step(net, opt, terms["total"], config.grad_clip)


def _log(msg: str) -> None:
    CONSOLE.log(f"[naka-gs] {msg}", markup=False)


def load_sources(config: TrainConfig) -> Tuple[PairSet, PairSet, List[Tuple[str, float]]]:
    """Training and validation pairs (misaligned training pairs dropped) and the dropped list."""
    train: List[Pair] = []
    val: List[Pair] = []
    scenes = [Path(s).name for s in config.lom + config.sim]
    unknown = sorted(set(config.hold_out) - set(scenes))
    if unknown:
        raise CorrectionTrainingError(
            f"--hold-out {' '.join(unknown)} names no --lom/--sim scene; choose among {scenes}"
        )
    for root in config.lol:
        train += lol_pairs(root, "train")
        val += lol_pairs(root, "eval")
    for scene in config.lom:
        if Path(scene).name not in config.hold_out:
            train += lom_pairs(scene, "train")
            val += lom_pairs(scene, "test")
    for scene in config.sim:
        if Path(scene).name not in config.hold_out:
            train += sim_pairs(scene)
    if not train:
        raise CorrectionTrainingError("no training pairs: pass at least one of --lol, --lom, --sim")
    if not val:
        raise CorrectionTrainingError("no validation pairs: --lol (eval/) or --lom (transforms_test.json) is needed")
    train_set = PairSet(train, "Reading training pairs")
    dropped = train_set.drop_misaligned(config.min_edge_correlation)
    return train_set, PairSet(val, "Reading validation pairs"), dropped


def training_device(name: str) -> torch.device:
    """``--device``: ``auto`` -> CUDA when available, else the CPU; an unusable name -> one-line error."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise CorrectionTrainingError(f"--device {name!r} is not a device: use auto, cpu, cuda or cuda:N") from None
    if device.type not in ("cpu", "cuda"):
        raise CorrectionTrainingError(f"--device {name!r}: the correction trainer runs on cpu or cuda (or auto)")
    if device.type == "cuda" and not torch.cuda.is_available():
        raise CorrectionTrainingError(
            f"--device {name}: CUDA is not available on this machine: use --device cpu (or auto)"
        )
    return device


def read_resume(path: Path, model: ChromaGuidedConfig) -> Tuple[dict, ChromaGuided]:
    """The ``--resume`` checkpoint and its network, checked whole; one-line ``FileNotFoundError`` /
    ``ValueError`` naming the file otherwise (a garbage file included)."""
    if not path.is_file():
        raise FileNotFoundError(f"resume checkpoint {path} not found: pass <output_dir>/latest.pt")
    saved = load_correction(path)  # a file torch cannot read: one line
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    missing = [k for k in ("optimizer", "scheduler", "epoch", "history", "best_psnr") if k not in ckpt]
    if missing:
        raise CorrectionTrainingError(f"{path} lacks {missing}: resume needs a latest.pt written by this trainer")
    if saved.config != model:
        raise CorrectionTrainingError(f"{path} holds a {saved.config} network, not the configured {model}")
    return ckpt, saved


def train(config: TrainConfig) -> Dict[str, list]:
    """Run the training; returns the history (per epoch: train loss terms, validation PSNR, seconds)."""
    if config.val_mode not in VAL_MODES:
        raise CorrectionTrainingError(f"unknown --val-mode {config.val_mode!r}; choose one of {VAL_MODES}")
    device = training_device(config.device)
    if device.type == "cuda" and config.val_mode not in ("exact", "half"):
        raise CorrectionTrainingError(f"--val-mode {config.val_mode} runs on the CPU only; on CUDA use exact or half")
    resumed = read_resume(config.resume, config.model) if config.resume is not None else None  # before any work
    if config.threads:
        torch.set_num_threads(config.threads)
    fit_threads()
    torch.manual_seed(config.seed)
    train_set, val_set, dropped = load_sources(config)
    out = config.output_dir
    out.mkdir(parents=True, exist_ok=True)  # once the sources are read: a bad source leaves no folder behind
    counts = {s: sum(p.source == s for p in train_set.pairs) for s in ("lol", "lom", "sim")}
    _log(
        f"correction training on {device}: {len(train_set)} pairs {counts}, {len(val_set)} validation pairs; "
        f"dropped {len(dropped)} misaligned (edge correlation < {config.min_edge_correlation}): "
        + (", ".join(f"{n} ({s:.2f})" for n, s in dropped) or "none")
    )
    weights = torch.tensor(
        [
            {"lol": config.lol_weight, "lom": config.lom_weight, "sim": config.sim_weight}[p.source]
            for p in train_set.pairs
        ],
        dtype=torch.float64,
    )
    if (weights <= 0).all():
        raise CorrectionTrainingError("all source weights are zero: set --lol-weight/--lom-weight/--sim-weight > 0")
    per_epoch = config.images_per_epoch or len(train_set)
    iters = per_epoch // config.batch_size
    if iters < 1:
        raise CorrectionTrainingError(
            f"images per epoch ({per_epoch}) < batch size ({config.batch_size}): no iteration"
        )

    net = ChromaGuided(config.model)
    if config.neutral_init:
        for head in (net.mul_head, net.add_head):
            torch.nn.init.zeros_(head.weight)
            torch.nn.init.zeros_(head.bias)
    net.to(device)
    loss_fn = CorrectionLoss(vgg_weights=config.vgg_weights).to(device)
    opt = torch.optim.AdamW(net.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=config.epochs)
    history: Dict[str, list] = {"epoch": [], "val": [], "train": [], "seconds": [], "lr": []}
    start_epoch, best = 1, -math.inf
    if resumed is not None:
        ckpt, saved = resumed
        net.load_state_dict(saved.state_dict())
        opt.load_state_dict(ckpt["optimizer"])
        sched.load_state_dict(ckpt["scheduler"])
        start_epoch, best, history = int(ckpt["epoch"]) + 1, float(ckpt["best_psnr"]), ckpt["history"]
        _log(f"resumed from {config.resume} at epoch {start_epoch - 1} (best PSNR {best:.2f} dB)")
    else:
        t0 = time.perf_counter()
        v = validate(net, val_set, config.val_mode)
        history["epoch"].append(0)
        history["val"].append(v)
        history["train"].append({})
        history["seconds"].append(time.perf_counter() - t0)
        history["lr"].append(config.lr)
        _log(f"epoch 0 (untrained): val {_fmt(v)} ({time.perf_counter() - t0:.0f} s)")
    net.train()

    skipped = 0
    for epoch in range(start_epoch, config.epochs + 1):
        t0 = time.perf_counter()
        rng = np.random.default_rng([config.seed, epoch])
        gen = torch.Generator().manual_seed(int(rng.integers(2**62)))
        order = torch.multinomial(weights, per_epoch, replacement=per_epoch > len(train_set), generator=gen).tolist()
        sums: Dict[str, float] = {}
        with StageProgress(CONSOLE) as progress:
            task = progress.add_task(f"epoch {epoch}/{config.epochs}", total=iters)
            for it in range(iters):
                idx = order[it * config.batch_size : (it + 1) * config.batch_size]
                crops = [
                    augment(train_set.low[i], train_set.high[i], config.crop, rng, config.scale_range) for i in idx
                ]
                low = torch.from_numpy(np.stack([c[0] for c in crops]))
                gt = torch.from_numpy(np.stack([c[1] for c in crops])).permute(0, 3, 1, 2).contiguous()
                terms, stepped = train_step(net, loss_fn, opt, low, gt, config)
                if not stepped:
                    skipped += 1
                    _log(f"epoch {epoch} it {it + 1}: non-finite gradient norm, step skipped ({skipped} so far)")
                for k, val in terms.items():
                    sums[k] = sums.get(k, 0.0) + float(val.detach())
                progress.advance(task)
                if config.log_every and (it + 1) % config.log_every == 0:
                    _log(
                        f"epoch {epoch} it {it + 1}/{iters}: loss {sums['total'] / (it + 1):.4f} ({time.perf_counter() - t0:.0f} s)"
                    )
        lr = opt.param_groups[0]["lr"]
        sched.step()
        train_terms = {k: v / iters for k, v in sums.items()}
        train_s = time.perf_counter() - t0
        v = validate(net, val_set, config.val_mode)
        seconds = time.perf_counter() - t0
        for key, value in (("epoch", epoch), ("val", v), ("train", train_terms), ("seconds", seconds), ("lr", lr)):
            history[key].append(value)
        improved = v["psnr"] > best
        best = max(best, v["psnr"])
        extra = {
            "epoch": epoch,
            "optimizer": opt.state_dict(),
            "scheduler": sched.state_dict(),
            "train_config": _jsonable(config),
            "best_psnr": best,
            "history": history,
        }
        save_correction(net, out / "latest.pt", half=False, extra=extra)
        if improved:
            save_correction(net, out / "best.pt", half=False, extra=extra)
        (out / "history.json").write_text(json.dumps(history, indent=1))
        _log(
            f"epoch {epoch}/{config.epochs}: loss {train_terms['total']:.4f} val {_fmt(v)}"
            f"{' (best)' if improved else ''}; lr {lr:.2e}; train {train_s:.0f} s, total {seconds:.0f} s "
            f"({train_s / iters:.2f} s/it)"
        )
    if config.export_to is not None:
        export_weights(out / "best.pt", config.export_to)
    return history


def iteration_seconds(config: TrainConfig, device: str = "cpu", repeats: int = 10, warmup: int = 3) -> float:
    """Mean seconds of one training iteration (Naka, forward, loss, backward, AdamW step) at ``config``'s
    network, batch and crop on random crops, after ``warmup`` untimed ones: what sizes a time-budgeted run
    (``scripts/gpu/run.sh correction``) and compares devices. Data loading and augmentation not included."""
    device_ = training_device(device)
    sync = torch.cuda.synchronize if device_.type == "cuda" else lambda: None
    gen = torch.Generator().manual_seed(config.seed)
    net = ChromaGuided(config.model).to(device_)
    loss_fn = CorrectionLoss(vgg_weights=config.vgg_weights).to(device_)
    opt = torch.optim.AdamW(net.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    shape = (config.batch_size, config.crop, config.crop, 3)

    def step() -> None:
        low = torch.rand(shape, generator=gen) * 0.1  # dark crops, as LOL's low images
        train_step(net, loss_fn, opt, low, torch.rand(low.permute(0, 3, 1, 2).shape, generator=gen), config)

    for _ in range(warmup):
        step()
    sync()
    start = time.perf_counter()
    for _ in range(repeats):
        step()
    sync()
    return (time.perf_counter() - start) / repeats


def export_weights(checkpoint: Path, dest: Path) -> Path:
    """A training checkpoint -> float16 weights + model config + provenance (epoch, validation PSNR per
    epoch, train config), without optimizer state: the format of the shipped default weights."""
    ckpt = torch.load(checkpoint, map_location="cpu", weights_only=True)
    missing = [k for k in ("epoch", "history", "train_config") if k not in ckpt]
    if missing:
        raise CorrectionTrainingError(
            f"{checkpoint} lacks {missing}: export needs a best.pt/latest.pt written by this trainer"
        )
    provenance = {
        "epoch": ckpt["epoch"],
        "best_psnr": ckpt["best_psnr"],
        "val_psnr": {int(e): v for e, v in zip(ckpt["history"]["epoch"], ckpt["history"]["val"])},
        "train_config": ckpt["train_config"],
    }
    dest = save_correction(load_correction(checkpoint), dest, half=True, extra={"provenance": provenance})
    _log(f"exported {checkpoint} (epoch {ckpt['epoch']}, val PSNR {ckpt['best_psnr']:.2f} dB) to {dest}")
    return dest


def _fmt(v: Dict[str, float]) -> str:
    return " ".join(f"{k} {x:.2f}" for k, x in v.items())
