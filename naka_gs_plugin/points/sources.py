"""Point sources behind one loader: PLY files, COLMAP sparse models, VGGT output folders, the simulator.

Every loader returns a :class:`PointCloud` in its **source frame** (whatever world frame the file
uses), with the camera centres it knows (image name -> centre, same frame) so that
:func:`naka_gs_plugin.points.seeding.align_cloud` can map it onto the training cameras. Coordinates
are float64; colours uint8 sRGB in [0, 255] or ``None``. Non-finite coordinates are dropped on
load and counted in ``nonfinite_dropped``.

Supported inputs (``load_points``):

- ``*.ply``: binary or ASCII, ``x y z`` + optional ``red green blue`` / ``r g b`` (uchar, or float
  in [0, 1]). A sibling ``points_cameras.json`` (written by ``naka-gs-sim``: image name -> centre)
  provides its camera centres.
- a COLMAP sparse model folder (``points3D.bin|.txt`` + ``images.bin|.txt`` + ``cameras``), read
  with pycolmap; camera centres from the registered images. If the folder also holds
  ``points.ply`` (VGGT's export of the same points) the PLY is read instead (faster).
- a VGGT output folder (``sparse/points.ply`` + ``sparse/{cameras,images,points3D}.bin``).

:func:`find_scene_source` lists a lowlight-data scene's own point sources in ``auto`` order.

Every file read must be a regular file: a FIFO, a device or a socket in a source's place (a PLY, a COLMAP model's
files, ``points_cameras.json``) is refused in one line before it is opened
(:func:`~naka_gs_plugin.data.safe_io.regular_file`), never found "missing" or waited on.
"""

from __future__ import annotations

import functools
import json
import stat
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np
from jaxtyping import Float, UInt8

from naka_gs_plugin.data.safe_io import atomic_write, input_stat, open_regular, read_regular, regular_file
from naka_gs_plugin.errors import UserError

SCENE_SOURCES = ("sparse/0", "sparse", "colmap_sparse/0", "points.ply")
"""``auto`` candidates inside a scene folder, in order: ``naka-gs-process-data``'s model, a VGGT
folder layout, LOM's COLMAP model, the simulator's cloud."""

CAMERAS_JSON = "points_cameras.json"

COLMAP_FILES = tuple(
    f"{name}{ext}" for name in ("cameras", "images", "points3D", "rigs", "frames") for ext in (".bin", ".txt")
)
"""The files of a COLMAP model pycolmap may read (``rigs`` and ``frames``: COLMAP 3.12 and later)."""
REPLACE_PLY = "replace it with the PLY file"
REPLACE_MODEL = "replace it with the COLMAP model file"


class PointSourceError(UserError, ValueError):
    """A point source is missing or malformed; the message names the file and the fix, on one line."""


@dataclass
class PointCloud:
    """Points in the source's own frame, with the camera centres that source knows."""

    xyz: Float[np.ndarray, "N 3"]
    """float64 positions in the source frame (units of the source)."""
    rgb: Optional[UInt8[np.ndarray, "N 3"]]
    """uint8 sRGB colours, or None when the source has none."""
    source: str
    """Human-readable description (kind and path)."""
    cameras: Dict[str, Float[np.ndarray, "3"]] = field(default_factory=dict)
    """Image file name -> camera centre in the source frame (for alignment; may be empty)."""
    nonfinite_dropped: int = 0
    """Points removed on load because a coordinate was NaN or Inf."""

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


def _finite(xyz: np.ndarray, rgb: Optional[np.ndarray], source: str, cameras=None) -> PointCloud:
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    ok = np.isfinite(xyz).all(axis=1)
    dropped = int((~ok).sum())
    if dropped:
        xyz = xyz[ok]
        rgb = None if rgb is None else rgb[ok]
    return PointCloud(xyz, rgb, source, dict(cameras or {}), dropped)


def _ply_colours(vertex, path: Path) -> Optional[np.ndarray]:
    names = vertex.data.dtype.names
    for keys in (("red", "green", "blue"), ("r", "g", "b"), ("diffuse_red", "diffuse_green", "diffuse_blue")):
        if all(k in names for k in keys):
            cols = np.stack([np.asarray(vertex[k]) for k in keys], axis=1)
            if np.issubdtype(cols.dtype, np.floating):
                finite = cols[np.isfinite(cols)]
                # float colours: [0, 1] (scaled to [0, 255], as the reference loader does) or [0, 255]
                if finite.size and finite.max() <= 1.0:
                    cols = cols * 255.0
                return np.clip(np.nan_to_num(np.round(cols)), 0, 255).astype(np.uint8)
            if cols.dtype.itemsize > 1 and cols.max(initial=0) > 255:  # e.g. ushort 16-bit colours
                return (cols.astype(np.float64) / 257.0).round().clip(0, 255).astype(np.uint8)
            return cols.astype(np.uint8)
    return None


def load_ply(path: Path, cameras: Optional[Dict[str, np.ndarray]] = None) -> PointCloud:
    """Read the ``vertex`` element of a binary or ASCII PLY (xyz + optional colours).

    plyfile rather than open3d: open3d converts colours to float [0, 1], only knows
    ``red/green/blue`` names and returns an empty cloud (no error) for a malformed file.
    """
    from plyfile import PlyData, PlyParseError

    path = Path(path)
    if not regular_file(path, fix=REPLACE_PLY):
        raise PointSourceError(f"{path}: PLY file not found -- check the path")
    try:
        with open_regular(path, fix=REPLACE_PLY) as stream:
            ply = PlyData.read(stream)
        vertex = ply["vertex"]
    except (PlyParseError, KeyError, IndexError, EOFError) as err:
        raise _not_a_ply(path, err) from None
    except ValueError as err:  # InputFileError, a ValueError too, is the user's one line already
        if isinstance(err, UserError):
            raise
        raise _not_a_ply(path, err) from None
    names = vertex.data.dtype.names or ()
    if not all(k in names for k in ("x", "y", "z")):
        raise PointSourceError(f"{path}: the PLY vertex element has no x, y, z properties (has {list(names)})")
    xyz = np.stack([np.asarray(vertex[k], dtype=np.float64) for k in ("x", "y", "z")], axis=1)
    if cameras is None:
        side = path.parent / CAMERAS_JSON
        cameras = (
            read_cameras_json(side) if regular_file(side, fix="replace it with the json file, or remove it") else {}
        )
    return _finite(xyz, _ply_colours(vertex, path), f"PLY {path}", cameras)


def _not_a_ply(path: Path, err: BaseException) -> PointSourceError:
    return PointSourceError(
        f"{path}: not a readable point-cloud PLY ({err.__class__.__name__}: {err}) -- "
        "write a PLY with a 'vertex' element holding x, y, z"
    )


def read_cameras_json(path: Path) -> Dict[str, np.ndarray]:
    """``{"image name": [x, y, z], ...}`` -> name -> centre (the simulator's ``points_cameras.json``)."""
    raw = read_regular(path, fix="replace it with the json file, or remove it")
    try:
        data = json.loads(raw.decode("utf-8-sig"))  # a UnicodeDecodeError is a ValueError
        cams = {str(k): np.asarray(v, dtype=np.float64).reshape(3) for k, v in data.items()}
    except (json.JSONDecodeError, AttributeError, TypeError, ValueError) as err:
        raise PointSourceError(
            f"{path}: expected a JSON object image name -> [x, y, z] ({err.__class__.__name__}) -- fix or delete it"
        ) from None
    return cams


def is_colmap_model(folder: Path) -> bool:
    """A folder with ``points3D`` and ``images`` in COLMAP's binary or text format (one of them a FIFO, a device or
    a socket: :class:`~naka_gs_plugin.data.safe_io.InputFileError`)."""
    return any(
        regular_file(folder / f"points3D{e}", fix=REPLACE_MODEL)
        and regular_file(folder / f"images{e}", fix=REPLACE_MODEL)
        for e in (".bin", ".txt")
    )


def colmap_camera_centres(folder: Path) -> Dict[str, np.ndarray]:
    """Registered image name -> camera centre (COLMAP world frame) of the model in ``folder``."""
    return _centres(_read_colmap(folder))


def _centres(rec) -> Dict[str, np.ndarray]:
    return {im.name: np.asarray(im.projection_center(), np.float64) for im in rec.images.values() if im.has_pose}


@functools.cache
def colmap_camera_params() -> Dict[int, int]:
    """COLMAP camera model id -> number of parameters (a cameras.bin record), from pycolmap itself, so models
    added by a newer COLMAP are known (imported here: pycolmap is loaded only for COLMAP sources)."""
    import pycolmap

    models = (m for m in pycolmap.CameraModelId.__members__.values() if int(m) >= 0)
    return {int(m): len(pycolmap.Camera.create_from_model_id(0, m, 1.0, 1, 1).params) for m in models}


def _check_colmap_binary(folder: Path) -> None:
    """Walk the record structure of ``cameras.bin``, ``images.bin`` and ``points3D.bin`` (COLMAP's
    documented layout) and refuse a file cut short or with trailing bytes, in one line.

    pycolmap itself does not check: a truncated ``points3D.bin`` makes it allocate garbage sizes
    (``std::bad_alloc``), and an empty one keeps it busy for minutes.
    """
    for name in COLMAP_FILES:  # before pycolmap opens any of them: regular files only
        regular_file(folder / name, fix=REPLACE_MODEL)
    for name in ("cameras.bin", "images.bin", "points3D.bin"):
        path = folder / name
        if regular_file(path, fix=REPLACE_MODEL):
            problem = _colmap_binary_problem(name, read_regular(path, fix=REPLACE_MODEL))
            if problem:
                raise PointSourceError(
                    f"{path}: unreadable COLMAP model file, truncated or corrupt ({problem}) -- copy the model again, or re-run "
                    "naka-gs-process-data / COLMAP"
                )


def _colmap_binary_problem(name: str, data: bytes) -> Optional[str]:
    """Why ``data`` is not a whole COLMAP ``name`` file, or None."""
    end = len(data)
    if end < 8:
        return f"{end} bytes, no record count"
    (total,) = struct.unpack_from("<Q", data, 0)
    pos = 8
    fixed = {"cameras.bin": 24, "images.bin": 64, "points3D.bin": 51}[name]  # bytes before a record's variable part
    params = colmap_camera_params() if name == "cameras.bin" else {}
    for record in range(total):
        if pos + fixed > end:
            return f"record {record + 1} of {total} runs past the end at byte {end}"
        if name == "cameras.bin":
            (model,) = struct.unpack_from("<i", data, pos + 4)
            if model not in params:
                return f"camera {record + 1} has unknown model id {model}"
            pos += fixed + 8 * params[model]
        elif name == "images.bin":
            nul = data.find(b"\0", pos + fixed)  # the image name, NUL-terminated
            if nul < 0 or nul + 9 > end:
                return f"record {record + 1} of {total} runs past the end at byte {end}"
            (points2d,) = struct.unpack_from("<Q", data, nul + 1)
            pos = nul + 9 + 24 * points2d
        else:
            (track,) = struct.unpack_from("<Q", data, pos + 43)
            pos += fixed + 8 * track
        if pos > end:
            return f"record {record + 1} of {total} runs past the end at byte {end}"
    if pos != end:
        return f"{end - pos} bytes after its {total} records"
    return None


def _read_colmap(folder: Path):
    import pycolmap

    _check_colmap_binary(folder)
    try:
        return pycolmap.Reconstruction(str(folder))
    except (RuntimeError, ValueError, OSError) as err:  # COLMAP's C++ checks surface as these
        first = str(err).splitlines()[0] if str(err) else ""
        raise PointSourceError(
            f"{folder}: unreadable COLMAP model ({err.__class__.__name__}: {first}) "
            "-- it needs cameras, images and points3D (.bin or .txt)"
        ) from None


def load_colmap(folder: Path) -> PointCloud:
    """Points (xyz, rgb) and registered camera centres of a COLMAP sparse model (bin or txt)."""
    folder = Path(folder)
    if not is_colmap_model(folder):
        raise PointSourceError(f"{folder}: no COLMAP model here (needs points3D.bin|.txt and images.bin|.txt)")
    rec = _read_colmap(folder)
    cams = _centres(rec)
    pts = list(rec.points3D.values())
    # pycolmap exposes points one by one (no array accessor); ~1 us per point.
    xyz = np.array([p.xyz for p in pts], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in pts], dtype=np.uint8).reshape(-1, 3)
    return _finite(xyz, rgb, f"COLMAP model {folder}", cams)


def load_points(path: Path) -> PointCloud:
    """Load any supported source (see the module docstring) in its own frame."""
    path = Path(path)
    found = input_stat(path)
    if found is not None and not stat.S_ISDIR(found.st_mode):
        regular_file(path, fix="replace it with the point file (.ply), or give a COLMAP model or VGGT folder")
        if path.suffix.lower() != ".ply":
            raise PointSourceError(f"{path}: unsupported point file (expected .ply, a COLMAP model or a VGGT folder)")
        return load_ply(path)
    if found is None:
        raise PointSourceError(
            f"{path}: not found -- give a .ply, a COLMAP sparse model folder or a VGGT output folder"
        )
    for model in (path, path / "sparse"):
        if is_colmap_model(model):
            # VGGT: points.ply == points3D.bin, much faster to read
            if regular_file(model / "points.ply", fix=REPLACE_PLY):
                cloud = load_ply(model / "points.ply", cameras=colmap_camera_centres(model))
                cloud.source = f"VGGT output {model} (points.ply + images)"
                return cloud
            return load_colmap(model)
    raise PointSourceError(
        f"{path}: no points3D.bin/.txt + images.bin/.txt here or in sparse/ -- "
        "give a .ply, a COLMAP sparse model folder or a VGGT output folder"
    )


def find_scene_source(scene: Path) -> Optional[Path]:
    """The first of :data:`SCENE_SOURCES` present in ``scene`` (None if the scene has no points)."""
    for rel in SCENE_SOURCES:
        cand = Path(scene) / rel
        if cand.suffix == ".ply" and regular_file(cand, fix=REPLACE_PLY):  # a FIFO there: one line, not skipped
            return cand
        if cand.is_dir() and is_colmap_model(cand):
            return cand
    return None


def source_files(path: Path) -> List[Path]:
    """Files a source is read from (for cache keys)."""
    path = Path(path)
    if path.is_file():
        side = path.parent / CAMERAS_JSON
        return [path] + ([side] if side.is_file() else [])
    files: List[Path] = []
    for model in (path, path / "sparse"):
        if is_colmap_model(model):
            files = sorted(p for p in model.iterdir() if p.is_file() and p.stem in ("points3D", "images", "points"))
            break
    return files


def write_ply(path: Path, xyz: Float[np.ndarray, "N 3"], rgb: Optional[UInt8[np.ndarray, "N 3"]]) -> None:
    """Binary little-endian PLY: float32 ``x y z`` (+ uchar ``red green blue``), written atomically
    (an existing ``path`` stays whole when the write fails)."""
    from plyfile import PlyData, PlyElement

    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if rgb is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vertex = np.empty(len(xyz), dtype=fields)
    for i, k in enumerate("xyz"):
        vertex[k] = xyz[:, i]
    if rgb is not None:
        for i, k in enumerate(("red", "green", "blue")):
            vertex[k] = rgb[:, i]
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda tmp: PlyData([PlyElement.describe(vertex, "vertex")], text=False).write(str(tmp)))
