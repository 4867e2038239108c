"""naka-gs: low-light 3D Gaussian Splatting (Naka-GS) as a nerfstudio method plugin.

Layers, bottom to top; a module imports only its own layer and those below (``tests/test_import_graph.py``):

- helpers: :mod:`.requirements` (versions checked at import), :mod:`.cpu` (thread caps), :mod:`.progress`,
  :mod:`.metrics`, :mod:`.sheet`, :mod:`.shipped` (the configs and weights shipped in the package),
  :mod:`.errors` (the user errors and how a command ends);
- :mod:`naka_gs_plugin.data`: the ``lowlight-data`` dataparser, the image reader, the cache, safe writes;
- :mod:`naka_gs_plugin.run`: the guard rails of a run: its folder's claim, its checkpoints, the checks of its
  configuration, and the one module that touches nerfstudio's internals (:mod:`.run.nerfstudio_hooks`);
- :mod:`naka_gs_plugin.enhance`: Naka-Rushton pre-enhancement and the chroma-correction network;
- :mod:`naka_gs_plugin.points`: point sources, alignment, PPM and seeding;
- :mod:`naka_gs_plugin.model`: the splatfacto-derived model and its CPU rasterizers;
- :mod:`naka_gs_plugin.sim` (the low-light scene simulator), then the method's wiring, one file above the other:
  :mod:`.datamanager`, :mod:`.pipeline`, :mod:`.trainer`, and :mod:`.config` (the presets, the roof);
- :mod:`naka_gs_plugin.scripts` (every console script). The benchmarks live outside the package, in the
  repository's ``benchmarks/``.

Importing the package changes nothing in nerfstudio or torch (every hook is turned on only inside a naka-gs command
or run: :mod:`.run.nerfstudio_hooks`). It lets run configs written before a module moved (:data:`RENAMED`) load:
nerfstudio's ``config.yml`` names the datamanager's module, and only that old name is mapped.
"""

import importlib as _importlib
import importlib.abc as _importlib_abc
import importlib.util as _importlib_util
import sys as _sys

from naka_gs_plugin.requirements import check_installed as _check_installed

_check_installed()  # before torch's import: a too old torch is one line, not an error deep in a kernel

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
