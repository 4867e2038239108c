"""A camera profile: how one camera renders a dark frame, learnt once from a few dark/normal pairs.

The profile maps the enhancement chain's output (sRGB [0, 1], after the Naka response, the correction network,
capture chroma and capture tone) onto the camera's normal-light rendering of the same view, per pixel:

1. a monotone curve per channel, from the enhanced sRGB value to linear light (level-dependent gains: the dark
   JPEG loses its red difference in the shadows, not in the highlights);
2. a 3x3 colour matrix in linear light (the cross-channel part of the cast), then the sRGB encoding;
3. optionally (version 2, ``naka-gs-calibrate --lut-size``), a residual 3D look-up table in sRGB, trilinear, fitted
   smooth: what depends on hue and saturation together (a red bent one way, a yellow another), which a curve per
   channel and one matrix cannot express.

It is fitted robustly (a Huber loss in sRGB: squared errors, as PSNR weighs them, up to :data:`HUBER_DELTA`; what a
pair does not share beyond it, a moved object or a lamp, pulls no harder) on area-downscaled pairs, in seconds, by :func:`fit_profile`; :func:`apply_profile` is the view stage's maths. A profile is a small JSON file
(``naka-gs-calibrate`` writes it) that also records the chain it was fitted after and the pairs' exposure ratios.
Version 1 files (no look-up table) are read as they always were.

A profile is checked as a photo is (:meth:`CameraProfile.load`, then :func:`check_view` on each view it renders): a
file that is too large or too deeply nested is refused before it is parsed, and maps that would make the views black,
white, flat or tone-inverted are refused with one line naming the check and the fix (the bounds below, each with
what ``naka-gs-calibrate`` writes against it).
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor

from naka_gs_plugin.enhance.exposure import linear_to_srgb, srgb_to_linear
from naka_gs_plugin.errors import UserError

PROFILE_FORMAT = "naka-gs-camera-profile"
PROFILE_VERSION = 2
READ_VERSIONS = (1, 2)
"""Versions read: 1 has no ``lut`` (the maps are the same without one)."""
KNOTS = 17
"""Curve knots, evenly spaced in the enhanced sRGB value: a step of 1/16 (16 codes of 255)."""
FIT_LONG_SIDE = 512
"""Pairs are area-downscaled to this longer side before fitting: it averages the dark frame's noise and a pair's
sub-pixel misalignment, and keeps the fit to seconds."""


HUBER_DELTA = 0.1
"""Residuals beyond this (sRGB, 25 codes) count linearly in the fit."""


MAX_BYTES = 4 << 20
"""Largest profile file read (4 MiB): without a look-up table the profiles naka-gs-calibrate wrote from RealX3D, LOL
and LOM pairs are 4.4-8.1 KB (17 knots x 3 curves, a 3x3 matrix, the chain's keys, about 200 bytes per pair); a
:data:`LUT_MAX_SIZE` table adds about 1.5 MB (3 x 33^3 numbers, one per line). Anything larger is not a profile; no
more of it is read."""
LUT_MAX_SIZE = 33
"""Largest look-up table side (cells per axis): 33 is the common size of colour LUTs (a step of 8 codes of 255)."""
LUT_MAX = 0.5
"""Largest residual of a look-up table cell, in magnitude (sRGB): half the range. A residual beyond it moves a colour
across the gamut: not a profile of a camera."""
MAX_DEPTH = 16
"""Deepest bracket nesting read (objects and arrays): a calibrated profile nests 4-5 deep (the chain's stage keys, a
pair's shift); checked on the bytes before ``json`` parses them, whose recursive parser ends in a ``RecursionError``
near 1000 levels."""
CURVE_MAX = 16.0
"""Largest curve value (linear light, 1 = white): 4 stops above white, where every pixel is clipped to white after
the matrix. Calibrated curves reach 0.76-1.41."""
MIN_RISE = 0.01
"""Least rise of each curve from its first knot to its last (linear light; from black, about 25 sRGB codes): a
curve rising less renders the views flat in that channel (an all-zero curve rises 0). Calibrated curves rise
0.55-0.72."""
FALL_TOLERANCE = 1e-6
"""A curve's knots never fall by more than this (linear light): the fit builds them rising (cumulative softplus
steps); this only forgives a hand edit's rounding. A falling curve inverts the tones."""
MATRIX_MAX = 8.0
"""Largest colour-matrix entry, in magnitude (1e30 clips every view to black or white). Calibrated matrices reach
1.77 (1.18 away from the identity)."""
CONDITION_MAX = 100.0
"""Largest condition number (2-norm) of the colour matrix: how much more it amplifies one colour direction than
another, noise included; a nearly singular matrix collapses the colours onto a plane. Calibrated matrices: 1.3-5.6
(determinants 0.49-1.98; one of ``-1``, as ``-I``'s, inverts the colours: the determinant must be > 0)."""
RAMP_MIN_SPAN = 0.05
"""Least rise (sRGB, about 13 codes) of each output channel from black to white over a grey ramp, through the curves
and the matrix together (rising curves and a matrix of determinant > 0 can still zero a channel or turn it down:
``diag(-1, -1, 1)``). Calibrated profiles rise 0.71-0.98."""
RAMP_MAX_FALL = 0.25
"""Largest fall (sRGB, a quarter of the range) of an output channel along that ramp, below its highest value so far:
a profile that tone-inverts the highlights. Not 0: a calibrated matrix mixes channels and grey near white is rare in
the pairs, so a channel may dip there (BlueHawaii's red falls 0.056-0.075 over the last 5 % of the ramp)."""
VIEW_FLAT_RANGE = 0.25 / 255.0
"""Least contrast (0.1-99.9 % pixel range, sRGB [0, 1]) of a view the profile rendered: a quarter of an 8-bit level,
the bound the photos themselves are held to (``naka_gs_plugin.datamanager.FLAT_RANGE``)."""
VIEW_MIN_INPUT_RANGE = 1.0 / 255.0
"""A view is blamed on the profile only when its input to the profile spans at least one 8-bit level: a flat
photo is the photo's check's to report."""


class CameraProfileError(UserError, ValueError):
    """A profile file that cannot be used (missing, not a profile, damaged); the message names it and the fix."""


class UnusableProfileError(CameraProfileError):
    """A camera profile (its ``format`` says so) whose curves or matrix would render the views black, white, flat or
    tone-inverted (:func:`check_maps`, :func:`check_view`): calibrating again replaces it (:func:`is_profile_file`)."""


def _number(value: Any) -> bool:
    """A JSON number: an int or a float, not a bool (``true`` is a Python ``bool``, a subclass of ``int``)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _describe(value: Any) -> str:
    """``value`` as its JSON reads (``true``, ``NaN``, ``"text"``), shortened."""
    if isinstance(value, float) and math.isfinite(value):
        return f"{value:g}"
    text = json.dumps(value, default=str)
    return text if len(text) <= 40 else text[:37] + "..."


def _grid(value: Any, rows: int, cols: int, name: str) -> Optional[str]:
    """What is wrong with ``value`` as ``rows`` lists of ``cols`` finite numbers, or None."""
    if not (isinstance(value, list) and len(value) == rows and all(isinstance(r, list) for r in value)):
        got = f"{len(value)} items" if isinstance(value, list) else f"a {type(value).__name__}"
        return f"{name} must be {rows} lists of {cols} numbers, not {got}"
    for i, row in enumerate(value):
        if len(row) != cols:
            return f"{name}[{i}] has {len(row)} numbers, not {cols}"
        for j, v in enumerate(row):
            if not _number(v):
                return f"{name}[{i}][{j}] is {_describe(v)}, not a number"
            try:
                finite = math.isfinite(float(v))
            except OverflowError:
                finite = False
            if not finite:
                return (
                    f"{name}[{i}][{j}] is {_describe(v) if isinstance(v, float) else 'too large'}, not a finite number"
                )
    return None


def _check_lut(lut: Any) -> Optional[str]:
    """What is wrong with ``lut`` as a profile's JSON holds a look-up table (``[3][D][D][D]`` finite numbers within
    :data:`LUT_MAX`, ``2 <= D <= LUT_MAX_SIZE``), or None."""
    size = len(lut[0]) if isinstance(lut, list) and lut and isinstance(lut[0], list) else 0
    if not (isinstance(lut, list) and len(lut) == 3 and 2 <= size <= LUT_MAX_SIZE):
        return f"lut must be 3 tables of D x D x D numbers (2 <= D <= {LUT_MAX_SIZE})"
    for c, table in enumerate(lut):
        if not (isinstance(table, list) and len(table) == size):
            return f"lut[{c}] has {len(table) if isinstance(table, list) else 'no'} planes, not {size}"
        for b, plane in enumerate(table):
            problem = _grid(plane, size, size, f"lut[{c}][{b}]")
            if problem:
                return problem
    big = float(torch.tensor(lut, dtype=torch.float64).abs().max())
    if big > LUT_MAX:
        return f"the look-up table has a residual of magnitude {big:g}, beyond {LUT_MAX:g} (sRGB)"
    return None


def check_maps(curves: Any, matrix: Any, lut: Any = None) -> Optional[str]:
    """What makes ``curves`` and ``matrix`` (as a profile's JSON holds them) unusable, in a few words, or None: the
    shapes and types, finite values in range (:data:`CURVE_MAX`, :data:`MATRIX_MAX`), rising curves
    (:data:`FALL_TOLERANCE`, :data:`MIN_RISE`), a matrix that neither inverts colours (determinant > 0) nor is
    ill-conditioned (:data:`CONDITION_MAX`), and a grey ramp that comes out rising in every channel
    (:data:`RAMP_MIN_SPAN`, :data:`RAMP_MAX_FALL`), the look-up table (if any) included. Every profile
    ``naka-gs-calibrate`` wrote passes (the bounds' notes give their values)."""
    problem = _grid(curves, 3, KNOTS, "curves") or _grid(matrix, 3, 3, "matrix")
    problem = problem or (None if lut is None else _check_lut(lut))
    if problem:
        return problem
    for c, curve in enumerate(curves):
        name = f"curves[{c}] ({'rgb'[c]})"
        low, high = min(curve), max(curve)
        if low < 0 or high > CURVE_MAX:
            return f"{name} reaches {low if low < 0 else high:g}, outside 0-{CURVE_MAX:g} (linear light, 1 = white)"
        fall = next((k for k in range(1, KNOTS) if curve[k] < curve[k - 1] - FALL_TOLERANCE), None)
        if fall is not None:
            return (
                f"{name} falls from {curve[fall - 1]:g} to {curve[fall]:g} at knot {fall}: a profile's curves "
                "rise (a falling one inverts the tones)"
            )
        if curve[-1] - curve[0] < MIN_RISE:
            return (
                f"{name} is flat ({curve[0]:g} to {curve[-1]:g}): a curve rises by at least {MIN_RISE:g} (linear light)"
            )
    m = torch.tensor(matrix, dtype=torch.float64)
    big = float(m.abs().max())
    if big > MATRIX_MAX:
        return f"the colour matrix has an entry of magnitude {big:g}, beyond {MATRIX_MAX:g}"
    det = float(torch.linalg.det(m))
    if det <= 0:
        return f"the colour matrix has determinant {det:g}: it inverts colours (a profile's matrix has determinant > 0)"
    cond = float(torch.linalg.cond(m))
    if not cond <= CONDITION_MAX:
        return f"the colour matrix has condition number {cond:.3g}, beyond {CONDITION_MAX:g}: it is nearly singular"
    ramp = torch.linspace(0, 1, 256, dtype=torch.float32)[:, None].expand(-1, 3)
    table = None if lut is None else torch.tensor(lut, dtype=torch.float32)
    out = apply_maps(ramp, torch.tensor(curves, dtype=torch.float32), m.float(), table)
    for c in range(3):
        channel = out[:, c]
        rise = float(channel[-1] - channel[0])
        fall = float((torch.cummax(channel, 0).values - channel).max())
        if rise < RAMP_MIN_SPAN or fall > RAMP_MAX_FALL:
            why = (
                f"falls by {fall:.3f} on the way, more than {RAMP_MAX_FALL:g}"
                if rise >= RAMP_MIN_SPAN
                else f"rises by less than {RAMP_MIN_SPAN:g}"
            )
            return (
                f"a grey ramp from black to white comes out {'rgb'[c]} {float(channel[0]):.3f} to "
                f"{float(channel[-1]):.3f} ({why}, sRGB): the profile's maps together flatten or invert that channel"
            )
    return None


_STRING = re.compile(rb'"(?:[^"\\]|\\.)*(?:"|\\?\Z)', re.DOTALL)
"""A JSON string, or an unterminated one to the end of the text: matched in one pass, never retried from a later
quote (linear time on any 1 MiB file)."""


def nesting_depth(raw: bytes) -> int:
    """The deepest bracket nesting (``[`` and ``{``) of JSON text, outside its strings, without parsing it."""
    b = np.frombuffer(_STRING.sub(b"", raw), dtype=np.uint8)
    step = np.isin(b, (ord("["), ord("{"))).astype(np.int64) - np.isin(b, (ord("]"), ord("}")))
    return int(np.cumsum(step).max(initial=0))


@dataclass
class CameraProfile:
    """The fitted maps (see the module docstring) and what they were fitted on."""

    curves: List[List[float]]
    """``[3][KNOTS]`` linear-light outputs at the knots ``k / (KNOTS - 1)`` of each channel's enhanced sRGB value."""
    matrix: List[List[float]]
    """``[3][3]`` colour matrix applied to the curves' linear RGB (row = output channel)."""
    chain: Dict[str, Any] = field(default_factory=dict)
    """The enhancement stages it was fitted after (their cache keys): a run with another chain is warned."""
    pairs: List[Dict[str, Any]] = field(default_factory=list)
    """Per calibration pair: name, exposure ratio, PSNR before and after the profile."""
    fit: Dict[str, Any] = field(default_factory=dict)
    """How the fit went: seconds, samples, loss."""
    lut: Optional[List[List[List[List[float]]]]] = None
    """``[3][D][D][D]`` residual look-up table (sRGB, added after the matrix), indexed ``[channel][blue][green][red]``
    at the cells ``k / (D - 1)``; None: none (every version 1 profile)."""

    def to_json(self) -> str:
        return json.dumps({"format": PROFILE_FORMAT, "version": PROFILE_VERSION, **asdict(self)}, indent=1)

    @classmethod
    def load(cls, path: Path, option: str = "--enhance.profile") -> "CameraProfile":
        """Read ``path``; a missing, damaged or unusable file (see :func:`check_maps`) raises one line naming
        ``option`` and the fix."""
        fix = f"pass {option} the .json file naka-gs-calibrate wrote, or leave {option} out"
        data = _read_json(Path(path), option, fix)
        if not isinstance(data, dict) or data.get("format") != PROFILE_FORMAT:
            raise CameraProfileError(f"{option} {path}: not a camera profile -- {fix}")
        version = data.get("version")
        if not (_number(version) and version in READ_VERSIONS):
            raise CameraProfileError(
                f"{option} {path}: profile version {_describe(version)}, this naka-gs reads "
                f"{' and '.join(map(str, READ_VERSIONS))} -- "
                "calibrate again with this version (naka-gs-calibrate PAIRS --out PROFILE)"
            )
        missing = [k for k in ("curves", "matrix") if k not in data]
        if missing:
            raise CameraProfileError(f"{option} {path}: damaged camera profile (no {' or '.join(missing)}) -- {fix}")
        for key, kind in (("chain", dict), ("pairs", list), ("fit", dict)):
            if not isinstance(data.get(key, kind()), kind):
                raise CameraProfileError(
                    f"{option} {path}: damaged camera profile ({key} is a {type(data[key]).__name__}, not a "
                    f"{'list' if kind is list else 'mapping'}) -- {fix}"
                )
        lut = data.get("lut") if version >= 2 else None
        problem = check_maps(data["curves"], data["matrix"], lut)
        if problem:
            raise UnusableProfileError(f"{option} {path}: unusable camera profile: {problem} -- {_refit(option)}")
        return cls(
            curves=[[float(v) for v in row] for row in data["curves"]],
            matrix=[[float(v) for v in row] for row in data["matrix"]],
            **{k: data.get(k, {} if k != "pairs" else []) for k in ("chain", "pairs", "fit")},
            lut=None if lut is None else torch.tensor(lut, dtype=torch.float64).tolist(),
        )

    def tensors(self) -> tuple[Float[Tensor, "3 K"], Float[Tensor, "3 3"], Optional[Float[Tensor, "3 D D D"]]]:
        """The curves, the matrix and the look-up table (None without one), float32."""
        lut = None if self.lut is None else torch.tensor(self.lut, dtype=torch.float32)
        return torch.tensor(self.curves, dtype=torch.float32), torch.tensor(self.matrix, dtype=torch.float32), lut


def _refit(option: str) -> str:
    """The fix of an unusable profile. A new file: ``naka-gs-calibrate --out`` replaces only a file it recognises."""
    return f"calibrate again (naka-gs-calibrate PAIRS --out NEW.json), or leave {option} out"


def _read_json(path: Path, option: str, fix: str) -> Any:
    """``path``'s JSON, read only if it is at most :data:`MAX_BYTES` and nests at most :data:`MAX_DEPTH` deep;
    otherwise, or when it is missing or not JSON, one line naming ``option`` and ``fix``."""
    try:
        with open(path, "rb") as f:
            raw = f.read(MAX_BYTES + 1)
    except FileNotFoundError:
        raise CameraProfileError(f"{option} {path}: no such file -- {fix}") from None
    except OSError as err:
        raise CameraProfileError(f"{option} {path}: not a camera profile ({err}) -- {fix}") from None
    if len(raw) > MAX_BYTES:
        raise CameraProfileError(
            f"{option} {path}: not a camera profile (larger than {MAX_BYTES >> 20} MiB; a profile is at most about 1.5 MB) -- {fix}"
        )
    depth = nesting_depth(raw)
    if depth > MAX_DEPTH:
        raise CameraProfileError(
            f"{option} {path}: not a camera profile (brackets nested {depth} deep, more than {MAX_DEPTH}) -- {fix}"
        )
    try:
        return json.loads(raw.decode("utf-8-sig"))
    except (UnicodeDecodeError, ValueError, RecursionError) as err:  # ValueError: JSONDecodeError, huge ints
        why = " ".join(str(err).split()) if not isinstance(err, RecursionError) else "nested too deep"
        raise CameraProfileError(f"{option} {path}: not a camera profile ({why}) -- {fix}") from None


def is_profile_file(path: Path) -> bool:
    """Whether ``path`` is a camera profile by its ``format``, usable or not (:class:`UnusableProfileError`): a file
    ``naka-gs-calibrate --out`` may replace."""
    try:
        data = _read_json(Path(path), "--out", "")
    except CameraProfileError:
        return False
    return isinstance(data, dict) and data.get("format") == PROFILE_FORMAT


def chain_key(stages: Sequence[Any]) -> Dict[str, Any]:
    """What a profile records of the view stages before it (their cache keys, as JSON values), leaving out the
    correction's inference mode: the modes agree to the quality bar, and which one runs depends on the CPU."""
    keys = [{k: v for k, v in stage.key().items() if k != "mode"} for stage in stages if stage.name != "profile"]
    return json.loads(json.dumps({"stages": keys}, default=str))


def _monotone(first: Float[Tensor, "3 1"], steps: Float[Tensor, "3 K-1"]) -> Float[Tensor, "3 K"]:
    """Curves from their fitted parameters: the first knot's value and the steps between knots, both through
    softplus, so every curve is positive and rising."""
    return torch.cumsum(torch.nn.functional.softplus(torch.cat([first, steps], 1)), 1)


def _curve(x: Float[Tensor, "*N 3"], curves: Float[Tensor, "3 K"]) -> Float[Tensor, "*N 3"]:
    """Piecewise-linear interpolation of each channel's curve at ``x`` (sRGB [0, 1]) -> linear light."""
    k = curves.shape[1] - 1
    pos = x.clamp(0, 1) * k
    lo = pos.floor().clamp(max=k - 1).long()
    frac = pos - lo
    flat = curves.t()  # [K, 3]: row = knot
    ch = torch.arange(3, device=x.device).expand_as(lo)
    return flat[lo, ch] * (1 - frac) + flat[lo + 1, ch] * frac


def apply_lut(x: Float[Tensor, "*N 3"], lut: Float[Tensor, "3 D D D"]) -> Float[Tensor, "*N 3"]:
    """The residual look-up table's value at sRGB ``x`` (channel-last, [0, 1]): trilinear between its cells
    (``grid_sample`` on the ``[blue][green][red]`` grid, whose ``x, y, z`` axes are red, green, blue)."""
    grid = (x.reshape(-1, 3).clamp(0, 1) * 2 - 1)[None, :, None, None, :]
    out = torch.nn.functional.grid_sample(lut[None], grid, mode="bilinear", align_corners=True)
    return out[0, :, :, 0, 0].t().reshape(x.shape)


def apply_maps(
    image: Float[Tensor, "*N 3"],
    curves: Float[Tensor, "3 K"],
    matrix: Float[Tensor, "3 3"],
    lut: Optional[Float[Tensor, "3 D D D"]] = None,
) -> Float[Tensor, "*N 3"]:
    """The profile's maths on sRGB [0, 1] values (channel-last): curves to linear light, matrix, sRGB encoding, then
    the look-up table's residual (if any)."""
    out = linear_to_srgb((_curve(image, curves) @ matrix.t()).clamp(0, 1))
    return out if lut is None else (out + apply_lut(out, lut)).clamp(0, 1)


def apply_profile(image: Float[Tensor, "H W 3"], profile: CameraProfile) -> Float[Tensor, "H W 3"]:
    """``image`` (sRGB [0, 1]) as the profile's camera renders it at normal light (sRGB [0, 1], float32)."""
    return apply_maps(image.float(), *profile.tensors())


def _contrast(image: Float[Tensor, "H W 3"]) -> tuple[float, float]:
    """The 0.1 and 99.9 % quantiles of ``image``'s values (every channel; on at most about 256x256 pixels), as
    the photos' own check measures them."""
    sample = image[:: max(1, image.shape[0] // 256), :: max(1, image.shape[1] // 256)].float().flatten().cpu()
    lo, hi = torch.quantile(sample, torch.tensor([0.001, 0.999])).tolist()
    return lo, hi


def check_view(before: Float[Tensor, "H W 3"], after: Float[Tensor, "H W 3"], path: Path, option: str) -> None:
    """Refuse, in one line naming the profile at ``path`` and the fix, a view the profile rendered all black, all
    white or flat (:data:`VIEW_FLAT_RANGE`) from one with contrast (``before``, its input; a flat photo is left to
    the photos' check)."""
    lo, hi = _contrast(after)
    if hi - lo >= VIEW_FLAT_RANGE:
        return
    lo_in, hi_in = _contrast(before)
    if hi_in - lo_in < VIEW_MIN_INPUT_RANGE:
        return
    kind = "all black" if hi < 0.1 else "all white" if lo > 0.9 else "flat"
    raise UnusableProfileError(
        f"{option} {path}: the camera profile renders a view {kind} (its values span {lo:.4f}-{hi:.4f}; "
        f"{lo_in:.4f}-{hi_in:.4f} before the profile) -- calibrate again with the --enhance options of this run "
        f"(naka-gs-calibrate PAIRS --out NEW.json), or leave {option} out"
    )


def _area(image: Float[Tensor, "H W 3"], long_side: int) -> Float[Tensor, "h w 3"]:
    """Area-average ``image`` so its longer side is at most ``long_side``."""
    h, w = image.shape[:2]
    f = max(1, math.ceil(max(h, w) / long_side))
    if f == 1:
        return image
    x = image.permute(2, 0, 1)[None, :, : h // f * f, : w // f * f]
    return torch.nn.functional.avg_pool2d(x, f)[0].permute(1, 2, 0)


def _fit_pixels(
    inputs: Sequence[Float[Tensor, "H W 3"]], references: Sequence[Float[Tensor, "H W 3"]]
) -> tuple[Float[Tensor, "N 3"], Float[Tensor, "N 3"]]:
    """The pixels the profile's maps are fitted on: each pair area-downscaled to :data:`FIT_LONG_SIDE`, less those
    whose reference is clipped (they carry no level or colour: they would pull the maps down at the top)."""
    x = torch.cat([_area(i.float(), FIT_LONG_SIDE).reshape(-1, 3) for i in inputs])
    y = torch.cat([_area(r.float(), FIT_LONG_SIDE).reshape(-1, 3) for r in references])
    keep = y.max(dim=1).values < 0.98
    return x[keep], y[keep]


def fit_profile(
    enhanced: Sequence[Float[Tensor, "H W 3"]],
    references: Sequence[Float[Tensor, "H W 3"]],
    steps: int = 600,
    batch: int = 4096,
    seed: int = 0,
) -> tuple[Float[Tensor, "3 K"], Float[Tensor, "3 3"], Dict[str, Any]]:
    """Fit the curves and matrix taking each ``enhanced`` view (sRGB [0, 1]) to its ``references`` photo (same
    size, aligned). Huber loss in sRGB on area-downscaled pixels, Adam on ``steps`` random batches of
    ``batch`` pixels (cosine learning rate); curves kept monotone by construction (cumulative softplus steps).
    Returns ``(curves, matrix, stats)``."""
    gen = torch.Generator().manual_seed(seed)
    x, y = _fit_pixels(enhanced, references)
    knots = torch.linspace(0, 1, KNOTS)
    start = srgb_to_linear(knots[:, None].expand(-1, 3))[:, 0].clamp(min=1e-6)
    # Parameters: the first knot's value and softplus steps between knots (monotone); identity start.
    base = torch.full((3, 1), math.log(math.expm1(max(float(start[0]), 1e-4))))
    steps0 = torch.log(torch.expm1((start[1:] - start[:-1]).clamp(min=1e-5)))
    first = base.clone().requires_grad_(True)
    inc = steps0.expand(3, -1).clone().requires_grad_(True)
    matrix = torch.eye(3).requires_grad_(True)
    opt = torch.optim.Adam([first, inc, matrix], lr=0.02)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    batch = min(len(x), batch)
    for _ in range(steps):
        idx = torch.randint(len(x), (batch,), generator=gen)
        out = apply_maps(x[idx], _monotone(first, inc), matrix)
        loss = torch.nn.functional.huber_loss(out, y[idx], delta=HUBER_DELTA)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
    with torch.no_grad():
        curves = _monotone(first, inc)
        final = float(torch.nn.functional.huber_loss(apply_maps(x, curves, matrix), y, delta=HUBER_DELTA))
    return curves.detach(), matrix.detach(), {"samples": int(len(x)), "steps": steps, "loss": final}


LUT_SMOOTHNESS = 0.3
"""Weight of the look-up table's smoothness term (the mean squared difference of neighbouring cells, against the
Huber loss): cells no pair reaches follow their neighbours, and the table cannot learn a pair's noise."""


def fit_lut(
    profiled: Sequence[Float[Tensor, "H W 3"]],
    references: Sequence[Float[Tensor, "H W 3"]],
    size: int,
    smoothness: float = LUT_SMOOTHNESS,
    steps: int = 1500,
    batch: int = 16384,
    seed: int = 0,
) -> tuple[Float[Tensor, "3 D D D"], Dict[str, Any]]:
    """A residual look-up table of ``size`` cells per axis taking each ``profiled`` view (sRGB [0, 1], the curves and
    matrix applied) to its ``references`` photo: Huber loss (:data:`HUBER_DELTA`) in sRGB on area-downscaled pixels
    plus ``smoothness`` x the mean squared difference of neighbouring cells, Adam on ``steps`` random batches (cosine
    learning rate), from zero (no change). Returns ``(lut, stats)``."""
    gen = torch.Generator().manual_seed(seed)
    x, y = _fit_pixels(profiled, references)
    lut = torch.zeros(3, size, size, size, requires_grad=True)
    opt = torch.optim.Adam([lut], lr=0.01)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    batch = min(len(x), batch)

    def smooth(table: Tensor) -> Tensor:
        return sum((table.diff(dim=k) ** 2).mean() for k in (1, 2, 3))

    for _ in range(steps):
        idx = torch.randint(len(x), (batch,), generator=gen)
        out = (x[idx] + apply_lut(x[idx], lut)).clamp(0, 1)
        loss = torch.nn.functional.huber_loss(out, y[idx], delta=HUBER_DELTA) + smoothness * smooth(lut)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
    with torch.no_grad():
        lut = lut.detach().clamp(-LUT_MAX, LUT_MAX)
        final = float(torch.nn.functional.huber_loss((x + apply_lut(x, lut)).clamp(0, 1), y, delta=HUBER_DELTA))
    return lut, {"lut_size": size, "lut_smoothness": smoothness, "lut_loss": final}
