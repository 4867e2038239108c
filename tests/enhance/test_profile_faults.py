"""A camera profile is checked as a photo is (issue 81 item 2): one row per bad profile, its one line, and every
file that existed before byte-identical after.

Each bad profile is a row three times: loading it (``CameraProfile.load``: the exact line), ``naka-gs-enhance`` and
``ns-train`` on a copy of the toy scene with it (exit status 1, the one ``naka-gs:`` line, no output folder or run,
the scene and the profile untouched). The case types and the runner are tests/bad_inputs.py's. Then the views a
loadable profile renders black, white or flat, and the profiles that must keep loading: ``naka-gs-calibrate``'s
(synthetic pairs, and those it wrote from RealX3D, LOL and LOM pairs, kept in tests/enhance/profiles/) and a
version-1 profile of curves and matrix alone.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable, Dict, List, Tuple

import cv2
import pytest
import torch

from naka_gs_plugin.datamanager import FLAT_RANGE
from naka_gs_plugin.enhance.exposure import srgb_to_linear
from naka_gs_plugin.enhance.pipeline import EnhanceConfig, Enhancer
from naka_gs_plugin.enhance.profile import (
    KNOTS,
    MAX_BYTES,
    VIEW_FLAT_RANGE,
    CameraProfile,
    CameraProfileError,
    UnusableProfileError,
    is_profile_file,
    nesting_depth,
)
from naka_gs_plugin.enhance.stages import ProfileStage
from naka_gs_plugin.scripts import enhance as enhance_cli
from naka_gs_plugin.scripts.calibrate import Calibrate
from tests.bad_inputs import Action, Case, Env, Exits, Ok, Raises, check_case, run_console
from tests.enhance.test_profile import _write_pairs

PROFILES = Path(__file__).parent / "profiles"
"""Profiles as ``naka-gs-calibrate`` wrote them from RealX3D, LOL and LOM pairs (its README.md: the commands)."""
BLUEHAWAII = PROFILES / "bluehawaii.json"
"""What ``naka-gs-calibrate ../shared/data/realx3d/BlueHawaii`` wrote (default chain, 30 pairs)."""

IDENTITY = srgb_to_linear(torch.linspace(0, 1, KNOTS)[:, None].expand(-1, 3).contiguous())[:, 0].tolist()
"""A curve that leaves a view as it is (the sRGB decoding at the knots)."""
EYE = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]
REFIT = "calibrate again (naka-gs-calibrate PAIRS --out NEW.json), or leave {option} out"
REPLACE = "pass {option} the .json file naka-gs-calibrate wrote, or leave {option} out"


def profile_text(curves=None, matrix=None, **extra) -> str:
    """A version-1 profile's JSON, the identity unless told otherwise."""
    data = {"format": "naka-gs-camera-profile", "version": 1, "curves": curves or [IDENTITY] * 3}
    return json.dumps({**data, "matrix": EYE if matrix is None else matrix, "chain": {}, "pairs": [], **extra})


def _lut(value: float = 0.0, nan_at=None) -> list:
    """A 2-cell look-up table of ``value`` everywhere (NaN at ``nan_at``, an index ``[c][b][g][r]``)."""
    lut = [[[[value] * 2 for _ in range(2)] for _ in range(2)] for _ in range(3)]
    if nan_at is not None:
        c, b, g, r = nan_at
        lut[c][b][g][r] = float("nan")
    return lut


BAD: Dict[str, Tuple[Callable[[], str], str, str]] = {
    # name: (the file's text, what the line says is wrong, which fix)
    "curves_all_zero": (
        lambda: profile_text(curves=[[0] * KNOTS] * 3),
        "unusable camera profile: curves[0] (r) is flat (0 to 0): a curve rises by at least 0.01 (linear light)",
        REFIT,
    ),
    "matrix_1e30": (
        lambda: profile_text(matrix=[[1e30, 0, 0], [0, 1e30, 0], [0, 0, 1e30]]),
        "unusable camera profile: the colour matrix has an entry of magnitude 1e+30, beyond 8",
        REFIT,
    ),
    "matrix_minus_identity": (
        lambda: profile_text(matrix=[[-1, 0, 0], [0, -1, 0], [0, 0, -1]]),
        "unusable camera profile: the colour matrix has determinant -1: it inverts colours (a profile's matrix has "
        "determinant > 0)",
        REFIT,
    ),
    "curves_decreasing": (
        lambda: profile_text(curves=[IDENTITY[::-1]] * 3),
        "unusable camera profile: curves[0] (r) falls from 1 to 0.863669 at knot 1: a profile's curves rise (a "
        "falling one inverts the tones)",
        REFIT,
    ),
    "curves_of_true": (
        lambda: profile_text(curves=[[True] * KNOTS] * 3),
        "unusable camera profile: curves[0][0] is true, not a number",
        REFIT,
    ),
    "nested_200000_deep": (
        lambda: profile_text()[:-1] + ', "x": ' + "[" * 200_000 + "]" * 200_000 + "}",
        "not a camera profile (brackets nested 200001 deep, more than 16)",
        REPLACE,
    ),
    "oversize_file": (
        lambda: profile_text(notes="x" * MAX_BYTES),
        "not a camera profile (larger than 4 MiB; a profile is at most about 1.5 MB)",
        REPLACE,
    ),
    "a_nan": (
        lambda: profile_text().replace('"matrix": [[1,', '"matrix": [[NaN,'),
        "unusable camera profile: matrix[0][0] is NaN, not a finite number",
        REFIT,
    ),
    "wrong_shape": (
        lambda: profile_text(curves=[IDENTITY[:16]] * 3),
        "unusable camera profile: curves[0] has 16 numbers, not 17",
        REFIT,
    ),
}
"""The issue's cases; each rendered black, white, tone-inverted or flat views (or a RecursionError) without a word."""

MORE: Dict[str, Tuple[Callable[[], str], str, str]] = {
    "version_true": (
        lambda: profile_text().replace('"version": 1', '"version": true'),
        "profile version true, this naka-gs reads 1 and 2",
        "calibrate again with this version (naka-gs-calibrate PAIRS --out PROFILE)",
    ),
    "a_huge_integer": (
        lambda: profile_text(matrix=[[10**400, 0, 0], [0, 1, 0], [0, 0, 1]]),
        "unusable camera profile: matrix[0][0] is too large, not a finite number",
        REFIT,
    ),
    "an_infinity": (
        lambda: profile_text(curves=[IDENTITY[:-1] + [float("inf")]] * 3),
        "unusable camera profile: curves[0][16] is Infinity, not a finite number",
        REFIT,
    ),
    "curves_too_bright": (
        lambda: profile_text(curves=[[v * 100 for v in IDENTITY]] * 3),
        "unusable camera profile: curves[0] (r) reaches 100, outside 0-16 (linear light, 1 = white)",
        REFIT,
    ),
    "matrix_nearly_singular": (
        lambda: profile_text(matrix=[[1, 0, 0], [0, 1, 0], [0, 0, 0.001]]),
        "unusable camera profile: the colour matrix has condition number 1e+03, beyond 100: it is nearly singular",
        REFIT,
    ),
    "matrix_inverting_two_channels": (
        lambda: profile_text(matrix=[[-1, 0, 0], [0, -1, 0], [0, 0, 1]]),
        "unusable camera profile: a grey ramp from black to white comes out r 0.000 to 0.000 (rises by less than "
        "0.05, sRGB): the profile's maps together flatten or invert that channel",
        REFIT,
    ),
    "highlights_inverted": (
        lambda: profile_text(
            curves=[IDENTITY, IDENTITY, [0.0] * (KNOTS - 1) + [1.0]], matrix=[[1, 0, -0.8], [0, 1, 0], [0, 0, 1]]
        ),
        "unusable camera profile: a grey ramp from black to white comes out r 0.000 to 0.485 (falls by 0.453 on the "
        "way, more than 0.25, sRGB): the profile's maps together flatten or invert that channel",
        REFIT,
    ),
    "lut_nan": (
        lambda: profile_text(version=2, lut=_lut(nan_at=(0, 1, 1, 0))),
        "unusable camera profile: lut[0][1][1][0] is NaN, not a finite number",
        REFIT,
    ),
    "lut_too_strong": (
        lambda: profile_text(version=2, lut=_lut(value=0.9)),
        "unusable camera profile: the look-up table has a residual of magnitude 0.9, beyond 0.5 (sRGB)",
        REFIT,
    ),
    "lut_two_channels": (
        lambda: profile_text(version=2, lut=_lut()[:2]),
        "unusable camera profile: lut must be 3 tables of D x D x D numbers (2 <= D <= 33)",
        REFIT,
    ),
    "lut_uneven": (
        lambda: profile_text(version=2, lut=[_lut()[0], _lut()[1], _lut()[2][:1]]),
        "unusable camera profile: lut[2] has 1 planes, not 2",
        REFIT,
    ),
    "matrix_missing": (
        lambda: json.dumps({"format": "naka-gs-camera-profile", "version": 1, "curves": [IDENTITY] * 3}),
        "damaged camera profile (no matrix)",
        REPLACE,
    ),
    "chain_not_a_mapping": (
        lambda: profile_text(chain=[1, 2]),
        "damaged camera profile (chain is a list, not a mapping)",
        REPLACE,
    ),
}
"""Further checks of the same kind, at the loader only."""


STEP = [0.0] * 8 + [(k - 7) / 9 for k in range(8, KNOTS)]
"""Black up to mid-grey, then rising to white: it loads (a grey ramp comes out rising), and a dark view's
pixels all fall where it is 0."""
SHOULDER = [0.0, 1.0] + [1.0] * (KNOTS - 2)
"""White from the second knot (1/16) on."""
PLATEAU = [0.0] + [0.2] * (KNOTS - 2) + [1.0]
"""One grey between its first and last knots."""
WIDE_PLATEAU = [0.2 * k / 3 for k in range(3)] + [0.2] * (KNOTS - 4) + [1.0]
"""One grey from 3/16 to 15/16: where the chain puts the views of :data:`BRIGHT_CAPTURE` (0.25-0.89)."""


def _gradient(lo: float, hi: float) -> torch.Tensor:
    """A 48x64 view from ``lo`` to ``hi`` (sRGB), left to right, with some colour."""
    ramp = torch.linspace(lo, hi, 64)[None, :, None].expand(48, 64, 3)
    return (ramp * torch.tensor([1.0, 0.95, 0.9])).contiguous()


BRIGHT_CAPTURE = (_gradient(0.5, 0.6) * 255).round().to(torch.uint8)
"""A capture far brighter than a dark one, with little contrast: the chain stretches it to 0.25-0.89."""


def write_profile(env: Env, text: str) -> Path:
    path = env.tmp / "camera.json"
    path.write_text(text)
    return path


def _line(env: Env, option: str, what: str, fix: str) -> str:
    """The whole line; with no ``fix``, its start up to ``what`` (a line with measured values in it)."""
    return f"{option} {env.tmp / 'camera.json'}: {what}" + (f" -- {fix.format(option=option)}" if fix else "")


def _nothing_written(env: Env) -> None:
    """No --out folder, no run folder, nothing left beside them (the cache is the only other entry)."""
    assert sorted(p.name for p in env.tmp.iterdir() if p.name != "naka-cache") == ["S", "camera.json"]


def load_row(name: str, text: Callable[[], str], what: str, fix: str) -> Case:
    def make(env: Env) -> Tuple[Action, List[Path]]:
        path = write_profile(env, text())
        return lambda: CameraProfile.load(path, "--enhance.profile"), [path]

    make.__name__ = f"load_{name}"
    error = UnusableProfileError if fix == REFIT else CameraProfileError
    return make, lambda env: Raises(error, _line(env, "--enhance.profile", what, fix))


def enhance_row(name: str, text: Callable[[], str], what: str, fix: str, scene_of=Env.scene) -> Case:
    def make(env: Env) -> Tuple[Action, List[Path]]:
        scene, path = scene_of(env), write_profile(env, text())
        argv = ["naka-gs-enhance", str(scene), "--out", str(env.tmp / "enh"), "--enhance.correction", "none"]
        return run_console(env, enhance_cli.entrypoint, argv + ["--enhance.profile", str(path)]), [scene, path]

    make.__name__ = f"naka_gs_enhance_{name}"
    option = "--pipeline.datamanager.enhance.profile"  # the stage's option, also under naka-gs-enhance
    return make, lambda env: Exits(1, "naka-gs: " + _line(env, option, what, fix), _nothing_written)


def train_row(name: str, text: Callable[[], str], what: str, fix: str, scene_of=Env.scene) -> Case:
    def make(env: Env) -> Tuple[Action, List[Path]]:
        from nerfstudio.scripts import train as ns_train  # here: it collects every nerfstudio method (seconds)

        scene, path = scene_of(env), write_profile(env, text())
        argv = ["ns-train", "naka-gs", "--data", str(scene), "--output-dir", str(env.tmp / "out")]
        argv += ["--pipeline.datamanager.enhance.correction", "none", "--max-num-iterations", "3"]
        argv += ["--pipeline.datamanager.enhance.profile", str(path), "--vis", "tensorboard"]
        return run_console(env, ns_train.entrypoint, argv), [scene, path]

    make.__name__ = f"ns_train_{name}"
    option = "--pipeline.datamanager.enhance.profile"
    return make, lambda env: Exits(1, "naka-gs: " + _line(env, option, what, fix), _nothing_written)


# --- profiles that load -----------------------------------------------------------------------------------


def calibrate_writes_a_profile_that_loads(env: Env) -> Tuple[Action, List[Path]]:
    pairs = _write_pairs(env.tmp / "pairs", n=4)
    out = env.tmp / "camera.json"

    def action():
        Calibrate(pairs=pairs, out=out, enhance=EnhanceConfig(correction="none"), sheet_pairs=0).main()
        return CameraProfile.load(out, "--enhance.profile")

    return action, [pairs]


def _loads(env: Env, profile: object) -> None:
    assert isinstance(profile, CameraProfile) and len(profile.pairs) == 4


def bluehawaii_profile_loads_and_enhances(env: Env) -> Tuple[Action, List[Path]]:
    """The profile naka-gs-calibrate wrote from 30 real pairs, on the toy scene: views with contrast come out."""
    scene = env.scene()
    argv = ["naka-gs-enhance", str(scene), "--out", str(env.tmp / "enh"), "--enhance.correction", "none"]
    argv += ["--enhance.profile", str(BLUEHAWAII), "--no-sheet"]
    return run_console(env, enhance_cli.entrypoint, argv), [scene, BLUEHAWAII]


def _eight_views(env: Env, _: object) -> None:
    assert len(list((env.tmp / "enh").glob("*.png"))) == 8


def version_1_of_curves_and_matrix_alone_loads(env: Env) -> Tuple[Action, List[Path]]:
    """The oldest form the loader reads: no chain, pairs or fit; integers in the matrix."""
    text = json.dumps({"format": "naka-gs-camera-profile", "version": 1, "curves": [IDENTITY] * 3, "matrix": EYE})
    path = write_profile(env, text)
    return lambda: CameraProfile.load(path), [path]


def _identity_loaded(env: Env, profile: object) -> None:
    assert profile.matrix == [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]] and profile.chain == {}


def bright_scene(env: Env) -> Path:
    """The toy scene with every training capture :data:`BRIGHT_CAPTURE`."""
    scene = env.scene()
    for frame in json.loads((scene / "transforms_train.json").read_text())["frames"]:
        cv2.imwrite(str(scene / frame["file_path"]), BRIGHT_CAPTURE.numpy()[..., ::-1])
    return scene


VIEW_FLAT = (lambda: profile_text(curves=[WIDE_PLATEAU] * 3), "the camera profile renders a view flat (its values", "")
"""A profile that loads and flattens the views of :func:`bright_scene`."""

CASES: List[Case] = [
    *(load_row(name, *row) for name, row in {**BAD, **MORE}.items()),
    *(enhance_row(name, *row) for name, row in BAD.items()),
    *(train_row(name, *row) for name, row in BAD.items()),
    enhance_row("view_flat", *VIEW_FLAT, scene_of=bright_scene),
    train_row("view_flat", *VIEW_FLAT, scene_of=bright_scene),
    (calibrate_writes_a_profile_that_loads, Ok(_loads)),
    (bluehawaii_profile_loads_and_enhances, Ok(_eight_views)),
    (version_1_of_curves_and_matrix_alone_loads, Ok(_identity_loaded)),
]


@pytest.mark.parametrize("make, expect", CASES, ids=[make.__name__ for make, _ in CASES])
def test_profile_fault(make, expect, toy_scene, tmp_path, monkeypatch, capsys):
    check_case(Env(tmp_path, toy_scene, monkeypatch, capsys), make, expect)


# --- the views a loadable profile renders -------------------------------------------------------------------


@pytest.mark.parametrize(
    "curve, view, kind",
    [(STEP, (0.05, 0.4), "all black"), (SHOULDER, (0.3, 0.9), "all white"), (PLATEAU, (0.2, 0.8), "flat")],
    ids=["black", "white", "flat"],
)
def test_a_view_the_profile_renders_black_white_or_flat_is_one_line(tmp_path, curve, view, kind):
    path = tmp_path / "camera.json"
    path.write_text(profile_text(curves=[curve] * 3))
    before = path.read_bytes()
    stage = ProfileStage.build(EnhanceConfig(correction="none", profile=path), None)  # it loads
    image = _gradient(*view)
    with pytest.raises(UnusableProfileError) as err:
        stage.apply(image, image)
    option = "--pipeline.datamanager.enhance.profile"
    line = str(err.value)
    assert line.startswith(f"{option} {path}: the camera profile renders a view {kind} (its values span ")
    assert line.endswith(
        " -- calibrate again with the --enhance options of this run (naka-gs-calibrate PAIRS --out NEW.json), or "
        f"leave {option} out"
    )
    assert "\n" not in line and path.read_bytes() == before
    # A view that came in flat is the photos' check's to report.
    flat = torch.full((48, 64, 3), 0.3)
    assert stage.apply(flat, flat).shape == flat.shape


def test_the_enhancer_stops_at_the_first_view_the_profile_flattens_and_caches_none(tmp_path):
    """Through the whole chain (Naka, chroma, tone): a bright capture's view lies on the profile's plateau."""
    path = tmp_path / "camera.json"
    path.write_text(profile_text(curves=[WIDE_PLATEAU] * 3))
    enhancer = Enhancer(EnhanceConfig(correction="none", profile=path))
    with pytest.raises(CameraProfileError, match=r"renders a view flat \(its values span 0.4845-0.4845; 0.2"):
        enhancer.enhance_images([BRIGHT_CAPTURE, BRIGHT_CAPTURE])
    assert not enhancer.cache_dir.exists() or not list(enhancer.cache_dir.rglob("*.npy"))


@pytest.mark.parametrize("path", sorted(PROFILES.glob("*.json")), ids=lambda p: p.stem)
def test_every_profile_calibrate_wrote_from_real_pairs_still_loads(path):
    profile = CameraProfile.load(path)
    assert profile.pairs and profile.chain["stages"][0]["stage"] == "naka"


def test_the_views_are_held_to_the_photos_bound():
    assert VIEW_FLAT_RANGE == FLAT_RANGE


def test_the_nesting_is_counted_outside_strings():
    assert nesting_depth(b'{"a": "[[[[{{{{", "b": [[1], {"c": "\\"]]]"}]}') == 3
    assert nesting_depth(b"[" * 100 + b"]" * 100) == 100
    assert nesting_depth(b"") == 0


def test_an_unusable_profile_is_still_a_profile_that_calibrating_again_may_replace(tmp_path):
    """``naka-gs-calibrate --out`` replaces only a camera profile: an unusable one still is one by its format."""
    for name, (text, _, fix) in {**BAD, **MORE}.items():
        path = tmp_path / f"{name}.json"
        path.write_text(text())
        assert is_profile_file(path) == (
            fix == REFIT or name in ("version_true", "matrix_missing", "chain_not_a_mapping")
        ), name
    (tmp_path / "notes.json").write_text('{"format": "something else"}')
    assert not is_profile_file(tmp_path / "notes.json") and not is_profile_file(tmp_path / "missing.json")
