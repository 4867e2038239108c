"""Low-light datamanager: train images enhanced and cached on disk, eval images untouched."""

import json
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

import naka_gs_plugin.datamanager as dm_mod
import naka_gs_plugin.enhance.stages as stages_mod
from naka_gs_plugin.data.images import read_rgb, read_stored
from naka_gs_plugin.data.lowlight_dataparser import LowLightDataError, LowLightDataParserConfig
from naka_gs_plugin.datamanager import LowLightDatamanagerConfig, MissingGroundTruthError
from naka_gs_plugin.enhance.chroma import capture_chroma
from naka_gs_plugin.enhance.naka import naka_enhance
from naka_gs_plugin.enhance.pipeline import EnhanceConfig
from naka_gs_plugin.run.checkpoints import random_state, set_random_state
from naka_gs_plugin.scripts.enhance import Enhance


def _dm(scene, dtype="float32", **enhance):
    cfg = LowLightDatamanagerConfig(
        dataparser=LowLightDataParserConfig(data=scene, downscale_factor=1),
        enhance=EnhanceConfig(**enhance),
        cache_images_type=dtype,
    )
    return cfg.setup(device="cpu", test_mode="val")


def test_train_images_are_naka_enhanced(toy_scene):
    dm = _dm(toy_scene, correction="none")  # Naka alone; the correction net: tests/enhance/test_correction_infer.py
    for data, path in zip(dm.cached_train, dm.train_dataset.image_filenames):
        low = torch.from_numpy(read_rgb(path))
        want = capture_chroma(naka_enhance(low), low)  # the default colour: the capture's
        assert torch.allclose(data["image"], want, atol=2e-5)  # 16-bit cache quantisation


def test_allocator_is_set_for_training_once_the_train_images_are_enhanced(toy_scene, monkeypatch):
    calls = []
    monkeypatch.setattr(dm_mod, "keep_freed_memory", lambda: calls.append("set"))
    dm = _dm(toy_scene, correction="none")
    assert calls == []  # nothing loaded yet: nerfstudio loads the training images lazily
    dm.cached_train
    assert calls == ["set"]


def test_eval_images_are_byte_identical_to_source(toy_scene):
    dm = _dm(toy_scene, dtype="uint8")
    assert len(dm.cached_eval) == 2
    for data, path in zip(dm.cached_eval, dm.eval_dataset.image_filenames):
        assert torch.equal(data["image"][..., :3], torch.from_numpy(read_stored(path)))
    _, batch = dm.next_eval_image(0)
    want = read_stored(dm.eval_dataset.image_filenames[batch["image_idx"]])
    assert torch.equal(batch["image"][..., :3], torch.from_numpy(want))


def _served(dm, n: int) -> list:
    return [dm.next_train(step)[0].metadata["cam_idx"] for step in range(n)]


@pytest.mark.parametrize("sampling", ["random", "fps"])
def test_the_view_order_continues_from_its_saved_state(toy_scene, tmp_path, sampling):
    """What a checkpoint keeps of the datamanager (``resume_state``, through ``torch.save`` and a ``weights_only``
    load) makes a new one serve the views the first would have served next, over the rounds after too; a state
    naming views this scene lacks is refused and changes nothing."""
    made = []
    for _ in range(2):
        dm = _dm(toy_scene, correction="none")
        dm.config.train_cameras_sampling_strategy = sampling
        dm.config.fps_reset_every = 5  # rounds of 5 of the 8 views: the views' unsampled-round counts differ
        dm.train_unseen_cameras = dm.sample_train_cameras()  # as upstream's __init__ does, with this strategy
        made.append(dm)
    first, second = made
    _served(first, len(first.train_dataset) + 5)  # a round and part of the next: its generator has moved on
    first.eval_unseen_cameras.pop()
    # With fps, upstream's sampler draws from numpy's global generator: the trainer saves that state beside this one.
    torch.save((first.resume_state(), random_state()), tmp_path / "state.pt")
    state, generators = torch.load(tmp_path / "state.pt", weights_only=True)
    expected = _served(first, 3 * len(first.train_dataset))
    set_random_state(generators)

    bad = dict(state, train_unseen_cameras=state["train_unseen_cameras"] + [len(second.train_dataset)])
    order = list(second.train_unseen_cameras)
    assert second.load_resume_state(bad) is False and second.train_unseen_cameras == order
    assert second.load_resume_state(state) is True
    assert second.eval_unseen_cameras == [0]
    assert _served(second, len(expected)) == expected


def test_cache_hit_on_second_run_and_miss_when_sigma_changes(toy_scene, monkeypatch):
    first = _dm(toy_scene, sigma=0.07)
    t0 = time.perf_counter()
    first.cached_train
    cold = time.perf_counter() - t0
    assert first.enhancer.last_run["computed"] == 8

    calls = []
    real = stages_mod.naka_rushton
    monkeypatch.setattr(stages_mod, "naka_rushton", lambda *a, **k: calls.append(1) or real(*a, **k))
    second = _dm(toy_scene, sigma=0.07)
    t0 = time.perf_counter()
    second.cached_train
    warm = time.perf_counter() - t0
    assert second.enhancer.last_run == {
        "computed": 0,
        "cached": 8,
        "seconds": pytest.approx(second.enhancer.last_run["seconds"]),
        "naka_seconds": 0.0,
        "correction_seconds": 0.0,
        "chroma_seconds": 0.0,
        "tone_seconds": 0.0,
        "exposure_gain": 1.0,
    }
    assert calls == [], "a cache hit must not recompute the response"
    for a, b in zip(first.cached_train, second.cached_train):
        assert torch.equal(a["image"], b["image"])
    print(f"cold {cold:.3f} s, warm {warm:.3f} s")

    third = _dm(toy_scene, sigma=0.05)
    third.cached_train
    assert third.enhancer.last_run["computed"] == 8 and len(calls) == 8


def test_no_enhancement_baseline_passes_images_through(toy_scene):
    dm = _dm(toy_scene, method="none")
    for data, path in zip(dm.cached_train, dm.train_dataset.image_filenames):
        assert torch.allclose(data["image"], torch.from_numpy(read_rgb(path)))


def test_scene_without_test_images_trains_and_refuses_metrics(toy_scene, tmp_path):
    scene = tmp_path / "scene"
    shutil.copytree(toy_scene, scene)
    shutil.rmtree(scene / "test")
    dm = _dm(scene)
    assert len(dm.cached_train) == 8
    assert not dm.eval_dataset and len(dm.eval_dataset.cameras) == 2  # poses still load
    with pytest.raises(MissingGroundTruthError, match="no ground-truth images"):
        dm.next_eval_image(0)
    with pytest.raises(MissingGroundTruthError):
        dm.fixed_indices_eval_dataloader


def test_missing_test_images_render_as_placeholders_not_metrics(toy_scene, tmp_path):
    scene = tmp_path / "scene"
    shutil.copytree(toy_scene, scene)
    shutil.rmtree(scene / "test")
    dm = _dm(scene)
    batch = dm.eval_dataset[1]  # what ns-render dataset reads: poses render, gt is a black placeholder
    assert batch["image"].shape == (48, 64, 3) and batch["image"].abs().sum() == 0
    assert batch["image_idx"] == 1


def test_enhance_cli_fills_the_training_cache(toy_scene, tmp_path):
    """``naka-gs-enhance SCENE`` then ``ns-train`` on SCENE (distorted camera): training computes nothing."""
    scene = tmp_path / "scene"
    shutil.copytree(toy_scene, scene)
    for split in ("train", "test"):
        meta_path = scene / f"transforms_{split}.json"
        meta = json.loads(meta_path.read_text())
        meta.update(k1=0.05, p1=0.002)  # undistortion changes the pixels the enhancer sees
        meta_path.write_text(json.dumps(meta))
    written = Enhance(scene=scene, out=tmp_path / "enhanced", sheet=False).main()
    assert len(written) == 8 and all(p.is_file() for p in written)

    dm = LowLightDatamanagerConfig(dataparser=LowLightDataParserConfig(data=scene)).setup(device="cpu")
    assert dm.train_dataset.cameras.distortion_params.abs().sum() > 0
    dm.cached_train
    assert dm.enhancer.last_run["computed"] == 0 and dm.enhancer.last_run["cached"] == 8


def test_enhance_cli_scores_against_references_of_the_training_views(toy_scene, tmp_path):
    """A scene with ``transforms_reference.json`` is scored: its own output as reference is a perfect score,
    a red-tinted one shows as missing red in the chromaticity."""
    scene = tmp_path / "scene"
    shutil.copytree(toy_scene, scene)
    first = Enhance(scene=scene, out=tmp_path / "first", sheet=False, reference="none").main()
    assert not (tmp_path / "first" / "scores.json").exists()
    (scene / "reference").mkdir()
    meta = json.loads((scene / "transforms_train.json").read_text())
    for frame, png in zip(meta["frames"], first):
        image = read_rgb(png)
        image[..., 0] = (image[..., 0] * 1.3).clip(0, 1)  # references redder than the enhancement
        name = f"{Path(frame['file_path']).stem}.png"
        Image.fromarray((image * 255 + 0.5).astype(np.uint8)).save(scene / "reference" / name)
        frame["file_path"] = f"reference/{name}"
    (scene / "transforms_reference.json").write_text(json.dumps(meta))

    Enhance(scene=scene, out=tmp_path / "scored", sheet=False).main()
    scores = json.loads((tmp_path / "scored" / "scores.json").read_text())
    assert scores["n_views"] == 8 and len(scores["per_view"]) == 8
    m = scores["means"]
    assert m["chroma_r"] < -0.01 and m["chroma_g"] > 0 and m["chroma_b"] > 0 and m["luma_ratio"] < 1.0
    assert m["chroma_l1"] == pytest.approx(2 * -m["chroma_r"], abs=1e-6)  # fractions sum to 1
    assert 0.0 < m["lpips"] < 0.5 and 10.0 < m["psnr"] < 60.0 and 0.0 < m["ssim"] <= 1.0

    (scene / "reference" / f"{Path(meta['frames'][0]['file_path']).stem}.png").rename(scene / "elsewhere.png")
    meta["frames"] = meta["frames"][1:]
    (scene / "transforms_reference.json").write_text(json.dumps(meta))
    with pytest.raises(LowLightDataError, match="no reference for training view"):
        Enhance(scene=scene, out=tmp_path / "again", sheet=False).main()


def test_colour_error_of_identical_images_is_zero():
    from naka_gs_plugin.metrics import colour_error, colour_stats

    g = torch.Generator().manual_seed(1)
    image = torch.rand(16, 16, 3, generator=g)
    chroma, luma = colour_stats(image)
    assert float(chroma.sum()) == pytest.approx(1.0) and luma > 0
    err = colour_error(image, image)
    assert err["chroma_l1"] == 0.0 and err["luma_ratio"] == pytest.approx(1.0)
    grey = torch.full((4, 4, 3), 0.5)
    torch.testing.assert_close(colour_stats(grey)[0], torch.full((3,), 1 / 3))
