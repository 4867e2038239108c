"""LOL v1 normal-light photos: sRGB mean vs metered level (sRGB of the mean linear luminance), per image,
summarised; the photos' exposure is what the metering target should reproduce."""

from pathlib import Path

import numpy as np

from naka_gs_plugin.data.images import read_rgb

D = Path(__file__).resolve().parents[4] / "shared" / "data" / "lol"
W = np.array([0.2126, 0.7152, 0.0722], np.float32)


def lin(x):
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def enc(v):
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(v, 1 / 2.4) - 0.055)


s, m = [], []
for p in sorted(D.glob("*/high/*.jpg")):
    x = read_rgb(p)[::2, ::2]
    s.append(float(x.mean()))
    m.append(float(enc((lin(x) @ W).mean())))
s, m = np.array(s), np.array(m)
for name, v in (("sRGB mean", s), ("metered", m)):
    q = np.percentile(v, [10, 25, 50, 75, 90])
    print(f"LOL high ({len(v)}): {name}: mean {v.mean():.3f} sd {v.std():.3f} pct10/25/50/75/90 " + " ".join(f"{a:.3f}" for a in q))
