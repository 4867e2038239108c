"""``naka-gs-sim SPEC --out DIR``: generate a synthetic low-light scene from a YAML spec.

Relative paths inside the spec (a capture's folder) resolve against the current working
directory: run from the repository root. Spec errors print one line and exit with status 2.

The scene is generated in a hidden sibling of --out and moved into place when complete. An
existing non-empty --out is replaced only if it holds nothing but an earlier naka-gs-sim scene
(its ``.naka-gs-output`` marker lists the files), so no stale file of another scene survives;
--out may not be, contain or lie inside the spec file or the captured scene it darkens. Ctrl-C or SIGTERM
removes the unfinished scene and exits 130 / 143.
"""

from __future__ import annotations

import shutil
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import tyro
from nerfstudio.utils.rich_utils import CONSOLE

from naka_gs_plugin.data.safe_io import (
    RemovedOnStop,
    UnsafeOutputError,
    check_not_input,
    check_replaceable,
    publish_dir,
    staging_dir,
)
from naka_gs_plugin.shipped import config_file
from naka_gs_plugin.sim.generate import generate
from naka_gs_plugin.sim.spec import CaptureSource, SimSpecError, load_spec


@dataclass
class Sim:
    """Generate a synthetic low-light scene from a YAML spec."""

    spec: tyro.conf.Positional[Path]
    """Scene spec YAML, e.g. configs/scenes/dark-noisy.yaml."""
    out: Path = Path("outputs/sim/scene")
    """Output scene folder (lowlight-data layout)."""
    seed: Optional[int] = None
    """Override the spec's noise seed."""

    def main(self) -> Path:
        """Generate the scene of ``spec`` into ``out`` (see the module docstring); returns ``out``."""
        spec_file = config_file(self.spec)  # the spec --out may not overwrite, shipped or not
        spec = load_spec(spec_file)
        inputs = [spec_file] + ([spec.source.path] if isinstance(spec.source, CaptureSource) else [])
        check_not_input(self.out, inputs, "--out")
        check_replaceable(self.out, "--out", None)
        out = self.out.resolve()
        stage = staging_dir(out)
        try:
            with RemovedOnStop(stage, out, "naka-gs-sim") as stop:
                generate(spec, stage, seed=self.seed)
                with stop.publishing():
                    publish_dir(stage, out, "naka-gs-sim", "--out", None)
        finally:
            shutil.rmtree(stage, ignore_errors=True)  # our own staging folder; gone already once published
        CONSOLE.log(f"naka-gs-sim: scene ready in {self.out}", markup=False)
        return self.out


def entrypoint(args: Optional[Sequence[str]] = None) -> None:
    """Console script ``naka-gs-sim``; a bad spec or --out prints one line and exits with status 2."""
    sim = tyro.cli(Sim, args=args)
    try:
        sim.main()
    except (SimSpecError, UnsafeOutputError) as err:
        CONSOLE.print(f"naka-gs-sim: {err}", markup=False, soft_wrap=True)
        sys.exit(2)


if __name__ == "__main__":
    entrypoint()
