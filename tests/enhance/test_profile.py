"""Camera profiles: the fit, the stage in the chain, the pairs' checks and ``naka-gs-calibrate``."""

import json
import shutil

import cv2
import numpy as np
import pytest
import torch
from torch.testing import assert_close

from naka_gs_plugin.data.pairs import PairsError, align, find_pairs, load_pairs
from naka_gs_plugin.data.safe_io import UnsafeOutputError
from naka_gs_plugin.enhance.exposure import linear_to_srgb, srgb_to_linear
from naka_gs_plugin.enhance.pipeline import EnhanceConfig, EnhanceOptionError, Enhancer
from naka_gs_plugin.enhance.profile import (
    KNOTS,
    CameraProfile,
    CameraProfileError,
    apply_maps,
    apply_profile,
    fit_lut,
    fit_profile,
)
from naka_gs_plugin.enhance.stages import CaptureToneStage, ExposureStage, ProfileStage
from naka_gs_plugin.scripts.calibrate import Calibrate

KNOT_X = torch.linspace(0, 1, KNOTS)[:, None].expand(-1, 3)


def _identity() -> CameraProfile:
    return CameraProfile(curves=srgb_to_linear(KNOT_X).t().tolist(), matrix=torch.eye(3).tolist())


def _scene(seed: int, h: int = 96, w: int = 128) -> np.ndarray:
    """A normal-light sRGB [0, 1] picture with structure at several scales (for the alignment) and colour."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.random((h, w, 3)).astype(np.float32), (0, 0), 3.0)
    img = (img - img.min()) / (img.max() - img.min())
    for _ in range(6):
        y, x = rng.integers(0, h - 20), rng.integers(0, w - 20)
        img[y : y + 16, x : x + 16] = rng.random(3)
    return 0.05 + 0.8 * img


def _dark(high: np.ndarray, ratio: float = 40.0) -> np.ndarray:
    """``high`` taken with a ``ratio`` times shorter shutter: linear light divided, 8-bit sRGB codes."""
    lin = torch.from_numpy(high)
    low = torch.from_numpy(np.asarray(srgb_to_linear(lin))) / ratio
    return (np.asarray(linear_to_srgb(low)) * 255).round().astype(np.uint8)


def _write_pairs(root, n=4, shift=None, seed=0):
    (root / "low").mkdir(parents=True)
    (root / "high").mkdir()
    for i in range(n):
        high = _scene(seed + i)
        low = _dark(high)
        if shift is not None and i == 1:
            high = np.roll(high, shift, axis=(1, 0))
        cv2.imwrite(str(root / "low" / f"{i:03d}.png"), low[..., ::-1])
        cv2.imwrite(str(root / "high" / f"{i:03d}.png"), (high[..., ::-1] * 255).round().astype(np.uint8))
    return root


def test_the_fit_recovers_a_known_camera_on_views_it_never_saw():
    g = torch.Generator().manual_seed(0)
    true_curves = (srgb_to_linear(KNOT_X) * torch.tensor([1.2, 0.9, 0.7])).t() ** 1.1
    true_matrix = torch.tensor([[1.1, -0.05, -0.05], [-0.1, 1.0, 0.1], [0.0, -0.1, 1.1]])
    images = [
        torch.from_numpy(_scene(i)).float() * torch.rand(1, 1, 3, generator=g).add(0.5).clamp(max=1) for i in range(6)
    ]
    refs = [apply_maps(x, true_curves, true_matrix) for x in images]
    curves, matrix, stats = fit_profile(images[:4], refs[:4], steps=400)
    for x, ref in zip(images[4:], refs[4:]):
        assert_close(apply_maps(x, curves, matrix), ref, atol=0.03, rtol=0)
    assert stats["samples"] > 0


def test_the_identity_profile_leaves_an_image_alone():
    image = torch.from_numpy(_scene(1)).float()
    # Exact at the knots; between them the curve is the sRGB decoding's chord (at most 5e-3 in sRGB).
    assert_close(apply_profile(image, _identity()), image, atol=5e-3, rtol=0)
    knots = KNOT_X[None].contiguous()
    assert_close(apply_profile(knots, _identity()), knots, atol=1e-5, rtol=0)


def test_a_profile_file_round_trips_and_bad_files_say_so_in_one_line(tmp_path):
    path = tmp_path / "camera.json"
    path.write_text(_identity().to_json())
    assert CameraProfile.load(path).curves == _identity().curves
    (tmp_path / "notes.json").write_text('{"format": "something else"}')
    (tmp_path / "broken.json").write_text('{"format": "naka-gs-camera-profile", "version": 1, "curves": [[1]]}')
    for bad, words in [
        (tmp_path / "missing.json", "no such file"),
        (tmp_path / "notes.json", "not a camera profile"),
        (tmp_path / "broken.json", "damaged"),
    ]:
        with pytest.raises(CameraProfileError, match=words) as err:
            CameraProfile.load(bad, "--enhance.profile")
        assert "\n" not in str(err.value) and str(bad) in str(err.value) and "--enhance.profile" in str(err.value)


def test_the_profile_is_a_stage_after_capture_tone_keyed_by_content_and_turns_the_lift_off(tmp_path):
    path = tmp_path / "camera.json"
    path.write_text(_identity().to_json())
    enhancer = Enhancer(EnhanceConfig(correction="none", profile=path))
    assert [type(s) for s in enhancer.view_stages][-2:] == [CaptureToneStage, ProfileStage]
    assert enhancer.scene_stages == []  # exposure auto: the profile carries the camera's normal exposure
    lifted = Enhancer(EnhanceConfig(correction="none", profile=path, exposure=0.5))
    assert [type(s) for s in lifted.scene_stages] == [ExposureStage]
    plain = Enhancer(EnhanceConfig(correction="none"))
    assert [type(s) for s in plain.scene_stages] == [ExposureStage]
    assert "profile" not in plain.key()  # no profile: the cache keys of every earlier run stay valid
    moved = tmp_path / "elsewhere.json"
    shutil.copy(path, moved)
    assert Enhancer(EnhanceConfig(correction="none", profile=moved)).key() == enhancer.key()
    other = _identity()
    other.matrix[0][0] = 1.1
    path.write_text(other.to_json())
    assert Enhancer(EnhanceConfig(correction="none", profile=path)).key() != enhancer.key()


def test_a_profile_with_method_none_is_refused(tmp_path):
    path = tmp_path / "camera.json"
    path.write_text(_identity().to_json())
    with pytest.raises(EnhanceOptionError, match="enhance.profile"):
        Enhancer(EnhanceConfig(method="none", profile=path))


def test_a_saved_config_from_before_profiles_loads_without_one():
    config = EnhanceConfig()
    state = dict(config.__dict__)
    del state["profile"]
    restored = EnhanceConfig.__new__(EnhanceConfig)
    restored.__setstate__(state)
    assert restored.profile is None and restored.exposure_target() == pytest.approx(0.505)


def test_a_tripod_shift_is_found_and_undone(tmp_path):
    high = _scene(3, 192, 256)
    low = _dark(high).astype(np.float32) / 255
    moved = np.roll(high, (2, -1), axis=(1, 0))
    (dx, dy), corr = align(low, moved)
    assert corr > 0.9
    assert dx == pytest.approx(2.0, abs=0.3) and dy == pytest.approx(-1.0, abs=0.3)


def test_pairs_are_read_aligned_and_their_exposure_ratio_measured(tmp_path):
    pairs = load_pairs(find_pairs(_write_pairs(tmp_path / "pairs", shift=(2, 0))))
    assert [p.name for p in pairs] == ["000.png", "001.png", "002.png", "003.png"]
    assert pairs[1].shift[0] == pytest.approx(2.0, abs=0.3)
    for p in pairs:
        assert p.exposure_ratio == pytest.approx(40.0, rel=0.15)


@pytest.mark.parametrize(
    "damage, words",
    [
        ("few", "at least 3 needed"),
        ("size", "pair 001.png: .* is 64x48 but"),
        ("darker", "pair 001.png: the normal image .* is no brighter"),
        ("shift", r"pair 001.png: .* shifted by \(\+20"),
        ("saturated", "pair 001.png: .* saturated"),
    ],
)
def test_each_bad_pair_gets_one_line_naming_it_and_the_fix(tmp_path, damage, words):
    root = _write_pairs(tmp_path / "pairs", n=2 if damage == "few" else 4, shift=(20, 0) if damage == "shift" else None)
    bad = root / "high" / "001.png"
    if damage == "size":
        cv2.imwrite(str(root / "low" / "001.png"), np.zeros((48, 64, 3), np.uint8))
    elif damage == "darker":
        cv2.imwrite(str(bad), np.zeros((96, 128, 3), np.uint8))
    elif damage == "saturated":
        cv2.imwrite(str(bad), np.full((96, 128, 3), 255, np.uint8))
    with pytest.raises(PairsError, match=words) as err:
        load_pairs(find_pairs(root))
    assert "\n" not in str(err.value) and " -- " in str(err.value)


def test_a_folder_without_pairs_is_refused(tmp_path):
    with pytest.raises(PairsError, match="low/ and high/"):
        find_pairs(tmp_path)


def test_calibrate_writes_a_profile_that_a_run_uses(tmp_path):
    root = _write_pairs(tmp_path / "pairs", n=4)
    out = tmp_path / "camera.json"
    cli = Calibrate(pairs=root, out=out, enhance=EnhanceConfig(correction="none"))
    profile = cli.main()
    saved = json.loads(out.read_text())
    assert saved["format"] == "naka-gs-camera-profile" and len(saved["pairs"]) == 4
    assert cli.sheet_path().is_file()
    # On the pairs it was fitted on, the profile is closer to the normal images than the enhancement alone.
    assert all(row["psnr_after"] > row["psnr_before"] for row in profile.pairs)
    # A run with the same chain reads it without a warning about another chain.
    enhancer = Enhancer(EnhanceConfig(correction="none", profile=out))
    assert enhancer.view_stages[-1].profile().chain == profile.chain


def test_calibrate_never_replaces_a_file_that_is_not_a_profile(tmp_path):
    root = _write_pairs(tmp_path / "pairs", n=3)
    notes = tmp_path / "notes.json"
    notes.write_text("{}")
    with pytest.raises(UnsafeOutputError, match="not a camera profile"):
        Calibrate(pairs=root, out=notes, enhance=EnhanceConfig(correction="none")).main()
    assert notes.read_text() == "{}"


def test_the_profile_path_is_recorded_absolute(tmp_path, monkeypatch):
    """A run's config.yml names the profile so that ns-eval or ns-viewer started in another folder finds it."""
    monkeypatch.chdir(tmp_path)
    assert EnhanceConfig(profile="camera.json").profile == tmp_path / "camera.json"


def _hue_camera(x: torch.Tensor) -> torch.Tensor:
    """A camera that bends colours by hue, as no curve per channel and matrix can: reds gain saturation (towards
    pure red), greens lose it (towards their grey), greys and blues stay."""
    grey = x.mean(-1, keepdim=True)
    red = (x[..., :1] - x[..., 1:].max(-1, keepdim=True).values).clamp(min=0)
    green = (x[..., 1:2] - torch.maximum(x[..., :1], x[..., 2:])).clamp(min=0)
    return (x + 0.8 * red * (x - grey) - 2.0 * green * (x - grey)).clamp(0, 1)


def test_the_look_up_table_learns_what_depends_on_hue_and_the_curves_cannot():
    g = torch.Generator().manual_seed(0)
    images = [torch.rand(24, 32, 3, generator=g) for _ in range(6)]
    images = [torch.nn.functional.interpolate(x.permute(2, 0, 1)[None], (48, 64))[0].permute(1, 2, 0) for x in images]
    refs = [_hue_camera(x) for x in images]
    curves, matrix, _ = fit_profile(images[:4], refs[:4], steps=300)
    profiled = [apply_maps(x, curves, matrix) for x in images]
    lut, stats = fit_lut(profiled[:4], refs[:4], size=9, steps=600)
    assert stats["lut_size"] == 9 and lut.shape == (3, 9, 9, 9)
    for x, p, ref in zip(images[4:], profiled[4:], refs[4:]):
        without = (p - ref).abs().mean()
        with_lut = (apply_maps(x, curves, matrix, lut) - ref).abs().mean()
        assert with_lut < 0.6 * without  # on views the fit never saw


def test_a_profile_with_a_look_up_table_round_trips_and_a_run_applies_it(tmp_path):
    lut = torch.zeros(3, 5, 5, 5)
    lut[0] = 0.1  # red up by 0.1 everywhere
    profile = _identity()
    profile.lut = lut.tolist()
    path = tmp_path / "camera.json"
    path.write_text(profile.to_json())
    loaded = CameraProfile.load(path)
    assert json.loads(path.read_text())["version"] == 2 and loaded.lut == profile.lut
    stage = ProfileStage(profile_sha1="x", path=path)
    image = torch.full((4, 4, 3), 0.5)
    out = stage.apply(image, image)
    assert_close(out[..., 0], torch.full((4, 4), 0.6), atol=6e-3, rtol=0)  # the identity curve's chord, then +0.1
    assert_close(out[..., 1:], apply_profile(image, _identity())[..., 1:])


def test_a_version_1_profile_has_no_look_up_table_and_renders_as_before(tmp_path):
    path = tmp_path / "camera.json"
    data = json.loads(_identity().to_json())
    data.pop("lut")
    path.write_text(json.dumps({**data, "version": 1}))
    loaded = CameraProfile.load(path)
    image = torch.from_numpy(_scene(2)).float()
    assert loaded.lut is None
    assert torch.equal(apply_profile(image, loaded), apply_maps(image, *loaded.tensors()[:2]))


def test_calibrate_fits_a_look_up_table_only_when_asked_and_refuses_a_bad_size(tmp_path):
    pairs = _write_pairs(tmp_path / "pairs", n=3)
    plain = Calibrate(pairs=pairs, out=tmp_path / "a.json", enhance=EnhanceConfig(correction="none"), sheet_pairs=0)
    assert plain.main().lut is None
    table = Calibrate(
        pairs=pairs, out=tmp_path / "b.json", enhance=EnhanceConfig(correction="none"), sheet_pairs=0, lut_size=5
    )
    profile = table.main()
    assert torch.tensor(profile.lut).shape == (3, 5, 5, 5) and profile.fit["lut_size"] == 5
    assert CameraProfile.load(tmp_path / "b.json").lut == profile.lut
    bad = Calibrate(pairs=pairs, out=tmp_path / "c.json", lut_size=1)
    with pytest.raises(EnhanceOptionError, match=r"^--lut-size 1: a look-up table has 2 to 33 cells per axis"):
        bad.main()
    assert not (tmp_path / "c.json").exists()
