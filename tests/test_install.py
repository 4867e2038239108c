"""pyproject.toml's dependency ranges against the exact sets that are measured (scripts/constraints*.txt): every
pinned version lies in its range, and every lower bound is the oldest set's pin (a bound nobody measured fails)."""

from __future__ import annotations

import fnmatch
import re
import subprocess
import sys
from pathlib import Path
from typing import Dict

import pytest
from packaging.requirements import Requirement
from packaging.specifiers import SpecifierSet
from packaging.utils import canonicalize_name
from packaging.version import Version

from naka_gs_plugin.requirements import incompatible, too_old

tomllib = pytest.importorskip("tomllib", reason="Python < 3.11 has no tomllib; CI runs these on 3.11")

ROOT = Path(__file__).resolve().parents[1]
PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
DEPENDENCIES = {canonicalize_name(r.name): r for r in map(Requirement, PROJECT["dependencies"])}
SETS = {"oldest": ROOT / "scripts" / "constraints-oldest.txt", "newest": ROOT / "scripts" / "constraints.txt"}


def pins(path: Path) -> Dict[str, Version]:
    """``name == version`` lines of a constraints file (comments and blank lines skipped)."""
    found = {}
    for line in path.read_text().splitlines():
        line = line.split("#")[0].strip()
        if line:
            name, version = re.fullmatch(r"([A-Za-z0-9_.\-]+)==(\S+)", line).groups()
            found[canonicalize_name(name)] = Version(version)
    return found


@pytest.mark.parametrize("name", SETS)
def test_each_measured_set_lies_inside_the_ranges(name):
    pinned = pins(SETS[name])
    missing = sorted(set(DEPENDENCIES) - set(pinned))
    assert not missing, f"{SETS[name].name} pins no version of {missing}"
    outside = {dep: str(pinned[dep]) for dep, req in DEPENDENCIES.items() if pinned[dep] not in req.specifier}
    assert not outside, f"{SETS[name].name}: outside pyproject.toml's ranges: {outside}"


def test_every_lower_bound_is_the_oldest_sets_pin():
    oldest = pins(SETS["oldest"])
    for dep, req in DEPENDENCIES.items():
        lower = [Version(s.version) for s in req.specifier if s.operator == ">="]
        assert lower == [oldest[dep]], f"{dep}: lower bound {lower} is not the oldest set's {oldest[dep]}"


def test_requires_python_matches_the_classifiers():
    """The Python versions the classifiers name (the measured ones) are the minor versions requires-python admits."""
    admitted = SpecifierSet(PROJECT["requires-python"])
    named = {c.rsplit(" :: ", 1)[1] for c in PROJECT["classifiers"] if re.fullmatch(r".*Python :: 3\.\d+", c)}
    assert named == {f"3.{minor}" for minor in range(6, 20) if Version(f"3.{minor}.0") in admitted}


def test_every_weights_file_has_its_licence_beside_it():
    """In the package as imported (the wheel, under scripts/check_compat.sh), and named by pyproject's license-files."""
    import naka_gs_plugin

    package = Path(naka_gs_plugin.__file__).parent
    weights = sorted(package.glob("*/weights/*.pt"))
    assert weights and all(list(w.parent.glob("LICENSE-*.txt")) for w in weights), "weights without a licence"
    assert (ROOT / "LICENSE").is_file() and "LICENSE" in PROJECT["license-files"]
    for lic in {lic for w in weights for lic in w.parent.glob("LICENSE-*.txt")}:
        path = lic.relative_to(package.parent).as_posix()
        assert any(fnmatch.fnmatch(path, pattern) for pattern in PROJECT["license-files"]), (
            f"{path}: not in license-files"
        )


REQUIRES = ["torch<2.16,>=2.1.2", "numba<0.69,>=0.60.0", "tyro>=0.8.14", 'pytest>=7; extra == "dev"', "rich>=13.7.1"]


@pytest.mark.parametrize(
    "versions,refused",
    [
        ({"torch": "2.1.2+cu121", "numba": "0.60.0", "tyro": "1.0.17"}, None),  # a local build label is the release
        ({"torch": "2.15.0", "numba": None, "tyro": "0.8.14"}, None),  # numba missing: its fallback, not a refusal
        ({"torch": "2.17.0", "numba": "0.70.0", "tyro": "2.0"}, None),  # newer than tested: pip's to refuse
        ({"torch": "2.0.1", "numba": "0.60.0", "tyro": "1.0"}, "torch"),
        ({"torch": "2.14.1", "numba": "0.59.1", "tyro": "1.0"}, "numba"),
        ({"torch": "2.14.1", "numba": "0.60.0", "tyro": "0.8.4"}, "tyro"),
    ],
)
def test_an_older_dependency_is_refused_in_one_line(versions, refused):
    message = too_old(REQUIRES, lambda name: versions.get(name, "0.0.1"))
    if refused is None:
        assert message is None
    else:
        req = next(r for r in REQUIRES if r.startswith(refused))
        spec = str(Requirement(req).specifier)
        assert message == (
            f"naka-gs supports {refused}{spec}, and this environment has {refused} {versions[refused]}: "
            f"pip install '{refused}{spec}' (or pip install naka-gs again, which installs it)"
        )


KORNIA_RANGE = "kornia<0.8.3,>=0.7.3"


@pytest.mark.parametrize(
    "versions,refused",
    [
        ({"kornia": "0.8.2", "torch": "2.1.2+cu121"}, False),  # our range's newest, with the guide's torch
        ({"kornia": "0.8.3", "torch": "2.14.1"}, False),  # outside the range, but not known to fail: pip's to refuse
        ({"kornia": "0.8.3", "torch": "2.2.0"}, False),
        ({"kornia": "0.8.3", "torch": None}, False),  # torch missing is another problem, not this pair's
        ({"kornia": "0.8.3", "torch": "2.1.2+cu121"}, True),
        ({"kornia": "0.9.2", "torch": "2.1.2"}, True),
        ({"kornia": "0.8.3", "torch": "2.2.0rc1"}, True),  # a pre-release of 2.2 is below 2.2
    ],
)
def test_a_pair_known_to_fail_together_is_refused_in_one_line(versions, refused):
    message = incompatible([KORNIA_RANGE, "torch>=2.1.2,<2.16"], versions.get)
    if not refused:
        assert message is None
    else:
        assert message == (
            f"kornia {versions['kornia']} fails at import with torch {versions['torch']} (kornia>=0.8.3 needs "
            f"torch>=2.2): pip install '{KORNIA_RANGE}' (naka-gs's range, which works with torch {versions['torch']})"
        )


def test_importing_the_plugin_beside_a_known_bad_pair_ends_in_one_line():
    """As ns-train loading our entry point (or a naka-gs-* script) meets it: no traceback, the fix, exit status 1."""
    fake = (
        "import importlib.metadata as m; version = m.version; "
        "m.version = lambda n: {'kornia': '0.8.3', 'torch': '2.1.2'}.get(n) or version(n); "
        "import naka_gs_plugin"
    )
    proc = subprocess.run([sys.executable, "-c", fake], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr.splitlines() == [
        f"naka-gs: kornia 0.8.3 fails at import with torch 2.1.2 (kornia>=0.8.3 needs torch>=2.2): "
        f"pip install '{DEPENDENCIES['kornia']}' (naka-gs's range, which works with torch 2.1.2)"
    ], proc.stderr
