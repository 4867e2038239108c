"""Inputs that are not regular files, paths too long, cache entries under another key (issue 81, item 5: "no input
blocks"), one row per case.

A FIFO opened for reading waits for a writer, ``/dev/zero`` never ends: every file a scene is read from (the
transforms jsons, the images of every split, the point sources) is refused in one line naming it before it is opened.
The table follows tests/faults/ (tests/bad_inputs.py's ``Raises`` / ``Exits`` / ``Ok`` outcomes and its check that
every protected input is byte-identical after); every row runs under :func:`promptly`, so a read that blocks fails
its row after :data:`DEADLINE_S` instead of hanging the suite. A folder holding a FIFO or a socket cannot be
snapshotted (reading the FIFO would block): those rows protect the folder's regular files and check after that the
special file is still one.
"""

from __future__ import annotations

import hashlib
import json
import os
import resource
import shutil
import signal
import socket
import stat
import subprocess
import sys
from pathlib import Path
from typing import List, Optional

import numpy as np
import pytest
import torch
from nerfstudio.scripts import train as ns_train

from naka_gs_plugin.data import safe_io
from naka_gs_plugin.data.cache import checksum_path
from naka_gs_plugin.data.images import read_rgb
from naka_gs_plugin.data.lowlight_dataparser import LowLightDataParserConfig, downscaled_copy
from naka_gs_plugin.data.safe_io import InputFileError, open_regular, read_regular, regular_file
from naka_gs_plugin.enhance.pipeline import Enhancer
from naka_gs_plugin.points.sources import find_scene_source, load_points, write_ply
from tests.bad_inputs import NAKA, Case, Env, Exits, Make, Ok, Raises, check_case, edit_frame0, parse
from tests.helpers import tiny_run_config

DEADLINE_S = 120
"""Seconds a row may take before it counts as blocked (each takes a few)."""
FIFO = "is a FIFO (named pipe), not a regular file"
TOO_LONG = "the path, or a name in it, is longer than the system allows -- use a shorter path"
LONG = 3800
"""Characters of the too-long paths (a name over the system's 255, as a pasted path or a generated name gives)."""


def promptly(make: Make, seconds: float = DEADLINE_S) -> Make:
    """``make`` whose action fails its row when it has not returned within ``seconds``: a SIGALRM handler raises
    pytest's failure, which interrupts a blocked ``open`` or ``read`` (Python restarts neither after a handler that
    raises) and passes every ``except Exception`` on its way out."""

    def timed(env: Env):
        action, protected = make(env)

        def action_in_time():
            def alarm(signum, frame):
                pytest.fail(f"{make.__name__}: no answer within {seconds} s (a read blocked?)", pytrace=False)

            previous = signal.signal(signal.SIGALRM, alarm)
            signal.setitimer(signal.ITIMER_REAL, seconds)
            try:
                return action()
            finally:
                signal.setitimer(signal.ITIMER_REAL, 0)
                signal.signal(signal.SIGALRM, previous)

        return action_in_time, protected

    timed.__name__ = make.__name__
    return timed


def regular_files(root: Path) -> List[Path]:
    """The regular files under ``root``: what a row protects when ``root`` also holds a FIFO or a socket."""
    return sorted(p for p in root.rglob("*") if stat.S_ISREG(p.lstat().st_mode))


def frame_image(scene: Path, index: int, split: str = "train") -> Path:
    frames = json.loads((scene / f"transforms_{split}.json").read_text())["frames"]
    return scene / frames[index]["file_path"]


def fifo_at(path: Path) -> Path:
    """``path`` (a file of a scene copy) replaced by a FIFO with no writer."""
    path.unlink(missing_ok=True)
    os.mkfifo(path)
    return path


def socket_at(path: Path) -> Path:
    """``path`` replaced by a Unix socket (bound from its folder: a socket path is at most 108 bytes)."""
    path.unlink(missing_ok=True)
    here = os.getcwd()
    sock = socket.socket(socket.AF_UNIX)
    try:
        os.chdir(path.parent)
        sock.bind(path.name)
    finally:
        os.chdir(here)
        sock.close()  # the socket file stays
    return path


def still(path: Path, test) -> None:
    assert test(os.lstat(path).st_mode), f"{path} was replaced"


def no_run_folder(env: Env) -> None:
    assert not (env.tmp / "out").exists()


def train(env: Env, scene: Path, **overrides):
    return lambda: ns_train.main(tiny_run_config(scene, env.tmp / "out", 3, **overrides))


# --- scenes: the transforms jsons and every split's images ----------------------------------------------------


def fifo_training_image(env):
    """ns-train on a scene whose 4th training image is a FIFO: it waited for a writer, with no line."""
    s = env.scene()
    fifo_at(frame_image(s, 3))
    return train(env, s), regular_files(s)


def _fifo_training_image(env):
    image = frame_image(env.tmp / "S", 3).resolve()
    line = (
        f"{env.tmp / 'S' / 'transforms_train.json'}: frame 3 file_path train/0003.png: {image} {FIFO} -- replace it "
        "with the image file, or remove it from the scene"
    )
    return Exits(1, line, lambda env: (no_run_folder(env), still(image, stat.S_ISFIFO)))


def fifo_transforms_train(env):
    """ns-train on a scene whose transforms_train.json is a FIFO."""
    s = env.scene()
    fifo_at(s / "transforms_train.json")
    return train(env, s), regular_files(s)


def _fifo_transforms_train(env):
    path = env.tmp / "S" / "transforms_train.json"
    return Exits(
        1,
        f"{path} {FIFO} -- replace it with the transforms json file",
        lambda env: (no_run_folder(env), still(path, stat.S_ISFIFO)),
    )


def fifo_test_truth_image(env):
    """The test split's ground truth: read for metrics, checked the same way."""
    s = env.scene()
    fifo_at(frame_image(s, 1, "test"))
    config = LowLightDataParserConfig(data=s, downscale_factor=1)
    return lambda: config.setup().get_dataparser_outputs("test"), regular_files(s)


def socket_training_image(env):
    s = env.scene()
    socket_at(frame_image(s, 0))
    return parse(s), regular_files(s)


def block_device_file_path(env):
    """``file_path`` naming a block device (a disk: gigabytes of someone else's data)."""
    devices = [e.path for e in os.scandir("/dev") if stat.S_ISBLK(e.stat(follow_symlinks=False).st_mode)]
    if not devices:
        pytest.skip("no block device in /dev here")
    s = env.scene()
    edit_frame0(s, file_path=devices[0])
    return parse(s), [s]


def folder_as_training_image(env):
    s = env.scene()
    image = frame_image(s, 2)
    image.unlink()
    image.mkdir()
    return parse(s), [s]


def fifo_at_the_reader(env):
    """The one reader (the datamanager's, ns-eval's): an image replaced by a FIFO after the dataparser's check."""
    return lambda: read_rgb(fifo_at(env.tmp / "0000.png")), [env.toy]


def long_file_path(env):
    """A file_path of 3,800 characters: a raw ``OSError: File name too long`` with the whole path before."""
    s = env.scene()
    edit_frame0(s, file_path="a" * LONG + ".png")
    return parse(s), [s]


def long_data_path(env):
    config = LowLightDataParserConfig(data=env.tmp / ("d" * LONG), downscale_factor=1)
    return lambda: config.setup().get_dataparser_outputs("train"), [env.toy]


# --- point sources -------------------------------------------------------------------------------------------


def _cloud(env: Env, name: str = "pts.ply") -> Path:
    path = env.tmp / name
    write_ply(path, np.random.default_rng(0).normal(size=(200, 3)), np.full((200, 3), 128, np.uint8))
    return path


def fifo_ply_point_source(env):
    """--pipeline.init.points naming a PLY that is a FIFO: was 'not found' (is_file() is False for a FIFO)."""
    return lambda: load_points(fifo_at(env.tmp / "pts.ply")), [env.toy]


def fifo_ply_init_points_ns_train(env):
    """The same through ns-train: one line, exit status 1."""
    s = env.scene()
    ply = fifo_at(env.tmp / "pts.ply")
    return train(env, s, **{"pipeline.init.points": str(ply)}), [s]


def fifo_scene_points_ply(env):
    """The scene's own points.ply a FIFO: ``auto`` skipped it in silence (random init), now one line."""
    s = env.scene()
    fifo_at(s / "points.ply")
    return lambda: find_scene_source(s), regular_files(s)


def _colmap_model(env: Env, fifo: str, ext: str) -> Path:
    model = env.tmp / "model"
    model.mkdir()
    for name in ("cameras", "images", "points3D"):
        (model / f"{name}{ext}").write_bytes(b"\0" * 8 if ext == ".bin" else b"# empty\n")
    fifo_at(model / fifo)
    return model


def fifo_colmap_points3d_bin(env):
    model = _colmap_model(env, "points3D.bin", ".bin")
    return lambda: load_points(model), regular_files(model)


def fifo_colmap_cameras_txt(env):
    model = _colmap_model(env, "cameras.txt", ".txt")
    return lambda: load_points(model), regular_files(model)


def fifo_cameras_json_beside_ply(env):
    ply = _cloud(env)
    fifo_at(env.tmp / "points_cameras.json")
    return lambda: load_points(ply), [ply]


def long_point_source_path(env):
    return lambda: load_points(env.tmp / ("p" * LONG + ".ply")), [env.toy]


# --- the cache: an entry belongs to its key -----------------------------------------------------------------


def _wide(env: Env) -> None:
    """One log line per line: nerfstudio's console wraps at 120 columns."""
    from nerfstudio.utils.rich_utils import CONSOLE

    env.monkeypatch.setattr(CONSOLE, "width", 100_000)


def _images(scene: Path, count: int) -> List[torch.Tensor]:
    return [torch.from_numpy(read_rgb(frame_image(scene, i))) for i in range(count)]


def _swap(a: Path, b: Path) -> None:
    aside = a.with_name(a.name + ".aside")
    os.replace(a, aside)
    os.replace(b, a)
    os.replace(aside, b)


def _enhanced_entries(env: Env) -> List[Path]:
    return sorted((env.tmp / "naka-cache" / "enhanced").glob("*.npy"))


def cache_swapped_enhanced_entries(env):
    """Two enhanced views' entries swapped together with their checksum files (same size and type): each checksum
    matched its bytes, so each view trained on the other's image."""
    _wide(env)
    s = env.scene()
    images = _images(s, 2)
    first = Enhancer(NAKA).enhance_images(images)
    a, b = _enhanced_entries(env)
    _swap(a, b)
    _swap(checksum_path(a), checksum_path(b))

    def action():
        again, third = Enhancer(NAKA), Enhancer(NAKA)
        result = again.enhance_images(images)
        third.enhance_images(images)
        return (a, b), first, result, again.last_run, third.last_run

    return action, [s]


def _swapped_recomputed(env, result):
    entries, first, again, run, later = result
    assert (run["computed"], run["cached"]) == (2, 0), run
    assert all(torch.equal(x, y) for x, y in zip(first, again))  # the originals' result
    assert later["cached"] == 2, later  # sealed under their own keys again
    log = env.log()
    assert log.count("recomputing") == 1, log
    assert any(
        f"warning: cache entry {entry} and 1 more: each does not match its checksum (edited or damaged since it was "
        "written); recomputing them" in log
        for entry in entries
    ), log


def cache_swapped_downscaled_copies(env):
    """Two downscaled copies (same size) swapped together with their checksum files."""
    _wide(env)
    s = env.scene()
    sources = [frame_image(s, 0), frame_image(s, 1)]
    copies = [downscaled_copy(src, 2) for src in sources]
    originals = [c.read_bytes() for c in copies]
    _swap(*copies)
    _swap(checksum_path(copies[0]), checksum_path(copies[1]))

    def action():
        made = [downscaled_copy(src, 2) for src in sources]
        return copies, originals, made

    return action, [s]


def _copies_made_again(env, result):
    copies, originals, made = result
    assert made == copies and [c.read_bytes() for c in made] == originals
    log = env.log()
    for copy in copies:
        assert (
            f"warning: cached copy {copy} does not match its checksum (edited or damaged since it was written); "
            "making it again" in log
        ), log


def cache_old_checksum(env):
    """An entry sealed by a naka-gs before the key-bound checksums (the sha256 of its bytes alone): recomputed once
    with the mismatch warning, then used."""
    _wide(env)
    s = env.scene()
    images = _images(s, 1)
    first = Enhancer(NAKA).enhance_images(images)
    (entry,) = _enhanced_entries(env)
    checksum_path(entry).write_text(hashlib.sha256(entry.read_bytes()).hexdigest())

    def action():
        again, third = Enhancer(NAKA), Enhancer(NAKA)
        result = again.enhance_images(images)
        third.enhance_images(images)
        return entry, first, result, again.last_run, third.last_run

    return action, [s]


def _old_recomputed_once(env, result):
    entry, first, again, run, later = result
    assert (run["computed"], later["cached"]) == (1, 1)
    assert torch.equal(first[0], again[0])
    log = env.log()
    assert log.count(f"cache entry {entry} does not match its checksum") == 1, log


def cache_entry_is_a_fifo(env):
    """A FIFO where an enhanced entry was: recomputed (and replaced by the file), never waited on."""
    _wide(env)
    s = env.scene()
    images = _images(s, 1)
    first = Enhancer(NAKA).enhance_images(images)
    (entry,) = _enhanced_entries(env)
    fifo_at(entry)

    def action():
        again = Enhancer(NAKA)
        return entry, first, again.enhance_images(images), again.last_run

    return action, [s]


def _fifo_entry_recomputed(env, result):
    entry, first, again, run = result
    assert run["computed"] == 1 and torch.equal(first[0], again[0])
    assert stat.S_ISREG(os.lstat(entry).st_mode)
    assert f"warning: cache entry {entry} {FIFO}; recomputing it" in env.log()


# --- the helper itself ---------------------------------------------------------------------------------------


def fifo_put_there_after_the_check(env):
    """A regular file replaced by a FIFO between the check and the open: opened O_NONBLOCK and checked again on
    the descriptor, so it is refused, not waited on."""
    path = fifo_at(env.tmp / "image.png")
    env.monkeypatch.setattr(safe_io, "regular_file", lambda *args, **kwargs: True)  # the check saw a file
    return lambda: open_regular(path, fix="replace it"), [env.toy]


def regular_and_missing_files(env):
    """A regular file: True and read; a missing one: False (its caller says "not found" its own way)."""
    path = env.tmp / "a.txt"
    path.write_bytes(b"abc")
    return lambda: (regular_file(path), regular_file(env.tmp / "none"), read_regular(path)), [path]


def _true_false_read(env, result):
    assert result == (True, False, b"abc")


CASES: List[Case] = [
    (fifo_training_image, _fifo_training_image),
    (fifo_transforms_train, _fifo_transforms_train),
    (
        fifo_test_truth_image,
        lambda env: Raises(
            InputFileError,
            f"{env.tmp / 'S' / 'transforms_test.json'}: frame 1 file_path test/0001.png: "
            f"{frame_image(env.tmp / 'S', 1, 'test').resolve()} {FIFO} -- replace it with the image file",
        ),
    ),
    (socket_training_image, Raises(InputFileError, "train/0000.png is a socket, not a regular file -- replace it")),
    (block_device_file_path, Raises(InputFileError, "is a block device, not a regular file -- replace it")),
    (folder_as_training_image, Raises(InputFileError, "train/0002.png is a folder, not a regular file -- replace it")),
    (fifo_at_the_reader, Raises(InputFileError, f"0000.png {FIFO} -- replace it with the image file")),
    (
        long_file_path,
        lambda env: Raises(
            InputFileError,
            f"frame 0 file_path {'a' * 60}... ({LONG + 4} characters): "
            f"{str((env.tmp / 'S').resolve() / ('a' * LONG))[:60]}... "
            f"({len(str((env.tmp / 'S').resolve())) + LONG + 5} characters): {TOO_LONG}",
        ),
    ),
    (
        long_data_path,
        lambda env: Raises(
            InputFileError,
            f"--data: {str(env.tmp / ('d' * LONG))[:60]}... ({len(str(env.tmp)) + LONG + 1} characters): {TOO_LONG}",
        ),
    ),
    (fifo_ply_point_source, Raises(InputFileError, f"pts.ply {FIFO} -- replace it with the point file (.ply)")),
    (
        fifo_ply_init_points_ns_train,
        lambda env: Exits(1, f"{env.tmp / 'pts.ply'} {FIFO} -- replace it with the point file (.ply)", no_run_folder),
    ),
    (fifo_scene_points_ply, Raises(InputFileError, f"points.ply {FIFO} -- replace it with the PLY file")),
    (fifo_colmap_points3d_bin, Raises(InputFileError, f"points3D.bin {FIFO} -- replace it with the COLMAP model file")),
    (fifo_colmap_cameras_txt, Raises(InputFileError, f"cameras.txt {FIFO} -- replace it with the COLMAP model file")),
    (fifo_cameras_json_beside_ply, Raises(InputFileError, f"points_cameras.json {FIFO} -- replace it with the json")),
    (
        long_point_source_path,
        lambda env: Raises(
            InputFileError,
            f"{str(env.tmp / ('p' * LONG))[:60]}... ({len(str(env.tmp)) + LONG + 5} characters): {TOO_LONG}",
        ),
    ),
    (cache_swapped_enhanced_entries, Ok(_swapped_recomputed)),
    (cache_swapped_downscaled_copies, Ok(_copies_made_again)),
    (cache_old_checksum, Ok(_old_recomputed_once)),
    (cache_entry_is_a_fifo, Ok(_fifo_entry_recomputed)),
    (fifo_put_there_after_the_check, Raises(InputFileError, f"image.png {FIFO} -- replace it")),
    (regular_and_missing_files, Ok(_true_false_read)),
]


@pytest.mark.parametrize("make, expect", CASES, ids=[make.__name__ for make, _ in CASES])
def test_input_kind(make, expect, toy_scene, tmp_path, monkeypatch, capsys):
    check_case(Env(tmp_path, toy_scene, monkeypatch, capsys), promptly(make), expect)


def test_a_blocked_read_fails_its_row(tmp_path, monkeypatch, capsys, toy_scene):
    """The deadline works: a plain read of a FIFO (what the scene reads did) fails the row within it."""
    fifo = fifo_at(tmp_path / "pipe")

    def blocks(env):
        return lambda: fifo.read_bytes(), [env.toy]

    with pytest.raises(pytest.fail.Exception, match="blocks: no answer within 2 s"):
        check_case(Env(tmp_path, toy_scene, monkeypatch, capsys), promptly(blocks, 2), Raises(OSError, ""))


def _limit_memory() -> None:
    """The child's heap capped (a regression reading /dev/zero dies of MemoryError, not the machine of OOM)."""
    resource.setrlimit(resource.RLIMIT_DATA, (8 << 30, 8 << 30))


@pytest.mark.slow  # an ns-train subprocess (its exit status and its last line, as a user sees them)
def test_ns_train_with_file_path_dev_zero_is_one_line(toy_scene, tmp_path):
    """``file_path: /dev/zero``: PIL could not identify it and the reader read it whole, forever (MemoryError at best)."""
    s = Path(shutil.copytree(toy_scene, tmp_path / "S"))
    edit_frame0(s, file_path="/dev/zero")
    before = {p: p.read_bytes() for p in regular_files(s)}
    ns_train_bin = Path(sys.executable).parent / "ns-train"
    argv = [str(ns_train_bin), "naka-gs", "--max-num-iterations", "3", "--output-dir", str(tmp_path / "out"),
            "--vis", "tensorboard", "--timestamp", "run", "--data", str(s)]  # fmt: skip
    env = dict(os.environ, TORCHDYNAMO_DISABLE="1", NAKA_GS_CACHE=str(tmp_path / "cache"))
    res = subprocess.run(
        argv, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        timeout=DEADLINE_S, preexec_fn=_limit_memory,
    )  # fmt: skip
    log = res.stdout
    assert res.returncode == 1, log
    assert "Traceback" not in log, log
    last: Optional[str] = log.strip().splitlines()[-1]
    assert last == (
        f"naka-gs: {s / 'transforms_train.json'}: frame 0 file_path /dev/zero: /dev/zero is a character device, not a "
        "regular file -- replace it with the image file, or remove it from the scene"
    ), log
    assert not (tmp_path / "out").exists()
    assert {p: p.read_bytes() for p in regular_files(s)} == before
