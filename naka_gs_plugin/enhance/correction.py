"""Correction-network inference (paper Sec. 3.1): :class:`CorrectionRunner` and its modes.

:class:`CorrectionRunner` runs a network in one of the :data:`MODES`, each a trade-off a user may want:

- ``auto`` (default): ``exact`` for a network on CUDA; on the CPU ``lean`` where it has native bfloat16,
  else ``lean-f32`` (:func:`resolve_mode`);
- ``exact``: the authors' network as written, plain float32 (the reference of every other mode);
- ``lean``: inference-only forward with a bfloat16 body and fused kernels (:mod:`.lean_ops`): about 4x
  faster than ``exact`` on CPUs with native bfloat16, 4x *slower* elsewhere, within 0.01 dB;
- ``lean-f32``: the same forward in float32: about 2x faster than ``exact`` on any CPU, equal to 1e-5;
- ``tiled-lowmem``: for images that do not fit in memory: 512-px tiles replaying image-global
  statistics recorded on the image at 0.7 of its resolution (about half of ``exact``'s peak memory;
  the statistics, not the tiles, are approximate).

Tiles equal the full-image forward given the same statistics: GroupNorm, squeeze-excitation pooling
and the input standardisation are global per image, so a first pass records those statistics on the
whole image (at ``stats_scale`` of its resolution) and every tile replays them; tile origins are
multiples of 8 (the U-Net's stride), decoder upsampling uses the full image's sampling grid, and
each tile carries ``halo`` pixels of context beyond the part it contributes, which is blended with
raised-cosine ramps of ``blend`` pixels. Checkpoints: :mod:`naka_gs_plugin.enhance.checkpoint`.

Images are sRGB-encoded float in [0, 1], channel-first ``[B, 3, H, W]`` unless stated otherwise.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import math
from dataclasses import dataclass
from typing import Dict, Iterator, List, Literal, Optional, Tuple, Union

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor, nn

from naka_gs_plugin.cpu import native_bf16

# Re-exported: the enhancement pipeline takes the runner and the checkpoint helpers it keys on from here.
from naka_gs_plugin.enhance.checkpoint import (
    DEFAULT_WEIGHTS,
    CorrectionWeightsError,
    CorrectionWeightsNotFoundError,
    file_digest,
    load_correction,
)
from naka_gs_plugin.enhance.correction_net import (
    STD_FLOOR,
    ChromaGuided,
    ChromaGuidedConfig,
    DecoderBlock,
    SqueezeExcite,
    apply_maps,
)
from naka_gs_plugin.enhance.lean_ops import lean_maps

__all__ = [
    "DEFAULT_MODE",
    "DEFAULT_WEIGHTS",
    "MODES",
    "CorrectionWeightsError",
    "CorrectionWeightsNotFoundError",
    "CorrectionRunner",
    "InferenceMode",
    "ModeName",
    "correct_image",
    "file_digest",
    "load_correction",
    "receptive_radius",
    "resolve_mode",
]

STRIDE = 8
"""Total downsampling of the U-Net: tile origins must be multiples of it to share the image's grid."""


@dataclass(frozen=True)
class InferenceMode:
    """How :class:`CorrectionRunner` evaluates the network; :data:`MODES` names the useful ones."""

    lean: bool = False
    """Inference-only forward (:func:`~naka_gs_plugin.enhance.lean_ops.lean_predict_maps`): each
    activation freed after its last use, GroupNorm + residual + GELU fused in one pass, in-place SE ops,
    the decoders' concatenations and full upsampled inputs never built, freed blocks kept in the heap
    for reuse during the call. Channels-last; the heads and maps stay float32. Not combined with tiles
    (they replay statistics through the module forwards)."""
    bf16: bool = False
    """With ``lean``: the body's weights and activations in bfloat16. Fast only on CPUs with native
    bfloat16 (AVX-512 BF16, AMX): elsewhere oneDNN emulates it, about 5x slower than float32."""
    tile: int = 0
    """Tile core size in pixels (multiple of 8); 0 = whole image at once."""
    halo: Optional[int] = None
    """Context pixels around each tile's output window (discarded); ``None``: the network's receptive
    radius (:func:`receptive_radius`, which makes tiles exact), rounded up so halo + blend is a multiple of 8."""
    blend: int = 16
    """Half-width of the raised-cosine ramp between neighbouring tiles, pixels."""
    stats_scale: float = 1.0
    """Tiled only: resolution factor of the pass that records the global statistics (1 = exact)."""


ModeName = Literal["auto", "exact", "lean", "lean-f32", "tiled-lowmem"]
MODES: Dict[str, InferenceMode] = {
    "exact": InferenceMode(),
    "lean": InferenceMode(lean=True, bf16=True),
    "lean-f32": InferenceMode(lean=True),
    "tiled-lowmem": InferenceMode(tile=512, stats_scale=0.7),
}
DEFAULT_MODE: ModeName = "auto"
"""The datamanager's default: :func:`resolve_mode` picks ``lean`` where the CPU has native bfloat16,
else ``lean-f32``. Measured with ``python -m benchmarks.correction_speed`` and the shipped weights (docs/): each is
the fastest mode on its kind of CPU that stays within 0.05 dB / 0.002 SSIM of ``exact`` on LOM test +
LOL eval15."""


_RESOLVED: Dict[str, str] = {}


def resolve_mode(name: str, device: Union[torch.device, str] = "cpu") -> str:
    """A concrete :data:`MODES` name for a network on ``device``: ``auto`` becomes ``exact`` on CUDA (the
    lean modes are CPU kernels; the plain forward takes 0.05 s per 882x586 image on an H100, 30x less than
    lean on 2 CPU cores: docs/cuda.md), on the CPU ``lean`` with native bfloat16, else ``lean-f32`` (logged
    once per process with the reason); any other known name is returned as is."""
    if name != "auto":
        if name not in MODES:
            raise ValueError(f"unknown correction mode {name!r}; choose auto or one of {sorted(MODES)}")
        return name
    if torch.device(device).type == "cuda":
        if "auto-cuda" not in _RESOLVED:
            _RESOLVED["auto-cuda"] = "exact"
            print("[naka-gs] correction mode auto -> exact on CUDA: the lean modes are CPU kernels", flush=True)
        return _RESOLVED["auto-cuda"]
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
        if mode.bf16 and not mode.lean:
            raise ValueError("bfloat16 runs only in the lean forward: set lean=True (or use the mode 'lean')")
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
        if mode.lean:
            # A private copy: the caller's network keeps its layout and dtype.
            self.net = copy.deepcopy(net).eval().to(memory_format=torch.channels_last)
        if mode.bf16:
            self.net.to(torch.bfloat16)
            self.net.mul_head.float()
            self.net.add_head.float()

    @torch.no_grad()
    def __call__(self, low: Float[Tensor, "B 3 H W"], naka: Float[Tensor, "B 3 H W"]) -> Dict[str, Tensor]:
        if low.shape != naka.shape or low.ndim != 4 or low.shape[1] != 3:
            raise ValueError(f"low and naka must both be [B, 3, H, W], got {tuple(low.shape)} and {tuple(naka.shape)}")
        low, naka = low.float(), naka.float()
        mul, add = self.predict_maps(low, naka)
        cfg = self.net.config
        return {"enhanced": apply_maps(naka, mul, add, cfg.lf_kernel, cfg.lf_sigma), "mul_map": mul, "add_map": add}

    def predict_maps(self, low: Tensor, naka: Tensor) -> Tuple[Tensor, Tensor]:
        """``(mul, add)`` float32 at the resolution of ``low``/``naka`` (whole image or tiles)."""
        if self.mode.lean:
            return lean_maps(self.net, low, naka)
        if not self.mode.tile or (low.shape[-2] <= self.mode.tile and low.shape[-1] <= self.mode.tile):
            mul, add = self.net.predict_maps(low.contiguous(), naka.contiguous())
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
        with _global_ops(self.net, stats, record=True):
            self.net.predict_maps(low.contiguous(), naka.contiguous())
        return stats

    def predict_maps_with_stats(self, low: Tensor, naka: Tensor, stats: _Stats, origin=(0, 0), full_hw=None):
        """Maps of a crop starting at ``origin`` of a ``full_hw`` image, replaying ``stats``."""
        full_hw = full_hw or tuple(low.shape[-2:])
        with _global_ops(self.net, stats, record=False, origin=origin, full_hw=full_hw):
            mul, add = self.net.predict_maps(low.contiguous(), naka.contiguous())
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
