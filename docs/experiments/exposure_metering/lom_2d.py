"""2D, LOM hold-out weights: the exposure exponent each metering rule picks from a scene's training views
(network + capture chroma, as the 3D run sees them) and the test views' PSNR / SSIM against the
normal-light photos with it. Needs /tmp/exp/X.pt (docs/experiments/capture_chroma/cache2d.py)."""

import kornia
import torch

from naka_gs_plugin.enhance.chroma import capture_chroma
from naka_gs_plugin.enhance.exposure import METERED_TARGET, MIDDLE_GREY, apply_gamma, lift_gamma, metered_level
from naka_gs_plugin.metrics import psnr

torch.set_grad_enabled(False)
RULES = {"mean 0.461 (before)": ("mean", MIDDLE_GREY), "luminance 0.505": ("luminance", METERED_TARGET), "none": None}
total = {k: [] for k in RULES}
for scene in ("bike", "chair", "shrub", "sofa"):
    d = torch.load(f"/tmp/exp/{scene}.pt")
    cap = {k: capture_chroma(v["net"].float(), v["low"].float()) for k, v in d.items()}
    train = [cap[k] for k, v in d.items() if v["split"] == "train"]
    test = [(cap[k], v["truth"].float()) for k, v in d.items() if v["split"] == "test"]
    truth_level = metered_level([t for _, t in test])
    for name, rule in RULES.items():
        g = 1.0 if rule is None else lift_gamma(train, rule[1], rule[0])
        p = s = 0.0
        for im, truth in test:
            out = apply_gamma([im], g)[0]
            p += psnr(out, truth)
            s += float(kornia.metrics.ssim(out.permute(2, 0, 1)[None], truth.permute(2, 0, 1)[None], 11).mean())
        p, s = p / len(test), s / len(test)
        total[name].append((p, s))
        lifted = apply_gamma(train, g)
        print(
            f"{scene:6s} {name:20s} g {g:.3f}  test {p:.2f} / {s:.3f}  train mean {sum(float(i.mean()) for i in lifted) / len(lifted):.3f}"
            f" metered {metered_level(lifted):.3f}  (truth test metered {truth_level:.3f})",
            flush=True,
        )
for name, rows in total.items():
    print(f"mean   {name:20s} {sum(p for p, _ in rows) / 4:.2f} / {sum(s for _, s in rows) / 4:.3f}")
