"""naka-gs touches nerfstudio in one module, and only inside a naka-gs command or run
(``naka_gs_plugin/run/nerfstudio_hooks.py``)."""

from __future__ import annotations

import importlib
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from naka_gs_plugin.run import nerfstudio_hooks as hooks
from tests.helpers import upstream_sha256

PACKAGE = Path(__file__).resolve().parents[2] / "naka_gs_plugin"


def _resolve(dotted: str):
    """The function a dotted name of :data:`~naka_gs_plugin.run.nerfstudio_hooks.UPSTREAM_SHA256` names."""
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        for attr in parts[cut:]:
            obj = getattr(obj, attr)
        return obj
    raise AssertionError(dotted)


@pytest.mark.parametrize("name", sorted(hooks.UPSTREAM_SHA256))
def test_upstream_code_the_hooks_rely_on_is_the_pinned_one(name):
    digest = upstream_sha256(_resolve(name))
    assert digest == hooks.UPSTREAM_SHA256[name], (
        f"nerfstudio's {name} changed (sha256 {digest}): re-check the hook in naka_gs_plugin/run/nerfstudio_hooks.py "
        "that relies on it, then update its pin there"
    )


def test_only_the_hooks_module_reads_frames_patches_or_installs_hooks():
    pattern = re.compile(r"_getframe|f_locals|f_back|excepthook|mock\.patch|linecache")
    found = sorted(
        str(path.relative_to(PACKAGE))
        for path in PACKAGE.rglob("*.py")
        if pattern.search(path.read_text()) and path != PACKAGE / "run" / "nerfstudio_hooks.py"
    )
    assert not found, found


def test_importing_the_plugin_turns_on_nothing():
    """What every ``ns-*`` command does with an installed plugin: import its entry points. The interpreter's
    excepthook and torch's safe globals stay as they were."""
    probe = (
        "import sys, torch\n"
        "def ours():\n"
        "    safe = getattr(torch.serialization, 'get_safe_globals', lambda: [])()\n"
        "    return [g for g in safe if isinstance(g, tuple) and 'numpy' in g[1]]\n"
        "import naka_gs_plugin.config, naka_gs_plugin.data.lowlight_dataparser\n"
        "assert sys.excepthook is sys.__excepthook__, sys.excepthook\n"
        "assert ours() == []\n"
        "from naka_gs_plugin.run import nerfstudio_hooks as h\n"
        "assert not h._ACTIVE\n"
        "h.activate()\n"
        "assert sys.excepthook is not sys.__excepthook__\n"
        "assert len(ours()) == (2 if torch.__version__ >= '2.6' else 0)\n"
    )
    proc = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]


def test_the_command_line_of_a_naka_gs_run_turns_the_hooks_on(tmp_path):
    """At import, only a command that loads a naka-gs run's config.yml activates the hooks: by the file's content
    (our package named in it) or by its place in a run folder of our presets (a file too broken to name it)."""
    ours = tmp_path / "a.yml"
    ours.write_text("!!python/object:naka_gs_plugin.trainer.NakaGSTrainerConfig\nmethod_name: naka-gs\n")
    other = tmp_path / "b.yml"
    other.write_text("!!python/object:nerfstudio.engine.trainer.TrainerConfig\nmethod_name: splatfacto\n")
    broken = tmp_path / "out" / "scene" / "naka-gs" / "run" / "config.yml"
    broken.parent.mkdir(parents=True)
    broken.write_text("{{ not yaml")
    assert hooks.loaded_config_path(["ns-eval", "--load-config", str(ours)]) == ours
    assert hooks.loaded_config_path(["ns-render", "dataset", f"--load-config={ours}"]) == ours
    assert hooks.loaded_config_path(["ns-train", "naka-gs", "--load-config", str(ours)]) is None
    assert hooks.loaded_config_path(["ns-train", "splatfacto", "--data", "x"]) is None
    assert hooks.is_naka_gs_run_config(ours) and hooks.is_naka_gs_run_config(broken)
    assert not hooks.is_naka_gs_run_config(other)
    assert not hooks.is_naka_gs_run_config(tmp_path / "missing.yml")


WITHOUT_US = """
import importlib.metadata as md, sys
entry_points = md.entry_points
def without_naka_gs(**kwargs):
    found = entry_points(**kwargs)
    if "group" not in kwargs:
        return found
    return md.EntryPoints(e for e in found if not e.value.startswith("naka_gs_plugin"))
md.entry_points = without_naka_gs
"""

NS_TRAIN = """
import atexit, json, sys, torch
def report():
    print("PROBE " + json.dumps({
        "plugin_imported": "naka_gs_plugin" in sys.modules,
        "excepthook_untouched": sys.excepthook is sys.__excepthook__,
        "numpy_safe_globals": [
            str(g) for g in getattr(torch.serialization, "get_safe_globals", lambda: [])() if "numpy" in str(g)
        ],
    }), flush=True)
atexit.register(report)
from nerfstudio.scripts.train import entrypoint
sys.argv = ["ns-train"] + sys.argv[1:]
entrypoint()
"""


@pytest.mark.slow
def test_ns_train_splatfacto_runs_exactly_as_without_the_plugin(toy_scene, tmp_path):
    """``ns-train splatfacto`` on the toy scene (nerfstudio-data layout) with our entry points installed and with
    them hidden from nerfstudio: the same exit status, the same last lines, the same files (checkpoint bits where
    it gets that far: on a CPU stock splatfacto stops before its first step, as it does without us)."""
    scene = tmp_path / "scene"
    shutil.copytree(toy_scene, scene)
    shutil.copy(scene / "transforms_train.json", scene / "transforms.json")
    runs = {}
    out = tmp_path / "out"  # the same path for both: config.yml records it
    for name, prelude in (("with", ""), ("without", WITHOUT_US)):
        args = [
            "splatfacto", "--max-num-iterations", "2", "--machine.device-type", "cpu", "--vis", "tensorboard",
            "--output-dir", str(out), "--timestamp", "run", "--viewer.quit-on-train-completion", "True",
            "nerfstudio-data", "--data", str(scene),
        ]  # fmt: skip
        proc = subprocess.run(
            [sys.executable, "-c", prelude + NS_TRAIN, *args], capture_output=True, text=True, timeout=600
        )
        probe = json.loads(next(line[6:] for line in proc.stdout.splitlines() if line.startswith("PROBE ")))
        files = {
            str(p.relative_to(out)): p.read_bytes()
            for p in sorted(out.rglob("*"))
            if p.is_file() and "events.out" not in p.name
        }
        tail = proc.stderr.strip().splitlines()[-3:]
        runs[name] = (proc.returncode, tail, files, probe)
        out.rename(tmp_path / name)
    (rc, tail, files, probe), (rc0, tail0, files0, probe0) = runs["with"], runs["without"]
    assert probe0["plugin_imported"] is False
    assert probe["plugin_imported"] is True and probe["excepthook_untouched"] is True
    assert probe["numpy_safe_globals"] == probe0["numpy_safe_globals"] == []
    assert (rc, tail) == (rc0, tail0)
    assert files.keys() == files0.keys() and files == files0
