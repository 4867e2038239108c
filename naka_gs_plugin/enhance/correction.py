"""Correction-network checkpoints and fast inference (paper Sec. 3.1, issue 6).

Checkpoints
    :func:`save_correction` / :func:`load_correction` read and write our format, a ``torch.save`` dict
    ``{"format": "naka-gs-correction", "config": ChromaGuidedConfig.to_dict(), "state_dict": {...}}``
    (float16 weights are cast to float32 on load; extra keys such as an optimizer are ignored).
    :func:`load_correction` also reads checkpoints written by the authors' ``naka_color_correction.py``
    (``{"epoch", "model", "optimizer", "scheduler", "args", "best_psnr"}`` or a bare state dict),
    through the explicit key table of :func:`authors_key_map`, including their older 3-channel
    multiplicative head (its filters are averaged to one channel, as their loader does).

Inference
    :class:`CorrectionRunner` runs a network in one of the :data:`MODES`: ``exact`` is the plain
    float32 full-resolution forward; the others buy speed or memory (channels-last layout, bfloat16
    autocast, the ``lean`` bfloat16 inference forward with fused GroupNorm/GELU kernels
    (:mod:`naka_gs_plugin.enhance.lean_ops`), maps predicted at reduced resolution and upsampled bilinearly -- they act on the
    low-frequency part and are smooth by design -- and overlapping tiles) at a measured cost in
    accuracy (``naka-gs-bench-correction``; figures in the README). Tiles are exact, not
    approximations of the full-image forward: GroupNorm,
    squeeze-excitation pooling and the input standardisation are global per image, so a first pass
    records those statistics on the whole image (at ``stats_scale`` of its resolution) and every
    tile replays them; tile origins are multiples of 8 (the U-Net's stride), decoder upsampling uses
    the full image's sampling grid, and each tile carries ``halo`` pixels of context beyond the part
    it contributes, which is blended with raised-cosine ramps of ``blend`` pixels.

Images are sRGB-encoded float in [0, 1], channel-first ``[B, 3, H, W]`` unless stated otherwise.
"""

from __future__ import annotations

import contextlib
import copy
import ctypes
import dataclasses
import hashlib
import math
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Callable, Dict, Iterator, List, Literal, Optional, Tuple, Union

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor, nn

from naka_gs_plugin.cpu import native_bf16
from naka_gs_plugin.enhance.lean_ops import norm_act
from naka_gs_plugin.enhance.correction_net import (
    STD_FLOOR,
    ChromaGuided,
    ChromaGuidedConfig,
    ConvUnit,
    DecoderBlock,
    ResBlock,
    SqueezeExcite,
    Stage,
    apply_maps,
    standardize,
)

CHECKPOINT_FORMAT = "naka-gs-correction"
DEFAULT_WEIGHTS = Path(__file__).resolve().parent / "weights" / "chroma_guided_default.pt"
"""The shipped weights (``EnhanceConfig.correction = "default"``)."""

# --------------------------------------------------------------------------------------------------
# Checkpoints
# --------------------------------------------------------------------------------------------------


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

    Raises ``FileNotFoundError``/``ValueError`` with a one-line message naming ``path``.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"correction checkpoint {path} not found: pass an existing .pt/.pth file")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # pickle/zip errors have many types; all mean "not a torch checkpoint"
        raise ValueError(
            f"{path} is not a readable torch checkpoint ({type(err).__name__}): re-save it with torch.save"
        ) from None
    if not isinstance(ckpt, dict):
        raise ValueError(
            f"{path} holds a {type(ckpt).__name__}, not a checkpoint dict: expected a naka-gs correction checkpoint"
        )
    state = ckpt.get("state_dict", ckpt.get("model", ckpt))
    if not isinstance(state, dict) or not all(isinstance(v, Tensor) for v in state.values()):
        raise ValueError(
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
        net = ChromaGuided(config)
        incompatible = net.load_state_dict(
            {k: v.float() if v.is_floating_point() else v for k, v in state.items()}, strict=False
        )
    except (ValueError, TypeError, RuntimeError) as err:
        msg = " ".join(str(err).split())
        raise ValueError(f"{path} does not fit the correction network: {msg[:300]}") from None
    if incompatible.missing_keys or incompatible.unexpected_keys:
        raise ValueError(
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


# --------------------------------------------------------------------------------------------------
# Inference modes
# --------------------------------------------------------------------------------------------------

STRIDE = 8
"""Total downsampling of the U-Net: tile origins must be multiples of it to share the image's grid."""


@dataclass(frozen=True)
class InferenceMode:
    """How :class:`CorrectionRunner` evaluates the network; :data:`MODES` names the useful ones."""

    map_scale: float = 1.0
    """Predict the maps on the image resized by this factor (area filter), then upsample them bilinearly."""
    bf16: bool = False
    """bfloat16 arithmetic for the network's body: CPU autocast, or with ``lean`` a bfloat16 copy of the
    body (maps and the final composition stay float32). Fast only on CPUs with native bfloat16
    (AVX-512 BF16, AMX): elsewhere oneDNN emulates it, about 5x slower than float32."""
    channels_last: bool = False
    """NHWC memory layout for the network (faster oneDNN convolutions on CPU)."""
    tile: int = 0
    """Tile core size in pixels of the map resolution (multiple of 8); 0 = whole image at once."""
    halo: Optional[int] = None
    """Context pixels around each tile's output window (discarded); ``None``: the network's receptive
    radius (:func:`receptive_radius`, which makes tiles exact), rounded up so halo + blend is a multiple of 8."""
    blend: int = 16
    """Half-width of the raised-cosine ramp between neighbouring tiles, pixels."""
    stats_scale: float = 1.0
    """Tiled only: resolution factor of the pass that records the global statistics (1 = exact)."""
    lean: bool = False
    """Inference-only forward (:func:`lean_predict_maps`): each activation freed after its last use,
    GroupNorm + residual + GELU fused in one pass (:mod:`naka_gs_plugin.enhance.lean_ops`), in-place
    SE ops, the decoders' concatenations and full upsampled inputs never built, freed blocks kept in
    the heap for reuse during the call (:func:`reuse_freed_memory`). With ``bf16`` the body's weights
    and activations are bfloat16 (no float32 round trips as under autocast); without, float32. The
    heads and maps stay float32.
    Implies channels-last; not combined with tiles (they replay statistics through the module forwards)."""


ModeName = Literal[
    "auto",
    "exact",
    "channels-last",
    "bf16",
    "lean",
    "lean-f32",
    "tiled",
    "tiled-lowmem",
    "0.8-bf16",
    "0.7-bf16",
    "half",
    "half-bf16",
    "quarter-bf16",
]
MODES: Dict[str, InferenceMode] = {
    "exact": InferenceMode(),
    "channels-last": InferenceMode(channels_last=True),
    "bf16": InferenceMode(bf16=True, channels_last=True),
    "lean": InferenceMode(lean=True, bf16=True, channels_last=True),
    "lean-f32": InferenceMode(lean=True, channels_last=True),
    "tiled": InferenceMode(tile=512, stats_scale=1.0),
    "tiled-lowmem": InferenceMode(tile=512, stats_scale=0.7),
    "0.8-bf16": InferenceMode(map_scale=0.8, bf16=True, channels_last=True),
    "0.7-bf16": InferenceMode(map_scale=0.7, bf16=True, channels_last=True),
    "half": InferenceMode(map_scale=0.5, channels_last=True),
    "half-bf16": InferenceMode(map_scale=0.5, bf16=True, channels_last=True),
    "quarter-bf16": InferenceMode(map_scale=0.25, bf16=True, channels_last=True),
}
DEFAULT_MODE: ModeName = "auto"
"""The datamanager's default: :func:`resolve_mode` picks ``lean`` where the CPU has native bfloat16,
else ``lean-f32``. Measured with ``naka-gs-bench-correction`` and the shipped weights (docs/): each is
the fastest mode on its kind of CPU that stays within 0.05 dB / 0.002 SSIM of ``exact`` on LOM test +
LOL eval15. Every reduced-resolution mode loses more than 0.002 SSIM with these weights: the maps
carry detail that even an ideal downsample-upsample of the exact maps loses."""


_RESOLVED: Dict[str, str] = {}


def resolve_mode(name: str) -> str:
    """A concrete :data:`MODES` name: ``auto`` becomes ``lean`` with native bfloat16, else ``lean-f32``
    (logged once per process with the reason); any other known name is returned as is."""
    if name != "auto":
        if name not in MODES:
            raise ValueError(f"unknown correction mode {name!r}; choose auto or one of {sorted(MODES)}")
        return name
    if "auto" not in _RESOLVED:
        native, why = native_bf16()
        _RESOLVED["auto"] = "lean" if native else "lean-f32"
        print(f"[naka-gs] correction mode auto -> {_RESOLVED['auto']}: {why}", flush=True)
    return _RESOLVED["auto"]


@dataclass
class _Stats:
    """Per-image global statistics of one forward pass, keyed by module name."""

    std_mean: Tensor
    """[B, 9, 1, 1] spatial mean of ``[low, naka, delta]`` (the standardisation)."""
    std_scale: Tensor
    """[B, 9, 1, 1] matching population std, clamped like the network's."""
    norm: Dict[str, Tuple[Tensor, Tensor]]
    """GroupNorm name -> (mean, var) of its input, each [B, groups]."""
    gate: Dict[str, Tensor]
    """SqueezeExcite name -> its channel gate [B, C, 1, 1]."""


def receptive_radius(config: ChromaGuidedConfig) -> int:
    """Upper bound, in input pixels, of how far an output pixel of ``predict_maps`` sees (global
    statistics aside): 3x3 convolutions add 2**level each, upsampling one cell of the coarser level."""
    r = 1  # stem
    for level, n_res in enumerate(config.enc_residual):
        r += (1 + 2 * n_res) * 2**level + 2**level  # encoder stage, then its stride-2 conv
    r += 5 * 8  # bottleneck: conv unit + 2 residual blocks at 1/8
    for level in (2, 1, 0):
        r += 2 ** (level + 1) + 5 * 2**level  # upsample, decoder stage
    return r + 3 + 1  # fuse (conv unit + residual block), heads


def _level_sizes(h: int, w: int) -> List[Tuple[int, int]]:
    """Image size at scales 1, 1/2, 1/4, 1/8 (stride-2 convolutions give ceil)."""
    sizes = [(h, w)]
    for _ in range(3):
        sizes.append(((sizes[-1][0] + 1) // 2, (sizes[-1][1] + 1) // 2))
    return sizes


def _bilinear_axis(n_out: int, out_origin: int, in_full: int, out_full: int, in_origin: int, n_in: int, device):
    """Row (or column) indices and weights of PyTorch's bilinear resize ``in_full -> out_full``
    (align_corners False), for output pixels ``out_origin + [0, n_out)``, relative to ``in_origin``."""
    dst = torch.arange(out_origin, out_origin + n_out, dtype=torch.float64, device=device)
    src = ((dst + 0.5) * (in_full / out_full) - 0.5).clamp(min=0.0)
    i0 = src.floor().long()
    lam = (src - i0).float()
    i1 = torch.where(i0 < in_full - 1, i0 + 1, i0)
    return (i0 - in_origin).clamp(0, n_in - 1), (i1 - in_origin).clamp(0, n_in - 1), lam


def _upsample_global(
    x: Tensor, out_hw: Tuple[int, int], out_origin: Tuple[int, int], in_full, out_full, in_origin
) -> Tensor:
    """Bilinear upsampling of a tile with the full image's sampling grid (separable gathers).

    Written out because ``F.interpolate``/kornia resize a tensor onto its own grid; a tile needs the
    whole image's (input/output size ratio and offset), which differs from 2x unless H, W are
    multiples of 8."""
    y0, y1, ly = _bilinear_axis(out_hw[0], out_origin[0], in_full[0], out_full[0], in_origin[0], x.shape[2], x.device)
    x0, x1, lx = _bilinear_axis(out_hw[1], out_origin[1], in_full[1], out_full[1], in_origin[1], x.shape[3], x.device)
    ly = ly.to(x.dtype)[:, None]
    lx = lx.to(x.dtype)
    rows = x.index_select(2, y0) * (1 - ly) + x.index_select(2, y1) * ly
    return rows.index_select(3, x0) * (1 - lx) + rows.index_select(3, x1) * lx


@contextlib.contextmanager
def _global_ops(
    net: ChromaGuided,
    stats: _Stats,
    record: bool,
    origin: Tuple[int, int] = (0, 0),
    full_hw: Optional[Tuple[int, int]] = None,
) -> Iterator[None]:
    """Swap the network's image-global operations for recording / replaying versions.

    ``record``: GroupNorm and SE compute their statistics on the input they see and store them in
    ``stats`` (the network's output is unchanged). Otherwise they replay ``stats``, the stem sees the
    standardisation of ``stats``, and decoders upsample on the grid of a ``full_hw`` image of which
    the input is the crop starting at ``origin`` (a multiple of :data:`STRIDE`).
    Instance attributes shadow the class ``forward`` and are removed on exit.
    """
    patched: List[nn.Module] = []
    hooks = []

    def groupnorm(name: str, m: nn.GroupNorm):
        def forward(x: Tensor) -> Tensor:
            b, c = x.shape[:2]
            if record:
                xf = x.float().reshape(b, m.num_groups, -1)
                stats.norm[name] = (xf.mean(dim=2), xf.var(dim=2, unbiased=False))
            mean, var = stats.norm[name]
            # Frozen statistics make GroupNorm a per-channel affine map: x * a + b.
            rstd = (var + m.eps).rsqrt().repeat_interleave(c // m.num_groups, dim=1)
            a = m.weight[None] * rstd
            shift = m.bias[None] - mean.repeat_interleave(c // m.num_groups, dim=1) * a
            return torch.addcmul(shift[:, :, None, None].to(x.dtype), x, a[:, :, None, None].to(x.dtype))

        return forward

    def squeeze_excite(name: str, m: SqueezeExcite):
        def forward(x: Tensor) -> Tensor:
            if record:
                pooled = x.float().mean(dim=(2, 3), keepdim=True)
                stats.gate[name] = torch.sigmoid(m.fc2(m.act(m.fc1(pooled.to(m.fc1.weight.dtype))))).float()
            return x * stats.gate[name].to(x.dtype)

        return forward

    levels = {"dec3": 2, "dec2": 1, "dec1": 0}
    sizes = _level_sizes(*full_hw) if full_hw is not None else None

    def decoder(name: str, m: DecoderBlock):
        skip_level = levels[name]

        def forward(x: Tensor, skip: Tensor) -> Tensor:
            s_out, s_in = 1 << skip_level, 1 << (skip_level + 1)  # pixels per cell of skip / input
            up = _upsample_global(
                x,
                skip.shape[-2:],
                (origin[0] // s_out, origin[1] // s_out),
                sizes[skip_level + 1],
                sizes[skip_level],
                (origin[0] // s_in, origin[1] // s_in),
            )
            return m.stage(torch.cat([up, skip], dim=1))

        return forward

    def stem_input(_module, args):
        (x,) = args
        raw = x[:, :9]
        return (torch.cat([raw, ((raw - stats.std_mean) / stats.std_scale).to(x.dtype)], dim=1),)

    try:
        for name, m in net.named_modules():
            if isinstance(m, nn.GroupNorm):
                m.forward = groupnorm(name, m)
            elif isinstance(m, SqueezeExcite):
                m.forward = squeeze_excite(name, m)
            elif isinstance(m, DecoderBlock) and not record:
                m.forward = decoder(name, m)
            else:
                continue
            patched.append(m)
        if not record:
            hooks.append(net.stem.conv.register_forward_pre_hook(stem_input))
        yield
    finally:
        for m in patched:
            del m.forward
        for h in hooks:
            h.remove()


# --------------------------------------------------------------------------------------------------
# Lean inference forward
# --------------------------------------------------------------------------------------------------


def _unit(m: ConvUnit, x: Tensor, residual: Optional[Tensor] = None) -> Tensor:
    """The conv unit, or with ``residual`` a residual block's tail: ``gelu(norm(conv(x)) + residual)``."""
    return norm_act(m.conv(x), m.norm, residual, act=residual is not None or isinstance(m.act, nn.GELU))


def _res_block(m: ResBlock, x: Tensor) -> Tensor:
    return _unit(m.unit2, _unit(m.unit1, x), residual=x)


def _stage_steps(m: Stage) -> Iterator[Callable[[Tensor], Tensor]]:
    """A :class:`Stage` as single-input steps, so the caller can drop each input as soon as it is used."""
    yield partial(_unit, m.conv_in)
    for block in m.res:
        yield partial(_res_block, block)
    se = m.se
    yield lambda x: x.mul_(torch.sigmoid(se.fc2(se.act(se.fc1(x.mean(dim=(2, 3), keepdim=True))))))


def lean_predict_maps(
    net: ChromaGuided, low: Float[Tensor, "B 3 H W"], naka: Float[Tensor, "B 3 H W"]
) -> Tuple[Float[Tensor, "B 1 H W"], Float[Tensor, "B 3 H W"]]:
    """``net.predict_maps`` for inference (no autograd): the same operations in the same order, but
    each activation is rebound as soon as the next one exists (``x = step(x)``), overwritten in place
    where the op allows, and skips are released at their decoder, so the peak holds one decoder
    level's tensors instead of the whole graph's. The body runs in the dtype and memory format of
    ``net.stem``'s weights; the input standardisation is computed in float32 and the heads in theirs.
    Equal to ``predict_maps`` for a float32 network (tested)."""
    body = net.stem.conv.weight
    layout = torch.channels_last if body.is_contiguous(memory_format=torch.channels_last) else torch.contiguous_format
    delta = naka - low
    x = torch.cat([low, naka, delta, standardize(low), standardize(naka), standardize(delta)], dim=1)
    del delta
    x = x.to(dtype=body.dtype, memory_format=layout)
    x = _unit(net.stem, x)
    skips = []
    for enc in (net.enc1, net.enc2, net.enc3):
        for step in _stage_steps(enc.stage):
            x = step(x)
        skips.append(x)
        x = _unit(enc.down, x)
    for step in _stage_steps(net.bottleneck):
        x = step(x)
    for dec in (net.dec3, net.dec2, net.dec1):
        # conv(cat([up, skip])) as conv(skip, W_skip) + conv(up, W_up): the concatenation (3x a skip's
        # size at full resolution) is never built, and each operand is dropped right after its conv.
        # The upsampled input (2x the skip's channels at the skip's resolution) is built and convolved
        # in groups of the skip's channel count, so it never exists whole either.
        skip = skips.pop()
        conv_in = dec.stage.conv_in
        w_up, w_skip = conv_in.conv.weight.split([x.shape[1], skip.shape[1]], dim=1)
        y = F.conv2d(skip, w_skip, padding=1)
        size, group = skip.shape[-2:], skip.shape[1]
        del skip
        for c in range(0, x.shape[1], group):
            up = F.interpolate(x[:, c : c + group], size=size, mode="bilinear", align_corners=False)
            y.add_(F.conv2d(up, w_up[:, c : c + group], padding=1))
            del up
        x = norm_act(y, conv_in.norm, act=True)
        del y
        for step in list(_stage_steps(dec.stage))[1:]:
            x = step(x)
    x = _unit(net.fuse[0], x)
    x = _res_block(net.fuse[1], x)
    # Both heads in one convolution (a 1- and a 3-filter conv each cost a full pass over x).
    weight = torch.cat([net.mul_head.weight, net.add_head.weight])
    x = F.conv2d(x.to(weight.dtype), weight, torch.cat([net.mul_head.bias, net.add_head.bias]), padding=1)
    mul = 1.0 + net.config.mul_range * torch.tanh(x[:, :1])
    add = net.config.add_range * torch.tanh(x[:, 1:])
    return mul, add


def _glibc():
    """glibc's ``mallopt``/``malloc_trim`` through ctypes, or None off glibc (macOS, musl, Windows)."""
    try:
        libc = ctypes.CDLL("libc.so.6")
        return libc if hasattr(libc, "mallopt") and hasattr(libc, "malloc_trim") else None
    except OSError:
        return None


_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_GLIBC_DEFAULTS = {_M_TRIM_THRESHOLD: 128 * 1024, _M_MMAP_THRESHOLD: 128 * 1024}
HEAP_BLOCK_LIMIT = {torch.bfloat16: 192 << 20, torch.float32: 64 << 20}
"""Largest full-resolution activation (the stem's width x H x W) for which the lean forward keeps
freed blocks in the heap (:func:`reuse_freed_memory`), by the body's dtype: 1764x1172 in bfloat16
(132 MB), 882x586 in float32 (66 MB). Beyond, fragmentation between freed blocks costs more memory
than the page faults cost time: the float32 forward at 1764x1172 peaked at 2.2-2.7 GB with the heap
(10-15% faster) and at 1.9-2.0 GB without; at 882x586 the heap made it 12% faster for no memory."""


@contextlib.contextmanager
def reuse_freed_memory(max_block: int = HEAP_BLOCK_LIMIT[torch.bfloat16]) -> Iterator[None]:
    """Within the block, serve large allocations up to ``max_block`` bytes (:data:`HEAP_BLOCK_LIMIT`)
    from the process heap and keep freed ones there.

    glibc maps every block above 32 MiB with ``mmap`` and unmaps it on free, so each new activation
    page-faults its memory back in, zeroed by the kernel: measured on a 2-core CPU, ``x + x`` on a
    32x1172x1764 bfloat16 tensor took 50 ms against 6 ms in place. PyTorch has no caching CPU
    allocator to switch on, and ``THP_MEM_ALLOC_ENABLE`` is read once when torch is imported, so the
    lean forward raises ``M_MMAP_THRESHOLD`` (and ``M_TRIM_THRESHOLD``) for the call and restores
    glibc's defaults afterwards, handing the unused heap back with ``malloc_trim``. A no-op where the
    C library is not glibc."""
    libc = _glibc()
    if libc is None:
        yield
        return
    libc.mallopt(_M_MMAP_THRESHOLD, max_block)
    libc.mallopt(_M_TRIM_THRESHOLD, 1 << 30)
    try:
        yield
    finally:
        for option, value in _GLIBC_DEFAULTS.items():
            libc.mallopt(option, value)
        libc.malloc_trim(0)


def _standardisation(low: Tensor, naka: Tensor) -> Tuple[Tensor, Tensor]:
    """Mean and clamped std of ``[low, naka, naka - low]`` per sample and channel, as the network's."""
    raw = torch.cat([low, naka, naka - low], dim=1).float()
    mean = raw.mean(dim=(2, 3), keepdim=True)
    std = raw.var(dim=(2, 3), keepdim=True, unbiased=False).sqrt().clamp(min=STD_FLOOR)
    return mean, std


def _ramp(n: int, lead: bool, trail: bool, blend: int, device) -> Tensor:
    """Raised-cosine weights of an ``n``-pixel output window whose inner edges blend over
    ``2 * blend`` pixels (``lead``/``trail``: whether a neighbour tile shares that edge)."""
    w = torch.ones(n, device=device)
    if blend <= 0:
        return w
    t = (torch.arange(n, dtype=torch.float32, device=device) + 0.5) / (2 * blend)
    if lead:
        w = w * (0.5 - 0.5 * torch.cos(math.pi * t.clamp(max=1.0)))
    if trail:
        w = w * (0.5 - 0.5 * torch.cos(math.pi * t.flip(0).clamp(max=1.0)))
    return w


def _spans(size: int, tile: int) -> List[Tuple[int, int]]:
    return [(s, min(s + tile, size)) for s in range(0, size, tile)]


class CorrectionRunner:
    """Evaluates a :class:`ChromaGuided` network in an :class:`InferenceMode` (no gradients).

    ``runner(low, naka)`` returns ``{"enhanced", "mul_map", "add_map"}`` like ``net(low, naka)``,
    with the maps at the input's resolution.
    """

    def __init__(self, net: ChromaGuided, mode: Union[str, InferenceMode] = DEFAULT_MODE) -> None:
        if isinstance(mode, str):
            mode = MODES[resolve_mode(mode)]
        if mode.tile and mode.halo is None:
            halo = -(-(receptive_radius(net.config) + mode.blend) // STRIDE) * STRIDE - mode.blend
            mode = dataclasses.replace(mode, halo=halo)
        if mode.tile and (mode.tile % STRIDE or (mode.halo + mode.blend) % STRIDE):
            raise ValueError(
                f"tile ({mode.tile}) and halo + blend ({mode.halo + mode.blend}) must be multiples of {STRIDE}"
            )
        if mode.lean and mode.tile:
            raise ValueError("a lean mode runs untiled: set tile=0")
        self.mode = mode
        self.net = net.eval()
        if mode.channels_last or mode.lean:
            # A private copy: the caller's network keeps its layout and dtype.
            self.net = copy.deepcopy(net).eval().to(memory_format=torch.channels_last)
        if mode.lean and mode.bf16:
            self.net.to(torch.bfloat16)
            self.net.mul_head.float()
            self.net.add_head.float()

    def _prepare(self, x: Tensor) -> Tensor:
        return x.contiguous(memory_format=torch.channels_last) if self.mode.channels_last else x.contiguous()

    @contextlib.contextmanager
    def _autocast(self) -> Iterator[None]:
        """bfloat16 autocast for the body of the network; the two 3x3 heads stay float32, since a
        bfloat16 map (8 mantissa bits) would quantise M_mul near 1 in steps of 0.008."""
        if not self.mode.bf16 or self.mode.lean:
            yield
            return
        heads = (self.net.mul_head, self.net.add_head)

        def float32_conv(m: nn.Conv2d):
            def forward(x: Tensor) -> Tensor:
                with torch.autocast("cpu", enabled=False):
                    return F.conv2d(x.float(), m.weight.float(), m.bias.float(), m.stride, m.padding)

            return forward

        try:
            for m in heads:
                m.forward = float32_conv(m)
            with torch.autocast("cpu", dtype=torch.bfloat16):
                yield
        finally:
            for m in heads:
                del m.forward

    @torch.no_grad()
    def __call__(self, low: Float[Tensor, "B 3 H W"], naka: Float[Tensor, "B 3 H W"]) -> Dict[str, Tensor]:
        if low.shape != naka.shape or low.ndim != 4 or low.shape[1] != 3:
            raise ValueError(f"low and naka must both be [B, 3, H, W], got {tuple(low.shape)} and {tuple(naka.shape)}")
        low, naka = low.float(), naka.float()
        h, w = low.shape[-2:]
        m_low, m_naka = low, naka
        if self.mode.map_scale != 1.0:
            size = (max(1, round(h * self.mode.map_scale)), max(1, round(w * self.mode.map_scale)))
            m_low, m_naka = (F.interpolate(t, size=size, mode="area") for t in (low, naka))
        mul, add = self.predict_maps(m_low, m_naka)
        if mul.shape[-2:] != (h, w):
            mul = F.interpolate(mul, size=(h, w), mode="bilinear", align_corners=False)
            add = F.interpolate(add, size=(h, w), mode="bilinear", align_corners=False)
        cfg = self.net.config
        return {"enhanced": apply_maps(naka, mul, add, cfg.lf_kernel, cfg.lf_sigma), "mul_map": mul, "add_map": add}

    def predict_maps(self, low: Tensor, naka: Tensor) -> Tuple[Tensor, Tensor]:
        """``(mul, add)`` float32 at the resolution of ``low``/``naka`` (whole image or tiles)."""
        if self.mode.lean:
            stem = self.net.stem.conv.weight
            limit = HEAP_BLOCK_LIMIT[stem.dtype]
            largest = stem.shape[0] * low.shape[-2] * low.shape[-1] * stem.element_size()
            with reuse_freed_memory(limit) if largest <= limit else contextlib.nullcontext():
                mul, add = lean_predict_maps(self.net, low, naka)
            return mul.contiguous(), add.contiguous()
        if not self.mode.tile or (low.shape[-2] <= self.mode.tile and low.shape[-1] <= self.mode.tile):
            with self._autocast():
                mul, add = self.net.predict_maps(self._prepare(low), self._prepare(naka))
            return mul.float().contiguous(), add.float().contiguous()
        return self._predict_tiled(low, naka, self.record_stats(low, naka))

    def record_stats(self, low: Tensor, naka: Tensor) -> _Stats:
        """The image-global statistics, from a pass on the image resized by ``mode.stats_scale``;
        the standardisation is always taken at full resolution (it is cheap and exact)."""
        std_mean, std_scale = _standardisation(low, naka)
        stats = _Stats(std_mean, std_scale, {}, {})
        if self.mode.stats_scale != 1.0:
            h, w = low.shape[-2:]
            size = (max(1, round(h * self.mode.stats_scale)), max(1, round(w * self.mode.stats_scale)))
            low, naka = (F.interpolate(t, size=size, mode="area") for t in (low, naka))
        with _global_ops(self.net, stats, record=True), self._autocast():
            self.net.predict_maps(self._prepare(low), self._prepare(naka))
        return stats

    def predict_maps_with_stats(self, low: Tensor, naka: Tensor, stats: _Stats, origin=(0, 0), full_hw=None):
        """Maps of a crop starting at ``origin`` of a ``full_hw`` image, replaying ``stats``."""
        full_hw = full_hw or tuple(low.shape[-2:])
        with _global_ops(self.net, stats, record=False, origin=origin, full_hw=full_hw), self._autocast():
            mul, add = self.net.predict_maps(self._prepare(low), self._prepare(naka))
        return mul.float(), add.float()

    def _predict_tiled(self, low: Tensor, naka: Tensor, stats: _Stats) -> Tuple[Tensor, Tensor]:
        mode = self.mode
        b, _, h, w = low.shape
        mul_acc = low.new_zeros(b, 1, h, w)
        add_acc = low.new_zeros(b, 3, h, w)
        w_acc = low.new_zeros(1, 1, h, w)
        rows, cols = _spans(h, mode.tile), _spans(w, mode.tile)
        for ri, (r0, r1) in enumerate(rows):
            for ci, (c0, c1) in enumerate(cols):
                # Output window: the core plus the blend ramps; input window: plus the halo.
                o_r0, o_r1 = max(0, r0 - mode.blend), min(h, r1 + mode.blend)
                o_c0, o_c1 = max(0, c0 - mode.blend), min(w, c1 + mode.blend)
                i_r0, i_r1 = max(0, o_r0 - mode.halo), min(h, o_r1 + mode.halo)
                i_c0, i_c1 = max(0, o_c0 - mode.halo), min(w, o_c1 + mode.halo)
                mul, add = self.predict_maps_with_stats(
                    low[..., i_r0:i_r1, i_c0:i_c1], naka[..., i_r0:i_r1, i_c0:i_c1], stats, (i_r0, i_c0), (h, w)
                )
                sl = (..., slice(o_r0 - i_r0, o_r1 - i_r0), slice(o_c0 - i_c0, o_c1 - i_c0))
                wy = _ramp(o_r1 - o_r0, ri > 0, ri < len(rows) - 1, mode.blend, low.device)
                wx = _ramp(o_c1 - o_c0, ci > 0, ci < len(cols) - 1, mode.blend, low.device)
                weight = (wy[:, None] * wx[None, :])[None, None]
                mul_acc[..., o_r0:o_r1, o_c0:o_c1] += mul[sl] * weight
                add_acc[..., o_r0:o_r1, o_c0:o_c1] += add[sl] * weight
                w_acc[..., o_r0:o_r1, o_c0:o_c1] += weight
        return mul_acc / w_acc, add_acc / w_acc


def correct_image(
    net: ChromaGuided,
    low: Float[Tensor, "H W 3"],
    naka: Float[Tensor, "H W 3"],
    mode: Union[str, InferenceMode] = DEFAULT_MODE,
) -> Float[Tensor, "H W 3"]:
    """One channel-last sRGB [0, 1] image pair -> the corrected image (float32, channel-last)."""
    out = CorrectionRunner(net, mode)(low.permute(2, 0, 1)[None], naka.permute(2, 0, 1)[None])["enhanced"]
    return out[0].permute(1, 2, 0).contiguous()
