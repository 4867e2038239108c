"""The plugin's errors a user can fix, and the one line they end a command with.

A leaf module (it imports nothing of the plugin), so the data layer and the trainer can both use it.
"""

from __future__ import annotations

from typing import Optional

USER_ERRORS = frozenset(
    {
        "naka_gs_plugin.data.images.ImageReadError",
        "naka_gs_plugin.data.lowlight_dataparser.LowLightDataError",
        "naka_gs_plugin.data.pairs.PairsError",
        "naka_gs_plugin.data.safe_io.UnsafeOutputError",
        "naka_gs_plugin.enhance.checkpoint.CorrectionWeightsError",
        "naka_gs_plugin.enhance.checkpoint.CorrectionWeightsNotFoundError",
        "naka_gs_plugin.enhance.pipeline.EnhanceOptionError",
        "naka_gs_plugin.enhance.profile.CameraProfileError",
        "naka_gs_plugin.model.lpips.LPIPSWeightsError",
        "naka_gs_plugin.model.naka_gs_model.NonFiniteTrainingError",
        "naka_gs_plugin.model.naka_gs_model.RasterizerOptionError",
        "naka_gs_plugin.points.align.AlignmentError",
        "naka_gs_plugin.points.sfm.SfMError",
        "naka_gs_plugin.points.sources.PointSourceError",
        "naka_gs_plugin.requirements.UnsupportedVersionError",
        "naka_gs_plugin.scripts.ppm.PpmOutputError",
        "naka_gs_plugin.scripts.process_data.ProcessDataError",
        "naka_gs_plugin.sim.spec.SimSpecError",
    }
)
"""The plugin's exceptions for a problem the user can fix (a bad file, an option out of range), by qualified
name: each message is one line naming the file or option and the fix. Named, not imported (points.sfm imports
pycolmap): a class whose module is not loaded cannot have been raised. tests/test_run_folder.py checks that every
``*Error`` class of the package is here or is a ``SystemExit`` already."""


def signal_exit_status(signum: int) -> int:
    """The exit status of a command that ``signum`` stopped: 128 + its number, as shells report a command the signal
    killed (130 for Ctrl-C, 143 for SIGTERM), also when the command cleaned up and exited by itself."""
    return 128 + int(signum)


def is_user_error(err: BaseException) -> bool:
    """Whether ``err`` is one of :data:`USER_ERRORS` (or a subclass of one)."""
    return any(f"{cls.__module__}.{cls.__qualname__}" in USER_ERRORS for cls in type(err).__mro__)


def user_error_exit(err: BaseException) -> Optional[SystemExit]:
    """``SystemExit("naka-gs: <message>")`` (exit status 1, no traceback) for one of :data:`USER_ERRORS`, else
    None: any other exception is a bug and keeps its traceback."""
    return SystemExit(f"naka-gs: {err}") if is_user_error(err) else None
