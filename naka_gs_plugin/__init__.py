"""naka-gs: low-light 3D Gaussian Splatting (Naka-GS) as a nerfstudio method plugin.

Layers, bottom to top; a module imports only its own layer and those below (``tests/test_import_graph.py``):

- helpers: :mod:`.cpu` (thread caps), :mod:`.progress`, :mod:`.metrics`, :mod:`.sheet`, :mod:`.shipped`
  (the configs and weights shipped in the package);
- :mod:`naka_gs_plugin.data`: the ``lowlight-data`` dataparser, the image reader, the cache, safe writes;
- :mod:`naka_gs_plugin.enhance`: Naka-Rushton pre-enhancement and the chroma-correction network;
- :mod:`naka_gs_plugin.points`: point sources, alignment, PPM and seeding;
- :mod:`naka_gs_plugin.model`: the splatfacto-derived model and its CPU rasterizers;
- side by side: :mod:`naka_gs_plugin.sim` (the low-light scene simulator) and the method's wiring (the
  low-light datamanager, :mod:`.pipeline`, :mod:`.trainer`, :mod:`.config`, which is kept import-light);
- :mod:`naka_gs_plugin.scripts` (every console script) and :mod:`naka_gs_plugin.bench` (the benchmarks).

Importing the package registers numpy's scalar types as safe globals for ``torch.load``: torch >= 2.6
loads with ``weights_only=True`` and nerfstudio 1.1.5 writes ``np.float64`` learning rates into its
checkpoints, which otherwise breaks ``ns-eval``, ``ns-viewer`` and resume on every machine.
"""

import numpy as _np
import torch as _torch

try:  # numpy >= 1.26; ``numpy.core`` is a deprecated alias from numpy 2 on
    from numpy._core.multiarray import scalar as _scalar
except ImportError:
    from numpy.core.multiarray import scalar as _scalar

# Both names: a checkpoint written under numpy 1 says ``numpy.core...``, under numpy 2 ``numpy._core...``.
_torch.serialization.add_safe_globals(
    [
        (_scalar, "numpy.core.multiarray.scalar"),
        (_scalar, "numpy._core.multiarray.scalar"),
        _np.dtype,
        type(_np.dtype(_np.float64)),
    ]
)
