"""The versions this package needs of what it imports, checked once at import (a leaf module).

pip installs naka-gs only beside versions inside its ranges (pyproject.toml); a forced install or a later downgrade
can still leave torch, numba, jaxtyping or tyro below what the code uses. Those get one line at import naming the
version and the fix, instead of an AttributeError deep in a kernel. Versions above the ranges are pip's to refuse:
they are untested, not known to fail. Running from a source tree without an install there is nothing to compare.
"""

from __future__ import annotations

from importlib import metadata
from typing import Callable, Iterable, Optional

from packaging.requirements import Requirement
from packaging.version import Version

from naka_gs_plugin.errors import UserError

CHECKED = ("torch", "numba", "jaxtyping", "tyro")
"""Where an older version fails at run time, not at import: torch's CPU kernels and probes, numba's compiled
kernels, jaxtyping's shape annotations, tyro's CLIs."""


class UnsupportedVersionError(UserError, ImportError):
    """A dependency older than this package supports (one line: the version found, the range, the fix)."""


def too_old(
    requirements: Iterable[str], version_of: Callable[[str], Optional[str]], checked: Iterable[str] = CHECKED
) -> Optional[str]:
    """The one-line refusal for the first of ``checked`` whose installed version is below its requirement's lower
    bound, else None (a package not installed is not refused here: numba's absence has a fallback)."""
    for req in map(Requirement, requirements):
        if req.marker is not None or req.name not in checked:
            continue
        found = version_of(req.name)
        lower = [s for s in req.specifier if s.operator in (">=", ">")]
        if found is not None and not all(s.contains(Version(found).public, prereleases=True) for s in lower):
            return (
                f"naka-gs supports {req.name}{req.specifier}, and this environment has {req.name} {found}: "
                f"pip install '{req.name}{req.specifier}' (or pip install naka-gs again, which installs it)"
            )
    return None


def _installed(name: str) -> Optional[str]:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def check_installed() -> None:
    """Raise :class:`UnsupportedVersionError` if an installed dependency is older than naka-gs supports."""
    try:
        requirements = metadata.requires("naka-gs") or []
    except metadata.PackageNotFoundError:
        return
    message = too_old(requirements, _installed)
    if message:
        raise UnsupportedVersionError(message)
