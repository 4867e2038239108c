"""Shared fixtures: a private cache dir per test and a tiny toy low-light scene."""

from pathlib import Path

import pytest
import torch

from naka_gs_plugin.sim.toy_scene import ToySceneConfig, write_toy_scene


@pytest.fixture(autouse=True)
def _isolated_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("NAKA_GS_CACHE", str(tmp_path / "naka-cache"))
    torch.manual_seed(0)


@pytest.fixture(scope="session")
def toy_scene(tmp_path_factory) -> Path:
    """8 train / 2 test views at 64x48 with truth; read-only by convention (copy to modify)."""
    return write_toy_scene(
        tmp_path_factory.mktemp("toy") / "scene", ToySceneConfig(n_train=8, n_test=2, width=64, height=48)
    )
