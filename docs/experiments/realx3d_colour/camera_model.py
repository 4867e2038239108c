"""Does the simulator's camera model make BlueHawaii's dark colour? Its references degraded, against its captures.

Issue 33 asks for training pairs at RealX3D's darkness from a camera model calibrated on the dark frames. Before
any training, this checks the model on the one scene with truth: each reference (normal light, same pose and
pixel grid as its dark capture) is brought to the dark exposure in linear light and passed through the
simulator's effects (:mod:`naka_gs_plugin.sim.effects`: Poisson-Gaussian noise, the sensor clip, the sRGB
response, 8-bit rounding, then JPEG with 4:2:0 chroma at the quality of the RealX3D files), and the simulated
dark frame's colour is compared with the real one's, level by level: JPEG chroma over luma (Cr / Y, Cb / Y) and
the mean linear chromaticity per bin of the capture's luma (codes), after a 3 px blur, as the enhancement's
capture chroma reads it.

Calibration, from the pairs themselves (every third view, full 1764x1172): the exposure ratio per channel, the
median of capture / reference in linear light where the blurred capture is between 4 and 40 codes; the noise
line per channel, ``var = shot * x + read**2`` in linear light, fitted to the pixel-scale variance of capture
minus ratio x reference (high-pass residuals, binned by the predicted level). The reference's own noise and
JPEG are in that residual too, so the fit is an upper bound of the dark frame's noise.

    .venv/bin/python docs/experiments/realx3d_colour/camera_model.py
"""

import io
from pathlib import Path

import cv2
import numpy as np
import torch
from PIL import Image

from naka_gs_plugin.data.images import read_stored
from naka_gs_plugin.sim.effects import add_noise, encode, sensor, srgb_to_linear
from naka_gs_plugin.sim.spec import Exposure, Noise, Quantize, Response

SCENE = Path("../shared/data/realx3d/BlueHawaii")
VIEWS = range(1, 31, 3)
QUALITY = 90  # the RealX3D files' quantisation tables (luma 2 1 1 2 2 4 5 6 ...) are libjpeg's quality 90
YCC = np.array([[0.299, 0.587, 0.114], [-0.168736, -0.331264, 0.5], [0.5, -0.418688, -0.081312]])
EDGES = np.array([0, 1.1, 2.6, 4, 6.8, 10.9, 16, 25, 40, 255])


def linear(codes):
    """8-bit sRGB codes ``[H, W, 3]`` as linear light (kornia's sRGB curve, in float64)."""
    return srgb_to_linear(torch.from_numpy(np.ascontiguousarray(codes / 255.0))).numpy()


def read(path):
    """An image as RGB codes in [0, 255], float64 (the project's reader)."""
    return read_stored(path).astype(np.float64)


def jpeg(codes):
    buffer = io.BytesIO()
    Image.fromarray(np.clip(np.round(codes), 0, 255).astype(np.uint8)).save(buffer, "JPEG", quality=QUALITY)
    return np.asarray(Image.open(buffer), dtype=np.float64)


def blur(x, sigma=3.0):
    return cv2.GaussianBlur(x.astype(np.float32), (0, 0), sigma).astype(np.float64)


def calibrate(pairs):
    """Per channel exposure ratio and noise line (linear light), from (capture codes, reference codes) pairs."""
    ratios, levels, variances = [], [], []
    for dark, ref in pairs:
        d, r = linear(dark), linear(ref)
        db, rb = blur(d, 2), blur(r, 2)
        y = blur(dark, 2).mean(2)
        m = (y >= 4) & (y <= 40)
        ratios.append(np.stack([db[..., c][m] / np.maximum(rb[..., c][m], 1e-6) for c in range(3)], 1))
    ratio = np.median(np.concatenate(ratios), 0)
    for dark, ref in pairs:
        predicted = linear(ref) * ratio
        residual = linear(dark) - predicted
        high = residual - blur(residual, 1.0)  # keeps most of the pixel noise, drops misregistration
        levels.append(blur(predicted, 1.0).reshape(-1, 3))
        variances.append((high**2).reshape(-1, 3))
    level, var = np.concatenate(levels), np.concatenate(variances)
    lines = []
    for c in range(3):
        edges = np.quantile(level[:, c], np.linspace(0.05, 0.95, 12))
        xs, vs = [], []
        for a, b in zip(edges[:-1], edges[1:]):
            m = (level[:, c] >= a) & (level[:, c] < b)
            xs.append(level[m, c].mean())
            vs.append(np.median(var[m, c]) / 0.5)  # a 1 px high-pass keeps about half of white noise's variance
        shot, read2 = np.polyfit(xs, vs, 1)
        lines.append((max(shot, 0.0), max(read2, 0.0) ** 0.5))
    return ratio, lines


def simulate(ref, ratio, line, seed):
    clean = torch.from_numpy(linear(ref) * ratio)
    generator = torch.Generator().manual_seed(seed)
    noisy = torch.stack(
        [
            add_noise(clean[..., c : c + 1], Noise(shot_gain=s, read_std=r), generator)[..., 0]
            for c, (s, r) in enumerate(line)
        ],
        -1,
    )
    codes = encode(sensor(noisy, [Exposure(1.0)]), [Response("srgb"), Quantize()]).numpy() * 255
    return jpeg(codes)


def colour_by_level(images):
    """Per luma bin of the 3 px blurred image: Cr / Y, Cb / Y and the mean linear r, g, b fractions."""
    ycc, lin = [], []
    for codes in images:
        b = blur(codes)
        ycc.append(b.reshape(-1, 3) @ YCC.T)
        lin.append(blur(linear(codes)).reshape(-1, 3))
    ycc, lin = np.concatenate(ycc), np.concatenate(lin)
    rows = []
    for a, b in zip(EDGES[:-1], EDGES[1:]):
        m = (ycc[:, 0] >= a) & (ycc[:, 0] < b)
        if m.sum() < 100:
            rows.append(None)
            continue
        y = ycc[m, 0].mean()
        frac = lin[m].sum(0) / lin[m].sum()
        rows.append((m.mean(), ycc[m, 2].mean() / y, ycc[m, 1].mean() / y, frac))
    return rows


def main():
    pairs = [(read(SCENE / f"train/{i:04d}.JPG"), read(SCENE / f"reference/{i:04d}.JPG")) for i in VIEWS]
    ratio, lines = calibrate(pairs)
    print("exposure ratio r / g / b (capture over reference, linear):", " / ".join(f"1/{1 / k:.0f}" for k in ratio))
    for name, (shot, read_std) in zip("rgb", lines):
        print(f"noise {name}: shot {shot:.2e}, read {read_std:.2e} (linear; {read_std * 12.92 * 255:.2f} codes)")
    sets = {
        "capture (real)": [dark for dark, _ in pairs],
        "reference at the ratio, no noise": [
            np.round(encode(torch.from_numpy(linear(ref) * ratio), [Response("srgb")]).numpy() * 255)
            for _, ref in pairs
        ],
        "simulated (noise, clip, sRGB, 8 bit, JPEG)": [
            simulate(ref, ratio, lines, i) for i, (_, ref) in enumerate(pairs)
        ],
    }
    print("luma bins (codes):", " ".join(f"{a:g}-{b:g}" for a, b in zip(EDGES[:-1], EDGES[1:])))
    for name, images in sets.items():
        rows = colour_by_level(images)
        print(name)
        print("  pixels %  " + " ".join("    -" if r is None else f"{100 * r[0]:5.1f}" for r in rows))
        print("  Cr / Y    " + " ".join("    -" if r is None else f"{r[1]:5.2f}" for r in rows))
        print("  Cb / Y    " + " ".join("    -" if r is None else f"{r[2]:5.2f}" for r in rows))
        for c, channel in enumerate("rgb"):
            print(f"  {channel} frac    " + " ".join("    -" if r is None else f"{r[3][c]:5.3f}" for r in rows))


if __name__ == "__main__":
    main()
