"""nerfstudio checkpoints hold numpy scalars (learning rates); ``import naka_gs_plugin`` lets torch's
``weights_only`` loader accept them under the name numpy 1 writes and the one numpy 2 writes, once a naka-gs command
or run has turned the hooks on."""

import io
import pickle
import zipfile

import numpy as np
import pytest
import torch

from naka_gs_plugin.run import nerfstudio_hooks

nerfstudio_hooks.activate()  # as a naka-gs command or run does: registers the safe globals


def _checkpoint_bytes(module: str) -> bytes:
    """``torch.save({"lr": np.float64(...)})`` with the scalar's pickled module name set to ``module``."""
    buf = io.BytesIO()
    torch.save({"lr": np.float64(1.6e-4), "step": 7}, buf, pickle_protocol=2)
    src = zipfile.ZipFile(io.BytesIO(buf.getvalue()))
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as dst:
        for info in src.infolist():
            data = src.read(info)
            if info.filename.endswith("data.pkl"):
                # Protocol 2 names a global as "module\nname\n" (no length prefix): a textual swap is exact.
                old = f"{np.float64(0).__reduce__()[0].__module__}\nscalar\n".encode()
                assert old in data
                data = data.replace(old, f"{module}\nscalar\n".encode())
            dst.writestr(info, data)
    return out.getvalue()


@pytest.mark.parametrize("module", ["numpy.core.multiarray", "numpy._core.multiarray"])
def test_numpy_scalars_load_as_nerfstudio_loads_them(module):
    """torch.load's default, as nerfstudio calls it: ``weights_only=True`` from torch 2.6 on (the registered safe
    globals let numpy scalars through), unrestricted before."""
    state = torch.load(io.BytesIO(_checkpoint_bytes(module)), map_location="cpu")
    assert state == {"lr": pytest.approx(1.6e-4), "step": 7}
    assert isinstance(state["lr"], np.float64)


def test_other_globals_stay_refused():
    payload = io.BytesIO()
    torch.save({"f": print}, payload)
    with pytest.raises(pickle.UnpicklingError):
        torch.load(io.BytesIO(payload.getvalue()), weights_only=True)
