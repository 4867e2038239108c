"""The compiled cpu-fast rasterizer against the torch path (the reference), a per-pixel absgrad
reference and a short training run.

The first run compiles the numba kernels (float32 and float64, ~40 s on 2 cores); numba caches
them on disk, so later runs take a few seconds.
"""

from __future__ import annotations

import numba
import numpy as np
import pytest
import torch
from nerfstudio.data.scene_box import SceneBox

from naka_gs_plugin.model import compile_ahead, rasterize_cpu_fast, rasterize_cpu_kernels, rasterize_cpu_lists
from naka_gs_plugin.model.projection import pixel_bounds, project_gaussians
from naka_gs_plugin.model.rasterize import ALPHA_MIN, TILE_SIZE, rasterization
from naka_gs_plugin.model.rasterize_cpu_fast import rasterize_to_pixels_cpu_fast
from naka_gs_plugin.model.rasterize_dense import rasterize_to_pixels_dense
from tests.helpers import F32, F64, make_scene, train_steps

PARAMS = ("means", "quats", "scales", "opacities", "colors")


def render_and_grads(fn, scene, weights, **kwargs):
    """Render, backpropagate ``sum(weights * [colour, alpha])``; returns outputs, grads, meta."""
    inputs = {k: scene[k].clone().requires_grad_() for k in PARAMS}
    colors, alphas, meta = fn(**{**scene, **inputs}, **kwargs)
    meta["means2d"].retain_grad()
    (torch.cat([colors, alphas], -1) * weights).sum().backward()
    return colors.detach(), alphas.detach(), {k: inputs[k].grad for k in PARAMS}, meta


def _weights(scene, n_channels, dtype):
    gen = torch.Generator().manual_seed(11)
    shape = (scene["viewmats"].shape[0], scene["height"], scene["width"], n_channels + 1)
    return torch.randn(shape, generator=gen, dtype=F64).to(dtype)


def rel_err(a, b):
    """Largest absolute difference relative to the largest magnitude of the reference."""
    return float((a - b).abs().max() / b.abs().max().clamp(min=1e-30))


@pytest.mark.parametrize("hard", [False, True])
@pytest.mark.parametrize("render_mode", ["RGB+ED", "RGB", "D"])
def test_float32_matches_torch_path(render_mode, hard):
    """float32 cpu-fast against the torch path on the same inputs in float64: cpu-fast projects in
    float64 and rounds, so the torch path's own float32 rounding (as large as cpu-fast's error
    here) would blur the comparison."""
    scene = make_scene(400, 61, 45, hard=hard, seed=int(hard))
    scene64 = {k: v.double() if torch.is_tensor(v) else v for k, v in scene.items()}
    bg = torch.rand(2, 3, generator=torch.Generator().manual_seed(5))
    kwargs = dict(render_mode=render_mode, absgrad=True)
    dim = {"RGB": 3, "D": 1}.get(render_mode, 4)
    weights = _weights(scene, dim, F32)
    fast = render_and_grads(rasterize_cpu_fast.rasterization, scene, weights, backgrounds=bg, **kwargs)
    ref = render_and_grads(rasterization, scene64, weights.double(), backgrounds=bg.double(), **kwargs)
    (fc, fa, fg, fmeta), (rc, ra, rg, rmeta) = fast, ref
    assert fc.shape == rc.shape == (2, 45, 61, dim) and fc.dtype == F32 and fmeta["means2d"].dtype == F32
    assert 0.3 < float(ra.mean()) < 0.999  # covered and overlapping, not saturated everywhere
    if hard:
        assert (rmeta["radii"][:, [9, 10]] == 0).all() and (rmeta["radii"][0, [0, 1]] > 0).all()
    assert (fa - ra).abs().max() <= 1e-5
    if render_mode in ("RGB", "RGB+ED"):
        assert (fc[..., :3] - rc[..., :3]).abs().max() <= 1e-5
    if render_mode != "RGB":
        # Depth is in scene units (2..6 here, float32 spacing 2.4e-7..4.8e-7 there): relative.
        depth_f, depth_r = fc[..., -1], rc[..., -1]
        assert ((depth_f - depth_r).abs() / depth_r.abs().clamp(min=1.0)).max() <= 1e-5
    for k in PARAMS:  # float32 sums in a different order: relative to the largest component
        if render_mode == "D" and k == "colors":
            assert fg[k] is None and rg[k] is None
            continue
        assert rel_err(fg[k], rg[k]) <= 1e-4, k
    assert rel_err(fmeta["means2d"].absgrad, rmeta["means2d"].absgrad) <= 1e-4
    assert rel_err(fmeta["means2d"].grad, rmeta["means2d"].grad) <= 1e-4
    assert torch.equal(fmeta["radii"], rmeta["radii"])
    for key in ("means2d", "depths", "conics", "opacities"):
        scale = float(rmeta[key].abs().max())
        assert torch.allclose(fmeta[key].double(), rmeta[key], rtol=1e-6, atol=1e-7 * scale), key
    assert {k: v for k, v in fmeta.items() if not torch.is_tensor(v)} == {
        k: v for k, v in rmeta.items() if not torch.is_tensor(v)
    }


@pytest.mark.parametrize("rasterize_mode", ["classic", "antialiased"])
def test_float64_gradients_match_torch_autograd(rasterize_mode):
    scene = make_scene(150, 40, 30, sh_degree=2, dtype=F64, hard=True, seed=3)
    bg = torch.rand(2, 3, dtype=F64, generator=torch.Generator().manual_seed(2))
    weights = _weights(scene, 4, F64)
    results = []
    for fn in (rasterize_cpu_fast.rasterization, rasterization):
        background = bg.clone().requires_grad_()
        inputs = {k: scene[k].clone().requires_grad_() for k in PARAMS}
        colors, alphas, _ = fn(
            **{**scene, **inputs},
            backgrounds=background,
            render_mode="RGB+ED",
            rasterize_mode=rasterize_mode,
        )
        (torch.cat([colors, alphas], -1) * weights).sum().backward()
        results.append((colors, alphas, [inputs[k].grad for k in PARAMS] + [background.grad]))
    (fc, fa, fg), (rc, ra, rg) = results
    assert torch.allclose(fc, rc, rtol=1e-9, atol=1e-9) and torch.allclose(fa, ra, rtol=0, atol=1e-9)
    for name, fast, ref in zip(PARAMS + ("backgrounds",), fg, rg):
        assert ref.abs().max() > 0, name
        # 1e-4 relative per element; entries that cancel to ~0 get a floor of 1e-7 of the largest.
        assert torch.allclose(fast, ref, rtol=1e-4, atol=1e-7 * float(ref.abs().max())), name


def test_absgrad_matches_per_pixel_reference():
    width, height = 12, 9
    scene = make_scene(30, width, height, n_cams=1, sh_degree=0, dtype=F64, scale=0.1, seed=2)
    proj = project_gaussians(
        scene["means"], scene["quats"], scene["scales"], scene["viewmats"], scene["Ks"], width, height
    )
    feats = torch.rand(1, 30, 3, dtype=F64, generator=torch.Generator().manual_seed(4))
    opac = scene["opacities"][None]
    weights = torch.randn(1, height, width, 4, generator=torch.Generator().manual_seed(1), dtype=F64)
    means2d = proj.means2d.clone().requires_grad_()
    out, alpha = rasterize_to_pixels_cpu_fast(
        means2d, proj.conics, feats, opac, proj.depths, proj.radii, width, height, absgrad=True
    )
    (torch.cat([out, alpha], -1) * weights).sum().backward()

    expected = torch.zeros_like(proj.means2d)  # sum over pixels of |d(pixel's term)/d means2d|
    for y in range(height):
        for x in range(width):
            m2d = proj.means2d.clone().requires_grad_()
            o, a = rasterize_to_pixels_dense(m2d, proj.conics, feats, opac, proj.depths, proj.radii, width, height)
            (grad,) = torch.autograd.grad((torch.cat([o, a], -1)[:, y, x] * weights[:, y, x]).sum(), m2d)
            expected += grad.abs()
    assert float(expected.sum()) > 1.0
    assert torch.allclose(means2d.absgrad, expected, rtol=1e-9, atol=1e-12)
    assert (means2d.absgrad >= means2d.grad.abs() - 1e-12).all()
    assert (means2d.absgrad > means2d.grad.abs() + 1e-6).any()  # pixels do cancel somewhere


def test_empty_scenes():
    bg = torch.tensor([[0.2, 0.4, 0.6]])
    none = torch.zeros(1, 0)
    out, alpha = rasterize_to_pixels_cpu_fast(
        none.reshape(1, 0, 2),
        none.reshape(1, 0, 3),
        none.reshape(1, 0, 3),
        none,
        none,
        torch.zeros(1, 0, dtype=torch.int32),
        5,
        4,
        backgrounds=bg,
    )
    assert out.shape == (1, 4, 5, 3) and (alpha == 0).all() and (out == bg).all()

    scene = make_scene(30, 20, 16, n_cams=1, sh_degree=1)
    scene["means"][:, 2] = -2.0  # everything behind the camera
    means = scene["means"].clone().requires_grad_()
    colors, alphas, meta = rasterize_cpu_fast.rasterization(**{**scene, "means": means}, backgrounds=bg)
    (colors.sum() + alphas.sum()).backward()
    assert (meta["radii"] == 0).all() and (alphas == 0).all() and torch.allclose(colors, bg.expand_as(colors))
    assert (means.grad == 0).all()

    faint = make_scene(30, 20, 16, n_cams=1, sh_degree=1)
    faint["opacities"] = torch.full((30,), 0.5 * ALPHA_MIN)  # can never reach 1/255
    _, alphas, _ = rasterize_cpu_fast.rasterization(**faint)
    assert (alphas == 0).all()


def test_a_gaussian_is_listed_only_in_the_tiles_its_ellipse_reaches(monkeypatch):
    """A thin diagonal Gaussian's box covers a 4x4 block of tiles; only the tiles its
    ``alpha >= 1/255`` pixels are in get a list entry (its box's other tiles would composite
    nothing), and the render still equals the dense reference's."""
    size = 64
    means2d = torch.tensor([[[31.7, 32.2]]], dtype=F64)
    # Covariance with variances 200 along the diagonal and 0.3 across it: its box spans the image.
    rot = torch.tensor([[1.0, -1.0], [1.0, 1.0]], dtype=F64) / 2**0.5
    cov = rot @ torch.diag(torch.tensor([200.0, 0.3], dtype=F64)) @ rot.T
    inv = torch.linalg.inv(cov)
    conics = torch.stack([inv[0, 0], inv[0, 1], inv[1, 1]])[None, None]
    opacities = torch.tensor([[0.9]], dtype=F64)
    colors = torch.tensor([[[0.2, 0.5, 0.8]]], dtype=F64)
    depths = torch.ones(1, 1, dtype=F64)
    radii = torch.tensor([[32]], dtype=torch.int32)
    rasterize_cpu_fast.warm_up(F64)  # compiles the kernels before one is wrapped
    kernel, listed = rasterize_cpu_fast._forward_kernel, []

    def forward_kernel(*args):
        listed.append(args[1].copy())  # tile_start
        return kernel(*args)

    monkeypatch.setattr(rasterize_cpu_fast, "_forward_kernel", forward_kernel)
    args = (means2d, conics, colors, opacities, depths, radii, size, size)
    out, alpha = rasterize_to_pixels_cpu_fast(*args)
    tiles_listed = set(torch.nonzero(torch.from_numpy(listed[0]).diff() > 0).flatten().tolist())
    ys, xs = torch.meshgrid(torch.arange(size, dtype=F64) + 0.5, torch.arange(size, dtype=F64) + 0.5, indexing="ij")
    dx, dy = means2d[0, 0, 0] - xs, means2d[0, 0, 1] - ys
    a, b, c = conics[0, 0]
    reached = 0.9 * torch.exp(-(0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy)) >= ALPHA_MIN
    tiles_reached = {int(t) for t in torch.unique((ys[reached] // 16) * 4 + xs[reached] // 16)}
    assert tiles_listed == tiles_reached and len(tiles_reached) < 16
    dense_out, dense_alpha = rasterize_to_pixels_dense(*args)
    torch.testing.assert_close(out, dense_out)
    torch.testing.assert_close(alpha, dense_alpha)


def test_tile_lists_are_in_depth_order_per_tile(monkeypatch):
    """The parallel counting sort of the binning (records in chunks) gives every tile the list of
    the records with pixels in it in record (depth) order, each record its slots in tile order,
    and each slot the start of its pixels and the first and last row of its row spans in its tile:
    a plain per-record walk's lists, with two cameras."""
    scene = make_scene(400, 70, 50, n_cams=2, seed=5)
    rasterize_cpu_fast.warm_up(F32)  # compiles the kernels before one is wrapped
    calls = {}

    def recorded(name):
        stage = getattr(rasterize_cpu_fast, name)

        def call(*args):
            calls[name] = (args, stage(*args))
            return calls[name][1]

        monkeypatch.setattr(rasterize_cpu_fast, name, call)

    recorded("_row_spans")
    recorded("_bin_tiles")
    rasterize_cpu_fast.rasterization(**scene)
    row_start, spans = calls["_row_spans"][1]
    (boxes, entries, n_gauss, n_cams, tiles_x, tiles_y, box_start, pixels, _), got = calls["_bin_tiles"]
    lists = [[] for _ in range(n_cams * tiles_x * tiles_y)]
    per_record, sizes, rows = [], {}, {}
    for j in range(boxes.shape[0]):
        q, tiles = box_start[j], []
        for ty in range(boxes[j, 2] // TILE_SIZE, boxes[j, 3] // TILE_SIZE + 1):
            for tx in range(boxes[j, 0] // TILE_SIZE, boxes[j, 1] // TILE_SIZE + 1):
                if pixels[q] > 0:
                    tile = (entries[j] // n_gauss) * tiles_x * tiles_y + ty * tiles_x + tx
                    tiles.append(tile)
                    lists[tile].append(j)
                    sizes[(tile, j)] = pixels[q]
                    span_rows = [
                        py
                        for py in range(
                            max(boxes[j, 2], ty * TILE_SIZE), min(boxes[j, 3], ty * TILE_SIZE + TILE_SIZE - 1) + 1
                        )
                        if max(spans[row_start[j] + py - boxes[j, 2], 0], tx * TILE_SIZE)
                        <= min(spans[row_start[j] + py - boxes[j, 2], 1], tx * TILE_SIZE + TILE_SIZE - 1)
                    ]
                    rows[(tile, j)] = [span_rows[0], span_rows[-1]]
                q += 1
        per_record.append(tiles)
    tile_start, tile_items, rec_start, rec_slots, vis_start, slot_y = got
    assert (
        boxes.shape[0] > 4 * rasterize_cpu_lists._BIN_CHUNKS
        and len({t // (tiles_x * tiles_y) for t in sum(per_record, [])}) == 2
    )
    assert tile_start.tolist() == np.cumsum([0] + [len(items) for items in lists]).tolist()
    assert tile_items.tolist() == sum(lists, [])
    slots = [tile_start[t] + lists[t].index(j) for j, tiles in enumerate(per_record) for t in tiles]
    assert rec_start.tolist() == np.cumsum([0] + [len(tiles) for tiles in per_record]).tolist()
    assert rec_slots.tolist() == slots
    slot_sizes = [sizes[(t, j)] for t, items in enumerate(lists) for j in items]
    assert vis_start.tolist() == np.cumsum([0] + slot_sizes).tolist()
    assert slot_y.tolist() == [rows[(t, j)] for t, items in enumerate(lists) for j in items]
    box_rows = [
        min(boxes[j, 3], t % (tiles_x * tiles_y) // tiles_x * TILE_SIZE + TILE_SIZE - 1)
        for t, items in enumerate(lists)
        for j in items
    ]
    assert (slot_y[:, 1] < np.array(box_rows)).any()  # some slots' rows narrower than their box's in the tile


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_depth_sort_is_torchs_stable_argsort(dtype):
    """The radix sort on the keys' varying bits orders as ``torch.argsort(stable=True)``: ties in input
    order, -0.0 equal to 0.0, negatives before positives, keys spanning a few bits or all of them,
    a single key and keys that are all equal."""
    rng = np.random.default_rng(3)
    depths = rng.uniform(0.5, 6.0, 5000)
    depths[::7] = depths[3]
    signed = rng.normal(size=5000) * np.exp(rng.uniform(-30, 30, 5000))
    signed[::5], signed[1::5] = -0.0, 0.0
    close = 2.0 + np.arange(300) % 5 * np.spacing(np.float32(2.0))  # only the lowest mantissa bits differ
    cases = [depths, signed, close, rng.uniform(1, 2, 1), np.full(50, 1.5)]
    for keys in (k.astype(dtype) for k in cases):
        expected = torch.argsort(torch.from_numpy(keys), stable=True).numpy()
        assert np.array_equal(rasterize_cpu_lists._stable_argsort(keys), expected)


@pytest.mark.parametrize("hard", [False, True])
def test_pixel_boxes_lose_only_rows_and_columns_without_span_pixels(monkeypatch, hard):
    """The records' pixel boxes are the radius's boxes (pixel_bounds) cut to the lenient ellipse's extent:
    the row spans from them hold every pixel those of the radius's boxes hold, pixel for pixel, from fewer
    box rows (the hard scene: collapsed, huge, saturated, faint, needle-like and near-plane Gaussians)."""
    scene = make_scene(300, 70, 50, hard=hard, seed=3)
    rasterize_cpu_fast.warm_up(F32)
    calls = {}
    make_records = rasterize_cpu_fast._make_records

    def recorded(*args):
        calls["args"], calls["out"] = args, make_records(*args)
        return calls["out"]

    monkeypatch.setattr(rasterize_cpu_fast, "_make_records", recorded)
    rasterize_cpu_fast.rasterization(**scene)
    entries, means2d, _, _, _, radii_f, _, width, height = calls["args"]
    records, boxes = calls["out"]
    radius_boxes = pixel_bounds(
        torch.from_numpy(means2d[entries]), torch.from_numpy(radii_f[entries]).long(), width, height
    ).numpy()
    finite = np.isfinite(records[:, :5]).all(1) & np.isfinite(radii_f[entries])
    radius_boxes[~finite] = (0, -1, 0, -1)
    ys = np.arange(height, dtype=np.float32) + 0.5

    def span_pixels(box_set):
        row_start, spans = rasterize_cpu_fast._row_spans(records, box_set, ys)
        return {
            (j, py, px)
            for j in range(len(box_set))
            for py in range(box_set[j, 2], box_set[j, 3] + 1)
            for px in range(
                spans[row_start[j] + py - box_set[j, 2], 0], spans[row_start[j] + py - box_set[j, 2], 1] + 1
            )
        }

    rows = lambda b: int(np.maximum(b[:, 3] - b[:, 2] + 1, 0).sum())  # noqa: E731
    inside = (boxes[:, 0] >= radius_boxes[:, 0]) & (boxes[:, 1] <= radius_boxes[:, 1])
    inside &= (boxes[:, 2] >= radius_boxes[:, 2]) & (boxes[:, 3] <= radius_boxes[:, 3])
    assert (inside | (boxes[:, 1] < boxes[:, 0])).all()
    assert span_pixels(boxes) == span_pixels(radius_boxes) and len(span_pixels(boxes)) > 1000
    assert rows(boxes) < 0.8 * rows(radius_boxes)


def test_results_do_not_depend_on_the_thread_count():
    scene = make_scene(300, 70, 50, seed=7)
    weights = _weights(scene, 3, F32)
    before = numba.get_num_threads()
    runs = []
    try:
        for threads in (1, 2):
            numba.set_num_threads(threads)
            runs.append(render_and_grads(rasterize_cpu_fast.rasterization, scene, weights, absgrad=True))
    finally:
        numba.set_num_threads(before)
    (c1, a1, g1, m1), (c2, a2, g2, m2) = runs
    assert torch.equal(c1, c2) and torch.equal(a1, a2)
    assert all(torch.equal(g1[k], g2[k]) for k in PARAMS)
    assert torch.equal(m1["means2d"].absgrad, m2["means2d"].absgrad)


def test_interleaved_renders_and_retained_graphs():
    """A render whose graph is retained keeps its scratch memory while other renders run."""
    scenes = [make_scene(200, 40, 30, seed=seed) for seed in (8, 9)]
    weights = [_weights(sc, 3, F32) for sc in scenes]
    alone = [render_and_grads(rasterize_cpu_fast.rasterization, sc, w)[2] for sc, w in zip(scenes, weights)]
    inputs = [{k: sc[k].clone().requires_grad_() for k in PARAMS} for sc in scenes]

    def loss(i):
        colors, alphas, _ = rasterize_cpu_fast.rasterization(**{**scenes[i], **inputs[i]})
        return (torch.cat([colors, alphas], -1) * weights[i]).sum()

    first = loss(0)
    first.backward(retain_graph=True)
    second = loss(1)  # renders while the first graph is still alive
    first.backward()  # the retained graph again: the same gradients once more
    second.backward()
    for k in PARAMS:
        assert torch.allclose(inputs[0][k].grad, 2 * alone[0][k], rtol=1e-6, atol=0), k
        assert torch.equal(inputs[1][k].grad, alone[1][k]), k


def test_backward_without_the_forward_store_gives_the_same_results(monkeypatch):
    """Beyond VIS_STORE_MAX the backward recomputes exp(-sigma) instead of reading the forward's."""
    scene = make_scene(300, 50, 40, seed=6, hard=True)
    weights = _weights(scene, 4, F32)
    kwargs = dict(render_mode="RGB+ED", absgrad=True)
    stored = render_and_grads(rasterize_cpu_fast.rasterization, scene, weights, **kwargs)
    monkeypatch.setattr(rasterize_cpu_fast, "VIS_STORE_MAX", 0)
    kernel, store_sizes = rasterize_cpu_fast._forward_kernel, []

    def forward_kernel(*args):
        store_sizes.append(args[-1].size)  # vis_store
        return kernel(*args)

    monkeypatch.setattr(rasterize_cpu_fast, "_forward_kernel", forward_kernel)
    recomputed = render_and_grads(rasterize_cpu_fast.rasterization, scene, weights, **kwargs)
    assert store_sizes == [0]  # the fallback ran
    assert torch.equal(stored[0], recomputed[0]) and torch.equal(stored[1], recomputed[1])
    assert all(torch.equal(stored[2][k], recomputed[2][k]) for k in PARAMS)
    assert torch.equal(stored[3]["means2d"].absgrad, recomputed[3]["means2d"].absgrad)


def test_exp_f32_is_within_two_ulp():
    """The 8-wide kernels' float32 exp against float64's, over the range alphas come from."""

    @numba.njit
    def exp_all(x):
        out = np.empty_like(x)
        for i in range(x.shape[0]):
            out[i] = rasterize_cpu_kernels._exp_f32(x[i])
        return out

    x = np.linspace(-80.0, 0.0, 1_000_003, dtype=np.float32)
    ref = np.exp(x.astype(np.float64))
    ulp = np.spacing(ref.astype(np.float32)).astype(np.float64)
    assert float((np.abs(exp_all(x) - ref) / ulp).max()) <= 2.0


def test_float32_rgb_takes_the_8_wide_kernels_and_matches_the_generic_ones(monkeypatch):
    """Training renders (float32 RGB) with wide enough row spans composite 8 pixels at a time in
    float32; lists too long for its float32 entry counts take the generic kernels (float64
    transmittance). Both agree to float32 rounding, image-edge tiles (61x45) included."""
    scene = make_scene(400, 61, 45, hard=True, seed=4)
    weights = _weights(scene, 3, F32)
    bg = torch.rand(2, 3, generator=torch.Generator().manual_seed(5))
    rasterize_cpu_fast.warm_up(F32)  # compiled before the kernels are wrapped
    calls = []
    for name in ("_forward_kernel_rgb32", "_forward_kernel"):
        kernel = getattr(rasterize_cpu_fast, name)
        monkeypatch.setattr(rasterize_cpu_fast, name, lambda *a, k=kernel, n=name: (calls.append(n), k(*a))[1])
    kwargs = dict(backgrounds=bg, absgrad=True)
    monkeypatch.setattr(rasterize_cpu_fast, "RGB32_MIN_RUN", 0.0)
    fast = render_and_grads(rasterize_cpu_fast.rasterization, scene, weights, **kwargs)
    monkeypatch.setattr(rasterize_cpu_fast, "_MAX_LAST_F32", 0)
    generic = render_and_grads(rasterize_cpu_fast.rasterization, scene, weights, **kwargs)
    assert calls == ["_forward_kernel_rgb32", "_forward_kernel"]
    (fc, fa, fg, fmeta), (gc, ga, gg, gmeta) = fast, generic
    assert (fc - gc).abs().max() <= 1e-5 and (fa - ga).abs().max() <= 1e-5
    for k in PARAMS:
        assert rel_err(fg[k], gg[k]) <= 1e-4, k
    assert rel_err(fmeta["means2d"].absgrad, gmeta["means2d"].absgrad) <= 1e-4


def test_narrow_row_spans_take_the_generic_kernels():
    """Row spans of a few pixels leave most of the 8 lanes idle: the generic kernels do them."""
    tile_start = np.array([0, 2, 3])
    slot_y = np.array([[0, 3], [5, 5], [2, 4]])  # 4 + 1 + 3 = 8 (entry, tile row) pairs
    wide = np.array([0, 30, 36, 50])  # 50 span pixels: 6.25 per row
    narrow = np.array([0, 20, 24, 30])  # 30: 3.75 per row
    assert rasterize_cpu_fast._spans_suit_lanes(tile_start, wide, slot_y)
    assert not rasterize_cpu_fast._spans_suit_lanes(tile_start, narrow, slot_y)
    assert not rasterize_cpu_fast._spans_suit_lanes(np.array([0]), np.array([0]), np.zeros((0, 2), np.int64))


def test_half_precision_is_refused():
    x = torch.zeros(1, 1, 3, dtype=torch.float16)
    radii = torch.ones(1, 1, dtype=torch.int32)
    with pytest.raises(ValueError, match="float32/float64"):
        rasterize_to_pixels_cpu_fast(x[..., :2], x, x, x[..., 0], x[..., 0], radii, 4, 4)


def _train(rasterizer, toy_scene, steps=30):
    """``steps`` of splatfacto training (with densification) on the toy scene; returns the model
    and its last loss."""
    from naka_gs_plugin.data.images import read_rgb
    from naka_gs_plugin.data.lowlight_dataparser import LowLightDataParserConfig
    from naka_gs_plugin.model.naka_gs_model import NakaGSModelConfig

    out = LowLightDataParserConfig(data=toy_scene, downscale_factor=1).setup().get_dataparser_outputs("train")
    cameras = out.cameras
    images = [torch.from_numpy(read_rgb(p)) for p in out.image_filenames]
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    xyz = (torch.rand(250, 3, generator=g) - 0.5) * 1.2
    rgb = (torch.rand(250, 3, generator=g) * 255).to(torch.uint8)
    cfg = NakaGSModelConfig(
        sh_degree=1,
        rasterizer=rasterizer,
        warmup_length=2,
        refine_every=6,
        densify_grad_thresh=1e-4,
        densify_size_thresh=0.02,
        reset_alpha_every=100,
    )
    box = SceneBox(aabb=torch.tensor([[-1.0, -1, -1], [1, 1, 1]]))
    model = cfg.setup(scene_box=box, num_train_data=len(images), seed_points=(xyz, rgb))
    counts = []
    loss = train_steps(model, cameras, images, steps, after_step=lambda _: counts.append(model.num_points))
    return model, float(loss), counts


def test_training_matches_torch_path(toy_scene):
    fast, fast_loss, fast_counts = _train("cpu-fast", toy_scene)
    ref, ref_loss, ref_counts = _train("torch", toy_scene)
    assert fast._backend_logged == "cpu-fast" and ref._backend_logged == "torch"
    assert len(set(ref_counts)) > 1, "densification never changed the Gaussian count"
    # Same Gaussians after every step: densification saw the same gradients and radii.
    assert fast_counts == ref_counts
    # Both are float32 and differ per step by summation order only (~1e-6 relative, see
    # test_float32_matches_torch_path); 30 Adam steps (whose update direction is the gradient's sign
    # for tiny gradients) amplify that, but not beyond 1e-3 of the loss.
    assert abs(fast_loss - ref_loss) <= 1e-3 * ref_loss
    for k, p in ref.gauss_params.items():
        assert rel_err(fast.gauss_params[k].data, p.data) <= 1e-2, k


def test_first_render_keeps_pytorch_thread_count():
    """numba's OpenMP pool starts on the first cpu-fast render and shares the runtime with PyTorch;
    a fresh process that asked PyTorch for one thread must still have one afterwards."""
    import subprocess
    import sys

    code = (
        "import torch; torch.set_num_threads(1)\n"
        "from naka_gs_plugin.model.rasterize_cpu_fast import warm_up\n"
        "warm_up(torch.float32); print(torch.get_num_threads())\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip().splitlines()[-1] == "1"


@pytest.fixture
def no_kernels_yet(monkeypatch):
    """This process as if nothing were compiled nor on disk, with no background compile started (the kernels
    compiled in fact, so that a render that did not wait would finish before a child that sleeps)."""
    rasterize_cpu_fast.warm_up(F32)
    monkeypatch.setattr(compile_ahead, "_READY", {})
    monkeypatch.setattr(compile_ahead, "_BACKGROUND", {})
    monkeypatch.setattr(compile_ahead, "kernels_on_disk", lambda: False)


def _child(monkeypatch, code):
    import sys

    monkeypatch.setattr(compile_ahead, "BACKGROUND_COMMAND", (sys.executable, "-c", code))


def test_first_render_waits_for_the_background_compile(no_kernels_yet, monkeypatch, tmp_path):
    """One child at a time; the first render of float32 starts only once it has finished."""
    done = tmp_path / "done"
    _child(monkeypatch, f"import time, pathlib; time.sleep(1.0); pathlib.Path({str(done)!r}).touch()")
    assert compile_ahead.compile_in_background()
    assert not compile_ahead.compile_in_background()  # the first is still running
    rasterize_cpu_fast.warm_up(F32)
    assert done.exists()
    assert not compile_ahead.compile_in_background()  # float32 is ready in this process now


def test_a_failed_background_compile_is_said_and_the_render_compiles(no_kernels_yet, monkeypatch):
    logged = []
    monkeypatch.setattr(compile_ahead.CONSOLE, "log", lambda message, **_: logged.append(message))
    _child(monkeypatch, "raise SystemExit(3)")
    assert compile_ahead.compile_in_background()
    assert rasterize_cpu_fast.warm_up(F32) > 0
    assert any(m.endswith("background compile failed (exit code 3); compiling here") for m in logged), logged
    assert F32 in compile_ahead._READY


def test_no_background_compile_when_the_training_kernels_are_on_disk(monkeypatch):
    """After :func:`warm_training_kernels` (what the child runs) every training kernel is in numba's disk
    cache, and a new process would start no child."""
    rasterize_cpu_fast.warm_training_kernels()
    assert compile_ahead.kernels_on_disk()
    monkeypatch.setattr(compile_ahead, "_READY", {})
    monkeypatch.setattr(compile_ahead, "_BACKGROUND", {})
    assert not compile_ahead.compile_in_background()


def test_the_background_child_imports_this_checkout_whatever_its_working_directory(tmp_path):
    """A copy of the package in the child's working directory (a clone, a worktree) is not the one it compiles."""
    import subprocess
    import sys

    shadow = tmp_path / "naka_gs_plugin" / "model"
    shadow.mkdir(parents=True)
    for folder in (shadow.parent, shadow):
        (folder / "__init__.py").write_text("")
    (shadow / "rasterize_cpu_fast.py").write_text("")
    code = compile_ahead.child_code("print(m.__file__)")
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == rasterize_cpu_fast.__file__


def test_the_block_beside_the_child_runs_on_one_thread_fewer(no_kernels_yet, monkeypatch):
    """Two usable CPUs: the child takes one, the block the other, and the block gets both back at its first
    reclaim_core once the child has exited; without a child the block keeps its threads."""
    import naka_gs_plugin.cpu as cpu

    for module in (compile_ahead, cpu):
        monkeypatch.setattr(module, "usable_cpus", lambda: (2, "test"))
    _child(monkeypatch, "import time; time.sleep(0.5)")
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        with compile_ahead.compiling_in_background() as started:
            assert started
            assert torch.get_num_threads() == 1
            compile_ahead._BACKGROUND[F32].wait()
            cpu.reclaim_core()
            assert torch.get_num_threads() == 2
        assert torch.get_num_threads() == 2
        rasterize_cpu_fast.warm_up(F32)  # waits for the child
        with compile_ahead.compiling_in_background() as started:
            assert not started  # float32 is ready in this process now
            assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(threads)


def test_no_background_compile_on_a_single_usable_cpu(no_kernels_yet, monkeypatch):
    """On one CPU the child would only take turns with the enhancement."""
    monkeypatch.setattr(compile_ahead, "usable_cpus", lambda: (1, "CPU affinity"))
    assert not compile_ahead.compile_in_background()
