"""The enhancement as a chain of stages, each a dataclass whose fields are everything that changes its output.

:class:`naka_gs_plugin.enhance.pipeline.Enhancer` runs the chain: per view the Naka response, the
correction network and capture chroma, then the cache, then the stages that look at the whole
scene's enhanced views (exposure). A :class:`ViewStage` runs per view before the cache, a
:class:`SceneStage` on the cached views of the whole scene. The cache key is :meth:`Stage.key` of every cached
stage, derived from the stage's fields, so an option a stage reads is in the key by construction;
only a field declared with :func:`runtime` is left out: one that does not change the output (a
device, a path whose content is keyed instead, state computed from the scene).

A stage's ``apply`` takes and returns sRGB [0, 1] ``float32`` images, channel-last ``[H, W, 3]``.
"""

from __future__ import annotations

import abc
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Dict, List, Literal, Optional, Sequence, Tuple, Union

import torch
from jaxtyping import Float
from torch import Tensor

from naka_gs_plugin.enhance.chroma import capture_chroma
from naka_gs_plugin.enhance.correction import CorrectionRunner, file_digest, load_correction
from naka_gs_plugin.enhance.exposure import Curve, Metering, apply_curve, lift
from naka_gs_plugin.enhance.naka import linear_stretch, naka_rushton, stretch_stats

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

    def key(self) -> Dict[str, Any]:
        """Everything that changes this stage's output: its name and every field not marked :func:`runtime`."""
        fields = dataclasses.fields(self)
        return {"stage": self.name, **{f.name: getattr(self, f.name) for f in fields if f.metadata.get("key", True)}}

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
    stats: Literal["image", "scene"] = "image"
    _sigma: Optional[float] = runtime(default=None, init=False)
    _scene_range: Optional[Tuple[Tensor, Tensor]] = runtime(default=None, init=False)

    def scene_wide(self) -> bool:
        return self.sigma == "auto" or self.stats == "scene"

    def prepare(self, lows: Sequence[Tensor]) -> None:
        self._sigma = scene_sigma(lows) if self.sigma == "auto" else float(self.sigma)
        if self.stats == "scene":
            ranges = [stretch_stats(naka_rushton(to_float01(im), self._sigma, self.n)) for im in lows]
            los, his = zip(*ranges)
            self._scene_range = (torch.stack(los).amin(), torch.stack(his).amax())

    def apply(self, image: Float[Tensor, "H W 3"], low: Float[Tensor, "H W 3"]) -> Float[Tensor, "H W 3"]:
        if self._sigma is None:
            raise RuntimeError("NakaStage.prepare must run before apply")
        response = naka_rushton(low, self._sigma, self.n)
        lo, hi = self._scene_range if self._scene_range is not None else stretch_stats(response)
        return linear_stretch(response, lo, hi)

    def describe(self) -> str:
        sigma = f"{self._sigma:.4g}" if self._sigma is not None else str(self.sigma)
        return f"naka, sigma {sigma}, {self.stats} stats"


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

    def apply(self, image: Float[Tensor, "H W 3"], low: Float[Tensor, "H W 3"]) -> Float[Tensor, "H W 3"]:
        return capture_chroma(image, low, self.blur)

    def describe(self) -> str:
        return f"capture chroma (blur {self.blur:g} px)"


@dataclass
class ExposureStage(SceneStage):
    """One curve shared by every view lifts the scene's metered level to ``target`` when it is below it
    (:mod:`naka_gs_plugin.enhance.exposure`); after the cache, as it needs the whole scene."""

    name: ClassVar[str] = "exposure"
    target: float = 0.505
    curve: Curve = "gain"
    metering: Metering = "luminance"
    value: float = runtime(default=1.0, init=False)
    """The curve's parameter the last :meth:`apply_all` chose (1: the scene was left alone)."""

    def apply_all(self, images: List[Float[Tensor, "H W 3"]]) -> List[Float[Tensor, "H W 3"]]:
        """Every view of the scene, lifted by one curve (unchanged when the scene meters at ``target`` or above)."""
        self.value = lift(images, self.curve, float(self.target), self.metering)
        return images if self.value == 1.0 else apply_curve(images, self.curve, self.value)
