"""``naka-gs-cuda-parity``: our rasterizers against gsplat's CUDA rasterization, and GPU timings.

What is compared, and the tolerances, are described in :mod:`naka_gs_plugin.bench.cuda_parity`. Imports
no nerfstudio (a GPU machine may have none): ``python -m naka_gs_plugin.scripts.cuda_parity`` there.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import tyro

from naka_gs_plugin.bench.cuda_parity import ParityConfig, run


@dataclass
class CudaParity(ParityConfig):
    """Our rasterizers against gsplat's CUDA rasterization (or the torch path as a stand-in)."""

    def main(self) -> None:
        run(self)


def entrypoint(args: Optional[Sequence[str]] = None) -> None:
    """Console script ``naka-gs-cuda-parity``; bad options print one line."""
    parity = tyro.cli(CudaParity, args=args)
    try:
        parity.main()
    except (FileNotFoundError, ValueError) as err:
        raise SystemExit(f"naka-gs-cuda-parity: {err}") from None


if __name__ == "__main__":
    entrypoint()
