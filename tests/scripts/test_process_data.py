"""``naka-gs-process-data`` on a simulated dark capture (LOM bike darkened by the simulator).

The simulator's ``capture`` source keeps the real poses of the views it darkens, so the poses that
SfM recovers from the dark images can be checked against them after a sim3 alignment. LOM bike's
calibration has its principal point at the image centre, where COLMAP keeps it, so the comparison
measures the poses and not a calibration convention.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from naka_gs_plugin.data.lowlight_dataparser import LowLightDataParserConfig
from naka_gs_plugin.datamanager import LowLightDatamanagerConfig, MissingGroundTruthError
from naka_gs_plugin.enhance.pipeline import EnhanceConfig
from naka_gs_plugin.points.align import match_names
from naka_gs_plugin.points.sfm import compare_poses
from naka_gs_plugin.scripts.process_data import ProcessData, ProcessDataError, TooFewRegisteredError
from tests.helpers import dark_capture

N_VIEWS = 16
NAKA = EnhanceConfig(use_cache=False, correction="none")  # Naka only: fast, and independent of shipped weights


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    return dark_capture(tmp_path_factory.mktemp("capture"), n_train=N_VIEWS, downscale=1, scene="bike")


@pytest.fixture(scope="module")
def processed(capture, tmp_path_factory):
    out = tmp_path_factory.mktemp("processed") / "scene"
    report = ProcessData(data=capture / "train", output_dir=out, enhance=NAKA).main()  # default: every view trains
    return out, report


def _frames(scene: Path):
    """The scene's registered views, once each (the default's test split lists the training views again)."""
    frames = {
        f["file_path"]: f
        for split in ("train", "test")
        for f in json.loads((scene / f"transforms_{split}.json").read_text())["frames"]
    }
    return list(frames.values())


def _datamanager(scene: Path, test_mode: str):
    config = LowLightDatamanagerConfig(
        dataparser=LowLightDataParserConfig(data=scene, downscale_factor=4), enhance=NAKA
    )
    return config.setup(device="cpu", test_mode=test_mode)


def _ns_eval_line(scene: Path) -> str:
    """What ``ns-eval`` on a run of ``scene`` ends with (its datamanager is built with test_mode ``test``)."""
    with pytest.raises(MissingGroundTruthError) as err:
        _datamanager(scene, "test").fixed_indices_eval_dataloader
    return str(err.value)


def test_recovered_poses_match_the_truth_after_sim3(capture, processed):
    scene, report = processed
    assert report["registered"] == report["total"] == N_VIEWS
    est, true = _frames(scene), json.loads((capture / "transforms_train.json").read_text())["frames"]
    pairs = match_names([f["file_path"] for f in est], [f["file_path"] for f in true])
    assert len(pairs) == N_VIEWS
    errors = compare_poses(
        np.array([est[i]["transform_matrix"] for i, _ in pairs]),
        np.array([true[j]["transform_matrix"] for _, j in pairs]),
    )
    assert errors["rotation_deg"].max() < 1.0, errors["rotation_deg"]
    assert errors["centre_error_pct"].max() < 2.0, errors["centre_error_pct"]


def test_scene_references_the_original_images_and_trains_on_every_view(capture, processed):
    scene, report = processed
    train = json.loads((scene / "transforms_train.json").read_text())
    test = json.loads((scene / "transforms_test.json").read_text())
    names = sorted(p.name for p in (capture / "train").iterdir())
    assert [f["file_path"] for f in train["frames"]] == [f"images/{n}" for n in names]  # no view held out
    assert test["frames"] == train["frames"] and test["eval_truth"] == "dark"
    assert (report["train_views"], report["test_views"]) == (N_VIEWS, 0)
    for name in names:  # byte copies of the dark originals
        assert (scene / "images" / name).read_bytes() == (capture / "train" / name).read_bytes()
    assert {"k1", "k2", "p1", "p2", "fl_x", "cx", "w", "h"} <= set(train)
    assert (train["w"], train["h"]) == (500, 375)
    model = pycolmap.Reconstruction(scene / "sparse" / "0")
    assert sorted(im.name for im in model.images.values()) == names
    assert model.num_points3D() == report["points"] > 100
    saved = json.loads((scene / "process_data.json").read_text())
    assert saved["registered"] == N_VIEWS and set(saved["seconds"]) >= {"enhance", "extract", "match", "mapping"}
    assert report["mean_reprojection_error_px"] < 1.5
    assert not [p for p in scene.parent.iterdir() if p.name.startswith(".")]  # no staging left behind


def test_sparse_points_share_the_frame_of_the_transforms(processed):
    scene, _ = processed
    model = pycolmap.Reconstruction(scene / "sparse" / "0")
    frames = {f["file_path"]: np.array(f["transform_matrix"]) for f in _frames(scene)}
    for image in model.images.values():
        assert np.allclose(frames[f"images/{image.name}"][:3, 3], image.projection_center(), atol=1e-9)


@pytest.mark.slow  # ns-train in a subprocess
def test_scene_parses_and_trains_30_steps(processed, tmp_path):
    scene, _ = processed
    outputs = LowLightDataParserConfig(data=scene).setup().get_dataparser_outputs("train")
    assert len(outputs.image_filenames) == N_VIEWS
    cmd = [
        str(Path(sys.executable).parent / "ns-train"), "naka-gs", "--data", str(scene),
        "--max-num-iterations", "30", "--output-dir", str(tmp_path / "out"), "--vis", "tensorboard",
        "--viewer.quit-on-train-completion", "True", "--pipeline.model.num-random", "2000",
        "--pipeline.datamanager.enhance.correction", "none",
        "--timestamp", "run", "lowlight-data", "--downscale-factor", "4",
    ]  # fmt: skip
    env = {**os.environ, "TORCHDYNAMO_DISABLE": "1", "NAKA_GS_CACHE": str(tmp_path / "cache")}
    result = subprocess.run(cmd, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    assert result.returncode == 0, result.stdout[-4000:]
    assert list((tmp_path / "out").rglob("step-*.ckpt"))
    log = " ".join(result.stdout.split())
    assert f"seed points: COLMAP model {scene / 'sparse' / '0'}" in log  # the scene's default point source


def test_the_default_scene_evaluates_nothing_and_ns_eval_says_there_is_no_truth(processed):
    scene, _ = processed
    training = _datamanager(scene, "val")
    assert training.against_dark and not training.eval_dataset  # the eval views are the dark training views
    line = _ns_eval_line(scene)
    assert "\n" not in line and line.startswith(f"naka-gs: {scene}: no normal-light truth (transforms_test.json")


def test_eval_every_holds_out_dark_views_labelled_as_such(capture, processed, tmp_path):
    """``--eval-every 4`` still holds out every 4th view: scored during training against its dark image (labelled),
    refused by ns-eval. The same registration as the default's (seeded), only the split differs."""
    default, _ = processed
    scene = tmp_path / "held-out"
    report = ProcessData(data=capture / "train", output_dir=scene, eval_every=4, enhance=NAKA).main()
    test = json.loads((scene / "transforms_test.json").read_text())
    names = sorted(p.name for p in (capture / "train").iterdir())
    assert [f["file_path"] for f in test["frames"]] == [f"images/{n}" for n in names[::4]]
    assert test["eval_truth"] == "dark" and (report["train_views"], report["test_views"]) == (12, 4)
    training = _datamanager(scene, "val")
    assert training.against_dark and len(training.eval_dataset) == 4 and training.eval_dataset
    assert "no normal-light truth" in _ns_eval_line(scene)


@pytest.mark.parametrize("every", [1, -2])
def test_eval_every_one_or_negative_is_refused(capture, tmp_path, every):
    with pytest.raises(ProcessDataError, match=f"--eval-every {every}: must be 0 .* or >= 2"):
        ProcessData(data=capture / "train", output_dir=tmp_path / "out", eval_every=every, enhance=NAKA).main()
    assert not (tmp_path / "out").exists()


def test_unmatchable_images_fail_clearly_and_write_nothing(tmp_path):
    import cv2

    folder = tmp_path / "noise"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(4):  # unrelated views: features, but no geometry between them
        cv2.imwrite(str(folder / f"{i}.png"), rng.integers(0, 256, (120, 160, 3), dtype=np.uint8))
    with pytest.raises(TooFewRegisteredError, match=r"only 0 of 4 images registered .* try more overlapping") as err:
        ProcessData(data=folder, output_dir=tmp_path / "out", enhance=NAKA).main()
    assert (err.value.registered, err.value.total) == (0, 4) and set(err.value.seconds) >= {"extract", "match"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["noise"]


def test_two_images_fail_clearly(capture, tmp_path):
    folder = tmp_path / "two"
    folder.mkdir()
    for p in sorted((capture / "train").iterdir())[:2]:
        (folder / p.name).write_bytes(p.read_bytes())
    with pytest.raises(ProcessDataError, match="2 image\\(s\\) found .* at least 3"):
        ProcessData(data=folder, output_dir=tmp_path / "out", enhance=NAKA).main()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["two"]


def test_unreadable_image_is_named(capture, tmp_path):
    folder = tmp_path / "bad"
    folder.mkdir()
    for p in sorted((capture / "train").iterdir())[:4]:
        (folder / p.name).write_bytes(p.read_bytes())
    (folder / "0002.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(ProcessDataError, match="0002.jpg: unreadable image"):
        ProcessData(data=folder, output_dir=tmp_path / "out", enhance=NAKA).main()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad"]


def test_mixed_sizes_are_refused(capture, tmp_path):
    import cv2

    folder = tmp_path / "mixed"
    folder.mkdir()
    for p in sorted((capture / "train").iterdir())[:3]:
        (folder / p.name).write_bytes(p.read_bytes())
    cv2.imwrite(str(folder / "9999.png"), np.zeros((10, 20, 3), np.uint8))
    with pytest.raises(ProcessDataError, match="9999.png: 20x10 but"):
        ProcessData(data=folder, output_dir=tmp_path / "out", enhance=NAKA).main()


def test_video_without_ffmpeg_says_so(tmp_path, monkeypatch):
    video = tmp_path / "clip.mp4"
    video.write_bytes(b"\x00")
    monkeypatch.setenv("PATH", str(tmp_path / "empty-bin"))
    with pytest.raises(ProcessDataError, match="needs the ffmpeg binary, which is not on PATH"):
        ProcessData(data=video, output_dir=tmp_path / "out").main()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clip.mp4"]


def test_existing_output_is_not_overwritten_by_default(capture, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    with pytest.raises(ProcessDataError, match="already exists and is not empty .* --overwrite"):
        ProcessData(data=capture / "train", output_dir=out).main()
    assert (out / "keep.txt").read_text() == "x"
