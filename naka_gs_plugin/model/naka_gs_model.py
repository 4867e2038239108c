"""NakaGSModel: nerfstudio's splatfacto, rasterizing with gsplat on CUDA and our rasterizer elsewhere.

Everything splatfacto does (parameters, L1 + SSIM loss, SH schedule, camera optimizer, bilateral
grid, gsplat's DefaultStrategy densification, export) is inherited. Overridden, and only because
stock splatfacto breaks on a CPU-only or offline machine:

- ``populate_modules``: stock code calls ``.cuda()`` on seed colours and builds torchmetrics' LPIPS
  (downloads AlexNet; offline it raises). We keep the seed colours on the CPU and build LPIPS from
  the weights we ship, lazily and outside the module tree (:mod:`naka_gs_plugin.model.lpips`).
- ``get_outputs``: stock code calls ``K.cuda()``, the ``torch.compile``d ``get_viewmat`` (~20 s per
  CPU process) and gsplat's CUDA-only ``rasterization``, all inside the one method with no hook
  between, so it is a copy of splatfacto 1.1.5's (a test pins the upstream source: an upgrade fails
  until the copy is re-checked) that dispatches by device: gsplat for CUDA tensors, the compiled numba
  tile rasterizer (:mod:`naka_gs_plugin.model.rasterize_cpu_fast`) or our PyTorch one
  (:mod:`naka_gs_plugin.model.rasterize`) otherwise (never by try/except around gsplat: each
  failed call re-attempts a CUDA JIT build).
- the SSIM of the loss and the eval metric: splatfacto's ``pytorch_msssim`` module, with compiled
  kernels for CPU images (:mod:`naka_gs_plugin.model.ssim`; on CUDA it is upstream's); its PSNR the
  same torchmetrics formula without the metric module's bookkeeping (:class:`PairPSNR`).
- per-view appearance (``appearance affine``, :mod:`naka_gs_plugin.model.appearance`): a gain and
  offset per training view, applied to its render in training only (after splatfacto's bilateral grid
  would be); ``get_param_groups`` adds their group. The render's compositing onto the background and
  that appearance run as one compiled pass on a CPU (:mod:`naka_gs_plugin.model.composite`).
- ``get_gt_img``: the training target at a downscaled step's size is kept per image and scale (upstream
  box-filters the full-size image again twice a step), the same bits.
- training safety: a non-finite loss or parameter stops training with a clear message before
  anything non-finite can reach a checkpoint.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Type, Union

import torch
from jaxtyping import Float
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes
from nerfstudio.models.splatfacto import RGB2SH, SplatfactoModel, SplatfactoModelConfig
from nerfstudio.utils.misc import step_check
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor
from torch.nn import Parameter
from torchmetrics.functional.image import peak_signal_noise_ratio

from naka_gs_plugin.errors import UserError
from naka_gs_plugin.model.appearance import ViewAppearance
from naka_gs_plugin.model.composite import composite
from naka_gs_plugin.model.lpips import LazyLPIPS, LPIPSWeightsError, load_lpips
from naka_gs_plugin.model.projection import MAX_SH_DEGREE
from naka_gs_plugin.model.schedule import SPLATFACTO_SCHEDULE, schedule_for_device
from naka_gs_plugin.model.ssim import SSIMLoss, squared_error_sum
from naka_gs_plugin.run.nerfstudio_hooks import splatfacto_lpips_replaced


class NonFiniteTrainingError(UserError, RuntimeError):
    """Training produced NaN/Inf; raised before the bad state can be checkpointed."""


class RasterizerOptionError(UserError, ValueError):
    """A ``--pipeline.model.rasterizer`` (or ``sh-degree``) this machine's tensors or our rasterizers cannot run:
    one line naming the option and what to pass instead."""


@dataclass
class NakaGSModelConfig(SplatfactoModelConfig):
    """Splatfacto's options plus the rasterizer backend, per-view appearance and LPIPS's backbone weights."""

    _target: Type = field(default_factory=lambda: NakaGSModel)
    rasterizer: Literal["auto", "gsplat", "torch", "cpu-fast"] = "auto"
    """auto: gsplat for CUDA tensors, otherwise cpu-fast (compiled numba tile kernels) when numba
    imports, else torch (pure PyTorch, same results, slower). gsplat needs CUDA, cpu-fast CPU."""
    lpips_weights: Optional[Path] = None
    """LPIPS's AlexNet backbone from this file (torchvision's ``alexnet-owt-7be5be79.pth``) instead of the
    copy shipped with naka-gs (the same numbers)."""
    appearance: Literal["affine", "none"] = "affine"
    """``affine``: a per-channel gain and offset per training view, learned in training and averaging the
    identity over the views (the views are enhanced one by one, so their brightness differs); eval and
    novel views render the views' average appearance. ``none``: one appearance for all views."""

    # Splatfacto's schedule fields, which may be left to the device the run trains on (None; the naka-gs preset
    # does so): model/schedule.py.
    warmup_length: Optional[int] = SPLATFACTO_SCHEDULE["warmup_length"]
    """Steps before densification starts; None: by device (CPU 300, CUDA splatfacto's 500)."""
    stop_split_at: Optional[int] = SPLATFACTO_SCHEDULE["stop_split_at"]
    """Step at which densification stops; None: by device (CPU 5000, CUDA splatfacto's 15000)."""
    stop_screen_size_at: Optional[int] = SPLATFACTO_SCHEDULE["stop_screen_size_at"]
    """Step at which screen-size splitting stops; None: by device (CPU 3300, CUDA splatfacto's 4000)."""
    reset_alpha_every: Optional[int] = SPLATFACTO_SCHEDULE["reset_alpha_every"]
    """Refinements between opacity resets; None: by device (CPU 10, CUDA splatfacto's 30)."""
    sh_degree_interval: Optional[int] = SPLATFACTO_SCHEDULE["sh_degree_interval"]
    """Steps between SH degree increases; None: by device (CPU 500, CUDA splatfacto's 1000)."""
    resolution_schedule: Optional[int] = SPLATFACTO_SCHEDULE["resolution_schedule"]
    """Steps per training-image downscale level; None: by device (CPU 3250, CUDA splatfacto's 3000)."""

    def resolve_schedule(self, device_type: str) -> None:
        """Set each schedule field left to the device (None) to its value for ``device_type``
        (:func:`~naka_gs_plugin.model.schedule.schedule_for_device`); the others are the user's."""
        for key, value in schedule_for_device(device_type).items():
            if getattr(self, key) is None:
                setattr(self, key, value)

    def __setstate__(self, state: dict) -> None:
        """Runs saved before ``appearance`` existed have no such parameters in their checkpoints."""
        state.setdefault("appearance", "none")
        self.__dict__.update(state)


def _numba_available() -> bool:
    """Whether the cpu-fast rasterizer's compiler (numba) imports."""
    try:
        import numba  # noqa: F401
    except ImportError:
        return False
    return True


def resolve_rasterizer(choice: str, device: torch.device) -> str:
    """``--pipeline.model.rasterizer`` with ``auto`` resolved for tensors on ``device`` (whether the choice can run
    there, the model checks at its first render)."""
    if choice != "auto":
        return choice
    return "gsplat" if device.type == "cuda" else ("cpu-fast" if _numba_available() else "torch")


def all_finite(tensor: Tensor) -> bool:
    """Whether every element is finite. One min/max pass: NaN propagates into both and an infinity is one of
    them, so this is ``torch.isfinite(tensor).all()`` without its full-size boolean temporary (20x faster on a
    CPU for the Gaussians' parameters, checked every step)."""
    if tensor.numel() == 0:
        return True
    low, high = torch.aminmax(tensor.detach())
    return bool(torch.isfinite(low) & torch.isfinite(high))


class PairPSNR(torch.nn.Module):
    """Splatfacto's ``PeakSignalNoiseRatio(data_range=1.0)`` for the way splatfacto calls it: one image pair at
    a time (every training step, every eval image), [0, 1] images, dB. The same value, from torchmetrics'
    functional form and outside autograd: the module form also keeps running sums over calls that splatfacto
    never reads and records the computation for a backward nobody runs, which at every training step cost as
    much as a loss term."""

    def forward(self, preds: Float[Tensor, "*shape"], target: Float[Tensor, "*shape"]) -> Float[Tensor, ""]:
        with torch.no_grad():
            squared = squared_error_sum(preds, target)  # one compiled pass on a CPU, else None
            if squared is None:
                return peak_signal_noise_ratio(preds, target, data_range=1.0)
            mse = squared / preds.numel()
            return preds.new_tensor(math.inf if mse == 0 else -10.0 * math.log10(mse))  # NaN stays NaN


def viewmat_from_c2w(c2w: Float[Tensor, "C 3 4"]) -> Float[Tensor, "C 4 4"]:
    """OpenGL camera-to-world -> OpenCV world-to-camera (gsplat's ``viewmats``).

    Splatfacto's own ``get_viewmat`` is wrapped in ``torch.compile``, which costs ~20 s per process
    on a CPU for a 3x3 inverse; this is the same maths, uncompiled.
    """
    rot = c2w[:, :3, :3] * torch.tensor([1.0, -1.0, -1.0], device=c2w.device, dtype=c2w.dtype)
    rot_inv = rot.transpose(1, 2)
    viewmat = torch.zeros(c2w.shape[0], 4, 4, device=c2w.device, dtype=c2w.dtype)
    viewmat[:, :3, :3] = rot_inv
    viewmat[:, :3, 3] = -(rot_inv @ c2w[:, :3, 3:4]).squeeze(-1)
    viewmat[:, 3, 3] = 1.0
    return viewmat


class NakaGSModel(SplatfactoModel):
    """See the module docstring."""

    config: NakaGSModelConfig

    def populate_modules(self) -> None:
        device = self.kwargs.get("device")
        self.config.resolve_schedule(torch.device(device).type if device is not None else "cpu")
        seed_rgb = None
        if self.seed_points is not None and not self.config.random_init and self.seed_points[1].shape[0] > 0:
            # Hide the colours from splatfacto (its colour branch calls .cuda()); set them below.
            seed_rgb = self.seed_points[1]
            self.seed_points = (self.seed_points[0], seed_rgb[:0])
        if self.config.lpips_weights is not None:
            try:  # a wrong file fails here, in one line, rather than at the first evaluation
                load_lpips(self.config.lpips_weights)
            except LPIPSWeightsError as err:
                raise LPIPSWeightsError(f"--pipeline.model.lpips-weights {err}") from None
        # Splatfacto imports LPIPS inside populate_modules; swap in ours (offline weights, lazy) there.
        with splatfacto_lpips_replaced(lambda **_: LazyLPIPS(self.config.lpips_weights)):
            super().populate_modules()
        # Splatfacto's SSIM module, with compiled kernels for CPU images (the same loss and metric).
        self.ssim = SSIMLoss(data_range=1.0, size_average=True, channel=3)
        self.psnr = PairPSNR()
        self._downscaled_gt: Dict[int, tuple] = {}
        if seed_rgb is not None:
            self.seed_points = (self.seed_points[0], seed_rgb)
            rgb = seed_rgb.float() / 255.0
            # splatfacto uses logit(eps=1e-10), but 1 - 1e-10 == 1 in float32: a pure white (255) seed
            # point got an infinite colour logit with sh_degree 0. 1e-4 keeps |logit| <= 9.2.
            dc = RGB2SH(rgb) if self.config.sh_degree > 0 else torch.logit(rgb, eps=1e-4)
            self.gauss_params["features_dc"].data.copy_(dc)
        self.view_appearance = ViewAppearance(self.num_train_data) if self.config.appearance == "affine" else None
        self._backend_logged: Optional[str] = None
        self._metrics_every = 0  # the trainer's --logging.steps-per-log, once it has set up its callbacks

    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        groups = super().get_param_groups()
        if self.view_appearance is not None:
            groups["appearance"] = list(self.view_appearance.parameters())
        return groups

    def resume_state(self) -> Dict[str, Any]:
        """What training carries from step to step outside the ``state_dict``: the densification strategy's running
        statistics (gsplat's ``DefaultStrategy`` state: each Gaussian's summed screen-space gradient, visibility count
        and largest screen radius since the last refinement). :meth:`load_resume_state` puts it back."""
        return {"strategy": dict(self.strategy_state)}

    def load_resume_state(self, state: Dict[str, Any]) -> bool:
        """Continue from :meth:`resume_state`; False, changing nothing, when it does not fit this model's strategy
        or its number of Gaussians (the statistics are per Gaussian)."""
        strategy = state.get("strategy")
        if not isinstance(strategy, dict) or set(strategy) != set(self.strategy_state):
            return False
        per_gaussian = [v for v in strategy.values() if isinstance(v, Tensor)]
        if any(v.shape[:1] != (self.num_points,) for v in per_gaussian):
            return False
        # Copies: the loaded tensors may be mapped from the checkpoint file, which a later save deletes.
        self.strategy_state.update(
            {k: v.to(self.device, copy=True) if isinstance(v, Tensor) else v for k, v in strategy.items()}
        )
        return True

    # ------------------------------------------------------------------ rasterization
    def _backend(self, device: torch.device) -> str:
        choice = resolve_rasterizer(self.config.rasterizer, device)
        if choice == "gsplat" and device.type != "cuda":
            raise RasterizerOptionError(
                f"rasterizer 'gsplat' needs CUDA tensors but the model is on {device} -- "
                "use --pipeline.model.rasterizer cpu-fast, torch or auto"
            )
        if choice == "cpu-fast" and device.type != "cpu":
            raise RasterizerOptionError(
                f"rasterizer 'cpu-fast' needs CPU tensors but the model is on {device} -- "
                "use --pipeline.model.rasterizer gsplat (or auto)"
            )
        if choice != "gsplat" and not 0 <= self.config.sh_degree <= MAX_SH_DEGREE:
            # Checked here, at the first render: the degree in use grows to sh_degree only after
            # sh_degree * sh_degree_interval steps (thousands), when our rasterizers would refuse it.
            raise RasterizerOptionError(
                f"--pipeline.model.sh-degree {self.config.sh_degree}: the {choice} rasterizer supports degrees "
                f"0..{MAX_SH_DEGREE} -- use --pipeline.model.sh-degree {MAX_SH_DEGREE} or less"
            )
        if choice != self._backend_logged:
            CONSOLE.log(
                f"[naka-gs] rasterizer: {choice} (device {device}, config '{self.config.rasterizer}')", markup=False
            )
            self._backend_logged = choice
        return choice

    def _rasterize(self, device: torch.device, **kwargs):
        backend = self._backend(device)
        if backend == "gsplat":
            from gsplat.rendering import rasterization as gsplat_rasterization

            if isinstance(kwargs["colors"], tuple):  # ours read (features_dc, features_rest) without the copy
                dc, rest = kwargs["colors"]
                kwargs["colors"] = torch.cat((dc[:, None, :], rest), dim=1)
            return gsplat_rasterization(packed=False, sparse_grad=False, **kwargs)
        if backend == "cpu-fast":
            from naka_gs_plugin.model.rasterize_cpu_fast import rasterization as cpu_fast_rasterization

            return cpu_fast_rasterization(**kwargs)
        from naka_gs_plugin.model.rasterize import rasterization

        return rasterization(**kwargs)

    def get_outputs(self, camera: Cameras) -> Dict[str, Union[Tensor, list]]:
        """Splatfacto's ``get_outputs`` with device-agnostic intrinsics and rasterizer dispatch."""
        if not isinstance(camera, Cameras):
            raise TypeError(f"get_outputs expects a Cameras object, got {type(camera).__name__}")
        if self.training:
            assert camera.shape[0] == 1, "Only one camera at a time"
            optimized_camera_to_world = self.camera_optimizer.apply_to_camera(camera)
        else:
            optimized_camera_to_world = camera.camera_to_worlds

        crop_ids = None
        if self.crop_box is not None and not self.training:
            crop_ids = self.crop_box.within(self.means).squeeze()
            if crop_ids.sum() == 0:
                return self.get_empty_outputs(
                    int(camera.width.item()), int(camera.height.item()), self.background_color
                )
        params = {
            k: (v[crop_ids] if crop_ids is not None else v)
            for k, v in (
                ("opacities", self.opacities),
                ("means", self.means),
                ("features_dc", self.features_dc),
                ("features_rest", self.features_rest),
                ("scales", self.scales),
                ("quats", self.quats),
            )
        }
        # The two SH parameters as they are; only gsplat needs their [N, 16, 3] concatenation (_rasterize).
        colors = (params["features_dc"], params["features_rest"])
        if self.config.sh_degree == 0:
            colors = torch.cat((colors[0][:, None, :], colors[1]), dim=1)

        camera_scale_fac = self._get_downscale_factor()
        camera.rescale_output_resolution(1 / camera_scale_fac)
        viewmat = viewmat_from_c2w(optimized_camera_to_world)
        K = camera.get_intrinsics_matrices().to(self.device)
        W, H = int(camera.width.item()), int(camera.height.item())
        self.last_size = (H, W)
        camera.rescale_output_resolution(camera_scale_fac)  # type: ignore

        if self.config.rasterize_mode not in ["antialiased", "classic"]:
            raise ValueError(f"Unknown rasterize_mode: {self.config.rasterize_mode}")
        render_mode = "RGB+ED" if (self.config.output_depth_during_training or not self.training) else "RGB"
        if self.config.sh_degree > 0:
            sh_degree_to_use = min(self.step // self.config.sh_degree_interval, self.config.sh_degree)
        else:
            colors = torch.sigmoid(colors).squeeze(1)
            sh_degree_to_use = None

        render, alpha, self.info = self._rasterize(
            self.means.device,
            means=params["means"],
            quats=params["quats"],
            scales=torch.exp(params["scales"]),
            opacities=torch.sigmoid(params["opacities"]).squeeze(-1),
            colors=colors,
            viewmats=viewmat,
            Ks=K,
            width=W,
            height=H,
            near_plane=0.01,
            far_plane=1e10,
            render_mode=render_mode,
            sh_degree=sh_degree_to_use,
            absgrad=self.strategy.absgrad,
            rasterize_mode=self.config.rasterize_mode,
        )
        if self.training:
            self.strategy.step_pre_backward(
                self.gauss_params, self.optimizers, self.strategy_state, self.step, self.info
            )

        background = self._get_background_color()
        # Compositing, splatfacto's bilateral grid, the view's appearance; compiled into one pass on a CPU where
        # no bilateral grid comes between the two (naka_gs_plugin.model.composite).
        cam_idx = (
            camera.metadata["cam_idx"] if self.training and camera.metadata and "cam_idx" in camera.metadata else None
        )
        appearance = None
        if self.view_appearance is not None and cam_idx is not None:
            appearance = self.view_appearance.transform(int(cam_idx))
        if self.config.use_bilateral_grid and cam_idx is not None:
            rgb = self._apply_bilateral_grid(composite(render[:, ..., :3], alpha, background), cam_idx, H, W)
            if appearance is not None:
                rgb = self.view_appearance(rgb, int(cam_idx))
        else:
            rgb = composite(render[:, ..., :3], alpha, background, *(appearance or ()))
        depth_im = None
        if render_mode == "RGB+ED":
            depth_im = render[:, ..., 3:4]
            depth_im = torch.where(alpha > 0, depth_im, depth_im.detach().max()).squeeze(0)
        if background.shape[0] == 3 and not self.training:
            background = background.expand(H, W, 3)
        return {"rgb": rgb.squeeze(0), "depth": depth_im, "accumulation": alpha.squeeze(0), "background": background}

    # ------------------------------------------------------------------ training images
    def get_gt_img(self, image: Tensor) -> Tensor:
        """Splatfacto's target image at the step's scale, kept per training image while the scale is below 1.

        Upstream box-filters the full-size image on every call (a strided conv2d, twice a step: loss and
        metrics; on a CPU a sizeable part of a downscaled step, docs/cpu.md). The images are the datamanager's
        cached tensors, so each downscaled copy is computed once per image and scale, bit for bit upstream's; an
        entry is recomputed when its image was changed in place and dropped with its image.
        """
        d = self._get_downscale_factor()
        if d == 1:
            if self.training:
                self._downscaled_gt.clear()  # full size from here on
            return super().get_gt_img(image)
        key = id(image)
        entry = self._downscaled_gt.get(key)
        if entry is not None and entry[0]() is image and entry[1:3] == (image._version, d):
            return entry[3]
        out = super().get_gt_img(image)
        ref = weakref.ref(image, lambda _, cache=self._downscaled_gt, key=key: cache.pop(key, None))
        self._downscaled_gt[key] = (ref, image._version, d, out)
        return out

    # ------------------------------------------------------------------ safety and metrics
    def get_training_callbacks(
        self, training_callback_attributes: TrainingCallbackAttributes
    ) -> List[TrainingCallback]:
        trainer = training_callback_attributes.trainer
        if trainer is not None:
            self._metrics_every = trainer.config.logging.steps_per_log
        return super().get_training_callbacks(training_callback_attributes)

    def get_metrics_dict(self, outputs, batch) -> Dict[str, Tensor]:
        """Splatfacto's metrics; in training, only at the steps whose metrics the trainer writes (every
        ``--logging.steps-per-log``, from step 0): nerfstudio discards the others, and their PSNR is a pass over
        the full-size images at every step."""
        if self.training and self._metrics_every and not step_check(self.step, self._metrics_every, run_at_zero=True):
            return {}
        return super().get_metrics_dict(outputs, batch)

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, Tensor]:
        if "mask" in batch or self.config.use_scale_regularization or self.config.use_bilateral_grid:
            loss_dict = super().get_loss_dict(outputs, batch, metrics_dict)
        else:
            loss_dict = self._photometric_loss_dict(outputs, batch)
        bad = [k for k, v in loss_dict.items() if not all_finite(v)]
        if bad:
            raise NonFiniteTrainingError(
                f"non-finite loss ({', '.join(bad)}) at step {self.step}: training stopped before the optimizer "
                "step; the last checkpoint is intact -- lower the learning rates or check the input images"
            )
        return loss_dict

    def _photometric_loss_dict(self, outputs, batch) -> Dict[str, Tensor]:
        """Splatfacto's ``get_loss_dict`` where no mask, scale regularisation or bilateral grid takes part (that
        method is the reference the tests compare this with): the same losses, its L1 and SSIM terms computed as
        one node (:meth:`.ssim.SSIMLoss.l1_ssim_loss`)."""
        gt_img = self.composite_with_background(self.get_gt_img(batch["image"]), outputs["background"])
        pred_img = outputs["rgb"]
        main_loss = self.ssim.l1_ssim_loss(
            gt_img.permute(2, 0, 1)[None, ...], pred_img.permute(2, 0, 1)[None, ...], self.config.ssim_lambda
        )
        loss_dict = {"main_loss": main_loss, "scale_reg": torch.tensor(0.0).to(self.device)}
        if self.training:
            self.camera_optimizer.get_loss_dict(loss_dict)
        return loss_dict

    def step_post_backward(self, step):
        bad = [k for k, v in self.gauss_params.items() if not all_finite(v)]
        if bad:
            raise NonFiniteTrainingError(
                f"non-finite Gaussian parameters ({', '.join(bad)}) after step {step}: training stopped before "
                "they could be checkpointed; the last checkpoint is intact -- lower the learning rates"
            )
        super().step_post_backward(step)
