"""``naka-gs-calibrate PAIRS --out PROFILE``: calibrate a camera once from a few dark/normal pairs.

PAIRS is a folder with ``low/`` and ``high/`` (same file names) or a ``lowlight-data`` scene with
``transforms_reference.json`` (:mod:`naka_gs_plugin.data.pairs`). The pairs are checked and aligned (one line
per bad pair, ``naka-gs: <message>``, exit status 1), each pair's exposure ratio is printed, the dark images go through the enhancement
chain a run uses (``--enhance.*``, the same cache), and a camera profile is fitted from the chain's output to the
normal images (:mod:`naka_gs_plugin.enhance.profile`), where each aligned normal image has data. A pair that does
not align is left out with one warning line naming it, and so is said of pairs the fitted profile leaves far below
the others (:data:`FAR_BELOW_DB`). Writes PROFILE (a .json file) and a before/after sheet beside it
(``<PROFILE stem>_sheet.png``; rows: dark, enhanced without the profile, with it, normal). Use it with
``ns-train naka-gs --pipeline.datamanager.enhance.profile PROFILE`` or ``naka-gs-enhance --enhance.profile PROFILE``.

It keeps to its own files: PROFILE (and the sheet) may not lie inside the pairs' folder or one of its image folders,
nor contain them; an existing PROFILE is replaced only if it is a camera profile, an existing sheet only if
naka-gs-calibrate wrote it (its PNG text chunk :data:`SHEET_MARK` says so), each refused in one line before anything
is written. Both files are written into a hidden sibling folder and moved into place when complete (the profile
last); Ctrl-C or SIGTERM removes the unfinished output and exits 130 / 143.
"""

from __future__ import annotations

import dataclasses
import resource
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional, Sequence

import numpy as np
import torch
import tyro
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image, PngImagePlugin

from naka_gs_plugin.data.pairs import Pair, find_pairs, load_pairs
from naka_gs_plugin.data.safe_io import OutputFile, UnsafeOutputError, staged_output
from naka_gs_plugin.enhance.pipeline import EnhanceConfig, EnhanceOptionError, Enhancer
from naka_gs_plugin.enhance.profile import (
    LUT_MAX_SIZE,
    CameraProfile,
    CameraProfileError,
    apply_maps,
    apply_profile,
    chain_key,
    fit_lut,
    fit_profile,
)
from naka_gs_plugin.enhance.stages import ExposureStage
from naka_gs_plugin.metrics import psnr
from naka_gs_plugin.scripts import run
from naka_gs_plugin.sheet import contact_sheet

SHEET_MARK = ("naka-gs-output", "naka-gs-calibrate sheet")
"""The PNG text chunk (key, value) of a sheet naka-gs-calibrate wrote: the one file at the sheet's path it replaces
(as :data:`~naka_gs_plugin.data.safe_io.MARKER` marks the folders a command wrote)."""
FAR_BELOW_DB = 3.0
"""A pair whose PSNR with the profile is more than this below the pairs' median is named in a warning."""


def _log(message: str) -> None:
    CONSOLE.log(f"[naka-gs] {message}", markup=False)


def _warn(message: str) -> None:
    _log(f"warning: {message}")


def is_sheet(path: Path) -> bool:
    """Whether ``path`` is a before/after sheet naka-gs-calibrate wrote (a PNG file, not a link, with
    :data:`SHEET_MARK`); only its header is read."""
    if path.is_symlink() or not path.is_file():
        return False
    try:
        with Image.open(path) as image:
            return image.format == "PNG" and image.info.get(SHEET_MARK[0]) == SHEET_MARK[1]
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError):  # not an image, a damaged or huge one
        return False


def is_profile(path: Path) -> bool:
    """Whether ``path`` is a camera profile file (one that ``--out`` may replace)."""
    try:
        CameraProfile.load(path, "--out")
    except CameraProfileError:
        return False
    return True


@dataclass
class Calibrate:
    """Fit a camera profile from dark/normal pairs of one camera."""

    pairs: tyro.conf.Positional[Path]
    """A folder with low/ and high/ (matching file names), or a lowlight-data scene with transforms_reference.json."""
    out: Path = Path("camera-profile.json")
    """The profile file to write (.json); an existing file is replaced only if it is a camera profile."""
    enhance: EnhanceConfig = field(default_factory=EnhanceConfig)
    """The enhancement chain the profile is fitted after: use the options the runs will use."""
    sheet_pairs: int = 4
    """Pairs shown in the before/after sheet (``<out stem>_sheet.png`` beside the profile; 0: no sheet)."""
    seed: int = 0
    """Seed of the fit's random pixel batches."""
    lut_size: int = 0
    """Cells per axis of a residual 3D look-up table fitted after the curves and matrix (hue- and
    saturation-dependent colour; 17 or 33, up to 33; about 1-2 minutes more), or 0: none. Off by default: on
    BlueHawaii's unseen views it adds 0.8-1.3 dB, and it is not yet measured on scenes its pairs did not show
    (records/2026-12-07-hue-and-saturation.md)."""

    def sheet_path(self) -> Path:
        return self.out.with_name(f"{self.out.stem}_sheet.png")

    def _check_sheet(self) -> None:
        """Refuse a sheet path holding anything naka-gs-calibrate did not write (checked again before publishing)."""
        sheet = self.sheet_path()
        if self.sheet_pairs > 0 and (sheet.exists() or sheet.is_symlink()) and not is_sheet(sheet):
            raise UnsafeOutputError(
                f"{sheet}: exists and naka-gs-calibrate did not write it (the before/after sheet of --out {self.out} "
                "goes there; it is not replaced) -- move it away, choose another --out, or pass --sheet-pairs 0"
            )

    def _check_not_in_pairs(self, folders: Sequence[Path]) -> None:
        """Refuse --out (or its sheet) inside or containing the pairs' folder or one of its image folders: what it
        writes there would be read as pairs (or break them) the next time. The message names the innermost folder
        it is inside, else the outermost it contains."""
        for path in (self.out, self.sheet_path()):
            target = path.resolve()
            places = sorted(((f.resolve(), f) for f in folders), key=lambda pf: len(pf[0].parts))
            inside = [f for place, f in places if target == place or place in target.parents]
            contains = [f for place, f in places if target in place.parents]
            if inside or contains:
                relation, folder = ("is inside", inside[-1]) if inside else ("contains", contains[0])
                raise UnsafeOutputError(
                    f"--out {self.out}: {relation} the pairs' folder {folder} -- write the profile outside "
                    f"{self.pairs} (an output inside an input is refused)"
                )

    def _check_out(self) -> None:
        if self.lut_size != 0 and not 2 <= self.lut_size <= LUT_MAX_SIZE:
            raise EnhanceOptionError(
                f"--lut-size {self.lut_size}: a look-up table has 2 to {LUT_MAX_SIZE} cells per axis -- pass 17 or "
                f"33, or 0 for none"
            )
        if self.out.suffix.lower() != ".json":
            raise UnsafeOutputError(
                f"--out {self.out}: a camera profile is a .json file -- pass e.g. --out camera.json"
            )
        if self.enhance.profile is not None:
            raise EnhanceOptionError(
                f"--enhance.profile {self.enhance.profile}: calibration fits a profile, it does not apply one -- drop it"
            )
        if self.enhance.method != "naka":
            raise EnhanceOptionError("--enhance.method none: a profile is fitted after the naka enhancement -- drop it")

    def main(self) -> CameraProfile:
        """Check the pairs, fit, write the profile (and sheet); returns the profile."""
        start = time.perf_counter()
        self._check_out()
        self._check_sheet()
        found = find_pairs(self.pairs)
        inputs = sorted({self.pairs, *(p.parent for pair in found for p in (pair.low_path, pair.high_path))})
        self._check_not_in_pairs(inputs)
        output = OutputFile("a camera profile", is_profile)
        with staged_output(self.out, tool="naka-gs-calibrate", what="--out", inputs=inputs, file=output) as stage:
            profile = self._calibrate(found, stage, start)
            self._check_sheet()  # again: the folder may have changed while we worked
            return profile

    def _calibrate(self, found: Sequence[Pair], stage: Path, start: float) -> CameraProfile:
        pairs = load_pairs(list(found), warn=_warn)
        for pair in pairs:
            turned = f", turned {pair.rotation:+.2f} deg" if abs(pair.rotation) >= 0.01 else ""
            zoomed = f", zoomed x{pair.scale:.3f}" if abs(pair.scale - 1) >= 0.001 else ""
            _log(
                f"pair {pair.name}: exposure ratio x{pair.exposure_ratio:.1f}, aligned by "
                f"({pair.shift[0]:+.2f}, {pair.shift[1]:+.2f}) px{turned}{zoomed} (ECC correlation "
                f"{pair.correlation:.3f})"
            )
        ratios = np.array([p.exposure_ratio for p in pairs])
        if np.isfinite(ratios).any() and np.nanmax(ratios) > 1.5 * np.nanmin(ratios):
            _log(
                f"note: exposure ratios range x{np.nanmin(ratios):.0f}-x{np.nanmax(ratios):.0f}: the profile learns their "
                "mix; pairs shot with one pair of shutter speeds calibrate one darkness"
            )
        # The chain as a run applies it before the profile: no profile, no scene exposure lift (the profile
        # carries the normal exposure).
        enhancer = Enhancer(dataclasses.replace(self.enhance, exposure="none"))
        lows = [torch.from_numpy(p.low) for p in pairs]
        highs = [torch.from_numpy(p.high) for p in pairs]
        whole = enhancer.enhance_images(lows, description=f"Enhancing {len(pairs)} dark images")
        # Fitted and scored where the aligned normal image has data (a turned pair's corners have none).
        enhanced = [_crop(e, p) for e, p in zip(whole, pairs)]
        highs = [_crop(h, p) for h, p in zip(highs, pairs)]
        fit_start = time.perf_counter()
        curves, matrix, stats = fit_profile(enhanced, highs, seed=self.seed)
        lut = None
        if self.lut_size:
            lut, lut_stats = fit_lut(
                [apply_maps(e, curves, matrix) for e in enhanced], highs, self.lut_size, seed=self.seed
            )
            stats.update(lut_stats)
            lut = ((lut.double() * 1e5).round() / 1e5).tolist()  # 5 decimals: 1/400 of a code, a file a third as long
        stats["seconds"] = round(time.perf_counter() - fit_start, 2)
        profile = CameraProfile(
            curves=curves.tolist(), matrix=matrix.tolist(), chain=chain_key(enhancer.view_stages), lut=lut
        )
        profiled = [apply_profile(e, profile) for e in enhanced]
        # "Before": what a run without the profile trains on (the scene exposure step at its default).
        target = self.enhance.exposure_target()
        lifted = whole if target is None else ExposureStage(target=target).apply_all(list(whole))
        unprofiled = [_crop(e, p) for e, p in zip(lifted, pairs)]
        for pair, e, p, h in zip(pairs, unprofiled, profiled, highs):
            before = psnr(e.permute(2, 0, 1), h.permute(2, 0, 1))
            after = psnr(p.permute(2, 0, 1), h.permute(2, 0, 1))
            profile.pairs.append(
                {
                    "name": pair.name,
                    "exposure_ratio": round(pair.exposure_ratio, 2),
                    "shift_px": [round(s, 2) for s in pair.shift],
                    "psnr_before": round(before, 2),
                    "psnr_after": round(after, 2),
                }
            )
        self._far_below(profile.pairs)
        peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
        profile.fit = {**stats, "pairs": len(pairs), "total_seconds": round(time.perf_counter() - start, 1)}
        (stage / self.out.name).write_bytes(profile.to_json().encode())
        mean = lambda key: float(np.mean([row[key] for row in profile.pairs]))  # noqa: E731
        _log(
            f"profile {self.out}: {len(pairs)} pairs, PSNR against the normal images {mean('psnr_before'):.2f} -> "
            f"{mean('psnr_after'):.2f} dB (pairs it was fitted on), fit {stats['seconds']:.1f} s, "
            f"all {profile.fit['total_seconds']:.0f} s, peak memory {peak_gb:.1f} GB"
        )
        if self.sheet_pairs > 0:
            self._sheet(stage, pairs, unprofiled, profiled)
        return profile

    def _far_below(self, rows: List[dict]) -> None:
        """One warning line naming the pairs the profile leaves far below the others (another light, a moved
        object, another camera: pairs that teach something else)."""
        median = float(np.median([row["psnr_after"] for row in rows]))
        low = [row for row in rows if row["psnr_after"] < median - FAR_BELOW_DB]
        if low:
            names = ", ".join(f"{row['name']} ({row['psnr_after']:.1f} dB)" for row in low)
            _warn(
                f"with the profile, pair(s) {names} stay far below the others (median {median:.1f} dB against their "
                "normal images) -- look at them (another light, a moved object, another camera?) and calibrate "
                "again without them if they differ"
            )

    def _sheet(self, stage: Path, pairs: Sequence[Pair], enhanced: list, profiled: list) -> None:
        k = min(self.sheet_pairs, len(pairs))
        pick = np.linspace(0, len(pairs) - 1, k).round().astype(int)
        rows = [[_crop(pairs[i].low, pairs[i]) for i in pick], [enhanced[i].numpy() for i in pick]]
        rows += [[profiled[i].numpy() for i in pick], [_crop(pairs[i].high, pairs[i]) for i in pick]]
        sheet = contact_sheet(rows)
        mark = PngImagePlugin.PngInfo()
        mark.add_text(*SHEET_MARK)
        Image.fromarray(sheet).save(stage / self.sheet_path().name, format="PNG", pnginfo=mark)
        _log(f"sheet (dark | enhanced | with the profile | normal): {self.sheet_path()}")


def _crop(image, pair: Pair):
    """``image`` (``H W 3``, array or tensor) inside ``pair``'s :attr:`~naka_gs_plugin.data.pairs.Pair.box`."""
    x0, y0, x1, y1 = pair.box
    return image[y0:y1, x0:x1]


def entrypoint(args: Optional[Sequence[str]] = None) -> None:
    """Console script ``naka-gs-calibrate`` (:func:`naka_gs_plugin.scripts.run`); bad pairs print one line each."""
    run(Calibrate.main, Calibrate, args)


if __name__ == "__main__":
    entrypoint()
