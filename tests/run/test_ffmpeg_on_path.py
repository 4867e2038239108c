"""ns-render's ffmpeg: a system one is kept, else imageio-ffmpeg's binary is put on PATH as ``ffmpeg``, else one line
(:func:`naka_gs_plugin.run.nerfstudio_hooks.put_ffmpeg_on_path`). ns-render writing a video with it:
``tests/scripts/test_cli_e2e.py``."""

from __future__ import annotations

import os
import shutil
import subprocess

import imageio_ffmpeg

from naka_gs_plugin.run import nerfstudio_hooks as hooks


def test_without_a_system_ffmpeg_imageio_ffmpegs_binary_is_found_as_ffmpeg(tmp_path, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path))
    assert shutil.which("ffmpeg") is None
    hooks.put_ffmpeg_on_path()
    found = shutil.which("ffmpeg")
    assert found is not None and os.path.realpath(found) == os.path.realpath(imageio_ffmpeg.get_ffmpeg_exe())
    assert os.environ["PATH"].split(os.pathsep)[0] == str(tmp_path), "the user's PATH comes first"
    proc = subprocess.run(["ffmpeg", "-version"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and proc.stdout.startswith("ffmpeg version"), proc.stderr


def test_a_system_ffmpeg_is_kept(tmp_path, monkeypatch):
    system = tmp_path / "ffmpeg"
    system.write_text("#!/bin/sh\n")
    system.chmod(0o755)
    monkeypatch.setenv("PATH", str(tmp_path))
    hooks.put_ffmpeg_on_path()
    assert os.environ["PATH"] == str(tmp_path)
    assert shutil.which("ffmpeg") == str(system)


def test_no_binary_for_this_platform_is_one_line_and_changes_nothing(tmp_path, monkeypatch, capsys):
    def missing():
        raise RuntimeError("No ffmpeg exe could be found.")

    monkeypatch.setattr(imageio_ffmpeg, "get_ffmpeg_exe", missing)
    monkeypatch.setenv("PATH", str(tmp_path))
    hooks.put_ffmpeg_on_path()
    assert os.environ["PATH"] == str(tmp_path)
    assert capsys.readouterr().err.splitlines() == [
        "naka-gs: imageio-ffmpeg gives no ffmpeg here (No ffmpeg exe could be found.): install ffmpeg to write videos"
    ]
