"""A run folder you can trust (issue 36, part A): what loads a run, what may write into one, and signals.

One row per case. Each bad case asserts its one ``naka-gs:`` line and that every file that existed before is
byte-identical after. Runs are trained in-process through nerfstudio's own ``ns-train`` main (what the
console script calls after parsing), on the 64x48 toy scene; the commands that load a run are driven
through their script classes, which all call nerfstudio's ``eval_setup`` as the console scripts do. One
``ns-eval`` subprocess checks the real command prints no traceback.
"""

from __future__ import annotations

import ast
import hashlib
import importlib
import inspect
import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path
from typing import Dict

import numpy as np
import pytest
import yaml
from nerfstudio.scripts import exporter
from nerfstudio.scripts import train as ns_train
from nerfstudio.utils import eval_utils

from naka_gs_plugin.enhance.stages import NakaStage
from naka_gs_plugin.errors import UserError, user_error_exit
from naka_gs_plugin.trainer import INTERRUPTED_EXIT_CODE, NakaGSTrainer, NakaGSTrainerConfig
from tests.helpers import tiny_run_config

BIN = Path(sys.executable).parent


# ---------------------------------------------------------------------------------------- helpers
def _config(scene: Path, out: Path, steps: int = 20, **overrides) -> NakaGSTrainerConfig:
    """:func:`tiny_run_config`, saving every 10 steps."""
    return tiny_run_config(scene, out, steps, **{"steps_per_save": 10, **overrides})


def _train(config: NakaGSTrainerConfig) -> Path:
    ns_train.main(config)
    return config.get_base_dir()


def _snapshot(*folders: Path) -> Dict[Path, str]:
    """sha256 of every file under ``folders``."""
    return {
        path: hashlib.sha256(path.read_bytes()).hexdigest()
        for folder in folders
        for path in sorted(folder.rglob("*"))
        if path.is_file()
    }


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _naka_lines(text: str) -> list:
    return [line for line in text.splitlines() if line.startswith("naka-gs:")]


@pytest.fixture(scope="module")
def run(toy_scene, tmp_path_factory) -> Path:
    """A 20-step run (checkpoints of steps 10 and 19); read-only by convention (copy it to change it)."""
    work = tmp_path_factory.mktemp("run_folder")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("NAKA_GS_CACHE", str(work / "cache"))
        return _train(_config(toy_scene, work / "outputs"))


def _copy_run(run: Path, dst: Path) -> Path:
    shutil.copytree(run, dst)
    return dst


# ---------------------------------------------------------------------------------------- 1. truncated newest
@pytest.fixture(scope="module")
def truncated(toy_scene, tmp_path_factory) -> Path:
    """A run whose newest checkpoint (step 19) was cut in half; step 10 is intact. Read-only by convention."""
    work = tmp_path_factory.mktemp("truncated")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("NAKA_GS_CACHE", str(work / "cache"))
        run = _train(_config(toy_scene, work / "outputs"))
    _truncate(run / "nerfstudio_models" / "step-000000019.ckpt")
    return run


def test_loading_skips_a_truncated_newest_checkpoint(truncated, capsys):
    before = _snapshot(truncated)
    _, _, path, step = eval_utils.eval_setup(truncated / "config.yml")
    models = truncated / "nerfstudio_models"
    assert (path, step) == (models / "step-000000010.ckpt", 10)
    assert _naka_lines(capsys.readouterr().out) == [
        f"naka-gs: skipping corrupt or truncated step-000000019.ckpt in {models}; loading step-000000010.ckpt"
    ]
    assert _snapshot(truncated) == before


@pytest.mark.slow  # one ns-eval subprocess
def test_ns_eval_cli_skips_it_without_a_traceback(truncated, tmp_path):
    before = _snapshot(truncated)
    out = tmp_path / "eval.json"
    res = subprocess.run(
        [str(BIN / "ns-eval"), "--load-config", str(truncated / "config.yml"), "--output-path", str(out)],
        cwd=tmp_path,
        env=dict(os.environ, TORCHDYNAMO_DISABLE="1", NAKA_GS_CACHE=str(tmp_path / "cache")),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        timeout=300,
    )
    assert res.returncode == 0 and "Traceback" not in res.stdout, res.stdout[-3000:]
    models = truncated / "nerfstudio_models"
    assert (
        f"naka-gs: skipping corrupt or truncated step-000000019.ckpt in {models}; loading step-000000010.ckpt"
        in _naka_lines(res.stdout)
    ), res.stdout[-3000:]
    assert yaml.safe_load(out.read_text())["checkpoint"] == str(models / "step-000000010.ckpt")
    assert _snapshot(truncated) == before


def test_no_valid_checkpoint_is_one_line_and_ns_export_leaves_no_folder(truncated, tmp_path, capsys):
    run = _copy_run(truncated, tmp_path / "run")
    _truncate(run / "nerfstudio_models" / "step-000000010.ckpt")
    before = _snapshot(run)
    out = tmp_path / "export"
    with pytest.raises(SystemExit) as exc:
        exporter.ExportGaussianSplat(load_config=run / "config.yml", output_dir=out).main()
    models = run / "nerfstudio_models"
    assert str(exc.value) == (
        f"naka-gs: {models}: every checkpoint there is corrupt or truncated "
        "(step-000000019.ckpt, step-000000010.ckpt); nothing to load: train this run again"
    )
    assert not out.exists()
    assert _snapshot(run) == before

    # ns-render and ns-viewer load through the same eval_setup: the same line, nothing written.
    from nerfstudio.scripts.render import DatasetRender
    from nerfstudio.scripts.viewer.run_viewer import RunViewer

    renders = tmp_path / "renders"
    for command in (DatasetRender(load_config=run / "config.yml", output_path=renders), RunViewer(run / "config.yml")):
        with pytest.raises(SystemExit) as again:
            command.main()
        assert str(again.value) == str(exc.value)
    assert not renders.exists()
    assert _snapshot(run) == before

    for ckpt in models.iterdir():
        ckpt.unlink()
    with pytest.raises(SystemExit) as exc:
        eval_utils.eval_setup(run / "config.yml")
    assert str(exc.value) == (
        f"naka-gs: {models}: no step-*.ckpt checkpoint there; train this run first, "
        "or load the config.yml of a run that saved one"
    )


# ---------------------------------------------------------------------------------------- 2. copied run
def test_a_copied_run_loads_its_own_checkpoints(run, tmp_path, capsys):
    """config.yml records the original's absolute output path; the copy must not load the original's
    (intact) step 19 but its own, whose step 19 is truncated here: its step 10."""
    copied = _copy_run(run, tmp_path / "copy")
    _truncate(copied / "nerfstudio_models" / "step-000000019.ckpt")
    before = _snapshot(run, copied)
    config, _, path, step = eval_utils.eval_setup(copied / "config.yml")
    assert (path, step) == (copied / "nerfstudio_models" / "step-000000010.ckpt", 10)
    assert config.get_base_dir() == copied  # ns-viewer's log and render tab use the copy too
    assert _naka_lines(capsys.readouterr().out) == [
        f"naka-gs: {copied / 'config.yml'} records its run folder as {run}; using the folder it is in, {copied} "
        "(a copied or moved run loads its own checkpoints)",
        f"naka-gs: skipping corrupt or truncated step-000000019.ckpt in {copied / 'nerfstudio_models'}; "
        "loading step-000000010.ckpt",
    ]
    assert _snapshot(run, copied) == before


# ---------------------------------------------------------------------------------------- 3. same timestamp
def _clash(folder: Path) -> str:
    models = folder / "nerfstudio_models"
    return (
        f"naka-gs: {folder} already holds a run (its config.yml); resume it with --load-dir {models} or pick "
        "another --timestamp -- with --load-config these flags are ignored (every option comes from the file): "
        f"set load_dir: {models} in that file to resume, or change the timestamp: line in a copy for a new run"
    )


def test_a_second_run_into_the_same_folder_is_refused_and_resuming_it_works(run, toy_scene, tmp_path):
    outputs = tmp_path / "outputs"
    folder = _copy_run(run, outputs / toy_scene.name / "naka-gs" / "run")
    before = _snapshot(folder)
    with pytest.raises(SystemExit) as exc:
        _train(_config(toy_scene, outputs))
    models = folder / "nerfstudio_models"
    assert str(exc.value) == _clash(folder)
    assert _snapshot(folder) == before

    assert _train(_config(toy_scene, outputs, steps=21, load_dir=models)) == folder  # one step: 20
    after = _snapshot(folder)
    assert (models / "step-000000020.ckpt").is_file()
    assert {p: h for p, h in after.items() if p in before and p.name != "config.yml"} == {
        p: h for p, h in before.items() if p.name != "config.yml"
    }


def test_load_config_of_an_existing_run_is_refused_with_advice_that_works(run, toy_scene, tmp_path, capsys):
    """``ns-train naka-gs --load-config <run>/config.yml``: ns-train takes every option from the file (the run
    folder included) and ignores the command line's, so "another --timestamp" cannot help; the file edits the
    refusal names do."""
    outputs = tmp_path / "outputs"
    folder = _copy_run(run, outputs / toy_scene.name / "naka-gs" / "run")
    config = yaml.load((folder / "config.yml").read_text(), Loader=yaml.Loader)
    config.output_dir = outputs  # the copy's config.yml records the copy's folder, as a run trained there does
    (folder / "config.yml").write_text(yaml.dump(config))
    before = _snapshot(folder)
    elsewhere = tmp_path / "elsewhere"
    with pytest.raises(SystemExit) as exc:  # the flags next to --load-config are ignored by ns-train
        _train(_config(toy_scene, elsewhere, timestamp="other", load_config=folder / "config.yml"))
    assert exc.value.code == _clash(folder)
    captured = capsys.readouterr()
    assert "Traceback" not in captured.out + captured.err
    assert _snapshot(folder) == before and not elsewhere.exists()

    # The advice works: load_dir: in the file resumes that run; another timestamp: in a copy starts a new one.
    models = folder / "nerfstudio_models"
    text = (folder / "config.yml").read_text().replace("max_num_iterations: 20", "max_num_iterations: 1")  # fast
    resume, other = tmp_path / "resume.yml", tmp_path / "other.yml"
    resume.write_text(text.replace("load_dir: null", f"load_dir: {models}"))
    other.write_text(text.replace("timestamp: run", "timestamp: run2"))
    ns_train.main(_config(toy_scene, elsewhere, load_config=resume))
    assert (models / "step-000000020.ckpt").is_file()  # resumed after step 19, in that run's folder
    assert {p: h for p, h in _snapshot(folder).items() if p in before and p.name != "config.yml"} == {
        p: h for p, h in before.items() if p.name != "config.yml"
    }
    ns_train.main(_config(toy_scene, elsewhere, load_config=other))
    assert not elsewhere.exists()
    assert sorted(p.name for p in (folder.parent / "run2" / "nerfstudio_models").iterdir()) == ["step-000000000.ckpt"]


# ---------------------------------------------------------------------------------------- 6. bad inputs
def test_ns_eval_without_ground_truth_is_one_line(run, toy_scene, tmp_path):
    scene = shutil.copytree(toy_scene, tmp_path / "no_test_images")
    shutil.rmtree(scene / "test")
    copied = _copy_run(run, tmp_path / "run")
    config = yaml.load((copied / "config.yml").read_text(), Loader=yaml.Loader)
    config.data = config.pipeline.datamanager.data = config.pipeline.datamanager.dataparser.data = scene
    (copied / "config.yml").write_text(yaml.dump(config))
    before = _snapshot(copied, scene)
    from nerfstudio.scripts.eval import ComputePSNR

    out = tmp_path / "eval.json"
    with pytest.raises(SystemExit) as exc:  # a SystemExit: the console script prints its message, no traceback
        ComputePSNR(load_config=copied / "config.yml", output_path=out).main()
    assert str(exc.value) == (
        f"naka-gs: {scene}: the 'test' split has no ground-truth images (its transforms json points at missing "
        "files), so there is nothing to evaluate against -- use a scene with test images (e.g. LOM, or a "
        "naka-gs-sim scene) for metrics"
    )
    assert not out.exists()
    assert _snapshot(copied, scene) == before


def test_an_image_broken_after_training_is_one_line_in_ns_eval_and_ns_render(run, toy_scene, tmp_path, capsys):
    """A test image truncated after training is read after eval_setup (ns-eval's metrics, ns-render's loop):
    one ``naka-gs:`` line naming it (exit status 1), no traceback."""
    scene = shutil.copytree(toy_scene, tmp_path / "scene")
    image = scene / json.loads((scene / "transforms_test.json").read_text())["frames"][0]["file_path"]
    _truncate(image)
    copied = _copy_run(run, tmp_path / "outputs" / toy_scene.name / "naka-gs" / "run")
    config = yaml.load((copied / "config.yml").read_text(), Loader=yaml.Loader)
    config.data = config.pipeline.datamanager.data = config.pipeline.datamanager.dataparser.data = scene
    config.output_dir = tmp_path / "outputs"  # as if trained there: the only naka-gs line is the image's
    (copied / "config.yml").write_text(yaml.dump(config))
    before = _snapshot(copied, scene)
    from nerfstudio.scripts.eval import ComputePSNR
    from nerfstudio.scripts.render import DatasetRender

    out = tmp_path / "out"
    for command in (
        ComputePSNR(load_config=copied / "config.yml", output_path=out / "eval.json"),
        DatasetRender(load_config=copied / "config.yml", output_path=out, split="test"),
    ):
        with pytest.raises(SystemExit) as exc:  # the console script prints its message: exit status 1
            command.main()
        assert exc.value.code == (
            f"naka-gs: {image}: unreadable image (truncated, corrupt or not a PNG/JPEG/TIFF) -- restore the complete "
            "file (copy it again from the camera or backup) or remove it from the scene"
        ), type(command).__name__
    captured = capsys.readouterr()
    assert _naka_lines(captured.out + captured.err) == [] and "Traceback" not in captured.out + captured.err
    assert not out.exists()
    assert _snapshot(copied, scene) == before


def test_missing_data_is_one_line_and_leaves_no_run_folder(tmp_path):
    with pytest.raises(SystemExit) as exc:
        _train(_config(tmp_path / "nowhere", tmp_path / "outputs"))
    assert str(exc.value) == (
        f"naka-gs: --data {tmp_path / 'nowhere'}: no such scene folder; pass --data <folder with transforms_train.json>"
    )
    assert sorted(tmp_path.iterdir()) == []


def test_a_failed_setup_removes_only_the_run_folder_it_made(tmp_path):
    scene = tmp_path / "not_a_scene"
    scene.mkdir()
    outputs = tmp_path / "outputs"
    outputs.mkdir()
    (outputs / "keep.txt").write_text("the user's")
    before = _snapshot(tmp_path)
    with pytest.raises(SystemExit) as exc:  # the plugin's LowLightDataError, as one line
        _train(_config(scene, outputs))
    assert exc.value.code == (
        f"naka-gs: {scene / 'transforms_train.json'}: file not found -- every lowlight-data scene needs "
        "transforms_train.json and transforms_test.json"
    )
    assert sorted(p.name for p in outputs.iterdir()) == ["keep.txt"]
    assert _snapshot(tmp_path) == before


def test_user_errors_are_every_error_class_of_the_package():
    """Each ``*Error`` class in naka_gs_plugin is a user error (one line at the ns-* and naka-gs-* boundaries: a
    subclass of ``UserError``) or a SystemExit already."""
    package = Path(inspect.getfile(NakaGSTrainer)).parent
    found = set()
    for path in package.rglob("*.py"):
        module = ".".join(("naka_gs_plugin", *path.relative_to(package).with_suffix("").parts))
        found |= {
            f"{module}.{node.name}"
            for node in ast.walk(ast.parse(path.read_text()))
            if isinstance(node, ast.ClassDef) and node.name.endswith("Error")
        }
    assert "naka_gs_plugin.data.images.ImageReadError" in found  # the scan sees the package
    for name in sorted(found):
        module, _, cls = name.rpartition(".")
        error = getattr(importlib.import_module(module), cls)
        assert issubclass(error, (UserError, SystemExit)), f"{name}: subclass UserError (or SystemExit)"
        if issubclass(error, UserError):
            err = error.__new__(error)  # without the arguments some take besides the message
            BaseException.__init__(err, "bad --option -- fix it")
            assert user_error_exit(err).code == "naka-gs: bad --option -- fix it", name


def test_a_plugin_error_is_one_line_in_ns_train_and_when_loading_a_run(run, toy_scene, tmp_path, monkeypatch, capsys):
    """The plugin's own errors (a bad scene, an unreadable image...) reach the user as one ``naka-gs:`` line
    (SystemExit: exit status 1, no traceback), from ns-train's first step and from eval_setup (ns-eval,
    ns-render, ns-export, ns-viewer); any other exception is a bug and keeps its traceback."""
    # ns-train: an unreadable training image, found when the first step loads the images.
    scene = Path(shutil.copytree(toy_scene, tmp_path / "scene"))
    image = scene / json.loads((scene / "transforms_train.json").read_text())["frames"][0]["file_path"]
    image.write_bytes(image.read_bytes()[:50])
    before = _snapshot(scene)
    with pytest.raises(SystemExit) as exc:
        _train(_config(scene, tmp_path / "outputs"))
    assert exc.value.code == (
        f"naka-gs: {image}: unreadable image (truncated, corrupt or not a PNG/JPEG/TIFF) -- restore the complete "
        "file (copy it again from the camera or backup) or remove it from the scene"
    )
    assert _snapshot(scene) == before

    # Loading a run whose scene was moved away after training: config.yml is where ns-eval & co. find it.
    trained_on = Path(shutil.copytree(toy_scene, tmp_path / "trained_on"))
    copied = _copy_run(run, tmp_path / "run")
    config = yaml.load((copied / "config.yml").read_text(), Loader=yaml.Loader)
    config.data = config.pipeline.datamanager.data = config.pipeline.datamanager.dataparser.data = trained_on
    (copied / "config.yml").write_text(yaml.dump(config))
    shutil.move(trained_on, tmp_path / "moved_away")
    before = _snapshot(copied)
    expected = (
        f"naka-gs: {copied / 'config.yml'} records --data {trained_on}, and no scene folder is there (moved or deleted "
        "since training): move the scene back there, or edit the data: path at the top of that config.yml"
    )
    from nerfstudio.scripts.eval import ComputePSNR
    from nerfstudio.scripts.render import DatasetRender
    from nerfstudio.scripts.viewer.run_viewer import RunViewer

    out = tmp_path / "loaded"
    for command in (
        ComputePSNR(load_config=copied / "config.yml", output_path=out / "eval.json"),
        exporter.ExportGaussianSplat(load_config=copied / "config.yml", output_dir=out),
        DatasetRender(load_config=copied / "config.yml", output_path=out),
        RunViewer(copied / "config.yml"),
    ):
        with pytest.raises(SystemExit) as exc:
            command.main()
        assert exc.value.code == expected, type(command).__name__
    assert not out.exists()  # ns-export removed the folder it had made
    captured = capsys.readouterr()
    assert "Traceback" not in captured.out + captured.err
    assert _snapshot(copied) == before

    # A bug is not a user error: its own exception, with its traceback.
    from naka_gs_plugin.data.lowlight_dataparser import LowLightDataParser

    def bug(self, split="train", **kwargs):
        raise ValueError("a bug")

    monkeypatch.setattr(LowLightDataParser, "_generate_dataparser_outputs", bug)
    with pytest.raises(ValueError, match="a bug"):
        _train(_config(toy_scene, tmp_path / "outputs2"))
    with pytest.raises(ValueError, match="a bug"):
        eval_utils.eval_setup(copied / "config.yml")


def _bad_option(weights: Path) -> Dict[str, tuple]:
    """Rows of the test below: (config overrides, the one line ns-train ends with)."""
    naka = "--pipeline.datamanager.enhance.correction"
    fix = f"or pass {naka} default (the shipped weights) or none (Naka only)"
    lpips_fix = "pass torchvision's alexnet-owt-7be5be79.pth or leave the option out (weights ship with naka-gs)"
    return {
        "sigma": (
            {"pipeline.datamanager.enhance.sigma": -1.0},
            "naka-gs: --pipeline.datamanager.enhance.sigma must be > 0 or auto, got -1.0 (default 0.05)",
        ),
        "correction weights missing": (
            {"pipeline.datamanager.enhance.correction": str(weights / "nope.pt")},
            f"naka-gs: correction weights {weights / 'nope.pt'} not found (no such file): pass {naka} none "
            "(Naka only) or the path of a checkpoint",
        ),
        "correction weights corrupt": (  # found when the first step enhances the training images
            {"pipeline.datamanager.enhance.correction": str(weights / "corrupt.pt")},
            f"naka-gs: {naka} {weights / 'corrupt.pt'} is not a readable torch checkpoint (UnpicklingError): "
            f"re-save it with torch.save -- {fix}",
        ),
        "lpips weights bad": (
            {"pipeline.model.lpips_weights": weights / "cut.pth"},
            f"naka-gs: --pipeline.model.lpips-weights {weights / 'cut.pth'}: not a readable torch weights file "
            f"(RuntimeError) -- {lpips_fix}",
        ),
        "rasterizer": (  # found at the first render
            {"pipeline.model.rasterizer": "gsplat"},
            "naka-gs: rasterizer 'gsplat' needs CUDA tensors but the model is on cpu -- use "
            "--pipeline.model.rasterizer cpu-fast, torch or auto",
        ),
        "sh degree": (  # in use only after 4 * sh_degree_interval steps: refused at the first render instead
            {"pipeline.model.sh_degree": 4},
            "naka-gs: --pipeline.model.sh-degree 4: the cpu-fast rasterizer supports degrees 0..3 -- use "
            "--pipeline.model.sh-degree 3 or less",
        ),
    }


@pytest.mark.parametrize("row", sorted(_bad_option(Path("w"))))
def test_a_bad_option_or_weights_file_is_one_line_in_ns_train(row, toy_scene, tmp_path, capsys):
    """A bad ``--pipeline.*`` value or weights file ends ns-train with one ``naka-gs:`` line naming the option (exit
    status 1, no traceback), before or at the first step; the scene and the files named are left as they were."""
    weights = tmp_path / "weights"
    weights.mkdir()
    (weights / "corrupt.pt").write_bytes(b"not a torch checkpoint")
    (weights / "cut.pth").write_bytes(b"PK\x03\x04" + b"\0" * 100)  # a zip header, then nothing: a cut-off download
    overrides, expected = _bad_option(weights)[row]
    config = _config(toy_scene, tmp_path / "outputs", steps=2)
    for dotted, value in overrides.items():
        *parents, name = dotted.split(".")
        target = config
        for parent in parents:
            target = getattr(target, parent)
        setattr(target, name, value)
    before = _snapshot(toy_scene, weights)
    with pytest.raises(SystemExit) as exc:
        _train(config)
    assert exc.value.code == expected
    captured = capsys.readouterr()
    assert "Traceback" not in captured.out + captured.err
    assert _snapshot(toy_scene, weights) == before


def test_unwritable_output_dir_is_one_line(toy_scene, tmp_path, monkeypatch):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    if os.geteuid() == 0:  # root writes anywhere: refuse it as a read-only folder would
        real_mkdir = Path.mkdir

        def mkdir(self, *args, **kwargs):
            if locked in self.parents:
                raise PermissionError(13, "Permission denied", str(self))
            return real_mkdir(self, *args, **kwargs)

        monkeypatch.setattr(Path, "mkdir", mkdir)
    before = _snapshot(toy_scene)
    try:
        with pytest.raises(SystemExit) as exc:
            _train(_config(toy_scene, locked / "outputs"))
    finally:
        locked.chmod(0o755)
    run = locked / "outputs" / toy_scene.name / "naka-gs" / "run"
    assert str(exc.value) == (
        f"naka-gs: cannot write the run folder {run} (Permission denied); pick a writable --output-dir"
    )
    assert list(locked.iterdir()) == []
    assert _snapshot(toy_scene) == before


# ---------------------------------------------------------------------------------------- 7. signals, temp files
def test_sigterm_finishes_the_step_saves_and_exits_as_ctrl_c(toy_scene, tmp_path, monkeypatch, capsys):
    real_step_done = NakaGSTrainer._step_done

    def step_done(self, step):
        if step == 2:
            os.kill(os.getpid(), signal.SIGTERM)  # handled at the next bytecode, inside this step's callbacks
        real_step_done(self, step)

    monkeypatch.setattr(NakaGSTrainer, "_step_done", step_done)
    handler = signal.getsignal(signal.SIGTERM)
    before = _snapshot(toy_scene)
    with pytest.raises(SystemExit) as exc:
        _train(_config(toy_scene, tmp_path / "outputs", steps=1000, steps_per_save=1000))
    assert exc.value.code == 143  # 128 + SIGTERM (Ctrl-C: 130)
    assert signal.getsignal(signal.SIGTERM) == handler  # restored
    models = tmp_path / "outputs" / toy_scene.name / "naka-gs" / "run" / "nerfstudio_models"
    saved = models / "step-000000002.ckpt"
    assert _naka_lines(capsys.readouterr().out)[-2:] == [
        "naka-gs: SIGTERM: finishing step 2, then saving a checkpoint (SIGTERM again: quit without saving)",
        f"naka-gs: interrupted; step 2 saved to {saved} (resume with --load-dir {models} --max-num-iterations 997 "
        "to end at the same step)",
    ]
    assert sorted(p.name for p in models.iterdir()) == [saved.name]
    assert _snapshot(toy_scene) == before


def test_ctrl_c_while_enhancing_stops_after_the_image_in_hand(toy_scene, tmp_path, monkeypatch, capsys):
    calls = []
    real_apply = NakaStage.apply

    def apply(self, image, low):
        calls.append(1)
        if len(calls) == 3:  # Ctrl-C while the third of eight images is enhanced
            os.kill(os.getpid(), signal.SIGINT)
        return real_apply(self, image, low)

    monkeypatch.setattr(NakaStage, "apply", apply)
    before = _snapshot(toy_scene)
    # Ctrl-C as in a terminal: a suite started in the background (`cmd &` in a script) inherits SIGINT ignored,
    # which the trainer rightly leaves ignored.
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(SystemExit) as exc:
            _train(_config(toy_scene, tmp_path / "outputs", steps=1000))
    finally:
        signal.signal(signal.SIGINT, previous)
    assert exc.value.code == INTERRUPTED_EXIT_CODE
    assert len(calls) == 3  # not the whole stage
    assert _naka_lines(capsys.readouterr().out)[-1] == (
        "naka-gs: Ctrl-C before the first training step finished, nothing to save (enhanced images already "
        "cached are kept); this run saved no checkpoint"
    )
    cached = sorted((tmp_path / "naka-cache" / "enhanced").iterdir())
    assert len(cached) == 2 and all(p.suffix == ".npy" for p in cached), cached  # no partial file
    assert all(np.load(p).shape == (48, 64, 3) for p in cached)
    assert _snapshot(toy_scene) == before


@pytest.mark.slow  # a Python subprocess: the removal happens at its exit
def test_a_fallback_cache_in_the_temp_folder_is_removed_at_exit(tmp_path):
    not_a_folder = tmp_path / "cache-is-a-file"
    not_a_folder.write_text("")
    temp = tmp_path / "temp"
    temp.mkdir()
    code = "from naka_gs_plugin.data.cache import default_cache_dir; d = default_cache_dir(); print(d, d.is_dir())"
    res = subprocess.run(
        [sys.executable, "-c", code],
        env=dict(os.environ, NAKA_GS_CACHE=str(not_a_folder), TMPDIR=str(temp)),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        timeout=120,
    )
    assert res.returncode == 0, res.stdout
    fallback = Path(res.stdout.split()[-2])
    assert res.stdout.split()[-1] == "True" and fallback.parent == temp, res.stdout
    assert list(temp.iterdir()) == []
