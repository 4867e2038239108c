"""The enhancement as a chain of stages, each a dataclass whose fields are everything that changes its output.

:class:`naka_gs_plugin.enhance.pipeline.Enhancer` runs the chain: per view the Naka response, the
correction network, capture chroma, capture tone and a camera profile when one is given, then the cache, then the stages that look at the whole
scene's enhanced views (exposure). A :class:`ViewStage` runs per view before the cache, a
:class:`SceneStage` on the cached views of the whole scene. The cache key is :meth:`Stage.key` of every cached
stage, derived from the stage's fields, so an option a stage reads is in the key by construction;
only a field declared with :func:`runtime` is left out: one that does not change the output (a
device, a path whose content is keyed instead, state computed from the scene). A change of a stage's maths
that no field expresses bumps its :attr:`Stage.version`, which the key carries too.

A stage's ``apply`` takes and returns sRGB [0, 1] ``float32`` images, channel-last ``[H, W, 3]``.
"""

from __future__ import annotations

import abc
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Dict, List, Literal, Optional, Sequence, Tuple, Type, Union

import torch
from jaxtyping import Float
from torch import Tensor

from naka_gs_plugin.enhance.chroma import capture_chroma
from naka_gs_plugin.enhance.correction import CorrectionRunner, file_digest, load_correction
from naka_gs_plugin.enhance.exposure import apply_gain, lift_gain
from naka_gs_plugin.enhance.naka import linear_stretch, naka_rushton, stretch_stats
from naka_gs_plugin.enhance.profile import CameraProfile, apply_maps, check_view
from naka_gs_plugin.enhance.tone import DEFAULT_BLUR as TONE_BLUR
from naka_gs_plugin.enhance.tone import FLOOR_CODES as TONE_FLOOR
from naka_gs_plugin.enhance.tone import capture_tone

SIGMA_FLOOR = 1e-3
"""Lower bound of ``sigma auto`` (an all-black scene must not divide by zero)."""


def runtime(**kwargs: Any) -> Any:
    """A stage field that does not change the output (device, handles): left out of :meth:`Stage.key`."""
    return field(metadata={"key": False}, compare=False, repr=False, **kwargs)


def to_float01(image: Tensor) -> Float[Tensor, "H W 3"]:
    """``uint8`` [0, 255] or float [0, 1] -> ``float32`` [0, 1]; only the first 3 channels (RGB)."""
    image = image[..., :3]
    if image.dtype == torch.uint8:
        return image.float() / 255.0
    return image.float()


def scene_sigma(images: Sequence[Tensor]) -> float:
    """``sigma auto``: the mean sRGB [0, 1] value over every pixel and channel of ``images`` (views may
    differ in size; each pixel weighs the same), at least :data:`SIGMA_FLOOR`."""
    total = sum(float(to_float01(im).sum(dtype=torch.float64)) for im in images)
    count = sum(to_float01(im).numel() for im in images)
    return max(SIGMA_FLOOR, total / max(count, 1))


@dataclass
class Stage:
    """One step of the enhancement; subclasses are dataclasses and set :attr:`name`."""

    name: ClassVar[str]
    version: ClassVar[int] = 1
    """Bump when this stage's output changes for the same fields (its maths), so no cached view of the old maths
    is read again."""

    @classmethod
    @abc.abstractmethod
    def build(cls, config: Any, enhancer: Any) -> Optional["Stage"]:
        """This stage as an :class:`~naka_gs_plugin.enhance.pipeline.EnhanceConfig` asks for it, or ``None``
        when the config leaves it out (``enhancer``: the resolved weights, inference mode and device)."""

    def key(self) -> Dict[str, Any]:
        """Everything that changes this stage's output: its name, version and every field not marked :func:`runtime`."""
        fields = dataclasses.fields(self)
        values = {f.name: getattr(self, f.name) for f in fields if f.metadata.get("key", True)}
        return {"stage": self.name, "version": self.version, **values}

    def describe(self) -> str:
        """A few words for the progress bar."""
        return self.name


@dataclass
class ViewStage(Stage, abc.ABC):
    """A stage applied to each view on its own, before the cache (its key is part of the cache key)."""

    def scene_wide(self) -> bool:
        """Whether one view's output depends on every view (then the cache key covers the whole set)."""
        return False

    def prepare(self, lows: Sequence[Tensor]) -> None:
        """Scene statistics from every input view (``uint8`` or float, as captured), before any :meth:`apply`."""

    @abc.abstractmethod
    def apply(self, image: Float[Tensor, "H W 3"], low: Float[Tensor, "H W 3"]) -> Float[Tensor, "H W 3"]:
        """This stage on one view: ``image`` from the stage before, ``low`` the capture it came from."""


@dataclass
class SceneStage(Stage, abc.ABC):
    """A stage applied to the cached views of the whole scene at once (it reads all of them)."""

    @abc.abstractmethod
    def apply_all(self, images: List[Float[Tensor, "H W 3"]]) -> List[Float[Tensor, "H W 3"]]:
        """This stage on every view of the scene."""


@dataclass
class NakaStage(ViewStage):
    """The Naka-Rushton response ``R = I^n / (I^n + sigma^n)`` per channel, then a min-max stretch
    (:mod:`naka_gs_plugin.enhance.naka`); the first stage, it ignores ``image`` and reads ``low``."""

    name: ClassVar[str] = "naka"
    sigma: Union[float, Literal["auto"]] = 0.05
    n: float = 1.0
    _sigma: Optional[float] = runtime(default=None, init=False)

    @classmethod
    def build(cls, config: Any, enhancer: Any) -> Optional["NakaStage"]:
        return cls(sigma=config.sigma, n=config.n) if config.method == "naka" else None

    def scene_wide(self) -> bool:
        return self.sigma == "auto"

    def prepare(self, lows: Sequence[Tensor]) -> None:
        self._sigma = scene_sigma(lows) if self.sigma == "auto" else float(self.sigma)

    def apply(self, image: Float[Tensor, "H W 3"], low: Float[Tensor, "H W 3"]) -> Float[Tensor, "H W 3"]:
        if self._sigma is None:
            raise RuntimeError("NakaStage.prepare must run before apply")
        response = naka_rushton(low, self._sigma, self.n)
        return linear_stretch(response, *stretch_stats(response))

    def describe(self) -> str:
        sigma = f"{self._sigma:.4g}" if self._sigma is not None else str(self.sigma)
        return f"naka, sigma {sigma}"


@dataclass
class CorrectionStage(ViewStage):
    """The chroma-correction U-Net on (capture, Naka image) (:mod:`naka_gs_plugin.enhance.correction`).

    Keyed by the weights' content hash and the concrete inference mode, not by the file's path."""

    name: ClassVar[str] = "correction"
    weights_sha1: str = ""
    mode: str = "exact"
    path: Path = runtime(default=Path())
    device: torch.device = runtime(default=torch.device("cpu"))
    """Where the network runs (only ``exact`` runs on a GPU); images stay on the CPU between stages."""
    _runner: Optional[CorrectionRunner] = runtime(default=None, init=False)

    @classmethod
    def from_file(cls, path: Path, mode: str, device: torch.device) -> "CorrectionStage":
        return cls(weights_sha1=file_digest(path), mode=mode, path=Path(path), device=device)

    @classmethod
    def build(cls, config: Any, enhancer: Any) -> Optional["CorrectionStage"]:
        if config.method != "naka" or enhancer.correction_path is None:
            return None
        return cls.from_file(enhancer.correction_path, enhancer.correction_mode, enhancer.correction_device)

    def runner(self) -> CorrectionRunner:
        """The network, loaded on first use."""
        if self._runner is None:
            self._runner = CorrectionRunner(load_correction(self.path).to(self.device), self.mode)
        return self._runner

    def prepare(self, lows: Sequence[Tensor]) -> None:
        self.runner()

    def apply(self, image: Float[Tensor, "H W 3"], low: Float[Tensor, "H W 3"]) -> Float[Tensor, "H W 3"]:
        pair = [x.permute(2, 0, 1)[None].to(self.device) for x in (low, image)]
        return self.runner()(*pair)["enhanced"][0].permute(1, 2, 0).cpu()

    def describe(self) -> str:
        return f"correction {self.path.name} ({self.mode})"


@dataclass
class CaptureChromaStage(ViewStage):
    """The enhanced brightness with the capture's own (blurred) chromaticity (:mod:`naka_gs_plugin.enhance.chroma`)."""

    name: ClassVar[str] = "chroma"
    blur: float = 3.0

    @classmethod
    def build(cls, config: Any, enhancer: Any) -> Optional["CaptureChromaStage"]:
        return cls(blur=config.chroma_blur) if config.method == "naka" else None

    def apply(self, image: Float[Tensor, "H W 3"], low: Float[Tensor, "H W 3"]) -> Float[Tensor, "H W 3"]:
        return capture_chroma(image, low, self.blur)

    def describe(self) -> str:
        return f"capture chroma (blur {self.blur:g} px)"


@dataclass
class CaptureToneStage(ViewStage):
    """No pixel brighter, against the capture, than the view's median enhancement gain
    (:mod:`naka_gs_plugin.enhance.tone`)."""

    name: ClassVar[str] = "tone"
    blur: float = TONE_BLUR
    floor: Tuple[float, float] = TONE_FLOOR

    @classmethod
    def build(cls, config: Any, enhancer: Any) -> Optional["CaptureToneStage"]:
        return cls() if config.method == "naka" and config.tone == "capture" else None

    def apply(self, image: Float[Tensor, "H W 3"], low: Float[Tensor, "H W 3"]) -> Float[Tensor, "H W 3"]:
        return capture_tone(image, low, self.blur, self.floor)

    def describe(self) -> str:
        return f"capture tone (blur {self.blur:g} px, below {self.floor[0]:g}-{self.floor[1]:g} codes)"


@dataclass
class ProfileStage(ViewStage):
    """A camera profile from ``naka-gs-calibrate`` (:mod:`naka_gs_plugin.enhance.profile`): the chain's output as
    that camera renders it at normal light. Keyed by the profile file's content hash, not its path."""

    name: ClassVar[str] = "profile"
    profile_sha1: str = ""
    path: Path = runtime(default=Path())
    _profile: Optional[CameraProfile] = runtime(default=None, init=False)
    _maps: Optional[Tuple[Tensor, Tensor, Optional[Tensor]]] = runtime(default=None, init=False)
    """The profile's curves, matrix and look-up table (or None) as tensors, made once for every view."""

    @classmethod
    def build(cls, config: Any, enhancer: Any) -> Optional["ProfileStage"]:
        if config.method != "naka" or config.profile is None:
            return None
        path = Path(config.profile)
        CameraProfile.load(path, PROFILE_OPTION)  # a bad file fails here, before any image is read
        return cls(profile_sha1=file_digest(path), path=path)

    def profile(self) -> CameraProfile:
        if self._profile is None:
            self._profile = CameraProfile.load(self.path, PROFILE_OPTION)
        return self._profile

    def apply(self, image: Float[Tensor, "H W 3"], low: Float[Tensor, "H W 3"]) -> Float[Tensor, "H W 3"]:
        if self._maps is None:
            self._maps = self.profile().tensors()
        out = apply_maps(image.float(), *self._maps)
        check_view(image, out, self.path, PROFILE_OPTION)  # a view it made black, white or flat: one line
        return out

    def describe(self) -> str:
        return f"camera profile {self.path.name}"


PROFILE_OPTION = "--pipeline.datamanager.enhance.profile"


@dataclass
class ExposureStage(SceneStage):
    """One linear-light gain shared by every view lifts the scene's metered level to ``target`` when it is
    below it (:mod:`naka_gs_plugin.enhance.exposure`); after the cache, as it needs the whole scene."""

    name: ClassVar[str] = "exposure"
    target: float = 0.505
    value: float = runtime(default=1.0, init=False)
    """The gain the last :meth:`apply_all` chose (1: the scene was left alone)."""

    @classmethod
    def build(cls, config: Any, enhancer: Any) -> Optional["ExposureStage"]:
        target = config.exposure_target()
        return cls(target=target) if config.method == "naka" and target is not None else None

    def apply_all(self, images: List[Float[Tensor, "H W 3"]]) -> List[Float[Tensor, "H W 3"]]:
        """Every view of the scene, lifted by one gain (unchanged when the scene meters at ``target`` or above)."""
        self.value = lift_gain(images, float(self.target))
        return images if self.value == 1.0 else apply_gain(images, self.value)


CHAIN: Tuple[Type[Stage], ...] = (
    NakaStage,
    CorrectionStage,
    CaptureChromaStage,
    CaptureToneStage,
    ProfileStage,
    ExposureStage,
)
"""The enhancement, in order: each stage's :meth:`Stage.build` decides from the config whether it runs. A new
stage is a class here (with ``build``) plus the config field it reads."""
