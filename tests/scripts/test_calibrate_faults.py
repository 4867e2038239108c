"""``naka-gs-calibrate`` keeps to its own files and aligns turned pairs: one row per case, its outcome (the one line
and exit status, or the result and its warning lines), and every file that was there before byte-identical after.

The pairs are small synthetic ones (a textured picture and its dark copy at a 40x shorter shutter, 160x120), built in
the row's own folder; a turned pair is cut from a picture turned about its centre, so that its corners show new
content as a camera's would. The rows run the console script (:func:`tests.bad_inputs.run_console`) and use the case
machinery of tests/bad_inputs.py.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import List

import cv2
import numpy as np
import pytest
import torch

from naka_gs_plugin.data.pairs import describe_warp, find_pairs, fit_warp, load_pairs, valid_box, warp_onto
from naka_gs_plugin.enhance.exposure import linear_to_srgb, srgb_to_linear
from naka_gs_plugin.scripts import calibrate as calibrate_cli
from tests.bad_inputs import Case, Env, Exits, Ok, check_case, run_console

H, W, MARGIN = 120, 160, 24
TURN = 3.0
"""Degrees the turned rows' normal images are turned by (anticlockwise as shown: the pair reports -3)."""
TURN_TOLERANCE = 0.15
"""Degrees: how close the alignment finds :data:`TURN` (it finds it to 0.01-0.07 on these pictures)."""
CORNER_TOLERANCE = 0.6
"""Pixels: the found warp against the true one at the corners of the box it keeps (0.12-0.42 on these pictures)."""
NO_CORRECTION = ["--enhance.correction", "none"]
CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-5)


def picture(seed: int) -> np.ndarray:
    """A normal-light sRGB [0, 1] picture ``(H + 2 MARGIN) x (W + 2 MARGIN)``: smooth colour and patches."""
    rng = np.random.default_rng(seed)
    h, w = H + 2 * MARGIN, W + 2 * MARGIN
    img = cv2.GaussianBlur(rng.random((h, w, 3)).astype(np.float32), (0, 0), 4.0)
    img = (img - img.min()) / (img.max() - img.min())
    for _ in range(14):
        y, x = rng.integers(0, h - 24), rng.integers(0, w - 24)
        dy, dx = rng.integers(6, 24, 2)
        img[y : y + dy, x : x + dx] = rng.random(3)
    return (0.05 + 0.8 * img).astype(np.float32)


def turned(big: np.ndarray, degrees: float) -> np.ndarray:
    """``big`` turned about its centre (positive: anticlockwise as shown)."""
    h, w = big.shape[:2]
    m = cv2.getRotationMatrix2D(((w - 1) / 2, (h - 1) / 2), degrees, 1.0)
    return np.clip(cv2.warpAffine(big, m, (w, h), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT), 0, 1)


def cut(big: np.ndarray) -> np.ndarray:
    return big[MARGIN : MARGIN + H, MARGIN : MARGIN + W]


def dark(high: np.ndarray, ratio: float = 40.0) -> np.ndarray:
    """``high`` at a ``ratio`` times shorter shutter (linear light divided), sRGB [0, 1]."""
    return linear_to_srgb(srgb_to_linear(torch.from_numpy(np.ascontiguousarray(high))) / ratio).numpy()


def save(path: Path, image: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), (np.clip(image, 0, 1)[..., ::-1] * 255).round().astype(np.uint8))


def write_pairs(root: Path, n: int = 4, turn: float = 0.0, foreign: int = -1, tinted: int = -1) -> Path:
    """``root/low`` and ``root/high`` with ``n`` pairs ``000.png``...; the normal images turned by ``turn`` degrees;
    pair ``foreign``'s normal image of another picture; pair ``tinted``'s in another white balance."""
    for i in range(n):
        big = picture(i)
        high = cut(turned(big, turn) if turn else big)
        if i == foreign:
            high = cut(picture(100 + i))
        if i == tinted:
            high = high * np.array([0.45, 1.0, 1.6], np.float32)
        save(root / "low" / f"{i:03d}.png", dark(cut(big)))
        save(root / "high" / f"{i:03d}.png", high)
    return root


def calibrate(env: Env, pairs: Path, out: Path, *extra: str):
    return run_console(env, calibrate_cli.entrypoint, ["naka-gs-calibrate", str(pairs), "--out", str(out), *extra])


def warnings_of(env: Env) -> List[str]:
    """The warning lines the row's calibration prints (each as one string; the console wraps them), from now on."""
    said: List[str] = []
    show = calibrate_cli._warn

    def warn(message: str) -> None:
        said.append(message)
        show(message)

    env.monkeypatch.setattr(calibrate_cli, "_warn", warn)
    return said


WARNED: dict = {}
"""Each row's warning lines, by its folder."""


def nothing_new(folder: Path):
    """An ``after`` check, made once the row's inputs are built: ``folder`` then holds exactly the names it holds now
    (no profile, sheet or staging folder was left)."""
    before = sorted(p.name for p in folder.iterdir())

    def after(env: Env) -> None:
        assert sorted(p.name for p in folder.iterdir()) == before

    return after


# --- rows: the sheet is the user's ------------------------------------------------------------------------------


def sheet_of_the_user(env):
    pairs = write_pairs(env.tmp / "pairs")
    sheet = env.tmp / "mycam_sheet.png"
    cv2.imwrite(str(sheet), np.full((20, 30, 3), 90, np.uint8))  # the user's own picture of that name
    return calibrate(env, pairs, env.tmp / "mycam.json", *NO_CORRECTION), [pairs, sheet]


def _sheet_of_the_user(env):
    sheet = env.tmp / "mycam_sheet.png"
    return Exits(
        1,
        f"naka-gs: {sheet}: exists and naka-gs-calibrate did not write it (the before/after sheet of --out "
        f"{env.tmp / 'mycam.json'} goes there; it is not replaced) -- move it away, choose another --out, or pass "
        "--sheet-pairs 0",
        nothing_new(env.tmp),
    )


def sheet_of_the_user_not_an_image(env):
    pairs = write_pairs(env.tmp / "pairs")
    sheet = env.tmp / "mycam_sheet.png"
    sheet.write_text("my notes, named like a sheet")
    return calibrate(env, pairs, env.tmp / "mycam.json", *NO_CORRECTION), [pairs, sheet]


def sheet_is_a_link_to_our_sheet(env):
    """Even a link to a sheet we wrote is the user's link: replacing it would drop the link."""
    pairs = write_pairs(env.tmp / "pairs")
    run_console(
        env, calibrate_cli.entrypoint, ["x", str(pairs), "--out", str(env.tmp / "a" / "old.json"), *NO_CORRECTION]
    )()
    sheet = env.tmp / "mycam_sheet.png"
    sheet.symlink_to(env.tmp / "a" / "old_sheet.png")
    return calibrate(env, pairs, env.tmp / "mycam.json", *NO_CORRECTION), [pairs, env.tmp / "a", sheet]


def sheet_and_profile_of_an_earlier_run(env):
    """The control: what naka-gs-calibrate wrote itself it replaces."""
    pairs = write_pairs(env.tmp / "pairs")
    out = env.tmp / "mycam.json"
    calibrate(env, pairs, out, *NO_CORRECTION)()
    return calibrate(env, pairs, out, *NO_CORRECTION, "--seed", "1"), [pairs]


def _replaced_both(env, result):
    assert result is None  # returned: exit status 0
    profile = json.loads((env.tmp / "mycam.json").read_text())
    assert profile["format"] == "naka-gs-camera-profile" and len(profile["pairs"]) == 4
    assert calibrate_cli.is_sheet(env.tmp / "mycam_sheet.png")
    assert not [p.name for p in env.tmp.iterdir() if p.name.startswith(".")]  # no staging folder left


# --- rows: --out inside or containing the pairs ----------------------------------------------------------------


def out_inside_low(env):
    pairs = write_pairs(env.tmp / "pairs")
    return calibrate(env, pairs, pairs / "low" / "mycam.json", *NO_CORRECTION), [pairs]


def out_inside_the_pairs_folder(env):
    pairs = write_pairs(env.tmp / "pairs")
    return calibrate(env, pairs, pairs / "mycam.json", *NO_CORRECTION), [pairs]


def out_contains_the_pairs(env):
    pairs = write_pairs(env.tmp / "box.json" / "pairs")
    return calibrate(env, pairs, env.tmp / "box.json", *NO_CORRECTION), [env.tmp / "box.json"]


def _refused_in(where: str, relation: str):
    def expect(env):
        pairs = env.tmp / "box.json" / "pairs" if where == "box" else env.tmp / "pairs"
        out = {"low": pairs / "low" / "mycam.json", "root": pairs / "mycam.json", "box": env.tmp / "box.json"}[where]
        folder = pairs / "low" if where == "low" else pairs  # the innermost it is in, or the outermost it holds
        return Exits(
            1,
            f"naka-gs: --out {out}: {relation} the pairs' folder {folder} -- write the profile outside {pairs} "
            "(an output inside an input is refused)",
            nothing_new(env.tmp),
        )

    return expect


# --- rows: alignment -------------------------------------------------------------------------------------------


def turned_pairs(env):
    pairs = write_pairs(env.tmp / "pairs", turn=TURN)
    WARNED[env.tmp] = warnings_of(env)
    return calibrate(env, pairs, env.tmp / "mycam.json", *NO_CORRECTION), [pairs]


def _turned_aligned(env, result):
    """Every pair found turned by -3 degrees (anticlockwise) within :data:`TURN_TOLERANCE`, its warp within
    :data:`CORNER_TOLERANCE` px of the truth, all four fitted on, and no warning."""
    assert result is None and WARNED.pop(env.tmp) == []
    assert "turned -3.0" in env.log()
    profile = json.loads((env.tmp / "mycam.json").read_text())
    assert [row["name"] for row in profile["pairs"]] == ["000.png", "001.png", "002.png", "003.png"]
    truth = cv2.getRotationMatrix2D(((W - 1) / 2, (H - 1) / 2), TURN, 1.0)
    for i in range(4):
        low = cv2.imread(str(env.tmp / "pairs" / "low" / f"{i:03d}.png"))[..., ::-1].astype(np.float32) / 255
        high = cv2.imread(str(env.tmp / "pairs" / "high" / f"{i:03d}.png"))[..., ::-1].astype(np.float32) / 255
        warp, corr = fit_warp(low, high)
        shift, rotation, scale, skew = describe_warp(warp, low.shape)
        assert rotation == pytest.approx(-TURN, abs=TURN_TOLERANCE) and scale == pytest.approx(1, abs=0.005)
        x0, y0, x1, y1 = valid_box(warp, low.shape)
        corners = np.array([[x0, x1 - 1, x0, x1 - 1], [y0, y0, y1 - 1, y1 - 1], [1, 1, 1, 1]], np.float64)
        assert np.abs((warp - truth) @ corners).max() < CORNER_TOLERANCE
        # The aligned normal image is the unturned one, where it has data (translation alone leaves ~20 dB).
        aligned = warp_onto(high, warp)[y0:y1, x0:x1]
        assert 10 * np.log10(1 / np.mean((aligned - cut(picture(i))[y0:y1, x0:x1]) ** 2)) > 35


def pair_of_another_scene(env):
    pairs = write_pairs(env.tmp / "pairs", foreign=2)
    WARNED[env.tmp] = warnings_of(env)
    return calibrate(env, pairs, env.tmp / "mycam.json", *NO_CORRECTION), [pairs]


def _left_out(env, result):
    """One warning line names the pair and its files; the profile is fitted on the other three."""
    assert result is None
    pairs = env.tmp / "pairs"
    (line,) = WARNED.pop(env.tmp)
    start = f"pair 002.png: {pairs / 'high' / '002.png'} does not align with {pairs / 'low' / '002.png'} ("
    end = ") -- left out of the calibration; shoot it again from a tripod (only the shutter changes) or remove it"
    assert line.startswith(start) and line.endswith(end) and "\n" not in line, line
    assert "warning: pair 002.png:" in env.log()  # on the console
    profile = json.loads((env.tmp / "mycam.json").read_text())
    assert [row["name"] for row in profile["pairs"]] == ["000.png", "001.png", "003.png"]


def too_few_pairs_align(env):
    pairs = write_pairs(env.tmp / "pairs", n=3, foreign=1)
    return calibrate(env, pairs, env.tmp / "mycam.json", *NO_CORRECTION), [pairs]


def pair_in_another_white_balance(env):
    pairs = write_pairs(env.tmp / "pairs", n=5, tinted=3)
    WARNED[env.tmp] = warnings_of(env)
    return calibrate(env, pairs, env.tmp / "mycam.json", *NO_CORRECTION), [pairs]


def _named_far_below(env, result):
    """It aligns (the pattern is the same) but teaches another colour: one warning line after the fit names it."""
    assert result is None
    (line,) = WARNED.pop(env.tmp)
    assert line.startswith("with the profile, pair(s) 003.png (") and "stay far below the others (median" in line, line
    assert "\n" not in line and " -- " in line
    assert (env.tmp / "mycam.json").is_file()


CASES: List[Case] = [
    (sheet_of_the_user, _sheet_of_the_user),
    (
        sheet_of_the_user_not_an_image,
        lambda env: Exits(1, f"naka-gs: {env.tmp / 'mycam_sheet.png'}: exists and naka-gs-calibrate did not write it"),
    ),
    (sheet_is_a_link_to_our_sheet, lambda env: Exits(1, f"naka-gs: {env.tmp / 'mycam_sheet.png'}: exists and")),
    (sheet_and_profile_of_an_earlier_run, Ok(_replaced_both)),
    (out_inside_low, _refused_in("low", "is inside")),
    (out_inside_the_pairs_folder, _refused_in("root", "is inside")),
    (out_contains_the_pairs, _refused_in("box", "contains")),
    (turned_pairs, Ok(_turned_aligned)),
    (pair_of_another_scene, Ok(_left_out)),
    (
        too_few_pairs_align,
        lambda env: Exits(
            1,
            "naka-gs: 2 of 3 calibration pairs align (001.png did not), at least 3 needed -- shoot those again from "
            "a tripod, or add more pairs",
            nothing_new(env.tmp),
        ),
    ),
    (pair_in_another_white_balance, Ok(_named_far_below)),
]


@pytest.mark.parametrize("make, expect", CASES, ids=[make.__name__ for make, _ in CASES])
def test_calibrate_fault(make, expect, toy_scene, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    check_case(Env(tmp_path, toy_scene, monkeypatch, capsys), make, expect)


def test_translation_alone_does_not_align_a_turned_pair(tmp_path):
    """The premise of the turned row: the shift the old alignment found leaves the turned pair far off (it refused
    them, or with its limit lifted fitted on them: 16.4 -> 17.6 dB on BlueHawaii turned by 3 degrees)."""
    pairs = load_pairs(find_pairs(write_pairs(tmp_path / "pairs", turn=TURN)), warn=pytest.fail)
    for pair in pairs:
        assert pair.rotation == pytest.approx(-TURN, abs=TURN_TOLERANCE)
    low, high = dark(cut(picture(0))), cut(turned(picture(0), TURN))
    a, b = (cv2.cvtColor(x, cv2.COLOR_RGB2GRAY) for x in (low / (low + low.mean()), high))
    _, shift_only = cv2.findTransformECC(
        a, b, np.eye(2, 3, dtype=np.float32), cv2.MOTION_TRANSLATION, CRITERIA, None, 5
    )
    moved = warp_onto(high, shift_only.astype(np.float64))
    assert 10 * np.log10(1 / np.mean((moved - cut(picture(0))) ** 2)) < 25
