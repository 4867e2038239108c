"""How much of BlueHawaii's 3D error one scene-wide colour or tone correction would remove (diagnosis only).

Reads the truth | render pairs ``ns-eval --render-output-path`` writes (``eval_img_*.png``, truth left) and
fits, on all test views together, one correction of the renders per scene: a gain per channel in linear
light (exposure and white balance), the same with the luminance kept (white balance alone), a gain and
offset per channel on the sRGB values (adds a black level and contrast), and a 3x4 colour matrix on the sRGB
values. Each is a ceiling (fitted to the truth), never a method. From the repository root:

    .venv/bin/ns-eval --load-config outputs/bench/bluehawaii/runs/BlueHawaii/naka-gs/naka-gs/config.yml \\
        --output-path outputs/bench/bluehawaii/eval.json --render-output-path outputs/bench/bluehawaii/renders
    .venv/bin/python docs/experiments/realx3d_colour/tone_oracle_3d.py outputs/bench/bluehawaii/renders
"""

import sys
from pathlib import Path

import kornia
import numpy as np
import torch
from PIL import Image

LUMA = np.array([0.2126, 0.7152, 0.0722])


def _channelwise(fn, x):
    """Apply a kornia colour transform (channels first) to a channel-last NumPy array of any shape."""
    flat = torch.from_numpy(np.ascontiguousarray(x.reshape(-1, 3).T))[:, :, None]
    return fn(flat)[:, :, 0].T.numpy().reshape(x.shape)


def linear(x):
    """sRGB -> linear light (kornia's transfer function)."""
    return _channelwise(kornia.color.rgb_to_linear_rgb, x)


def encode(x):
    """Linear light -> sRGB, clipped to [0, 1]."""
    return _channelwise(kornia.color.linear_rgb_to_rgb, np.clip(x, 0, 1))


def psnr(a, b):
    return float(-10 * np.log10(((np.clip(a, 0, 1) - b) ** 2).mean()))


def main(folder: Path) -> None:
    truths, renders = [], []
    for path in sorted(folder.glob("eval_img_*.png")):
        pair = np.asarray(Image.open(path).convert("RGB"), dtype=np.float64) / 255
        half = pair.shape[1] // 2
        truths.append(pair[:, :half])
        renders.append(pair[:, half:])
    t = np.concatenate([x.reshape(-1, 3) for x in truths])
    r = np.concatenate([x.reshape(-1, 3) for x in renders])

    def mean_psnr(correct):
        return np.mean([psnr(correct(x), y) for x, y in zip(renders, truths)])

    gains = (linear(r) * linear(t)).sum(0) / (linear(r) ** 2).sum(0)
    balance = gains / (gains @ LUMA)
    affine = [np.linalg.lstsq(np.stack([r[:, c], np.ones(len(r))], 1), t[:, c], rcond=None)[0] for c in range(3)]
    matrix = np.linalg.lstsq(np.concatenate([r, np.ones((len(r), 1))], 1), t, rcond=None)[0]
    print(f"{len(renders)} test views")
    print(f"as rendered: {mean_psnr(lambda x: x):.2f} dB")
    print(
        f"linear gain per channel {np.round(gains, 3).tolist()}: {mean_psnr(lambda x: encode(linear(x) * gains)):.2f} dB"
    )
    print(
        f"white balance alone {np.round(balance, 3).tolist()}: {mean_psnr(lambda x: encode(linear(x) * balance)):.2f} dB"
    )
    print(
        f"sRGB gain + offset per channel {np.round(affine, 3).tolist()}: "
        f"{mean_psnr(lambda x: np.stack([x[..., c] * affine[c][0] + affine[c][1] for c in range(3)], -1)):.2f} dB"
    )
    print(
        f"sRGB 3x4 colour matrix: {mean_psnr(lambda x: np.concatenate([x, np.ones(x.shape[:2] + (1,))], -1) @ matrix):.2f} dB"
    )
    for name, images in (("truth", truths), ("render", renders)):
        lum = np.concatenate([(linear(x) @ LUMA).ravel() for x in images])
        print(
            f"{name}: linear luminance percentiles 1 / 5 / 50 / 95: {np.round(np.percentile(lum, [1, 5, 50, 95]), 4).tolist()}, mean {lum.mean():.4f}"
        )


if __name__ == "__main__":
    main(Path(sys.argv[1]))
