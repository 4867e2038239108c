"""A run's config.yml is data: a tag that would run code while the file is read is refused, by every command that
loads a naka-gs run, before anything in the file is constructed (``naka_gs_plugin/run/config_check.py``)."""

from __future__ import annotations

import copy
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from naka_gs_plugin.run import nerfstudio_hooks as hooks
from naka_gs_plugin.run.config_check import allowed_tag, check_config_file, refuse_code_in_config

BIN = Path(sys.executable).parent
P = "tag:yaml.org,2002:python/"


def _run_config_text() -> str:
    """What ns-train writes as a naka-gs run's config.yml (``save_config``: ``yaml.dump`` of the settled config)."""
    from naka_gs_plugin.config import naka_gs_method

    config = copy.deepcopy(naka_gs_method.config)
    config.machine.device_type = "cpu"
    config.resolve_device()
    config.data = Path("scene")
    return yaml.dump(config)


def _evil(tmp_path: Path, line: str) -> Path:
    """A run folder whose config.yml ends with ``line``, laid out as ns-train lays one out."""
    path = tmp_path / "outputs" / "scene" / "naka-gs" / "run" / "config.yml"
    path.parent.mkdir(parents=True)
    path.write_text(_run_config_text() + line + "\n")
    return path


@pytest.mark.parametrize(
    "tag, allowed",
    [
        ("tag:yaml.org,2002:str", True),
        ("tag:yaml.org,2002:map", True),
        (P + "tuple", True),
        (P + "object/apply:pathlib.PosixPath", True),
        (P + "object:naka_gs_plugin.trainer.NakaGSTrainerConfig", True),
        (P + "object:nerfstudio.configs.base_config.ViewerConfig", True),
        (P + "object/apply:nerfstudio.utils.writer.EventName", True),
        (P + "name:naka_gs_plugin.trainer.NakaGSTrainer", True),
        (P + "name:torch.optim.adam.Adam", True),
        (P + "object/apply:os.system", False),
        (P + "object/apply:subprocess.check_call", False),
        (P + "name:os.system", False),
        (P + "name:nerfstudio.utils.eval_utils.eval_setup", False),  # a function: a _target would call it
        (P + "object:collections.OrderedDict", False),
        (P + "object/new:pathlib.PosixPath", False),
        (P + "object/apply:naka_gs_plugin.run.config_check.check_config_file", False),
        (P + "module:os", False),
        ("!custom", False),
    ],
)
def test_only_the_tags_a_run_config_holds_are_allowed(tag, allowed):
    assert allowed_tag(tag) is allowed


def test_the_config_ns_train_writes_passes(tmp_path):
    text = _run_config_text()
    refuse_code_in_config(tmp_path / "config.yml", text)  # no SystemExit
    assert yaml.load(text, Loader=yaml.Loader).method_name == "naka-gs"


@pytest.mark.parametrize(
    "line, tag",
    [
        ("pwned: !!python/object/apply:os.system ['touch {marker}']", "!!python/object/apply:os.system"),
        ("pwned: !!python/object/new:subprocess.Popen [['touch', '{marker}']]", "!!python/object/new:subprocess.Popen"),
        ("_pwned: !!python/name:os.system ''", "!!python/name:os.system"),
    ],
)
def test_a_tag_that_runs_code_is_refused_in_one_line_and_nothing_runs(line, tag, tmp_path):
    marker = tmp_path / "marker"
    path = _evil(tmp_path, line.format(marker=marker))
    lineno = len(path.read_text().splitlines())
    expected = f"naka-gs: {path}: line {lineno} holds the tag {tag}, which a run's config.yml never holds"
    for check in (
        lambda: check_config_file(path),  # ns-train naka-gs --load-config
        lambda: hooks.activate_for_command(["ns-eval", "--load-config", str(path)]),  # eval_setup's commands
    ):
        with pytest.raises(SystemExit) as exc:
            check()
        assert str(exc.value.code).startswith(expected), exc.value.code
        assert "\n" not in str(exc.value.code)
    assert not marker.exists()


@pytest.mark.slow
def test_no_command_runs_the_code_of_a_config_yml(tmp_path):
    """The issue's case, for real: ns-eval, ns-export, ns-render, ns-viewer and ns-train --load-config on a
    config.yml with an ``os.system`` tag: each exits 1 with the one line, and the marker file is never created."""
    marker = tmp_path / "marker"
    path = _evil(tmp_path, f"pwned: !!python/object/apply:os.system ['touch {marker}']")
    commands = [
        ["ns-eval", "--load-config", str(path), "--output-path", str(tmp_path / "eval.json")],
        ["ns-export", "gaussian-splat", "--load-config", str(path), "--output-dir", str(tmp_path / "export")],
        ["ns-render", "dataset", "--load-config", str(path), "--output-path", str(tmp_path / "renders")],
        ["ns-viewer", f"--load-config={path}"],
        ["ns-train", "naka-gs", "--load-config", str(path)],
    ]
    for argv in commands:
        proc = subprocess.run([str(BIN / argv[0]), *argv[1:]], capture_output=True, text=True, timeout=300)
        lines = [line for line in proc.stderr.splitlines() if line.startswith("naka-gs:")]
        assert proc.returncode == 1 and len(lines) == 1 and "os.system" in lines[0], (argv, proc.stderr[-2000:])
        assert "Traceback" not in proc.stderr, (argv, proc.stderr[-2000:])
        assert not marker.exists(), argv


def test_the_loader_itself_builds_no_tag_outside_a_run_config(tmp_path):
    """Behind :func:`refuse_code_in_config`, the loader that builds the config refuses such a tag too."""
    from naka_gs_plugin.run.config_check import RunConfigLoader

    marker = tmp_path / "marker"
    with pytest.raises(yaml.constructor.ConstructorError, match="os.system"):
        yaml.load(f"pwned: !!python/object/apply:os.system ['touch {marker}']", Loader=RunConfigLoader)
    assert not marker.exists()
    assert yaml.load(_run_config_text(), Loader=RunConfigLoader).method_name == "naka-gs"
