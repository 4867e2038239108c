"""The nerfstudio-data and colmap layouts (``naka_gs_plugin.data.layouts``) of a simulator scene, written by
``benchmarks.layouts``: same images and poses as the lowlight-data scene, every view trains, the eval images are
labelled dark captures, seed points from the layout's own points, downscaled copies outside the scene folder; and
``ns-train naka-gs`` with no layout subcommand is still lowlight-data."""

from __future__ import annotations

import copy
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import tyro

from benchmarks.layouts import map_poses, to_colmap, to_nerfstudio
from naka_gs_plugin.data.layouts import ColmapLayoutConfig, NerfstudioLayoutConfig
from naka_gs_plugin.data.lowlight_dataparser import LowLightDataError, LowLightDataParserConfig, read_split
from naka_gs_plugin.datamanager import LowLightDatamanagerConfig, MissingGroundTruthError
from naka_gs_plugin.enhance.pipeline import EnhanceConfig
from naka_gs_plugin.pipeline import NakaGSPipeline
from naka_gs_plugin.points.seeding import PointInitConfig, TrainingFrame, resolve_seed_points
from naka_gs_plugin.sim.generate import generate
from naka_gs_plugin.sim.spec import load_spec
from tests.helpers import TINY_VIEWS, write_spec

NAKA = EnhanceConfig(use_cache=False, correction="none")


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """A lowlight-data simulator scene with a point cloud (8 train / 2 test views, 64x48), and its two layouts."""
    tmp = tmp_path_factory.mktemp("layouts")
    views = {**TINY_VIEWS, "n_train": 8, "n_test": 2, "width": 64, "height": 48}
    points = {"n_points": 500, "n_clusters": 1, "cluster_size": 50}
    spec = write_spec(tmp, [{"exposure": {"factor": 0.05}}], source={"procedural": {**views, "points": points}})
    scene = generate(load_spec(spec), tmp / "scene", seed=0)
    return {
        "lowlight-data": scene,
        "nerfstudio-data": to_nerfstudio(scene, tmp / "ns"),
        "colmap": to_colmap(scene, tmp / "colmap"),
    }


LAYOUTS = {"nerfstudio-data": NerfstudioLayoutConfig, "colmap": ColmapLayoutConfig}


def _by_name(outputs):
    return [Path(p).name for p in outputs.metadata["source_images"]]


@pytest.mark.parametrize("layout", LAYOUTS)
def test_a_converted_layout_has_the_same_images_and_poses_and_trains_on_every_view(scenes, layout):
    scene = scenes["lowlight-data"]
    reference = LowLightDataParserConfig(data=scene).setup().get_dataparser_outputs("train")
    parser = LAYOUTS[layout](data=scenes[layout]).setup()
    train, test = parser.get_dataparser_outputs("train"), parser.get_dataparser_outputs("test")
    names = [p.name for p in reference.image_filenames]
    assert sorted(_by_name(train)) == sorted(names) and _by_name(test) == _by_name(train)  # all views train
    assert all(Path(p).is_symlink() for p in train.metadata["source_images"])  # links, never copies
    assert test.metadata["eval_truth"] == "dark" and "dark captures" in test.metadata["truth_note"]
    order = [_by_name(train).index(n) for n in names]
    mapped = map_poses(
        reference.cameras.camera_to_worlds,
        (reference.dataparser_transform, reference.dataparser_scale),
        (train.dataparser_transform, train.dataparser_scale),
    )
    assert torch.allclose(mapped, train.cameras.camera_to_worlds[order], atol=1e-5)
    assert torch.equal(train.cameras.fx[order], reference.cameras.fx)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_a_layout_seeds_from_its_own_points_as_lowlight_data_does(scenes, layout):
    scene = scenes["lowlight-data"]
    reference = LowLightDataParserConfig(data=scene).setup().get_dataparser_outputs("train")
    frame = TrainingFrame.from_split(
        scene, read_split(scene, "transforms_train.json"), reference.dataparser_transform, reference.dataparser_scale
    )
    expected = resolve_seed_points(PointInitConfig(), frame)
    outputs = LAYOUTS[layout](data=scenes[layout]).setup().get_dataparser_outputs("train")
    seed = resolve_seed_points(
        PointInitConfig(), TrainingFrame.from_layout(scenes[layout], outputs.metadata["seed_frame"])
    )
    own = scenes[layout] / ("points.ply" if layout == "nerfstudio-data" else "sparse/0")
    assert seed.summary["source"].endswith(str(own)) and len(seed.xyz) == len(expected.xyz) > 100
    # the same points, in each run's normalized frame: mapped into the lowlight-data one they coincide
    rot_a, rot_b = outputs.dataparser_transform[:, :3].double(), reference.dataparser_transform[:, :3].double()
    t_a, t_b = outputs.dataparser_transform[:, 3].double(), reference.dataparser_transform[:, 3].double()
    world = (torch.from_numpy(seed.xyz) / outputs.dataparser_scale - t_a) @ rot_a
    back = ((world @ rot_b.T + t_b) * reference.dataparser_scale).numpy()
    ref = expected.xyz
    nearest = np.sqrt(((back[:, None, :] - ref[None, :, :]) ** 2).sum(-1)).min(axis=1)
    assert nearest.max() < 1e-4, nearest.max()


@pytest.mark.parametrize("layout", LAYOUTS)
def test_downscaled_copies_go_to_the_cache_not_the_scene(scenes, layout, tmp_path):
    before = sorted(str(p) for p in scenes[layout].rglob("*"))
    outputs = LAYOUTS[layout](data=scenes[layout], downscale_factor=2).setup().get_dataparser_outputs("train")
    assert sorted(str(p) for p in scenes[layout].rglob("*")) == before
    assert all(str(p).startswith(str(tmp_path / "naka-cache")) for p in outputs.image_filenames)
    assert int(outputs.cameras.width[0]) == 32 and outputs.metadata["downscale_factor"] == 2


def test_a_colmap_scene_without_a_model_is_one_line(tmp_path):
    (tmp_path / "images").mkdir()
    with pytest.raises(LowLightDataError, match=r"no COLMAP model .* pass --colmap-path"):
        ColmapLayoutConfig(data=tmp_path).setup().get_dataparser_outputs("train")


def _datamanager(parser, test_mode: str):
    config = LowLightDatamanagerConfig(dataparser=parser, enhance=NAKA)
    return config.setup(device="cpu", test_mode=test_mode)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_dark_eval_images_are_not_evaluated_and_ns_eval_says_so_in_one_line(scenes, layout):
    train = _datamanager(LAYOUTS[layout](data=scenes[layout]), "val")
    assert train.against_dark and not train.eval_dataset  # the eval views are the training views: no evaluation
    loaded = _datamanager(LAYOUTS[layout](data=scenes[layout]), "test")  # as ns-eval builds it
    with pytest.raises(MissingGroundTruthError) as err:
        loaded.fixed_indices_eval_dataloader
    message = str(err.value)
    assert "\n" not in message and message.startswith(f"naka-gs: {scenes[layout]}: no normal-light truth ({layout}")


def test_held_out_dark_views_are_evaluated_with_labelled_metrics(scenes):
    parser = NerfstudioLayoutConfig(data=scenes["nerfstudio-data"], eval_mode="interval", eval_interval=4)
    datamanager = _datamanager(parser, "val")
    assert datamanager.against_dark and len(datamanager.eval_dataset) == 2 and datamanager.eval_dataset
    assert len(datamanager.train_dataset) == 6
    stub = SimpleNamespace(datamanager=datamanager)
    metrics = {"psnr": 20.0, "ssim": 0.5, "lpips": 0.3, "num_rays": 7, "fps": 2.0}
    assert NakaGSPipeline._labelled(stub, metrics) == {
        "vs_dark_psnr": 20.0,
        "vs_dark_ssim": 0.5,
        "vs_dark_lpips": 0.3,
        "num_rays": 7,
        "fps": 2.0,
    }


def test_lowlight_data_with_truth_is_not_labelled(scenes):
    datamanager = _datamanager(LowLightDataParserConfig(data=scenes["lowlight-data"], downscale_factor=1), "val")
    assert not datamanager.against_dark and datamanager.eval_dataset
    assert NakaGSPipeline._labelled(SimpleNamespace(datamanager=datamanager), {"psnr": 1.0}) == {"psnr": 1.0}


def _parse(args):
    from naka_gs_plugin.config import naka_gs_method

    config = copy.deepcopy(naka_gs_method.config)
    return tyro.cli(type(config), default=config, args=args)


def test_ns_train_without_a_layout_is_lowlight_data_and_each_layout_is_a_subcommand():
    from naka_gs_plugin.config import naka_gs_method

    plain = _parse(["--data", "X"]).pipeline.datamanager.dataparser
    assert plain == naka_gs_method.config.pipeline.datamanager.dataparser
    assert type(plain) is LowLightDataParserConfig
    named = _parse(["--data", "X", "lowlight-data", "--downscale-factor", "2"]).pipeline.datamanager.dataparser
    assert type(named) is LowLightDataParserConfig and named.downscale_factor == 2
    ns = _parse(["--data", "X", "nerfstudio-data"]).pipeline.datamanager.dataparser
    assert type(ns) is NerfstudioLayoutConfig and ns.eval_mode == "all" and not ns.load_3D_points
    colmap = _parse(["--data", "X", "colmap", "--eval-mode", "interval"]).pipeline.datamanager.dataparser
    assert type(colmap) is ColmapLayoutConfig and colmap.eval_mode == "interval"
    assert colmap.colmap_path == Path("sparse/0")
