"""The enhancement applied to training images: a chain of stages (:mod:`naka_gs_plugin.enhance.stages`).

One :class:`Enhancer` turns a scene's low-light training images into enhanced ones, once, with a
rich progress bar: per view the Naka-Rushton response, the correction network, capture chroma and tone,
kept in an on-disk cache keyed by image content plus every cached stage's :meth:`~Stage.key`, so a
second run (or ``ns-eval``/``ns-viewer`` after training) does not recompute anything; then the
scene's exposure. Eval images never pass through here.

Images in and out are sRGB-encoded, channel-last ``[H, W, 3]``; input ``uint8`` in [0, 255] or
float in [0, 1]; output ``float32`` in [0, 1].
"""

from __future__ import annotations

import hashlib
import io
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Sequence, Tuple, Type, Union

import numpy as np
import torch
import tyro
from jaxtyping import Float, UInt8
from nerfstudio.configs.base_config import InstantiateConfig
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor

from naka_gs_plugin.cpu import fit_threads, reclaim_core
from naka_gs_plugin.data.cache import content_hash, default_cache_dir, read_sealed, seal
from naka_gs_plugin.data.safe_io import atomic_write
from naka_gs_plugin.enhance.chroma import DEFAULT_BLUR
from naka_gs_plugin.enhance.correction import (
    DEFAULT_MODE,
    DEFAULT_WEIGHTS,
    CorrectionWeightsError,
    CorrectionWeightsNotFoundError,
    ModeName,
    resolve_mode,
)
from naka_gs_plugin.enhance.exposure import METERED_TARGET
from naka_gs_plugin.enhance.profile import chain_key
from naka_gs_plugin.enhance.stages import (
    CHAIN,
    CorrectionStage,
    ExposureStage,
    ProfileStage,
    SceneStage,
    ViewStage,
    to_float01,
)
from naka_gs_plugin.errors import UserError
from naka_gs_plugin.progress import StageProgress

CACHE_VERSION = 1
"""Bump when the cache's own format changes (a stage's maths: that stage's ``version``), so stale entries are never
read."""


RETIRED: Dict[str, Tuple[Any, str]] = {
    "stats": ("image", "each view's own stretch runs (scene-pooled statistics were no better)"),
    "chroma": ("capture", "the capture's chromaticity runs (the network's own colour lost to it)"),
    "exposure_curve": ("gain", "the linear-light gain runs (the sRGB power curve lost to it)"),
    "exposure_metering": ("luminance", "linear-luminance metering runs (mean sRGB metering lost to it)"),
    "cache_dir": (None, "every cache lives in $NAKA_GS_CACHE: set it to keep using that folder"),
}
"""Options removed from :class:`EnhanceConfig`: the value that behaves as today, and what runs instead
(each measurement: records/2026-11-27-levers.md)."""
LEGACY_DEFAULTS = {
    "chroma": "network",
    "exposure_metering": "mean",
    "exposure_curve": "power",
    "tone": "network",
    "profile": None,
}
"""What runs saved before an option existed did (their ``config.yml`` lacks the key): a live option loads with it,
a retired one is checked against what runs now."""
CORRECTION_OPTION = "--pipeline.datamanager.enhance.correction"


class EnhanceOptionError(UserError, ValueError):
    """An :class:`EnhanceConfig` value out of its range (``sigma``, ``n``, ``exposure``, ``chroma-blur``): one line
    naming the ``--pipeline.datamanager.enhance.*`` option, the value and the default."""


@dataclass
class EnhanceConfig(InstantiateConfig):
    """Train-image enhancement. CLI: ``--pipeline.datamanager.enhance.sigma 0.05`` and so on."""

    _target: Type = field(default_factory=lambda: Enhancer)
    method: Literal["naka", "none"] = "naka"
    """``naka``: Naka-Rushton response + min-max stretch, the correction network, the capture's
    chromaticity and tone, and the scene exposure; ``none``: train on the raw images (baseline)."""
    sigma: Union[float, Literal["auto"]] = 0.05
    """Naka-Rushton semi-saturation constant, in [0, 1] sRGB image units (reference: 0.05), or ``auto``:
    the mean sRGB value of the scene's training views (all pixels and channels), so that the scene's
    mean maps to half the response, as the retina's adaptation does -- LOM and LOL captures average
    about 0.05 (the reference value), RealX3D's about 0.02."""
    n: tyro.conf.Suppress[float] = 1.0
    """Naka-Rushton exponent (reference: 1)."""
    use_cache: bool = True
    """Read and write the on-disk cache of enhanced images (in ``$NAKA_GS_CACHE``, default ``~/.cache/naka-gs``)."""
    correction: str = "default"
    """Correction network applied after Naka (method ``naka`` only): ``none``, ``default`` (the weights
    shipped in ``naka_gs_plugin/enhance/weights/``) or the path of a checkpoint (ours or the authors')."""
    chroma_blur: tyro.conf.Suppress[float] = DEFAULT_BLUR
    """Gaussian low-pass, in pixels, on the capture before its chromaticity is taken
    (:mod:`naka_gs_plugin.enhance.chroma`): a dark capture's colour is noise at the pixel scale."""
    tone: Literal["capture", "network"] = "capture"
    """``capture``: where the dark capture recorded no signal (under 2-4 codes), no part of a view brighter against
    it, in linear light, than the view's median enhancement gain (:mod:`naka_gs_plugin.enhance.tone`: the network
    lifts black, most on captures far darker than LOL and LOM, such as RealX3D); ``network``: the tone of the Naka
    response and the correction network as they come."""
    profile: Optional[Path] = None
    """A camera profile from ``naka-gs-calibrate`` (a .json file): the enhanced views as the camera that took the
    calibration pairs renders normal light (its colour and tone at this darkness;
    :mod:`naka_gs_plugin.enhance.profile`). Applied after capture tone; its content hash is in the cache key."""
    exposure: Union[float, Literal["auto", "none"]] = "auto"
    """Scene exposure after the correction network (:mod:`naka_gs_plugin.enhance.exposure`): when the
    enhanced views meter below this sRGB level (mean luminance in linear light, as a camera meters), one
    linear-light gain shared by every view lifts them there; ``auto``: 0.505 (the metered level of normal-light
    photos) without a profile, and no lift with one (the profile carries its camera's normal exposure);
    ``none`` keeps the chain's exposure. Applied after the cache."""
    correction_mode: ModeName = DEFAULT_MODE
    """Correction inference mode (``naka_gs_plugin.enhance.correction.MODES``): ``auto`` picks the fastest
    one that keeps the quality bar: when training on CUDA ``exact`` on that GPU, else on this CPU ``lean``
    with native bfloat16, else ``lean-f32``; ``exact`` is the plain float32 full-resolution forward (on the
    GPU when training there; every other mode runs on the CPU)."""

    def __setstate__(self, state: dict) -> None:
        """A saved run's ``config.yml`` may lack options added since (it loads with what it ran,
        :data:`LEGACY_DEFAULTS`) or name options retired since (:data:`RETIRED`): each one that asked for something
        other than what runs now is dropped with one warning."""
        for option in LEGACY_DEFAULTS.keys() - RETIRED.keys():
            state.setdefault(option, LEGACY_DEFAULTS[option])
        if state.keys() & RETIRED.keys():  # saved before the retirement (a config saved since has none)
            for option, (now, why) in RETIRED.items():
                asked = state.pop(option, LEGACY_DEFAULTS.get(option))
                if asked is not None and asked != now:
                    CONSOLE.log(
                        f"[naka-gs] warning: this run's config asks for enhance.{option} {asked!r}, retired: {why}",
                        markup=False,
                    )
        self.__dict__.update(state)

    def __post_init__(self) -> None:
        # Absolute, so that the run's config.yml names the profile from any folder ns-eval or ns-viewer start in.
        if self.profile is not None:
            self.profile = Path(self.profile).expanduser().absolute()

    def exposure_target(self) -> Optional[float]:
        """The metered level the exposure step lifts to, or None when it is off (``none``; ``auto`` with a profile)."""
        if self.exposure == "auto":
            return METERED_TARGET if self.profile is None else None
        return None if self.exposure == "none" else float(self.exposure)

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
            self.cache_dir = default_cache_dir() / "enhanced"
        self._cache_warned = False
        self.last_run = {"computed": 0, "cached": 0, "seconds": 0.0}
        """Counts of the last :meth:`enhance_images` call: images computed vs read from cache."""
        if config.sigma != "auto" and not (isinstance(config.sigma, (int, float)) and config.sigma > 0):
            raise EnhanceOptionError(
                f"--pipeline.datamanager.enhance.sigma must be > 0 or auto, got {config.sigma!r} (default 0.05)"
            )
        if config.exposure not in ("auto", "none") and not (
            isinstance(config.exposure, (int, float)) and 0 < config.exposure < 1
        ):
            raise EnhanceOptionError(
                f"--pipeline.datamanager.enhance.exposure must be in (0, 1), auto or none, got {config.exposure!r} "
                f"(default auto: {METERED_TARGET} without a profile)"
            )
        if config.profile is not None and config.method != "naka":
            raise EnhanceOptionError(
                f"--pipeline.datamanager.enhance.profile {config.profile} applies to the naka enhancement, not method "
                f"{config.method}: drop the profile or use --pipeline.datamanager.enhance.method naka"
            )
        if not (isinstance(config.chroma_blur, (int, float)) and config.chroma_blur > 0):
            raise EnhanceOptionError(
                f"--pipeline.datamanager.enhance.chroma-blur must be > 0 pixels, got {config.chroma_blur!r} (default {DEFAULT_BLUR})"
            )
        if not config.n > 0:
            raise EnhanceOptionError(f"--pipeline.datamanager.enhance.n must be > 0, got {config.n!r} (default 1.0)")
        fit_threads()  # the heavy stages (correction network, cpu-fast rasterizer) follow this count
        self.correction_path = config.correction_path() if config.method == "naka" else None
        self.correction_mode = (
            resolve_mode(config.correction_mode, device) if self.correction_path is not None else config.correction_mode
        )
        """The concrete inference mode (``auto`` resolved, and its choice printed, only where the network runs)."""
        on_cuda = torch.device(device).type == "cuda"
        self.correction_device = torch.device(device if on_cuda and self.correction_mode == "exact" else "cpu")
        """Where the correction network runs (only ``exact`` runs on a GPU); images are enhanced on the CPU."""
        if self.correction_path is not None and not self.correction_path.is_file():
            hint = (
                "the shipped default weights are missing from this install"
                if config.correction == "default"
                else "no such file"
            )
            raise CorrectionWeightsNotFoundError(
                f"correction weights {self.correction_path} not found ({hint}): pass "
                f"{CORRECTION_OPTION} none (Naka only) or the path of a checkpoint"
            )
        self.view_stages: List[ViewStage] = []
        """Applied to each view, in order, before the cache."""
        self.scene_stages: List[SceneStage] = []
        """Applied to the whole scene's views, in order, after the cache."""
        for stage_type in CHAIN:
            stage = stage_type.build(config, self)
            if stage is not None:
                (self.view_stages if isinstance(stage, ViewStage) else self.scene_stages).append(stage)
        self.correction: Optional[CorrectionStage] = next(
            (stage for stage in self.view_stages if isinstance(stage, CorrectionStage)), None
        )
        profile = next((stage for stage in self.view_stages if isinstance(stage, ProfileStage)), None)
        if profile is not None and profile.profile().chain != chain_key(self.view_stages):
            CONSOLE.log(
                f"[naka-gs] warning: camera profile {profile.path} was fitted after another enhancement chain "
                f"({profile.profile().chain}); its colours may be off -- calibrate again with these "
                "--enhance options",
                markup=False,
            )

    def _correction_fix(self) -> str:
        """What to pass instead of correction weights that do not load."""
        if self.config.correction == "default":
            return f"reinstall naka-gs (its shipped weights are damaged) or pass {CORRECTION_OPTION} none (Naka only)"
        return f"or pass {CORRECTION_OPTION} default (the shipped weights) or none (Naka only)"

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

    def _read(self, key: str, like: Tensor, bad: Dict[str, List[Path]]) -> Optional[Tensor]:
        """The cached enhancement of ``like`` (an input image), or None: a miss, or an entry that cannot be used
        (added to ``bad`` under the reason; it is recomputed and replaced)."""
        if self.cache_dir is None:
            return None
        path = self.cache_dir / f"{key}.npy"
        data, why = read_sealed(path)
        if data is None:
            if why:
                bad.setdefault(why, []).append(path)
            return None
        try:
            arr = np.load(io.BytesIO(data))
            ok = arr.dtype == np.uint16 and arr.shape == (*like.shape[:2], 3)
        except (OSError, ValueError, EOFError):
            ok = False
        if not ok:
            bad.setdefault("is corrupt", []).append(path)
            return None
        return torch.from_numpy(arr.astype(np.float32) / 65535.0)

    @staticmethod
    def _warn_bad_entries(bad: Dict[str, List[Path]]) -> None:
        """One line per reason naming the entries that are recomputed (the first of many)."""
        for why, paths in bad.items():
            if len(paths) == 1:
                line = f"cache entry {paths[0]} {why}; recomputing it"
            else:
                line = f"cache entry {paths[0]} and {len(paths) - 1} more: each {why}; recomputing them"
            CONSOLE.log(f"[naka-gs] warning: {line}", markup=False)

    def _write(self, key: str, image: Tensor) -> None:
        """Store ``image`` atomically; a failed write (disk full, permissions) warns once and the run goes on."""
        if self.cache_dir is None:
            return
        # Raw uint16 .npy: lossless to 1.5e-5 and far faster to read than a 16-bit PNG, which matters once
        # the correction network makes recomputation expensive.
        arr = (image.detach().cpu().clamp(0, 1).numpy() * 65535.0).round().astype(np.uint16)
        try:
            self.cache_dir.mkdir(parents=True, exist_ok=True)
            seal(atomic_write(self.cache_dir / f"{key}.npy", lambda tmp: np.save(tmp, arr)))
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
        bad: Dict[str, List[Path]] = {}
        out: List[Optional[Tensor]] = [self._read(k, im, bad) for k, im in zip(keys, images)]
        self._warn_bad_entries(bad)
        todo = [i for i, o in enumerate(out) if o is None]
        seconds: Dict[str, float] = {stage.name: 0.0 for stage in self.view_stages}
        if todo:
            for stage in self.view_stages:
                try:
                    stage.prepare(images)  # scene statistics read every view, cached or not
                except CorrectionWeightsError as err:  # the network loads here, on first use
                    raise type(err)(f"{CORRECTION_OPTION} {err} -- {self._correction_fix()}") from None
            chain = "; ".join(stage.describe() for stage in self.view_stages)
            with StageProgress() as progress:
                task = progress.add_task(f"{description} ({chain})", total=len(todo))
                for i in todo:
                    reclaim_core()  # a core lent to a first run's kernel compile comes back once it is done
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
        reclaim_core()
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
            "exposure_gain": value,
        }
        CONSOLE.log(
            f"[naka-gs] {description}: {len(images)} images, {len(todo)} computed, "
            f"{len(images) - len(todo)} from cache ({self.cache_dir or 'cache off'}) in {total:.2f} s"
            + (f", exposure lifted to {exposure.target} (linear-light gain {value:.3f})" if value != 1.0 else ""),
            markup=False,
        )
        return done
