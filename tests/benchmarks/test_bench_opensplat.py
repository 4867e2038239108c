"""The OpenSplat side-by-side bench gives both trainers the same views, images and seed points."""

import json
from pathlib import Path

import pycolmap
import pytest

from benchmarks.harness import timed
from benchmarks.opensplat import prepare
from tests.helpers import SHARED_DATA

SOFA = SHARED_DATA / "lom" / "sofa"


@pytest.mark.skipif(not SOFA.is_dir(), reason="needs the LOM data (../shared/data/lom)")
@pytest.mark.parametrize("images", ["high", "low"])
def test_both_trainers_get_the_training_views_and_their_colmap_points(tmp_path, images):
    project, scene = prepare(SOFA, images, tmp_path)
    train = json.loads((SOFA / "transforms_train.json").read_text())["frames"]
    names = sorted(Path(f["file_path"]).name for f in train)
    model = pycolmap.Reconstruction(str(project / "sparse" / "0"))
    assert sorted(image.name for image in model.images.values()) == names
    assert sorted(p.name for p in (project / "images").iterdir()) == names
    assert all((project / "images" / n).resolve() == (SOFA / images / n).resolve() for n in names)
    ours = json.loads((scene / "transforms_train.json").read_text())["frames"]
    assert [f["file_path"] for f in ours] == [f"{images}/{Path(f['file_path']).name}" for f in train]
    assert all((scene / f["file_path"]).resolve() == (SOFA / f["file_path"]).resolve() for f in ours)
    assert (scene / "colmap_sparse" / "0" / "points3D.bin").resolve() == (project / "sparse" / "0" / "points3D.bin")
    full = pycolmap.Reconstruction(str(SOFA / "colmap_sparse" / "0"))
    assert 0 < model.num_points3D() <= full.num_points3D()


@pytest.mark.skipif(not Path("/usr/bin/time").exists(), reason="needs GNU time (/usr/bin/time)")
def test_timed_reads_wall_and_peak_rss(tmp_path):
    wall, rss = timed(["python3", "-c", "x = bytearray(64 << 20)"], {"PATH": "/usr/bin:/bin"}, tmp_path / "log")
    assert 0 < wall < 30 and 0.06 < rss < 1.0
