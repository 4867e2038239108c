"""Parity of our rasterizers with gsplat 1.4.0's CUDA ``rasterization``, and GPU timings.

``parity`` renders the same float32 Gaussians with a reference and with our ``torch``
(:mod:`naka_gs_plugin.model.rasterize`) and ``cpu-fast`` (:mod:`~naka_gs_plugin.model.rasterize_cpu_fast`)
paths, called as ``NakaGSModel.get_outputs`` calls them (unpacked, pinhole, near 0.01, far 1e10,
``absgrad``), and reports max / mean absolute differences of the image, alpha, accumulated depth
(``RGB+D``'s last channel: gsplat's expected depth is this divided by alpha), radii, the gradients
of every input (means, quats, scales, opacities, colours; viewmats in a second pass, since a
viewmats gradient sends cpu-fast to the torch projection), ``means2d``'s gradient and ``absgrad``,
under the loss ``sum(w_c * render) + sum(w_a * alpha)`` with fixed random weights. The reference is
gsplat's CUDA ``rasterization`` when CUDA is present, else our torch path itself (stand-in: then only
cpu-fast is compared). ``--save-reference`` writes the inputs and the reference's outputs, and
``--reference-file`` compares against such a file instead of rendering the reference, so cpu-fast
(numba, CPU only) can be checked on a CPU against results gsplat produced on a GPU.

Every synthetic scene is also run with its opacities capped at :data:`EXACT_PAIRS_OPACITY`: gsplat
evaluates every Gaussian of a 16x16 tile, we only the pixels of its ``mean +- radius`` box, and
outside that box ``alpha <= 0.0111 * opacity``, below 1/255 for those opacities. So in the capped
variants both composite exactly the same pairs and any difference beyond float32 rounding is a bug.

``timing`` measures forward and forward+backward at the CPU benchmark's sizes
(:mod:`benchmarks.rasterizer`, same scenes and loss) and divides the 2-core CPU's
figures (a ``python -m benchmarks.rasterizer --out-json`` file) by them.

Imports only torch, numpy, jaxtyping, tyro and rich (and gsplat / numba when used): runs on a GPU
machine without nerfstudio.

Run from the repository root: ``python -m benchmarks.cuda_parity --help``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import platform
import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, Literal, Optional, Sequence, Tuple

import torch
import tyro
from jaxtyping import Float
from torch import Tensor

from benchmarks.rasterizer import make_scene as bench_scene
from benchmarks.rasterizer import sync, time_fwd_bwd

F64 = torch.float64
EXACT_PAIRS_OPACITY = 0.35
"""Below 1 / (255 * exp(-4.5)) = 0.353 no pair outside a Gaussian's radius box reaches alpha 1/255."""
GRAD_INPUTS = ("means", "quats", "scales", "opacities", "colors")
FORWARD_QUANTITIES = ("image", "alpha", "depth", "radii")
TOLERANCE = {"forward": 2e-4, "gradient": 1e-3}
"""Float32 noise bounds on ``max |ours - ref| / max |ref|``. Forward: a last-bit difference in a
conic can move one pair across the 1e-4 transmittance stop, changing that pixel by up to 1e-4 times
its colour (seen between torch and cpu-fast on a trained scene). Gradients: summed over pixels in
another order (gsplat with float32 atomics and ``--use_fast_math``)."""
REPO = Path(__file__).resolve().parents[1]

Scene = Dict[str, object]
"""rasterization's keyword inputs: means [N,3], quats [N,4] (wxyz), scales [N,3] (exp'ed),
opacities [N] (sigmoid'ed), colors ([N,K,3] SH or [N,3]), viewmats [C,4,4] (OpenCV world-to-camera),
Ks [C,3,3] (px), width, height, sh_degree (None: colours are used as they are)."""


def make_scene(
    n: int,
    width: int,
    height: int,
    n_cams: int = 1,
    sh_degree: Optional[int] = None,
    seed: int = 0,
    dtype: torch.dtype = F64,
    scale: float = 0.04,
) -> Scene:
    """Random Gaussians at depths 2..6 in front of ``n_cams`` nearby cameras (the first at the
    origin, the others shifted by ~0.1), focal 0.8 * width px; ``scale`` is the median axis length."""
    gen = torch.Generator().manual_seed(seed)
    focal = 0.8 * width
    z = 2.0 + 4.0 * torch.rand(n, generator=gen, dtype=dtype)
    x = (torch.rand(n, generator=gen, dtype=dtype) - 0.5) * 1.2 * width / focal * z
    y = (torch.rand(n, generator=gen, dtype=dtype) - 0.5) * 1.2 * height / focal * z
    if sh_degree is None:
        colors = torch.rand(n, 3, generator=gen, dtype=dtype)
    else:
        colors = 0.4 * torch.randn(n, (sh_degree + 1) ** 2, 3, generator=gen, dtype=dtype)
    viewmats = torch.eye(4, dtype=dtype).repeat(n_cams, 1, 1)
    viewmats[1:, :3, 3] = 0.1 * torch.randn(n_cams - 1, 3, generator=gen, dtype=dtype)
    k = torch.tensor([[focal, 0, 0.5 * width], [0, focal, 0.5 * height], [0, 0, 1]], dtype=dtype)
    return dict(
        means=torch.stack([x, y, z], dim=1),
        quats=torch.randn(n, 4, generator=gen, dtype=dtype),
        scales=scale * torch.exp(0.5 * torch.randn(n, 3, generator=gen, dtype=dtype)),
        opacities=torch.sigmoid(2.0 * torch.randn(n, generator=gen, dtype=dtype)),
        colors=colors,
        viewmats=viewmats,
        Ks=k.repeat(n_cams, 1, 1),
        width=width,
        height=height,
        sh_degree=sh_degree,
    )


@dataclasses.dataclass(frozen=True)
class SyntheticCase:
    """A :func:`make_scene` scene (the scenes of ``tests/model/test_rasterize.py``) and its rasterize mode."""

    scene_kwargs: Dict[str, object]
    rasterize_mode: Literal["classic", "antialiased"] = "classic"


SYNTHETIC = {
    "rgb-2cam": SyntheticCase(dict(n=150, width=40, height=30, n_cams=2, scale=0.08)),
    "sh1": SyntheticCase(dict(n=120, width=36, height=28, sh_degree=1, seed=1, scale=0.08)),
    "sh3": SyntheticCase(dict(n=300, width=48, height=36, sh_degree=3, scale=0.08)),
    "sh2-2cam-aa": SyntheticCase(dict(n=120, width=32, height=24, n_cams=2, sh_degree=2, scale=0.08), "antialiased"),
}


def look_at(eye: Float[Tensor, "3"], target: Float[Tensor, "3"]) -> Float[Tensor, "4 4"]:
    """OpenCV world-to-camera matrix of a camera at ``eye`` looking at ``target`` (+z forward,
    +y down, world +z up unless the view is vertical)."""
    forward = torch.nn.functional.normalize(target - eye, dim=0)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=eye.dtype)
    if abs(float(forward @ up)) > 0.99:
        up = torch.tensor([0.0, 1.0, 0.0], dtype=eye.dtype)
    right = torch.nn.functional.normalize(torch.linalg.cross(forward, -up), dim=0)
    down = torch.linalg.cross(forward, right)
    rot = torch.stack([right, down, forward])
    viewmat = torch.eye(4, dtype=eye.dtype)
    viewmat[:3, :3] = rot
    viewmat[:3, 3] = -rot @ eye
    return viewmat


def scene_from_checkpoint(
    path: Path,
    width: int,
    height: int,
    n_cams: int = 2,
    max_gaussians: Optional[int] = None,
    seed: int = 0,
) -> Scene:
    """The Gaussians of a nerfstudio checkpoint (``pipeline`` state dict, ``_model.gauss_params.*``,
    activated as splatfacto does), seen by ``n_cams`` 60-degree cameras on a ring at 30 degrees
    elevation around their median, 2.5x their 90th-percentile distance from it away (checkpoints
    hold no cameras). ``max_gaussians`` keeps a seeded random subset."""
    import naka_gs_plugin  # noqa: F401  (registers numpy's scalars for torch.load's weights_only)

    state = torch.load(path, map_location="cpu")["pipeline"]
    params = {k.rsplit(".", 1)[1]: v.float() for k, v in state.items() if k.startswith("_model.gauss_params.")}
    n = params["means"].shape[0]
    keep = torch.arange(n)
    if max_gaussians is not None and max_gaussians < n:
        keep = torch.randperm(n, generator=torch.Generator().manual_seed(seed))[:max_gaussians].sort().values
    params = {k: v[keep] for k, v in params.items()}
    rest = params["features_rest"]
    if rest.shape[1] == 0:  # sh_degree 0 in the config: colours are logits, as in get_outputs
        colors, sh_degree = torch.sigmoid(params["features_dc"]), None
    else:
        colors = torch.cat([params["features_dc"][:, None, :], rest], dim=1)
        sh_degree = int(round(math.sqrt(colors.shape[1]))) - 1
    means = params["means"]
    centre = means.median(dim=0).values
    radius = 2.5 * float(torch.quantile((means - centre).norm(dim=1), 0.9))
    focal = 0.5 * width / math.tan(math.radians(30.0))
    k = torch.tensor([[focal, 0, 0.5 * width], [0, focal, 0.5 * height], [0, 0, 1]])
    viewmats = []
    for i in range(n_cams):
        azimuth = 2 * math.pi * i / n_cams
        offset = torch.tensor([math.cos(azimuth), math.sin(azimuth), math.tan(math.radians(30.0))])
        viewmats.append(look_at(centre + radius * offset / offset.norm(), centre))
    return dict(
        means=means,
        quats=params["quats"],
        scales=torch.exp(params["scales"]),
        opacities=torch.sigmoid(params["opacities"]).squeeze(-1),
        colors=colors,
        viewmats=torch.stack(viewmats),
        Ks=k.repeat(n_cams, 1, 1),
        width=width,
        height=height,
        sh_degree=sh_degree,
    )


def cap_opacities(scene: Scene, cap: float = EXACT_PAIRS_OPACITY) -> Scene:
    """The scene with opacities scaled into ``(0, cap]`` (see :data:`EXACT_PAIRS_OPACITY`)."""
    return {**scene, "opacities": scene["opacities"] * cap}


# ---------------------------------------------------------------------------------------- renderers
Renderer = Callable[..., Tuple[Tensor, Tensor, Dict]]


def gsplat_renderer() -> Renderer:
    """gsplat's ``rasterization`` as ``NakaGSModel`` calls it (unpacked, dense gradients)."""
    from gsplat.rendering import rasterization

    def render(**kwargs):
        return rasterization(packed=False, sparse_grad=False, **kwargs)

    return render


def torch_renderer() -> Renderer:
    from naka_gs_plugin.model.rasterize import rasterization

    return rasterization


def cpu_fast_renderer() -> Renderer:
    """Needs numba; the module also imports nerfstudio (for its console), so it is unavailable on a
    GPU machine without them (compare there through ``--save-reference``)."""
    from naka_gs_plugin.model.rasterize_cpu_fast import rasterization

    return rasterization


def loss_weights(scene: Scene, seed: int) -> Tuple[Float[Tensor, "C H W 4"], Float[Tensor, "C H W 1"]]:
    """Fixed random weights of the loss on the ``RGB+D`` render and on alpha."""
    gen = torch.Generator().manual_seed(seed)
    n_cams = scene["viewmats"].shape[0]
    shape = (n_cams, scene["height"], scene["width"])
    return torch.randn(*shape, 4, generator=gen), torch.randn(*shape, 1, generator=gen)


def render_and_backprop(
    render: Renderer,
    scene: Scene,
    device: str,
    rasterize_mode: str,
    weights: Tuple[Tensor, Tensor],
    grad_inputs: Tuple[str, ...],
) -> Dict[str, Tensor]:
    """One float32 forward (``RGB+D``, ``absgrad``) and backward on ``device``; returns the forward
    outputs and the gradients of ``grad_inputs`` (as ``"d <name>"``), ``d means2d`` and ``absgrad``,
    all on the CPU."""
    # copy=True: fresh leaves every call, so no gradient accumulates into (or aliases) the scene's tensors.
    leaves = {
        k: v.detach().to(device=device, dtype=torch.float32, copy=True) for k, v in scene.items() if torch.is_tensor(v)
    }
    for name in grad_inputs:
        leaves[name].requires_grad_()
    colors, alphas, meta = render(
        **leaves,
        width=scene["width"],
        height=scene["height"],
        sh_degree=scene["sh_degree"],
        near_plane=0.01,
        far_plane=1e10,
        render_mode="RGB+D",
        rasterize_mode=rasterize_mode,
        absgrad=True,
    )
    meta["means2d"].retain_grad()
    w_render, w_alpha = (w.to(device) for w in weights)
    ((colors * w_render).sum() + (alphas * w_alpha).sum()).backward()
    out = {
        "image": colors[..., :3],
        "alpha": alphas,
        "depth": colors[..., 3:],
        "radii": meta["radii"],
        "d means2d": meta["means2d"].grad,
        "absgrad": meta["means2d"].absgrad,
    }
    out.update({f"d {name}": leaves[name].grad for name in grad_inputs})
    return {k: v.detach().cpu() for k, v in out.items()}


def render_all(render: Renderer, scene: Scene, device: str, rasterize_mode: str, seed: int) -> Dict[str, Tensor]:
    """Every compared quantity: the outputs and Gaussian gradients, then the viewmats gradient from
    a second pass (kept apart so that cpu-fast's compiled projection is what the first pass tests)."""
    weights = loss_weights(scene, seed)
    out = render_and_backprop(render, scene, device, rasterize_mode, weights, GRAD_INPUTS)
    out["d viewmats"] = render_and_backprop(render, scene, device, rasterize_mode, weights, ("viewmats",))["d viewmats"]
    return out


def compare(ref: Tensor, ours: Tensor) -> Dict[str, float]:
    """max / mean |ours - ref| (float64), max |ref|, their ratio, and the number of differing entries."""
    if ref.shape != ours.shape:
        raise ValueError(f"shape mismatch: reference {tuple(ref.shape)}, ours {tuple(ours.shape)}")
    diff = (ours.double() - ref.double()).abs()
    ref_max = float(ref.double().abs().max()) if ref.numel() else 0.0
    max_abs = float(diff.max()) if diff.numel() else 0.0
    return {
        "max_abs": max_abs,
        "mean_abs": float(diff.mean()) if diff.numel() else 0.0,
        "ref_max_abs": ref_max,
        "rel": max_abs / ref_max if ref_max > 0 else max_abs,
        "n_differ": int((diff > 0).sum()),
    }


def within_noise(quantity: str, stats: Dict[str, float]) -> bool:
    """Radii must be equal; the rest within :data:`TOLERANCE` relative to the reference's max."""
    if quantity == "radii":
        return stats["n_differ"] == 0
    kind = "forward" if quantity in FORWARD_QUANTITIES else "gradient"
    return stats["rel"] <= TOLERANCE[kind]


# ------------------------------------------------------------------------------------------ parity
@dataclasses.dataclass
class ParityConfig:
    """Our rasterizers against gsplat's CUDA rasterization (or the torch path as a stand-in)."""

    mode: Literal["parity", "timing"] = "parity"
    """parity: the difference tables; timing: GPU forward(+backward) seconds and ratios to the CPU."""
    reference: Literal["auto", "gsplat", "torch"] = "auto"
    """auto: gsplat when CUDA is available, else our torch path (stand-in)."""
    scenes: Tuple[str, ...] = tuple(SYNTHETIC)
    """Synthetic scenes to run (each also with opacities capped at 0.35, suffix "/o<=0.35")."""
    checkpoint: Optional[Path] = None
    """Also compare on the Gaussians of this nerfstudio .ckpt (seen from synthetic ring cameras)."""
    checkpoint_size: str = "320x240"
    """Image size (WIDTHxHEIGHT) of the checkpoint's cameras."""
    checkpoint_cameras: int = 2
    max_gaussians: Optional[int] = None
    """Random subset of the checkpoint's Gaussians (seeded), to keep the CPU side quick."""
    torch_device: str = "cpu"
    """Device of our torch path (the model runs it on the CPU; cuda tests it there too)."""
    seed: int = 0
    """Seed of the loss weights and of the checkpoint subset."""
    save_reference: Optional[Path] = None
    """Write the scenes and the reference's outputs here (torch.save) for --reference-file."""
    reference_file: Optional[Path] = None
    """Compare against a --save-reference file instead of rendering the reference (its scenes)."""
    out_dir: Optional[Path] = None
    """Write parity.md / parity.json (or timing.md / timing.json) here."""
    timing_sizes: Tuple[int, ...] = (10_000, 50_000, 100_000, 300_000)
    """timing: numbers of Gaussians (the CPU benchmark's)."""
    timing_resolutions: Tuple[str, ...] = ("220x146", "441x293", "882x586")
    """timing: image sizes (the CPU benchmark's)."""
    timing_methods: Tuple[str, ...] = ("gsplat", "torch-cuda")
    """timing: any of gsplat, torch-cuda (our torch path on the GPU), torch, cpu-fast (this machine's CPU)."""
    timing_correction: Tuple[str, ...] = ("882x586", "1764x1172")
    """timing: image sizes of the correction network's per-image timing (``exact`` on CUDA); () skips it."""
    timing_repeats: int = 5
    """timing: timed repetitions after one warm-up; the median is reported."""
    cpu_baseline: Path = REPO / "scripts" / "gpu" / "cpu_baseline.json"
    """timing: ``python -m benchmarks.rasterizer --out-json`` results of the 2-core CPU (ratios are CPU / GPU)."""

    def resolved_reference(self) -> str:
        if self.reference == "auto":
            return "gsplat" if torch.cuda.is_available() else "torch"
        if self.reference == "gsplat" and not torch.cuda.is_available():
            raise ValueError("reference gsplat needs CUDA (torch.cuda.is_available() is False)")
        return self.reference

    def cases(self) -> Dict[str, Tuple[Scene, str]]:
        """name -> (scene, rasterize mode), from the options."""
        unknown = [s for s in self.scenes if s not in SYNTHETIC]
        if unknown:
            raise ValueError(f"unknown scenes {unknown}; choose from {sorted(SYNTHETIC)}")
        cases = {}
        for name in self.scenes:
            case = SYNTHETIC[name]
            scene = make_scene(**case.scene_kwargs)
            cases[name] = (scene, case.rasterize_mode)
            cases[f"{name}/o<={EXACT_PAIRS_OPACITY}"] = (cap_opacities(scene), case.rasterize_mode)
        if self.checkpoint is not None:
            width, height = parse_size(self.checkpoint_size)
            scene = scene_from_checkpoint(
                self.checkpoint, width, height, self.checkpoint_cameras, self.max_gaussians, self.seed
            )
            cases[f"ckpt:{self.checkpoint.name}"] = (scene, "classic")
        return cases


def parse_size(text: str) -> Tuple[int, int]:
    """``"WIDTHxHEIGHT"`` -> (width, height)."""
    width, height = (int(v) for v in text.lower().split("x"))
    return width, height


def available_ours(reference: str, torch_device: str) -> Tuple[Dict[str, Tuple[Renderer, str]], Dict[str, str]]:
    """Our rasterizers to compare (name -> (renderer, device)) and the unavailable ones with why.
    With the torch path as the reference only cpu-fast is compared (torch vs itself is 0)."""
    ours: Dict[str, Tuple[Renderer, str]] = {}
    missing: Dict[str, str] = {}
    if reference != "torch":
        ours["torch"] = (torch_renderer(), torch_device)
    try:
        ours["cpu-fast"] = (cpu_fast_renderer(), "cpu")
    except ImportError as err:  # no numba (or nerfstudio) on this machine: report, compare the rest
        missing["cpu-fast"] = f"{type(err).__name__}: {err}"
    return ours, missing


def versions() -> Dict[str, str]:
    info = {"python": platform.python_version(), "torch": str(torch.__version__), "machine": platform.machine()}
    try:
        import gsplat

        info["gsplat"] = str(gsplat.__version__)
    except ImportError:
        info["gsplat"] = "not installed"
    if torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(0)
        info["cuda"] = str(torch.version.cuda)
    from benchmarks.machine import cpu_model

    info["cpu"] = cpu_model()
    return info


def run_parity(cfg: ParityConfig) -> Dict:
    """Render every case with the reference and ours; returns the comparison (see :func:`parity_table`)."""
    if cfg.reference_file is not None:
        saved = torch.load(cfg.reference_file, map_location="cpu")
        reference = saved["reference"]
        cases = {name: (c["scene"], c["rasterize_mode"]) for name, c in saved["cases"].items()}
        ref_outputs = {name: c["outputs"] for name, c in saved["cases"].items()}
        seed, ref_versions = saved["seed"], saved["versions"]
    else:
        reference = cfg.resolved_reference()
        render = gsplat_renderer() if reference == "gsplat" else torch_renderer()
        device = "cuda" if reference == "gsplat" else cfg.torch_device
        cases = cfg.cases()
        seed, ref_versions = cfg.seed, versions()
        ref_outputs = {name: render_all(render, scene, device, mode, seed) for name, (scene, mode) in cases.items()}
    if cfg.save_reference is not None:
        cfg.save_reference.parent.mkdir(parents=True, exist_ok=True)
        torch.save(
            {
                "reference": reference,
                "seed": seed,
                "versions": ref_versions,
                "cases": {
                    name: {"scene": scene, "rasterize_mode": mode, "outputs": ref_outputs[name]}
                    for name, (scene, mode) in cases.items()
                },
            },
            cfg.save_reference,
        )
    ours, missing = available_ours(reference, cfg.torch_device)
    results: Dict[str, Dict] = {}
    for name, (scene, mode) in cases.items():
        n_cams = scene["viewmats"].shape[0]
        results[name] = {
            "gaussians": scene["means"].shape[0],
            "image": f"{n_cams}x{scene['width']}x{scene['height']}",
            "sh_degree": scene["sh_degree"],
            "rasterize_mode": mode,
            "compared": {},
        }
        for label, (render, device) in ours.items():
            out = render_all(render, scene, device, mode, seed)
            results[name]["compared"][label] = {q: compare(ref_outputs[name][q], out[q]) for q in out}
    return {
        "reference": reference,
        "reference_file": str(cfg.reference_file) if cfg.reference_file else None,
        "tolerance": TOLERANCE,
        "unavailable": missing,
        "versions": versions(),
        "reference_versions": ref_versions,
        "cases": results,
    }


def parity_table(result: Dict) -> str:
    """Markdown: one row per (case, our rasterizer, quantity), with the float32-noise verdict."""
    lines = [
        f"Reference: **{result['reference']}**; float32 throughout; loss = sum(w * RGB+D render) + sum(w * alpha).",
        "",
        "| case | ours | quantity | max abs | mean abs | max abs ref | max / max ref | differ | within noise |",
        "|---|---|---|---:|---:|---:|---:|---:|---|",
    ]
    for name, case in result["cases"].items():
        for label, stats_by_q in case["compared"].items():
            for quantity, s in stats_by_q.items():
                ok = "yes" if within_noise(quantity, s) else "**no**"
                lines.append(
                    f"| {name} | {label} | {quantity} | {s['max_abs']:.2e} | {s['mean_abs']:.2e} | "
                    f"{s['ref_max_abs']:.2e} | {s['rel']:.2e} | {s['n_differ']} | {ok} |"
                )
    for label, why in result["unavailable"].items():
        lines.append(f"\n{label} not compared: {why}")
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------------------ timing
TIMING_METHODS = {
    "gsplat": (gsplat_renderer, "cuda"),
    "torch-cuda": (torch_renderer, "cuda"),
    "torch": (torch_renderer, "cpu"),
    "cpu-fast": (cpu_fast_renderer, "cpu"),
}


def run_timing(cfg: ParityConfig) -> Dict:
    """Forward and forward+backward seconds per (method, Gaussians, image), and CPU / GPU ratios."""

    unknown = [m for m in cfg.timing_methods if m not in TIMING_METHODS]
    if unknown:
        raise ValueError(f"unknown timing methods {unknown}; choose from {sorted(TIMING_METHODS)}")
    if any(TIMING_METHODS[m][1] == "cuda" for m in cfg.timing_methods) and not torch.cuda.is_available():
        raise ValueError("timing of gsplat / torch-cuda needs CUDA; use --timing-methods torch cpu-fast on a CPU")
    baseline = json.loads(cfg.cpu_baseline.read_text())
    cpu_rows = {(r["gaussians"], r["resolution"]): r for r in baseline["rows"]}
    rows = []
    for res in cfg.timing_resolutions:
        width, height = parse_size(res)
        for n in cfg.timing_sizes:
            row: Dict = {"gaussians": n, "resolution": res}
            for method in cfg.timing_methods:
                make_renderer, device = TIMING_METHODS[method]
                scene = bench_scene(n, width, height, device=device)
                fwd, fwd_bwd = time_fwd_bwd(make_renderer(), scene, width, height, cfg.timing_repeats, device)
                row[method] = {"fwd_s": fwd, "fwd_bwd_s": fwd_bwd}
                if device == "cuda":
                    torch.cuda.empty_cache()
            cpu = cpu_rows.get((n, res))
            if cpu is not None:
                row["cpu"] = {m: cpu[m] for m in ("cpu-fast", "torch") if cpu.get(m)}
            rows.append(row)
    correction = [time_correction(res, cfg.timing_repeats) for res in cfg.timing_correction]
    cpu_correction = {r["resolution"]: r for r in baseline.get("correction", {}).get("rows", [])}
    for row in correction:
        if row["resolution"] in cpu_correction:
            row["cpu"] = {k: v for k, v in cpu_correction[row["resolution"]].items() if k != "resolution"}
    return {
        "versions": versions(),
        "cpu_baseline": baseline.get("source", str(cfg.cpu_baseline)),
        "rows": rows,
        "correction_cpu_baseline": baseline.get("correction", {}).get("source"),
        "correction": correction,
    }


def time_correction(resolution: str, repeats: int) -> Dict:
    """Median seconds of the shipped correction network (``exact``: the plain float32 forward, the only
    mode that runs on CUDA; the lean modes are CPU kernels) per image on CUDA, after one warm-up."""
    from naka_gs_plugin.enhance.checkpoint import DEFAULT_WEIGHTS, load_correction
    from naka_gs_plugin.enhance.correction import CorrectionRunner
    from naka_gs_plugin.enhance.naka import naka_enhance

    width, height = parse_size(resolution)
    gen = torch.Generator().manual_seed(0)
    low = torch.rand(height, width, 3, generator=gen) * 0.2  # a dark sRGB capture in [0, 0.2]
    pair = [t.permute(2, 0, 1)[None].contiguous().cuda() for t in (low, naka_enhance(low))]
    runner = CorrectionRunner(load_correction(DEFAULT_WEIGHTS).cuda(), "exact")
    seconds = []
    with torch.no_grad():
        for _ in range(repeats + 1):
            sync("cuda")
            t0 = time.perf_counter()
            runner(*pair)
            sync("cuda")
            seconds.append(time.perf_counter() - t0)
    torch.cuda.empty_cache()
    return {"resolution": resolution, "exact_cuda_s": statistics.median(seconds[1:])}


def timing_table(result: Dict) -> str:
    """Markdown: seconds per method, and each 2-core CPU rasterizer's forward+backward / each GPU one's."""
    methods = [m for m in TIMING_METHODS if any(m in r for r in result["rows"])]
    gpu = [m for m in methods if TIMING_METHODS[m][1] == "cuda"]
    header = ["Gaussians", "image"] + [f"{m} f+b (fwd) s" for m in methods]
    header += [f"2-core {c} f+b / {g}" for c in ("cpu-fast", "torch") for g in gpu]
    lines = [
        f"CPU baseline: {result['cpu_baseline']}",
        "",
        "| " + " | ".join(header) + " |",
        "|" + "---:|" * len(header),
    ]
    for r in result["rows"]:
        cells = [f"{r['gaussians']:,}", r["resolution"]]
        cells += [f"{r[m]['fwd_bwd_s']:.4f} ({r[m]['fwd_s']:.4f})" if m in r else "-" for m in methods]
        for c in ("cpu-fast", "torch"):
            for g in gpu:
                cpu = r.get("cpu", {}).get(c)
                cells.append(f"{cpu['fwd_bwd_s'] / r[g]['fwd_bwd_s']:.1f}x" if cpu and g in r else "-")
        lines.append("| " + " | ".join(cells) + " |")
    if result.get("correction"):
        lines += [
            "",
            f"Correction network per image; CPU baseline: {result.get('correction_cpu_baseline')}",
            "",
            "| image | exact on CUDA s | 2-core exact s (/ CUDA) | 2-core auto s (/ CUDA) |",
            "|---|---:|---:|---:|",
        ]
        for r in result["correction"]:
            gpu, cpu = r["exact_cuda_s"], r.get("cpu", {})
            cells = [r["resolution"], f"{gpu:.4f}"]
            cells += [f"{cpu[k]:.2f} ({cpu[k] / gpu:.0f}x)" if k in cpu else "-" for k in ("exact_s", "auto_s")]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def run(cfg: ParityConfig) -> Tuple[Dict, str]:
    """Run the parity comparison or the timing; print the markdown table, write files to ``out_dir``."""
    if cfg.mode == "timing":
        result, stem = run_timing(cfg), "timing"
        table = timing_table(result)
    else:
        result, stem = run_parity(cfg), "parity"
        table = parity_table(result)
    print(table)
    if cfg.out_dir is not None:
        cfg.out_dir.mkdir(parents=True, exist_ok=True)
        (cfg.out_dir / f"{stem}.md").write_text(table)
        (cfg.out_dir / f"{stem}.json").write_text(json.dumps(result, indent=2))
    return result, table


@dataclass
class CudaParity(ParityConfig):
    """Our rasterizers against gsplat's CUDA rasterization (or the torch path as a stand-in)."""

    def main(self) -> None:
        run(self)


def entrypoint(args: Optional[Sequence[str]] = None) -> None:
    """``python -m benchmarks.cuda_parity``; bad options print one line."""
    parity = tyro.cli(CudaParity, args=args)
    try:
        parity.main()
    except (FileNotFoundError, ValueError) as err:
        raise SystemExit(f"python -m benchmarks.cuda_parity: {err}") from None


if __name__ == "__main__":
    entrypoint()
