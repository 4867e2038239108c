"""Scene specs: YAML files (``configs/scenes/*.yaml``) read into dataclasses and validated.

A spec names a **source** (``procedural`` or ``capture``) and an explicit list of **effects**;
an effect that is not listed is not applied at all. Example::

    name: dark-noisy
    seed: 0              # sensor-noise stream (a different seed changes the noise only)
    scene_seed: 0        # textures, lamps, exposure jitter, point cloud
    source:
      procedural: {n_train: 16, n_test: 4, width: 160, height: 120}
    effects:
      - exposure: {factor: 0.012}
      - noise: {shot_gain: 0.0002, read_std: 0.001}
      - quantize: {}

Effects run in the fixed order of :data:`EFFECT_ORDER` whatever their order in the file.
Relative capture paths resolve against the **current working directory** (run the CLI and the
tests from the repository root, so ``../shared/data/lom/sofa`` is the shared LOM scene).
Every problem raises :class:`SimSpecError` with one line naming the file and the field.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Tuple, Union, get_args, get_type_hints

import numpy as np
import yaml

from naka_gs_plugin.errors import UserError
from naka_gs_plugin.shipped import CONFIGS, config_file


class SimSpecError(UserError, ValueError):
    """A scene spec is invalid; the message is one line: ``<file>: field '<field>': <problem>``."""


@dataclass(frozen=True)
class Sim3Spec:
    """Known similarity ``x' = scale * R @ x + translation`` from the training frame to the points' frame."""

    scale: float = 1.0
    rotation_deg: Tuple[float, float, float] = (0.0, 0.0, 0.0)
    """XYZ Euler angles in degrees, applied as ``Rz @ Ry @ Rx``."""
    translation: Tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class PointCloudSpec:
    """Dense "feed-forward-like" point cloud of a procedural scene (``points.ply``)."""

    n_points: int = 20000
    """Points sampled on the object surfaces (before outliers and clusters)."""
    noise_std: float = 0.01
    """Gaussian position noise, world units of the training frame."""
    outlier_fraction: float = 0.02
    """Extra points uniform in the scene's bounding box, as a fraction of ``n_points``."""
    n_clusters: int = 3
    """Over-dense clusters (many points piled at one surface spot)."""
    cluster_size: int = 400
    cluster_std: float = 0.02
    sim3: Sim3Spec = field(default_factory=Sim3Spec)


@dataclass(frozen=True)
class ProceduralSource:
    """Textured spheres, boxes, a floor and a backdrop of small opaque Gaussians, seen by a rig."""

    n_train: int = 16
    n_test: int = 4
    width: int = 160
    height: int = 120
    fov_deg: float = 55.0
    """Horizontal field of view; ``fl_x = fl_y = 0.5 * width / tan(fov/2)``, principal point at the centre."""
    layout: Literal["orbit", "forward"] = "orbit"
    """``orbit``: a ring around the objects; ``forward``: a grid of forward-facing cameras."""
    spacing: float = 0.05
    """Distance between neighbouring surface Gaussians, world units (smaller = more Gaussians)."""
    points: PointCloudSpec = field(default_factory=PointCloudSpec)


@dataclass(frozen=True)
class CaptureSource:
    """A clean multi-view capture in the ``lowlight-data`` layout with normal-light images (LOM ``high/``)."""

    path: Path = Path("../shared/data/lom/sofa")
    """Scene folder; relative paths resolve against the current working directory."""
    n_train: int = 16
    """First ``n_train`` frames of ``transforms_train.json`` (their ``low/`` paths map to ``high/``)."""
    n_test: int = 4
    """First ``n_test`` frames of ``transforms_test.json``."""
    downscale: int = 4
    """Integer image downscale (box filter, size floored; intrinsics scaled as nerfstudio does)."""


@dataclass(frozen=True)
class Exposure:
    """Multiply linear radiance by ``factor`` (< 1 darkens; real low-light scenes: mean sRGB 0.01-0.05)."""

    factor: float = 0.01


@dataclass(frozen=True)
class ExposureJitter:
    """Per-view exposure multiplier ``2 ** N(0, stops)`` (drawn from ``scene_seed``)."""

    stops: float = 0.3


@dataclass(frozen=True)
class LightSources:
    """Bright lamps at fixed 3D points (added after exposure), saturating with a blurred bloom."""

    count: int = 3
    intensity: float = 20.0
    """Peak linear radiance of a lamp core (1.0 = sensor white), independent of ``exposure``."""
    radius: float = 0.06
    """Lamp core radius, world units."""
    bloom_sigma_px: float = 4.0
    """Gaussian blur sigma of the glare, pixels."""
    bloom_strength: float = 0.15
    """Fraction of the above-white energy spread as glare."""


@dataclass(frozen=True)
class ColorCast:
    """White-balance gains per channel (R, G, B), linear light."""

    gains: Tuple[float, float, float] = (1.2, 1.0, 0.7)


@dataclass(frozen=True)
class Noise:
    """Poisson shot + Gaussian read noise on the linear signal ``x`` in [0, 1]: ``var = shot_gain * x + read_std**2``."""

    shot_gain: float = 2e-4
    read_std: float = 1e-3


@dataclass(frozen=True)
class Response:
    """Camera response: ``srgb`` (the sRGB transfer curve) or ``gamma`` (``x ** (1/gamma)``)."""

    curve: Literal["srgb", "gamma"] = "srgb"
    gamma: float = 2.2


@dataclass(frozen=True)
class Quantize:
    """Round to 8 bits (``round(255 x) / 255``) and write 8-bit files; without it files are 16-bit PNG."""


@dataclass(frozen=True)
class Jpeg:
    """JPEG compression of the training images at ``quality`` (1-95); requires ``quantize``."""

    quality: int = 90


Effect = Union[Exposure, ExposureJitter, LightSources, ColorCast, Noise, Response, Quantize, Jpeg]

EFFECT_ORDER: Dict[str, type] = {
    "exposure": Exposure,
    "exposure_jitter": ExposureJitter,
    "light_sources": LightSources,
    "color_cast": ColorCast,
    "noise": Noise,
    "response": Response,
    "quantize": Quantize,
    "jpeg": Jpeg,
}
"""Effect names in the fixed, physically ordered pipeline (scene light -> sensor -> file)."""

EFFECT_NAMES: Dict[type, str] = {cls: name for name, cls in EFFECT_ORDER.items()}


@dataclass(frozen=True)
class SceneSpec:
    name: str
    source: Union[ProceduralSource, CaptureSource]
    effects: Tuple[Effect, ...]
    """Listed effects only, sorted into :data:`EFFECT_ORDER`."""
    seed: int = 0
    scene_seed: int = 0
    path: Optional[Path] = None

    def effect(self, cls: type) -> Optional[Effect]:
        """The listed effect of type ``cls``, or ``None`` if the spec does not list it."""
        return next((e for e in self.effects if isinstance(e, cls)), None)

    def to_dict(self) -> Dict[str, Any]:
        """Plain, YAML/JSON-ready dict that :func:`parse_spec` reads back to an equal spec."""
        kind = "procedural" if isinstance(self.source, ProceduralSource) else "capture"
        return {
            "name": self.name,
            "seed": self.seed,
            "scene_seed": self.scene_seed,
            "source": {kind: to_jsonable(dataclasses.asdict(self.source))},
            "effects": [{EFFECT_NAMES[type(e)]: to_jsonable(dataclasses.asdict(e))} for e in self.effects],
        }


def to_jsonable(value: Any) -> Any:
    """Dicts, lists, paths and numpy scalars -> plain JSON/YAML types (recursively)."""
    if isinstance(value, dict):
        return {k: to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return value


_POSITIVE = {
    "n_train", "n_test", "width", "height", "fov_deg", "spacing", "factor", "intensity", "radius", "gamma", "scale",
    "downscale", "cluster_std", "bloom_sigma_px", "quality", "cluster_size",
}  # fmt: skip
_NON_NEGATIVE = {
    "n_points", "noise_std", "outlier_fraction", "n_clusters", "stops", "count", "bloom_strength",
    "shot_gain", "read_std",
}  # fmt: skip


class _Reader:
    """Builds dataclasses from YAML mappings, raising :class:`SimSpecError` with the field path."""

    def __init__(self, path: Path):
        self.path = path

    def fail(self, where: str, problem: str) -> SimSpecError:
        return SimSpecError(f"{self.path}: field '{where}': {problem}")

    def build(self, cls: type, data: Any, where: str) -> Any:
        if data is None:
            data = {}
        if not isinstance(data, dict):
            raise self.fail(where, f"expected a mapping, got {type(data).__name__}")
        fields = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - set(fields))
        if unknown:
            raise self.fail(f"{where}.{unknown[0]}", f"unknown field (known: {', '.join(fields) or 'none'})")
        kwargs = {name: self.value(cls, name, data[name], f"{where}.{name}") for name in data}
        return cls(**kwargs)

    def value(self, cls: type, name: str, raw: Any, where: str) -> Any:
        default = next(f for f in dataclasses.fields(cls) if f.name == name)
        sample = default.default if default.default is not dataclasses.MISSING else default.default_factory()
        if dataclasses.is_dataclass(sample):
            return self.build(type(sample), raw, where)
        if isinstance(sample, Path):
            if not isinstance(raw, str):
                raise self.fail(where, "expected a path string")
            return Path(raw)
        if isinstance(sample, tuple):
            if not isinstance(raw, (list, tuple)) or len(raw) != len(sample):
                raise self.fail(where, f"expected a list of {len(sample)} numbers, got {raw!r}")
            values = tuple(self.number(float, v, where) for v in raw)
            if name == "gains" and any(v <= 0 for v in values):
                raise self.fail(where, f"gains must be > 0 (got {list(values)})")
            return values
        if isinstance(sample, str):
            allowed = get_args(get_type_hints(cls)[name])
            if raw not in allowed:
                raise self.fail(where, f"invalid value {raw!r} (allowed: {', '.join(allowed)})")
            return raw
        value = self.number(type(sample), raw, where)
        if name in _POSITIVE and not value > 0:
            raise self.fail(where, f"must be > 0 (got {raw!r})")
        if name in _NON_NEGATIVE and not value >= 0:
            raise self.fail(where, f"must be >= 0 (got {raw!r})")
        return value

    def number(self, kind: type, raw: Any, where: str) -> Union[int, float]:
        if isinstance(raw, bool) or not isinstance(raw, (int, float)):
            raise self.fail(where, f"expected a number, got {raw!r}")
        if kind is int and not float(raw).is_integer():
            raise self.fail(where, f"expected an integer, got {raw!r}")
        if not math.isfinite(raw):
            raise self.fail(where, f"must be finite (got {raw!r})")
        return kind(raw)


MAX_VIEWS = 2000
"""Most views (train + test) a spec may ask for: simulated scenes need tens to a few hundred; more is a typo."""
MAX_SIDE = 8192
"""Largest procedural image width or height, pixels."""
MAX_OUTPUT_GB = 16.0
"""Largest scene a procedural spec may write, in GB of uncompressed image data (PNG saves a part of it)."""


def _check_plausible(reader: "_Reader", kind: str, source: Union[ProceduralSource, CaptureSource]) -> None:
    """Refuse view counts and sizes no scene needs, before minutes of work and gigabytes of files (one line each)."""
    views = source.n_train + source.n_test
    if views > MAX_VIEWS:
        field_ = "n_train" if source.n_train >= source.n_test else "n_test"
        raise reader.fail(
            f"source.{kind}.{field_}",
            f"{source.n_train} training + {source.n_test} test views is over the limit of {MAX_VIEWS} -- "
            "a simulated scene needs tens to a few hundred views: lower n_train / n_test",
        )
    if not isinstance(source, ProceduralSource):
        return  # a capture's views are its images: their number and size are the capture's
    for side in ("width", "height"):
        if getattr(source, side) > MAX_SIDE:
            raise reader.fail(
                f"source.{kind}.{side}", f"{getattr(source, side)} px is over the limit of {MAX_SIDE} -- lower it"
            )
    # Each training view writes its degraded image and its truth, each test view its truth; 16-bit RGB at most.
    gigabytes = (2 * source.n_train + source.n_test) * source.width * source.height * 3 * 2 / 1e9
    if gigabytes > MAX_OUTPUT_GB:
        raise reader.fail(
            f"source.{kind}",
            f"{views} views of {source.width}x{source.height} would write about {gigabytes:.0f} GB of images, over "
            f"the limit of {MAX_OUTPUT_GB:.0f} GB -- lower n_train, n_test, width or height",
        )


def parse_spec(data: Any, path: Path) -> SceneSpec:
    """Validate a spec mapping (as read from ``path``, which only names the file in errors)."""
    reader = _Reader(path)
    if not isinstance(data, dict):
        raise SimSpecError(f"{path}: field '<root>': expected a mapping with name, source and effects")
    unknown = sorted(set(data) - {"name", "seed", "scene_seed", "source", "effects"})
    if unknown:
        raise reader.fail(unknown[0], "unknown field (known: name, seed, scene_seed, source, effects)")
    name = data.get("name", Path(path).stem)
    if not isinstance(name, str) or not name:
        raise reader.fail("name", "expected a non-empty string")
    seeds = {k: int(reader.number(int, data.get(k, 0), k)) for k in ("seed", "scene_seed")}

    source_data = data.get("source")
    if not isinstance(source_data, dict) or len(source_data) != 1:
        raise reader.fail("source", "expected exactly one of 'procedural: {...}' or 'capture: {...}'")
    ((kind, params),) = source_data.items()
    kinds = {"procedural": ProceduralSource, "capture": CaptureSource}
    if kind not in kinds:
        raise reader.fail(f"source.{kind}", "unknown source (known: procedural, capture)")
    source = reader.build(kinds[kind], params, f"source.{kind}")
    if isinstance(source, CaptureSource):
        if "path" not in (params or {}):
            raise reader.fail("source.capture.path", "required (the clean capture's scene folder)")
        if not (source.path / "transforms_train.json").is_file():
            raise reader.fail(
                "source.capture.path", f"no capture at {source.path.resolve()} (needs transforms_train.json)"
            )

    _check_plausible(reader, kind, source)

    effects_data = data.get("effects", [])
    if not isinstance(effects_data, list):
        raise reader.fail("effects", "expected a list of one-key mappings like '- exposure: {factor: 0.01}'")
    found: Dict[str, Effect] = {}
    for i, item in enumerate(effects_data):
        if isinstance(item, str):
            item = {item: {}}
        if not isinstance(item, dict) or len(item) != 1:
            raise reader.fail(f"effects[{i}]", "expected a one-key mapping like '- exposure: {factor: 0.01}'")
        ((ename, eparams),) = item.items()
        if ename not in EFFECT_ORDER:
            raise reader.fail(f"effects[{i}].{ename}", f"unknown effect (known: {', '.join(EFFECT_ORDER)})")
        if ename in found:
            raise reader.fail(f"effects[{i}].{ename}", "listed twice")
        found[ename] = reader.build(EFFECT_ORDER[ename], eparams, f"effects[{i}].{ename}")
    if "jpeg" in found and "quantize" not in found:
        raise reader.fail("effects.jpeg", "JPEG stores 8-bit values: list 'quantize' too")
    if "jpeg" in found and found["jpeg"].quality > 95:
        raise reader.fail("effects.jpeg.quality", f"must be <= 95 (got {found['jpeg'].quality})")
    effects = tuple(found[n] for n in EFFECT_ORDER if n in found)
    return SceneSpec(name=name, source=source, effects=effects, path=Path(path), **seeds)


def load_spec(path: Union[str, Path]) -> SceneSpec:
    """Read and validate a YAML scene spec (``configs/scenes/...``: the shipped one if there is no such file)."""
    path = config_file(Path(path))
    if not path.is_file():
        raise SimSpecError(f"{path}: field '<file>': spec file not found")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as err:
        raise SimSpecError(f"{path}: field '<yaml>': malformed YAML ({' '.join(str(err).split())})") from None
    return parse_spec(data, path)


def shipped_specs() -> List[Path]:
    """The spec files shipped in the package's ``configs/scenes/``."""
    return sorted((CONFIGS / "scenes").glob("*.yaml"))
