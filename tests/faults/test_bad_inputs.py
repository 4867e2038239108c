"""Bad inputs and faults, one row per class: the exact outcome, and every input byte-identical after.

Each case builds its inputs under ``tmp`` (copies of the toy scene; nothing shared is modified)
and returns the action plus the paths that must not change (files, or folders compared by their
whole tree). Outcomes: ``Raises`` (exception type + message substring, one line), ``Exits`` (a
console script's exit status + one-line message, the last line it prints) or ``Ok`` (a check of the result);
the case types and the runner are tests/bad_inputs.py's, shared with the other tables of tests/faults/.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Callable, Dict, List, Optional

import cv2
import numpy as np
import pytest
import torch

from naka_gs_plugin.data import safe_io
from naka_gs_plugin.data.images import ImageReadError, read_rgb
from naka_gs_plugin.data.lowlight_dataparser import LowLightDataError, LowLightDataParserConfig, downscaled_copy
from naka_gs_plugin.data.safe_io import MARKER, UnsafeOutputError, atomic_write
from naka_gs_plugin.datamanager import LowLightDatamanagerConfig
from naka_gs_plugin.enhance.pipeline import EnhanceConfig, Enhancer
from naka_gs_plugin.points.sources import PointSourceError
from naka_gs_plugin.scripts import enhance as enhance_cli
from naka_gs_plugin.scripts import sim as sim_cli
from naka_gs_plugin.scripts.process_data import ProcessData, ProcessDataError
from tests.bad_inputs import (
    NAKA,
    Action,
    Case,
    Env,
    Exits,
    Ok,
    Raises,
    check_case,
    edit_frame0,
    first_train_image,
    parse,
    run_console,
)
from tests.helpers import SHARED_DATA, write_spec


def truncate(path: Path, fraction: float = 1 / 3) -> Path:
    """Keep the first ``fraction`` of the file; of a JPEG, its headers and that fraction of the scan
    (the case OpenCV decodes "successfully", padding the rest with grey)."""
    data = path.read_bytes()
    start = data.find(b"\xff\xda") if data[:2] == b"\xff\xd8" else 0
    path.write_bytes(data[: start + int((len(data) - start) * fraction)])
    return path


def test_truncated_jpeg_is_the_silent_case_for_opencv(tmp_path, toy_scene):
    """The premise of the truncated-JPEG rows: OpenCV alone returns a full-size, partly grey image."""
    env = Env(tmp_path, toy_scene, pytest.MonkeyPatch())
    path = truncate(first_train_image(env.jpeg_scene()))
    assert cv2.imread(str(path)).shape == (48, 64, 3)


def edit_frames(scene: Path, edit: Callable[[dict, dict], None]) -> Path:
    """Apply ``edit(frame, first_frame)`` to every training frame in transforms_train.json."""
    path = scene / "transforms_train.json"
    meta = json.loads(path.read_text())
    for frame in meta["frames"]:
        edit(frame, meta["frames"][0])
    path.write_text(json.dumps(meta))
    return path


def pose0(scene: Path) -> np.ndarray:
    return np.array(json.loads((scene / "transforms_train.json").read_text())["frames"][0]["transform_matrix"])


def datamanager(scene: Path, dtype: str = "float32") -> Action:
    cfg = LowLightDatamanagerConfig(
        dataparser=LowLightDataParserConfig(data=scene, downscale_factor=1), enhance=NAKA, cache_images_type=dtype
    )
    return lambda: cfg.setup(device="cpu", test_mode="val").cached_train  # loaded on first use


def captures(env: Env) -> Path:
    """``P/night1`` (3 photos), ``P/night2`` (another capture) and ``P/notes.txt``, as in the issue."""
    root = env.tmp / "P"
    for i in range(3):
        (root / "night1").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(root / "night1" / f"{i}.png"), np.full((24, 32, 3), 10 * i, np.uint8))
    (root / "night2").mkdir()
    (root / "night2" / "0.png").write_bytes((root / "night1" / "0.png").read_bytes())
    (root / "notes.txt").write_text("my notes")
    return root


def ours(folder: Path, files: Dict[str, str], tool: str = "naka-gs-process-data") -> Path:
    """A folder as one of our tools leaves it: ``files`` plus the marker listing them."""
    folder.mkdir(parents=True)
    for name, text in files.items():
        (folder / name).write_text(text)
    safe_io.write_marker(folder, tool)
    return folder


def fake_process(env: Env, fail: bool = False) -> None:
    """Replace SfM by a stand-in writing one file to the stage (the publishing logic is under test)."""

    def process(self, stage: Path):
        if fail:
            raise ProcessDataError(f"{self.data}: only 0 of 3 images registered")
        (stage / "transforms_train.json").write_text("{}")
        return {}

    env.monkeypatch.setattr(ProcessData, "_process", process)
    env.monkeypatch.setattr(ProcessData, "_print", lambda self, report: None)


# --- the table -------------------------------------------------------------------------------------


def pd_out_parent_of_input(env):
    p = captures(env)
    return lambda: ProcessData(data=p / "night1", output_dir=p, overwrite=True).main(), [p]


def pd_out_equal_input(env):
    p = captures(env)
    return lambda: ProcessData(data=p / "night1", output_dir=p / "night1", overwrite=True).main(), [p]


def pd_out_inside_input(env):
    p = captures(env)
    return lambda: ProcessData(data=p / "night1", output_dir=p / "night1" / "scene").main(), [p]


def pd_overwrite_foreign_folder(env):
    p = captures(env)
    return lambda: ProcessData(data=p / "night1", output_dir=p / "night2", overwrite=True).main(), [p]


def pd_existing_without_overwrite(env):
    p = captures(env)
    return lambda: ProcessData(data=p / "night1", output_dir=p / "night2").main(), [p]


def pd_overwrite_ours_holding_a_user_file(env):
    p = captures(env)
    old = ours(env.tmp / "scene", {"transforms_train.json": "old"})
    (old / "notes.txt").write_text("added by the user")
    return lambda: ProcessData(data=p / "night1", output_dir=old, overwrite=True).main(), [p, old]


def pd_output_is_a_file(env):
    p = captures(env)
    return lambda: ProcessData(data=p / "night1", output_dir=p / "notes.txt", overwrite=True).main(), [p]


def pd_overwrite_ours_replaces_it(env):
    p = captures(env)
    fake_process(env)
    old = ours(env.tmp / "scene", {"transforms_train.json": "old", "stale.txt": "old"})
    return lambda: ProcessData(data=p / "night1", output_dir=old, overwrite=True).main(), [p]


def _replaced(env, _):
    scene = env.tmp / "scene"
    assert sorted(q.name for q in scene.iterdir()) == [MARKER, "transforms_train.json"]  # stale.txt gone
    assert (scene / "transforms_train.json").read_text() == "{}"
    assert sorted(q.name for q in env.tmp.iterdir()) == ["P", "scene"]  # no staging or old copy left


def pd_failed_run_keeps_old_output(env):
    p = captures(env)
    fake_process(env, fail=True)
    old = ours(env.tmp / "scene", {"transforms_train.json": "old"})
    return lambda: ProcessData(data=p / "night1", output_dir=old, overwrite=True).main(), [p, old, env.tmp]


def pd_console_exit(env):
    from naka_gs_plugin.scripts.process_data import entrypoint

    p = captures(env)
    argv = ["naka-gs-process-data", "--data", str(p / "night1"), "--output-dir", str(p), "--overwrite"]
    return run_console(env, entrypoint, argv), [p]


def pd_three_photos_one_point_console(env):
    """3 dark LOM sofa views: 3 register on 1 triangulated point on one CPU, 2 on another (SIFT's floating
    point differs between AVX-512 and AVX2), so the minimum registered here is 2: the row checks the point
    count's refusal either way (SfM on 500x375 images, ~3 s)."""
    from naka_gs_plugin.scripts import process_data
    from naka_gs_plugin.scripts.process_data import entrypoint

    env.monkeypatch.setattr(process_data, "MIN_REGISTERED", 2)

    photos = env.tmp / "photos"
    photos.mkdir()
    for n in (1, 2, 3):
        shutil.copyfile(SHARED_DATA / "lom" / "sofa" / "low" / f"{n}.JPG", photos / f"{n}.JPG")
    argv = ["naka-gs-process-data", "--data", str(photos), "--output-dir", str(env.tmp / "scene")]
    argv += ["--enhance.correction", "none"]
    return run_console(env, entrypoint, argv), [photos, env.tmp]


def enh_out_is_the_images_folder(env):
    s = env.scene()
    return lambda: enhance_cli.Enhance(scene=s, out=s / "train", enhance=NAKA).main(), [s]


def enh_out_is_the_scene(env):
    s = env.scene()
    return lambda: enhance_cli.Enhance(scene=s, out=s, enhance=NAKA).main(), [s]


def enh_out_inside_the_images_folder(env):
    s = env.scene()
    return lambda: enhance_cli.Enhance(scene=s, out=s / "train" / "enh", enhance=NAKA).main(), [s]


def enh_out_foreign_nonempty(env):
    s, other = env.scene(), env.tmp / "mine"
    other.mkdir()
    (other / "0000.png").write_bytes(b"user's picture")
    return lambda: enhance_cli.Enhance(scene=s, out=other, enhance=NAKA).main(), [s, other]


def enh_rerun_replaces_own_output(env):
    s, out = env.scene(), env.tmp / "enh"

    def action():
        enhance_cli.Enhance(scene=s, out=out, enhance=NAKA, sheet=False).main()
        return enhance_cli.Enhance(scene=s, out=out, enhance=NAKA, sheet=False).main()

    return action, [s]


def _enhanced_written(env, written):
    out = env.tmp / "enh"
    assert sorted(q.name for q in out.iterdir()) == sorted([MARKER] + [q.name for q in written])
    assert len(written) == 8 and all(cv2.imread(str(q)).shape == (48, 64, 3) for q in written)
    assert sorted(q.name for q in env.tmp.iterdir()) == ["S", "enh", "naka-cache"]


def enh_truncated_jpeg_console(env):
    s = env.jpeg_scene()
    truncate(first_train_image(s))
    argv = ["naka-gs-enhance", str(s), "--out", str(env.tmp / "enh"), "--enhance.correction", "none"]
    return run_console(env, enhance_cli.entrypoint, argv), [s]


def img_truncated_jpeg(env):
    s = env.jpeg_scene()
    truncate(first_train_image(s))
    return lambda: read_rgb(first_train_image(s)), [s]


def img_zero_size(env):
    s = env.scene()
    first_train_image(s).write_bytes(b"")
    return lambda: read_rgb(first_train_image(s)), [s]


def img_not_an_image(env):
    s = env.scene()
    first_train_image(s).write_text("this is not a picture")
    return lambda: read_rgb(first_train_image(s)), [s]


def img_truncated_png(env):
    s = env.scene()
    truncate(first_train_image(s))
    return lambda: read_rgb(first_train_image(s)), [s]


def dm_truncated_jpeg_float32(env):
    s = env.jpeg_scene()
    truncate(first_train_image(s))
    return datamanager(s), [s]


def dm_truncated_jpeg_uint8(env):
    s = env.jpeg_scene()
    truncate(first_train_image(s))
    return datamanager(s, "uint8"), [s]


def dp_downscale_truncated_jpeg(env):
    s = env.jpeg_scene()
    truncate(first_train_image(s))
    return parse(s, factor=2), [s]


def flat_scene(env, value: int, count: Optional[int] = None) -> Path:
    """The toy scene with its first ``count`` (default all) training captures one flat 16-bit ``value``."""
    s = env.scene()
    for frame in json.loads((s / "transforms_train.json").read_text())["frames"][:count]:
        path = s / frame["file_path"]
        cv2.imwrite(str(path), np.full_like(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), value))
    return s


def dm_all_black_images(env):
    s = flat_scene(env, 0)
    return datamanager(s), [s]


def dm_all_white_images_uint8(env):
    s = flat_scene(env, 65535)
    return datamanager(s, "uint8"), [s]


def dm_one_black_image(env):
    s = flat_scene(env, 0, count=1)
    return datamanager(s), [s]


def _warned_blank_view(env, cached):
    log = env.log()
    assert len(cached) == 8 and log.count("warning: 1 of 8 training images are black (no contrast: 0000.png") == 1


def cam_focal_1e10(env):
    s = env.scene()
    edit_frame0(s, fl_x=1e10, fl_y=1e10)
    return parse(s), [s]


def cam_focal_zero(env):
    s = env.scene()
    edit_frame0(s, fl_x=0)
    return parse(s), [s]


def cam_focal_nan(env):
    s = env.scene()
    edit_frame0(s, fl_x=float("nan"))
    return parse(s), [s]


def cam_focal_string(env):
    s = env.scene()
    edit_frame0(s, fl_x="abc")
    return parse(s), [s]


def cam_width_zero(env):
    s = env.scene()
    edit_frame0(s, w=0)
    return parse(s), [s]


def cam_distortion_string(env):
    s = env.scene()
    edit_frame0(s, k1="x")
    return parse(s), [s]


def cam_zero_rotation(env):
    s = env.scene()
    pose = pose0(s)
    pose[:3, :3] = 0.0
    edit_frame0(s, transform_matrix=pose.tolist())
    return parse(s), [s]


def cam_scaled_rotation(env):
    s = env.scene()
    pose = pose0(s)
    pose[:3, :3] *= 2.0
    edit_frame0(s, transform_matrix=pose.tolist())
    return parse(s), [s]


def cam_reflection(env):
    s = env.scene()
    pose = pose0(s)
    pose[:3, 0] *= -1.0
    edit_frame0(s, transform_matrix=pose.tolist())
    return parse(s), [s]


def cam_infinite_translation(env):
    s = env.scene()
    pose = pose0(s)
    pose[0, 3] = float("inf")
    edit_frame0(s, transform_matrix=pose.tolist())
    return parse(s), [s]


def cam_bottom_rows_zero(env):
    """Every pose a 3x4 padded with a zero row: read as meant, with one warning (the scale as without it)."""
    s = env.scene()
    edit_frames(s, lambda frame, _: frame["transform_matrix"].__setitem__(3, [0, 0, 0, 0]))
    expected = parse(env.toy)().dataparser_scale
    return lambda: (parse(s)(), expected), [s]


def _padded_read_as_meant(env, result):
    outputs, expected = result
    log = env.log()
    assert outputs.dataparser_scale == expected and log.count("bottom row 0 0 0 0; read as 0 0 0 1") == 1, log


def cam_bottom_row_not_homogeneous(env):
    s = env.scene()
    pose = pose0(s)
    pose[3] = [0.0, 0.0, 1.0, 1.0]
    edit_frame0(s, transform_matrix=pose.tolist())
    return parse(s), [s]


def cam_one_camera_far_out(env):
    s = env.scene()
    pose = pose0(s)
    pose[0, 3] = 1e9
    edit_frame0(s, transform_matrix=pose.tolist())
    return parse(s), [s]


def cam_all_at_one_position(env):
    s = env.scene()
    edit_frames(s, lambda frame, first: frame.update(transform_matrix=first["transform_matrix"]))
    return parse(s), [s]


def cam_distortion_absurd(env):
    s = env.scene()
    path = s / "transforms_train.json"
    meta = json.loads(path.read_text())
    meta.update(k1=50, k2=-80)
    path.write_text(json.dumps(meta))
    return parse(s), [s]


def float_tiff_scene(env, nan: bool = False) -> Path:
    """The toy scene with its first training capture as a float32 RGB TIFF (one NaN pixel if ``nan``)."""
    s = env.scene()
    png = first_train_image(s)
    arr = cv2.imread(str(png), cv2.IMREAD_UNCHANGED).astype(np.float32) / 65535.0
    if nan:
        arr[5, 5, 1] = np.nan
    cv2.imwrite(str(png.with_suffix(".tif")), arr, [cv2.IMWRITE_TIFF_COMPRESSION, 1])  # uncompressed keeps NaN
    png.unlink()
    edit_frame0(s, file_path=str(png.with_suffix(".tif").relative_to(s)))
    return s


def img_float32_tiff_trains(env):
    s = float_tiff_scene(env)
    return datamanager(s), [s]


def _all_loaded(env, cached):
    assert len(cached) == 8 and all(torch.isfinite(d["image"]).all() for d in cached)


def img_float32_tiff_trains_uint8(env):
    s = float_tiff_scene(env)
    return datamanager(s, "uint8"), [s]


def img_float32_tiff_with_nan(env):
    s = float_tiff_scene(env, nan=True)
    return datamanager(s), [s]


def colmap_model(folder: Path, n_points: int = 50) -> Path:
    """A small binary COLMAP model in ``folder`` (one camera, one image, ``n_points`` points)."""
    import pycolmap

    text = folder.parent / "text"
    text.mkdir(parents=True)
    (text / "cameras.txt").write_text("1 PINHOLE 64 48 50 50 32 24\n")
    (text / "images.txt").write_text("1 1 0 0 0 0 0 4 1 0000.png\n\n")
    rng = np.random.default_rng(0)
    (text / "points3D.txt").write_text(
        "".join(f"{i + 1} {x} {y} {z} 9 9 9 0.5\n" for i, (x, y, z) in enumerate(rng.normal(size=(n_points, 3))))
    )
    folder.mkdir(parents=True)
    pycolmap.Reconstruction(str(text)).write_binary(str(folder))
    shutil.rmtree(text)
    return folder


def seed_points(env, scene: Path, **init) -> Action:
    from naka_gs_plugin.points.seeding import PointInitConfig, TrainingFrame, resolve_seed_points

    return lambda: resolve_seed_points(PointInitConfig(**init), TrainingFrame.from_scene(scene))


def seed_truncated_colmap_points(env):
    """The scene's own sparse/0 with points3D.bin cut short (pycolmap alone: std::bad_alloc, or minutes)."""
    s = env.scene()
    truncate(colmap_model(s / "sparse" / "0") / "points3D.bin")
    return seed_points(env, s), [s]


def far_ply(env, n_far: int) -> Path:
    from naka_gs_plugin.points.sources import write_ply

    xyz = np.random.default_rng(0).normal(size=(300, 3))
    xyz[:n_far] = 1e30
    write_ply(env.tmp / "points.ply", xyz, None)
    return env.tmp / "points.ply"


def seed_ply_all_at_1e30(env):
    s, ply = env.scene(), far_ply(env, 300)
    return seed_points(env, s, points=str(ply), align="none"), [s, ply]


def seed_ply_some_at_1e30(env):
    s, ply = env.scene(), far_ply(env, 3)
    return seed_points(env, s, points=str(ply), align="none"), [s, ply]


def _far_dropped_with_warning(env, seeded):
    assert seeded.xyz.shape[0] == 297 and np.abs(seeded.xyz).max() < 10
    assert env.log().count("warning: PLY") == 1


def ppm_out_unwritable_console(env):
    from naka_gs_plugin.scripts import ppm

    ply = far_ply(env, 0)
    return run_console(env, ppm.entrypoint, ["naka-gs-ppm", str(ply), "--out", "/proc/naka-gs.ply"]), [ply]


def ppm_out_is_the_input(env):
    from naka_gs_plugin.scripts import ppm

    ply = far_ply(env, 0)
    return run_console(env, ppm.entrypoint, ["naka-gs-ppm", str(ply), "--out", str(ply)]), [ply]


BENCH = "[naka-gs bench] error: "
"""How the benchmarks' error line starts."""


def grid_console(env, text: str) -> Action:
    from benchmarks import grid

    path = env.tmp / "grid.yaml"
    path.write_text(text)
    return run_console(env, grid.entrypoint, ["benchmarks.grid", str(path), "--out", str(env.tmp / "out")])


def grid_malformed_yaml(env):
    return grid_console(env, "name: x\nscenes: {toy: {data: S}\nmilestones: [3\n"), [env.tmp / "grid.yaml"]


def grid_every_run_failed(env):
    """Both runs fail at once (a scene without test views): recorded, and the grid exits 1 saying so."""
    s = env.scene()
    (s / "transforms_test.json").unlink()
    text = f"name: x\nscenes: {{toy: {{data: {s}}}}}\nmilestones: [3]\nfamilies: {{a: {{}}, b: {{enhance: none}}}}\n"
    return grid_console(env, text), [s, env.tmp / "grid.yaml"]


def correction_resume_garbage_console(env):
    """Checked before any data is read or the output folder is made."""
    from naka_gs_plugin.scripts import train_correction

    garbage = env.tmp / "latest.pt"
    garbage.write_text("not a checkpoint")
    argv = ["naka-gs-train-correction", "--resume", str(garbage), "--output-dir", str(env.tmp / "out")]
    return run_console(env, train_correction.entrypoint, argv), [garbage, env.tmp]


def cache_nested_writes_use_unique_temporaries(env):
    """Two writers of one cache entry at once (as two ns-train runs): neither clobbers the other's temp file."""
    target = env.tmp / "cache" / "entry.npy"
    target.parent.mkdir()

    def outer(tmp):
        atomic_write(target, lambda inner: np.save(inner, np.ones(3)))  # the other run, mid-way through ours
        np.save(tmp, np.zeros(3))

    def action():
        atomic_write(target, outer)
        return np.load(target)

    return action, []


def _last_writer_wins(env, arr):
    assert np.array_equal(arr, np.zeros(3)) and os.listdir(env.tmp / "cache") == ["entry.npy"]


def cache_imwrite_fails(env):
    s = env.scene()
    env.monkeypatch.setattr(cv2, "imwrite", lambda *a, **k: False)  # what cv2 does on a full disk
    env.monkeypatch.setenv("NAKA_GS_CACHE", str(env.tmp / "c"))
    return parse(s, factor=2), [s]


def _nothing_committed(env):
    assert not [q for q in (env.tmp / "c").rglob("*") if q.is_file()]


def cache_disk_full_cuts_a_copy_short(env):
    """A full disk (tmpfs): OpenCV reports success for a PNG cut short; nothing may be kept as complete."""
    s = env.scene()
    imwrite = cv2.imwrite

    def cut_short(name, img, *args):
        ok = imwrite(name, img, *args)
        truncate(Path(name), 1 / 2)
        return ok

    env.monkeypatch.setattr(cv2, "imwrite", cut_short)
    env.monkeypatch.setenv("NAKA_GS_CACHE", str(env.tmp / "c"))
    return parse(s, factor=2), [s]


def cache_unreadable_entry_is_not_the_photo(env):
    """A cache entry broken after it was made (e.g. by another program) is named as ours, with the fix."""
    s = env.scene()
    copy = truncate(downscaled_copy(first_train_image(s), 2))
    return lambda: read_rgb(copy), [s]


def cache_corrupt_downscaled_copy(env):
    s = env.scene()
    src = first_train_image(s)
    good = downscaled_copy(src, 2).read_bytes()
    truncate(downscaled_copy(src, 2))
    return lambda: downscaled_copy(src, 2).read_bytes() == good, [s]


def _recomputed_with_warning(env, same):
    assert same is True and "does not match its checksum (edited or damaged since it was written); making it again" in (
        env.log()
    )


def cache_corrupt_enhanced_entry(env):
    s = env.scene()
    images = [torch.from_numpy(read_rgb(first_train_image(s)))]
    enhancer = Enhancer(NAKA)
    first = enhancer.enhance_images(images)[0]
    entry = next(enhancer.cache_dir.glob("*.npy"))
    truncate(entry)

    def action():
        again = Enhancer(NAKA)
        return again, torch.equal(again.enhance_images(images)[0], first)

    return action, [s]


def _enhanced_recomputed(env, result):
    enhancer, same = result
    assert same and enhancer.last_run["computed"] == 1
    assert "does not match its checksum (edited or damaged since it was written); recomputing it" in env.log()


def cache_env_names_a_file(env):
    s = env.scene()
    blocker = env.tmp / "not-a-dir"
    blocker.write_text("a file")
    env.monkeypatch.setenv("NAKA_GS_CACHE", str(blocker))
    env.monkeypatch.setattr(safe_io, "_fallback", {})

    def action():
        parse(s, factor=2)()
        return Enhancer(NAKA).enhance_images([torch.zeros(4, 4, 3)])

    return action, [s, blocker]


def _fell_back_once(env, _):
    log = env.log()
    assert log.count("is not writable") == 1 and "using" in log


def cache_unwritable_dir(env):
    """An unwritable cache (/proc refuses new entries even to root, unlike a chmod-ed folder)."""
    s = env.scene()
    env.monkeypatch.setenv("NAKA_GS_CACHE", "/proc/naka-gs-cache")
    env.monkeypatch.setattr(safe_io, "_fallback", {})
    return lambda: Enhancer(NAKA).enhance_images([torch.zeros(4, 4, 3)]), [s]


def cache_off_touches_no_cache(env):
    blocker = env.tmp / "not-a-dir"
    blocker.write_text("a file")
    env.monkeypatch.setenv("NAKA_GS_CACHE", str(blocker))
    env.monkeypatch.setattr(safe_io, "_fallback", {})
    enhancer = Enhancer(EnhanceConfig(correction="none", use_cache=False))
    return lambda: (enhancer, enhancer.enhance_images([torch.zeros(4, 4, 3)])), [blocker]


def _no_cache_used(env, result):
    enhancer, _ = result
    assert enhancer.cache_dir is None and "not writable" not in env.log()
    assert sorted(q.name for q in env.tmp.iterdir()) == ["not-a-dir"]


def cache_disk_full_on_write(env):
    def full(*_a, **_k):
        raise OSError(28, "No space left on device")

    env.monkeypatch.setattr(np, "save", full)
    images = [torch.zeros(4, 4, 3), torch.ones(4, 4, 3)]
    return lambda: Enhancer(NAKA).enhance_images(images), []


def _warned_once_and_went_on(env, out):
    log = env.log()
    assert len(out) == 2 and log.count("not caching enhanced images") == 1
    assert not [q for q in (env.tmp / "naka-cache").rglob("*") if q.is_file()]


def sim_out_existing_scene(env):
    s = env.scene()
    spec = write_spec(env.tmp, [])
    argv = ["naka-gs-sim", str(spec), "--out", str(s)]
    return run_console(env, sim_cli.entrypoint, argv), [s, spec]


def sim_out_contains_spec(env):
    folder = env.tmp / "specs"
    folder.mkdir()
    spec = write_spec(folder, [])
    return lambda: sim_cli.Sim(spec=spec, out=folder).main(), [folder]


def sim_rerun_replaces_own_scene(env):
    spec, out = write_spec(env.tmp, []), env.tmp / "scene"

    def action():
        sim_cli.Sim(spec=spec, out=out).main()
        (out / "sparse").mkdir()  # e.g. a COLMAP model that naka-gs-sim did not write
        (out / "sparse" / "cameras.bin").write_bytes(b"x")
        sim_cli.Sim(spec=spec, out=out).main()

    return action, [spec]


def sim_rerun_replaces_own_scene_cleanly(env):
    spec, out = write_spec(env.tmp, []), env.tmp / "scene"

    def action():
        sim_cli.Sim(spec=spec, out=out).main()
        (out / "train" / "stale.png").write_bytes((out / "train_gt" / "0000.png").read_bytes())
        safe_io.write_marker(out, "naka-gs-sim")  # a file of an earlier (bigger) scene of ours
        return sim_cli.Sim(spec=spec, out=out).main()

    return action, [spec]


def _fresh_scene(env, out):
    assert not (out / "train" / "stale.png").exists() and (out / "transforms_train.json").is_file()
    assert "train/stale.png" not in safe_io.written_files(out)
    assert sorted(q.name for q in env.tmp.iterdir()) == ["s.yaml", "scene"]  # no staging or old copy left


def raster_absurd_focal_and_nan_means(env):
    from naka_gs_plugin.model.rasterize_cpu_fast import rasterization
    from tests.helpers import make_scene

    scene = make_scene(200, 64, 48)
    scene["Ks"][:, 0, 0] = scene["Ks"][:, 1, 1] = 1e10
    scene["means"][5] = float("nan")

    def action():
        means = scene["means"].clone().requires_grad_()
        colors, alphas, _ = rasterization(**{**scene, "means": means})
        (colors.sum() + alphas.sum()).backward()
        return colors, alphas

    return action, []


def _finite_render(env, out):
    colors, alphas = out
    assert torch.isfinite(colors).all() and torch.isfinite(alphas).all()


CASES: List[Case] = [
    (pd_out_parent_of_input, Raises(ProcessDataError, "--output-dir")),
    (pd_out_equal_input, Raises(ProcessDataError, "is the input")),
    (pd_out_inside_input, Raises(ProcessDataError, "is inside the input")),
    (pd_overwrite_foreign_folder, Raises(ProcessDataError, "not written by naka-gs (no .naka-gs-output marker)")),
    (pd_existing_without_overwrite, Raises(ProcessDataError, "already exists and is not empty")),
    (pd_overwrite_ours_holding_a_user_file, Raises(ProcessDataError, "holds notes.txt, which naka-gs did not write")),
    (pd_output_is_a_file, Raises(ProcessDataError, "exists and is not a folder")),
    (pd_overwrite_ours_replaces_it, Ok(_replaced)),
    (pd_failed_run_keeps_old_output, Raises(ProcessDataError, "only 0 of 3 images registered")),
    (pd_console_exit, Exits(1, "contains the input")),
    (pd_three_photos_one_point_console, Exits(1, "3D point(s) triangulated from")),
    (enh_out_is_the_images_folder, Raises(UnsafeOutputError, "--out")),
    (enh_out_is_the_scene, Raises(UnsafeOutputError, "contains the input")),
    (enh_out_inside_the_images_folder, Raises(UnsafeOutputError, "is inside the input")),
    (enh_out_foreign_nonempty, Raises(UnsafeOutputError, "not written by naka-gs")),
    (enh_rerun_replaces_own_output, Ok(_enhanced_written)),
    (enh_truncated_jpeg_console, Exits(1, "truncated or corrupt JPEG")),
    (img_truncated_jpeg, Raises(ImageReadError, "truncated or corrupt JPEG (image file is truncated")),
    (img_zero_size, Raises(ImageReadError, "empty file (0 bytes)")),
    (img_not_an_image, Raises(ImageReadError, "unreadable image (truncated, corrupt or not a PNG/JPEG/TIFF)")),
    (img_truncated_png, Raises(ImageReadError, "unreadable image")),
    (dm_truncated_jpeg_float32, Raises(ImageReadError, "truncated or corrupt JPEG")),
    (dm_truncated_jpeg_uint8, Raises(ImageReadError, "truncated or corrupt JPEG")),
    (dp_downscale_truncated_jpeg, Raises(ImageReadError, "truncated or corrupt JPEG")),
    (dm_all_black_images, Raises(LowLightDataError, "all 8 training images are black (no contrast: 0000.png spans")),
    (dm_all_white_images_uint8, Raises(LowLightDataError, "all 8 training images are white")),
    (dm_one_black_image, Ok(_warned_blank_view)),
    (cam_focal_1e10, Raises(LowLightDataError, "px is over 100.0x the image size -- give focal lengths in pixels")),
    (cam_focal_zero, Raises(LowLightDataError, "focal length fl_x, fl_y = 0.0")),
    (cam_focal_nan, Raises(LowLightDataError, "are not all finite")),
    (cam_focal_string, Raises(LowLightDataError, "'fl_x' is 'abc', not a number")),
    (cam_width_zero, Raises(LowLightDataError, "image size w x h = 0.0")),
    (cam_distortion_string, Raises(LowLightDataError, "'k1' is 'x', not a number")),
    (cam_zero_rotation, Raises(LowLightDataError, "frame 0 'transform_matrix' rotation block is not a rotation")),
    (cam_scaled_rotation, Raises(LowLightDataError, "rotation block is not a rotation (|R^T R - I| = 3")),
    (cam_reflection, Raises(LowLightDataError, "det -1")),
    (cam_infinite_translation, Raises(LowLightDataError, "frame 0 'transform_matrix' is not a finite 4x4")),
    (cam_bottom_rows_zero, Ok(_padded_read_as_meant)),
    (cam_bottom_row_not_homogeneous, Raises(LowLightDataError, "bottom row is [0.0, 0.0, 1.0, 1.0], not [0, 0, 0, 1]")),
    (cam_one_camera_far_out, Raises(LowLightDataError, "camera is 1e+09 from the cameras' median centre, over 100x")),
    (cam_all_at_one_position, Raises(LowLightDataError, "all 8 training cameras are at one position")),
    (cam_distortion_absurd, Raises(LowLightDataError, "distortion k1=50, k2=-80 scales the image corner by 3.07")),
    (img_float32_tiff_trains, Ok(_all_loaded)),
    (img_float32_tiff_trains_uint8, Ok(_all_loaded)),
    (img_float32_tiff_with_nan, Raises(ImageReadError, "0000.tif: 1 pixels are NaN/Inf")),
    (
        seed_truncated_colmap_points,
        Raises(PointSourceError, "points3D.bin: unreadable COLMAP model file, truncated or corrupt (record"),
    ),
    (seed_ply_all_at_1e30, Raises(PointSourceError, "300 of 300 points lie over 10000x the camera spread away")),
    (seed_ply_some_at_1e30, Ok(_far_dropped_with_warning)),
    (ppm_out_unwritable_console, Exits(1, "--out /proc/naka-gs.ply: cannot write it")),
    (ppm_out_is_the_input, Exits(1, "is an input of this run")),
    (
        grid_malformed_yaml,
        Exits(2, "grid.yaml: malformed YAML (expected ',' or '}', but got '<scalar>' at line 3", prefix=BENCH),
    ),
    (grid_every_run_failed, Exits(1, "all 2 runs failed (first toy/a: BenchSpecError:", prefix=BENCH)),
    (correction_resume_garbage_console, Exits(1, "latest.pt is not a readable torch checkpoint (UnpicklingError)")),
    (cache_nested_writes_use_unique_temporaries, Ok(_last_writer_wins)),
    (cache_imwrite_fails, Raises(LowLightDataError, "cannot write the downscaled copy", _nothing_committed)),
    (
        cache_disk_full_cuts_a_copy_short,
        Raises(LowLightDataError, "(disk full or not writable?; nothing was kept)", _nothing_committed),
    ),
    (cache_unreadable_entry_is_not_the_photo, Raises(ImageReadError, "naka-gs cache file, not your photo: delete it")),
    (cache_corrupt_downscaled_copy, Ok(_recomputed_with_warning)),
    (cache_corrupt_enhanced_entry, Ok(_enhanced_recomputed)),
    (cache_env_names_a_file, Ok(_fell_back_once)),
    (cache_unwritable_dir, Ok(_fell_back_once)),
    (cache_off_touches_no_cache, Ok(_no_cache_used)),
    (cache_disk_full_on_write, Ok(_warned_once_and_went_on)),
    (sim_out_existing_scene, Exits(1, "not written by naka-gs")),
    (sim_out_contains_spec, Raises(UnsafeOutputError, "contains the input")),
    (sim_rerun_replaces_own_scene, Raises(UnsafeOutputError, "holds sparse/cameras.bin, which naka-gs did not write")),
    (sim_rerun_replaces_own_scene_cleanly, Ok(_fresh_scene)),
    (raster_absurd_focal_and_nan_means, Ok(_finite_render)),
]


@pytest.mark.parametrize("make, expect", CASES, ids=[make.__name__ for make, _ in CASES])
def test_bad_input(make, expect, toy_scene, tmp_path, monkeypatch, capsys):
    check_case(Env(tmp_path, toy_scene, monkeypatch, capsys), make, expect)
