"""Where BlueHawaii's colour cast comes from: its dark captures against their normal-light references.

Every second training view, both images area-downscaled to 220x146 (sRGB JPEG codes, decoded to linear light
by the sRGB curve). Prints (1) the mean linear chromaticity of both, binned by the reference's luminance;
(2) the dark frame's JPEG chroma (Cb, Cr, in 8-bit codes) against the reference's as the dark exposure would
record it through the sRGB curve (reference linear / k, k the ratio of mean linear luminance), binned by the
dark frame's luma Y; (3) the scene's chromaticity error of capture chroma when the rectification of clipped
read noise (E[max(mu + n, 0)], n ~ N(0, sigma^2) codes) is undone per channel before decoding.

    .venv/bin/python docs/experiments/realx3d_colour/capture_vs_reference.py
"""

from pathlib import Path

import cv2
import numpy as np
from scipy.stats import norm

SCENE = Path("../shared/data/realx3d/BlueHawaii")
SIZE = (220, 146)
YCC = np.array([[0.299, 0.587, 0.114], [-0.168736, -0.331264, 0.5], [0.5, -0.418688, -0.081312]])


def linear(x):
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def encode(x):
    x = np.clip(x, 0, 1)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def load(blur=0.0):
    dark, ref = [], []
    for i in range(1, 31, 2):
        d = cv2.imread(str(SCENE / f"train/{i:04d}.JPG"))[:, :, ::-1].astype(np.float32)
        r = cv2.imread(str(SCENE / f"reference/{i:04d}.JPG"))[:, :, ::-1].astype(np.float32) / 255
        if blur:
            d = cv2.GaussianBlur(d, (0, 0), blur)
        dark.append(cv2.resize(d, SIZE, interpolation=cv2.INTER_AREA).reshape(-1, 3))
        ref.append(cv2.resize(r, SIZE, interpolation=cv2.INTER_AREA).reshape(-1, 3))
    return np.concatenate(dark), np.concatenate(ref)  # dark in codes [0, 255], reference sRGB [0, 1]


def chromaticity(x):
    return x.sum(0) / x.sum()


def by_reference_level(dark, ref):
    d, r = linear(dark / 255), linear(ref)
    y = r.mean(1)
    print("(1) mean linear chromaticity r/g/b, binned by the reference's linear luminance")
    edges = np.quantile(y, [0, 0.2, 0.4, 0.6, 0.8, 0.9, 0.97, 1])
    for a, b in zip(edges[:-1], edges[1:]):
        m = (y >= a) & (y <= b)
        cr, cd = chromaticity(r[m]), chromaticity(d[m])
        print(
            f"  {a:.3f}-{b:.3f}: reference {np.round(cr, 3)}  dark {np.round(cd, 3)}  dark/reference {np.round(cd / cr, 2)}"
        )


def jpeg_chroma(dark, ref):
    k = linear(ref).mean() / linear(dark / 255).mean()
    predicted = encode(linear(ref) / k) * 255  # the reference at the dark exposure, sRGB curve
    yd, yp = (dark @ YCC.T), (predicted @ YCC.T)
    print(f"(2) JPEG chroma of the dark frame against the reference at 1/{k:.0f}, binned by the dark frame's Y (codes)")
    edges = np.quantile(yd[:, 0], [0, 0.2, 0.4, 0.6, 0.8, 0.95, 1])
    for a, b in zip(edges[:-1], edges[1:]):
        m = (yd[:, 0] >= a) & (yd[:, 0] <= b)
        cb, cr = yd[m, 1].mean() / yp[m, 1].mean(), yd[m, 2].mean() / yp[m, 2].mean()
        print(f"  Y {a:5.1f}-{b:5.1f}: mean Cb dark/predicted {cb:.2f}, mean Cr dark/predicted {cr:.2f}")


def rectification(dark, ref):
    r = linear(ref)
    truth = chromaticity(r)

    def scene_error(d):
        chroma = (d + 1e-6) / (d.mean(1, keepdims=True) + 1e-6)
        err = chromaticity(r.mean(1, keepdims=True) * chroma) - truth
        return f"L1 {np.abs(err).sum():.3f} (r {err[0]:+.3f}, g {err[1]:+.3f}, b {err[2]:+.3f})"

    print("(3) capture chroma's scene chromaticity error (reference brightness, capture blurred 3 px)")
    print(f"  sRGB decode (as now): {scene_error(linear(dark / 255))}")
    for sigma in (0.5, 1, 2, 3, 4):
        mu = np.linspace(-6 * sigma, 60, 4000)
        rectified = mu * norm.cdf(mu / sigma) + sigma * norm.pdf(mu / sigma)
        undone = np.clip(np.interp(dark, rectified, mu), 0, None)
        print(f"  rectification undone, sigma {sigma} codes: {scene_error(linear(undone / 255))}")


if __name__ == "__main__":
    by_reference_level(*load())
    jpeg_chroma(*load())
    rectification(*load(blur=3.0))
