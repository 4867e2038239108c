"""``naka-gs-train-correction [--config RECIPE.yaml] [flags]``: train the chroma-correction network.

Sources, recipe and checkpoints are described in :mod:`naka_gs_plugin.enhance.correction_train`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Sequence

from naka_gs_plugin.enhance.correction_train import CorrectionTrainingError, TrainConfig, config_from_yaml, train
from naka_gs_plugin.errors import UserError
from naka_gs_plugin.scripts import run


@dataclass
class TrainCorrection(TrainConfig):
    """Train the correction network (defaults: the reference recipe, 200 epochs; ``--config`` sets others)."""

    def main(self) -> None:
        train(self)


def recipe_defaults(argv: List[str]) -> TrainCorrection:
    """The values flags start from: those of ``--config RECIPE`` when the arguments name one, else the defaults."""
    if "--config" not in argv:
        return TrainCorrection()
    i = argv.index("--config")
    if i + 1 >= len(argv):
        raise CorrectionTrainingError("--config needs a YAML path, e.g. configs/correction/default.yaml")
    try:
        return TrainCorrection(**vars(config_from_yaml(Path(argv[i + 1]))))
    except (ValueError, TypeError) as err:
        if isinstance(err, UserError):
            raise
        raise CorrectionTrainingError(f"{argv[i + 1]}: {err}") from None


def entrypoint(args: Optional[Sequence[str]] = None) -> None:
    """Console script ``naka-gs-train-correction`` (:func:`naka_gs_plugin.scripts.run`): ``--config RECIPE`` sets
    the defaults, later flags override."""
    run(TrainCorrection.main, TrainCorrection, args, defaults=recipe_defaults)


if __name__ == "__main__":
    entrypoint()
