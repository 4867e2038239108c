"""Compiled CPU tile rasterizer ("cpu-fast"): numba kernels with a hand-written backward.

Same interface, conventions and results as :mod:`naka_gs_plugin.model.rasterize` (gsplat 1.4.0
``rasterization``, unpacked, pinhole). Every stage is compiled: projection and SH colours
(:mod:`~naka_gs_plugin.model.project_cpu_fast`, float64 inside, so float32 results are the float64
reference's rounded, within rounding of the torch path's float32 arithmetic), the depth sort (a
stable radix sort), the tile binning, compositing and its backward, and the per-Gaussian reduction.

Layout (as gsplat's CUDA path): the image is cut into 16x16 tiles. On each row of its pixel box
(:func:`~naka_gs_plugin.model.projection.pixel_bounds`) a visible Gaussian (``radius > 0``,
``opacity >= 1/255``) visits only the columns of its lenient ``alpha >= 1/255`` ellipse (the torch
path's enumeration), computed once per row before the kernels; it is listed, in stable depth order,
in each tile those row spans reach (not every tile of its box: for trained scenes two thirds of
those would composite nothing). Unlike gsplat, which evaluates every Gaussian of a tile, a Gaussian
only touches the pixels of its spans, so exactly the pairs of the torch path are composited.
Forward (``prange`` over tiles): front to back with ``alpha = min(0.999, opacity * exp(-sigma))``,
pairs with ``sigma < 0`` or ``alpha < 1/255`` skipped, a pixel stops *before* the pair that would
bring its transmittance to ``<= 1e-4``; transmittance is carried in float64 and the final
transmittance and the number of list entries up to the last contributing one are stored per pixel.
Backward (``prange`` over tiles): each pixel's list is walked back to front from that last entry,
recovering the transmittance by division (and reusing the ``exp(-sigma)`` the forward stored, one
per span pixel, up to ``VIS_STORE_MAX``), with the gradients for 2D means (and their per-pixel
absolute values, gsplat's ``absgrad``), conics, opacities and colours summed per (tile, list
entry) slot; a pass parallel over Gaussians then adds each one's slots up in tile order, so there
are no races and the result does not depend on the thread count.

In these generic kernels ``sigma`` and ``alpha`` are computed in the inputs' dtype,
operation for operation as the torch path (so the same pairs pass the 1/255 test, and the
backward re-derives exactly the forward's alphas); gradients accumulate in float64. No
``fastmath``: contraction into FMAs or approximate ``exp`` would let the forward, the backward and
the torch path disagree on pairs at the thresholds. They are the reference for the float32 RGB
kernels that training renders take when their row spans are wide enough (``RGB32_MIN_RUN``):
:func:`_forward_kernel_rgb32` and :func:`_backward_kernel_rgb32` evaluate 8 pixels of a tile row
as one vector, in float32 throughout (gsplat's CUDA precision) with a vectorisable ``exp``; both
derive bitwise the same alphas from each other, and agree with the generic kernels to float32
rounding. Kernels are compiled on first use per dtype
(tens of seconds) and cached on disk by numba (``cache=True``: next to this file, or under
``NUMBA_CACHE_DIR`` / the user cache directory when the package directory is not writable); the
first call logs how long the compile or cache load took. The naka-gs pipeline starts the float32
kernels' compile in a child process before it enhances the training images, on one thread fewer until the
child exits (:func:`compiling_in_background`), so that on a first run the two overlap. ``numba.set_num_threads`` sets the
number of threads.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from functools import partial
from pathlib import Path
from typing import Dict, Iterator, Literal, Optional, Set, Tuple, Union

import numba
import numpy as np
import torch
from jaxtyping import Float, Int
from llvmlite import ir
from numba import njit, prange, types
from numba.extending import intrinsic
from rich.console import Console
from torch import Tensor

from naka_gs_plugin.cpu import core_lent, torch_threads_kept, untraced, usable_cpus
from naka_gs_plugin.model.project_cpu_fast import (
    _project_backward,
    _project_forward,
    _sh_backward,
    _sh_forward,
    project_gaussians,
    sh_colors,
)
from naka_gs_plugin.model.rasterize import (
    _ENUM_SLACK,
    ALPHA_MAX,
    ALPHA_MIN,
    TILE_SIZE,
    TRANSMITTANCE_MIN,
    RenderMode,
    rasterization_with_compositor,
)

CONSOLE = Console(width=120)
"""rich's console, as nerfstudio's (this module imports without nerfstudio, e.g. on the GPU machine)."""

VIS_STORE_MAX = 1 << 27
"""Most ``exp(-sigma)`` values (one per row-span pixel of each list entry; ~1.4x the composited
pairs for trained-scene-like Gaussians) the forward keeps for the backward (512 MB in float32);
beyond, the backward recomputes them (slower, same results)."""

_BIN_CHUNKS = 16
"""Chunks of records :func:`_bin_tiles` bins in parallel (the lists do not depend on it)."""

N_GRAD = 8
"""Per-Gaussian gradient columns before the colours: d means2d (2), |d means2d| (2), d conics (3),
d opacity (1)."""

REC_COLORS = 8
"""Record layout per visible entry, in the inputs' dtype: mean x, y (0, 1), conic a, b, c (2..4),
opacity (5), the lenient ellipse's level and conic determinant (6, 7; :func:`_ellipse_level`),
colours (8..). The pixel boxes are a separate int64 array."""


_SORT_DIGIT_BITS = 12
"""Widest digit of :func:`_stable_argsort`: its counts (4,097 int64) stay in L1."""


@njit(cache=True)
def _stable_argsort(keys):
    """Stable argsort of finite floats: LSD radix sort on their float64 bits mapped to order-preserving
    unsigned integers. Only the bits that differ between keys are sorted on (float32 keys have 29 zero
    low bits; depths in a scene share their sign and most of their exponent), split evenly into digits
    of at most ``_SORT_DIGIT_BITS``; every digit's counts come from one pass, and each scatter moves the
    keys with their indices (sequential reads). Gives ``torch.argsort(stable=True)``'s order."""
    n = keys.shape[0]
    bits = (keys.astype(np.float64) + 0.0).view(np.uint64)  # + 0.0: -0.0 becomes 0.0, its equal
    sign = np.uint64(1) << np.uint64(63)
    all_and, all_or = ~np.uint64(0), np.uint64(0)
    for i in range(n):
        b = ~bits[i] if bits[i] & sign else bits[i] | sign
        bits[i] = b
        all_and &= b
        all_or |= b
    order = np.arange(n)
    varying = all_and ^ all_or
    if varying == 0:
        return order
    lo, hi = 0, 63
    while not (varying >> np.uint64(lo)) & np.uint64(1):
        lo += 1
    while not (varying >> np.uint64(hi)) & np.uint64(1):
        hi -= 1
    n_digits = (hi - lo + _SORT_DIGIT_BITS) // _SORT_DIGIT_BITS
    width = (hi - lo + n_digits) // n_digits
    mask = (np.uint64(1) << np.uint64(width)) - np.uint64(1)
    counts = np.zeros((n_digits, (1 << width) + 1), dtype=np.int64)
    for i in range(n):
        b = bits[i] >> np.uint64(lo)
        for d in range(n_digits):
            counts[d, np.int64((b >> np.uint64(d * width)) & mask) + 1] += 1
    keys_in, keys_out = bits, np.empty(n, dtype=np.uint64)
    scratch = np.empty(n, dtype=np.int64)
    for d in range(n_digits):
        starts = counts[d]
        for j in range(starts.shape[0] - 1):
            starts[j + 1] += starts[j]
        sh = np.uint64(lo + d * width)
        for i in range(n):
            b = keys_in[i]
            q = np.int64((b >> sh) & mask)
            p = starts[q]
            starts[q] = p + 1
            keys_out[p] = b
            scratch[p] = order[i]
        order, scratch = scratch, order
        keys_in, keys_out = keys_out, keys_in
    return order


@njit(cache=True)
def _visible_by_depth(radii, opacities, depths, alpha_min):
    """Flat (camera, Gaussian) indices with ``radius > 0`` and ``opacity >= 1/255``, stable-sorted
    by depth (the torch path's order; ``alpha_min`` is 1/255 in the inputs' dtype, as torch compares)."""
    flat_radii, flat_opac, flat_depths = radii.ravel(), opacities.ravel(), depths.ravel()
    entries = np.nonzero((flat_radii > 0) & (flat_opac >= alpha_min))[0]
    return entries[_stable_argsort(flat_depths[entries])]


@njit(parallel=True, cache=True)
def _make_records(entries, means2d, conics, opacities, colors, radii_f, consts, width, height):
    """Records (see ``REC_COLORS``) of the sorted entries and their pixel boxes
    (:func:`~naka_gs_plugin.model.projection.pixel_bounds`, evaluated in the inputs' dtype as there:
    ``consts`` = (0.5, ALPHA_MAX, ALPHA_MIN, 0) in that dtype). Inputs are flat [C*N, ...].

    The box is then narrowed to the rows and columns its lenient ellipse can reach (:func:`_ellipse_box`),
    as the torch path's enumeration narrows its rows: on a trained scene about half the rows of the radius's
    box have an empty row span, and every list stage walks a box row by row and tile by tile. Only rows and
    columns without a span pixel go, so the lists and every render are the same bits.

    An entry with a non-finite centre, radius or conic, or whose box misses the image, gets the
    empty box (0, -1, 0, -1): it covers no tile, so it is culled (a reversed box would index out of
    bounds: absurd cameras and diverged Gaussians must not crash the process)."""
    n_dim = colors.shape[1]
    records = np.empty((entries.shape[0], REC_COLORS + n_dim), dtype=means2d.dtype)
    boxes = np.empty((entries.shape[0], 4), dtype=np.int64)
    for j in prange(entries.shape[0]):
        e = entries[j]
        mx, my, r = means2d[e, 0], means2d[e, 1], radii_f[e]
        records[j, 0], records[j, 1] = mx, my
        records[j, 2], records[j, 3], records[j, 4] = conics[e, 0], conics[e, 1], conics[e, 2]
        records[j, 5] = opacities[e]
        records[j, 6], records[j, 7] = _ellipse_level(conics[e, 0], conics[e, 1], conics[e, 2], opacities[e])
        for d in range(n_dim):
            records[j, REC_COLORS + d] = colors[e, d]
        boxes[j, 0], boxes[j, 1], boxes[j, 2], boxes[j, 3] = 0, -1, 0, -1
        finite = np.isfinite(mx) and np.isfinite(my) and np.isfinite(r)
        if finite and np.isfinite(conics[e, 0]) and np.isfinite(conics[e, 1]) and np.isfinite(conics[e, 2]):
            x0, x1, y0, y1 = _ellipse_box(
                records[j],
                max(np.ceil(mx - r - consts[0]), consts[3]),
                min(np.floor(mx + r - consts[0]), width - 1),
                max(np.ceil(my - r - consts[0]), consts[3]),
                min(np.floor(my + r - consts[0]), height - 1),
            )
            if x0 <= x1 and y0 <= y1:
                boxes[j, 0], boxes[j, 1], boxes[j, 2], boxes[j, 3] = x0, x1, y0, y1
    return records, boxes


_BOX_MARGIN = 1e-6
"""Relative margin of :func:`_ellipse_box`'s half-extents (plus as much in pixels): far above the float64
rounding of :func:`_row_span` and the float32 rounding of ``mean - pixel centre`` it is fed."""


@njit(cache=True, inline="always")
def _ellipse_box(rec, x0, x1, y0, y1):
    """Integer pixel box ``(x0, x1, y0, y1)`` of the radius's box (pixel_bounds, given as floats) cut to the
    columns and rows whose centres lie within the lenient ellipse's half-extents ``sqrt(2 level c / det)``
    and ``sqrt(2 level a / det)`` of the record's centre, widened by ``_BOX_MARGIN``: every pixel with a
    row span (:func:`_row_span`, from the same stored ``level`` and ``det``) stays inside. Degenerate
    conics keep the radius's box, as ``_row_span`` falls back to it."""
    a, c = np.float64(rec[2]), np.float64(rec[4])
    level, det = np.float64(rec[6]), np.float64(rec[7])
    if rec[2] > 0 and det > 0 and level < np.inf:
        both = 2.0 * max(level, 0.0) / det
        half_w = np.sqrt(both * c) * (1.0 + _BOX_MARGIN) + _BOX_MARGIN
        half_h = np.sqrt(both * a) * (1.0 + _BOX_MARGIN) + _BOX_MARGIN
        mx, my = np.float64(rec[0]), np.float64(rec[1])
        x0, x1 = max(x0, np.ceil(mx - half_w - 0.5)), min(x1, np.floor(mx + half_w - 0.5))
        y0, y1 = max(y0, np.ceil(my - half_h - 0.5)), min(y1, np.floor(my + half_h - 0.5))
    return np.int64(x0), np.int64(x1), np.int64(y0), np.int64(y1)


@njit(parallel=True, cache=True)
def _row_spans(records, boxes, ys):
    """Per record and row of its box, the columns ``[lo, hi]`` of its lenient ellipse
    (:func:`_row_span`, image columns; ``lo > hi``: none), in ``spans[row_start[j] + py - y_lo]``."""
    n = boxes.shape[0]
    row_start = np.zeros(n + 1, dtype=np.int64)
    for j in range(n):
        row_start[j + 1] = row_start[j] + max(boxes[j, 3] - boxes[j, 2] + 1, 0)
    spans = np.empty((row_start[n], 2), dtype=np.int32)
    for j in prange(n):
        rec = records[j]
        mx, my, a, b = rec[0], rec[1], rec[2], rec[3]
        level, det = np.float64(rec[6]), np.float64(rec[7])
        for py in range(boxes[j, 2], boxes[j, 3] + 1):
            lo, hi = _row_span(my - ys[py], mx, a, b, level, det, boxes[j, 0], boxes[j, 1])
            q = row_start[j] + py - boxes[j, 2]
            spans[q, 0], spans[q, 1] = lo, max(hi, lo - 1)
    return row_start, spans


@njit(parallel=True, cache=True)
def _tile_pixels(boxes, row_start, spans):
    """Per record and tile of its box (row-major), how many of its row-span pixels fall in the tile,
    and the first and last image row holding them (``rows``, meaningful where pixels > 0);
    ``box_start[j]`` is record ``j``'s first."""
    n = boxes.shape[0]
    box_start = np.zeros(n + 1, dtype=np.int64)
    for j in range(n):
        box_start[j + 1] = box_start[j] + (boxes[j, 1] // TILE_SIZE - boxes[j, 0] // TILE_SIZE + 1) * (
            boxes[j, 3] // TILE_SIZE - boxes[j, 2] // TILE_SIZE + 1
        )
    pixels = np.zeros(box_start[n], dtype=np.int64)
    rows = np.empty((box_start[n], 2), dtype=np.int64)
    for j in prange(n):
        tx0, tx1 = boxes[j, 0] // TILE_SIZE, boxes[j, 1] // TILE_SIZE
        for py in range(boxes[j, 2], boxes[j, 3] + 1):
            q = row_start[j] + py - boxes[j, 2]
            lo, hi = np.int64(spans[q, 0]), np.int64(spans[q, 1])
            if lo > hi:
                continue
            band = box_start[j] + (py // TILE_SIZE - boxes[j, 2] // TILE_SIZE) * (tx1 - tx0 + 1)
            for tx in range(lo // TILE_SIZE, hi // TILE_SIZE + 1):
                q = band + tx - tx0
                if pixels[q] == 0:
                    rows[q, 0] = py
                rows[q, 1] = py
                pixels[q] += min(hi, tx * TILE_SIZE + TILE_SIZE - 1) - max(lo, tx * TILE_SIZE) + 1
    return box_start, pixels, rows


@njit(parallel=True, cache=True)
def _bin_tiles(boxes, entries, n_gauss, n_cams, tiles_x, tiles_y, box_start, pixels, rows):
    """CSR lists, per tile, of the record indices whose lenient ellipse has a pixel in it (a row
    span of :func:`_row_spans`; the tiles its box only grazes would composite nothing), in record
    (depth) order; per record the list (slot) positions it got, in increasing tile order; per
    slot the start of its pixels in the forward's ``exp(-sigma)`` store (``vis_start``) and the
    first and last image row of its pixels in its tile (``slot_y``: the kernels visit only those
    rows; the box's other rows in the tile have empty spans there, about two fifths of them).

    A counting sort, parallel over ``_BIN_CHUNKS`` contiguous chunks of records: each chunk counts
    its records per tile, then fills its own part of every tile's list, which starts after the
    earlier chunks' parts; so each list is in record order, whatever the chunking and threads."""
    n_rec = boxes.shape[0]
    tiles_per_cam = tiles_x * tiles_y
    n_tiles = n_cams * tiles_per_cam
    n_chunks = min(_BIN_CHUNKS, max(n_rec, 1))
    per_chunk = (n_rec + n_chunks - 1) // n_chunks
    chunk_counts = np.zeros((n_chunks, n_tiles), dtype=np.int64)
    rec_counts = np.zeros(n_rec + 1, dtype=np.int64)
    for chunk in prange(n_chunks):
        for j in range(chunk * per_chunk, min((chunk + 1) * per_chunk, n_rec)):
            base = (entries[j] // n_gauss) * tiles_per_cam
            tx0, tx1 = boxes[j, 0] // TILE_SIZE, boxes[j, 1] // TILE_SIZE
            q = box_start[j]
            for ty in range(boxes[j, 2] // TILE_SIZE, boxes[j, 3] // TILE_SIZE + 1):
                for tx in range(tx0, tx1 + 1):
                    if pixels[q] > 0:
                        chunk_counts[chunk, base + ty * tiles_x + tx] += 1
                        rec_counts[j + 1] += 1
                    q += 1
    rec_start = np.cumsum(rec_counts)
    tile_start = np.empty(n_tiles + 1, dtype=np.int64)
    fill = np.empty((n_chunks, n_tiles), dtype=np.int64)
    total = 0
    for tile in range(n_tiles):
        tile_start[tile] = total
        for chunk in range(n_chunks):
            fill[chunk, tile] = total
            total += chunk_counts[chunk, tile]
    tile_start[n_tiles] = total
    tile_items = np.empty(total, dtype=np.int32)
    rec_slots = np.empty(total, dtype=np.int64)
    vis_start = np.zeros(total + 1, dtype=np.int64)
    slot_y = np.empty((total, 2), dtype=np.int64)
    for chunk in prange(n_chunks):
        for j in range(chunk * per_chunk, min((chunk + 1) * per_chunk, n_rec)):
            base = (entries[j] // n_gauss) * tiles_per_cam
            tx0, tx1 = boxes[j, 0] // TILE_SIZE, boxes[j, 1] // TILE_SIZE
            q, slot = box_start[j], rec_start[j]
            for ty in range(boxes[j, 2] // TILE_SIZE, boxes[j, 3] // TILE_SIZE + 1):
                for tx in range(tx0, tx1 + 1):
                    if pixels[q] > 0:
                        tile = base + ty * tiles_x + tx
                        k = fill[chunk, tile]
                        tile_items[k] = j
                        rec_slots[slot] = k
                        vis_start[k + 1] = pixels[q]
                        slot_y[k, 0], slot_y[k, 1] = rows[q, 0], rows[q, 1]
                        fill[chunk, tile] = k + 1
                        slot += 1
                    q += 1
    for k in range(total):
        vis_start[k + 1] += vis_start[k]
    return tile_start, tile_items, rec_start, rec_slots, vis_start, slot_y


@njit(parallel=True, cache=True)
def _gather_rows(records, tile_items, row_start, boxes):
    """``records[tile_items]``: one record per list slot, so that each tile reads its list from
    contiguous memory (scattered reads of depth-ordered records made the kernels ~25 % slower); and per
    slot the position of its record's image row 0 in ``spans`` (``row_start - box row 0``)."""
    out = np.empty((tile_items.shape[0], records.shape[1]), dtype=records.dtype)
    slot_rows = np.empty(tile_items.shape[0], dtype=np.int64)
    for k in prange(tile_items.shape[0]):
        j = tile_items[k]
        for col in range(records.shape[1]):
            out[k, col] = records[j, col]
        slot_rows[k] = row_start[j] - boxes[j, 2]
    return out, slot_rows


@njit(cache=True, inline="always")
def _alpha(dx, dy, a, b, c, opacity, consts):
    """``(vis, raw, alpha)`` of one pair in the inputs' dtype; ``alpha = 0`` when skipped.

    ``consts`` = (0.5, ALPHA_MAX, ALPHA_MIN, 0) in that dtype, so that nothing is promoted to float64
    and the arithmetic is the torch path's, operation for operation.
    """
    sigma = consts[0] * (a * dx * dx + c * dy * dy) + b * dx * dy
    vis = np.exp(-sigma)
    raw = opacity * vis
    alpha = min(raw, consts[1])
    if sigma < 0 or alpha < consts[2]:
        alpha = consts[3]
    return vis, raw, alpha


@njit(cache=True, inline="always")
def _ellipse_level(a, b, c, opacity):
    """``(level, det)`` in float64 of the lenient ``alpha >= 1/255`` ellipse ``sigma <= level``."""
    level = np.log(255.0 * np.float64(opacity)) * (1.0 + _ENUM_SLACK) + _ENUM_SLACK
    return level, np.float64(a) * c - np.float64(b) * b


@njit(cache=True, inline="always")
def _row_span(dy, mx, a, b, level, det, bx0, bx1):
    """Columns ``[lo, hi]`` of box columns ``[bx0, bx1]`` on a row ``dy = mean.y - centre.y`` that
    can be inside the lenient ellipse (the torch path's enumeration, up to rounding well inside its
    slack: ``level`` and ``det`` are stored in the records' dtype); the exact per-pair test still
    decides. Falls back to the box for degenerate conics."""
    if not (a > 0 and det > 0 and level < np.inf):
        return bx0, bx1
    dy64 = np.float64(dy)
    disc = 2.0 * a * level - dy64 * dy64 * det
    if disc < 0:
        return 1, 0
    root = np.sqrt(disc)
    t_lo = (-b * dy64 - root) / a
    t_hi = (-b * dy64 + root) / a
    # Clip in float64 before converting: the span can exceed int64 for near-degenerate conics.
    lo = np.int64(max(np.float64(bx0), np.ceil(mx - t_hi - 0.5)))
    hi = np.int64(min(np.float64(bx1), np.floor(mx - t_lo - 0.5)))
    return lo, hi


@njit(cache=True, inline="always")
def _tile_box(tile, tiles_x, tiles_y, width, height):
    """``(camera, x0, y0, x1, y1)`` of a global tile index; ``x1``, ``y1`` exclusive."""
    cam = tile // (tiles_x * tiles_y)
    ty = (tile % (tiles_x * tiles_y)) // tiles_x
    x0, y0 = (tile % tiles_x) * TILE_SIZE, ty * TILE_SIZE
    return cam, x0, y0, min(x0 + TILE_SIZE, width), min(y0 + TILE_SIZE, height)


@njit(parallel=True, cache=True)
def _forward_kernel(
    tile_order,
    tile_start,
    vis_start,
    slot_rows,
    slot_y,
    records,
    xs,
    ys,
    consts,
    n_cams,
    width,
    height,
    spans,
    vis_store,
):
    """Composite every tile; returns colours without background, T_final (f64) and last entries.
    Slot ``k``'s record has pixels in its tile on rows ``slot_y[k]`` (first, last); row ``py`` has
    the row span ``spans[slot_rows[k] + py]`` (see :func:`_row_spans`). Stores, for the backward to
    reuse instead of recomputing, the ``exp(-sigma)`` of every pair it evaluated (0 for skipped
    pairs) in ``vis_store``, slot ``k``'s span pixels from ``vis_start[k]`` on, row by row (unless it
    is shorter than ``vis_start[-1]``: then the backward recomputes them)."""
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    n_dim = records.shape[1] - REC_COLORS
    store_vis = vis_store.shape[0] >= vis_start[-1]
    # RGB (the training case) composites three scalars held in registers; the generic loop over
    # n_dim re-reads the record per pixel. Same sums in the same order: bitwise the generic result.
    rgb = n_dim == 3
    out = np.zeros((n_cams * height * width, n_dim), dtype=records.dtype)
    t_final = np.ones(n_cams * height * width, dtype=np.float64)
    last = np.zeros(n_cams * height * width, dtype=np.int32)
    for job in prange(tile_order.shape[0]):
        tile = tile_order[job]
        s, e = tile_start[tile], tile_start[tile + 1]
        cam, x0, y0, x1, y1 = _tile_box(tile, tiles_x, tiles_y, width, height)
        tw = x1 - x0
        n_pix = tw * (y1 - y0)
        trans = np.ones(n_pix, dtype=np.float64)
        done = np.zeros(n_pix, dtype=np.bool_)
        acc = np.zeros((n_pix, n_dim), dtype=np.float64)
        last_local = np.zeros(n_pix, dtype=np.int32)
        alive = n_pix
        for k in range(s, e):
            rec = records[k]
            mx, my, a, b, c, opacity = rec[0], rec[1], rec[2], rec[3], rec[4], rec[5]
            c0 = np.float64(rec[REC_COLORS])
            c1 = np.float64(rec[REC_COLORS + min(1, n_dim - 1)])
            c2 = np.float64(rec[REC_COLORS + min(2, n_dim - 1)])
            by0, by1 = slot_y[k, 0], slot_y[k, 1]
            pos = vis_start[k]
            for py in range(by0, by1 + 1):
                lo = max(np.int64(spans[slot_rows[k] + py, 0]), x0)
                hi = min(np.int64(spans[slot_rows[k] + py, 1]), x1 - 1)
                if lo > hi:
                    continue
                dy = my - ys[py]
                row_store = pos - lo
                pos += hi - lo + 1
                for px in range(lo, hi + 1):
                    i = (py - y0) * tw + (px - x0)
                    if done[i]:
                        continue
                    vis, _, alpha = _alpha(mx - xs[px], dy, a, b, c, opacity, consts)
                    if store_vis:
                        vis_store[row_store + px] = vis if alpha != 0 else consts[3]
                    if alpha == 0:
                        continue
                    t_next = trans[i] * (1.0 - np.float64(alpha))
                    if t_next <= TRANSMITTANCE_MIN:
                        done[i] = True
                        alive -= 1
                        continue
                    weight = np.float64(alpha) * trans[i]
                    if rgb:
                        acc[i, 0] += weight * c0
                        acc[i, 1] += weight * c1
                        acc[i, 2] += weight * c2
                    else:
                        for d in range(n_dim):
                            acc[i, d] += weight * rec[REC_COLORS + d]
                    trans[i] = t_next
                    last_local[i] = k - s + 1
            if alive == 0:
                break
        for i in range(n_pix):
            p = (cam * height + y0 + i // tw) * width + x0 + i % tw
            for d in range(n_dim):
                out[p, d] = acc[i, d]
            t_final[p] = trans[i]
            last[p] = last_local[i]
    return out, t_final, last


@njit(parallel=True, cache=True)
def _backward_kernel(
    tile_order,
    tile_start,
    vis_start,
    slot_rows,
    slot_y,
    records,
    xs,
    ys,
    consts,
    n_cams,
    width,
    height,
    spans,
    t_final,
    last,
    vis_store,
    grad_colors,
    grad_q,
    slots,
):
    """Fill the per (tile, list entry) gradient ``slots`` [K, N_GRAD + D], walking each pixel back
    to front.

    ``grad_colors`` [P, D] is dL/d(colour without background) and ``grad_q`` [P] is
    ``T_final * (dL/dcolour . background - dL/dalpha)``: the upstream term every pair's
    transmittance derivative carries.
    """
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    n_dim = records.shape[1] - REC_COLORS
    store_vis = vis_store.shape[0] >= vis_start[-1]
    for job in prange(tile_order.shape[0]):
        tile = tile_order[job]
        s = tile_start[tile]
        cam, x0, y0, x1, y1 = _tile_box(tile, tiles_x, tiles_y, width, height)
        tw = x1 - x0
        n_pix = tw * (y1 - y0)
        trans = np.empty(n_pix, dtype=np.float64)
        behind = np.zeros(n_pix, dtype=np.float64)
        last_local = np.empty(n_pix, dtype=np.int32)
        gcol = np.empty((n_pix, n_dim), dtype=np.float64)
        gq = np.empty(n_pix, dtype=np.float64)
        k_end = 0
        for i in range(n_pix):
            p = (cam * height + y0 + i // tw) * width + x0 + i % tw
            trans[i] = t_final[p]
            last_local[i] = last[p]
            k_end = max(k_end, last[p])
            gq[i] = grad_q[p]
            for d in range(n_dim):
                gcol[i, d] = grad_colors[p, d]
        gcolor = np.empty(n_dim, dtype=np.float64)
        slots[s + k_end : tile_start[tile + 1]] = 0.0  # entries behind every pixel's last one
        for kk in range(k_end - 1, -1, -1):
            rec = records[s + kk]
            mx, my, a, b, c, opacity = rec[0], rec[1], rec[2], rec[3], rec[4], rec[5]
            by0, by1 = slot_y[s + kk, 0], slot_y[s + kk, 1]
            rows = slot_rows[s + kk]
            pos = vis_start[s + kk]
            # Scalars (kept in registers) for the geometry, the colour part in a small array.
            g_mx = g_my = g_absx = g_absy = g_ca = g_cb = g_cc = g_op = 0.0
            gcolor[:] = 0.0
            for py in range(by0, by1 + 1):
                lo, hi = max(np.int64(spans[rows + py, 0]), x0), min(np.int64(spans[rows + py, 1]), x1 - 1)
                if lo > hi:
                    continue
                dy = my - ys[py]
                row_store = pos - lo
                pos += hi - lo + 1
                for px in range(lo, hi + 1):
                    i = (py - y0) * tw + (px - x0)
                    if kk >= last_local[i]:
                        continue
                    if store_vis:
                        # The forward evaluated this pair (the pixel was still compositing): its
                        # exp(-sigma), hence bitwise its alpha, or 0 where it skipped the pair.
                        vis = vis_store[row_store + px]
                        if vis == 0:
                            continue
                        raw = opacity * vis
                        alpha = min(raw, consts[1])
                    else:
                        vis, raw, alpha = _alpha(mx - xs[px], dy, a, b, c, opacity, consts)
                        if alpha == 0:
                            continue
                    dx = mx - xs[px]
                    alpha64 = np.float64(alpha)
                    inv_one_minus = 1.0 / (1.0 - alpha64)
                    t_before = trans[i] * inv_one_minus
                    trans[i] = t_before
                    weight = alpha64 * t_before
                    gc = 0.0
                    for d in range(n_dim):
                        gc += gcol[i, d] * rec[REC_COLORS + d]
                        gcolor[d] += weight * gcol[i, d]
                    grad_alpha = t_before * gc - (behind[i] + gq[i]) * inv_one_minus
                    behind[i] += weight * gc
                    if raw <= consts[1]:
                        grad_sigma = -np.float64(raw) * grad_alpha
                        g_op += np.float64(vis) * grad_alpha
                        dx64, dy64 = np.float64(dx), np.float64(dy)
                        gmx = grad_sigma * (a * dx64 + b * dy64)
                        gmy = grad_sigma * (b * dx64 + c * dy64)
                        g_mx += gmx
                        g_my += gmy
                        g_absx += abs(gmx)
                        g_absy += abs(gmy)
                        g_ca += 0.5 * grad_sigma * dx64 * dx64
                        g_cb += grad_sigma * dx64 * dy64
                        g_cc += 0.5 * grad_sigma * dy64 * dy64
            k = s + kk
            slots[k, 0], slots[k, 1], slots[k, 2], slots[k, 3] = g_mx, g_my, g_absx, g_absy
            slots[k, 4], slots[k, 5], slots[k, 6], slots[k, 7] = g_ca, g_cb, g_cc, g_op
            for d in range(n_dim):
                slots[k, N_GRAD + d] = gcolor[d]


LANES = 8
"""Pixels the float32 RGB kernels evaluate as one vector (AVX2's 8 float32 lanes): a tile row is
two such halves. Passed to the kernels at run time: a constant trip count gets the lane loop
unrolled, and LLVM does not vectorise the unrolled stores (they may alias). The kernels loop over
``lanes & -LANES``, a multiple of LANES to LLVM, which then emits no scalar remainder loop (and no
register shuffling between the two loops) after each vector."""

_PLANE = TILE_SIZE * TILE_SIZE
_MAX_LAST_F32 = 1 << 24
"""Tile lists at least this long take the generic kernels: the float32 kernels keep each pixel's
last entry in a float32 plane, exact below 2**24."""

RGB32_MIN_RUN = 5.5
"""Fewest span pixels per (list entry, tile row), on average over a render, for the 8-wide kernels:
below, most lanes of a half row idle and the generic kernels are faster (about 1.1x the time at
4.6 pixels, 0.85x at 6.5, 0.77x at 8.9 for a render's forward and backward: docs/cpu.md)."""


def span_counts(vis_start: Int[np.ndarray, " K1"], slot_y: Int[np.ndarray, "K 2"]) -> Tuple[int, int]:
    """A render's span pixels and (list entry, tile row) pairs over all its tiles: their ratio is the
    row-span width ``RGB32_MIN_RUN`` is compared with."""
    return int(vis_start[-1]), int((slot_y[:, 1] - slot_y[:, 0]).sum()) + len(slot_y)


def _spans_suit_lanes(
    tile_start: Int[np.ndarray, " T1"], vis_start: Int[np.ndarray, " K1"], slot_y: Int[np.ndarray, "K 2"]
) -> bool:
    """Whether a float32 RGB render's lists take the 8-wide kernels: wide enough row spans in its
    tiles (``RGB32_MIN_RUN``) and no list too long for their float32 entry counts."""
    if len(slot_y) == 0 or int(np.diff(tile_start).max()) >= _MAX_LAST_F32:
        return False
    pixels, rows = span_counts(vis_start, slot_y)
    return pixels >= RGB32_MIN_RUN * rows


@intrinsic
def _bits_as_f32(typingctx, bits):
    """The float32 whose bits are the int32 ``bits`` (an LLVM bitcast, which vectorises)."""

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.FloatType())

    return types.float32(types.int32), codegen


@njit(cache=True, inline="always")
def _exp_f32(x):
    """``exp(x)`` of a float32 ``x <= 0``, within 2 ulp (Cephes ``expf``; clamped at -80, where it
    is far below ``ALPHA_MIN``). Written out rather than ``np.exp``: libm's ``expf`` is a call LLVM
    cannot vectorise (no SVML here), and with no integer op wider than 32 bits its cost model picks
    8 lanes on AVX2."""
    half, one = np.float32(0.5), np.float32(1.0)
    x = max(x, np.float32(-80.0))
    n = np.float32(np.int32(x * np.float32(1.4426950408889634) - half))  # x <= 0: truncation rounds
    r = x - n * np.float32(0.693359375)
    r = r - n * np.float32(-2.12194440e-4)
    p = np.float32(1.9875691500e-4) * r + np.float32(1.3981999507e-3)
    p = p * r + np.float32(8.3334519073e-3)
    p = p * r + np.float32(4.1665795894e-2)
    p = p * r + np.float32(1.6666665459e-1)
    p = p * r + half
    p = p * (r * r) + r + one
    return p * _bits_as_f32(np.int32((n + np.float32(127.0)) * np.float32(8388608.0)))


@njit(cache=True)
def _sigma_vis_f32(dx, cdy, bdy, a):
    """``(sigma, exp(-sigma))`` of a pixel at ``dx`` in float32 (``exp(0)`` where ``sigma < 0``), with
    ``cdy = c * dy * dy`` and ``bdy = b * dy``. Not inlined by numba: LLVM inlines it after numba has
    set the backward's ``fastmath`` flags on the caller's own instructions only, so both float32
    kernels get bitwise the same alphas (the backward recovers the forward's transmittance)."""
    sigma = np.float32(0.5) * (a * dx * dx + cdy) + bdy * dx
    return sigma, _exp_f32(min(-sigma, np.float32(0.0)))


@njit(parallel=True, cache=True)
def _forward_kernel_rgb32(
    tile_order, tile_start, slot_rows, slot_y, records, xs, ys, consts, n_cams, width, height, spans, lanes
):
    """:func:`_forward_kernel` for float32 RGB, 8 pixels at a time: colours, T_final and last entries.

    Each row span's 8-pixel halves of its tile row are evaluated as one vector (``lanes`` = 8), every
    update a select on "inside the span, alpha passes, pixel still compositing"; transmittance is
    carried in float32 (gsplat's CUDA precision) and alpha comes from :func:`_exp_f32`, so results
    match the generic kernel's to float32 rounding (not bitwise). The tile's state lives in one array
    of 256-pixel planes (one base pointer: LLVM needs no runtime alias checks): transmittance, still
    compositing (1/0), r, g, b, last entry (small integers, exact), pixel centre x."""
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    half, one, zero = np.float32(0.5), np.float32(1.0), np.float32(0.0)
    alpha_max, alpha_min, t_min = consts[1], consts[2], np.float32(TRANSMITTANCE_MIN)
    out = np.zeros((n_cams * height * width, 3), dtype=np.float32)
    t_final = np.ones(n_cams * height * width, dtype=np.float32)
    last = np.zeros(n_cams * height * width, dtype=np.int32)
    for job in prange(tile_order.shape[0]):
        tile = tile_order[job]
        s, e = tile_start[tile], tile_start[tile + 1]
        cam, x0, y0, x1, y1 = _tile_box(tile, tiles_x, tiles_y, width, height)
        tw = x1 - x0
        st = np.zeros(7 * _PLANE + LANES, dtype=np.float32)
        st[:_PLANE] = one
        for r in range(TILE_SIZE):
            for q in range(TILE_SIZE):
                st[_PLANE + r * TILE_SIZE + q] = one if r < y1 - y0 and q < tw else zero
                st[6 * _PLANE + r * TILE_SIZE + q] = np.float32(x0 + q) + half
        row_live = np.ones(TILE_SIZE, dtype=np.int64)
        for k in range(s, e):
            rec = records[k]
            mx, my, a, b, c, opacity = rec[0], rec[1], rec[2], rec[3], rec[4], rec[5]
            c0, c1, c2 = rec[REC_COLORS], rec[REC_COLORS + 1], rec[REC_COLORS + 2]
            entry = np.float32(k - s + 1)
            for py in range(slot_y[k, 0], slot_y[k, 1] + 1):
                if row_live[py - y0] == 0:
                    continue
                lo_i = max(np.int64(spans[slot_rows[k] + py, 0]), x0)
                hi_i = min(np.int64(spans[slot_rows[k] + py, 1]), x1 - 1)
                if lo_i > hi_i:
                    continue
                lo, hi = xs[lo_i], xs[hi_i]
                dy = my - ys[py]
                cdy, bdy = c * dy * dy, b * dy
                for h in range((lo_i - x0) // LANES, (hi_i - x0) // LANES + 1):
                    v = st[(py - y0) * TILE_SIZE + h * LANES :]
                    for q in range(lanes & -LANES):
                        px = v[6 * _PLANE + q]
                        dx = mx - px
                        sigma, vis = _sigma_vis_f32(dx, cdy, bdy, a)
                        alpha = min(opacity * vis, alpha_max)
                        ok = (px >= lo) & (px <= hi) & (sigma >= zero) & (alpha >= alpha_min) & (v[_PLANE + q] > zero)
                        t = v[q]
                        t_next = t * (one - alpha)
                        stop = ok & (t_next <= t_min)
                        use = ok & (t_next > t_min)
                        w = alpha * t if use else zero
                        v[2 * _PLANE + q] += w * c0
                        v[3 * _PLANE + q] += w * c1
                        v[4 * _PLANE + q] += w * c2
                        v[q] = t_next if use else t
                        v[_PLANE + q] = zero if stop else v[_PLANE + q]
                        v[5 * _PLANE + q] = entry if use else v[5 * _PLANE + q]
            if (k - s) % 8 == 7:  # rows with no pixel left compositing are skipped from here on
                n_live = 0
                for r in range(TILE_SIZE):
                    row_live[r] = 1 if st[_PLANE + r * TILE_SIZE : _PLANE + (r + 1) * TILE_SIZE].max() > zero else 0
                    n_live += row_live[r]
                if n_live == 0:
                    break
        for i in range((y1 - y0) * tw):
            j = (i // tw) * TILE_SIZE + i % tw
            p = (cam * height + y0 + i // tw) * width + x0 + i % tw
            out[p, 0], out[p, 1], out[p, 2] = st[2 * _PLANE + j], st[3 * _PLANE + j], st[4 * _PLANE + j]
            t_final[p] = st[j]
            last[p] = np.int32(st[5 * _PLANE + j])
    return out, t_final, last


@njit(cache=True, inline="always")
def _lane_sum(acc, row):
    """The sum of the 8 lanes ``acc[row * LANES : (row + 1) * LANES]``, pairwise."""
    o = row * LANES
    return ((acc[o] + acc[o + 1]) + (acc[o + 2] + acc[o + 3])) + ((acc[o + 4] + acc[o + 5]) + (acc[o + 6] + acc[o + 7]))


@njit(parallel=True, cache=True, fastmath={"reassoc", "nsz"})
def _backward_kernel_rgb32(
    tile_order,
    tile_start,
    slot_rows,
    slot_y,
    records,
    xs,
    ys,
    consts,
    n_cams,
    width,
    height,
    spans,
    lanes,
    t_final,
    last,
    grad_colors,
    grad_q,
    slots,
):
    """:func:`_backward_kernel` for float32 RGB from :func:`_forward_kernel_rgb32`'s ``t_final`` and
    ``last``: each pixel walked back to front, 8 pixels of a tile row at a time, alphas recomputed
    (nothing stored by the forward), float32 ``slots`` [K, N_GRAD + 3].

    An entry's gradient sums are kept per lane (``acc``, 11 rows of 8) over all its rows in the tile
    and added across the lanes once per entry (:func:`_lane_sum`): kept as scalars, LLVM reduces its
    8-wide partial sums after every half row, eleven horizontal sums per vector of pixels. Another
    summation order than the generic kernel's, fixed, so results do not depend on the thread count. The 8 pixels
    of a half row are skipped once the entry lies behind all their last entries. State planes:
    transmittance, the colour behind, last entry, upstream ``grad_q``, dL/dr, g, b, pixel centre x."""
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    half, one, zero = np.float32(0.5), np.float32(1.0), np.float32(0.0)
    alpha_max, alpha_min = consts[1], consts[2]
    for job in prange(tile_order.shape[0]):
        tile = tile_order[job]
        s, e = tile_start[tile], tile_start[tile + 1]
        cam, x0, y0, x1, y1 = _tile_box(tile, tiles_x, tiles_y, width, height)
        tw = x1 - x0
        st = np.zeros(8 * _PLANE + LANES, dtype=np.float32)
        acc = np.zeros((N_GRAD + 3) * LANES, dtype=np.float32)  # slot columns x lanes
        half_last = np.zeros(2 * TILE_SIZE, dtype=np.int64)  # per 8 pixels of a tile row: their last entry
        k_end = 0
        for r in range(TILE_SIZE):
            for q in range(TILE_SIZE):
                j = r * TILE_SIZE + q
                st[7 * _PLANE + j] = np.float32(x0 + q) + half
                if r < y1 - y0 and q < tw:
                    p = (cam * height + y0 + r) * width + x0 + q
                    st[j] = t_final[p]
                    st[2 * _PLANE + j] = np.float32(last[p])
                    st[3 * _PLANE + j] = grad_q[p]
                    st[4 * _PLANE + j] = grad_colors[p, 0]
                    st[5 * _PLANE + j] = grad_colors[p, 1]
                    st[6 * _PLANE + j] = grad_colors[p, 2]
                    k_end = max(k_end, np.int64(last[p]))
                    half_last[r * 2 + q // LANES] = max(half_last[r * 2 + q // LANES], np.int64(last[p]))
        slots[s + k_end : e] = zero  # entries behind every pixel's last one
        for kk in range(k_end - 1, -1, -1):
            k = s + kk
            rec = records[k]
            mx, my, a, b, c, opacity = rec[0], rec[1], rec[2], rec[3], rec[4], rec[5]
            c0, c1, c2 = rec[REC_COLORS], rec[REC_COLORS + 1], rec[REC_COLORS + 2]
            entry = np.float32(kk)
            acc[:] = zero
            for py in range(slot_y[k, 0], slot_y[k, 1] + 1):
                lo_i = max(np.int64(spans[slot_rows[k] + py, 0]), x0)
                hi_i = min(np.int64(spans[slot_rows[k] + py, 1]), x1 - 1)
                if lo_i > hi_i:
                    continue
                lo, hi = xs[lo_i], xs[hi_i]
                dy = my - ys[py]
                cdy, bdy = c * dy * dy, b * dy
                for h in range((lo_i - x0) // LANES, (hi_i - x0) // LANES + 1):
                    if kk >= half_last[(py - y0) * 2 + h]:
                        continue
                    v = st[(py - y0) * TILE_SIZE + h * LANES :]
                    for q in range(lanes & -LANES):
                        px = v[7 * _PLANE + q]
                        dx = mx - px
                        sigma, vis = _sigma_vis_f32(dx, cdy, bdy, a)
                        raw = opacity * vis
                        alpha = min(raw, alpha_max)
                        ok = (px >= lo) & (px <= hi) & (sigma >= zero) & (alpha >= alpha_min)
                        ok = ok & (v[2 * _PLANE + q] > entry)
                        inv = one / (one - alpha)
                        t_before = v[q] * inv
                        weight = alpha * t_before if ok else zero
                        gr, gg, gb = v[4 * _PLANE + q], v[5 * _PLANE + q], v[6 * _PLANE + q]
                        gc = gr * c0 + gg * c1 + gb * c2
                        behind = v[_PLANE + q]
                        grad_alpha = t_before * gc - (behind + v[3 * _PLANE + q]) * inv
                        v[q] = t_before if ok else v[q]
                        v[_PLANE + q] = behind + weight * gc
                        # alpha clamped at ALPHA_MAX: no gradient to the geometry or opacity.
                        ga = grad_alpha if ok & (raw <= alpha_max) else zero
                        gs = -raw * ga  # d/dsigma
                        gmx = gs * (a * dx + b * dy)
                        gmy = gs * (b * dx + c * dy)
                        acc[q] += gmx
                        acc[LANES + q] += gmy
                        acc[2 * LANES + q] += abs(gmx)
                        acc[3 * LANES + q] += abs(gmy)
                        acc[4 * LANES + q] += half * gs * dx * dx
                        acc[5 * LANES + q] += gs * dx * dy
                        acc[6 * LANES + q] += half * gs * dy * dy
                        acc[7 * LANES + q] += vis * ga
                        acc[N_GRAD * LANES + q] += weight * gr
                        acc[(N_GRAD + 1) * LANES + q] += weight * gg
                        acc[(N_GRAD + 2) * LANES + q] += weight * gb
            for col in range(N_GRAD + 3):
                slots[k, col] = _lane_sum(acc, col)


@njit(parallel=True, cache=True)
def _reduce_slots(slots, rec_start, rec_slots, entries, g_means2d, g_abs, g_conics, g_opac, g_colors):
    """Sum each record's (tile, entry) slots in increasing tile order (deterministic) into the
    zero-initialised per-entry gradients (flat [C*N, ...], the inputs' dtype; ``g_opac`` [C*N, 1])."""
    n_rec, n_cols = entries.shape[0], slots.shape[1]
    chunk = 256
    for first in prange((n_rec + chunk - 1) // chunk):
        acc = np.empty(n_cols)
        for j in range(first * chunk, min((first + 1) * chunk, n_rec)):
            acc[:] = 0.0
            for q in range(rec_start[j], rec_start[j + 1]):
                k = rec_slots[q]
                for col in range(n_cols):
                    acc[col] += slots[k, col]
            e = entries[j]
            g_means2d[e, 0], g_means2d[e, 1], g_abs[e, 0], g_abs[e, 1] = acc[0], acc[1], acc[2], acc[3]
            g_conics[e, 0], g_conics[e, 1], g_conics[e, 2], g_opac[e, 0] = acc[4], acc[5], acc[6], acc[7]
            for d in range(n_cols - N_GRAD):
                g_colors[e, d] = acc[N_GRAD + d]


def _np(x: Tensor) -> np.ndarray:
    return x.detach().contiguous().numpy()


_SCRATCH: Dict[Tuple[str, type], np.ndarray] = {}
_SCRATCH_LOCK = threading.Lock()


def _take_scratch(name: str, size: int, dtype: type) -> np.ndarray:
    """A scratch array of at least ``size`` elements, reused across renders: first writes to fresh
    memory (page faults) cost more than the kernels' own work on it. The caller owns it until it
    hands it back with :func:`_give_scratch` (concurrent renders get their own arrays)."""
    with _SCRATCH_LOCK:
        buf = _SCRATCH.pop((name, dtype), None)
    if buf is None or buf.size < size:
        buf = np.empty(max(size, 1), dtype=dtype)
    return buf


def _give_scratch(name: str, buf: np.ndarray) -> None:
    """Keep ``buf`` for the next render (only the largest one per name and dtype is kept)."""
    with _SCRATCH_LOCK:
        kept = _SCRATCH.get((name, buf.dtype.type))
        if kept is None or kept.size < buf.size:
            _SCRATCH[(name, buf.dtype.type)] = buf


class _ScratchLease:
    """Hands a scratch array back when the autograd node holding it is freed (not after its
    backward: ``retain_graph`` may run that again)."""

    def __init__(self, name: str, buf: np.ndarray):
        self.name, self.buf = name, buf

    def __del__(self):
        _give_scratch(self.name, self.buf)


def _balanced_tile_order(tile_start: np.ndarray) -> np.ndarray:
    """Non-empty tiles, ordered so that numba's static schedule (equal contiguous blocks of the
    ``prange`` per thread) gives every thread a similar share of list entries: sorted by entries,
    dealt round-robin. (numba's dynamic ``parallel_chunksize`` costs more than it saves here.)"""
    counts = np.diff(tile_start)
    order = np.argsort(-counts, kind="stable")
    order = order[: int(np.count_nonzero(counts))]
    n_threads = numba.get_num_threads()
    return np.concatenate([order[t::n_threads] for t in range(n_threads)])


_READY: Dict[torch.dtype, float] = {}
_WARMING: Set[torch.dtype] = set()

STAGE_SECONDS: Optional[Dict[str, float]] = None
"""When a dict (see :func:`profile_stages`), wall seconds per stage are added to it."""


@contextmanager
def profile_stages() -> Iterator[Dict[str, float]]:
    """Collect wall seconds per stage ("sort+bin", "forward kernel", "backward kernel",
    "reduce+scatter") of the renders inside the block (used by ``python -m benchmarks.rasterizer``)."""
    global STAGE_SECONDS
    STAGE_SECONDS = {}
    try:
        yield STAGE_SECONDS
    finally:
        STAGE_SECONDS = None


@contextmanager
def _stage(name: str) -> Iterator[None]:
    if STAGE_SECONDS is None:
        yield
        return
    started = time.perf_counter()
    yield
    STAGE_SECONDS[name] = STAGE_SECONDS.get(name, 0.0) + time.perf_counter() - started


_BACKGROUND: Dict[torch.dtype, subprocess.Popen] = {}
"""The running background compile (:func:`compile_in_background`), by the dtype of its kernels."""

_PACKAGE_ROOT = str(Path(__file__).resolve().parents[2])


def child_code(statement: str) -> str:
    """Python code running ``statement`` with this very module imported as ``m``: numba caches a kernel per
    source file, and ``python -c`` would put the working directory first on ``sys.path``, where another
    checkout of the package may be (a worktree, a clone)."""
    return f"import sys; sys.path.insert(0, {_PACKAGE_ROOT!r}); import {__name__} as m; {statement}"


BACKGROUND_COMMAND = (sys.executable, "-c", child_code("m.warm_training_kernels()"))
"""The child process of :func:`compile_in_background`."""


def _raster_kernels() -> Tuple:
    return (
        _visible_by_depth, _make_records, _row_spans, _tile_pixels, _bin_tiles, _gather_rows, _forward_kernel,
        _backward_kernel, _forward_kernel_rgb32, _backward_kernel_rgb32, _reduce_slots,
        _project_forward, _project_backward, _sh_forward, _sh_backward,
    )  # fmt: skip


def _training_kernels() -> Tuple:
    from naka_gs_plugin.model import composite_cpu_fast, ssim_cpu_fast

    return _raster_kernels() + (
        ssim_cpu_fast._forward_kernel, ssim_cpu_fast._backward_kernel,
        composite_cpu_fast._forward_kernel, composite_cpu_fast._backward_kernel,
    )  # fmt: skip


def kernels_on_disk() -> bool:
    """Whether numba's disk cache holds an index for every kernel a training step runs (whether it is
    current for this source and machine, numba decides when it loads)."""
    try:
        return all(os.path.exists(kernel._cache._cache_file._index_path) for kernel in _training_kernels())
    except AttributeError:  # a numba without this cache layout: assume nothing is on disk
        return False


def compile_in_background() -> bool:
    """Start compiling the float32 kernels of a training step in a child process (one thread), unless
    they are on disk already or this process may use only one CPU; returns whether it started one.
    numba compiles in Python and holds the GIL, so a thread would stall the caller's work, while a
    process compiles on another core during what the caller does meanwhile (the training images'
    enhancement, the seed points) and leaves the kernels in numba's disk cache. The first render waits
    for it (:func:`warm_up`), then loads them; if the child failed, that render compiles them itself,
    as without a child."""
    if torch.float32 in _READY or torch.float32 in _BACKGROUND or usable_cpus()[0] < 2 or kernels_on_disk():
        return False
    env = dict(os.environ, OMP_NUM_THREADS="1", NUMBA_NUM_THREADS="1")
    _BACKGROUND[torch.float32] = subprocess.Popen(
        BACKGROUND_COMMAND, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    return True


@contextmanager
def compiling_in_background() -> Iterator[bool]:
    """:func:`compile_in_background` for the block, which leaves the child its core until it exits
    (:func:`~naka_gs_plugin.cpu.core_lent`: the block takes it back at its
    :func:`~naka_gs_plugin.cpu.reclaim_core` calls). Yields whether a child started; the thread count is
    restored after the block."""
    if not compile_in_background():
        yield False
        return
    with core_lent(_BACKGROUND[torch.float32]):
        yield True


def warm_training_kernels() -> None:
    """Compile (or load) the float32 kernels of a training step: the rasterizer's, SSIM's and compositing's,
    by running each on a tiny input forward and backward (:func:`compile_in_background`'s child)."""
    from naka_gs_plugin.model.composite_cpu_fast import composite_cpu_fast
    from naka_gs_plugin.model.ssim import FAST_TAPS, SSIMLoss

    warm_up(torch.float32)
    size = FAST_TAPS + 1
    render = torch.rand(size, size, 3, requires_grad=True)
    alpha = torch.rand(size, size, 1, requires_grad=True)
    gain, offset = torch.ones(3, requires_grad=True), torch.zeros(3, requires_grad=True)
    composite_cpu_fast(render, alpha, torch.zeros(3)).sum().backward()
    image = composite_cpu_fast(render, alpha, torch.zeros(3), gain, offset).permute(2, 0, 1)[None]
    SSIMLoss(data_range=1.0, size_average=True, channel=3)(image, torch.rand(1, 3, size, size)).backward()


def _wait_for_background(dtype: torch.dtype) -> None:
    child = _BACKGROUND.pop(dtype, None)
    if child is None:
        return
    if child.poll() is None:
        started = time.perf_counter()
        child.wait()
        CONSOLE.log(
            f"[naka-gs] cpu-fast rasterizer: waited {time.perf_counter() - started:.1f} s for the background compile",
            markup=False,
        )
    if child.returncode != 0:
        CONSOLE.log(
            f"[naka-gs] cpu-fast rasterizer: background compile failed (exit code {child.returncode}); compiling here",
            markup=False,
        )


def warm_up(dtype: torch.dtype = torch.float32) -> float:
    """Compile (or load from numba's disk cache) every kernel for ``dtype`` by rendering a tiny
    scene forward and backward; returns the seconds taken and logs them once per dtype and
    process. Called by the first render of a dtype, after :func:`compile_in_background`'s child
    has finished, if there is one."""
    if dtype in _READY or dtype in _WARMING:
        return 0.0
    _wait_for_background(dtype)
    _WARMING.add(dtype)
    started = time.perf_counter()
    # The first parallel kernel starts numba's OpenMP pool: keep the caller's PyTorch thread count.
    try:
        with torch_threads_kept():
            params = dict(
                means=torch.tensor([[0.0, 0.0, 2.0], [0.1, 0.0, 3.0]], dtype=dtype),
                quats=torch.tensor([[1.0, 0.1, 0.2, 0.3], [1.0, 0.0, 0.0, 0.0]], dtype=dtype),
                scales=torch.full((2, 3), 0.3, dtype=dtype),
                opacities=torch.tensor([0.5, 0.9], dtype=dtype),
                colors=torch.ones(2, 16, 3, dtype=dtype),
            )
            params = {k: v.requires_grad_() for k, v in params.items()}
            camera = dict(
                viewmats=torch.eye(4, dtype=dtype)[None],
                Ks=torch.tensor([[[8.0, 0, 4], [0, 8, 4], [0, 0, 1]]], dtype=dtype),
                width=8,
                height=8,
            )
            with torch.enable_grad():
                for render_mode in ("RGB", "RGB+ED"):  # float32 RGB has kernels of its own
                    colors, alphas, _ = rasterization(
                        **params,
                        **camera,
                        sh_degree=3,
                        rasterize_mode="antialiased",
                        render_mode=render_mode,
                        absgrad=True,
                    )
                    (colors.sum() + alphas.sum()).backward()
    finally:
        _WARMING.discard(dtype)
    seconds = time.perf_counter() - started
    misses = sum(sum(k.stats.cache_misses.values()) for k in _raster_kernels())
    how = "compiled (and cached on disk)" if misses else "loaded from numba's disk cache"
    CONSOLE.log(
        f"[naka-gs] cpu-fast rasterizer: {dtype} kernels {how} in {seconds:.1f} s; {numba.get_num_threads()} threads",
        markup=False,
    )
    _READY[dtype] = seconds
    return seconds


class _TileComposite(torch.autograd.Function):
    """Front-to-back compositing over the tile lists; hand-written backward (see module docstring)."""

    @staticmethod
    @untraced()
    def forward(
        ctx,
        means2d: Tensor,
        conics: Tensor,
        opacities: Tensor,
        colors: Tensor,
        backgrounds: Optional[Tensor],
        depths: Tensor,
        radii: Tensor,
        width: int,
        height: int,
        absgrad: bool,
    ) -> Tuple[Tensor, Tensor]:
        n_cams, n, dim = colors.shape
        dtype = colors.dtype
        np_dtype = np.float32 if dtype == torch.float32 else np.float64
        with _stage("sort+bin"):
            consts = np.array([0.5, ALPHA_MAX, ALPHA_MIN, 0.0], dtype=np_dtype)
            entries = _visible_by_depth(_np(radii), _np(opacities), _np(depths), consts[2])
            # One record per visible entry, in depth order; the kernels get a copy per list slot.
            records, boxes = _make_records(
                entries,
                _np(means2d).reshape(-1, 2),
                _np(conics).reshape(-1, 3),
                _np(opacities).reshape(-1),
                _np(colors).reshape(-1, dim),
                radii.reshape(-1).to(dtype).numpy(),
                consts,
                width,
                height,
            )
            tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
            tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
            xs = (torch.arange(width, dtype=dtype) + 0.5).numpy()  # pixel centres, as the torch path
            ys = (torch.arange(height, dtype=dtype) + 0.5).numpy()
            row_start, spans = _row_spans(records, boxes, ys)
            tile_start, tile_items, rec_start, rec_slots, vis_start, slot_y = _bin_tiles(
                boxes, entries, n, n_cams, tiles_x, tiles_y, *_tile_pixels(boxes, row_start, spans)
            )
            slot_records, slot_rows = _gather_rows(records, tile_items, row_start, boxes)
            kernel_args = (
                _balanced_tile_order(tile_start),
                tile_start,
                vis_start,
                slot_rows,
                slot_y,
                slot_records,
                xs,
                ys,
                consts,
                n_cams,
                width,
                height,
                spans,
            )
        rgb32 = dtype == torch.float32 and dim == 3 and _spans_suit_lanes(tile_start, vis_start, slot_y)
        with _stage("forward kernel"):
            if rgb32:
                kernel_args = kernel_args[:2] + kernel_args[3:] + (LANES,)
                out, t_final, last = _forward_kernel_rgb32(*kernel_args)
                extra, ctx.leases = (), []
            else:
                n_vis = int(vis_start[-1])
                vis_store = _take_scratch("vis", n_vis, np_dtype) if n_vis <= VIS_STORE_MAX else np.zeros(0, np_dtype)
                out, t_final, last = _forward_kernel(*kernel_args, vis_store)
                extra = (vis_store,)
                ctx.leases = [_ScratchLease("vis", vis_store)] if vis_store.size else []
        out = torch.from_numpy(out)
        t_final_t = torch.from_numpy(t_final).to(dtype)
        if backgrounds is not None:
            out = out + (t_final_t.reshape(n_cams, -1, 1) * backgrounds[:, None, :].detach()).reshape(-1, dim)
        ctx.save_for_backward(means2d, backgrounds)
        ctx.kernel_args = kernel_args + (t_final, last) + extra
        ctx.rgb32, ctx.t_final = rgb32, t_final
        ctx.slot_lists = (rec_start, rec_slots, entries)
        ctx.meta = (n_cams, n, dim, absgrad)
        return out.reshape(n_cams, height, width, dim), (1.0 - t_final_t).reshape(n_cams, height, width, 1)

    @staticmethod
    @untraced()
    def backward(ctx, grad_colors: Tensor, grad_alphas: Tensor):
        means2d, backgrounds = ctx.saved_tensors
        n_cams, n, dim, absgrad = ctx.meta
        t_final = ctx.t_final
        dtype = grad_colors.dtype
        grad_colors = grad_colors.reshape(n_cams, -1, dim)
        upstream = -grad_alphas.reshape(n_cams, -1).double()
        if backgrounds is not None:
            upstream = upstream + (grad_colors * backgrounds[:, None, :]).sum(-1).double()
        grad_q = torch.from_numpy(t_final) * upstream.reshape(-1)
        with _stage("backward kernel"):
            n_slots = ctx.slot_lists[1].shape[0]
            slot_dtype = np.float32 if ctx.rgb32 else np.float64
            slot_buf = _take_scratch("slots", n_slots * (N_GRAD + dim), slot_dtype)
            slots = slot_buf[: n_slots * (N_GRAD + dim)].reshape(n_slots, N_GRAD + dim)
            kernel, grad_dtype = (
                (_backward_kernel_rgb32, torch.float32) if ctx.rgb32 else (_backward_kernel, torch.float64)
            )
            kernel(
                *ctx.kernel_args,
                grad_colors.reshape(-1, dim).to(grad_dtype).contiguous().numpy(),
                grad_q.to(grad_dtype).contiguous().numpy(),
                slots,
            )
        with _stage("reduce+scatter"):
            g_means2d = torch.zeros(n_cams, n, 2, dtype=dtype)
            g_abs = torch.zeros(n_cams, n, 2, dtype=dtype)
            g_conics = torch.zeros(n_cams, n, 3, dtype=dtype)
            g_opac = torch.zeros(n_cams, n, dtype=dtype)
            g_colors = torch.zeros(n_cams, n, dim, dtype=dtype)
            outs = (g_means2d, g_abs, g_conics, g_opac, g_colors)
            _reduce_slots(slots, *ctx.slot_lists, *(g.view(n_cams * n, -1).numpy() for g in outs))
            _give_scratch("slots", slot_buf)
        if absgrad:
            means2d.absgrad = g_abs
        grad_bg = None
        if backgrounds is not None and ctx.needs_input_grad[4]:
            t = torch.from_numpy(t_final).to(dtype).reshape(n_cams, -1, 1)
            grad_bg = (grad_colors * t).sum(1)
        return g_means2d, g_conics, g_opac, g_colors, grad_bg, None, None, None, None, None


def rasterize_to_pixels_cpu_fast(
    means2d: Float[Tensor, "C N 2"],
    conics: Float[Tensor, "C N 3"],
    colors: Float[Tensor, "C N D"],
    opacities: Float[Tensor, "C N"],
    depths: Float[Tensor, "C N"],
    radii: Int[Tensor, "C N"],
    width: int,
    height: int,
    backgrounds: Optional[Float[Tensor, "C D"]] = None,
    absgrad: bool = False,
) -> Tuple[Float[Tensor, "C H W D"], Float[Tensor, "C H W 1"]]:
    """Composite screen-space Gaussians front to back with the compiled tile kernels.

    Same semantics, inputs and outputs as
    :func:`~naka_gs_plugin.model.rasterize.rasterize_to_pixels_sparse` (including
    ``means2d.absgrad`` when ``absgrad``); CPU tensors only, float32 or float64.
    """
    if means2d.device.type != "cpu":
        raise ValueError(f"the cpu-fast rasterizer needs CPU tensors, got {means2d.device} -- use gsplat on CUDA")
    if colors.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"the cpu-fast rasterizer supports float32/float64, got {colors.dtype}")
    warm_up(colors.dtype)
    return _TileComposite.apply(means2d, conics, opacities, colors, backgrounds, depths, radii, width, height, absgrad)


def rasterization(
    means: Float[Tensor, "N 3"],
    quats: Float[Tensor, "N 4"],
    scales: Float[Tensor, "N 3"],
    opacities: Float[Tensor, " N"],
    colors: Union[Tensor, Tuple[Tensor, Tensor]],
    viewmats: Float[Tensor, "C 4 4"],
    Ks: Float[Tensor, "C 3 3"],
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    sh_degree: Optional[int] = None,
    backgrounds: Optional[Float[Tensor, "C D"]] = None,
    render_mode: RenderMode = "RGB",
    rasterize_mode: Literal["classic", "antialiased"] = "classic",
    absgrad: bool = False,
    eps2d: float = 0.3,
) -> Tuple[Float[Tensor, "C H W X"], Float[Tensor, "C H W 1"], Dict]:
    """:func:`naka_gs_plugin.model.rasterize.rasterization` (gsplat 1.4.0 interface, same outputs
    and ``meta``) with compiled projection, SH colours and compositing; CPU tensors only. With ``sh_degree``,
    ``colors`` may also be splatfacto's ``(features_dc [N, 3], features_rest [N, K - 1, 3])``, which the SH
    kernels read as they are (:func:`~naka_gs_plugin.model.project_cpu_fast.sh_colors`)."""
    if means.device.type != "cpu":
        raise ValueError(f"the cpu-fast rasterizer needs CPU tensors, got {means.device} -- use gsplat on CUDA")
    if means.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"the cpu-fast rasterizer supports float32/float64, got {means.dtype}")
    warm_up(means.dtype)
    return rasterization_with_compositor(
        partial(rasterize_to_pixels_cpu_fast, absgrad=absgrad),
        means,
        quats,
        scales,
        opacities,
        colors,
        viewmats,
        Ks,
        width,
        height,
        near_plane=near_plane,
        far_plane=far_plane,
        sh_degree=sh_degree,
        backgrounds=backgrounds,
        render_mode=render_mode,
        rasterize_mode=rasterize_mode,
        eps2d=eps2d,
        project=project_gaussians,
        shade=sh_colors,
    )
