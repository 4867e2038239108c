"""The enhancement applied to training images: a chain of stages (:mod:`naka_gs_plugin.enhance.stages`).

One :class:`Enhancer` turns a scene's low-light training images into enhanced ones, once, with a
rich progress bar: per view the Naka-Rushton response, the correction network and capture chroma,
kept in an on-disk cache keyed by image content plus every cached stage's :meth:`~Stage.key`, so a
second run (or ``ns-eval``/``ns-viewer`` after training) does not recompute anything; then the
scene's exposure. Eval images never pass through here.

Images in and out are sRGB-encoded, channel-last ``[H, W, 3]``; input ``uint8`` in [0, 255] or
float in [0, 1]; output ``float32`` in [0, 1].
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Literal, Optional, Sequence, Type, Union

import numpy as np
import torch
from jaxtyping import Float, UInt8
from nerfstudio.configs.base_config import InstantiateConfig
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor

from naka_gs_plugin.cpu import fit_threads
from naka_gs_plugin.data.cache import content_hash, default_cache_dir
from naka_gs_plugin.data.safe_io import atomic_write, usable_cache_dir
from naka_gs_plugin.enhance.chroma import DEFAULT_BLUR
from naka_gs_plugin.enhance.correction import DEFAULT_MODE, DEFAULT_WEIGHTS, ModeName, resolve_mode
from naka_gs_plugin.enhance.exposure import METERED_TARGET, Curve, Metering
from naka_gs_plugin.enhance.stages import (
    CaptureChromaStage,
    CorrectionStage,
    ExposureStage,
    NakaStage,
    SceneStage,
    ViewStage,
    to_float01,
)
from naka_gs_plugin.progress import StageProgress

CACHE_VERSION = 1
"""Bump when the enhancement maths change, so stale cache entries are never read."""


@dataclass
class EnhanceConfig(InstantiateConfig):
    """Train-image enhancement. CLI: ``--pipeline.datamanager.enhance.sigma 0.05`` and so on."""

    _target: Type = field(default_factory=lambda: Enhancer)
    method: Literal["naka", "none"] = "naka"
    """``naka``: Naka-Rushton response + min-max stretch; ``none``: train on the raw images (baseline)."""
    sigma: Union[float, Literal["auto"]] = 0.05
    """Naka-Rushton semi-saturation constant, in [0, 1] sRGB image units (reference: 0.05), or ``auto``:
    the mean sRGB value of the scene's training views (all pixels and channels), so that the scene's
    mean maps to half the response, as the retina's adaptation does -- LOM and LOL captures average
    about 0.05 (the reference value), RealX3D's about 0.02."""
    n: float = 1.0
    """Naka-Rushton exponent (reference: 1)."""
    stats: Literal["image", "scene"] = "image"
    """Min-max stretch statistics: per image (the reference) or pooled over all training views."""
    cache_dir: Optional[Path] = None
    """Where enhanced images are cached; default ``$NAKA_GS_CACHE`` or ``~/.cache/naka-gs``."""
    use_cache: bool = True
    """Read and write the on-disk cache of enhanced images."""
    correction: str = "default"
    """Correction network applied after Naka (method ``naka`` only): ``none``, ``default`` (the weights
    shipped in ``naka_gs_plugin/enhance/weights/``) or the path of a checkpoint (ours or the authors')."""
    chroma: Literal["capture", "network"] = "capture"
    """Colour of the enhanced views (method ``naka``; :mod:`naka_gs_plugin.enhance.chroma`): ``capture``
    keeps the enhanced brightness and takes each pixel's chromaticity (linear RGB) from the dark capture,
    which a shorter exposure does not change; ``network`` keeps the colour Naka + the correction network give."""
    chroma_blur: float = DEFAULT_BLUR
    """Gaussian low-pass, in pixels, on the capture before its chromaticity is taken (``chroma capture``):
    a dark capture's colour is noise at the pixel scale."""
    exposure: Union[float, Literal["none"]] = METERED_TARGET
    """Scene exposure after the correction network (:mod:`naka_gs_plugin.enhance.exposure`): when the
    enhanced views meter below this sRGB level, one curve (``exposure_curve``) shared by every view lifts
    them there (default 0.505, the metered level of normal-light photos); ``none`` keeps the network's
    exposure. Applied after the cache."""
    exposure_curve: Curve = "gain"
    """The curve ``exposure`` lifts with: ``gain``, every linear value times one factor with a highlight
    shoulder (a longer exposure: blacks and contrast kept), or ``power``, ``x ** g`` on the sRGB values
    (lifts shadows most, flattening the views; worse on the LOM protocol, docs/real-scenes.md)."""
    exposure_metering: Metering = "luminance"
    """How ``exposure`` reads a scene's level: ``luminance``, the mean luminance in linear light, as a
    camera meters (a dark-toned scene with bright areas is not lifted as if under-exposed), or ``mean``,
    the mean sRGB value."""
    correction_mode: ModeName = DEFAULT_MODE
    """Correction inference mode (``naka_gs_plugin.enhance.correction.MODES``): ``auto`` picks the fastest
    one that keeps the quality bar: when training on CUDA ``exact`` on that GPU, else on this CPU ``lean``
    with native bfloat16, else ``lean-f32``; ``exact`` is the plain float32 full-resolution forward (on the
    GPU when training there; every other mode runs on the CPU)."""

    def __setstate__(self, state: dict) -> None:
        """Runs saved before ``chroma`` or ``exposure_metering`` existed trained on the network's colour and
        on the mean sRGB metering: their ``config.yml`` keeps both."""
        state.setdefault("chroma", "network")
        state.setdefault("exposure_metering", "mean")
        state.setdefault("exposure_curve", "power")
        self.__dict__.update(state)

    def correction_path(self) -> Optional[Path]:
        """The checkpoint file of ``correction``, or ``None`` for ``none``."""
        if self.correction == "none":
            return None
        return DEFAULT_WEIGHTS if self.correction == "default" else Path(self.correction)


class Enhancer:
    """Applies the configured enhancement to a scene's training images, with a disk cache."""

    def __init__(self, config: EnhanceConfig, device: Union[torch.device, str] = "cpu") -> None:
        """``device``: where training runs; on CUDA the correction network runs there (see ``correction_mode``)."""
        self.config = config
        self.cache_dir: Optional[Path] = None
        """Where enhanced images are cached; None with ``use_cache False`` (no cache is touched)."""
        if config.use_cache:
            self.cache_dir = usable_cache_dir(config.cache_dir or default_cache_dir()) / "enhanced"
        self._cache_warned = False
        self.last_run = {"computed": 0, "cached": 0, "seconds": 0.0}
        """Counts of the last :meth:`enhance_images` call: images computed vs read from cache."""
        if config.sigma != "auto" and not (isinstance(config.sigma, (int, float)) and config.sigma > 0):
            raise ValueError(
                f"--pipeline.datamanager.enhance.sigma must be > 0 or auto, got {config.sigma!r} (default 0.05)"
            )
        if config.exposure != "none" and not (isinstance(config.exposure, (int, float)) and 0 < config.exposure < 1):
            raise ValueError(
                f"--pipeline.datamanager.enhance.exposure must be in (0, 1) or none, got {config.exposure!r} (default {METERED_TARGET})"
            )
        if config.exposure_metering not in ("luminance", "mean"):
            raise ValueError(
                "--pipeline.datamanager.enhance.exposure-metering must be luminance or mean, "
                f"got {config.exposure_metering!r} (default luminance)"
            )
        if config.exposure_curve not in ("gain", "power"):
            raise ValueError(
                "--pipeline.datamanager.enhance.exposure-curve must be gain or power, "
                f"got {config.exposure_curve!r} (default gain)"
            )
        if config.chroma not in ("capture", "network"):
            raise ValueError(
                f"--pipeline.datamanager.enhance.chroma must be capture or network, got {config.chroma!r} (default capture)"
            )
        if not (isinstance(config.chroma_blur, (int, float)) and config.chroma_blur > 0):
            raise ValueError(
                f"--pipeline.datamanager.enhance.chroma-blur must be > 0 pixels, got {config.chroma_blur!r} (default {DEFAULT_BLUR})"
            )
        if not config.n > 0:
            raise ValueError(f"--pipeline.datamanager.enhance.n must be > 0, got {config.n!r} (default 1.0)")
        fit_threads()  # the heavy stages (correction network, cpu-fast rasterizer) follow this count
        self.correction_path = config.correction_path() if config.method == "naka" else None
        self.correction_mode = resolve_mode(config.correction_mode, device)
        """The concrete inference mode (``auto`` resolved for this machine): part of the cache key."""
        on_cuda = torch.device(device).type == "cuda"
        self.correction_device = torch.device(device if on_cuda and self.correction_mode == "exact" else "cpu")
        """Where the correction network runs (only ``exact`` runs on a GPU); images are enhanced on the CPU."""
        if self.correction_path is not None and not self.correction_path.is_file():
            hint = (
                "the shipped default weights are missing from this install"
                if config.correction == "default"
                else "no such file"
            )
            raise FileNotFoundError(
                f"[naka-gs] correction weights {self.correction_path} not found ({hint}): pass "
                "--pipeline.datamanager.enhance.correction none (Naka only) or the path of a checkpoint"
            )
        self.view_stages: List[ViewStage] = []
        """Applied to each view, in order, before the cache."""
        self.scene_stages: List[SceneStage] = []
        """Applied to the whole scene's views, in order, after the cache."""
        self.correction: Optional[CorrectionStage] = None
        if config.method == "naka":
            self.view_stages.append(NakaStage(sigma=config.sigma, n=config.n, stats=config.stats))
            if self.correction_path is not None:
                self.correction = CorrectionStage.from_file(
                    self.correction_path, self.correction_mode, self.correction_device
                )
                self.view_stages.append(self.correction)
            if config.chroma == "capture":
                self.view_stages.append(CaptureChromaStage(blur=config.chroma_blur))
            if config.exposure != "none":
                self.scene_stages.append(
                    ExposureStage(
                        target=config.exposure, curve=config.exposure_curve, metering=config.exposure_metering
                    )
                )

    def key(self) -> str:
        """The parameter part of the cache key: every cached stage's :meth:`~Stage.key`, as JSON."""
        stages = [stage.key() for stage in self.view_stages]
        return json.dumps({"version": CACHE_VERSION, "stages": stages}, sort_keys=True, default=str)

    def _keys(self, images: Sequence[Tensor]) -> List[str]:
        hashes = [content_hash(im) for im in images]
        params = self.key()
        scene = ""
        if any(stage.scene_wide() for stage in self.view_stages):
            # Each view's output depends on every view: the key covers the whole set.
            scene = hashlib.sha1("".join(sorted(hashes)).encode()).hexdigest()
        return [hashlib.sha1(f"{params}|{h}|{scene}".encode()).hexdigest() for h in hashes]

    def _read(self, key: str, like: Tensor) -> Optional[Tensor]:
        """The cached enhancement of ``like`` (an input image), or None: a miss, or a corrupt entry
        (warned; it is recomputed and replaced)."""
        if self.cache_dir is None:
            return None
        path = self.cache_dir / f"{key}.npy"
        if not path.exists():
            return None
        try:
            arr = np.load(path)
            ok = arr.dtype == np.uint16 and arr.shape == (*like.shape[:2], 3)
        except (OSError, ValueError, EOFError):
            ok = False
        if not ok:
            CONSOLE.log(f"[naka-gs] warning: cache entry {path} is corrupt; recomputing it", markup=False)
            return None
        return torch.from_numpy(arr.astype(np.float32) / 65535.0)

    def _write(self, key: str, image: Tensor) -> None:
        """Store ``image`` atomically; a failed write (disk full, permissions) warns once and the run goes on."""
        if self.cache_dir is None:
            return
        # Raw uint16 .npy: lossless to 1.5e-5 and far faster to read than a 16-bit PNG, which matters once
        # the correction network makes recomputation expensive.
        arr = (image.detach().cpu().clamp(0, 1).numpy() * 65535.0).round().astype(np.uint16)
        try:
            self.cache_dir.mkdir(parents=True, exist_ok=True)
            atomic_write(self.cache_dir / f"{key}.npy", lambda tmp: np.save(tmp, arr))
        except OSError as err:
            if not self._cache_warned:
                CONSOLE.log(f"[naka-gs] warning: not caching enhanced images ({err})", markup=False)
                self._cache_warned = True

    def enhance_images(
        self, images: Sequence[UInt8[Tensor, "H W C"] | Float[Tensor, "H W C"]], description: str = "Enhancing"
    ) -> List[Float[Tensor, "H W 3"]]:
        """Enhance every image (sRGB [0,1] float32 out), reading/writing the cache; shows progress.

        ``images`` are one scene: the exposure curve (and ``sigma auto``, ``stats scene``) is computed over
        all of them."""
        start = time.perf_counter()
        if not self.view_stages:
            self.last_run = {"computed": 0, "cached": 0, "seconds": 0.0}
            return [to_float01(im) for im in images]
        keys = self._keys(images)
        out: List[Optional[Tensor]] = [self._read(k, im) for k, im in zip(keys, images)]
        todo = [i for i, o in enumerate(out) if o is None]
        seconds: Dict[str, float] = {stage.name: 0.0 for stage in self.view_stages}
        if todo:
            for stage in self.view_stages:
                stage.prepare(images)  # scene statistics read every view, cached or not
            chain = "; ".join(stage.describe() for stage in self.view_stages)
            with StageProgress() as progress:
                task = progress.add_task(f"{description} ({chain})", total=len(todo))
                for i in todo:
                    low = enhanced = to_float01(images[i])
                    for stage in self.view_stages:
                        t = time.perf_counter()
                        enhanced = stage.apply(enhanced, low)
                        seconds[stage.name] += time.perf_counter() - t
                    # Round to the cache's 16-bit grid so a run is identical with a cold or warm cache.
                    out[i] = (enhanced * 65535.0).round() / 65535.0
                    self._write(keys[i], out[i])
                    progress.advance(task)
        done = [o for o in out if o is not None]
        for stage in self.scene_stages:
            done = [(im * 65535.0).round() / 65535.0 for im in stage.apply_all(done)]
        exposure = next((stage for stage in self.scene_stages if isinstance(stage, ExposureStage)), None)
        value = exposure.value if exposure is not None else 1.0
        total = time.perf_counter() - start
        self.last_run = {
            "computed": len(todo),
            "cached": len(images) - len(todo),
            "seconds": total,
            **{f"{name}_seconds": s for name, s in seconds.items()},
            "exposure_curve": self.config.exposure_curve,
            "exposure_value": value,
        }
        CONSOLE.log(
            f"[naka-gs] {description}: {len(images)} images, {len(todo)} computed, "
            f"{len(images) - len(todo)} from cache ({self.cache_dir or 'cache off'}) in {total:.2f} s"
            + (
                f", exposure lifted to {exposure.target} ({exposure.metering} metering, "
                f"{'gain' if exposure.curve == 'gain' else 'gamma'} {value:.3f})"
                if value != 1.0
                else ""
            ),
            markup=False,
        )
        return done
