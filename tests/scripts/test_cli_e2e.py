"""End-to-end tests of the stock nerfstudio CLIs with the naka-gs plugin, on the CPU.

Every test drives the real console scripts (``ns-train``, ``ns-eval``, ``ns-export``, ``ns-render``,
``ns-viewer``) in subprocesses on the tiny toy scene, exactly as a user would. Trainings are kept
to a few dozen iterations of 2000 random Gaussians at 64x48, so the module runs in a few minutes on
two cores; each ``ns-*`` process spends ~8 s importing torch and nerfstudio.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional

import pytest
import torch

pytestmark = pytest.mark.slow  # every test here runs ns-* commands in subprocesses

BIN = Path(sys.executable).parent
NUM_RANDOM = 2000
TRAIN_STEPS = 30

# Shared by every ns-train call: tiny, CPU, no blocking viewer, frequent checkpoints.
TRAIN_FLAGS = [
    "--pipeline.model.num-random", str(NUM_RANDOM),
    "--vis", "tensorboard",
    "--viewer.quit-on-train-completion", "True",
    "--steps-per-save", "10",
    "--timestamp", "run",  # deterministic run folder: <output-dir>/<scene name>/naka-gs/run
]  # fmt: skip
# Evaluate one image every 10 steps (cheap at 64x48): the no-ground-truth test checks it is skipped there.
EVAL_FLAGS = ["--steps-per-eval-image", "10"]


# ---------------------------------------------------------------------------------------- helpers
def _env(cache: Optional[Path] = None, torch_home: Optional[Path] = None) -> Dict[str, str]:
    env = dict(os.environ)
    env["TORCHDYNAMO_DISABLE"] = "1"
    env["PYTHONUNBUFFERED"] = "1"
    if cache is not None:
        env["NAKA_GS_CACHE"] = str(cache)
    if torch_home is not None:
        env["TORCH_HOME"] = str(torch_home)
    return env


def _cmd(script: str, *args: str) -> List[str]:
    exe = BIN / script
    assert exe.exists(), f"console script {exe} not found (is nerfstudio installed in this venv?)"
    return [str(exe), *args]


@dataclass
class Result:
    rc: int
    out: str  # stdout + stderr, interleaved
    seconds: float

    def tail(self, n: int = 4000) -> str:
        return f"rc={self.rc} after {self.seconds:.1f}s; output tail:\n{self.out[-n:]}"


def _run(cmd: List[str], cwd: Path, env: Dict[str, str], timeout: float) -> Result:
    t0 = time.monotonic()
    proc = subprocess.run(
        cmd, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=timeout
    )
    return Result(proc.returncode, proc.stdout, time.monotonic() - t0)


def _flat(text: str) -> str:
    """nerfstudio's rich console wraps at 120 columns; compare on whitespace-normalized text."""
    return " ".join(text.split())


def _ckpt_step(path: Path) -> int:
    return int(re.fullmatch(r"step-(\d+)\.ckpt", path.name).group(1))  # type: ignore[union-attr]


def _ckpts(ckpt_dir: Path) -> List[Path]:
    return sorted(ckpt_dir.glob("step-*.ckpt"), key=_ckpt_step) if ckpt_dir.is_dir() else []


def _strict_json(text: str):
    def reject(token: str):
        raise ValueError(f"non-standard JSON constant {token!r}")

    return json.loads(text, parse_constant=reject)


def _scalar_tags(run_dir: Path) -> List[str]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run_dir))
    acc.Reload()
    return list(acc.Tags()["scalars"])


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _train(data: Path, output_dir: Path, cwd: Path, env: Dict[str, str], steps: int, *extra: str) -> Result:
    cmd = _cmd(
        "ns-train", "naka-gs", "--max-num-iterations", str(steps), "--output-dir", str(output_dir),
        *TRAIN_FLAGS, *extra, "--data", str(data),
    )  # fmt: skip
    return _run(cmd, cwd=cwd, env=env, timeout=420)


# ---------------------------------------------------------------------------------------- fixtures
@dataclass
class TrainRun:
    result: Result
    run_dir: Path  # <output>/<experiment>/naka-gs/run
    config: Path
    work: Path


@pytest.fixture(scope="module")
def trained(toy_scene, tmp_path_factory) -> TrainRun:
    """One 30-step ``ns-train naka-gs`` on the toy scene, shared by the module (not asserted here)."""
    work = tmp_path_factory.mktemp("e2e_train")
    env = _env(cache=work / "naka-cache")
    result = _train(toy_scene, work / "outputs", work, env, TRAIN_STEPS, *EVAL_FLAGS)
    run_dir = work / "outputs" / toy_scene.name / "naka-gs" / "run"
    return TrainRun(result, run_dir, run_dir / "config.yml", work)


@pytest.fixture
def config_yml(trained) -> Path:
    """The trained config.yml; errors out (with the training log) if that training failed."""
    assert trained.result.rc == 0 and trained.config.exists(), "ns-train failed:\n" + trained.result.tail()
    return trained.config


# ---------------------------------------------------------------------------------------- 1. train
def test_train_writes_checkpoint_transforms_and_logs_torch_rasterizer(trained):
    res = trained.result
    assert res.rc == 0, res.tail()
    assert "Traceback" not in res.out, res.tail()
    assert trained.config.is_file(), f"no config.yml at {trained.config}\n" + res.tail()

    ckpts = _ckpts(trained.run_dir / "nerfstudio_models")
    assert ckpts, f"no nerfstudio_models/step-*.ckpt under {trained.run_dir}\n" + res.tail()
    # Steps are 0-based: a 30-iteration run ends with (and, keeping only the latest, leaves) step 29.
    assert _ckpt_step(ckpts[-1]) == TRAIN_STEPS - 1, [p.name for p in ckpts]

    transforms = _strict_json((trained.run_dir / "dataparser_transforms.json").read_text())
    assert set(transforms) >= {"transform", "scale"}, transforms
    assert len(transforms["transform"]) == 3 and all(len(row) == 4 for row in transforms["transform"])
    assert math.isfinite(transforms["scale"]) and transforms["scale"] > 0

    assert re.search(r"rasterizer: torch\b", res.out), "log does not report the 'torch' rasterizer\n" + res.tail()


# ---------------------------------------------------------------------------------------- 2. eval
def test_eval_writes_strict_json_with_psnr_ssim_and_lpips_offline(config_yml, tmp_path):
    torch_home = tmp_path / "torch-home"  # empty: no torchvision download; LPIPS uses the shipped weights
    out = tmp_path / "eval.json"
    res = _run(
        _cmd("ns-eval", "--load-config", str(config_yml), "--output-path", str(out)),
        cwd=config_yml.parents[4],
        env=_env(torch_home=torch_home),
        timeout=300,
    )
    assert res.rc == 0, res.tail()
    assert out.is_file(), "ns-eval wrote no JSON\n" + res.tail()
    text = out.read_text()
    try:
        doc = _strict_json(text)
    except ValueError as err:
        pytest.fail(f"{out} is not strict JSON ({err}):\n{text}")
    results = doc["results"]
    for key in ("psnr", "ssim", "lpips"):
        assert isinstance(results.get(key), (int, float)) and math.isfinite(results[key]), results
    assert 0.0 < results["psnr"] < 100.0 and -1.0 <= results["ssim"] <= 1.0 and 0.0 < results["lpips"] < 1.5, results
    assert not (torch_home / "hub" / "checkpoints").exists(), "LPIPS fetched weights instead of using the shipped ones"


# ---------------------------------------------------------------------------------------- 3. export
def test_export_gaussian_splat_ply_matches_checkpoint(config_yml, tmp_path):
    """The 3DGS PLY fields other viewers read (nerfstudio 1.1.5's exporter, ``--ply-color-mode sh_coeffs``), each
    with the checkpoint's values."""
    import numpy as np
    import open3d as o3d
    from plyfile import PlyData

    out_dir = tmp_path / "export"
    res = _run(
        _cmd("ns-export", "gaussian-splat", "--load-config", str(config_yml), "--output-dir", str(out_dir)),
        cwd=config_yml.parents[4],
        env=_env(),
        timeout=300,
    )
    assert res.rc == 0, res.tail()
    plys = sorted(out_dir.glob("*.ply"))
    assert len(plys) == 1, f"expected one PLY in {out_dir}, got {plys}\n" + res.tail()

    cloud = o3d.io.read_point_cloud(str(plys[0]))
    points = np.asarray(cloud.points)

    ckpt = _ckpts(config_yml.parent / "nerfstudio_models")[-1]
    state = torch.load(ckpt, map_location="cpu", weights_only=False)
    means = state["pipeline"]["_model.gauss_params.means"]
    assert points.shape == (means.shape[0], 3), (
        f"PLY has {points.shape[0]} points, checkpoint {means.shape[0]} Gaussians"
    )
    np.testing.assert_allclose(points, means.numpy(), rtol=0, atol=1e-6)

    vertex = PlyData.read(str(plys[0]))["vertex"]
    params = {k.rpartition(".")[2]: v.numpy() for k, v in state["pipeline"].items() if "gauss_params" in k}
    n_rest = params["features_rest"].shape[1] * 3
    assert [p.name for p in vertex.properties] == (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(n_rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )
    as_columns = {  # the exporter's layout: f_rest channel-major (the reference implementation's order)
        "f_dc": params["features_dc"],
        "f_rest": params["features_rest"].transpose(0, 2, 1).reshape(len(means), -1),
        "opacity": params["opacities"],
        "scale": params["scales"],
        "rot": params["quats"],
    }
    for prefix, expected in as_columns.items():
        names = [p.name for p in vertex.properties if p.name == prefix or p.name.startswith(prefix + "_")]
        got = np.stack([vertex[name] for name in names], axis=1)
        np.testing.assert_allclose(got, expected.reshape(len(means), -1), rtol=0, atol=1e-6, err_msg=prefix)


# ---------------------------------------------------------------------------------------- 4. render
def test_render_dataset_test_split_writes_two_images(config_yml, tmp_path):
    from PIL import Image

    out_dir = tmp_path / "renders"
    res = _run(
        _cmd(
            "ns-render",
            "dataset",
            "--load-config",
            str(config_yml),
            "--split",
            "test",
            "--output-path",
            str(out_dir),
            "--rendered-output-names",
            "rgb",
        ),  # fmt: skip
        cwd=config_yml.parents[4],
        env=_env(),
        timeout=300,
    )
    assert res.rc == 0, res.tail()
    images = sorted(p for p in out_dir.rglob("*") if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
    assert len(images) == 2, f"expected 2 rendered test images, got {images}\n" + res.tail()
    for path in images:
        with Image.open(path) as im:
            assert im.size == (64, 48), (path, im.size)


def test_render_interpolate_writes_a_video_with_the_ffmpeg_pip_installed(config_yml, tmp_path):
    """With no ffmpeg on PATH (folders holding one left out), ns-render of a naka-gs run writes its video with
    imageio-ffmpeg's binary: 3 steps between the 2 test cameras, at half the 64x48 scene."""
    import imageio_ffmpeg

    env = _env()
    env["PATH"] = os.pathsep.join(d for d in env["PATH"].split(os.pathsep) if not (Path(d) / "ffmpeg").exists())
    out = tmp_path / "interpolate.mp4"
    res = _run(
        _cmd(
            "ns-render",
            "interpolate",
            "--load-config",
            str(config_yml),
            "--output-path",
            str(out),
            "--interpolation-steps",
            "3",
            "--frame-rate",
            "3",
            "--downscale-factor",
            "2",
        ),  # fmt: skip
        cwd=config_yml.parents[4],
        env=env,
        timeout=300,
    )
    assert res.rc == 0, res.tail()
    assert out.is_file(), f"ns-render wrote no {out}\n" + res.tail()
    frames = imageio_ffmpeg.read_frames(str(out))
    meta = next(frames)
    assert tuple(meta["size"]) == (32, 24), meta
    assert sum(len(frame) == 32 * 24 * 3 for frame in frames) == 3
    assert imageio_ffmpeg.count_frames_and_secs(str(out))[0] == 3


# ---------------------------------------------------------------------------------------- 5. viewer
def _wait_http_200(url: str, proc: subprocess.Popen, log: Path, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            pytest.fail(f"ns-viewer exited early (rc={proc.returncode}):\n{log.read_text()[-4000:]}")
        try:
            with urllib.request.urlopen(url, timeout=2) as resp:
                if resp.status == 200:
                    return
                last = resp.status
        except (urllib.error.URLError, ConnectionError, OSError) as err:
            last = err
        time.sleep(0.5)
    pytest.fail(f"{url} did not answer 200 within {timeout}s (last: {last!r}):\n{log.read_text()[-4000:]}")


def _request_rendered_frame(port: int, timeout: float) -> bytes:
    """Act as a browser: send viser a camera pose and wait for the viewer's rendered background image.

    viser 0.2.7 speaks msgpack over the websocket: the client sends one message dict per frame
    (``Message.as_serializable_dict``, with a ``type`` key); the server (client_api_version=1) sends
    frames that are msgpack arrays of such dicts. nerfstudio renders once a camera message arrives
    and ships the image as a ``BackgroundImageMessage``.
    """
    import msgspec
    from viser import _messages as vm
    from websockets.sync.client import connect

    def camera(z: float) -> bytes:
        msg = vm.ViewerCameraMessage(
            wxyz=(1.0, 0.0, 0.0, 0.0),
            position=(0.0, 0.0, z),
            fov=1.0,
            aspect=64 / 48,
            look_at=(0.0, 0.0, 0.0),
            up_direction=(0.0, 1.0, 0.0),
        )
        return msgspec.msgpack.encode(msg.as_serializable_dict())

    seen: List[str] = []
    deadline = time.monotonic() + timeout
    with connect(f"ws://127.0.0.1:{port}", max_size=None, open_timeout=30) as ws:
        ws.send(camera(3.0))
        sends = 1
        next_send = time.monotonic() + 5.0
        while time.monotonic() < deadline:
            if time.monotonic() > next_send:  # camera moves retrigger a render (e.g. if sent before "ready")
                ws.send(camera(3.0 + 0.1 * sends))
                sends += 1
                next_send = time.monotonic() + 5.0
            try:
                raw = ws.recv(timeout=max(0.1, min(next_send, deadline) - time.monotonic()))
            except TimeoutError:
                continue
            assert isinstance(raw, bytes), f"viser sent a text frame: {raw[:200]!r}"
            batch = msgspec.msgpack.decode(raw)
            for message in batch if isinstance(batch, list) else [batch]:
                seen.append(message.get("type", "?"))
                if message.get("type") == "BackgroundImageMessage":
                    return message["rgb_bytes"]
    raise AssertionError(f"no BackgroundImageMessage within {timeout}s; got {len(seen)} messages: {sorted(set(seen))}")


def test_viewer_serves_http_and_renders_a_frame_over_websocket(config_yml, tmp_path):
    import io

    from PIL import Image

    port = _free_port()
    log = tmp_path / "viewer.log"
    cmd = _cmd(
        "ns-viewer", "--load-config", str(config_yml),
        "--viewer.websocket-host", "127.0.0.1", "--viewer.websocket-port", str(port),
    )  # fmt: skip
    with open(log, "w") as fh:
        proc = subprocess.Popen(cmd, cwd=config_yml.parents[4], env=_env(), stdout=fh, stderr=subprocess.STDOUT)
    try:
        _wait_http_200(f"http://127.0.0.1:{port}/", proc, log, timeout=120)
        try:
            frame = _request_rendered_frame(port, timeout=60)
        except AssertionError as err:
            raise AssertionError(f"{err}\nviewer log tail:\n{log.read_text()[-4000:]}") from None
        with Image.open(io.BytesIO(frame)) as im:
            im.load()
            assert im.width > 0 and im.height > 0 and im.mode in ("RGB", "L"), (im.size, im.mode)
        assert re.search(r"rasterizer: torch\b", log.read_text()), log.read_text()[-4000:]

        proc.terminate()
        try:
            rc = proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            pytest.fail("ns-viewer did not stop within 30 s of SIGTERM")
        assert rc is not None and proc.poll() is not None
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=30)


# ---------------------------------------------------------------------------------------- 6. resume
def _loads(path: Path) -> bool:
    try:
        torch.load(path, map_location="cpu", weights_only=False)
        return True
    except Exception:  # noqa: BLE001 - a half-written zip raises various errors
        return False


def test_resume_after_sigkill_continues_from_checkpoint(toy_scene, tmp_path):
    env = _env()
    out = tmp_path / "outputs"
    cmd = _cmd(
        "ns-train", "naka-gs", "--max-num-iterations", "400", "--output-dir", str(out),
        *TRAIN_FLAGS, "--data", str(toy_scene),
    )  # fmt: skip
    ckpt_dir = out / toy_scene.name / "naka-gs" / "run" / "nerfstudio_models"
    log = tmp_path / "killed.log"
    with open(log, "w") as fh:
        proc = subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=fh, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 240
        while True:
            if proc.poll() is not None:
                pytest.fail(f"training exited (rc={proc.returncode}) before a checkpoint:\n{log.read_text()[-4000:]}")
            if time.monotonic() > deadline:
                pytest.fail(f"no step>=10 checkpoint within 240 s:\n{log.read_text()[-4000:]}")
            if any(_ckpt_step(p) >= 10 for p in _ckpts(ckpt_dir)):
                # Freeze the trainer, and kill it only while its newest checkpoint is complete: nerfstudio
                # writes checkpoints in place (not atomically), so a kill mid-write would leave a torn file.
                proc.send_signal(signal.SIGSTOP)
                if _loads(_ckpts(ckpt_dir)[-1]):
                    proc.send_signal(signal.SIGKILL)
                    break
                proc.send_signal(signal.SIGCONT)
            time.sleep(0.2)
        assert proc.wait(timeout=30) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=30)

    latest = _ckpts(ckpt_dir)[-1]
    resumed_from = _ckpt_step(latest)
    assert 10 <= resumed_from < 399, latest

    # nerfstudio counts --max-num-iterations from the loaded step (trainer.py: range(start, start + n)),
    # so 10 more iterations end at resumed_from + 10.
    out2 = tmp_path / "resumed"
    res = _run(
        _cmd(
            "ns-train",
            "naka-gs",
            "--max-num-iterations",
            "10",
            "--output-dir",
            str(out2),
            *TRAIN_FLAGS,
            "--load-dir",
            str(ckpt_dir),
            "--data",
            str(toy_scene),
        ),  # fmt: skip
        cwd=tmp_path,
        env=env,
        timeout=420,
    )
    assert res.rc == 0, res.tail()
    # rich folds long paths mid-word at 120 columns: match with all whitespace removed (paths have none here).
    loaded = re.sub(r"\s+", "", f"Done loading Nerfstudio checkpoint from {latest}")
    assert loaded in re.sub(r"\s+", "", res.out), f"log does not say it loaded {latest}\n" + res.tail()
    new_ckpts = _ckpts(out2 / toy_scene.name / "naka-gs" / "run" / "nerfstudio_models")
    assert new_ckpts, "resumed run wrote no checkpoint\n" + res.tail()
    assert _ckpt_step(new_ckpts[-1]) == resumed_from + 10, ([p.name for p in new_ckpts], resumed_from)
    state = torch.load(new_ckpts[-1], map_location="cpu", weights_only=False)
    assert state["step"] == resumed_from + 10
    assert torch.isfinite(state["pipeline"]["_model.gauss_params.means"]).all()


# ---------------------------------------------------------------------------------------- 7. no test images
def test_scene_without_test_images_trains_and_eval_fails_cleanly(toy_scene, trained, tmp_path):
    scene = tmp_path / "no_test_scene"
    shutil.copytree(toy_scene, scene)
    shutil.rmtree(scene / "test")
    env = _env()

    res = _train(scene, tmp_path / "outputs", tmp_path, env, 10, *EVAL_FLAGS)
    assert res.rc == 0, res.tail()
    flat = _flat(res.out)
    assert "Traceback" not in res.out and "MissingGroundTruthError" not in res.out, res.tail()
    assert "no ground-truth images" in flat, res.tail()
    run_dir = tmp_path / "outputs" / scene.name / "naka-gs" / "run"
    # Evaluation was scheduled (every 10 steps, as in the `trained` run) but never attempted:
    # the with-ground-truth run logged eval metrics, this one logged none.
    tags = _scalar_tags(run_dir)
    assert "Train Loss" in tags, tags
    assert not [t for t in tags if t.startswith(("Eval", "Test"))], tags
    if trained.result.rc == 0:  # positive control: the same schedule does evaluate with ground truth
        assert any(t.startswith("Eval Images Metrics") for t in _scalar_tags(trained.run_dir))

    eval_json = tmp_path / "eval.json"
    ev = _run(
        _cmd("ns-eval", "--load-config", str(run_dir / "config.yml"), "--output-path", str(eval_json)),
        cwd=tmp_path,
        env=env,
        timeout=300,
    )
    assert ev.rc != 0, "ns-eval succeeded on a scene without ground truth\n" + ev.tail()
    assert "no ground-truth images" in _flat(ev.out), ev.tail()
    assert "FileNotFoundError" not in ev.out, ev.tail()
    assert not eval_json.exists()
