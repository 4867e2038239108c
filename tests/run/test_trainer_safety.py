"""Training state is safe (``naka_gs_plugin.trainer.NakaGSTrainer``).

Ctrl-C on a real ``ns-train`` saves the current step and exits 130; checkpoints are published atomically;
resuming skips a truncated or damaged checkpoint for the newest valid older one, and fails with one
line when none is valid; a run killed (``kill -9``, during a save too) and resumed ends bit for bit as the
uninterrupted run. Two ``ns-train`` subprocesses on the toy scene (~10 s each to import) and one Python
subprocess running five ``ns-train`` runs (the kills); the rest runs in-process, on stub trainers or the toy scene.
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

from naka_gs_plugin.run import nerfstudio_hooks
from naka_gs_plugin.run.checkpoints import PARTIAL_PREFIX, RESUME_STATE, checkpoint_step
from naka_gs_plugin.trainer import INTERRUPTED_EXIT_CODE, LoggedStepsTensorboardWriter, NakaGSTrainer
from tests.helpers import upstream_sha256

nerfstudio_hooks.activate()  # the checkpoints here are read as inside a naka-gs run, where the hooks are on

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
    # torch < 2.3 has only the CUDA module's scaler (what upstream's Trainer builds); disabled, it is the same.
    amp = torch.amp if hasattr(torch.amp, "GradScaler") else torch.cuda.amp
    trainer.grad_scaler = amp.GradScaler(**({"device": "cpu"} if amp is torch.amp else {}), enabled=False)
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
        "then update UPSTREAM_SHA256 in tests/run/test_trainer_safety.py"
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
    saved = [re.fullmatch(r"naka-gs: interrupted; step (\d+) saved to (\S+) \(resume with --load-dir (\S+) "
                          r"--max-num-iterations (\d+) to end at the same step\)", line)
             for line in _naka_lines(interrupted.log)]  # fmt: skip
    saved = [m for m in saved if m]
    assert len(saved) == 1, interrupted.log[-4000:]
    step, path, load_dir = int(saved[0].group(1)), Path(saved[0].group(2)), Path(saved[0].group(3))
    assert step + int(saved[0].group(4)) == 2000 - 1  # the 2000-step run's last step
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


# ------------------------------------------------------------------------------------- 6. exact resume
EXACT_STEPS, EXACT_SAVE_EVERY = 40, 7
"""The resume runs: 40 steps saved every 7 (only the latest checkpoint kept, as by default). With refinement every 4
steps from step 12 (:func:`_exact_config`), the checkpoints of steps 14 and 21 fall between two refinements, where
the densification statistics hold two steps' gradients."""


def _exact_config(scene: Path, out: Path, steps: int, **overrides):
    """The naka-gs config as ``ns-train`` builds it, tiny and fast to densify: 500 random Gaussians refined every 4
    steps (gsplat grows and prunes them from step 12), one SH degree more every 10 steps, a test view evaluated every
    5 steps (it draws from Python's global generator)."""
    from naka_gs_plugin.config import naka_gs_method

    config = copy.deepcopy(naka_gs_method.config)
    config.data, config.output_dir, config.timestamp, config.vis = scene, out, "run", "tensorboard"
    config.max_num_iterations, config.steps_per_save = steps, EXACT_SAVE_EVERY
    config.steps_per_eval_image, config.steps_per_eval_all_images = 5, 10**6
    config.viewer.quit_on_train_completion = True
    config.pipeline.init.triangulate = False
    model = config.pipeline.model
    model.num_random, model.warmup_length, model.refine_every, model.sh_degree_interval = 500, 2, 4, 10
    for key, value in overrides.items():
        setattr(config, key, value)
    return config


def _resume_driver(spec_path: str) -> None:
    """Run the ``ns-train`` runs of ``spec_path`` (json) one after the other, each in a process of its own forked from
    this one (imported once, nothing computed yet), as ``nerfstudio.scripts.train.main`` runs them; a run may kill
    itself with SIGKILL after a given step or half-way through writing a given step's checkpoint. Writes each run's
    exit status and the files its checkpoint folder held before it started to ``spec["results"]``."""
    import json

    from nerfstudio.scripts import train as ns_train

    spec = json.loads(Path(spec_path).read_text())
    scene = Path(spec["scene"])
    results = []
    for run in spec["runs"]:
        out = Path(run["out"])
        models = out / scene.name / "naka-gs" / "run" / "nerfstudio_models"
        if run.get("partial_as_step") is not None:  # the partial file a kill left, as the newest step-*.ckpt
            (partial,) = models.glob(f"{PARTIAL_PREFIX}*.partial")
            shutil.copy(partial, models / f"step-{run['partial_as_step']:09d}.ckpt")
        before = sorted(p.name for p in models.iterdir()) if models.is_dir() else []
        pid = os.fork()
        if pid == 0:
            code = 1
            try:
                with open(run["log"], "w") as log:
                    os.dup2(log.fileno(), 1)
                    os.dup2(log.fileno(), 2)
                _arm_kill(run)
                extra = {"load_dir": models} if run.get("resume") else {}
                ns_train.main(_exact_config(scene, out, run["steps"], **extra))
                code = 0
            except SystemExit as exc:
                print(exc)
            except BaseException:
                import traceback

                traceback.print_exc()
            finally:
                sys.stdout.flush()
                os._exit(code)
        results.append({"rc": os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1]), "before": before})
    Path(spec["results"]).write_text(json.dumps(results))


def _arm_kill(run: dict) -> None:
    """In a driver's child: SIGKILL this process once step ``kill_after_step`` has finished (its checkpoint, if
    any, not yet written), or once half the checkpoint of step ``kill_saving_step`` is on disk."""
    if run.get("kill_after_step") is not None:
        real_step_done = NakaGSTrainer._step_done

        def step_done(self, step):
            real_step_done(self, step)
            if step == run["kill_after_step"]:
                os.kill(os.getpid(), signal.SIGKILL)

        NakaGSTrainer._step_done = step_done
    if run.get("kill_saving_step") is not None:
        real_save = torch.save

        def save(obj, fh, *args, **kwargs):
            real_save(obj, fh, *args, **kwargs)
            if isinstance(obj, dict) and obj.get("step") == run["kill_saving_step"]:
                fh.flush()
                fh.truncate(fh.tell() // 2)
                os.fsync(fh.fileno())
                os.kill(os.getpid(), signal.SIGKILL)

        torch.save = save


@pytest.mark.slow  # ns-train runs in one Python subprocess (~30 s)
def test_a_run_killed_and_resumed_ends_bit_identical_to_the_uninterrupted_run(toy_scene, tmp_path):
    """kill -9 after step 17 (the newest checkpoint: step 14), and kill -9 half-way through writing step 28's
    checkpoint (the newest complete one: step 21; the half-written file also copied as step-000000028.ckpt); each
    resumed with ``--load-dir`` for the remaining steps ends with the uninterrupted run's model, optimizer and
    scheduler states, bit for bit."""
    import json

    last = EXACT_STEPS - 1
    runs = [
        {"out": tmp_path / "whole", "steps": EXACT_STEPS},
        {"out": tmp_path / "killed", "steps": EXACT_STEPS, "kill_after_step": 17},
        {"out": tmp_path / "killed", "steps": last - 14, "resume": True},
        {"out": tmp_path / "cut", "steps": EXACT_STEPS, "kill_saving_step": 28},
        {"out": tmp_path / "cut", "steps": last - 21, "resume": True, "partial_as_step": 28},
    ]
    for i, run in enumerate(runs):
        run.update(out=str(run["out"]), log=str(tmp_path / f"run{i}.log"))
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps({"scene": str(toy_scene), "runs": runs, "results": str(tmp_path / "results.json")}))
    code = f"import sys; from tests.run.test_trainer_safety import _resume_driver; _resume_driver({str(spec)!r})"
    env = dict(_env(), PYTHONPATH=os.pathsep.join([str(Path(__file__).parents[2]), os.environ.get("PYTHONPATH", "")]))
    res = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT, text=True, timeout=600)  # fmt: skip
    assert res.returncode == 0, res.stdout[-4000:]
    results = json.loads((tmp_path / "results.json").read_text())
    logs = [Path(run["log"]).read_text() for run in runs]
    assert [r["rc"] for r in results] == [0, -signal.SIGKILL, 0, -signal.SIGKILL, 0], logs

    assert results[2]["before"] == ["step-000000014.ckpt"], logs[1][-4000:]
    (partial,) = [name for name in results[4]["before"] if name.endswith(".partial")]
    assert partial.startswith(PARTIAL_PREFIX) and results[4]["before"] == sorted(
        [partial, "step-000000021.ckpt", "step-000000028.ckpt"]
    ), logs[3][-4000:]
    models = tmp_path / "cut" / toy_scene.name / "naka-gs" / "run" / "nerfstudio_models"
    skipped = (
        f"naka-gs: skipping corrupt or truncated step-000000028.ckpt in {models}; resuming from step-000000021.ckpt"
    )
    assert skipped in _naka_lines(logs[4]), logs[4][-4000:]
    for log in logs[2], logs[4]:
        assert "Done loading Nerfstudio checkpoint" in log and not [line for line in _naka_lines(log)
                                                                    if "holds no" in line], log[-4000:]  # fmt: skip

    finals = [
        torch.load(Path(runs[i]["out"]) / toy_scene.name / "naka-gs" / "run" / "nerfstudio_models"
                   / f"step-{last:09d}.ckpt", map_location="cpu")
        for i in (0, 2, 4)
    ]  # fmt: skip
    whole = finals[0]
    assert whole["pipeline"]["_model.gauss_params.means"].shape[0] > 500, "the runs never densified"
    for resumed in finals[1:]:
        for part in ("pipeline", "optimizers", "schedulers", "scalers"):
            _assert_identical(resumed[part], whole[part], part)


@dataclass
class ShortRun:
    checkpoint: Path
    draws: tuple  # Python's, numpy's and torch's next random numbers after the checkpoint was written
    views: list  # the training views the datamanager serves next, in order
    strategy: dict  # the densification statistics


@pytest.fixture(scope="module")
def short_run(toy_scene, tmp_path_factory) -> ShortRun:
    """A 3-step run (its checkpoint: step 2), and what came after its checkpoint."""
    work = tmp_path_factory.mktemp("short_run")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("NAKA_GS_CACHE", str(work / "cache"))
        trainer = _toy_trainer(toy_scene, work, 3)
        trainer.train()
    (checkpoint,) = trainer.checkpoint_dir.glob("step-*.ckpt")
    datamanager, model = trainer.pipeline.datamanager, trainer.pipeline.model
    views = [datamanager.next_train(3 + i)[0].metadata["cam_idx"] for i in range(len(datamanager.train_dataset) + 3)]
    strategy = {k: v.clone() if isinstance(v, torch.Tensor) else v for k, v in model.strategy_state.items()}
    return ShortRun(checkpoint, _draws(), views, strategy)


def _draws() -> tuple:
    import random

    import numpy as np

    return random.random(), float(np.random.rand()), torch.rand(4).tolist()


def test_resuming_puts_back_the_random_state_view_order_and_densification_statistics(short_run, toy_scene, tmp_path):
    resumed = _toy_trainer(toy_scene, tmp_path, 1, load_dir=short_run.checkpoint.parent)
    assert _draws() == short_run.draws
    datamanager = resumed.pipeline.datamanager
    assert [datamanager.next_train(3 + i)[0].metadata["cam_idx"] for i in range(len(short_run.views))] == (
        short_run.views
    )
    strategy = resumed.pipeline.model.strategy_state
    assert strategy["grad2d"] is not None and set(strategy) == set(short_run.strategy)
    _assert_identical(strategy, short_run.strategy, "strategy_state")
    # Statistics of another number of Gaussians are refused, changing nothing.
    other = {k: v[:-1] if isinstance(v, torch.Tensor) else v for k, v in short_run.strategy.items()}
    assert resumed.pipeline.model.load_resume_state({"strategy": other}) is False
    _assert_identical(strategy, short_run.strategy, "strategy_state")


def test_a_checkpoint_without_the_resume_state_resumes_with_one_line(short_run, toy_scene, tmp_path, capsys):
    """A checkpoint of an older naka-gs (upstream's dict only) still resumes, saying in one line that the run will
    not continue exactly; the checkpoints it then writes carry the state again."""
    state = torch.load(short_run.checkpoint, map_location="cpu")  # as nerfstudio loads it
    assert set(state[RESUME_STATE]) == {"random", "datamanager", "model"}
    del state[RESUME_STATE]
    old = tmp_path / "old" / short_run.checkpoint.name
    old.parent.mkdir()
    torch.save(state, old)
    capsys.readouterr()
    resumed = _toy_trainer(toy_scene, tmp_path / "b", 1, load_dir=old.parent)
    assert _naka_lines(capsys.readouterr().out) == [
        f"naka-gs: {old} holds no random state, view order, densification statistics (saved by an older naka-gs): "
        "training resumes from step 3, but does not continue exactly as the interrupted run would have"
    ]
    before = resumed.pipeline.model.means.detach().clone()
    resumed.train()
    assert not torch.equal(resumed.pipeline.model.means.detach(), before)
    written = torch.load(resumed.checkpoint_dir / "step-000000003.ckpt", map_location="cpu")
    assert set(written[RESUME_STATE]) == {"random", "datamanager", "model"}


def _assert_identical(got, want, where: str) -> None:
    """Equal bit for bit: tensors by ``torch.equal`` (dtype and shape too), containers item by item."""
    if isinstance(want, torch.Tensor):
        assert isinstance(got, torch.Tensor) and got.dtype == want.dtype and torch.equal(got, want), where
    elif isinstance(want, dict):
        assert isinstance(got, dict) and sorted(got, key=str) == sorted(want, key=str), where
        for key in want:
            _assert_identical(got[key], want[key], f"{where}.{key}")
    elif isinstance(want, (list, tuple)):
        assert type(got) is type(want) and len(got) == len(want), where
        for i, (g, w) in enumerate(zip(got, want)):
            _assert_identical(g, w, f"{where}[{i}]")
    else:
        assert got == want, where
