"""The compiled SSIM (``naka_gs_plugin.model.ssim.SSIMLoss``) against its reference, ``pytorch_msssim``.

Forward and backward of the fused kernels are checked with ``assert_close`` against pytorch_msssim evaluated
in float64 (the exact value of what both compute in float32), on images as splatfacto passes them (NCHW
views of HWC tensors); inputs the kernels do not take run pytorch_msssim itself. The same for the training loss
with its L1 term (``SSIMLoss.l1_ssim_loss``, against splatfacto's formula) and PSNR's squared error.
"""

from __future__ import annotations

import warnings

import numba
import pytest
import torch
from pytorch_msssim import SSIM

from naka_gs_plugin.model.ssim import SSIMLoss

REFERENCE = SSIM(data_range=1.0, size_average=True, channel=3)
FUSED = SSIMLoss(data_range=1.0, size_average=True, channel=3)


def _pair(height: int, width: int, n: int = 1, noise: float = 0.1, seed: int = 0):
    """A ground truth and a noisy prediction in [0, 1], HWC tensors seen as NCHW (as splatfacto's loss does)."""
    gen = torch.Generator().manual_seed(seed)
    gt = torch.rand(n, height, width, 3, generator=gen)
    pred = (gt + noise * torch.randn(n, height, width, 3, generator=gen)).clamp(0, 1)
    return gt, pred


def _nchw(image: torch.Tensor) -> torch.Tensor:
    return image.permute(0, 3, 1, 2)


def _value_and_grads(module, gt, pred, grad_gt: bool, grad_pred: bool):
    gt = gt.clone().requires_grad_(grad_gt)
    pred = pred.clone().requires_grad_(grad_pred)
    value = module(_nchw(gt), _nchw(pred))
    if grad_gt or grad_pred:
        (1 - value).backward()
    return value.detach(), gt.grad, pred.grad


def _assert_matches_reference(got, ref):
    """(value, grad of gt, grad of pred) in float32 against the float64 reference's: value to 2e-6, gradients to
    1e-4 of their largest, a gradient exactly where the reference has one."""
    (value, g_gt, g_pred), (ref_value, ref_gt, ref_pred) = got, ref
    assert value.dtype == torch.float32
    torch.testing.assert_close(value.double(), ref_value, rtol=0, atol=2e-6)
    for grad, ref_grad in ((g_gt, ref_gt), (g_pred, ref_pred)):
        assert (grad is None) == (ref_grad is None)
        if ref_grad is not None:
            torch.testing.assert_close(grad.double(), ref_grad, rtol=0, atol=1e-4 * float(ref_grad.abs().max()))


def _at_thread_counts(run):
    """``run()`` with numba at 1 thread and at its current count (restored after)."""
    threads = numba.get_num_threads()
    runs = []
    try:
        for count in (1, threads):
            numba.set_num_threads(count)
            runs.append(run())
    finally:
        numba.set_num_threads(threads)
    return runs


@pytest.mark.parametrize("height, width, n", [(11, 11, 1), (36, 48, 1), (61, 45, 2), (120, 160, 1)])
@pytest.mark.parametrize("grads", ["pred", "gt", "both"])
def test_forward_and_backward_match_pytorch_msssim(height, width, n, grads):
    gt, pred = _pair(height, width, n)
    want = dict(grad_gt=grads in ("gt", "both"), grad_pred=grads in ("pred", "both"))
    _assert_matches_reference(
        _value_and_grads(FUSED, gt, pred, **want), _value_and_grads(REFERENCE, gt.double(), pred.double(), **want)
    )


def test_identical_images_score_one_with_zero_gradient():
    gt, _ = _pair(40, 30)
    value, _, grad = _value_and_grads(FUSED, gt, gt.clone(), grad_gt=False, grad_pred=True)
    torch.testing.assert_close(value, torch.tensor(1.0), rtol=0, atol=1e-6)
    assert grad.abs().max() < 1e-6


def test_results_do_not_depend_on_the_thread_count():
    gt, pred = _pair(64, 80)
    runs = _at_thread_counts(lambda: _value_and_grads(FUSED, gt, pred, grad_gt=False, grad_pred=True))
    assert torch.equal(runs[0][0], runs[1][0]) and torch.equal(runs[0][2], runs[1][2])


@pytest.mark.parametrize(
    "case",
    ["smaller than the window", "float64", "a 7-tap window", "one channel"],
)
def test_inputs_the_kernels_do_not_take_run_pytorch_msssim(case):
    gt, pred = _pair(8, 20) if case == "smaller than the window" else _pair(30, 30)
    fused, reference = FUSED, REFERENCE
    if case == "float64":
        gt, pred = gt.double(), pred.double()
    elif case == "a 7-tap window":
        fused = SSIMLoss(data_range=1.0, size_average=True, channel=3, win_size=7)
        reference = SSIM(data_range=1.0, size_average=True, channel=3, win_size=7)
    elif case == "one channel":
        gt, pred = gt[..., :1], pred[..., :1]
        fused = SSIMLoss(data_range=1.0, size_average=True, channel=1)
        reference = SSIM(data_range=1.0, size_average=True, channel=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pytorch_msssim warns that it skips smoothing a dimension under 11 pixels
        got = _value_and_grads(fused, gt, pred, grad_gt=False, grad_pred=True)
        ref = _value_and_grads(reference, gt, pred, grad_gt=False, grad_pred=True)
    assert torch.equal(got[0], ref[0]) and torch.equal(got[2], ref[2])


def test_eval_metric_without_grad_equals_the_loss_value():
    gt, pred = _pair(50, 70)
    with torch.no_grad():
        metric = FUSED(_nchw(gt), _nchw(pred))
    value, _, _ = _value_and_grads(FUSED, gt, pred, grad_gt=False, grad_pred=True)
    assert torch.equal(metric, value)


def _l1_ssim_reference(gt, pred, ssim_lambda):
    """Splatfacto's main loss as its ``get_loss_dict`` writes it, with pytorch_msssim's module."""
    return (1 - ssim_lambda) * torch.abs(gt - pred).mean() + ssim_lambda * (1 - REFERENCE(_nchw(gt), _nchw(pred)))


@pytest.mark.parametrize("height, width, n", [(11, 11, 1), (61, 45, 2), (120, 160, 1)])
@pytest.mark.parametrize("grads", ["pred", "gt", "both"])
def test_the_l1_ssim_loss_matches_splatfactos_in_value_and_gradient(height, width, n, grads):
    gt, pred = _pair(height, width, n)
    pred[0, 0, 0] = gt[0, 0, 0]  # |x - y| at 0: torch's gradient there is 0, as the kernel's sign(0)
    results = []
    for fused in (True, False):
        a = gt.clone() if fused else gt.double()
        b = pred.clone() if fused else pred.double()
        a.requires_grad_(grads in ("gt", "both"))
        b.requires_grad_(grads in ("pred", "both"))
        loss = FUSED.l1_ssim_loss(_nchw(a), _nchw(b), 0.2) if fused else _l1_ssim_reference(a, b, 0.2)
        loss.backward()
        results.append((loss.detach(), a.grad, b.grad))
    _assert_matches_reference(*results)


def test_the_l1_ssim_loss_does_not_depend_on_the_thread_count():
    gt, pred = _pair(64, 80)

    def run():
        b = pred.clone().requires_grad_(True)
        loss = FUSED.l1_ssim_loss(_nchw(gt), _nchw(b), 0.2)
        loss.backward()
        return loss.detach(), b.grad

    runs = _at_thread_counts(run)
    assert torch.equal(runs[0][0], runs[1][0]) and torch.equal(runs[0][1], runs[1][1])


def test_the_l1_ssim_loss_on_inputs_the_kernels_do_not_take_is_splatfactos_formula():
    gt, pred = _pair(30, 30)
    gt, pred = gt.double(), pred.double().requires_grad_(True)
    loss = FUSED.l1_ssim_loss(_nchw(gt), _nchw(pred), 0.2)
    torch.testing.assert_close(loss, _l1_ssim_reference(gt, pred, 0.2), rtol=0, atol=0)


def test_squared_error_sum_is_the_exact_sum_and_none_where_the_kernel_does_not_apply():
    from naka_gs_plugin.model.ssim import squared_error_sum

    gt, pred = _pair(37, 53)
    exact = float(((gt.double() - pred.double()) ** 2).sum())
    assert squared_error_sum(pred[0], gt[0]) == pytest.approx(exact, rel=1e-12)
    assert squared_error_sum(pred[0].permute(1, 0, 2), gt[0].permute(1, 0, 2)) == pytest.approx(exact, rel=1e-12)
    assert squared_error_sum(pred.double(), gt.double()) is None
    assert squared_error_sum(pred[0], gt[0, :-1]) is None
