"""Bad values as a user would pass them, one row per case: the one ``naka-gs:`` line and its exit status, or the
result, and every file that existed before byte-identical after (issue 72: D2, S4, R).

The pattern of tests/faults/test_bad_inputs.py (tests/bad_inputs.py's case types and runner): each case builds its
inputs under ``tmp`` (copies of the toy scene and of one trained run) and returns the action plus the paths that
must not change. The commands run in-process through their console entry points (``ns-train``, ``ns-eval``,
``ns-export``: tyro parses the same arguments), and an exception nobody catches is handed to ``sys.excepthook`` as
the interpreter would (:func:`uncaught`).
One slow test runs the real console scripts in subprocesses.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Callable, List, Tuple

import cv2
import numpy as np
import pytest
import yaml
from nerfstudio.scripts import eval as ns_eval_script
from nerfstudio.scripts import exporter
from nerfstudio.scripts import train as ns_train
from nerfstudio.utils import eval_utils

from naka_gs_plugin.config import METHODS
from naka_gs_plugin.data.lowlight_dataparser import LowLightDataError
from naka_gs_plugin.run.config_check import run_config_problem
from naka_gs_plugin.sim.toy_scene import ToySceneConfig, write_toy_scene
from tests.bad_inputs import Action, Case, Env, Exits, Ok, Raises, check_case, parse, snapshot
from tests.helpers import tiny_run_config

BIN = Path(sys.executable).parent


@pytest.fixture(scope="module")
def trained(toy_scene, tmp_path_factory) -> Path:
    """A 3-step run on the toy scene (8 training views; checkpoint step 2); read-only: rows copy it."""
    work = tmp_path_factory.mktemp("faults_values")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("NAKA_GS_CACHE", str(work / "cache"))
        config = tiny_run_config(toy_scene, work / "outputs", 3)
        ns_train.main(config)
    return config.get_base_dir()


def console(env: Env, entrypoint: Callable[[], None], argv: List[str]) -> Action:
    """The console script ``argv[0]`` as the interpreter runs it: :func:`uncaught` of its entry point."""

    def action():
        env.monkeypatch.setattr(sys, "argv", argv)
        uncaught(entrypoint)

    return action


def uncaught(action: Action) -> object:
    """``action()``; an exception it lets out goes to ``sys.excepthook`` and ends with exit status 1, as the
    interpreter does at the top of a console script."""
    try:
        return action()
    except (SystemExit, KeyboardInterrupt):
        raise
    except BaseException as exc:
        sys.excepthook(type(exc), exc, exc.__traceback__)
        raise SystemExit(1) from None


def replace(old: str, new: str) -> Callable[[str], str]:
    def edit(text: str) -> str:
        assert old in text, old
        return text.replace(old, new, 1)

    return edit


# --- R: scenes ---------------------------------------------------------------------------------------


def two_training_frames(env):
    """Two views (the simulator's two-view scene): both equally far from their centre; the spread check once took
    one of them, lower in x, y and z, for the centre and blamed the other."""
    s = write_toy_scene(env.tmp / "two", ToySceneConfig(n_train=2, n_test=1, width=64, height=48))
    config = tiny_run_config(s, env.tmp / "out", 3)

    def action():
        ns_train.main(config)
        return config.get_base_dir()

    return action, [s]


def _two_views_trained(env, base):
    models = base / "nerfstudio_models"
    assert [p.name for p in models.iterdir()] == ["step-000000002.ckpt"]
    _, pipeline, _, step = eval_utils.eval_setup(base / "config.yml")
    assert step == 2 and pipeline.model.num_train_data == 2


def one_pixel_scene(env):
    s = env.scene()
    path = s / "transforms_train.json"
    meta = json.loads(path.read_text())
    for frame in meta["frames"]:
        cv2.imwrite(str(s / frame["file_path"]), np.full((1, 1, 3), 20, np.uint8))
        frame.update(w=1, h=1, fl_x=1.0, fl_y=1.0, cx=0.5, cy=0.5)
    meta.update(w=1, h=1)
    path.write_text(json.dumps(meta))
    return lambda: ns_train.main(tiny_run_config(s, env.tmp / "out", 3)), [s]


def downscale_below_minimum(env):
    s = env.scene()
    return parse(s, factor=8), [s]


def symlink_loop_among_images(env):
    s = env.scene()
    frames = json.loads((s / "transforms_train.json").read_text())["frames"]
    a, b = s / frames[0]["file_path"], s / frames[1]["file_path"]
    a.unlink()
    b.unlink()
    os.symlink(b.name, a)  # train/0000.png -> 0001.png -> 0000.png
    os.symlink(a.name, b)
    return lambda: ns_train.main(tiny_run_config(s, env.tmp / "out", 3)), [s]


def _no_run_folder(env):
    assert not (env.tmp / "out").exists()


# --- R: ns-train's options ---------------------------------------------------------------------------


def train_with(env, **overrides) -> Tuple[Action, List[Path]]:
    s = env.scene()
    return lambda: ns_train.main(tiny_run_config(s, env.tmp / "out", 3, **overrides)), [s]


def max_iterations_zero(env):
    return train_with(env, max_num_iterations=0)


def max_iterations_negative(env):
    return train_with(env, max_num_iterations=-1)


def sh_degree_negative(env):
    return train_with(env, **{"pipeline.model.sh_degree": -1})


def sh_degree_absurd(env):
    return train_with(env, **{"pipeline.model.sh_degree": 9})


def sh_degree_negative_console(env):
    s = env.scene()
    argv = ["ns-train", "naka-gs", "--data", str(s), "--output-dir", str(env.tmp / "out")]
    return console(env, ns_train.entrypoint, argv + ["--pipeline.model.sh-degree", "-1"]), [s]


def load_dir_of_another_scenes_run(env):
    s, run = env.scene(n_train=3), env.run_copy()
    return lambda: ns_train.main(tiny_run_config(s, env.tmp / "out", 3, load_dir=run / "nerfstudio_models")), [s, run]


# --- S4 and R: a hand-edited config.yml ---------------------------------------------------------------


def ns_eval(env, run: Path) -> Action:
    argv = ["ns-eval", "--load-config", str(run / "config.yml"), "--output-path", str(env.tmp / "eval.json")]
    return console(env, ns_eval_script.entrypoint, argv)


def load_config(env, run: Path) -> Action:
    return console(env, ns_train.entrypoint, ["ns-train", "naka-gs", "--load-config", str(run / "config.yml")])


def config_typo_ns_eval(env):
    run = env.run_copy(edit=replace("sh_degree: 3", "sh_degre: 1"))
    return ns_eval(env, run), [run, env.toy]


def config_typo_ns_train_load_config(env):
    run = env.run_copy(edit=replace("sh_degree: 3", "sh_degre: 1"))
    return load_config(env, run), [run, env.toy]


def config_key_at_the_wrong_level(env):
    run = env.run_copy(edit=replace("max_num_iterations:", "sh_degree: 1\nmax_num_iterations:"))
    return ns_eval(env, run), [run]


def config_wrong_type(env):
    run = env.run_copy(edit=replace("sh_degree: 3", "sh_degree: three"))
    return ns_eval(env, run), [run]


def config_out_of_range_load_config(env):
    run = env.run_copy(edit=replace("max_num_iterations: 3", "max_num_iterations: -5"))
    return load_config(env, run), [run]


def config_not_yaml_ns_eval(env):
    run = env.run_copy(edit=lambda text: text.replace("sh_degree: 3", "sh_degree: [3"))
    return ns_eval(env, run), [run]


def config_not_yaml_load_config(env):
    run = env.run_copy(edit=lambda text: text.replace("sh_degree: 3", "sh_degree: [3"))
    return load_config(env, run), [run]


def config_empty_ns_eval(env):
    run = env.run_copy(edit=lambda text: "")
    return ns_eval(env, run), [run]


def config_empty_load_config(env):
    run = env.run_copy(edit=lambda text: "")
    return load_config(env, run), [run]


def config_not_a_run_config(env):
    run = env.run_copy(edit=lambda text: "scenes: [a, b]\n")
    return ns_eval(env, run), [run]


def config_data_points_at_a_scene_with_fewer_views(env):
    s = env.scene("three", n_train=3)
    run = env.run_copy()
    config = yaml.load((run / "config.yml").read_text(), Loader=yaml.Loader)
    config.data = config.pipeline.datamanager.data = config.pipeline.datamanager.dataparser.data = s
    (run / "config.yml").write_text(yaml.dump(config))
    return ns_eval(env, run), [run, s]


def config_data_as_a_plain_string(env):
    """A user who writes ``data: /my/scene`` writes a string where nerfstudio wrote a Path: taken as that path."""
    run = env.run_copy()
    config = yaml.load((run / "config.yml").read_text(), Loader=yaml.Loader)
    config.data = config.pipeline.datamanager.data = str(env.toy)
    (run / "config.yml").write_text(yaml.dump(config))
    return lambda: eval_utils.eval_setup(run / "config.yml")[0], [run, env.toy]


def _data_is_a_path(env, config):
    assert config.data == env.toy and isinstance(config.pipeline.datamanager.data, Path)


def presets_and_a_trained_run_have_no_problem(env):
    def action():
        loaded = yaml.load((env.run / "config.yml").read_text(), Loader=yaml.Loader)
        return [run_config_problem(spec.config, None) for spec in METHODS.values()] + [
            run_config_problem(loaded, env.run / "config.yml")
        ]

    return action, [env.run]


def _none(env, problems):
    assert problems == [None, None, None]


# --- D2 and R: ns-export -------------------------------------------------------------------------------


def ns_export(env, what: str, out: Path, *extra: str) -> Action:
    argv = ["ns-export", what, "--load-config", str(env.run / "config.yml"), "--output-dir", str(out), *extra]
    return console(env, exporter.entrypoint, argv)


def export_over_a_users_splat(env):
    out = env.tmp / "export"
    out.mkdir()
    (out / "splat.ply").write_text("the user's own splat")
    return ns_export(env, "gaussian-splat", out), [out, env.run]


def export_output_dir_is_a_file(env):
    out = env.tmp / "notes.txt"
    out.write_text("the user's notes")
    return ns_export(env, "gaussian-splat", out), [out, env.run]


def export_cameras_into_the_scene(env):
    s = env.scene()
    return ns_export(env, "cameras", s), [s, env.run]


def export_beside_other_files(env):
    """A folder holding other files (another export under another name) is fine: only splat.ply is written."""
    out = env.tmp / "export"
    out.mkdir()
    (out / "other.ply").write_text("another export")
    return ns_export(env, "gaussian-splat", out), [out / "other.ply", env.run]


def _exported(env, _):
    out = env.tmp / "export"
    assert sorted(p.name for p in out.iterdir()) == ["other.ply", "splat.ply"]
    assert (out / "splat.ply").read_bytes().startswith(b"ply\n")


def _export_left_nothing(env):
    assert not (env.tmp / "export").exists()


def export_with_a_bad_config_leaves_no_folder(env):
    run = env.run_copy(edit=replace("sh_degree: 3", "sh_degre: 1"))
    argv = ["ns-export", "gaussian-splat", "--load-config", str(run / "config.yml")]
    return console(env, exporter.entrypoint, argv + ["--output-dir", str(env.tmp / "export")]), [run]


CASES: List[Case] = [
    (two_training_frames, Ok(_two_views_trained)),
    (one_pixel_scene, Exits(1, "image size w x h = 1 x 1 px is under the 8 x 8 minimum", _no_run_folder)),
    (downscale_below_minimum, Raises(LowLightDataError, "downscale-factor 8: makes the images' shorter side 6 px")),
    (symlink_loop_among_images, Exits(1, "is a symbolic link that leads back to itself (a link loop)", _no_run_folder)),
    (max_iterations_zero, Exits(1, "--max-num-iterations 0: nothing to train; the number of training steps must")),
    (max_iterations_negative, Exits(1, "--max-num-iterations -1: the number of training steps must be at least 1")),
    (sh_degree_negative, Exits(1, "--pipeline.model.sh-degree -1: the spherical-harmonics degree must be 0 to 4")),
    (sh_degree_absurd, Exits(1, "--pipeline.model.sh-degree 9: the spherical-harmonics degree must be 0 to 4")),
    (sh_degree_negative_console, Exits(1, "e.g. --pipeline.model.sh-degree 3 (the default)", _no_run_folder)),
    (
        load_dir_of_another_scenes_run,
        Exits(1, "step-000000002.ckpt: was trained on a scene with 8 training views, and ", _no_run_folder),
    ),
    (config_typo_ns_eval, Exits(1, "unknown key pipeline.model.sh_degre (did you mean pipeline.model.sh_degree?)")),
    (config_typo_ns_train_load_config, Exits(1, "unknown key pipeline.model.sh_degre (did you mean")),
    (config_key_at_the_wrong_level, Exits(1, "unknown key sh_degree (it belongs under pipeline.model)")),
    (config_wrong_type, Exits(1, "pipeline.model.sh_degree is 'three', not a whole number -- write a whole")),
    (config_out_of_range_load_config, Exits(1, "max_num_iterations: -5 is out of range; the number of training")),
    (config_not_yaml_ns_eval, Exits(1, "not a readable YAML file (expected ',' or ']', but got ':' at line")),
    (config_not_yaml_load_config, Exits(1, "not a readable YAML file (expected ',' or ']'")),
    (config_empty_ns_eval, Exits(1, "config.yml: the file is empty -- it should hold the configuration")),
    (config_empty_load_config, Exits(1, "config.yml: the file is empty")),
    (config_not_a_run_config, Exits(1, "config.yml: holds dict, not a nerfstudio run configuration")),
    (
        config_data_points_at_a_scene_with_fewer_views,
        Exits(1, "was trained on a scene with 8 training views, and "),
    ),
    (config_data_as_a_plain_string, Ok(_data_is_a_path)),
    (presets_and_a_trained_run_have_no_problem, Ok(_none)),
    (export_over_a_users_splat, Exits(1, "export: already holds splat.ply, which would be replaced -- move it away")),
    (export_output_dir_is_a_file, Exits(1, "notes.txt: exists and is not a folder -- choose another --output-dir")),
    (export_cameras_into_the_scene, Exits(1, "already holds transforms_train.json, which would be replaced")),
    (export_beside_other_files, Ok(_exported)),
    (export_with_a_bad_config_leaves_no_folder, Exits(1, "unknown key pipeline.model.sh_degre", _export_left_nothing)),
]


@pytest.mark.parametrize("make, expect", CASES, ids=[make.__name__ for make, _ in CASES])
def test_bad_value(make, expect, toy_scene, trained, tmp_path, monkeypatch, capsys):
    check_case(Env(tmp_path, toy_scene, monkeypatch, capsys, run=trained), make, expect)


@pytest.mark.slow  # ns-eval and ns-export subprocesses
def test_the_console_scripts_print_one_line(trained, tmp_path):
    """The real ``ns-eval`` on a config.yml YAML cannot read (the excepthook the plugin installs at import) and
    ``ns-export`` over a user's splat.ply: exit status 1, one ``naka-gs:`` line, no traceback, nothing changed."""
    run = Path(shutil.copytree(trained, tmp_path / "run"))
    (run / "config.yml").write_text((run / "config.yml").read_text().replace("sh_degree: 3", "sh_degree: [3"))
    out = tmp_path / "export"
    out.mkdir()
    (out / "splat.ply").write_text("the user's own splat")
    env = dict(os.environ, TORCHDYNAMO_DISABLE="1", NAKA_GS_CACHE=str(tmp_path / "cache"))
    commands = {
        "ns-eval": (["--load-config", str(run / "config.yml")], f"naka-gs: {run / 'config.yml'}: not a readable YAML"),
        "ns-export": (
            ["gaussian-splat", "--load-config", str(trained / "config.yml"), "--output-dir", str(out)],
            f"naka-gs: --output-dir {out}: already holds splat.ply, which would be replaced",
        ),
    }
    before = snapshot([run, out, trained])
    for script, (args, expected) in commands.items():
        res = subprocess.run(
            [str(BIN / script), *args],
            cwd=tmp_path,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            timeout=300,
        )
        assert res.returncode == 1 and "Traceback" not in res.stdout, res.stdout[-3000:]
        assert res.stdout.strip().splitlines()[-1].startswith(expected), res.stdout[-3000:]
    assert snapshot([run, out, trained]) == before
