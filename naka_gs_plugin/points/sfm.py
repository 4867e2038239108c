"""Structure from motion with pycolmap: SIFT features, matching, triangulation from known poses and
incremental mapping. Thin wrappers shared by the classical point fallback (known training poses)
and ``naka-gs-process-data`` (unknown poses).

Conventions: images are sRGB ``uint8`` ``[H, W, 3]`` (feed them **enhanced**: SIFT finds next to
nothing in raw low-light frames). Intrinsics are pixels with COLMAP's pixel-centre convention
(the centre of the top-left pixel is (0.5, 0.5), the same as nerfstudio's). Poses here are
camera-to-world in the **OpenCV** convention (x right, y down, z forward); COLMAP itself stores
world-to-camera (``cam_from_world``). Distortion is OpenCV ``k1 k2 p1 p2``.
"""

from __future__ import annotations

import contextlib
import time
from pathlib import Path
from typing import Callable, Dict, Iterator, List, Literal, Optional, Sequence, Tuple

import numpy as np
import pycolmap
from jaxtyping import Float, UInt8
from PIL import Image

from naka_gs_plugin.errors import UserError

MatchingMethod = Literal["exhaustive", "sequential"]
CameraModel = Literal["OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"]
"""COLMAP camera models whose parameters map onto nerfstudio's OpenCV perspective camera."""


class SfMError(UserError, RuntimeError):
    """pycolmap produced no usable result; the message says what was found and what to try."""


@contextlib.contextmanager
def quiet_colmap(level: int = 2) -> Iterator[None]:
    """Silence COLMAP's glog INFO/WARNING lines (``level`` 2 keeps errors); our own log reports the figures."""
    previous = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = level
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = previous


def _device() -> pycolmap.Device:
    return pycolmap.Device.cuda if pycolmap.has_cuda else pycolmap.Device.cpu


def extract_features(
    database: Path,
    image_dir: Path,
    names: Sequence[str],
    camera_mode: pycolmap.CameraMode,
    camera_model: str,
    max_image_size: int,
    cameras: Optional[Sequence[pycolmap.Camera]] = None,
) -> None:
    """Import ``names`` (paths relative to ``image_dir``) in this order, then extract SIFT features.

    Image ids follow the order of ``names`` (1, 2, ...), which makes runs reproducible. ``cameras``
    (one per image, ``camera_mode`` PER_IMAGE) replaces the guessed calibration before extraction.
    SIFT runs on images resized to at most ``max_image_size`` px; keypoints are in full-resolution pixels.
    """
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    pycolmap.Database.open(database).close()  # import_images needs an existing database file
    pycolmap.import_images(database, image_dir, camera_mode=camera_mode, image_names=list(names), options=reader)
    if cameras is not None:
        db = pycolmap.Database.open(database)
        try:
            for image in db.read_all_images():
                camera = cameras[image.image_id - 1]
                camera.camera_id = image.camera_id
                db.update_camera(camera)
        finally:
            db.close()
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = int(max_image_size)
    pycolmap.extract_features(
        database,
        image_dir,
        image_names=list(names),
        camera_mode=camera_mode,
        reader_options=reader,
        extraction_options=extraction,
        device=_device(),
    )


def match_features(database: Path, method: MatchingMethod = "exhaustive", overlap: int = 10) -> None:
    """SIFT matching + geometric verification: all pairs, or each image with its ``overlap`` successors
    in name order (video-like captures) plus COLMAP's quadratic overlap."""
    if method == "exhaustive":
        pycolmap.match_exhaustive(database, device=_device())
    elif method == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = int(overlap)
        pycolmap.match_sequential(database, pairing_options=pairing, device=_device())
    else:
        raise ValueError(f"matching method must be 'exhaustive' or 'sequential', got {method!r}")


def database_stats(database: Path) -> Dict[str, int]:
    """Keypoints, and image pairs that passed geometric verification (with at least one inlier match;
    COLMAP also stores a geometry row for every pair that failed)."""
    db = pycolmap.Database.open(database)
    try:
        _, inliers = db.read_two_view_geometry_num_inliers()
        return {
            "images": db.num_images(),
            "keypoints": db.num_keypoints(),
            "verified_pairs": int(sum(1 for n in inliers if n > 0)),
            "inlier_matches": int(sum(inliers)),
        }
    finally:
        db.close()


def database_progress(database: Path) -> Dict[str, int]:
    """How far pycolmap has got, read while it runs: images with keypoints, and image pairs matched and verified.

    A separate SQLite connection that takes no lock at all (``immutable=1``): a reader that locks can race with
    COLMAP's own opening of the database, which then fails ("No registered database factory succeeded", seen once
    under load). Without locks it reads the main file only, so counts advance as COLMAP checkpoints its WAL, and a
    read that meets a page being written fails and is skipped. Zeros until the tables exist."""
    import sqlite3  # here: only the progress display reads the database directly

    counts = {"images_with_keypoints": 0, "matched_pairs": 0}
    if not Path(database).is_file():
        return counts
    connection = sqlite3.connect(f"file:{Path(database).absolute()}?mode=ro&immutable=1", uri=True)
    try:
        for key, table in (("images_with_keypoints", "keypoints"), ("matched_pairs", "two_view_geometries")):
            try:
                counts[key] = int(connection.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0])
            except sqlite3.Error:  # not created yet, or a page caught mid-write
                pass
    finally:
        connection.close()
    return counts


def incremental_mapping(
    database: Path,
    image_dir: Path,
    output: Path,
    seed: int = 0,
    next_image_callback: Optional[Callable[[], None]] = None,
    refine_principal_point: bool = False,
) -> Tuple[Optional[pycolmap.Reconstruction], int]:
    """COLMAP incremental mapping; the model with the most registered images (None if there is none)
    and how many models were built. Models of 3+ images are kept (COLMAP's default needs 10).
    Bundle adjustment refines focal length and distortion, and the principal point only on request."""
    options = pycolmap.IncrementalPipelineOptions()
    options.min_model_size = 3
    options.ba_refine_principal_point = bool(refine_principal_point)
    options.random_seed = int(seed)
    pycolmap.set_random_seed(int(seed))
    output.mkdir(parents=True, exist_ok=True)
    models = pycolmap.incremental_mapping(
        database, image_dir, output, options=options, next_image_callback=next_image_callback
    )
    if not models:
        return None, 0
    best = max(models.values(), key=lambda rec: rec.num_reg_images())
    return best, len(models)


def c2w_opencv_of(image: pycolmap.Image) -> Float[np.ndarray, "4 4"]:
    """Camera-to-world (OpenCV axes, the reconstruction's world frame) of a registered image."""
    c2w = np.eye(4)
    c2w[:3] = image.cam_from_world().inverse().matrix()
    return c2w


# " N": with the leading space linters read the one-axis shape as a string, not as the name N
def _angle_deg(rotations: Float[np.ndarray, "N 3 3"]) -> Float[np.ndarray, " N"]:
    return np.degrees(np.arccos(np.clip((np.trace(rotations, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)))


def compare_poses(estimated_c2w: Float[np.ndarray, "N 4 4"], true_c2w: Float[np.ndarray, "N 4 4"]) -> Dict[str, object]:
    """Pose accuracy after the sim3 (Umeyama on camera centres) that best maps estimated onto true.

    Both camera-to-world in the same axis convention (OpenCV or OpenGL), paired by index. Returns
    ``rotation_deg`` and ``centre_error`` per view (``centre_error`` in true-frame units), ``extent``
    (largest distance between two true camera centres), ``centre_error_pct`` (of ``extent``) and the
    alignment ``scale`` and ``rms``. Also ``camera_offset_deg``, the best constant rotation of the
    cameras' own frames (what a different principal point produces: COLMAP keeps it at the image
    centre unless told otherwise), and ``rotation_deg_offset_removed``, the per-view error without it.
    """
    from naka_gs_plugin.points.align import apply_sim3, umeyama

    est, true = np.asarray(estimated_c2w, np.float64), np.asarray(true_c2w, np.float64)
    s, r, t, rms = umeyama(est[:, :3, 3], true[:, :3, 3], "sim3")
    aligned = apply_sim3(s, r, t, est[:, :3, 3])
    centre_error = np.linalg.norm(aligned - true[:, :3, 3], axis=1)
    rel = np.einsum("nji,njk->nik", true[:, :3, :3], r @ est[:, :3, :3])  # R_true^T R R_est
    rotation_deg = _angle_deg(rel)
    u, _, vt = np.linalg.svd(rel.sum(axis=0))  # chordal mean of the per-view residual rotations
    offset = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    residual = rel @ offset.T
    centres = true[:, :3, 3]
    extent = float(np.max(np.linalg.norm(centres[:, None] - centres[None], axis=-1)))
    return {
        "rotation_deg": rotation_deg,
        "camera_offset_deg": _angle_deg(offset[None])[0],
        "rotation_deg_offset_removed": _angle_deg(residual),
        "centre_error": centre_error,
        "extent": extent,
        "centre_error_pct": 100.0 * centre_error / extent,
        "scale": s,
        "rms": rms,
    }


def points_of(
    reconstruction: pycolmap.Reconstruction,
) -> Tuple[Float[np.ndarray, "M 3"], UInt8[np.ndarray, "M 3"]]:
    """The 3D points (reconstruction's world frame) and their colours (sRGB uint8 of the images used)."""
    points = list(reconstruction.points3D.values())
    xyz = np.array([p.xyz for p in points], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in points], dtype=np.uint8).reshape(-1, 3)
    return xyz, rgb


def camera_params(
    model: str, fx: float, fy: float, cx: float, cy: float, distortion: Sequence[float] = (0.0, 0.0, 0.0, 0.0)
) -> List[float]:
    """COLMAP parameter list of ``model`` from pinhole intrinsics and OpenCV ``k1 k2 p1 p2``."""
    k1, k2, p1, p2 = (float(v) for v in distortion)
    if model == "OPENCV":
        return [fx, fy, cx, cy, k1, k2, p1, p2]
    if model == "PINHOLE":
        return [fx, fy, cx, cy]
    raise ValueError(f"camera model {model!r}: only OPENCV and PINHOLE are built from known intrinsics")


def _write_images(images: Sequence[np.ndarray], names: Sequence[str], folder: Path) -> List[str]:
    """Lossless PNG copies named ``<index>_<stem>.png`` (unique even when stems repeat across folders)."""
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for i, (image, name) in enumerate(zip(images, names)):
        array = np.asarray(image)
        if array.dtype != np.uint8 or array.ndim != 3 or array.shape[2] != 3:
            raise ValueError(
                f"image {i} ({name}): expected uint8 [H, W, 3] sRGB, got {array.dtype} {tuple(array.shape)}"
            )
        stem = "".join(c if c.isalnum() or c in "-_." else "_" for c in Path(name).stem)
        file_name = f"{i:05d}_{stem}.png"
        # Scratch copies that COLMAP reads once: zlib's fastest level, the same pixels for a fraction of the time.
        Image.fromarray(array).save(folder / file_name, compress_level=1)
        out.append(file_name)
    return out


def triangulate_known_poses(
    images: Sequence[UInt8[np.ndarray, "H W 3"]],
    names: Sequence[str],
    intrinsics: Float[np.ndarray, "N 4"],
    sizes: Float[np.ndarray, "N 2"],
    c2w_opencv: Float[np.ndarray, "N 4 4"],
    workdir: Path,
    max_image_size: int = 1600,
    distortion: Optional[Float[np.ndarray, "N 4"]] = None,
) -> Tuple[Float[np.ndarray, "M 3"], UInt8[np.ndarray, "M 3"], Dict[str, object]]:
    """Sparse points from images with known cameras: SIFT, exhaustive matching, ``triangulate_points``.

    Args:
        images: sRGB uint8 ``[H, W, 3]`` per view, already enhanced.
        names: one name per view (only for messages and the workdir's file names).
        intrinsics: ``fx fy cx cy`` in pixels of an image of size ``sizes``.
        sizes: ``w h`` the intrinsics refer to; when an image has another size the intrinsics are
            scaled to it (e.g. a downscaled copy of the training image).
        c2w_opencv: camera-to-world, OpenCV axes (x right, y down, z forward), caller's world frame.
        workdir: scratch folder for the PNG copies, the COLMAP database and the model (kept).
        max_image_size: SIFT runs on images resized to at most this many pixels per side.
        distortion: optional OpenCV ``k1 k2 p1 p2`` per view (OPENCV camera model; PINHOLE without).

    Returns:
        ``xyz`` ``[M, 3]`` float64 in the caller's world frame, ``rgb`` ``[M, 3]`` uint8 (sRGB of the
        given images), and ``info``: ``points``, ``mean_track_length``, ``mean_reprojection_error_px``,
        ``keypoints``, ``verified_pairs``, ``seconds`` per stage (write, extract, match, triangulate).
        Poses and intrinsics are held fixed; raises :class:`SfMError` when nothing is triangulated.
    """
    n = len(images)
    intrinsics = np.asarray(intrinsics, dtype=np.float64).reshape(-1, 4)
    sizes = np.asarray(sizes, dtype=np.float64).reshape(-1, 2)
    c2w_opencv = np.asarray(c2w_opencv, dtype=np.float64).reshape(-1, 4, 4)
    dist = None if distortion is None else np.asarray(distortion, dtype=np.float64).reshape(-1, 4)
    lengths = {"names": len(names), "intrinsics": len(intrinsics), "sizes": len(sizes), "c2w_opencv": len(c2w_opencv)}
    if dist is not None:
        lengths["distortion"] = len(dist)
    if any(v != n for v in lengths.values()):
        raise ValueError(
            f"triangulate_known_poses: {n} images but " + ", ".join(f"{k}={v}" for k, v in lengths.items())
        )
    if n < 2:
        raise SfMError(f"triangulate_known_poses needs at least 2 views, got {n}")
    if not np.isfinite(c2w_opencv).all() or not np.isfinite(intrinsics).all():
        raise ValueError("triangulate_known_poses: non-finite pose or intrinsics")

    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    image_dir, database, model_dir = workdir / "images", workdir / "database.db", workdir / "triangulated"
    for stale in (database, workdir / "database.db-wal", workdir / "database.db-shm"):
        stale.unlink(missing_ok=True)  # features of a previous call would mix with these
    seconds: Dict[str, float] = {}

    t0 = time.perf_counter()
    files = _write_images(images, names, image_dir)
    model = "OPENCV" if dist is not None and np.any(dist != 0) else "PINHOLE"
    cameras = []
    for i, image in enumerate(images):
        h, w = np.asarray(image).shape[:2]
        sx, sy = w / sizes[i, 0], h / sizes[i, 1]
        fx, fy, cx, cy = intrinsics[i] * np.array([sx, sy, sx, sy])
        params = camera_params(model, fx, fy, cx, cy, dist[i] if dist is not None else (0.0, 0.0, 0.0, 0.0))
        camera = pycolmap.Camera.create_from_model_name(i + 1, model, fx, w, h)
        camera.params = params
        cameras.append(camera)
    seconds["write"] = time.perf_counter() - t0

    with quiet_colmap():
        t0 = time.perf_counter()
        extract_features(
            database, image_dir, files, pycolmap.CameraMode.PER_IMAGE, model, max_image_size, cameras=cameras
        )
        seconds["extract"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        match_features(database, "exhaustive")
        seconds["match"] = time.perf_counter() - t0
        stats = database_stats(database)

        t0 = time.perf_counter()
        reconstruction = pycolmap.Reconstruction()
        db = pycolmap.Database.open(database)
        try:
            for camera in db.read_all_cameras():
                reconstruction.add_camera_with_trivial_rig(camera)
            for image in db.read_all_images():
                w2c = np.linalg.inv(c2w_opencv[image.image_id - 1])
                reconstruction.add_image_with_trivial_frame(
                    pycolmap.Image(name=image.name, camera_id=image.camera_id, image_id=image.image_id),
                    pycolmap.Rigid3d(w2c[:3, :4]),
                )
        finally:
            db.close()
        model_dir.mkdir(exist_ok=True)
        triangulated = pycolmap.triangulate_points(reconstruction, database, image_dir, model_dir)
        seconds["triangulate"] = time.perf_counter() - t0

    xyz, rgb = points_of(triangulated)
    if len(xyz) == 0:
        raise SfMError(
            f"pycolmap triangulated no points from {n} views ({stats['keypoints']} keypoints, "
            f"{stats['verified_pairs']} verified pairs; workdir {workdir}) -- check that the images are enhanced "
            "(not raw low-light), that neighbouring views overlap, and that c2w_opencv is OpenCV camera-to-world"
        )
    info: Dict[str, object] = {
        "points": int(len(xyz)),
        "mean_track_length": float(triangulated.compute_mean_track_length()),
        "mean_reprojection_error_px": float(triangulated.compute_mean_reprojection_error()),
        "keypoints": stats["keypoints"],
        "verified_pairs": stats["verified_pairs"],
        "seconds": seconds,
    }
    return xyz, rgb, info
