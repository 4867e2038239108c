"""Training state is safe (``naka_gs_plugin.trainer.NakaGSTrainer``).

Ctrl-C on a real ``ns-train`` saves the current step and exits 130; checkpoints are published atomically;
resuming skips a truncated or damaged checkpoint for the newest valid older one, and fails with one
line when none is valid. Two ``ns-train`` subprocesses on the toy scene (~10 s each to import); the rest
runs in-process on stub trainers.
"""

from __future__ import annotations

import copy
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
import yaml
from nerfstudio.engine.trainer import Trainer, TrainerConfig
from nerfstudio.utils import writer
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from naka_gs_plugin.trainer import (
    INTERRUPTED_EXIT_CODE,
    PARTIAL_PREFIX,
    LoggedStepsTensorboardWriter,
    NakaGSTrainer,
    checkpoint_step,
)
from tests.helpers import upstream_sha256

NS_TRAIN = Path(sys.executable).parent / "ns-train"
STEPS_PER_SAVE = 1000  # far beyond where the test interrupts: any checkpoint is the Ctrl-C one

# sha256 of the upstream (nerfstudio 1.1.5) methods NakaGSTrainer mirrors or relies on: the checkpoint dict
# (save_checkpoint), the --load-checkpoint branch (_load_checkpoint), the stop_training checks and the
# _after_train call (train), and the wait for Ctrl-C after training (_train_complete_viewer).
UPSTREAM_SHA256 = {
    "save_checkpoint": "dd69315ca38c457d64664979e430fd76be50d8d835d1c50e7fe905f35ce3fca6",
    "_load_checkpoint": "5019d2cbbacd0c13f6a6c2fe80548c583e1a39c3ff3cc352831b89cb4a75239a",
    "train": "3494f834a9252d41ff9947bb433bf3080cbc58581af550556a14ea00155d34e2",
    "_train_complete_viewer": "e536f431958844a09e334e70a7e5f22293544ec6666df3724af3600521a52484",
}


def _env() -> dict:
    return dict(os.environ, TORCHDYNAMO_DISABLE="1", PYTHONUNBUFFERED="1")


def _ns_train(scene: Path, out: Path, steps: int, *extra: str) -> list:
    return [
        str(NS_TRAIN), "naka-gs", "--max-num-iterations", str(steps), "--output-dir", str(out),
        "--pipeline.model.num-random", "2000", "--vis", "tensorboard", "--viewer.quit-on-train-completion", "True",
        "--steps-per-save", str(STEPS_PER_SAVE), "--timestamp", "run", *extra, "--data", str(scene),
    ]  # fmt: skip


def _naka_lines(text: str) -> list:
    return [line for line in text.splitlines() if line.startswith("naka-gs:")]


@dataclass
class Interrupted:
    rc: int
    log: str
    ckpt_dir: Path


@pytest.fixture(scope="module")
def interrupted(toy_scene, tmp_path_factory) -> Interrupted:
    """A 2000-step ``ns-train`` sent SIGINT once its first training step is logged."""
    work = tmp_path_factory.mktemp("ctrl_c")
    log_path = work / "train.log"
    with open(log_path, "w") as log:
        # A shell without job control starts background jobs with SIGINT ignored, and ns-train (rightly)
        # keeps it ignored: give the child the default disposition a terminal's Ctrl-C meets.
        proc = subprocess.Popen(
            _ns_train(toy_scene, work / "out", 2000),
            cwd=work,
            env=_env(),
            stdout=log,
            stderr=subprocess.STDOUT,
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        )
    try:
        deadline = time.monotonic() + 120
        # nerfstudio's step table is first written after step 0 has run.
        while "Step (% Done)" not in log_path.read_text():
            assert proc.poll() is None, f"ns-train exited (rc={proc.returncode}) early:\n{log_path.read_text()}"
            assert time.monotonic() < deadline, f"no training step within 120 s:\n{log_path.read_text()}"
            time.sleep(0.1)
        proc.send_signal(signal.SIGINT)
        rc = proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    ckpt_dir = work / "out" / toy_scene.name / "naka-gs" / "run" / "nerfstudio_models"
    return Interrupted(rc, log_path.read_text(), ckpt_dir)


def _stub_trainer(tmp_path: Path, **config) -> NakaGSTrainer:
    """A NakaGSTrainer whose pipeline is a tiny module, enough for saving and choosing checkpoints."""
    trainer = TrainerConfig(
        _target=NakaGSTrainer, method_name="naka-gs", output_dir=tmp_path / "out", timestamp="run", **config
    ).setup()
    trainer.pipeline = torch.nn.Linear(2, 2)
    trainer.optimizers = SimpleNamespace(optimizers={}, schedulers={})
    trainer.grad_scaler = torch.amp.GradScaler("cpu", enabled=False)
    return trainer


def _truncated_copy(src: Path, dst: Path) -> Path:
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.write_bytes(src.read_bytes()[: src.stat().st_size // 2])
    return dst


def _flipped_copy(src: Path, dst: Path) -> Path:
    """Same size, one byte of tensor data inverted: torch.load would accept it silently."""
    data = bytearray(src.read_bytes())
    data[len(data) // 2] ^= 0xFF
    dst.write_bytes(bytes(data))
    return dst


# ------------------------------------------------------------------------------------- upstream pinning
@pytest.mark.parametrize("name", sorted(UPSTREAM_SHA256))
def test_upstream_trainer_methods_are_the_pinned_ones(name):
    digest = upstream_sha256(getattr(Trainer, name))
    assert digest == UPSTREAM_SHA256[name], (
        f"nerfstudio's Trainer.{name} changed (sha256 {digest}): re-check naka_gs_plugin/trainer.py against it, "
        "then update UPSTREAM_SHA256 in tests/test_trainer_safety.py"
    )


def test_method_config_targets_the_safe_trainer_and_survives_config_yml():
    from naka_gs_plugin.config import naka_gs_method

    config = naka_gs_method.config
    assert config._target is NakaGSTrainer
    # ns-eval / ns-viewer / ns-export read config.yml back with yaml.Loader (eval_utils.eval_setup).
    assert yaml.load(yaml.dump(config), Loader=yaml.Loader)._target is NakaGSTrainer


# ------------------------------------------------------------------------------------- 1. Ctrl-C
@pytest.mark.slow  # ns-train in a subprocess (the interrupted fixture)
def test_ctrl_c_saves_the_current_step_and_exits_130(interrupted):
    assert interrupted.rc == INTERRUPTED_EXIT_CODE, interrupted.log[-4000:]
    saved = [re.fullmatch(r"naka-gs: interrupted; step (\d+) saved to (\S+) \(resume with --load-dir (\S+)\)", line)
             for line in _naka_lines(interrupted.log)]  # fmt: skip
    saved = [m for m in saved if m]
    assert len(saved) == 1, interrupted.log[-4000:]
    step, path, load_dir = int(saved[0].group(1)), Path(saved[0].group(2)), Path(saved[0].group(3))
    assert path.parent == load_dir == interrupted.ckpt_dir and checkpoint_step(path) == step
    assert sorted(p.name for p in interrupted.ckpt_dir.iterdir()) == [path.name], "stray files next to the checkpoint"
    assert step < STEPS_PER_SAVE  # so no periodic save wrote it
    state = torch.load(path, map_location="cpu")  # as upstream's resume loads it
    assert state["step"] == step
    assert torch.isfinite(state["pipeline"]["_model.gauss_params.means"]).all()


# ------------------------------------------------------------------------------------- 2. atomic save
def test_failed_write_leaves_the_previous_checkpoint_and_no_partial_file(tmp_path, monkeypatch):
    trainer = _stub_trainer(tmp_path)
    trainer.save_checkpoint(1)
    first = trainer.checkpoint_dir / "step-000000001.ckpt"
    before = first.read_bytes()
    real_save = torch.save

    def disk_full(obj, fh):  # writes half a checkpoint, then fails like a full disk
        real_save(obj, fh)
        fh.truncate(fh.tell() // 2)
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(torch, "save", disk_full)
    with pytest.raises(SystemExit) as exc:
        trainer.save_checkpoint(2)
    message = str(exc.value)
    assert "\n" not in message and "step-000000002.ckpt not written" in message and "No space left" in message
    assert f"resume with --load-dir {trainer.checkpoint_dir}" in message
    assert sorted(p.name for p in trainer.checkpoint_dir.iterdir()) == [first.name]
    assert first.read_bytes() == before


def test_write_killed_before_publishing_is_ignored_by_resume_and_by_ns_eval(tmp_path):
    from nerfstudio.utils.eval_utils import eval_load_checkpoint

    trainer = _stub_trainer(tmp_path)
    trainer.save_checkpoint(1)
    pid = os.fork()
    if pid == 0:  # a child killed once step 2 is written, before it is published
        os.replace = lambda src, dst: os._exit(9)
        trainer.save_checkpoint(2)
        os._exit(0)
    assert os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1]) == 9
    names = sorted(p.name for p in trainer.checkpoint_dir.iterdir())
    assert names[0] == "step-000000001.ckpt" and len(names) == 2, names
    assert names[1].startswith(f"{PARTIAL_PREFIX}{pid}-") and names[1].endswith(".partial"), names

    resumed = _stub_trainer(tmp_path / "again", load_dir=trainer.checkpoint_dir)
    assert resumed.checkpoint_to_resume() == trainer.checkpoint_dir / "step-000000001.ckpt"
    # ns-eval / ns-viewer / ns-export parse every name in the folder and load the largest step.
    loaded = []
    config = SimpleNamespace(load_dir=trainer.checkpoint_dir, load_step=None)
    pipeline = SimpleNamespace(load_pipeline=lambda state, step: loaded.append(step))
    assert eval_load_checkpoint(config, pipeline)[1] == 1 and loaded == [1]


# ------------------------------------------------------------------------------------- 3. corrupt resume
@pytest.mark.slow  # ns-train in a subprocess (the interrupted fixture)
def test_resume_skips_a_truncated_latest_checkpoint(interrupted, toy_scene, tmp_path):
    valid = min(interrupted.ckpt_dir.glob("step-*.ckpt"))
    step = checkpoint_step(valid)
    folder = tmp_path / "nerfstudio_models"
    folder.mkdir()
    shutil.copy(valid, folder / valid.name)
    newer = _truncated_copy(valid, folder / f"step-{step + 500:09d}.ckpt")
    res = subprocess.run(
        _ns_train(toy_scene, tmp_path / "out", 1, "--load-dir", str(folder)),
        cwd=tmp_path, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=300,
    )  # fmt: skip
    assert res.returncode == 0, res.stdout[-4000:]
    skipped = f"naka-gs: skipping corrupt or truncated {newer.name} in {folder}; resuming from {valid.name}"
    assert skipped in _naka_lines(res.stdout), res.stdout[-4000:]
    resumed = tmp_path / "out" / toy_scene.name / "naka-gs" / "run" / "nerfstudio_models"
    assert [p.name for p in resumed.glob("step-*.ckpt")] == [f"step-{step + 1:09d}.ckpt"], res.stdout[-4000:]


@pytest.mark.slow  # ns-train in a subprocess (the interrupted fixture)
def test_load_checkpoint_falls_back_past_a_damaged_file(interrupted, tmp_path, capsys):
    valid = min(interrupted.ckpt_dir.glob("step-*.ckpt"))
    folder = tmp_path / "models"
    folder.mkdir()
    shutil.copy(valid, folder / "step-000000001.ckpt")
    damaged = _flipped_copy(valid, folder / "step-000000007.ckpt")
    _truncated_copy(valid, folder / "step-000000009.ckpt")  # newer than the one asked for: never considered
    trainer = _stub_trainer(tmp_path, load_checkpoint=damaged)
    assert trainer.checkpoint_to_resume() == folder / "step-000000001.ckpt"
    out = " ".join(capsys.readouterr().out.split())
    assert f"skipping corrupt or truncated {damaged.name} in {folder}; resuming from step-000000001.ckpt" in out


@pytest.mark.slow  # ns-train in a subprocess (the interrupted fixture)
def test_no_valid_checkpoint_is_one_line_naming_the_folder_and_the_fix(interrupted, tmp_path):
    valid = min(interrupted.ckpt_dir.glob("step-*.ckpt"))
    folder = tmp_path / "models"
    _truncated_copy(valid, folder / "step-000000003.ckpt")
    _flipped_copy(valid, folder / "step-000000002.ckpt")
    with pytest.raises(SystemExit) as exc:
        _stub_trainer(tmp_path, load_dir=folder).checkpoint_to_resume()
    assert str(exc.value) == (
        f"naka-gs: --load-dir {folder}: every checkpoint there is corrupt or truncated "
        "(step-000000003.ckpt, step-000000002.ckpt); resume from another run's nerfstudio_models folder, "
        "or train from scratch without --load-dir"
    )

    with pytest.raises(SystemExit) as exc:
        _stub_trainer(tmp_path, load_dir=tmp_path / "nowhere").checkpoint_to_resume()
    assert str(exc.value) == (
        f"naka-gs: --load-dir {tmp_path / 'nowhere'}: no step-*.ckpt checkpoint there; "
        "point it at a run's nerfstudio_models folder"
    )


# ------------------------------------------------------------------------------------- 4. resumed training
def _toy_trainer(scene: Path, out: Path, steps: int, **config) -> NakaGSTrainer:
    """The ``naka-gs`` method's trainer on ``scene``, in this process, built as ``ns-train`` builds it."""
    from naka_gs_plugin.config import naka_gs_method

    cfg = copy.deepcopy(naka_gs_method.config)
    cfg.pipeline.datamanager.data = scene
    cfg.pipeline.model.num_random = 500
    settings = dict(output_dir=out, timestamp="run", vis="tensorboard", max_num_iterations=steps, steps_per_save=steps,
                    steps_per_eval_image=10**9, steps_per_eval_all_images=10**9)  # fmt: skip
    settings.update(config)
    for key, value in settings.items():
        setattr(cfg, key, value)
    trainer = cfg.setup(local_rank=0, world_size=1)
    trainer.setup(test_mode="val")
    return trainer


def test_a_resumed_run_keeps_optimizing_its_gaussians_with_their_adam_state(toy_scene, tmp_path):
    first = _toy_trainer(toy_scene, tmp_path / "a", 3)
    first.train()
    folder = first.checkpoint_dir
    saved = torch.load(max(folder.glob("step-*.ckpt")), map_location="cpu", weights_only=False)
    resumed = _toy_trainer(toy_scene, tmp_path / "b", 1, load_dir=folder)
    model, optimizers = resumed.pipeline.model, resumed.optimizers.optimizers
    for name, param in model.gauss_params.items():
        bound = optimizers[name].param_groups[0]["params"]
        assert len(bound) == 1 and bound[0] is param, f"the {name} optimizer steps a tensor the model does not use"
        moments = optimizers[name].state[param]["exp_avg"]
        torch.testing.assert_close(moments, saved["optimizers"][name]["state"][0]["exp_avg"], rtol=0, atol=0)
    before = model.means.detach().clone()
    resumed.train()
    assert not torch.equal(model.means.detach(), before), "the resumed step left the Gaussians where they were"


def test_evaluating_during_training_does_not_change_what_is_trained(toy_scene, tmp_path):
    """The evaluation cadence is a time lever only: seeded as ``ns-train`` seeds, the same Gaussians bit for
    bit whether the test views are rendered and scored every step or never."""
    from nerfstudio.scripts.train import _set_random_seed

    trained = []
    for name, cadence in (("watched", dict(steps_per_eval_image=1, steps_per_eval_all_images=4)), ("unwatched", {})):
        _set_random_seed(42)
        trainer = _toy_trainer(toy_scene, tmp_path / name, 12, **cadence)
        trainer.train()
        trained.append(trainer.pipeline.model.gauss_params)
    for name, param in trained[0].items():
        torch.testing.assert_close(param, trained[1][name], rtol=0, atol=0)


# ------------------------------------------------------------------------------------- 5. event writers
def test_upstream_event_writer_setup_is_the_pinned_one():
    """NakaGSTrainer.setup swaps nerfstudio's TensorboardWriter for LoggedStepsTensorboardWriter where
    ``writer.setup_event_writer`` makes it, by its module-level name."""
    digest = upstream_sha256(writer.setup_event_writer)
    assert digest == "e4ebc1768b0fe904ad1a607dab77dfdd18d0915272b3483c422162517a09d7d3", (
        f"nerfstudio's writer.setup_event_writer changed (sha256 {digest}): re-check NakaGSTrainer.setup against it"
    )


def test_tensorboard_gets_the_per_step_scalars_at_the_logged_steps_only(toy_scene, tmp_path):
    trainer = _toy_trainer(toy_scene, tmp_path, 25)  # --logging.steps-per-log 10: losses at steps 0, 10 and 20
    trainer.train()
    log_dir = trainer.base_dir / trainer.config.logging.relative_log_dir
    ours = [w for w in writer.EVENT_WRITERS if hasattr(w, "tb_writer") and Path(w.tb_writer.log_dir) == log_dir]
    (tb,) = ours
    assert isinstance(tb, LoggedStepsTensorboardWriter)
    tb.write_scalar("Test PSNR", 20.0, 5)  # not a per-step scalar: written at any step
    tb.tb_writer.flush()
    events = EventAccumulator(str(log_dir))
    events.Reload()
    steps = {tag: [event.step for event in events.Scalars(tag)] for tag in events.Tags()["scalars"]}
    assert steps["Train Loss"] == [0, 10, 20]
    for tag in ("Train Iter (time)", "ETA (time)", "learning_rate/means", "learning_rate/appearance"):
        assert steps[tag] == [0, 10, 20], tag
    assert steps["Train Rays / Sec"] == [10, 20]  # upstream records it from step 2 on
    assert steps["Test PSNR"] == [5]
