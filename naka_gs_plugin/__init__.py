"""naka-gs: low-light 3D Gaussian Splatting (Naka-GS) as a nerfstudio method plugin.

Data flows images -> :mod:`enhance` -> (points) -> :mod:`model` -> eval, with no back-edges:

- :mod:`naka_gs_plugin.data`: the ``lowlight-data`` dataparser and the low-light datamanager;
- :mod:`naka_gs_plugin.enhance`: Naka-Rushton pre-enhancement (and, later, the correction net);
- :mod:`naka_gs_plugin.model`: the splatfacto-derived model and its CPU rasterizer;
- :mod:`naka_gs_plugin.config`: the ``naka-gs`` method wiring them together (kept import-light).

Importing the package registers numpy's scalar types as safe globals for ``torch.load``: torch >= 2.6
loads with ``weights_only=True`` and nerfstudio 1.1.5 writes ``np.float64`` learning rates into its
checkpoints, which otherwise breaks ``ns-eval``, ``ns-viewer`` and resume on every machine.
"""

import numpy as _np
import torch as _torch

_torch.serialization.add_safe_globals(
    [_np.core.multiarray.scalar, _np.dtype, type(_np.dtype(_np.float64))]  # type: ignore[attr-defined]
)
