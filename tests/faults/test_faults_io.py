"""Faults of files and processes (issue 72: D1, S3, X5, X6 and the smaller ones), one row per case.

The table follows tests/faults/test_bad_inputs.py (tests/bad_inputs.py's ``Raises`` / ``Exits`` / ``Ok`` outcomes,
its check that every protected input is byte-identical after). The stop rows (Ctrl-C, SIGTERM) run the command in a
Python subprocess, send the signal once the command has reached the stage under test and check its exit status, its
one line and that no unfinished output is left.
"""

from __future__ import annotations

import copy
import json
import os
import signal
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import List, Tuple

import cv2
import numpy as np
import pytest
import torch

from naka_gs_plugin.config import naka_gs_method
from naka_gs_plugin.data.cache import CHECKSUMS
from naka_gs_plugin.data.images import read_rgb
from naka_gs_plugin.data.lowlight_dataparser import LowLightDataError, downscaled_copy
from naka_gs_plugin.enhance.pipeline import Enhancer
from naka_gs_plugin.errors import signal_exit_status
from naka_gs_plugin.run.claim import RUN_CLAIM
from naka_gs_plugin.scripts import process_data
from naka_gs_plugin.scripts import sim as sim_cli
from naka_gs_plugin.trainer import NakaGSTrainerConfig
from tests.bad_inputs import (
    NAKA,
    Case,
    Env,
    Exits,
    Ok,
    Raises,
    check_case,
    edit_frame0,
    first_train_image,
    parse,
    run_console,
    snapshot,
)
from tests.helpers import TINY_VIEWS, write_spec


# --- D1: the run folder is claimed in one step -----------------------------------------------------
def _trainer_config(env: Env, scene: Path) -> NakaGSTrainerConfig:
    config = copy.deepcopy(naka_gs_method.config)
    config.data = config.pipeline.datamanager.data = scene  # as ns-train's main sets it
    config.output_dir = env.tmp / "outputs"
    config.timestamp = "run"
    return config


def run_folder_two_runs_at_once(env):
    """Two ns-train with one --output-dir and --timestamp: both pass the "already holds a run" check before either
    has written config.yml (they started 2 s apart); the first to save its config claims the folder."""
    s = env.scene()
    first, second = _trainer_config(env, s), _trainer_config(env, s)
    first.set_timestamp()
    second.set_timestamp()  # the folder is still free: no config.yml yet
    first.save_config()  # its claim is released by the test's end (ns-train's, when its training ends)
    return lambda: second.save_config(), [s, first.get_base_dir()]


def _stale_claim(env: Env, record: dict) -> Tuple[NakaGSTrainerConfig, Path]:
    s = env.scene()
    config = _trainer_config(env, s)
    run = config.get_base_dir()
    run.mkdir(parents=True)
    (run / RUN_CLAIM).write_text(json.dumps(record))
    return config, s


def _dead_pid() -> int:
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def run_folder_claim_of_a_crashed_run(env):
    """A run killed (kill -9, a reboot) leaves its claim; the next run there takes it over, saying so."""
    _wide(env)
    pid = _dead_pid()
    config, s = _stale_claim(env, {"pid": pid, "host": socket.gethostname(), "token": "x", "started": 0})

    def action():
        config.save_config()
        held = json.loads((config.get_base_dir() / RUN_CLAIM).read_text())
        config.release_run_folder()
        return pid, held, config.get_base_dir()

    return action, [s]


def _taken_over(env, result):
    pid, held, run = result
    assert held["pid"] == os.getpid()
    assert (
        f"naka-gs: {run}: taking over the claim of a training that ended without releasing it (pid {pid}, no longer "
        "running)" in env.log()
    )
    assert sorted(p.name for p in run.iterdir()) == ["config.yml"]  # released: only the run's own file stays


def run_folder_claim_of_another_host(env):
    """A claim made on another machine (a shared disk) cannot be checked: refused, naming the file to delete."""
    config, s = _stale_claim(env, {"pid": 1, "host": "elsewhere", "token": "x", "started": 0})
    return lambda: config.save_config(), [s, config.get_base_dir()]


# --- S3: cache entries carry a checksum ----------------------------------------------------------------
def _images(scene: Path, count: int = 3) -> List[torch.Tensor]:
    frames = json.loads((scene / "transforms_train.json").read_text())["frames"][:count]
    return [torch.from_numpy(read_rgb(scene / f["file_path"])) for f in frames]


def cache_zeroed_enhanced_entries(env):
    """Every enhanced/*.npy replaced by zeros of its shape and type: none is used, all are recomputed."""
    _wide(env)
    s = env.scene()
    images = _images(s)
    first = Enhancer(NAKA).enhance_images(images)
    entries = sorted((env.tmp / "naka-cache" / "enhanced").glob("*.npy"))
    assert len(entries) == 3
    for entry in entries:
        np.save(entry, np.zeros_like(np.load(entry)))

    def action():
        again = Enhancer(NAKA)
        return again, first, again.enhance_images(images), entries

    return action, [s]


def _recomputed_zeroed(env, result):
    enhancer, first, again, entries = result
    assert enhancer.last_run["computed"] == 3 and all(torch.equal(a, b) for a, b in zip(first, again))
    assert all(np.load(entry).any() for entry in entries)  # replaced by the recomputed images
    log = env.log()
    assert log.count("recomputing") == 1, log
    assert any(
        f"warning: cache entry {entry} and 2 more: each does not match its checksum (edited or damaged since it was "
        "written); recomputing them" in log
        for entry in entries
    ), log


def cache_entry_without_checksum(env):
    """An entry of an older naka-gs (no checksum) is recomputed once, then used."""
    _wide(env)
    s = env.scene()
    images = _images(s, 1)
    Enhancer(NAKA).enhance_images(images)
    (entry,) = (env.tmp / "naka-cache" / "enhanced").glob("*.npy")
    for checksum in (env.tmp / "naka-cache" / CHECKSUMS).rglob("*.sha256"):
        checksum.unlink()

    def action():
        again, third = Enhancer(NAKA), Enhancer(NAKA)
        again.enhance_images(images)
        third.enhance_images(images)
        return entry, again.last_run["computed"], third.last_run["cached"]

    return action, [s]


def _recomputed_once(env, result):
    entry, computed, cached = result
    assert (computed, cached) == (1, 1)
    assert env.log().count(f"cache entry {entry} has no checksum (an older naka-gs wrote it, or it was copied in)") == 1


def cache_zeroed_downscaled_copy(env):
    """A downscaled copy overwritten with a valid, black PNG of its size: made again from the photo."""
    _wide(env)
    s = env.scene()
    src = first_train_image(s)
    copy_ = downscaled_copy(src, 2)
    good = copy_.read_bytes()
    cv2.imwrite(str(copy_), np.zeros_like(cv2.imread(str(copy_), cv2.IMREAD_UNCHANGED)))

    def action():
        return copy_, downscaled_copy(src, 2).read_bytes() == good

    return action, [s]


def _copy_made_again(env, result):
    copy_, same = result
    assert same
    assert (
        f"warning: cached copy {copy_} does not match its checksum (edited or damaged since it was written); making "
        "it again" in env.log()
    )


# --- X5: naka-gs-process-data ---------------------------------------------------------------------------
def _no_colmap(env: Env) -> None:
    def never(*_args, **_kwargs):
        raise AssertionError("pycolmap started")

    for name in ("extract_features", "match_features", "incremental_mapping"):
        env.monkeypatch.setattr(process_data, name, never)


def pd_identical_copies_console(env):
    """200 copies of one photo in the issue; 6 here, and one other photo: refused before any SfM."""
    s = env.scene()
    photos = env.tmp / "photos"
    photos.mkdir()
    one = first_train_image(s).read_bytes()
    for i in range(6):
        (photos / f"IMG_{i:03d}.png").write_bytes(one)
    (photos / "other.png").write_bytes((s / "train" / "0001.png").read_bytes())
    _no_colmap(env)
    argv = ["naka-gs-process-data", "--data", str(photos), "--output-dir", str(env.tmp / "scene")]
    return run_console(env, process_data.entrypoint, argv + ["--enhance.correction", "none"]), [env.tmp]


# --- X6: naka-gs-sim --------------------------------------------------------------------------------------
def sim_ten_thousand_views_console(env):
    spec = write_spec(env.tmp, [], source={"procedural": {**TINY_VIEWS, "n_train": 10000}})
    argv = ["naka-gs-sim", str(spec), "--out", str(env.tmp / "scene")]
    return run_console(env, sim_cli.entrypoint, argv), [env.tmp]


def sim_huge_images_console(env):
    spec = write_spec(env.tmp, [], source={"procedural": {**TINY_VIEWS, "n_train": 200, "width": 8000, "height": 6000}})
    argv = ["naka-gs-sim", str(spec), "--out", str(env.tmp / "scene")]
    return run_console(env, sim_cli.entrypoint, argv), [env.tmp]


# --- smaller: file_path spellings, a byte-order mark -------------------------------------------------------
def dp_windows_backslashes(env):
    s = env.scene()
    edit_frame0(s, file_path="train\\0000.png")
    return lambda: parse(s)().image_filenames[0], [s]


def _read_the_file(env, path):
    assert Path(path) == (env.tmp / "S" / "train" / "0000.png").resolve()


def dp_suffix_case(env):
    s = env.scene()
    edit_frame0(s, file_path="train/0000.PNG")
    return parse(s), [s]


def dp_backslashes_and_suffix_case(env):
    s = env.scene()
    edit_frame0(s, file_path="train\\0000.PNG")
    return parse(s), [s]


def dp_byte_order_mark(env):
    s = env.scene()
    for name in ("transforms_train.json", "transforms_test.json"):
        path = s / name
        path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    return lambda: (parse(s)(), parse(env.toy)()), [s]


def _same_as_without(env, result):
    outputs, expected = result
    assert torch.equal(outputs.cameras.camera_to_worlds, expected.cameras.camera_to_worlds)
    assert len(outputs.image_filenames) == 8


def _wide(env: Env) -> None:
    """One log line per line: nerfstudio's console wraps at 120 columns, and puts a source location in the wrap."""
    from nerfstudio.utils.rich_utils import CONSOLE

    env.monkeypatch.setattr(CONSOLE, "width", 100_000)


def _here(env: Env, name: str = "S") -> str:
    return str((env.tmp / name).resolve())


CASES: List[Case] = [
    (
        run_folder_two_runs_at_once,
        lambda env: Raises(
            SystemExit,
            f"naka-gs: {env.tmp}/outputs/S/naka-gs/run is claimed by another training (pid {os.getpid()} on "
            f"{socket.gethostname()}, its {RUN_CLAIM}); pick another --timestamp or --output-dir -- if no ns-train is "
            f"writing there any more, delete {env.tmp}/outputs/S/naka-gs/run/{RUN_CLAIM}",
        ),
    ),
    (run_folder_claim_of_a_crashed_run, lambda env: Ok(_taken_over)),
    (
        run_folder_claim_of_another_host,
        lambda env: Raises(SystemExit, "is claimed by another training (pid 1 on elsewhere, its .naka-gs-run)"),
    ),
    (cache_zeroed_enhanced_entries, lambda env: Ok(_recomputed_zeroed)),
    (cache_entry_without_checksum, lambda env: Ok(_recomputed_once)),
    (cache_zeroed_downscaled_copy, lambda env: Ok(_copy_made_again)),
    (
        pd_identical_copies_console,
        lambda env: Exits(
            1,
            f"naka-gs: {env.tmp}/photos/IMG_001.png is an identical copy of {env.tmp}/photos/IMG_000.png "
            "(5 copies in all) -- structure from motion needs photos from different viewpoints: keep one of each and "
            f"move the copies out of {env.tmp}/photos",
        ),
    ),
    (
        sim_ten_thousand_views_console,
        lambda env: Exits(
            1,
            f"naka-gs: {env.tmp}/s.yaml: field 'source.procedural.n_train': 10000 training + 1 test views is over "
            "the limit of 2000 -- a simulated scene needs tens to a few hundred views: lower n_train / n_test",
        ),
    ),
    (
        sim_huge_images_console,
        lambda env: Exits(
            1,
            f"naka-gs: {env.tmp}/s.yaml: field 'source.procedural': 201 views of 8000x6000 would write about "
            "115 GB of images, over the limit of 16 GB -- lower n_train, n_test, width or height",
        ),
    ),
    (dp_windows_backslashes, lambda env: Ok(_read_the_file)),
    (
        dp_suffix_case,
        lambda env: Raises(
            LowLightDataError,
            f"image {_here(env)}/train/0000.PNG not found (1 of 8 missing); did you mean {_here(env)}/train/0000.png? "
            "(file names are case-sensitive) -- fix file_path or restore the images",
        ),
    ),
    (
        dp_backslashes_and_suffix_case,
        lambda env: Raises(
            LowLightDataError,
            f"image {_here(env)}/train\\0000.PNG not found (1 of 8 missing); did you mean "
            f"{_here(env)}/train/0000.png? (file names are case-sensitive)",
        ),
    ),
    (dp_byte_order_mark, lambda env: Ok(_same_as_without)),
]


@pytest.mark.parametrize("make, expect", CASES, ids=[make.__name__ for make, _ in CASES])
def test_fault(make, expect, toy_scene, tmp_path, monkeypatch, capsys):
    try:
        check_case(Env(tmp_path, toy_scene, monkeypatch, capsys), make, expect)
    finally:
        _release_claims(tmp_path)


def _release_claims(tmp_path: Path) -> None:
    """Drop the claims this test's configs still hold (ns-train releases its claim when training ends)."""
    from naka_gs_plugin.run.claim import release_run_folder

    for claim in tmp_path.rglob(RUN_CLAIM):
        held = json.loads(claim.read_text())
        if held.get("pid") == os.getpid():
            release_run_folder(claim, held.get("token"))


# --- stopping a command: Ctrl-C and SIGTERM -------------------------------------------------------------
STUCK_IN_MATCHING = textwrap.dedent(
    """
    import signal, sys, time
    from naka_gs_plugin.scripts import process_data

    signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a terminal (a suite run with & ignores it)

    def extract(*args, **kwargs):
        pass

    def match(*args, **kwargs):
        # As pycolmap's matching: the main thread stays in one call, in which Python runs no signal handler.
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
        print("MATCHING", flush=True)
        time.sleep(120)

    process_data.extract_features, process_data.match_features = extract, match
    process_data.entrypoint(sys.argv[1:])
    """
)

SIM = textwrap.dedent(
    """
    import signal, sys
    from naka_gs_plugin.scripts import sim

    signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a terminal (a suite run with & ignores it)
    sim.entrypoint(sys.argv[1:])
    """
)


def _stop_when(argv: List[str], marker: str, signum: int, cwd: Path) -> Tuple[int, str]:
    """Run ``python -c argv[0] argv[1:]``; send ``signum`` once a line holds ``marker``; the exit status and output."""
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]), TORCHDYNAMO_DISABLE="1")
    child = subprocess.Popen(
        [sys.executable, "-c", *argv], cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    lines = []
    deadline = time.monotonic() + 240
    try:
        for line in child.stdout:  # type: ignore[union-attr]
            lines.append(line)
            if marker in line:
                child.send_signal(signum)
                break
            assert time.monotonic() < deadline, "".join(lines)
        rest, _ = child.communicate(timeout=60)
    finally:
        child.kill()
    return child.returncode, "".join(lines) + rest


@pytest.mark.slow  # a Python subprocess (the signal ends it)
def test_sigterm_in_process_data_matching_removes_the_unfinished_scene(toy_scene, tmp_path):
    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(4):
        (photos / f"{i}.png").write_bytes((toy_scene / "train" / f"{i:04d}.png").read_bytes())
    before = snapshot([photos])
    out = tmp_path / "scene"
    argv = [STUCK_IN_MATCHING, "--data", str(photos), "--output-dir", str(out), "--enhance.correction", "none"]
    code, log = _stop_when(argv, "MATCHING", signal.SIGTERM, tmp_path)
    assert code == signal_exit_status(signal.SIGTERM) == 143, log
    last = log.strip().splitlines()[-1]
    assert last == (
        f"naka-gs: SIGTERM: stopped; its unfinished output was removed and {out} was not created; run "
        "it again to make it"
    ), log
    assert "Traceback" not in log and "Checking the photos for copies: 4/4" in log, log
    assert sorted(p.name for p in tmp_path.iterdir()) == ["photos"]  # no hidden .partial folder
    assert snapshot([photos]) == before


@pytest.mark.slow  # a Python subprocess (the signal ends it)
def test_ctrl_c_in_sim_removes_the_unfinished_scene(tmp_path):
    spec = write_spec(tmp_path, [], source={"procedural": {**TINY_VIEWS, "n_train": 1500}})
    before = snapshot([spec])
    out = tmp_path / "scene"
    code, log = _stop_when([SIM, str(spec), "--out", str(out)], "naka-gs-sim s: 1/1501", signal.SIGINT, tmp_path)
    assert code == signal_exit_status(signal.SIGINT) == 130, log
    assert log.strip().splitlines()[-1] == (
        f"naka-gs: Ctrl-C: stopped; its unfinished output was removed and {out} was not created; run it again to "
        "make it"
    ), log
    assert "Traceback" not in log
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.yaml"]  # no hidden .partial folder
    assert snapshot([spec]) == before
