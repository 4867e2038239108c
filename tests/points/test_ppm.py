"""PPM (voxel pooling, progressive pruning) and point-set alignment on small seeded CPU data."""

import math
from collections import defaultdict

import numpy as np
import pytest

from naka_gs_plugin.points import ppm
from naka_gs_plugin.points.align import AlignmentError, apply_sim3, match_names, umeyama
from naka_gs_plugin.points.ppm import progressive_prune, run_ppm, voxel_pool


def _brute_pool(xyz, rgb, voxel):
    groups = defaultdict(list)
    for p, c in zip(xyz.tolist(), rgb.tolist()):
        groups[tuple(math.floor(v / voxel) for v in p)].append((p, c))
    out = {}
    for k, items in groups.items():
        ps = np.array([i[0] for i in items])
        cs = np.array([i[1] for i in items])
        out[k] = (ps.mean(axis=0), np.floor(cs.mean(axis=0) + 0.5), len(items))
    return out


def _assert_pool_matches_brute(xyz, rgb, voxel):
    ref = _brute_pool(xyz, rgb, voxel)
    pxyz, prgb = voxel_pool(xyz, rgb, voxel)
    assert pxyz.shape == (len(ref), 3) and prgb.dtype == np.uint8
    for p, c in zip(pxyz, prgb):
        rp, rc, _ = ref.pop(tuple(math.floor(v / voxel) for v in p))
        np.testing.assert_allclose(p, rp, rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(c, rc)
    assert not ref


@pytest.mark.parametrize("voxel", [0.01, 0.25])
def test_voxel_pool_matches_brute_force(voxel):
    rng = np.random.default_rng(0)
    xyz = rng.uniform(-1.0, 1.0, (3000, 3))
    # points exactly on voxel boundaries (incl. negative ones) and repeated voxels
    xyz[:200] = rng.integers(-8, 8, (200, 3)) * voxel
    xyz[200:400] = xyz[:200] + voxel * 0.5
    rgb = rng.integers(0, 256, (3000, 3), dtype=np.uint8)
    _assert_pool_matches_brute(xyz, rgb, voxel)


def test_voxel_pool_huge_key_range_uses_exact_fallback():
    rng = np.random.default_rng(1)
    xyz = np.concatenate([rng.uniform(-1, 1, (500, 3)), [[1e6, -1e6, 1e6], [1e6 + 1e-4, -1e6, 1e6]]])
    rgb = rng.integers(0, 256, (502, 3), dtype=np.uint8)
    _assert_pool_matches_brute(xyz, rgb, 0.01)


def test_voxel_pool_rejects_nonfinite():
    with pytest.raises(ValueError, match="finite"):
        voxel_pool(np.array([[0.0, np.nan, 0.0]]), np.zeros((1, 3), np.uint8))


def _cluster_and_isolated(seed=0):
    rng = np.random.default_rng(seed)
    cluster = rng.normal(0.0, 0.0005, (4000, 3))
    isolated = rng.uniform(2.0, 10.0, (2000, 3))
    xyz = np.concatenate([cluster, isolated])
    return xyz, np.zeros_like(xyz, dtype=np.uint8)


def test_prune_thins_dense_cluster_keeps_isolated():
    xyz, rgb = _cluster_and_isolated()
    pxyz, _, stats = progressive_prune(xyz, rgb, iterations=3, min_points=100)
    kept_cluster = (np.linalg.norm(pxyz, axis=1) < 1.0).sum() / 4000
    kept_isolated = (np.linalg.norm(pxyz, axis=1) >= 1.0).sum() / 2000
    assert kept_isolated == 1.0 and kept_cluster < 0.5
    counts = [stats["input_count"]] + [h["count_after"] for h in stats["iterations"]]
    assert all(a >= b for a, b in zip(counts, counts[1:])) and counts[-1] == stats["final_count"]


def test_prune_rollback_and_stop():
    xyz, rgb = _cluster_and_isolated()
    _, _, free = progressive_prune(xyz, rgb, iterations=6, min_points=0)
    first = free["iterations"][0]["count_after"]
    pxyz, _, stats = progressive_prune(xyz, rgb, iterations=6, min_points=first)
    hist = stats["iterations"]
    assert not hist[0]["rolled_back"] and hist[1]["rolled_back"] and len(hist) == 2
    assert hist[1]["count_after"] == hist[1]["count_before"] == first == stats["final_count"] == len(pxyz)
    assert hist[1]["count_proposed"] < first


def test_prune_deterministic_per_seed():
    xyz, rgb = _cluster_and_isolated()
    a = progressive_prune(xyz, rgb, iterations=1, tau0=3e-4, seed=3, min_points=0)[0]
    b = progressive_prune(xyz, rgb, iterations=1, tau0=3e-4, seed=3, min_points=0)[0]
    c = progressive_prune(xyz, rgb, iterations=1, tau0=3e-4, seed=4, min_points=0)[0]
    np.testing.assert_array_equal(a, b)
    assert len(a) > 2100
    assert a.shape != c.shape or not np.array_equal(a, c)


@pytest.mark.parametrize("mode", ["reference", "paper"])
def test_prune_tau_schedule(mode):
    xyz, rgb = _cluster_and_isolated()
    tau0, beta = 0.002, 0.5
    _, _, stats = progressive_prune(xyz, rgb, tau0=tau0, beta=beta, iterations=4, min_points=0, tau_update=mode)
    hist, m0, tau = stats["iterations"], stats["input_count"], tau0
    assert len(hist) == 4
    for h in hist:
        assert h["tau"] == pytest.approx(tau, rel=1e-12)
        n = h["count_before"] if mode == "reference" else h["count_after"]
        tau *= math.exp(beta * n / m0)
    assert stats["final_tau"] == pytest.approx(tau, rel=1e-12)


def test_run_ppm_edge_cases():
    empty = run_ppm(np.zeros((0, 3)), np.zeros((0, 3), np.uint8))
    assert empty[0].shape == (0, 3) and empty[2]["final_count"] == 0
    one = run_ppm(np.array([[0.3, 0.2, 0.1]]), np.array([[1, 2, 3]], np.uint8))
    assert one[2]["voxel_count"] == one[2]["final_count"] == 1
    np.testing.assert_array_equal(one[1], [[1, 2, 3]])
    dup = run_ppm(np.full((100, 3), 0.123), np.full((100, 3), 7, np.uint8))
    assert dup[2]["voxel_count"] == 1 and dup[2]["final_count"] == 1


def test_run_ppm_drops_nonfinite_and_handles_large_coordinates():
    rng = np.random.default_rng(2)
    xyz = rng.uniform(-1e6, 1e6, (2000, 3))
    xyz[:5, 0] = np.nan
    xyz[5:8, 2] = np.inf
    rgb = rng.integers(0, 256, (2000, 3), dtype=np.uint8)
    pxyz, prgb, summary = run_ppm(xyz, rgb, min_points=10)
    assert summary["nonfinite_dropped"] == 8 and summary["finite_count"] == 1992
    assert summary["voxel_count"] == 1992 and np.isfinite(pxyz).all() and len(pxyz) == len(prgb)
    assert set(summary["timings_s"]) == {"filter", "voxel_pool", "prune", "total"}


def _random_rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


@pytest.mark.parametrize("mode", ["sim3", "rigid"])
def test_umeyama_recovers_known_transform(mode):
    rng = np.random.default_rng(5)
    src = rng.normal(size=(50, 3))
    s_true = 2.5 if mode == "sim3" else 1.0
    r_true, t_true = _random_rotation(rng), rng.normal(size=3)
    dst = apply_sim3(s_true, r_true, t_true, src)
    s, r, t, rms = umeyama(src, dst, mode)
    assert abs(s - s_true) < 1e-6 and np.abs(r - r_true).max() < 1e-6 and np.abs(t - t_true).max() < 1e-6
    assert rms < 1e-6 and abs(np.linalg.det(r) - 1.0) < 1e-9
    noisy = dst + rng.normal(0.0, 0.01, dst.shape)
    s, r, t, rms = umeyama(src, noisy, mode)
    assert abs(s - s_true) < 0.01 and np.abs(r - r_true).max() < 0.01 and np.abs(t - t_true).max() < 0.02
    assert 0.005 < rms < 0.03


def test_umeyama_reflection_fixed():
    rng = np.random.default_rng(6)
    src = rng.normal(size=(20, 3))
    _, r, _, rms = umeyama(src, src * np.array([1.0, 1.0, -1.0]))
    assert np.linalg.det(r) == pytest.approx(1.0) and rms > 0.1


@pytest.mark.parametrize(
    "src, match",
    [
        (np.zeros((2, 3)), ">= 3 correspondences"),
        (np.ones((5, 3)), "coincident"),
        (np.outer(np.arange(5.0), [1.0, 2.0, 3.0]), "collinear"),
    ],
)
@pytest.mark.parametrize("mode", ["sim3", "rigid"])
def test_umeyama_rejects_degenerate(src, match, mode):
    with pytest.raises(AlignmentError, match=match) as err:
        umeyama(src, src + 1.0, mode)
    assert "\n" not in str(err.value) and isinstance(err.value, ValueError)


def test_match_names_rules_priority_and_uniqueness():
    src = ["IMG_001.JPG", "frame_02_enhanced.png", "view7.png", "a3.png", "b3.png", "shot_10.png", "x.png"]
    dst = ["img_001.jpg", "frame_02.jpg", "cam_007.jpg", "c3.jpg", "shot_10_img.png", "shot_0010.png", "y.png"]
    pairs = match_names(src, dst)
    # exact name (case-insensitive); suffix-stripped stem; last integer (7 == 007); "3" ambiguous in src;
    # shot_10 matches shot_10_img by stem before shot_0010 by integer; x/y unmatched.
    assert pairs == [(0, 0), (1, 1), (2, 2), (5, 4)]
    js = [j for _, j in pairs]
    assert len(js) == len(set(js))
    assert match_names(["1.png"], ["a1.png", "b01.png"]) == []


def _naive_prune(xyz, tau0, beta, iterations, min_points, eps, seed):
    from scipy.spatial import cKDTree

    rng, tau, m0, taus = np.random.default_rng(seed), tau0, len(xyz), []
    for _ in range(iterations):
        if len(xyz) <= 1:
            break
        d = cKDTree(xyz).query(xyz, k=2)[0][:, 1]
        keep = rng.random(len(xyz)) < np.minimum(1.0, d / (tau + eps))
        taus.append(tau)
        if keep.sum() < min_points:
            break
        tau *= math.exp(beta * len(xyz) / m0)
        xyz = xyz[keep]
    return xyz, taus


@pytest.mark.parametrize("tight_lists", [False, True])
@pytest.mark.parametrize("iterations, min_points", [(8, 0), (8, 2200), (3, 10)])
def test_prune_matches_naive_fresh_kdtree(iterations, min_points, tight_lists, monkeypatch):
    if tight_lists:  # force the re-query paths (original tree, then survivors' tree) often
        monkeypatch.setattr(ppm, "_NEIGHBOURS", 2)
        monkeypatch.setattr(ppm, "_RETRY_NEIGHBOURS", 3)
    xyz, rgb = _cluster_and_isolated(seed=7)
    xyz = np.concatenate([xyz, np.random.default_rng(8).uniform(-0.01, 0.01, (3000, 3))])
    xyz = np.concatenate([xyz, xyz[::40]])  # exact duplicates: nearest distance 0
    rgb = np.zeros_like(xyz, dtype=np.uint8)
    ref, taus = _naive_prune(xyz, 2e-3, 0.3, iterations, min_points, 1e-8, 11)
    got, _, stats = progressive_prune(xyz, rgb, 2e-3, 0.3, iterations, min_points, 1e-8, 11)
    np.testing.assert_array_equal(got, ref)
    assert [h["tau"] for h in stats["iterations"]] == taus
