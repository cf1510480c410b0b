"""Compiled CPU kernels of the tile rasterizer: binning, front-to-back compositing and its hand-written backward.

Inputs are projected Gaussians (float64, C-contiguous), N of them:
  means2d  [N, 2]  pixel coordinates (pixel centres at +0.5)
  conics   [N, 3]  inverse 2D covariance (a, b, c): power = -0.5 (a dx^2 + c dy^2) - b dx dy
  feats    [N, D]  per-Gaussian channels to composite (the CPU backend sends RGB and depth)
  opacity  [N]     activated opacity
  rects    [N, 4]  int32 (x0, x1, y0, y1): the pixels whose centre lies inside the 3-sigma box, clipped to the image
The compositing kernels read them packed, one record per Gaussian (``pack``).

A pixel takes a Gaussian only inside its rect, so binning by rect makes the image independent of the tile size.
Each tile first copies its Gaussians into contiguous local arrays and splits itself into 4x4-pixel blocks with their
own lists. A block walks its list once, front to back, carrying its pixels' colours and transmittances, and visits
only the pixels inside each Gaussian's rect: each pixel sees the same Gaussians in the same order as a walk pixel by
pixel (the same bits), without testing every pixel against every Gaussian of its block (at 1M Gaussians and 256 px,
a fifth of the time forward and backward). A cheap bound on the exponent skips most exp() calls that could not reach
alpha 1/255. Gradients are written per (tile, Gaussian) pair and summed afterwards in
a fixed order, so the backward pass has no races and gives the same bits for any thread count.

Compiled on first use; ``cache=True`` keeps the machine code between processes. Where numba finds no writable cache
location (read-only install and home), the kernels are compiled without a cache instead of failing at import.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4
# Per-intersection gradient row: d/du, d/dv, d/da, d/db, d/dc, d/dopacity, then d/dfeats.
GEOM_GRADS = 6
GEOMETRY = 7  # a record's leading values (``pack``): u, v, a, b, c, opacity, exponent cut
RECT = 4  # and its last: the rect x0, x1, y0, y1
# Side of the pixel blocks a tile is split into.
BLOCK = 4
RADIX_BITS = 11  # bits of a depth key sorted per pass when binning (a 2048-bucket histogram per thread)
# exp(power) is skipped when power < log(ALPHA_MIN / opacity) - CUT_MARGIN: the margin is far above rounding error,
# so the skip never changes a decision that the exact test would make.
CUT_MARGIN = 1e-6


def _compile(parallel: bool):
    def decorate(fn):
        try:
            return njit(parallel=parallel, cache=True, nogil=True)(fn)
        except RuntimeError:  # numba raises this when no cache directory is writable
            return njit(parallel=parallel, nogil=True)(fn)

    return decorate


@_compile(parallel=True)
def bin_gaussians(means2d, radii, depths, width, height, tile_size, threads):
    """Pixel rects [N, 4] int32 (empty: x0 > x1), tile offsets [T + 1] int64 and per-tile Gaussian ids [I] int32.

    Gaussians with radius 0 or no pixel centre inside their box are left out; the others enter each tile's list
    front to back (stable sort by ``depths``). Every step runs on ``threads`` threads (numba's count, passed in so the
    kernel stays cacheable) and the lists are the same for any count: the (Gaussian, tile) pairs are written in
    front-to-back order, then counting-sorted by tile, each thread placing its share of the pairs after those of the
    threads before it.
    """
    n = means2d.shape[0]
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    rects = np.empty((n, 4), dtype=np.int32)
    hits = np.zeros(n, dtype=np.int64)  # tiles each Gaussian touches
    for g in prange(n):
        r = radii[g]
        u = means2d[g, 0]
        v = means2d[g, 1]
        # Pixel j is inside when |j + 0.5 - u| <= r; bounds are clipped as floats so huge values convert safely.
        x0 = max(math.ceil(max(u - r - 0.5, -1.0)), 0)
        x1 = min(math.floor(min(u + r - 0.5, width)), width - 1)
        y0 = max(math.ceil(max(v - r - 0.5, -1.0)), 0)
        y1 = min(math.floor(min(v + r - 0.5, height)), height - 1)
        if not r > 0 or x0 > x1 or y0 > y1:
            x0, x1, y0, y1 = 1, 0, 1, 0
        else:
            hits[g] = (y1 // tile_size - y0 // tile_size + 1) * (x1 // tile_size - x0 // tile_size + 1)
        rects[g, 0] = x0
        rects[g, 1] = x1
        rects[g, 2] = y0
        rects[g, 3] = y1
    visible = np.flatnonzero(hits)
    front_to_back = visible[_stable_order(depths[visible], threads)]
    m = front_to_back.shape[0]
    first = np.zeros(m + 1, dtype=np.int64)  # where each Gaussian's pairs start, front to back
    for k in range(m):
        first[k + 1] = first[k] + hits[front_to_back[k]]
    pair_tile = np.empty(first[m], dtype=np.int64)
    pair_id = np.empty(first[m], dtype=np.int32)
    for k in prange(m):
        g = front_to_back[k]
        p = first[k]
        for ty in range(rects[g, 2] // tile_size, rects[g, 3] // tile_size + 1):
            for tx in range(rects[g, 0] // tile_size, rects[g, 1] // tile_size + 1):
                pair_tile[p] = ty * tiles_x + tx
                pair_id[p] = g
                p += 1
    tiles = tiles_x * tiles_y
    parts = max(min(threads, first[m] // 4096), 1)
    bounds = np.array([first[m] * q // parts for q in range(parts + 1)], dtype=np.int64)
    counts = np.zeros((parts, tiles), dtype=np.int64)
    for q in prange(parts):
        for p in range(bounds[q], bounds[q + 1]):
            counts[q, pair_tile[p]] += 1
    offsets = np.zeros(tiles + 1, dtype=np.int64)
    cursor = np.empty((parts, tiles), dtype=np.int64)
    at = 0
    for t in range(tiles):
        offsets[t] = at
        for q in range(parts):
            cursor[q, t] = at
            at += counts[q, t]
    offsets[tiles] = at
    ids = np.empty(at, dtype=np.int32)
    for q in prange(parts):
        for p in range(bounds[q], bounds[q + 1]):
            t = pair_tile[p]
            ids[cursor[q, t]] = pair_id[p]
            cursor[q, t] += 1
    return rects, offsets, ids


@_compile(parallel=True)
def _stable_order(keys, threads):
    """``np.argsort(keys, kind="stable")`` of float64 ``keys`` (NaN last, -0.0 equal to 0.0) on ``threads`` threads.

    An LSD radix sort: each key's bits are mapped to an unsigned integer that sorts as the float does, then counting
    sorted ``RADIX_BITS`` at a time from the lowest, each pass stable (every thread places its share of the keys
    after those of the threads before it). Passes over bits that no two keys differ in are skipped: depths in one
    scene share their sign, exponent and leading mantissa bits.
    """
    n = keys.shape[0]
    top = np.uint64(1) << np.uint64(63)
    bits = keys.view(np.uint64)
    code = np.empty(n, dtype=np.uint64)
    for i in prange(n):
        x = keys[i]
        if x != x:
            code[i] = ~np.uint64(0)
        elif x == 0.0:
            code[i] = top
        elif x > 0.0:
            code[i] = bits[i] | top
        else:
            code[i] = ~bits[i]
    differ = np.uint64(0)
    for i in range(n):
        differ |= code[i] ^ code[0]
    order = np.arange(n)
    parts = max(min(threads, n // 16384), 1)
    bounds = np.array([n * q // parts for q in range(parts + 1)], dtype=np.int64)
    buckets = 1 << RADIX_BITS
    mask = np.uint64(buckets - 1)
    next_code = np.empty_like(code)
    next_order = np.empty_like(order)
    for shift in range(0, 64, RADIX_BITS):
        s = np.uint64(shift)
        if (differ >> s) & mask == 0:
            continue
        counts = np.zeros((parts, buckets), dtype=np.int64)
        for q in prange(parts):
            for p in range(bounds[q], bounds[q + 1]):
                counts[q, (code[p] >> s) & mask] += 1
        cursor = np.empty((parts, buckets), dtype=np.int64)
        at = 0
        for b in range(buckets):
            for q in range(parts):
                cursor[q, b] = at
                at += counts[q, b]
        for q in prange(parts):
            for p in range(bounds[q], bounds[q + 1]):
                b = (code[p] >> s) & mask
                next_code[cursor[q, b]] = code[p]
                next_order[cursor[q, b]] = order[p]
                cursor[q, b] += 1
        code, next_code = next_code, code
        order, next_order = next_order, order
    return order


@_compile(parallel=False)
def balance_tiles(work, threads):
    """Tile order [T] int64 for ``threads`` equal contiguous chunks (numba's static split of a parallel loop) with
    about equal ``work`` [T] each: heaviest tile first into the lightest chunk that still has room."""
    n = work.shape[0]
    size = np.full(threads, n // threads, dtype=np.int64)
    size[: n % threads] += 1
    start = np.zeros(threads, dtype=np.int64)
    start[1:] = np.cumsum(size)[:-1]
    fill = np.zeros(threads, dtype=np.int64)
    load = np.zeros(threads)
    order = np.empty(n, dtype=np.int64)
    for tile in np.argsort(-work, kind="mergesort"):
        best = -1
        for b in range(threads):
            if fill[b] < size[b] and (best < 0 or load[b] < load[best]):
                best = b
        order[start[best] + fill[best]] = tile
        fill[best] += 1
        load[best] += work[tile]
    return order


@_compile(parallel=True)
def pack(means2d, conics, feats, opacity, rects):
    """One record [N, GEOMETRY + D + RECT] per Gaussian: u, v, a, b, c, opacity, exponent cut, feats, then its rect
    (exact as floats). A tile reads each of its Gaussians from one or two cache lines, not from five arrays (at 1M
    Gaussians, in depth order, every read a miss)."""
    n = means2d.shape[0]
    d = feats.shape[1]
    rec = np.empty((n, GEOMETRY + d + RECT))
    for g in prange(n):
        rec[g, 0] = means2d[g, 0]
        rec[g, 1] = means2d[g, 1]
        rec[g, 2] = conics[g, 0]
        rec[g, 3] = conics[g, 1]
        rec[g, 4] = conics[g, 2]
        rec[g, 5] = opacity[g]
        rec[g, 6] = math.log(ALPHA_MIN / opacity[g]) - CUT_MARGIN if opacity[g] > 0.0 else 1.0
        for c in range(d):
            rec[g, GEOMETRY + c] = feats[g, c]
        for c in range(RECT):
            rec[g, GEOMETRY + d + c] = rects[g, c]
    return rec


@_compile(parallel=False)
def _channels(rec):
    """D, the channels composited, of ``pack``'s records."""
    return rec.shape[1] - GEOMETRY - RECT


@_compile(parallel=False)
def _gather(ids, start, n, rec):
    """A tile's Gaussians from ``pack``'s records as contiguous arrays: geometry [n, GEOMETRY] (u, v, a, b, c,
    opacity, exponent cut), rects [n, 4] int32, feats [n, D]."""
    d = _channels(rec)
    geo = np.empty((n, GEOMETRY))
    box = np.empty((n, RECT), dtype=np.int32)
    col = np.empty((n, d))
    for j in range(n):
        g = ids[start + j]
        for c in range(GEOMETRY):
            geo[j, c] = rec[g, c]
        for c in range(d):
            col[j, c] = rec[g, GEOMETRY + c]
        for c in range(RECT):
            box[j, c] = np.int32(rec[g, GEOMETRY + d + c])
    return geo, box, col


@_compile(parallel=False)
def _blocks(box, x0, y0, x_end, y_end):
    """Per BLOCK x BLOCK pixel block of the tile [x0, x_end) x [y0, y_end): count and front-to-back local indices of
    the Gaussians whose rect overlaps it."""
    n = box.shape[0]
    nbx = (x_end - x0 + BLOCK - 1) // BLOCK
    nby = (y_end - y0 + BLOCK - 1) // BLOCK
    counts = np.zeros(nbx * nby, dtype=np.int64)
    lists = np.empty((nbx * nby, n), dtype=np.int32)
    for j in range(n):
        bx0 = (max(box[j, 0], x0) - x0) // BLOCK
        bx1 = (min(box[j, 1], x_end - 1) - x0) // BLOCK
        by0 = (max(box[j, 2], y0) - y0) // BLOCK
        by1 = (min(box[j, 3], y_end - 1) - y0) // BLOCK
        for by in range(by0, by1 + 1):
            for bx in range(bx0, bx1 + 1):
                q = by * nbx + bx
                lists[q, counts[q]] = j
                counts[q] += 1
    return nbx, counts, lists


@_compile(parallel=False)
def _block(q, nbx, x0, y0, x_end, y_end):
    """Pixel bounds (x0, y0, x1, y1), inclusive, of block ``q`` of the tile at (x0, y0) clipped to (x_end, y_end)."""
    bx0 = x0 + (q % nbx) * BLOCK
    by0 = y0 + (q // nbx) * BLOCK
    return bx0, by0, min(bx0 + BLOCK, x_end) - 1, min(by0 + BLOCK, y_end) - 1


@_compile(parallel=False)
def _splat(geo, j):
    """Gaussian ``j``'s row of ``_gather``'s geometry: u, v, a, b, c, opacity, exponent cut."""
    return geo[j, 0], geo[j, 1], geo[j, 2], geo[j, 3], geo[j, 4], geo[j, 5], geo[j, 6]


@_compile(parallel=True)
def composite_forward(rec, offsets, ids, order, background, width, height, tile_size):
    """Composited channels [H, W, D] (background included) and final transmittance [H, W] of ``pack``'s records."""
    d = _channels(rec)
    tiles_x = (width + tile_size - 1) // tile_size
    out = np.empty((height, width, d))
    t_final = np.empty((height, width))
    for k in prange(order.shape[0]):
        tile = order[k]
        y0 = (tile // tiles_x) * tile_size
        x0 = (tile % tiles_x) * tile_size
        y_end = min(y0 + tile_size, height)
        x_end = min(x0 + tile_size, width)
        start = offsets[tile]
        geo, box, col = _gather(ids, start, offsets[tile + 1] - start, rec)
        nbx, counts, lists = _blocks(box, x0, y0, x_end, y_end)
        acc = np.empty((BLOCK, BLOCK, d))
        t = np.empty((BLOCK, BLOCK))
        live = np.empty((BLOCK, BLOCK), dtype=np.bool_)
        for q in range(counts.shape[0]):
            bx0, by0, bx1, by1 = _block(q, nbx, x0, y0, x_end, y_end)
            acc[:] = 0.0
            t[:] = 1.0
            live[:] = True
            alive = (bx1 - bx0 + 1) * (by1 - by0 + 1)  # pixels still compositing
            for i in range(counts[q]):
                if alive == 0:
                    break
                j = lists[q, i]
                u, v, a, b, cc, o, cut = _splat(geo, j)
                for py in range(max(by0, box[j, 2]), min(by1, box[j, 3]) + 1):
                    dy = v - (py + 0.5)
                    for px in range(max(bx0, box[j, 0]), min(bx1, box[j, 1]) + 1):
                        ly, lx = py - by0, px - bx0
                        if not live[ly, lx]:
                            continue
                        dx = u - (px + 0.5)
                        power = -0.5 * (a * dx * dx + cc * dy * dy) - b * dx * dy
                        if power < cut:
                            continue
                        alpha = min(ALPHA_MAX, o * math.exp(power))
                        if alpha < ALPHA_MIN:
                            continue
                        t_next = t[ly, lx] * (1.0 - alpha)
                        if t_next < T_MIN:
                            live[ly, lx] = False
                            alive -= 1
                            continue
                        w = alpha * t[ly, lx]
                        for c in range(d):
                            acc[ly, lx, c] += w * col[j, c]
                        t[ly, lx] = t_next
            for py in range(by0, by1 + 1):
                for px in range(bx0, bx1 + 1):
                    ly, lx = py - by0, px - bx0
                    for c in range(d):
                        out[py, px, c] = acc[ly, lx, c] + t[ly, lx] * background[c]
                    t_final[py, px] = t[ly, lx]
    return out, t_final


@_compile(parallel=True)
def composite_backward(rec, offsets, ids, order, width, height, tile_size, out, t_final, grad_out, grad_t_final):
    """Gradient rows [I, 6 + D] per tile-Gaussian pair, in the order of ``ids``.

    Walks each block front to back again with the forward's exact decisions. With S = sum_c g_c out_c + g_T T_final
    and R_k the same sum over what Gaussians 0..k composited, dL/dalpha_k = T_k (g . f_k) - (S - R_k) / (1 - alpha_k).
    """
    d = _channels(rec)
    tiles_x = (width + tile_size - 1) // tile_size
    grads = np.zeros((ids.shape[0], GEOM_GRADS + d))
    for k in prange(order.shape[0]):
        tile = order[k]
        y0 = (tile // tiles_x) * tile_size
        x0 = (tile % tiles_x) * tile_size
        y_end = min(y0 + tile_size, height)
        x_end = min(x0 + tile_size, width)
        start = offsets[tile]
        geo, box, col = _gather(ids, start, offsets[tile + 1] - start, rec)
        nbx, counts, lists = _blocks(box, x0, y0, x_end, y_end)
        g_pix = np.empty((BLOCK, BLOCK, d))
        total = np.empty((BLOCK, BLOCK))
        done = np.empty((BLOCK, BLOCK))
        t = np.empty((BLOCK, BLOCK))
        live = np.empty((BLOCK, BLOCK), dtype=np.bool_)
        for q in range(counts.shape[0]):
            bx0, by0, bx1, by1 = _block(q, nbx, x0, y0, x_end, y_end)
            for py in range(by0, by1 + 1):
                for px in range(bx0, bx1 + 1):
                    ly, lx = py - by0, px - bx0
                    s = grad_t_final[py, px] * t_final[py, px]
                    for c in range(d):
                        g_pix[ly, lx, c] = grad_out[py, px, c]
                        s += grad_out[py, px, c] * out[py, px, c]
                    total[ly, lx] = s
            done[:] = 0.0
            t[:] = 1.0
            live[:] = True
            alive = (bx1 - bx0 + 1) * (by1 - by0 + 1)  # pixels still compositing
            for i in range(counts[q]):
                if alive == 0:
                    break
                j = lists[q, i]
                e = start + j
                u, v, a, b, cc, o, cut = _splat(geo, j)
                for py in range(max(by0, box[j, 2]), min(by1, box[j, 3]) + 1):
                    dy = v - (py + 0.5)
                    for px in range(max(bx0, box[j, 0]), min(bx1, box[j, 1]) + 1):
                        ly, lx = py - by0, px - bx0
                        if not live[ly, lx]:
                            continue
                        dx = u - (px + 0.5)
                        power = -0.5 * (a * dx * dx + cc * dy * dy) - b * dx * dy
                        if power < cut:
                            continue
                        gauss = math.exp(power)
                        raw = o * gauss
                        alpha = min(ALPHA_MAX, raw)
                        if alpha < ALPHA_MIN:
                            continue
                        t_here = t[ly, lx]
                        t_next = t_here * (1.0 - alpha)
                        if t_next < T_MIN:
                            live[ly, lx] = False
                            alive -= 1
                            continue
                        w = alpha * t_here
                        gf = 0.0
                        for c in range(d):
                            gf += g_pix[ly, lx, c] * col[j, c]
                            grads[e, GEOM_GRADS + c] += g_pix[ly, lx, c] * w
                        done[ly, lx] += w * gf
                        # Where alpha is clamped at ALPHA_MAX it no longer depends on opacity or geometry.
                        if raw <= ALPHA_MAX:
                            d_alpha = t_here * gf - (total[ly, lx] - done[ly, lx]) / (1.0 - alpha)
                            grads[e, 5] += gauss * d_alpha
                            d_power = raw * d_alpha
                            grads[e, 0] -= d_power * (a * dx + b * dy)
                            grads[e, 1] -= d_power * (cc * dy + b * dx)
                            grads[e, 2] -= 0.5 * d_power * dx * dx
                            grads[e, 3] -= d_power * dx * dy
                            grads[e, 4] -= 0.5 * d_power * dy * dy
                        t[ly, lx] = t_next
    return grads


@_compile(parallel=True)
def sum_by_gaussian(rows, ids, n, threads):
    """Per-Gaussian sums [n, C] of per-intersection rows [I, C], added in the order of ``ids``: each of ``threads``
    threads walks every row and adds those of its own range of Gaussians, so the order, and the bits, do not depend on
    the count."""
    total = np.zeros((n, rows.shape[1]))
    for q in prange(threads):
        lo = n * q // threads
        hi = n * (q + 1) // threads
        for e in range(ids.shape[0]):
            g = ids[e]
            if lo <= g < hi:
                for c in range(rows.shape[1]):
                    total[g, c] += rows[e, c]
    return total
