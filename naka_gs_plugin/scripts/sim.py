"""``naka-gs-sim SPEC --out DIR``: generate a synthetic low-light scene from a YAML spec.

Relative paths inside the spec (a capture's folder) resolve against the current working
directory: run from the repository root. Spec errors print one line ``naka-gs: <message>`` and exit with status 1.

The scene is generated in a hidden sibling of --out and moved into place when complete. An
existing non-empty --out is replaced only if it holds nothing but an earlier naka-gs-sim scene
(its ``.naka-gs-output`` marker lists the files), so no stale file of another scene survives;
--out may not be, contain or lie inside the spec file or the captured scene it darkens. Ctrl-C or SIGTERM
removes the unfinished scene and exits 130 / 143.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import tyro
from nerfstudio.utils.rich_utils import CONSOLE

from naka_gs_plugin.data.safe_io import staged_output
from naka_gs_plugin.scripts import run
from naka_gs_plugin.shipped import config_file
from naka_gs_plugin.sim.generate import generate
from naka_gs_plugin.sim.spec import CaptureSource, load_spec


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
        with staged_output(self.out, tool="naka-gs-sim", what="--out", inputs=inputs) as stage:
            generate(spec, stage, seed=self.seed)
        CONSOLE.log(f"naka-gs-sim: scene ready in {self.out}", markup=False)
        return self.out


def entrypoint(args: Optional[Sequence[str]] = None) -> None:
    """Console script ``naka-gs-sim`` (:func:`naka_gs_plugin.scripts.run`)."""
    run(Sim.main, Sim, args)


if __name__ == "__main__":
    entrypoint()
