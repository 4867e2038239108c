"""Spec-driven low-light simulator: effect isolation, noise model, determinism, layout, sim3, spec errors."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest
import torch

import benchmarks.sim_stats as stats
from naka_gs_plugin.data.images import read_rgb
from naka_gs_plugin.data.lowlight_dataparser import LowLightDataParserConfig
from naka_gs_plugin.scripts import sim as cli
from naka_gs_plugin.sim.effects import sensor
from naka_gs_plugin.sim.generate import build_scene, generate
from naka_gs_plugin.sim.spec import Noise, SimSpecError, load_spec, shipped_specs
from tests.helpers import TINY_VIEWS, write_spec

REPO = Path(__file__).resolve().parents[2]
TINY = TINY_VIEWS
U16 = 1.0 / 65535.0


def make(tmp_path: Path, effects: list, name: str = "s", seed: int | None = None, **kw) -> Path:
    return generate(load_spec(write_spec(tmp_path, effects, name, **kw)), tmp_path / f"out-{name}", seed=seed)


def train_images(scene: Path, folder: str = "train") -> np.ndarray:
    return np.stack([read_rgb(p, np.float64) for p in sorted((scene / folder).iterdir())])


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> tuple:
    """The tiny reference scene with no effects, and its exact linear renders (float64)."""
    tmp = tmp_path_factory.mktemp("clean")
    spec = load_spec(write_spec(tmp, [], "clean"))
    scene = build_scene(spec)
    linear = np.stack([scene.clean(v).numpy() for v in scene.views if v.split == "train"])
    return generate(spec, tmp / "out"), linear


def manifest(scene: Path) -> dict:
    return json.loads((scene / "sim_manifest.json").read_text())


def srgb(x: np.ndarray) -> np.ndarray:
    return np.where(x > 0.0031308, 1.055 * np.power(np.maximum(x, 0.0031308), 1 / 2.4) - 0.055, 12.92 * x)


# --- effect isolation ------------------------------------------------------------------------------


def test_clean_is_linear_16bit_and_equals_truth(clean):
    scene, linear = clean
    assert np.array_equal(train_images(scene), train_images(scene, "train_gt"))
    assert np.abs(train_images(scene) - linear).max() <= 0.5 * U16 + 1e-12  # written linearly, no response
    m = manifest(scene)
    assert m["effects_applied"] == [] and m["encoding"]["values"] == "linear" and m["encoding"]["bit_depth"] == 16
    assert (train_images(scene) < 1.0).all()  # no saturation without lamps or a bright exposure


def test_exposure_only_scales_clean(tmp_path, clean):
    dark = make(tmp_path, [{"exposure": {"factor": 0.02}}])
    assert np.abs(train_images(dark) - 0.02 * clean[1]).max() <= 0.5 * U16 + 1e-12
    assert np.array_equal(train_images(dark, "train_gt"), train_images(clean[0], "train_gt"))


def test_bright_exposure_saturates(tmp_path, clean):
    bright = train_images(make(tmp_path, [{"exposure": {"factor": 8.0}}]))
    assert (bright >= 1.0).any() and np.array_equal(bright, np.minimum(np.round(8.0 * clean[1] * 65535) / 65535, 1))


def test_exposure_jitter_is_a_recorded_per_view_gain(tmp_path, clean):
    scene = make(tmp_path, [{"exposure_jitter": {"stops": 0.5}}])
    gains = [v["exposure_multiplier"] for v in manifest(scene)["train_views"]]
    assert len(set(gains)) == len(gains)
    expected = np.minimum(clean[1] * np.array(gains)[:, None, None, None], 1.0)
    assert np.abs(train_images(scene) - expected).max() <= 0.5 * U16 + 1e-12


def test_light_sources_add_saturated_lamps_only(tmp_path, clean):
    effects = [{"light_sources": {"count": 2, "intensity": 50.0, "radius": 0.1, "bloom_sigma_px": 2.0}}]
    lit = train_images(make(tmp_path, effects))
    assert (lit >= 1.0).all(-1).any()  # saturated lamp cores
    assert (lit >= clean[1] - U16).all()  # lamps only add light
    assert np.mean(np.abs(lit - clean[1]) <= U16) > 0.3  # and leave most pixels untouched


def test_color_cast_scales_channel_ratios(tmp_path, clean):
    gains = np.array([1.2, 1.0, 0.7])
    cast = train_images(make(tmp_path, [{"color_cast": {"gains": gains.tolist()}}]))
    ok = (clean[1] > 0.05).all(-1) & (clean[1] * gains < 0.99).all(-1)
    assert ok.sum() > 100
    ratio = cast[ok] / clean[1][ok]
    assert np.abs(ratio - gains).max() < 2e-3


def test_noise_only_is_zero_mean_with_declared_variance(tmp_path, clean):
    noise = {"shot_gain": 1e-3, "read_std": 0.01}
    noisy = train_images(make(tmp_path, [{"noise": noise}]))
    x = clean[1]
    ok = (x > 0.1) & (x < 0.7)  # away from the clip at 0 and 1
    resid = (noisy - x)[ok]
    var = noise["shot_gain"] * x[ok] + noise["read_std"] ** 2
    assert abs(resid.mean()) < 4 * np.sqrt(var.mean() / ok.sum())
    assert abs(np.mean(resid**2 / var) - 1.0) < 0.08


def test_response_curves(tmp_path, clean):
    gamma = train_images(make(tmp_path, [{"response": {"curve": "gamma", "gamma": 2.2}}], "g"))
    assert np.abs(gamma - clean[1] ** (1 / 2.2)).max() <= 0.5 * U16 + 1e-9
    s = make(tmp_path, [{"response": {"curve": "srgb"}}], "s")
    assert np.abs(train_images(s) - srgb(clean[1])).max() <= 0.5 * U16 + 1e-9
    assert np.array_equal(train_images(s), train_images(s, "train_gt"))  # truth shares the response


def test_quantize_only_writes_8bit_linear(tmp_path, clean):
    scene = make(tmp_path, [{"quantize": {}}])
    assert np.array_equal(train_images(scene), np.round(clean[1] * 255) / 255)
    assert manifest(scene)["encoding"]["bit_depth"] == 8


def test_jpeg_compresses_training_images_only(tmp_path):
    png = train_images(make(tmp_path, [{"response": {}}, {"quantize": {}}], "png"))
    scene = make(tmp_path, [{"response": {}}, {"quantize": {}}, {"jpeg": {"quality": 80}}], "jpg")
    assert sorted(p.suffix for p in (scene / "train").iterdir()) == [".jpg"] * 3
    jpg = train_images(scene)
    psnr = -10 * np.log10(np.mean((jpg - png) ** 2))
    assert 25 < psnr < 60
    assert np.array_equal(train_images(scene, "train_gt"), png)


def test_noise_free_pipeline_has_zero_residual(tmp_path, clean):
    effects = [
        {"exposure": {"factor": 0.05}},
        {"exposure_jitter": {"stops": 0.3}},
        {"color_cast": {"gains": [1.1, 1.0, 0.8]}},
        {"response": {"curve": "srgb"}},
        {"quantize": {}},
    ]
    scene = make(tmp_path, effects)
    gains = np.array([v["exposure_multiplier"] for v in manifest(scene)["train_views"]])[:, None, None, None]
    linear = np.clip(clean[1] * 0.05 * gains * np.array([1.1, 1.0, 0.8]), 0, 1)
    assert np.array_equal(train_images(scene), np.round(srgb(linear) * 255) / 255)
    assert not (train_images(scene) >= 1.0).any()


def test_noise_statistics_follow_poisson_gaussian_line():
    levels = torch.linspace(0.02, 0.6, 8, dtype=torch.float64)
    flat = levels[:, None, None].expand(8, 128, 3).reshape(8, 128, 3).repeat_interleave(8, 1)
    noise = Noise(shot_gain=2e-3, read_std=0.02)
    out = sensor(flat, [noise], generator=torch.Generator().manual_seed(0))
    means, varis = out.mean((1, 2)).numpy(), out.var((1, 2)).numpy()
    slope, intercept = np.polyfit(means, varis, 1)
    assert np.abs(means - levels.numpy()).max() < 3e-3
    assert abs(slope / noise.shot_gain - 1) < 0.1 and abs(intercept / noise.read_std**2 - 1) < 0.15


# --- determinism, layout, point cloud --------------------------------------------------------------


def test_same_seed_identical_bytes_other_seed_changes_noise_only(tmp_path):
    effects = [{"exposure": {"factor": 0.05}}, {"noise": {}}, {"response": {}}, {"quantize": {}}]
    spec = load_spec(write_spec(tmp_path, effects))
    a, b, c = (generate(spec, tmp_path / n, seed=s) for n, s in (("a", 0), ("b", 0), ("c", 1)))
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    assert all((a / f).read_bytes() == (b / f).read_bytes() for f in files)
    changed = {str(f) for f in files if (a / f).read_bytes() != (c / f).read_bytes()}
    assert changed == {f"train/{i:04d}.png" for i in range(3)} | {"sim_manifest.json"}
    ma, mc = manifest(a), manifest(c)
    assert (ma["seed"], mc["seed"]) == (0, 1)
    diff = train_images(a) - train_images(c)
    assert abs(diff.mean()) < 2e-3  # zero-mean: the signal is the same


def test_scene_parses_and_point_cloud_sim3_is_recoverable(tmp_path):
    sim3 = {"scale": 0.5, "rotation_deg": [10.0, -20.0, 30.0], "translation": [0.3, -1.0, 2.0]}
    points = {"n_points": 800, "noise_std": 0.0, "outlier_fraction": 0.0, "n_clusters": 0, "sim3": sim3}
    source = {"procedural": {**TINY, "layout": "forward", "points": points}}
    spec = load_spec(write_spec(tmp_path, [{"exposure": {"factor": 0.1}}], source=source))
    scene = generate(spec, tmp_path / "out")
    outputs = LowLightDataParserConfig(data=scene, downscale_factor=1).setup().get_dataparser_outputs("train")
    assert len(outputs.image_filenames) == 3 and int(outputs.cameras.width[0]) == 48
    test = LowLightDataParserConfig(data=scene, downscale_factor=1).setup().get_dataparser_outputs("test")
    assert test.metadata["has_ground_truth"]

    m = np.array(manifest(scene)["points"]["sim3"]["matrix"])
    ply = o3d.io.read_point_cloud(str(scene / "points.ply"))
    xyz, rgb = np.asarray(ply.points), np.asarray(ply.colors)
    assert len(xyz) == 800 and rgb.max() > 0
    back = (xyz - m[:3, 3]) @ np.linalg.inv(m[:3, :3]).T
    surface = torch.from_numpy(build_scene(spec).points)
    nearest = torch.cdist(torch.from_numpy(back), surface).min(1).values
    assert nearest.max() < 1e-5 * 10  # float32 PLY rounding only
    frames = json.loads((scene / "transforms_train.json").read_text())["frames"]
    centres = json.loads((scene / "points_cameras.json").read_text())
    for frame in frames:
        c = np.array(centres[Path(frame["file_path"]).name])
        recovered = np.linalg.inv(m) @ np.append(c, 1.0)
        assert np.allclose(recovered[:3], np.array(frame["transform_matrix"])[:3, 3], atol=1e-9)


def test_point_cloud_noise_outliers_and_clusters(tmp_path):
    points = {"n_points": 600, "noise_std": 0.02, "outlier_fraction": 0.1, "n_clusters": 2, "cluster_size": 100}
    spec = load_spec(write_spec(tmp_path, [], source={"procedural": {**TINY, "points": points}}))
    scene = generate(spec, tmp_path / "out")
    xyz = np.asarray(o3d.io.read_point_cloud(str(scene / "points.ply")).points)  # identity sim3
    assert len(xyz) == 600 + 60 + 200
    nearest = torch.cdist(torch.from_numpy(xyz[:600]), torch.from_numpy(build_scene(spec).points)).min(1).values
    assert 0.01 < float(nearest.median()) < 0.05  # ~ noise_std away from the surface


# --- spec errors, shipped specs, CLI ---------------------------------------------------------------


@pytest.mark.parametrize(
    ("effects", "source", "field"),
    [
        ([{"sepia": {}}], None, "effects[0].sepia"),
        ([{"exposure": {"factor": -0.1}}], None, "effects[0].exposure.factor"),
        ([], {"procedural": {**TINY, "n_train": 0}}, "source.procedural.n_train"),
        ([], {"capture": {"path": "no/such/scene"}}, "source.capture.path"),
        (
            [{"quantize": {}}, {"jpeg": {"quality": 90}}, {"noise": {"read_std": "lots"}}],
            None,
            "effects[2].noise.read_std",
        ),
    ],
)
def test_bad_specs_fail_with_one_line_naming_file_and_field(tmp_path, effects, source, field):
    path = write_spec(tmp_path, effects, source=source)
    with pytest.raises(SimSpecError) as err:
        load_spec(path)
    message = str(err.value)
    assert "\n" not in message and str(path) in message and f"'{field}'" in message


def test_cli_reports_spec_errors_on_one_line(tmp_path, monkeypatch, capsys):
    path = write_spec(tmp_path, [{"sepia": {}}])
    monkeypatch.setattr("sys.argv", ["naka-gs-sim", str(path), "--out", str(tmp_path / "o")])
    with pytest.raises(SystemExit) as exit_info:
        cli.entrypoint()
    code = exit_info.value.code  # a str: Python prints it on stderr and exits 1
    assert isinstance(code, str) and code.startswith("naka-gs: ") and "\n" not in code and "effects[0].sepia" in code
    assert not capsys.readouterr().err


def test_shipped_specs_load(monkeypatch):
    monkeypatch.chdir(REPO)
    names = {load_spec(p).name for p in shipped_specs()}
    assert {"clean", "dark", "dark-noisy", "night-lamps", "lom-sofa-dark"} <= names


def test_shipped_capture_spec_generates(tmp_path, monkeypatch):
    monkeypatch.chdir(REPO)
    scene = cli.Sim(spec=Path("configs/scenes/lom-sofa-dark.yaml"), out=tmp_path / "sofa").main()
    outputs = LowLightDataParserConfig(data=scene, downscale_factor=1).setup().get_dataparser_outputs("train")
    assert len(outputs.image_filenames) == 16
    train = train_images(scene)
    assert 0.01 < train.mean() < 0.08  # real low-light range of mean sRGB values
    source = manifest(scene)["train_views"][0]["source_image"]
    assert Path(source).parent.name == "high"
    truth = read_rgb(scene / "train_gt" / "0000.png", np.float64)
    assert truth.mean() > 5 * train[0].mean()


def test_stats_noise_lines_recover_the_declared_model(tmp_path):
    noise = {"shot_gain": 1e-3, "read_std": 0.01}
    spec = load_spec(write_spec(tmp_path, [{"noise": noise}]))  # linear 16-bit files: stored = sensor values
    a, b = (generate(spec, tmp_path / f"seed{s}", seed=s) for s in (0, 1))
    pairs = [(p, b / "train" / p.name) for p in sorted((a / "train").iterdir())]
    slope, intercept = stats.seed_noise_line(pairs)  # of the grey image: a third of the channel variance
    assert abs(3 * slope / noise["shot_gain"] - 1) < 0.2 and abs(3 * intercept / noise["read_std"] ** 2 - 1) < 0.3

    rng = np.random.default_rng(0)
    ramp = np.repeat(np.linspace(0.05, 0.8, 256)[None, :, None], 256, 0).repeat(3, 2)
    flat = np.clip(ramp + rng.normal(size=ramp.shape) * np.sqrt(1e-3 * ramp + 1e-4), 0, 1)
    cv2.imwrite(str(tmp_path / "flat.png"), np.round(flat * 65535).astype(np.uint16))
    row = stats.image_stats(tmp_path / "flat.png")
    assert abs(row.mean - ramp.mean()) < 1e-3 and row.saturated_pct < 0.5
    # grey = mean of 3 independent channels: a third of the per-channel variance
    assert abs(row.noise_std_at_mean / np.sqrt((1e-3 * ramp.mean() + 1e-4) / 3) - 1) < 0.25
