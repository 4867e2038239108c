"""The compiled compositing and appearance (``naka_gs_plugin.model.composite``) against its PyTorch reference.

Forward values must be the reference's exactly (the same float32 operations), gradients within float32 rounding
(the gain's and offset's are sums over the image in another order); inputs the kernels do not take run the
reference itself.
"""

from __future__ import annotations

import numba
import pytest
import torch

from naka_gs_plugin.model.composite import composite, composite_torch


def _inputs(height: int = 37, width: int = 53, channels: int = 3, seed: int = 0):
    """A premultiplied render that overshoots [0, 1] in places, its alpha (exact 0 and 1 included), a background,
    and a view's gain and offset: leaves that require a gradient (the background does not, as in training)."""
    gen = torch.Generator().manual_seed(seed)
    render = torch.rand(1, height, width, channels, generator=gen) * 1.3 - 0.1
    alpha = torch.rand(1, height, width, 1, generator=gen)
    alpha[0, 0, :5] = 0.0
    alpha[0, 1, :5] = 1.0
    render[0, 2, :5, :3] = torch.tensor([0.0, 1.0, 0.5])  # exactly at the clamp's bounds with alpha 1
    alpha[0, 2, :5] = 1.0
    background = torch.rand(3, generator=gen)
    gain = torch.exp(0.3 * torch.randn(3, generator=gen))
    offset = 0.1 * torch.randn(3, generator=gen)
    leaves = [t.requires_grad_() for t in (render, alpha, gain, offset)]
    return leaves, background


def _run(fn, render, alpha, background, gain, offset, upstream):
    """Output and gradients of ``fn`` for leaves ``render, alpha, gain, offset`` (gain None: no appearance)."""
    leaves = [t for t in (render, alpha, gain, offset) if t is not None]
    for t in leaves:
        t.grad = None
    out = fn(render[..., :3], alpha, background, gain, offset)
    (out * upstream).sum().backward()
    return out.detach(), [t.grad.clone() for t in leaves]


@pytest.mark.parametrize("appearance", [True, False])
@pytest.mark.parametrize("channels", [3, 4])  # 4: the RGB of an RGB+depth render, a strided view
def test_forward_is_the_reference_and_backward_matches_it(appearance, channels):
    (render, alpha, gain, offset), background = _inputs(channels=channels)
    if not appearance:
        gain = offset = None
    upstream = torch.randn(1, 37, 53, 3, generator=torch.Generator().manual_seed(1))
    fast, fast_grads = _run(composite, render, alpha, background, gain, offset, upstream)
    ref, ref_grads = _run(composite_torch, render, alpha, background, gain, offset, upstream)
    assert 0 < (fast == 0).sum() and 0 < (fast == 1).sum()  # both clamps act
    assert torch.equal(fast, ref)
    for got, want in zip(fast_grads, ref_grads):
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5 * float(want.abs().max()))
    assert len(fast_grads) == (4 if appearance else 2)


def test_nan_passes_forward_and_gets_no_gradient_as_in_torch():
    (render, alpha, gain, offset), background = _inputs()
    with torch.no_grad():
        render[0, 5, 5, 1] = float("nan")
    upstream = torch.ones(1, 37, 53, 3)
    fast, fast_grads = _run(composite, render, alpha, background, gain, offset, upstream)
    ref, ref_grads = _run(composite_torch, render, alpha, background, gain, offset, upstream)
    assert torch.isnan(fast[0, 5, 5, 1]) and torch.isnan(ref[0, 5, 5, 1])
    assert fast_grads[0][0, 5, 5, 1] == ref_grads[0][0, 5, 5, 1] == 0


def test_results_do_not_depend_on_the_thread_count():
    (render, alpha, gain, offset), background = _inputs(height=64, width=40)
    upstream = torch.randn(1, 64, 40, 3, generator=torch.Generator().manual_seed(2))
    threads = numba.get_num_threads()
    runs = []
    try:
        for n in (1, threads):
            numba.set_num_threads(n)
            runs.append(_run(composite, render, alpha, background, gain, offset, upstream))
    finally:
        numba.set_num_threads(threads)
    assert torch.equal(runs[0][0], runs[1][0])
    for a, b in zip(runs[0][1], runs[1][1]):
        assert torch.equal(a, b)


def test_inputs_the_kernels_do_not_take_run_the_reference():
    """float64, and a background that requires a gradient (it gets one)."""
    (render, alpha, gain, offset), background = _inputs()
    upstream = torch.randn(1, 37, 53, 3, generator=torch.Generator().manual_seed(3))
    doubles = [t.detach().double().requires_grad_() for t in (render, alpha, gain, offset)]
    out, _ = _run(composite, *doubles[:2], background.double(), *doubles[2:], upstream.double())
    assert out.dtype == torch.float64
    learnable = background.clone().requires_grad_()
    _run(composite, render, alpha, learnable, gain, offset, upstream)
    assert learnable.grad is not None and learnable.grad.abs().sum() > 0
