"""The presets' front on a GPU (docs/cuda.md, "The presets on a GPU"), from the milestone lines of
`GRID=scripts/gpu/lom-big.yaml TRAIN_PARALLEL=1 bash scripts/gpu/run.sh train` (its train.log, or lom-big.tgz):
runs stopped by the lease write no results.json, their log lines are the record.

    .venv/bin/python docs/experiments/cuda/presets_front.py train.log [docs/img/gpu_presets_front.png]

Prints every milestone per scene and the mean over the scenes at each step every scene reached, per family;
plots the means (PSNR and LPIPS against training seconds, which are seconds of runs sharing one GPU).
"""

import re
import sys
import tarfile
from collections import defaultdict
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

LABELS = {
    "naka-gs": "splatfacto's schedule (the GPU naka-gs stops it at 7k)",
    "big": "splatfacto's schedule, splatfacto-big's densification",
    "naka-gs-fast": "the CPU's 7k of 10k (the GPU naka-gs-fast until 2026-12-04)",
}
"""The families of scripts/gpu/lom-big.yaml as run on 2026-12-04."""

LINE = re.compile(
    r"\[naka-gs bench\] (\w+)/([\w-]+) step (\d+): PSNR ([\d.]+) dB, SSIM ([\d.]+), LPIPS ([\d.]+), "
    r"(\d+) Gaussians, ([\d.]+) s training"
)


def _texts(source: Path):
    if not tarfile.is_tarfile(source):
        yield source.read_text(errors="replace")
        return
    with tarfile.open(source) as tar:
        for member in tar.getmembers():
            if member.isfile() and member.name.endswith(".log"):
                yield tar.extractfile(member).read().decode(errors="replace")


def milestones(source: Path) -> dict:
    """{family: {scene: {step: (psnr, ssim, lpips, gaussians, train_s)}}} from a log, or every log in an archive."""
    found = defaultdict(lambda: defaultdict(dict))
    for text in _texts(source):
        for m in LINE.finditer(text):
            scene, family, step = m.group(1), m.group(2), int(m.group(3))
            found[family][scene][step] = tuple(float(g) for g in m.groups()[3:])
    return found


def main(archive: Path, figure: Path | None) -> None:
    found = milestones(archive)
    means = {}
    for family, scenes in sorted(found.items()):
        print(f"\n{family}")
        for scene, steps in sorted(scenes.items()):
            for step, (p, s, lp, g, t) in sorted(steps.items()):
                print(f"  {scene:6s} {step:6d}: {p:.2f} / {s:.3f} / {lp:.3f}  {int(g):7d} G  {t:7.1f} s")
        common = sorted(set.intersection(*(set(v) for v in scenes.values())))
        rows = [(step, np.mean([scenes[sc][step] for sc in scenes], axis=0)) for step in common]
        means[family] = rows
        print(f"  mean over {', '.join(sorted(scenes))}:")
        for step, (p, s, lp, g, t) in rows:
            print(f"  {'mean':6s} {step:6d}: {p:.2f} / {s:.3f} / {lp:.3f}  {int(g):7d} G  {t:7.1f} s")
    if figure is None:
        return
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for family, rows in means.items():
        t = [r[1][4] for r in rows]
        for ax, k in zip(axes, (0, 2)):
            ax.plot(t, [r[1][k] for r in rows], marker="o", ms=3, label=LABELS.get(family, family))
            for step, r in rows:
                ax.annotate(f"{step // 1000}k", (r[4], r[k]), fontsize=6, xytext=(2, 2), textcoords="offset points")
    for ax, name in zip(axes, ("test PSNR (dB), mean", "test LPIPS, mean (lower is better)")):
        ax.set_xlabel("training seconds (runs sharing one GPU)")
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f"naka-gs presets on a GPU: LOM {', '.join(sorted(next(iter(found.values()))))}", fontsize=9)
    fig.tight_layout()
    fig.savefig(figure, dpi=110)
    print(f"\nwrote {figure}")


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]) if len(sys.argv) > 2 else None)
