"""lowlight-data parser on every real scene, plus its one-line errors on broken scenes."""

import json
import shutil

import pytest
import torch

from naka_gs_plugin.data.lowlight_dataparser import LowLightDataError, LowLightDataParserConfig, auto_downscale
from tests.helpers import SHARED_DATA

REALX3D = sorted(p for p in (SHARED_DATA / "realx3d").glob("*") if p.is_dir())
LOM = sorted(p for p in (SHARED_DATA / "lom").glob("*") if p.is_dir())


def _json(scene, name):
    return json.loads((scene / name).read_text())


def _check_scene(scene, expect_gt):
    parser = LowLightDataParserConfig(data=scene, downscale_factor=1).setup()
    train, test = parser.get_dataparser_outputs("train"), parser.get_dataparser_outputs("test")
    jtrain, jtest = _json(scene, "transforms_train.json"), _json(scene, "transforms_test.json")
    assert len(train.image_filenames) == len(jtrain["frames"])
    assert len(test.image_filenames) == len(jtest["frames"])
    assert test.metadata["has_ground_truth"] is expect_gt
    cams = train.cameras
    assert torch.allclose(cams.fx[:, 0], torch.tensor(jtrain["fl_x"]).float())
    assert torch.allclose(cams.fy[:, 0], torch.tensor(jtrain["fl_y"]).float())
    assert torch.allclose(cams.cx[:, 0], torch.tensor(jtrain["cx"]).float())
    assert int(cams.width[0]) == round(jtrain["w"]) and int(cams.height[0]) == round(jtrain["h"])
    want_dist = torch.tensor([jtrain.get(k, 0.0) for k in ("k1", "k2", "k3", "k4", "p1", "p2")]).float()
    assert torch.allclose(cams.distortion_params[0], want_dist)
    # Pose round trip: undo scale and transform, compare with the json (OpenGL c2w, unchanged axes).
    T, s = train.dataparser_transform.double(), train.dataparser_scale
    for split, meta in ((train, jtrain), (test, jtest)):
        c2w = split.cameras.camera_to_worlds.double()
        rot = T[:, :3].T @ c2w[:, :, :3]
        centre = (c2w[:, :, 3] / s - T[:, 3]) @ T[:, :3]
        want = torch.tensor([f["transform_matrix"] for f in meta["frames"]], dtype=torch.float64)
        assert torch.allclose(rot, want[:, :3, :3], atol=1e-5)
        assert torch.allclose(centre, want[:, :3, 3], atol=1e-4 * want[:, :3, 3].abs().max())
    # Unit-scale training frame, as splatfacto assumes.
    assert cams.camera_to_worlds[:, :, 3].abs().max() == pytest.approx(1.0, abs=1e-5)


REALX3D_WITH_TRUTH = {"BlueHawaii"}
"""The validation scene, with its test views' normal-light truth (``../shared/data/realx3d/README.md``)."""


@pytest.mark.parametrize("scene", REALX3D, ids=[p.name for p in REALX3D])
def test_realx3d_scene_parses_with_truth_only_for_the_validation_scene(scene):
    assert len(REALX3D) == 8
    _check_scene(scene, expect_gt=scene.name in REALX3D_WITH_TRUTH)


@pytest.mark.parametrize("scene", LOM, ids=[p.name for p in LOM])
def test_lom_scene_parses_with_distortion_and_ground_truth(scene):
    assert len(LOM) == 4
    _check_scene(scene, expect_gt=True)
    val = LowLightDataParserConfig(data=scene, downscale_factor=1).setup().get_dataparser_outputs("val")
    assert len(val.image_filenames) == len(_json(scene, "transforms_val.json")["frames"])


@pytest.mark.parametrize("factor", [0, -2])
def test_downscale_factor_below_one_names_the_option(toy_scene, tmp_path, factor):
    parser = LowLightDataParserConfig(data=toy_scene, downscale_factor=factor).setup()
    with pytest.raises(LowLightDataError, match=rf"downscale-factor must be a whole number >= 1, got {factor}"):
        parser.get_dataparser_outputs("train")


def test_auto_downscale_and_cached_copies(toy_scene, tmp_path, monkeypatch):
    monkeypatch.setenv("NAKA_GS_CACHE", str(tmp_path))
    assert auto_downscale(1764, 1172) == 2 and auto_downscale(500, 375) == 1
    out = LowLightDataParserConfig(data=toy_scene, downscale_factor=2).setup().get_dataparser_outputs("train")
    assert all(str(p).startswith(str(tmp_path)) for p in out.image_filenames)
    from PIL import Image

    with Image.open(out.image_filenames[0]) as im:
        assert im.size == (32, 24) == (int(out.cameras.width[0]), int(out.cameras.height[0]))
    assert float(out.cameras.fx[0]) == pytest.approx(float(_json(toy_scene, "transforms_train.json")["fl_x"]) / 2)


@pytest.fixture
def broken(toy_scene, tmp_path):
    scene = tmp_path / "scene"
    shutil.copytree(toy_scene, scene)
    return scene


def _one_line_error(scene, must_name):
    with pytest.raises(LowLightDataError) as err:
        LowLightDataParserConfig(data=scene, downscale_factor=1).setup().get_dataparser_outputs("train")
    msg = str(err.value)
    assert "\n" not in msg and str(must_name) in msg and "--" in msg  # names the file and the fix
    return msg


def test_malformed_json_names_the_file(broken):
    (broken / "transforms_train.json").write_text('{"frames": [')
    assert "malformed json" in _one_line_error(broken, broken / "transforms_train.json")


def test_missing_image_names_the_file(broken):
    (broken / "train" / "0003.png").unlink()
    assert "not found" in _one_line_error(broken, broken / "train" / "0003.png")


def test_bad_file_path_names_the_json(broken):
    meta = _json(broken, "transforms_train.json")
    meta["frames"][2]["file_path"] = None
    (broken / "transforms_train.json").write_text(json.dumps(meta))
    assert "frame 2" in _one_line_error(broken, broken / "transforms_train.json")


def test_image_size_mismatch_names_the_image(broken):
    from PIL import Image

    Image.new("RGB", (10, 10)).save(broken / "train" / "0001.png")
    assert "10x10" in _one_line_error(broken, broken / "train" / "0001.png")


def test_partially_missing_test_images_is_an_error(broken):
    (broken / "test" / "0001.png").unlink()
    with pytest.raises(LowLightDataError, match="0001.png"):
        LowLightDataParserConfig(data=broken, downscale_factor=1).setup().get_dataparser_outputs("test")


@pytest.mark.parametrize("scene", [*LOM[:1], *REALX3D[:1]], ids=[p.name for p in [*LOM[:1], *REALX3D[:1]]])
def test_world_points_map_into_the_training_frame_like_the_cameras(scene):
    from naka_gs_plugin.data.lowlight_dataparser import to_normalized_frame

    out = LowLightDataParserConfig(data=scene, downscale_factor=1).setup().get_dataparser_outputs("test")
    world_centres = torch.tensor([f["transform_matrix"] for f in _json(scene, "transforms_test.json")["frames"]])[
        :, :3, 3
    ]
    mapped = to_normalized_frame(world_centres, out.dataparser_transform, out.dataparser_scale)
    assert torch.allclose(mapped, out.cameras.camera_to_worlds[:, :, 3], atol=1e-5)
