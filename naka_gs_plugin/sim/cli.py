"""``naka-gs-sim SPEC --out DIR``: generate a synthetic low-light scene from a YAML spec.

Relative paths inside the spec (a capture's folder) resolve against the current working
directory: run from the repository root. Spec errors print one line and exit with status 2.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import tyro
from nerfstudio.utils.rich_utils import CONSOLE

from naka_gs_plugin.sim.generate import generate
from naka_gs_plugin.sim.spec import SimSpecError, load_spec


@dataclass
class SimArgs:
    spec: tyro.conf.Positional[Path]
    """Scene spec YAML, e.g. configs/scenes/dark-noisy.yaml."""
    out: Path = Path("outputs/sim/scene")
    """Output scene folder (lowlight-data layout)."""
    seed: Optional[int] = None
    """Override the spec's noise seed."""


def main(args: SimArgs) -> Path:
    return generate(load_spec(args.spec), args.out, seed=args.seed)


def entrypoint() -> None:
    args = tyro.cli(SimArgs, description=__doc__.splitlines()[0])
    try:
        main(args)
    except SimSpecError as err:
        CONSOLE.print(f"naka-gs-sim: {err}", markup=False, soft_wrap=True)
        sys.exit(2)


if __name__ == "__main__":
    entrypoint()
