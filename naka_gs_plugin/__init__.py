"""naka-gs: low-light 3D Gaussian Splatting (Naka-GS) as a nerfstudio method plugin.

Layers, bottom to top; a module imports only its own layer and those below (``tests/test_import_graph.py``):

- helpers: :mod:`.requirements` (versions checked at import), :mod:`.cpu` (thread caps), :mod:`.progress`,
  :mod:`.metrics`, :mod:`.sheet`, :mod:`.shipped`
  (the configs and weights shipped in the package);
- :mod:`naka_gs_plugin.data`: the ``lowlight-data`` dataparser, the image reader, the cache, safe writes;
- :mod:`naka_gs_plugin.enhance`: Naka-Rushton pre-enhancement and the chroma-correction network;
- :mod:`naka_gs_plugin.points`: point sources, alignment, PPM and seeding;
- :mod:`naka_gs_plugin.model`: the splatfacto-derived model and its CPU rasterizers;
- side by side: :mod:`naka_gs_plugin.sim` (the low-light scene simulator) and the method's wiring
  (:mod:`.datamanager`, :mod:`.pipeline`, :mod:`.trainer`, :mod:`.config`, which is kept import-light);
- :mod:`naka_gs_plugin.scripts` (every console script). The benchmarks live outside the package, in the
  repository's ``benchmarks/``.

Importing the package registers numpy's scalar types as safe globals for ``torch.load``: torch >= 2.6
loads with ``weights_only=True`` and nerfstudio 1.1.5 writes ``np.float64`` learning rates into its
checkpoints, which otherwise breaks ``ns-eval``, ``ns-viewer`` and resume on every machine. It also
lets run configs written before a module moved (:data:`RENAMED`) load: nerfstudio's ``config.yml`` names
the datamanager's module.
"""

import importlib as _importlib
import importlib.abc as _importlib_abc
import importlib.util as _importlib_util
import sys as _sys

from naka_gs_plugin.requirements import check_installed as _check_installed

_check_installed()  # before torch's import: a too old torch is one line, not an error deep in a kernel

import numpy as _np  # noqa: E402
import torch as _torch  # noqa: E402

try:  # numpy >= 1.26; ``numpy.core`` is a deprecated alias from numpy 2 on
    from numpy._core.multiarray import scalar as _scalar
except ImportError:
    from numpy.core.multiarray import scalar as _scalar

# Both names: a checkpoint written under numpy 1 says ``numpy.core...``, under numpy 2 ``numpy._core...``.
# Before torch 2.6 ``torch.load`` defaults to ``weights_only=False`` (nothing to register), and before 2.5 it
# has no ``add_safe_globals`` with names.
if _torch.__version__ >= "2.6":
    _torch.serialization.add_safe_globals(
        [
            (_scalar, "numpy.core.multiarray.scalar"),
            (_scalar, "numpy._core.multiarray.scalar"),
            _np.dtype,
            type(_np.dtype(_np.float64)),
        ]
    )

RENAMED = {"naka_gs_plugin.data.lowlight_datamanager": "naka_gs_plugin.datamanager"}
"""Old module name -> new one, for saved run configs (``!!python/object:<module>.<class>``)."""


class _RenamedModules(_importlib_abc.MetaPathFinder, _importlib_abc.Loader):
    """Imports an old module name as the module it became (the same module object, not a copy)."""

    def find_spec(self, name, path=None, target=None):
        return _importlib_util.spec_from_loader(name, self) if name in RENAMED else None

    def create_module(self, spec):
        module = _importlib.import_module(RENAMED[spec.name])
        spec.loader_state = module.__spec__  # importlib sets the alias's spec on it next
        return module

    def exec_module(self, module):
        module.__spec__ = module.__spec__.loader_state  # its own spec back


_sys.meta_path.append(_RenamedModules())
