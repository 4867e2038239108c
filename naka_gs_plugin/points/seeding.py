"""From a point source to the seed points of the Gaussians: align, normalize, PPM, cache.

Frames: a source's points live in its own frame; :func:`align_cloud` maps them onto the world
frame of ``transforms_train.json`` with a sim3/rigid Umeyama fit of the source's camera centres to
the training camera centres (names matched as :func:`~naka_gs_plugin.points.align.match_names`).
Camera centres do not depend on the OpenGL/OpenCV axis convention (only the rotation does), so
the fit is the same for either. The dataparser's normalization (``transform``, ``scale``) then
takes the points into the training frame, where PPM's voxel size and tau are defined.
"""

from __future__ import annotations

import hashlib
import io
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable, Dict, List, Literal, Optional, Tuple

import numpy as np
import torch
import tyro
from jaxtyping import Float, UInt8
from nerfstudio.utils.rich_utils import CONSOLE

from naka_gs_plugin.data.cache import default_cache_dir, read_sealed, seal
from naka_gs_plugin.data.lowlight_dataparser import (
    LowLightDataParserConfig,
    normalization,
    read_split,
    to_normalized_frame,
)
from naka_gs_plugin.data.safe_io import atomic_write
from naka_gs_plugin.points.align import AlignmentError, apply_sim3, match_names, umeyama
from naka_gs_plugin.points.ppm import BETA, ITERATIONS, MIN_POINTS, SEED, TAU0, VOXEL, run_ppm
from naka_gs_plugin.points.sources import PointCloud, PointSourceError, find_scene_source, load_points, source_files

CACHE_VERSION = 1
"""Bump when the seeding maths change, so stale cached clouds are never read."""
MIN_SEED_POINTS = 4
MAX_SEED_COORD = 1e4
"""Farthest seed point kept, in normalized units (the training cameras fill [-1, 1]).

Measured: the real COLMAP models of LOM (bike, chair, shrub, sofa) reach 7 to 31 (their farthest
background points). Past 1e4 a coordinate is a placeholder or a unit error (1e30), not geometry; it
would also overflow PPM's voxel keys."""
"""Splatfacto sizes each seed Gaussian by its 3 nearest neighbours."""


@dataclass
class PPMSettings:
    """Alignment and PPM parameters, shared by ``--pipeline.init`` and ``naka-gs-ppm``."""

    align: Literal["sim3", "rigid", "none"] = "sim3"
    """Map the source frame onto the training cameras by its camera centres; ``none``: the points
    are already in the frame of transforms_train.json."""
    ppm: bool = True
    """Clean the points with PPM (voxel pooling + progressive pruning) before seeding; False only
    aligns/normalizes and drops non-finite and duplicate points."""
    voxel_size: float = VOXEL
    """PPM voxel edge, normalized scene units (``naka-gs-ppm`` without ``--scene``: the source's units)."""
    tau0: float = TAU0
    """Initial pruning distance threshold, same units."""
    beta: float = BETA
    """Threshold growth rate per pruning iteration."""
    iterations: int = ITERATIONS
    """Pruning iterations."""
    min_points: int = MIN_POINTS
    """Minimum points kept by pruning (an iteration going below is rolled back and pruning stops)."""
    tau_update: Literal["reference", "paper"] = "reference"
    """tau *= exp(beta * N / M0) with N the count before (reference code) or after (paper) pruning."""
    seed: int = SEED
    """Seed of the pruning draws."""


@dataclass
class PointInitConfig(PPMSettings):
    """Where the Gaussians start (``--pipeline.init.*``)."""

    points: str = "auto"
    """``auto``: the scene's own points (sparse/0, sparse, colmap_sparse/0, points.ply), else
    triangulation from the enhanced training views, else random; ``triangulate``: always
    triangulate; ``random``: splatfacto's random init; or a path (.ply, COLMAP model folder, VGGT
    output folder)."""
    triangulate: bool = True
    """In ``auto``, triangulate from the enhanced training views when the scene has no points
    (False: go straight to random init)."""
    # PPM's internals keep the authors' values under ns-train: hidden from its --help, still set by a run's
    # config.yml (``ns-train naka-gs --load-config``) or a benchmark grid; naka-gs-ppm shows them all.
    voxel_size: tyro.conf.Suppress[float] = VOXEL
    tau0: tyro.conf.Suppress[float] = TAU0
    beta: tyro.conf.Suppress[float] = BETA
    iterations: tyro.conf.Suppress[int] = ITERATIONS
    min_points: tyro.conf.Suppress[int] = MIN_POINTS
    tau_update: tyro.conf.Suppress[Literal["reference", "paper"]] = "reference"
    seed: tyro.conf.Suppress[int] = SEED


@dataclass
class TrainingFrame:
    """The training cameras in the world frame of transforms_train.json, and the dataparser normalization."""

    names: List[str]
    """Training image file names, in transforms_train.json order."""
    centres: Float[np.ndarray, "N 3"]
    """Camera centres, world (transforms json) units."""
    transform: Float[np.ndarray, "3 4"]
    """Dataparser transform, world -> normalized (before ``scale``)."""
    scale: float
    """Dataparser scale (normalized units per world unit)."""
    scene: Path
    points: Optional[Path] = None
    """The layout's own point source (nerfstudio-data's ``ply_file_path``, a colmap layout's model): ``auto`` takes
    it before looking in the scene folder."""
    points_cameras: Optional[Dict[str, np.ndarray]] = None
    """Camera centres (world units, by image name) of ``points`` when the file carries none but shares the poses'
    frame (nerfstudio-data's ply): the alignment then fits them to themselves."""

    @classmethod
    def from_scene(cls, scene: Path, parser: Optional[LowLightDataParserConfig] = None) -> "TrainingFrame":
        """Read a lowlight-data scene's training cameras and compute its normalization as the dataparser does."""
        parser = parser or LowLightDataParserConfig(data=Path(scene))
        train = read_split(Path(scene), "transforms_train.json")
        transform, scale = normalization(train.poses, parser)
        return cls.from_split(Path(scene), train, transform, scale)

    @classmethod
    def from_split(cls, scene: Path, train, transform: torch.Tensor, scale: float) -> "TrainingFrame":
        return cls(
            names=[p.name for p in train.images],
            centres=train.poses[:, :3, 3].double().numpy(),
            transform=transform.double().numpy(),
            scale=float(scale),
            scene=Path(scene),
        )

    @classmethod
    def from_layout(cls, scene: Path, info: Dict[str, Any]) -> "TrainingFrame":
        """From a nerfstudio-data or colmap layout's ``metadata["seed_frame"]`` (:func:`~naka_gs_plugin.data.layouts.
        seed_frame`): its world frame is that of the layout's own points."""
        names, centres = list(info["names"]), np.asarray(info["centres"], np.float64)
        return cls(
            names=names,
            centres=centres,
            transform=np.asarray(info["transform"], np.float64),
            scale=float(info["scale"]),
            scene=Path(scene),
            points=info["points"],
            points_cameras=dict(zip(names, centres)) if info["points_share_frame"] else None,
        )

    def normalize(self, xyz: Float[np.ndarray, "N 3"]) -> Float[np.ndarray, "N 3"]:
        """World -> normalized training frame (the dataparser's map)."""
        return to_normalized_frame(
            torch.from_numpy(np.asarray(xyz, np.float64)), torch.from_numpy(self.transform), self.scale
        ).numpy()


def align_cloud(
    cloud: PointCloud, frame: TrainingFrame, mode: Literal["sim3", "rigid", "none"]
) -> Tuple[Float[np.ndarray, "N 3"], Dict[str, Any]]:
    """Points of ``cloud`` in the world frame of transforms_train.json, and the fit's report.

    The report holds the mode, the number of matched cameras, ``scale``, ``R``, ``t`` and the RMS
    camera-centre residual in world and normalized units. Raises :class:`AlignmentError` (one line,
    naming the source and the fix) when the source has too few or degenerate matches.
    """
    if mode == "none":
        return cloud.xyz, {"mode": "none"}
    if mode not in ("sim3", "rigid"):
        raise AlignmentError(f"align must be sim3, rigid or none, got {mode!r}")
    fix = "pass --pipeline.init.align none if the points are already in the transforms' world frame"
    if not cloud.cameras:
        raise AlignmentError(f"{cloud.source}: no camera centres to align with -- {fix}")
    src_names = list(cloud.cameras)
    pairs = match_names(src_names, frame.names)
    if len(pairs) < 3:
        raise AlignmentError(
            f"{cloud.source}: only {len(pairs)} of its {len(src_names)} cameras match the {len(frame.names)} "
            f"training images by name (need >= 3 for {mode}; e.g. {src_names[:2]} vs {frame.names[:2]}) -- {fix}"
        )
    src = np.stack([cloud.cameras[src_names[i]] for i, _ in pairs])
    dst = frame.centres[[j for _, j in pairs]]
    try:
        s, r, t, rms = umeyama(src, dst, mode)
    except AlignmentError as err:
        raise AlignmentError(f"{cloud.source}: {err} among the {len(pairs)} matched cameras -- {fix}") from None
    err = np.linalg.norm(apply_sim3(s, r, t, src) - dst, axis=1)
    extent = float(np.linalg.norm(dst - dst.mean(axis=0), axis=1).max())
    report = {
        "mode": mode,
        "matched_cameras": len(pairs),
        "source_cameras": len(src_names),
        "scale": s,
        "R": r.tolist(),
        "t": t.tolist(),
        "rms_world": rms,
        "max_world": float(err.max()),
        "rms_normalized": rms * frame.scale,
        "rms_relative_to_extent": rms / extent if extent > 0 else float("nan"),
    }
    return apply_sim3(s, r, t, cloud.xyz), report


def prepare_points(
    cloud: PointCloud, frame: Optional[TrainingFrame], init: PointInitConfig, normalized: bool = False
) -> Tuple[Float[np.ndarray, "K 3"], Optional[UInt8[np.ndarray, "K 3"]], Dict[str, Any]]:
    """Align (unless ``normalized``: the cloud is already in the training frame), normalize, then PPM.

    With ``frame=None`` the points stay in the source frame (PPM units are then the source's).
    Returns the points, colours (None if the source has none) and a JSON-able summary with the
    counts after every stage, the alignment report and timings in seconds.
    """
    t0 = time.perf_counter()
    summary: Dict[str, Any] = {
        "source": cloud.source,
        "loaded_count": len(cloud) + cloud.nonfinite_dropped,
        "nonfinite_dropped_on_load": cloud.nonfinite_dropped,
        "frame": "normalized" if normalized else ("source" if frame is None else "training (normalized)"),
    }
    xyz = cloud.xyz
    rgb = cloud.rgb
    if frame is not None and not normalized:
        xyz, summary["alignment"] = align_cloud(cloud, frame, init.align)
        xyz = frame.normalize(xyz)
    if frame is not None or normalized:
        xyz, rgb = _drop_far(xyz, rgb, cloud.source, summary)
    t1 = time.perf_counter()
    if init.ppm:
        pool_rgb = rgb if rgb is not None else np.zeros(xyz.shape, np.uint8)
        try:
            xyz, pool_rgb, ppm_summary = run_ppm(
                xyz, pool_rgb, voxel=init.voxel_size, tau0=init.tau0, beta=init.beta, iterations=init.iterations,
                min_points=init.min_points, seed=init.seed, tau_update=init.tau_update,
            )  # fmt: skip
        except ValueError as err:  # e.g. coordinates too large for the voxel keys (source frame: no far check)
            raise PointSourceError(
                f"{cloud.source}: PPM cannot pool it ({err}) -- check the file's coordinates"
            ) from None
        rgb = pool_rgb if rgb is not None else None
        summary["ppm"] = ppm_summary
    else:
        finite = np.isfinite(xyz).all(axis=1)
        summary["nonfinite_dropped_after_alignment"] = int((~finite).sum())
        xyz, rgb = xyz[finite], (None if rgb is None else rgb[finite])
        # exact duplicates would get zero neighbour distance, i.e. log(0) scales in splatfacto's init
        first = np.sort(np.unique(xyz, axis=0, return_index=True)[1])
        summary["duplicates_dropped"] = int(xyz.shape[0] - first.shape[0])
        xyz, rgb = xyz[first], (None if rgb is None else rgb[first])
    summary["final_count"] = int(xyz.shape[0])
    summary["timings_s"] = {"align_normalize": t1 - t0, "ppm": time.perf_counter() - t1}
    return xyz, rgb, summary


def _drop_far(
    xyz: Float[np.ndarray, "N 3"], rgb: Optional[np.ndarray], source: str, summary: Dict[str, Any]
) -> Tuple[Float[np.ndarray, "K 3"], Optional[np.ndarray]]:
    """Points of the training frame within :data:`MAX_SEED_COORD`: the rest dropped with one warning,
    or a one-line :class:`PointSourceError` when that leaves none."""
    with np.errstate(invalid="ignore"):
        far = np.abs(xyz).max(axis=1, initial=0.0) > MAX_SEED_COORD
    summary["far_dropped"] = int(far.sum())
    if not far.any():
        return xyz, rgb
    where = f"{source}: {int(far.sum())} of {len(xyz)} points lie over {MAX_SEED_COORD:g}x the camera spread away"
    if far.all():
        raise PointSourceError(
            f"{where} (coordinates like {np.abs(xyz).max():.3g}) -- not geometry of this scene: fix the file, "
            "or pass --pipeline.init.points auto / random"
        )
    log_points(f"warning: {where} (placeholders or a unit error); seeding without them")
    return xyz[~far], None if rgb is None else rgb[~far]


def describe(summary: Dict[str, Any]) -> str:
    """One line: source, counts per stage, residual."""
    parts = [f"{summary['source']}: {summary['loaded_count']} points"]
    if summary.get("nonfinite_dropped_on_load"):
        parts.append(f"{summary['nonfinite_dropped_on_load']} non-finite dropped")
    al = summary.get("alignment")
    if al and al["mode"] != "none":
        parts.append(
            f"{al['mode']} on {al['matched_cameras']} cameras, rms {al['rms_world']:.3g} "
            f"({al['rms_normalized']:.3g} normalized)"
        )
    if "ppm" in summary:
        ppm = summary["ppm"]
        its = "/".join(
            f"rolled back ({h['count_proposed']} < min)" if h["rolled_back"] else str(h["count_after"])
            for h in ppm["prune"]["iterations"]
        )
        parts.append(f"PPM voxel {ppm['voxel_count']} -> prune [{its}] -> {ppm['final_count']}")
    else:
        parts.append(f"no PPM -> {summary['final_count']}")
    return ", ".join(parts)


# ------------------------------------------------------------------------------------------ cache
def _stat(path: Path) -> List[Any]:
    st = Path(path).stat()
    return [str(Path(path).resolve()), st.st_size, st.st_mtime_ns]


def cache_key(parts: Dict[str, Any]) -> str:
    """SHA-1 of a JSON-able description of everything that changes the cleaned cloud."""
    return hashlib.sha1(json.dumps({"v": CACHE_VERSION, **parts}, sort_keys=True, default=str).encode()).hexdigest()


def cache_path(key: str) -> Path:
    return default_cache_dir() / "points" / f"{key}.npz"


def read_cache(key: str) -> Optional[Tuple[np.ndarray, Optional[np.ndarray], Dict[str, Any]]]:
    """The cached cloud of ``key``, or None: a miss, or an entry that cannot be used (one line; recomputed)."""
    path = cache_path(key)
    data, why = read_sealed(path)
    if data is not None:
        try:
            with np.load(io.BytesIO(data)) as arrays:
                rgb = arrays["rgb"] if bool(arrays["has_rgb"]) else None
                return arrays["xyz"], rgb, json.loads(str(arrays["summary"]))
        except (OSError, ValueError, KeyError):  # a foreign file sealed as ours
            why = "is corrupt"
    if why:
        CONSOLE.log(f"[naka-gs] warning: cache entry {path} {why}; recomputing it", markup=False)
    return None


def write_cache(key: str, xyz: np.ndarray, rgb: Optional[np.ndarray], summary: Dict[str, Any]) -> Path:
    path = cache_path(key)
    path.parent.mkdir(parents=True, exist_ok=True)
    empty = np.zeros((0, 3), np.uint8)

    def write(tmp: Path) -> None:
        np.savez(
            tmp, xyz=xyz, rgb=rgb if rgb is not None else empty, has_rgb=rgb is not None, summary=json.dumps(summary)
        )

    seal(atomic_write(path, write))
    return path


# ---------------------------------------------------------------------------------------- resolve
Triangulator = Callable[[], Tuple[np.ndarray, np.ndarray, Dict[str, Any]]]
"""Returns triangulated ``(xyz, rgb uint8, info)`` in the normalized training frame."""


@dataclass
class SeedResult:
    xyz: Optional[Float[np.ndarray, "K 3"]]
    """Seed positions in the normalized training frame; None = random init."""
    rgb: Optional[UInt8[np.ndarray, "K 3"]]
    summary: Dict[str, Any]


def _init_options(init: PointInitConfig) -> Dict[str, Any]:
    opts = asdict(init)
    opts.pop("points")
    opts.pop("triangulate")
    return opts


def _frame_key(frame: TrainingFrame) -> Dict[str, Any]:
    return {
        "transform": np.round(frame.transform, 9).tolist(),
        "scale": round(frame.scale, 12),
        "cameras": hashlib.sha1(np.round(frame.centres, 9).tobytes() + "|".join(frame.names).encode()).hexdigest(),
    }


def resolve_seed_points(
    init: PointInitConfig,
    frame: TrainingFrame,
    triangulate: Optional[Triangulator] = None,
    triangulation_key: Optional[Callable[[], Dict[str, Any]]] = None,
    compute: bool = True,
) -> SeedResult:
    """Choose the source per ``init.points``, then align, normalize, clean and cache it.

    ``triangulate`` is the source for ``triangulate`` and the ``auto`` fallback for scenes
    without points; ``triangulation_key()`` describes its inputs for the cache key. With
    ``compute=False`` (pipelines that load a checkpoint: ns-eval, ns-viewer, ns-export) nothing is
    computed: a source file's cached cloud is used if present, and the triangulation fallback is
    not even keyed (that would load and enhance the training images); random init is reported
    instead, and the checkpoint replaces it.
    Logs one line saying which source was used and how many points it produced.
    """
    if init.points == "random":
        return _random("requested: --pipeline.init.points random")
    path: Optional[Path] = None
    if init.points == "auto":
        path = frame.points or find_scene_source(frame.scene)
    elif init.points == "triangulate":
        if triangulate is None:
            raise PointSourceError(f"{frame.scene}: points 'triangulate' needs the training pipeline's enhanced images")
    else:
        path = Path(init.points).expanduser()
        if not path.exists():
            raise PointSourceError(
                f"{path}: --pipeline.init.points not found -- give a .ply, a COLMAP model or VGGT folder, "
                "'auto', 'triangulate' or 'random'"
            )
    if path is not None:
        key = cache_key({"files": [_stat(p) for p in source_files(path)], "path": str(path.resolve()),
                         "options": _init_options(init), "frame": _frame_key(frame)})  # fmt: skip

        def producer():
            cloud = load_points(path)
            if path == frame.points and frame.points_cameras and not cloud.cameras:
                cloud.cameras = frame.points_cameras
            return prepare_points(cloud, frame, init)

    elif triangulate is not None and (init.triangulate or init.points == "triangulate"):
        if not compute:
            return _random(_NO_COMPUTE)
        tri_key = triangulation_key() if triangulation_key is not None else None
        key = cache_key({"triangulation": tri_key, "options": _init_options(init), "frame": _frame_key(frame)})

        def producer():
            t0 = time.perf_counter()
            xyz, rgb, info = triangulate()
            cloud = PointCloud(
                np.asarray(xyz, np.float64).reshape(-1, 3), rgb, "triangulation of the enhanced training views"
            )
            finite = np.isfinite(cloud.xyz).all(axis=1)
            cloud.nonfinite_dropped = int((~finite).sum())
            cloud.xyz, cloud.rgb = cloud.xyz[finite], None if rgb is None else np.asarray(rgb)[finite]
            if len(cloud) == 0:
                return None, None, {"source": cloud.source, "triangulation": info, "error": info.get("error")}
            xyz, rgb, summary = prepare_points(cloud, frame, init, normalized=True)
            summary["triangulation"] = {**info, "total_seconds": time.perf_counter() - t0}
            return xyz, rgb, summary
    else:
        why = "the scene has no point source" + ("" if init.triangulate else " and triangulation is off")
        return _random(f"{why} ({frame.scene}: none of sparse/0, sparse, colmap_sparse/0, points.ply)")

    cached = read_cache(key)
    if cached is not None:
        xyz, rgb, summary = cached
        summary["cache"] = str(cache_path(key))
        log_points(f"seed points (cached {cache_path(key).name}): " + describe(summary))
        return SeedResult(xyz, rgb, summary)
    if not compute:
        return _random(_NO_COMPUTE)
    xyz, rgb, summary = producer()
    if xyz is None or len(xyz) < MIN_SEED_POINTS:
        why = f": {summary['error']}" if summary.get("error") else ""
        n = 0 if xyz is None else len(xyz)
        return _random(f"{summary['source']} produced {n} points, fewer than {MIN_SEED_POINTS}{why}")
    summary["cache"] = str(write_cache(key, xyz, rgb, summary))
    log_points("seed points: " + describe(summary))
    return SeedResult(xyz, rgb, summary)


_NO_COMPUTE = "this pipeline loads a checkpoint, whose Gaussians replace the seed; no cached cloud to reuse"


def _random(why: str) -> SeedResult:
    log_points(f"seed points: random init ({why})")
    return SeedResult(None, None, {"source": "random", "reason": why})


def log_points(message: str) -> None:
    """Console line prefixed with [naka-gs] (plain text: no rich markup)."""
    CONSOLE.log(f"[naka-gs] {message}", markup=False)
