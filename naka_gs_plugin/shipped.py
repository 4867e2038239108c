"""Files shipped inside the package (configs, weights), found through :mod:`importlib.resources`.

They live in ``naka_gs_plugin/configs`` and ``naka_gs_plugin/enhance/weights``, so a non-editable
``pip install`` carries them. A user-given path ``configs/...`` that does not exist where it is given
names the shipped file, so ``naka-gs-sim configs/scenes/dark-noisy.yaml`` works from any directory.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

CONFIGS = Path(str(files("naka_gs_plugin") / "configs"))
"""The shipped configs: ``scenes/`` simulator specs, ``correction/`` recipes."""


def config_file(path: Path) -> Path:
    """``path`` itself, or the shipped config it names (``configs/...``) when there is no such file."""
    path = Path(path)
    if not path.exists() and path.parts[:1] == ("configs",) and len(path.parts) > 1:
        shipped = CONFIGS.joinpath(*path.parts[1:])
        if shipped.exists():
            return shipped
    return path
