"""``naka-gs-train-correction [--config RECIPE.yaml] [flags]``: train the chroma-correction network.

Sources, recipe and checkpoints are described in :mod:`naka_gs_plugin.enhance.correction_train`.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import tyro

from naka_gs_plugin.enhance.correction_train import TrainConfig, config_from_yaml, train


@dataclass
class TrainCorrection(TrainConfig):
    """Train the correction network (defaults: the reference recipe, 200 epochs; ``--config`` sets others)."""

    def main(self) -> None:
        train(self)


def entrypoint(args: Optional[Sequence[str]] = None) -> None:
    """Console script ``naka-gs-train-correction``: ``--config RECIPE`` sets the defaults, later flags override."""
    argv = list(sys.argv[1:] if args is None else args)
    default = TrainCorrection()
    if "--config" in argv:
        i = argv.index("--config")
        if i + 1 >= len(argv):
            raise SystemExit(
                "naka-gs-train-correction: --config needs a YAML path, e.g. configs/correction/default.yaml"
            )
        try:
            default = TrainCorrection(**vars(config_from_yaml(Path(argv[i + 1]))))
        except (FileNotFoundError, ValueError, TypeError) as err:
            raise SystemExit(f"naka-gs-train-correction: {err}") from None
    correction = tyro.cli(TrainCorrection, default=default, args=argv)
    try:
        correction.main()
    except (FileNotFoundError, ValueError) as err:
        raise SystemExit(f"naka-gs-train-correction: {err}") from None


if __name__ == "__main__":
    entrypoint()
