"""Point Preprocessing Module (PPM) of Naka-GS: voxel pooling then progressive density pruning.

Coordinates are in the normalized scene frame (the same unit as ``voxel`` and ``tau0``); colours
are uint8 RGB. All functions take and return arrays (no file I/O). Voxel keys are
``floor(p / voxel)`` computed in float64; outputs are ordered by voxel key (x, then y, then z).
"""

from __future__ import annotations

import math
import time
from typing import Any, Dict, List, Literal, Optional, Tuple

import numpy as np
import torch
from jaxtyping import Float, UInt8
from scipy.spatial import cKDTree

from naka_gs_plugin.errors import UserError

_KEY_LIMIT = float(2**62)

# The PPM parameters' defaults (the authors'), also those of ``--pipeline.init.*`` and ``naka-gs-ppm``.
VOXEL = 0.01
"""Voxel edge of the pooling, normalized scene units."""
TAU0 = 0.005
"""Initial pruning distance threshold, same units."""
BETA = 0.01
"""Threshold growth rate per pruning iteration."""
ITERATIONS = 6
"""Pruning iterations."""
MIN_POINTS = 5000
"""Minimum points kept by pruning."""
SEED = 42
"""Seed of the pruning draws."""


class PPMOptionError(UserError, ValueError):
    """A PPM setting it cannot run with (a voxel size of 0 or one too small for the cloud's extent); one line."""


def _group_order(xyz: torch.Tensor, voxel: float) -> Tuple[np.ndarray, np.ndarray]:
    """Permutation sorting points by voxel key ``floor(xyz / voxel)`` (x, y, z lexicographic), and group sizes.

    Fast path: exact mixed-radix pack of the key offsets (a float64 dot product of integers
    < 2**53) with the point index in the low bits, sorted by ``torch.sort`` (multithreaded).
    Otherwise, an exact ``np.lexsort`` on the three key columns.
    """
    n = xyz.shape[0]
    q = xyz / voxel
    q.floor_()
    qmin, qmax = torch.aminmax(q, dim=0)
    if not bool(torch.isfinite(torch.cat([qmin, qmax])).all()) or max(-qmin.min(), qmax.max()) >= _KEY_LIMIT:
        raise PPMOptionError("voxel_pool needs finite coordinates whose voxel keys fit in int64")
    sx, sy, sz = (int(v) + 1 for v in (qmax - qmin).tolist())
    idx_bits = max(1, (n - 1).bit_length())
    key_bits = (sx * sy * sz - 1).bit_length()
    if key_bits <= 53 and key_bits + idx_bits <= 63:
        w = torch.tensor([float(sy * sz), float(sz), 1.0], dtype=torch.float64)
        packed = (q.sub_(qmin) @ w).long()
        packed <<= idx_bits
        packed |= torch.arange(n)
        packed = torch.sort(packed).values
        order = packed & ((1 << idx_bits) - 1)
        counts = torch.unique_consecutive(packed >> idx_bits, return_counts=True)[1]
        return order.numpy(), counts.numpy()
    k = q.numpy()
    order = np.lexsort((k[:, 2], k[:, 1], k[:, 0]))
    sk = k[order]
    new = np.ones(n, dtype=bool)
    np.any(sk[1:] != sk[:-1], axis=1, out=new[1:])
    return order, np.diff(np.append(np.flatnonzero(new), n))


def voxel_pool(
    xyz: Float[np.ndarray, "N 3"], rgb: UInt8[np.ndarray, "N 3"], voxel: float = VOXEL
) -> Tuple[Float[np.ndarray, "M 3"], UInt8[np.ndarray, "M 3"]]:
    """One point per occupied voxel ``floor(p / voxel)``: mean position (float64), mean colour rounded half-up."""
    if voxel <= 0:
        raise PPMOptionError(f"voxel must be > 0, got {voxel}")
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    rgb = np.asarray(rgb).reshape(-1, 3)
    if rgb.shape[0] != xyz.shape[0]:
        raise ValueError(f"xyz has {xyz.shape[0]} points but rgb has {rgb.shape[0]}")
    if xyz.shape[0] == 0:
        return np.zeros((0, 3), np.float64), np.zeros((0, 3), np.uint8)
    order, counts = _group_order(torch.from_numpy(xyz), voxel)
    sums = torch.segment_reduce(torch.from_numpy(np.take(xyz, order, axis=0)), "sum", lengths=torch.from_numpy(counts))
    mean_xyz = sums.numpy() / counts[:, None]
    starts = np.cumsum(counts) - counts
    csum = np.add.reduceat(np.take(rgb, order, axis=0).astype(np.int64), starts, axis=0)
    c = counts[:, None].astype(np.int64)
    mean_rgb = ((2 * csum + c) // (2 * c)).astype(np.uint8)  # exact round-half-up of csum / c
    return mean_xyz, mean_rgb


_NEIGHBOURS = 3
_RETRY_NEIGHBOURS = 32


class _NearestAlive:
    """Exact nearest-*surviving*-neighbour distances of a shrinking point set.

    Each point keeps its nearest others (ascending) from a KD-tree query. Removing points never
    brings a neighbour closer, so a point's nearest survivor is the first surviving entry of its
    list. Points whose whole list died are re-queried: first with more neighbours in the original
    tree, then (if still none survive) in a tree of the survivors. Distances are identical to a
    fresh query on the survivors.
    """

    def __init__(self, xyz: np.ndarray):
        self.xyz = xyz
        self.sentinel = xyz.shape[0]  # cKDTree's index for a missing neighbour; always dead
        self.alive = np.ones(xyz.shape[0] + 1, dtype=bool)
        self.alive[-1] = False
        self.tree = cKDTree(xyz, balanced_tree=False, compact_nodes=False)
        self.dist, self.nbr = self._query(self.tree, None, np.arange(xyz.shape[0]), _NEIGHBOURS)

    def _query(
        self, tree: cKDTree, index: Optional[np.ndarray], rows: np.ndarray, k: int
    ) -> Tuple[np.ndarray, np.ndarray]:
        """k nearest of ``rows`` in ``tree`` (points ``index`` of xyz, or all), self masked as dead."""
        d, j = tree.query(self.xyz[rows], k=k, workers=-1)
        if index is not None:
            j = np.append(index, self.sentinel)[j]
        j[j == rows[:, None]] = self.sentinel
        return d, j

    def distances(self, live: np.ndarray) -> np.ndarray:
        """Nearest-survivor distance of each index in ``live`` (the surviving indices, ascending)."""
        ok = self.alive[self.nbr[live]]
        lost = ~ok.any(axis=1)
        if lost.any():
            rows = live[lost]
            d, j = self._query(self.tree, None, rows, min(_RETRY_NEIGHBOURS, self.sentinel))
            still = ~self.alive[j].any(axis=1)
            if still.any():
                d[still], j[still] = self._query(cKDTree(self.xyz[live]), live, rows[still], d.shape[1])
            # keep the nearest survivors, ascending; padding entries are dead
            pick = np.argsort(~self.alive[j], axis=1, kind="stable")[:, :_NEIGHBOURS]
            self.dist[rows] = np.take_along_axis(d, pick, axis=1)
            self.nbr[rows] = np.take_along_axis(j, pick, axis=1)
            ok[lost] = self.alive[self.nbr[rows]]
        return self.dist[live, ok.argmax(axis=1)]

    def remove(self, dead: np.ndarray) -> None:
        """Mark indices ``dead`` as pruned."""
        self.alive[dead] = False


def progressive_prune(
    xyz: Float[np.ndarray, "N 3"],
    rgb: UInt8[np.ndarray, "N 3"],
    tau0: float = TAU0,
    beta: float = BETA,
    iterations: int = ITERATIONS,
    min_points: int = MIN_POINTS,
    eps: float = 1e-8,
    seed: int = SEED,
    tau_update: Literal["reference", "paper"] = "reference",
) -> Tuple[Float[np.ndarray, "K 3"], UInt8[np.ndarray, "K 3"], Dict[str, Any]]:
    """Randomly thin dense regions: keep each point with probability ``min(1, d_nn / (tau + eps))``.

    ``d_nn`` is the Euclidean distance to the nearest other point (scene units). One uniform draw
    per point per iteration from ``default_rng(seed)``. An iteration leaving fewer than
    ``min_points`` is rolled back and pruning stops. After an accepted iteration
    ``tau <- tau * exp(beta * N / M0)``, N = count before ("reference") or after ("paper") it.
    """
    if tau_update not in ("reference", "paper"):
        raise PPMOptionError(f"tau_update must be 'reference' or 'paper', got {tau_update!r}")
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    rgb = np.asarray(rgb).reshape(-1, 3)
    m0 = xyz.shape[0]
    rng = np.random.default_rng(seed)
    tau = float(tau0)
    history: List[Dict[str, Any]] = []
    live = np.arange(m0)
    nearest = _NearestAlive(xyz) if m0 > 1 and iterations > 0 else None
    for it in range(iterations):
        n = live.shape[0]
        if n <= 1:
            break
        d = nearest.distances(live)
        p = np.minimum(1.0, d / (tau + eps))
        keep = rng.random(n) < p
        n_after = int(keep.sum())
        rolled_back = n_after < min_points
        history.append(
            {
                "iteration": it,
                "tau": tau,
                "count_before": n,
                "count_after": n if rolled_back else n_after,
                "count_proposed": n_after,
                "nn_mean": float(d.mean()),
                "nn_median": float(np.median(d)),
                "keep_prob_mean": float(p.mean()),
                "rolled_back": rolled_back,
            }
        )
        if rolled_back:
            break
        nearest.remove(live[~keep])
        live = live[keep]
        tau *= math.exp(beta * (n if tau_update == "reference" else n_after) / m0)
    xyz, rgb = xyz[live], rgb[live]
    stats = {"input_count": m0, "final_count": xyz.shape[0], "final_tau": tau, "iterations": history}
    return xyz, rgb, stats


def run_ppm(
    xyz: Float[np.ndarray, "N 3"],
    rgb: UInt8[np.ndarray, "N 3"],
    voxel: float = VOXEL,
    tau0: float = TAU0,
    beta: float = BETA,
    iterations: int = ITERATIONS,
    min_points: int = MIN_POINTS,
    eps: float = 1e-8,
    seed: int = SEED,
    tau_update: Literal["reference", "paper"] = "reference",
) -> Tuple[Float[np.ndarray, "K 3"], UInt8[np.ndarray, "K 3"], Dict[str, Any]]:
    """Full PPM: drop non-finite points, ``voxel_pool``, then ``progressive_prune``.

    The summary holds counts after every stage (and per pruning iteration, in ``prune``) and
    wall-clock timings in seconds per stage.
    """
    t0 = time.perf_counter()
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    rgb = np.asarray(rgb).reshape(-1, 3)
    n_in = xyz.shape[0]
    if not np.isfinite(xyz).all():
        finite = np.isfinite(xyz).all(axis=1)
        xyz, rgb = xyz[finite], rgb[finite]
    t1 = time.perf_counter()
    vxyz, vrgb = voxel_pool(xyz, rgb, voxel)
    t2 = time.perf_counter()
    pxyz, prgb, stats = progressive_prune(
        vxyz,
        vrgb,
        tau0=tau0,
        beta=beta,
        iterations=iterations,
        min_points=min_points,
        eps=eps,
        seed=seed,
        tau_update=tau_update,
    )
    t3 = time.perf_counter()
    summary = {
        "input_count": n_in,
        "nonfinite_dropped": n_in - int(xyz.shape[0]),
        "finite_count": int(xyz.shape[0]),
        "voxel_count": int(vxyz.shape[0]),
        "final_count": int(pxyz.shape[0]),
        "prune": stats,
        "timings_s": {"filter": t1 - t0, "voxel_pool": t2 - t1, "prune": t3 - t2, "total": t3 - t0},
    }
    return pxyz, prgb, summary
