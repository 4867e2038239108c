"""Loss and training-PSNR curves of the CUDA-vs-CPU comparison (docs/cuda.md), from two nerfstudio runs'
tensorboard event files: a table every 500 steps and docs/img/cuda_vs_cpu_curves.png.

    .venv/bin/python docs/experiments/cuda/curves.py GPU_RUN_DIR CPU_RUN_DIR
(each the folder holding events.out.tfevents.*: <bench out>/runs/sofa/naka-gs/naka-gs)
"""

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator  # noqa: E402

TAGS = {"loss": "Train Loss", "train PSNR": "Train Metrics Dict/psnr", "Gaussians": "Train Metrics Dict/gaussian_count"}


def curves(run: Path) -> dict:
    acc = EventAccumulator(str(next(Path(run).glob("events.out.tfevents.*"))), size_guidance={"scalars": 0})
    acc.Reload()
    return {k: {e.step: e.value for e in acc.Scalars(tag)} for k, tag in TAGS.items()}


def window_mean(series: dict, step: int, half: int = 50) -> float:
    """Mean over steps [step - half, step + half]: single logged steps are one image's loss."""
    return float(np.mean([v for s, v in series.items() if abs(s - step) <= half]))


gpu, cpu = curves(Path(sys.argv[1])), curves(Path(sys.argv[2]))
print("| step | loss GPU / CPU | train PSNR GPU / CPU | Gaussians GPU / CPU |")
print("|---:|---:|---:|---:|")
for step in range(500, 7001, 500):
    cells = [f"{window_mean(gpu[k], step):.4g} / {window_mean(cpu[k], step):.4g}" for k in TAGS]
    print(f"| {step} | " + " | ".join(cells) + " |")

fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
for ax, key in zip(axes, TAGS):
    for name, data in (("GPU (gsplat)", gpu), ("CPU (cpu-fast)", cpu)):
        steps = np.array(sorted(data[key]))
        values = np.array([data[key][s] for s in steps])
        if key != "Gaussians":  # 100-step running mean: one logged step is one image
            values = np.convolve(values, np.ones(10) / 10, mode="same")
        ax.plot(steps, values, label=name)
    ax.set_xlabel("step")
    ax.set_title(key)
axes[0].legend()
fig.tight_layout()
out = Path(__file__).resolve().parents[2] / "img" / "cuda_vs_cpu_curves.png"
fig.savefig(out, dpi=90)
print(f"wrote {out}")
