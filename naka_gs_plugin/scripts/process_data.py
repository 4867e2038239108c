"""``naka-gs-process-data --data IMAGES_DIR --output-dir SCENE``: poses for a dark capture.

COLMAP on raw low-light photos registers few or no images. Here the photos are enhanced (the
training enhancement, :class:`~naka_gs_plugin.enhance.pipeline.Enhancer`) **for feature extraction
only**, pycolmap runs SIFT extraction, matching and incremental mapping with one shared camera, and
the result is written as a ``lowlight-data`` scene that references the **original** low-light images::

    SCENE/images/<name>            byte copies of the registered originals (or video frames)
    SCENE/transforms_train.json    fl_x fl_y cx cy w h + k1 k2 p1 p2, frames with OpenGL c2w
    SCENE/transforms_test.json     "eval_truth": "dark"; the training views themselves (the default), or with
                                   --eval-every N every N-th registered view (name order), held out
    SCENE/sparse/0/*.bin           the COLMAP model (image names = SCENE/images names): point source
    SCENE/process_data.json        the report: registered / total, reprojection error, points, timings

Poses stay in COLMAP's world frame (no re-orientation: the dataparser normalizes), so the sparse
points and the transforms share one frame. Every registered view trains by default: a held-out view would carry a
low-light image, not normal-light truth, so ``ns-eval`` on such a scene says so in one line, and metrics of views held
out with ``--eval-every N`` are labelled ``vs_dark_*`` during training. Everything is staged in a hidden sibling folder and moved into place only when
at least 3 images registered: a failed run leaves nothing behind, and Ctrl-C or SIGTERM removes it and exits
130 / 143, even inside pycolmap. The scene's ``.naka-gs-output`` marker lists its files; ``--overwrite`` replaces
only such a folder holding nothing else, and an --output-dir equal to, inside or containing --data is refused.
Byte-identical copies among the photos are refused before any work; every long stage shows its progress.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import re
import shutil
import subprocess
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import cv2
import numpy as np
import pycolmap
import torch
from nerfstudio.utils.rich_utils import CONSOLE
from rich.table import Table

from naka_gs_plugin.data.images import IMAGE_SUFFIXES, ImageReadError, read_rgb, write_image
from naka_gs_plugin.data.safe_io import UnsafeOutputError, staged_output
from naka_gs_plugin.enhance.checkpoint import DEFAULT_WEIGHTS
from naka_gs_plugin.enhance.pipeline import EnhanceConfig, Enhancer
from naka_gs_plugin.errors import UserError
from naka_gs_plugin.points.sfm import (
    CameraModel,
    MatchingMethod,
    c2w_opencv_of,
    database_progress,
    database_stats,
    extract_features,
    incremental_mapping,
    match_features,
    quiet_colmap,
)
from naka_gs_plugin.progress import StageProgress, progress_from
from naka_gs_plugin.scripts import run

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v")
MIN_REGISTERED = 3
MIN_MODEL_POINTS = 50
"""Fewest 3D points a model may have: below it the poses rest on a handful of matches.

Measured: LOM's COLMAP models hold 800-8700 points (33-48 views); this tool on 4 dark LOM bike views
gives 181; on 3 dark LOM sofa views (low/1-3) it registers all 3 with 1 point."""
ENHANCE_CHUNK = 16
"""Images enhanced per call with per-image statistics (bounds memory on large captures)."""
PNG_FAST = [cv2.IMWRITE_PNG_COMPRESSION, 1]
"""cv2 PNG options of the SfM copies (temporary: speed over size)."""
GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])
"""Right-multiply an OpenCV camera-to-world to get the OpenGL one (and back)."""


class ProcessDataError(UserError, ValueError):
    """Bad input or failed reconstruction; one line naming the file or folder and what to try."""


class TooFewRegisteredError(ProcessDataError):
    """Fewer than :data:`MIN_REGISTERED` images registered; carries the counts and stage timings."""

    def __init__(self, message: str, registered: int, total: int, seconds: Dict[str, float]):
        super().__init__(message)
        self.registered, self.total, self.seconds = registered, total, seconds


def natural_key(name: str) -> List[object]:
    """Sort key with numbers compared as numbers: ``2.JPG`` before ``10.JPG``."""
    return [int(tok) if tok.isdigit() else tok.lower() for tok in re.split(r"(\d+)", name)]


def list_images(folder: Path) -> List[Path]:
    """Image files directly inside ``folder`` (by suffix, case-insensitive), in natural name order."""
    return sorted(
        (p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
        key=lambda p: natural_key(p.name),
    )


def refuse_duplicates(sources: Sequence[Path]) -> None:
    """Refuse photos that are byte-identical copies of one another (by content hash, with progress): structure from
    motion cannot place two copies of one view, and pycolmap spends minutes matching them before it fails."""
    seen: Dict[str, Path] = {}
    copies: List[Tuple[Path, Path]] = []
    with StageProgress() as progress:
        task = progress.add_task("Checking the photos for copies", total=len(sources))
        for path in sources:
            digest = hashlib.sha256()
            try:
                with open(path, "rb") as fh:
                    for block in iter(lambda: fh.read(1 << 20), b""):
                        digest.update(block)
            except OSError as err:
                raise ProcessDataError(f"{path}: cannot be read ({err.strerror or err}) -- restore it or move it out")
            first = seen.setdefault(digest.hexdigest(), path)
            if first is not path:
                copies.append((first, path))
            progress.advance(task)
    if copies:
        first, copy = copies[0]
        more = f" ({len(copies)} copies in all)" if len(copies) > 1 else ""
        raise ProcessDataError(
            f"{copy} is an identical copy of {first}{more} -- structure from motion needs photos from different "
            f"viewpoints: keep one of each and move the copies out of {first.parent}"
        )


def extract_video_frames(video: Path, out: Path, fps: float) -> List[Path]:
    """Frames of ``video`` sampled at ``fps`` as lossless PNGs ``frame_00001.png`` ... (ffmpeg binary)."""
    ffmpeg = shutil.which("ffmpeg")
    if ffmpeg is None:
        raise ProcessDataError(
            f"{video}: video input needs the ffmpeg binary, which is not on PATH -- install it "
            "(e.g. `apt-get install ffmpeg`) or extract frames yourself and pass the folder to --data"
        )
    out.mkdir(parents=True, exist_ok=True)
    cmd = [ffmpeg, "-nostdin", "-loglevel", "error", "-i", str(video), "-vf", f"fps={fps}", str(out / "frame_%05d.png")]
    result = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    if result.returncode != 0:
        raise ProcessDataError(f"{video}: ffmpeg failed ({result.stdout.strip()[-300:]}) -- check the file plays")
    return list_images(out)


def camera_json(camera: pycolmap.Camera) -> Dict[str, float]:
    """A COLMAP camera as ``lowlight-data`` intrinsics: ``fl_x fl_y cx cy w h k1 k2 p1 p2``."""
    p = [float(v) for v in camera.params]
    model = camera.model_name
    if model == "OPENCV":
        fx, fy, cx, cy, k1, k2, p1, p2 = p
    elif model == "PINHOLE":
        (fx, fy, cx, cy), (k1, k2, p1, p2) = p, (0.0, 0.0, 0.0, 0.0)
    elif model == "SIMPLE_PINHOLE":
        (fx, cx, cy), fy, (k1, k2, p1, p2) = p, p[0], (0.0, 0.0, 0.0, 0.0)
    elif model == "SIMPLE_RADIAL":
        (fx, cx, cy, k1), fy, (k2, p1, p2) = p, p[0], (0.0, 0.0, 0.0)
    elif model == "RADIAL":
        (fx, cx, cy, k1, k2), fy, (p1, p2) = p, p[0], (0.0, 0.0)
    else:
        raise ProcessDataError(f"camera model {model} has no lowlight-data equivalent (use OPENCV or PINHOLE)")
    return {
        "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": int(camera.width), "h": int(camera.height),
        "k1": k1, "k2": k2, "p1": p1, "p2": p2,
    }  # fmt: skip


@dataclass
class ProcessData:
    """Enhance a folder of dark photos (or a video), run pycolmap SfM, write a lowlight-data scene."""

    data: Path
    """Folder of images (top level only) or a video file (needs the ffmpeg binary)."""
    output_dir: Path
    """Scene folder to create (must not exist or be empty, unless --overwrite)."""
    camera_model: CameraModel = "OPENCV"
    """One camera shared by all images; OPENCV estimates k1 k2 p1 p2."""
    matching_method: MatchingMethod = "exhaustive"
    """``exhaustive`` (all pairs; up to a few hundred images) or ``sequential`` (video / ordered captures)."""
    sequential_overlap: int = 10
    """Sequential matching: each image is matched with this many following ones (name order)."""
    max_image_size: int = 1600
    """SIFT runs on images resized to at most this many pixels per side (poses and intrinsics stay full size)."""
    eval_every: int = 0
    """0: every registered image trains (no held-out view: it would be a dark capture, not normal-light truth);
    N >= 2: hold out every N-th (name order, starting with the first), scored against its dark image."""
    video_fps: float = 2.0
    """Frames per second sampled from a video input."""
    enhance: EnhanceConfig = field(default_factory=lambda: EnhanceConfig(use_cache=False))
    """Enhancement of the copies SfM sees (the scene keeps the originals); ``--enhance.method none`` = raw."""
    overwrite: bool = False
    """Replace an existing non-empty --output-dir that naka-gs-process-data wrote (its .naka-gs-output
    marker lists every file in it), only after the new scene is complete."""
    refine_principal_point: bool = False
    """Let bundle adjustment move the principal point (COLMAP keeps it at the image centre by default)."""
    seed: int = 0
    """Seed of COLMAP's RANSAC and mapper."""

    def main(self) -> Dict[str, object]:
        self._check_args()
        try:
            with staged_output(
                self.output_dir,
                tool="naka-gs-process-data",
                what="--output-dir",
                inputs=[self.data],
                overwrite=self.overwrite,
            ) as stage:
                report = self._process(stage)
        except UnsafeOutputError as err:
            raise ProcessDataError(str(err)) from None
        report["scene"] = str(self.output_dir.resolve())
        self._print(report)
        return report

    def _check_args(self) -> None:
        if not self.data.exists():
            raise ProcessDataError(f"{self.data}: not found -- pass a folder of images or a video file to --data")
        if self.data.is_file() and self.data.suffix.lower() not in VIDEO_SUFFIXES:
            raise ProcessDataError(
                f"{self.data}: not a folder or a video ({', '.join(VIDEO_SUFFIXES)}) -- pass the folder of images"
            )
        if self.eval_every < 0 or self.eval_every == 1:
            raise ProcessDataError(
                f"--eval-every {self.eval_every}: must be 0 (every view trains) or >= 2 (one view in N is held out)"
            )
        if self.max_image_size < 64 or self.video_fps <= 0 or self.sequential_overlap < 1:
            raise ProcessDataError("--max-image-size must be >= 64, --video-fps > 0, --sequential-overlap >= 1")

    def _process(self, stage: Path) -> Dict[str, object]:
        seconds: Dict[str, float] = {}
        work, enhanced_dir = stage / "work", stage / "work" / "enhanced"
        enhanced_dir.mkdir(parents=True)

        t0 = time.perf_counter()
        if self.data.is_file():
            sources = extract_video_frames(self.data, work / "frames", self.video_fps)
            seconds["video"] = time.perf_counter() - t0
            t0 = time.perf_counter()
        else:
            sources = list_images(self.data)
            refuse_duplicates(sources)
        if len(sources) < MIN_REGISTERED:
            raise ProcessDataError(
                f"{self.data}: {len(sources)} image(s) found ({', '.join(IMAGE_SUFFIXES)}) -- "
                f"structure from motion needs at least {MIN_REGISTERED} overlapping photos (ideally 20+)"
            )
        names = [p.name for p in sources]
        sfm_names = [f"{name}.png" for name in names]  # 8-bit PNG copies seen by SIFT
        correction = self._enhance_to(sources, enhanced_dir, sfm_names)
        seconds["enhance"] = time.perf_counter() - t0

        database = work / "database.db"
        with quiet_colmap():
            t0 = time.perf_counter()
            with StageProgress() as progress:
                task = progress.add_task(f"SIFT features (images of {len(names)})", total=len(names))
                with progress_from(progress, task, lambda: database_progress(database)["images_with_keypoints"]):
                    extract_features(
                        database, enhanced_dir, sfm_names, pycolmap.CameraMode.SINGLE, self.camera_model,
                        self.max_image_size,
                    )  # fmt: skip
            seconds["extract"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            # Exhaustive: every pair; sequential: COLMAP's pairs are not known ahead, so the count alone.
            pairs = len(names) * (len(names) - 1) // 2 if self.matching_method == "exhaustive" else None
            with StageProgress() as progress:
                task = progress.add_task(f"{self.matching_method} matching (image pairs)", total=pairs)
                with progress_from(progress, task, lambda: database_progress(database)["matched_pairs"]):
                    match_features(database, self.matching_method, self.sequential_overlap)
            seconds["match"] = time.perf_counter() - t0
            stats = database_stats(database)
            t0 = time.perf_counter()
            with StageProgress() as progress:
                task = progress.add_task("Incremental mapping (images registered)", total=len(names))
                model, n_models = incremental_mapping(
                    database,
                    enhanced_dir,
                    work / "mapping",
                    self.seed,
                    lambda: progress.advance(task),
                    self.refine_principal_point,
                )
                progress.update(task, completed=model.num_reg_images() if model is not None else 0)
            seconds["mapping"] = time.perf_counter() - t0

        registered = 0 if model is None else model.num_reg_images()
        if model is None or registered < MIN_REGISTERED:
            raise TooFewRegisteredError(
                f"{self.data}: only {registered} of {len(names)} images registered "
                f"({stats['keypoints']} keypoints, {stats['verified_pairs']} verified pairs) -- try more overlapping "
                "photos, a larger --max-image-size, --matching-method exhaustive, or a stronger enhancement "
                "(--enhance.sigma smaller)",
                registered,
                len(names),
                seconds,
            )

        points = model.num_points3D()
        if points < MIN_MODEL_POINTS:
            raise ProcessDataError(
                f"{self.data}: only {points} 3D point(s) triangulated from {registered} registered images (real "
                f"captures give hundreds), so the poses are unreliable -- add more overlapping photos (ideally 20+), "
                "or try --matching-method exhaustive or a larger --max-image-size"
            )
        t0 = time.perf_counter()
        report = self._write_scene(stage, model, sources, names, sfm_names)
        shutil.rmtree(work)
        seconds["write"] = time.perf_counter() - t0
        report.update(
            {
                "models": n_models,
                "keypoints": stats["keypoints"],
                "verified_pairs": stats["verified_pairs"],
                "seconds": seconds,
                "args": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(self).items() if k != "enhance"},
                "enhance": {
                    **{
                        k: str(v) if isinstance(v, Path) else v
                        for k, v in asdict(self.enhance).items()
                        if k != "_target"
                    },
                    "correction": None if correction is None else str(correction),
                },
            }
        )
        (stage / "process_data.json").write_text(json.dumps(report, indent=1))
        return report

    def _enhancer(self) -> Enhancer:
        """The configured enhancement; the default correction network only where its weights are shipped."""
        config = self.enhance
        if config.method == "naka" and config.correction == "default" and not DEFAULT_WEIGHTS.is_file():
            CONSOLE.log(
                f"[naka-gs] correction network: no default weights in this install ({DEFAULT_WEIGHTS}); "
                "enhancing with Naka only",
                markup=False,
            )
            config = dataclasses.replace(config, correction="none")
        try:
            return Enhancer(config)
        except FileNotFoundError as err:
            raise ProcessDataError(f"{err}".replace("--pipeline.datamanager.enhance.", "--enhance.")) from None

    def _enhance_to(self, sources: Sequence[Path], folder: Path, sfm_names: Sequence[str]) -> Optional[Path]:
        """Enhanced 8-bit PNG of every source image in ``folder``; checks readability and equal sizes.
        Returns the correction checkpoint used (None: Naka only or no enhancement)."""
        enhancer = self._enhancer()
        chunk = ENHANCE_CHUNK if not any(stage.scene_wide() for stage in enhancer.view_stages) else len(sources)
        size: Optional[Tuple[int, int]] = None
        for start in range(0, len(sources), chunk):
            batch = []
            for path in sources[start : start + chunk]:
                try:
                    image = read_rgb(path)
                except ImageReadError as err:
                    raise ProcessDataError(f"{err} (or move it out of {path.parent})") from None
                if size is None:
                    size = image.shape[:2]
                elif image.shape[:2] != size:
                    raise ProcessDataError(
                        f"{path}: {image.shape[1]}x{image.shape[0]} but {sources[0].name} is {size[1]}x{size[0]} -- "
                        "one shared camera needs images of one size; move the odd ones out"
                    )
                batch.append(torch.from_numpy(image))
            end = min(start + chunk, len(sources))
            out = enhancer.enhance_images(batch, description=f"Enhancing images {start + 1}-{end} for SfM")
            for name, image in zip(sfm_names[start:end], out):
                bgr = (image.numpy() * 255.0 + 0.5).astype(np.uint8)[..., ::-1]
                try:
                    write_image(folder / name, np.ascontiguousarray(bgr), PNG_FAST)
                except OSError as err:
                    raise ProcessDataError(f"{err} -- free disk space next to --output-dir") from None
        return enhancer.correction_path

    def _write_scene(
        self,
        stage: Path,
        model: pycolmap.Reconstruction,
        sources: Sequence[Path],
        names: Sequence[str],
        sfm_names: Sequence[str],
    ) -> Dict[str, object]:
        index = {s: i for i, s in enumerate(sfm_names)}
        registered = []
        for image in model.images.values():
            i = index[image.name]
            image.name = names[i]  # the model names the scene's images, not the SfM copies
            if image.has_pose:
                registered.append((i, image))
        registered.sort(key=lambda pair: pair[0])
        (stage / "images").mkdir()
        frames: Dict[str, list] = {"train": [], "test": []}
        for k, (i, image) in enumerate(registered):
            shutil.copy2(sources[i], stage / "images" / names[i])
            c2w = c2w_opencv_of(image) @ GL_FROM_CV
            split = "test" if self.eval_every and k % self.eval_every == 0 else "train"
            frames[split].append({"file_path": f"images/{names[i]}", "transform_matrix": c2w.tolist()})
        if not frames["train"]:
            raise ProcessDataError(f"{self.data}: no training view left with --eval-every {self.eval_every}")
        cameras = {image.camera_id for _, image in registered}
        intrinsics = camera_json(model.cameras[cameras.pop()])
        # The eval split holds dark captures (the training views when none is held out): said in the json, so that
        # metrics against it are labelled and ns-eval refuses them.
        train = {**intrinsics, "frames": frames["train"]}
        test = {**intrinsics, "eval_truth": "dark", "frames": frames["test"] or frames["train"]}
        (stage / "transforms_train.json").write_text(json.dumps(train, indent=1))
        (stage / "transforms_test.json").write_text(json.dumps(test, indent=1))
        sparse = stage / "sparse" / "0"
        sparse.mkdir(parents=True)
        model.write_binary(sparse)
        done = {names[i] for i, _ in registered}
        return {
            "registered": len(registered),
            "total": len(names),
            "unregistered": [n for n in names if n not in done],
            "train_views": len(frames["train"]),
            "test_views": len(frames["test"]),
            "points": int(model.num_points3D()),
            "mean_reprojection_error_px": float(model.compute_mean_reprojection_error()),
            "mean_track_length": float(model.compute_mean_track_length()),
            "camera": {"model": model.cameras[registered[0][1].camera_id].model_name, **intrinsics},
        }

    def _print(self, report: Dict[str, object]) -> None:
        table = Table(title=f"naka-gs-process-data: {report['scene']}")
        table.add_column("quantity")
        table.add_column("value", justify="right")
        table.add_row("images registered / total", f"{report['registered']} / {report['total']}")
        table.add_row("train / test views", f"{report['train_views']} / {report['test_views']}")
        table.add_row("3D points", str(report["points"]))
        table.add_row("mean reprojection error (px)", f"{report['mean_reprojection_error_px']:.3f}")
        table.add_row("keypoints / verified pairs", f"{report['keypoints']} / {report['verified_pairs']}")
        for stage, sec in report["seconds"].items():  # type: ignore[union-attr]
            table.add_row(f"time: {stage} (s)", f"{sec:.2f}")
        CONSOLE.print(table)
        if report["unregistered"]:
            CONSOLE.log(
                f"[naka-gs] not registered (left out of the scene): {', '.join(report['unregistered'])}", markup=False
            )
        CONSOLE.log(
            f"[naka-gs] next: ns-train naka-gs --data {report['scene']}  (dataparser lowlight-data)", markup=False
        )


def entrypoint(args: Optional[Sequence[str]] = None) -> None:
    """Console script ``naka-gs-process-data`` (:func:`naka_gs_plugin.scripts.run`)."""
    run(ProcessData.main, ProcessData, args)


if __name__ == "__main__":
    entrypoint()
