"""The cpu-fast rasterizer's tile lists: numba kernels that sort the visible Gaussians by depth and list them per tile.

Layout (as gsplat's CUDA path): the image is cut into 16x16 tiles. On each row of its pixel box
(:func:`~naka_gs_plugin.model.projection.pixel_bounds`) a visible Gaussian (``radius > 0``,
``opacity >= 1/255``) visits only the columns of its lenient ``alpha >= 1/255`` ellipse (the torch
path's enumeration), computed once per row before the kernels; it is listed, in stable depth order,
in each tile those row spans reach (not every tile of its box: for trained scenes two thirds of
those would composite nothing). Unlike gsplat, which evaluates every Gaussian of a tile, a Gaussian
only touches the pixels of its spans, so exactly the pairs of the torch path are composited.

The stages, each a kernel, in the order :class:`~naka_gs_plugin.model.rasterize_cpu_fast._TileComposite` runs
them: the visible entries stable-sorted by depth (:func:`_visible_by_depth`, a radix sort), one record per entry
with its pixel box cut to its ellipse (:func:`_make_records`), the row spans (:func:`_row_spans`), the span pixels
per tile (:func:`_tile_pixels`), the per-tile lists (:func:`_bin_tiles`, a parallel counting sort) and one record
per list slot (:func:`_gather_rows`). The compositing kernels that walk the lists are in
:mod:`~naka_gs_plugin.model.rasterize_cpu_kernels`; :mod:`~naka_gs_plugin.model.compile_ahead` lists every kernel
and gets them compiled.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from naka_gs_plugin.model.rasterize import _ENUM_SLACK, TILE_SIZE

_BIN_CHUNKS = 16
"""Chunks of records :func:`_bin_tiles` bins in parallel (the lists do not depend on it)."""

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
