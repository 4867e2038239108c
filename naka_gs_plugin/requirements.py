"""The versions this package needs of what it imports, checked once at import (a leaf module).

pip installs naka-gs only beside versions inside its ranges (pyproject.toml); a forced install or a later downgrade
can still leave torch, numba, jaxtyping or tyro below what the code uses. Those get one line at import naming the
version and the fix, instead of an AttributeError deep in a kernel. Versions above the ranges are pip's to refuse:
they are untested, not known to fail, except the pairs in :data:`INCOMPATIBLE`, known to fail together, which get the
same one line. Running from a source tree without an install there is nothing to compare.
"""

from __future__ import annotations

from importlib import metadata
from typing import Callable, Iterable, Optional, Tuple

from packaging.requirements import Requirement
from packaging.specifiers import SpecifierSet
from packaging.version import Version

from naka_gs_plugin.errors import UserError, user_error_exit

CHECKED = ("torch", "numba", "jaxtyping", "tyro")
"""Where an older version fails at run time, not at import: torch's CPU kernels and probes, numba's compiled
kernels, jaxtyping's shape annotations, tyro's CLIs."""


INCOMPATIBLE = (
    # kornia 0.8.3 compiles ``Tensor.any(dim=(-2, -1))`` with torch.jit.script when kornia is imported
    # (kornia/geometry/epipolar/essential.py); TorchScript has ``any`` over several dims from torch 2.2 on.
    ("kornia", ">=0.8.3", "torch", ">=2.2"),
)
"""(package, its versions, other package, the versions of the other those need): pairs that fail at import, outside
our ranges (pip installs them only when told to: ``pip install kornia==0.8.3``)."""


class UnsupportedVersionError(UserError):
    """A dependency older than this package supports, or known to fail beside another (one line: the versions found,
    the range, the fix)."""


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


def incompatible(
    requirements: Iterable[str],
    version_of: Callable[[str], Optional[str]],
    pairs: Iterable[Tuple[str, str, str, str]] = INCOMPATIBLE,
) -> Optional[str]:
    """The one-line refusal for the first of ``pairs`` installed together, naming both versions and our range of the
    first package as the fix, else None."""
    ranges = {r.name: r.specifier for r in map(Requirement, requirements) if r.marker is None}
    for name, versions, other, needs in pairs:
        found, other_found = version_of(name), version_of(other)
        if found is None or other_found is None:
            continue
        if _within(found, versions) and not _within(other_found, needs):
            return (
                f"{name} {found} fails at import with {other} {other_found} ({name}{versions} needs {other}{needs}): "
                f"pip install '{name}{ranges[name]}' (naka-gs's range, which works with {other} {other_found})"
            )
    return None


def _within(version: str, specifier: str) -> bool:
    """A local build label (``2.1.2+cu121``) is its release; a pre-release is compared too (2.2.0rc1 is below 2.2)."""
    return SpecifierSet(specifier).contains(Version(version).public, prereleases=True)


def _installed(name: str) -> Optional[str]:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def check_installed() -> None:
    """End the process with the line ``naka-gs: <message>`` of an :class:`UnsupportedVersionError` if an installed
    dependency is older than naka-gs supports, or known to fail with another one installed beside it."""
    try:
        requirements = metadata.requires("naka-gs") or []
    except metadata.PackageNotFoundError:
        return
    message = too_old(requirements, _installed) or incompatible(requirements, _installed)
    if message:
        # At import, before any code of ours could catch an exception (ns-train loading our entry point, a naka-gs-*
        # script's module): the process ends as a command does on a UserError, in one line with exit status 1.
        raise user_error_exit(UnsupportedVersionError(message))
