"""Wall seconds per stage of cpu-fast renders (:func:`profile_stages`), for ``python -m benchmarks.rasterizer``.

The stages are those of :class:`~naka_gs_plugin.model.rasterize_cpu_fast._TileComposite`: "sort+bin" (the tile
lists), "forward kernel", "backward kernel" and "reduce+scatter". Outside :func:`profile_stages` a stage costs one
``is None`` test.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from typing import Dict, Iterator, Optional

STAGE_SECONDS: Optional[Dict[str, float]] = None
"""When a dict (see :func:`profile_stages`), wall seconds per stage are added to it."""


@contextmanager
def profile_stages() -> Iterator[Dict[str, float]]:
    """Collect wall seconds per stage ("sort+bin", "forward kernel", "backward kernel",
    "reduce+scatter") of the renders inside the block (used by ``python -m benchmarks.rasterizer``)."""
    global STAGE_SECONDS
    STAGE_SECONDS = {}
    try:
        yield STAGE_SECONDS
    finally:
        STAGE_SECONDS = None


@contextmanager
def _stage(name: str) -> Iterator[None]:
    if STAGE_SECONDS is None:
        yield
        return
    started = time.perf_counter()
    yield
    STAGE_SECONDS[name] = STAGE_SECONDS.get(name, 0.0) + time.perf_counter() - started
