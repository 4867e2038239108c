"""``naka-gs-calibrate PAIRS --out PROFILE``: calibrate a camera once from a few dark/normal pairs.

PAIRS is a folder with ``low/`` and ``high/`` (same file names) or a ``lowlight-data`` scene with
``transforms_reference.json`` (:mod:`naka_gs_plugin.data.pairs`). The pairs are checked and aligned (one line
per bad pair, ``naka-gs: <message>``, exit status 1), each pair's exposure ratio is printed, the dark images go through the enhancement
chain a run uses (``--enhance.*``, the same cache), and a camera profile is fitted from the chain's output to the
normal images (:mod:`naka_gs_plugin.enhance.profile`). Writes PROFILE (a .json file) and a before/after sheet
beside it (rows: dark, enhanced without the profile, with it, normal). Use it with
``ns-train naka-gs --pipeline.datamanager.enhance.profile PROFILE`` or ``naka-gs-enhance --enhance.profile PROFILE``.
Both files are written into a hidden sibling folder and moved into place when complete (the profile last); an
existing PROFILE is replaced only if it is a camera profile, and Ctrl-C or SIGTERM removes the unfinished output and
exits 130 / 143.
"""

from __future__ import annotations

import dataclasses
import resource
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch
import tyro
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image

from naka_gs_plugin.data.pairs import Pair, find_pairs, load_pairs
from naka_gs_plugin.data.safe_io import OutputFile, UnsafeOutputError, staged_output
from naka_gs_plugin.enhance.pipeline import EnhanceConfig, EnhanceOptionError, Enhancer
from naka_gs_plugin.enhance.profile import CameraProfile, CameraProfileError, apply_profile, chain_key, fit_profile
from naka_gs_plugin.enhance.stages import ExposureStage
from naka_gs_plugin.metrics import psnr
from naka_gs_plugin.scripts import run
from naka_gs_plugin.sheet import contact_sheet


def _log(message: str) -> None:
    CONSOLE.log(f"[naka-gs] {message}", markup=False)


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

    def sheet_path(self) -> Path:
        return self.out.with_name(f"{self.out.stem}_sheet.png")

    def _check_out(self) -> None:
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
        found = find_pairs(self.pairs)
        inputs = sorted({p.parent for pair in found for p in (pair.low_path, pair.high_path)})
        output = OutputFile("a camera profile", is_profile)
        with staged_output(self.out, tool="naka-gs-calibrate", what="--out", inputs=inputs, file=output) as stage:
            return self._calibrate(found, stage, start)

    def _calibrate(self, found: Sequence[Pair], stage: Path, start: float) -> CameraProfile:
        pairs = load_pairs(list(found))
        for pair in pairs:
            _log(
                f"pair {pair.name}: exposure ratio x{pair.exposure_ratio:.1f}, aligned by "
                f"({pair.shift[0]:+.2f}, {pair.shift[1]:+.2f}) px"
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
        enhanced = enhancer.enhance_images(lows, description=f"Enhancing {len(pairs)} dark images")
        fit_start = time.perf_counter()
        curves, matrix, stats = fit_profile(enhanced, highs, seed=self.seed)
        stats["seconds"] = round(time.perf_counter() - fit_start, 2)
        profile = CameraProfile(curves=curves.tolist(), matrix=matrix.tolist(), chain=chain_key(enhancer.view_stages))
        profiled = [apply_profile(e, profile) for e in enhanced]
        # "Before": what a run without the profile trains on (the scene exposure step at its default).
        target = self.enhance.exposure_target()
        unprofiled = enhanced if target is None else ExposureStage(target=target).apply_all(list(enhanced))
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

    def _sheet(self, stage: Path, pairs: Sequence[Pair], enhanced: list, profiled: list) -> None:
        k = min(self.sheet_pairs, len(pairs))
        pick = np.linspace(0, len(pairs) - 1, k).round().astype(int)
        rows = [[pairs[i].low for i in pick], [enhanced[i].numpy() for i in pick], [profiled[i].numpy() for i in pick]]
        rows.append([pairs[i].high for i in pick])
        sheet = contact_sheet(rows)
        Image.fromarray(sheet).save(stage / self.sheet_path().name, format="PNG")
        _log(f"sheet (dark | enhanced | with the profile | normal): {self.sheet_path()}")


def entrypoint(args: Optional[Sequence[str]] = None) -> None:
    """Console script ``naka-gs-calibrate`` (:func:`naka_gs_plugin.scripts.run`); bad pairs print one line each."""
    run(Calibrate.main, Calibrate, args)


if __name__ == "__main__":
    entrypoint()
