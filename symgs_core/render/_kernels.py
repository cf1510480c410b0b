"""Compiled CPU kernels of the tile rasterizer: binning, front-to-back compositing and its hand-written backward.

Inputs are depth-sorted, already projected Gaussians (float64, C-contiguous):
  means2d  [M, 2]  pixel coordinates (pixel centres at +0.5)
  conics   [M, 3]  inverse 2D covariance (a, b, c): power = -0.5 (a dx^2 + c dy^2) - b dx dy
  feats    [M, D]  per-Gaussian channels to composite (RGB, plus depth when asked)
  opacity  [M]     activated opacity
  rects    [M, 4]  int32 (x0, x1, y0, y1): the pixels whose centre lies inside the 3-sigma box, clipped to the image

A pixel takes a Gaussian only inside its rect, so binning by rect makes the image independent of the tile size.
Gradients are written per (tile, Gaussian) pair and summed afterwards in a fixed order, so the backward pass has no
races and gives the same bits for any thread count.

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


def _compile(parallel: bool):
    def decorate(fn):
        try:
            return njit(parallel=parallel, cache=True, nogil=True)(fn)
        except RuntimeError:  # numba raises this when no cache directory is writable
            return njit(parallel=parallel, nogil=True)(fn)

    return decorate


@_compile(parallel=False)
def bin_gaussians(means2d, radii, width, height, tile_size):
    """Pixel rects [M, 4] int32, tile offsets [T + 1] int64 and per-tile Gaussian ids [I] int32 (depth order kept)."""
    m = means2d.shape[0]
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    rects = np.empty((m, 4), dtype=np.int32)
    counts = np.zeros(tiles_x * tiles_y + 1, dtype=np.int64)
    for g in range(m):
        r = radii[g]
        u = means2d[g, 0]
        v = means2d[g, 1]
        # Pixel j is inside when |j + 0.5 - u| <= r.
        x0 = max(math.ceil(u - r - 0.5), 0)
        x1 = min(math.floor(u + r - 0.5), width - 1)
        y0 = max(math.ceil(v - r - 0.5), 0)
        y1 = min(math.floor(v + r - 0.5), height - 1)
        if r <= 0 or x0 > x1 or y0 > y1:
            x0, x1, y0, y1 = 1, 0, 1, 0
        rects[g, 0] = x0
        rects[g, 1] = x1
        rects[g, 2] = y0
        rects[g, 3] = y1
        if x0 > x1:
            continue
        for ty in range(y0 // tile_size, y1 // tile_size + 1):
            for tx in range(x0 // tile_size, x1 // tile_size + 1):
                counts[ty * tiles_x + tx + 1] += 1
    offsets = np.cumsum(counts)
    ids = np.empty(offsets[-1], dtype=np.int32)
    cursor = offsets[:-1].copy()
    for g in range(m):
        x0, x1, y0, y1 = rects[g, 0], rects[g, 1], rects[g, 2], rects[g, 3]
        if x0 > x1:
            continue
        for ty in range(y0 // tile_size, y1 // tile_size + 1):
            for tx in range(x0 // tile_size, x1 // tile_size + 1):
                t = ty * tiles_x + tx
                ids[cursor[t]] = g
                cursor[t] += 1
    return rects, offsets, ids


@_compile(parallel=True)
def composite_forward(
    means2d, conics, feats, opacity, rects, offsets, ids, order, background, width, height, tile_size
):
    """Composited channels [H, W, D] (background included) and final transmittance [H, W]."""
    d = feats.shape[1]
    tiles_x = (width + tile_size - 1) // tile_size
    out = np.empty((height, width, d))
    t_final = np.empty((height, width))
    for k in prange(order.shape[0]):
        tile = order[k]
        ty = tile // tiles_x
        tx = tile - ty * tiles_x
        start = offsets[tile]
        end = offsets[tile + 1]
        acc = np.empty(d)
        for py in range(ty * tile_size, min((ty + 1) * tile_size, height)):
            cy = py + 0.5
            for px in range(tx * tile_size, min((tx + 1) * tile_size, width)):
                cx = px + 0.5
                acc[:] = 0.0
                t = 1.0
                for e in range(start, end):
                    g = ids[e]
                    if px < rects[g, 0] or px > rects[g, 1] or py < rects[g, 2] or py > rects[g, 3]:
                        continue
                    dx = means2d[g, 0] - cx
                    dy = means2d[g, 1] - cy
                    power = -0.5 * (conics[g, 0] * dx * dx + conics[g, 2] * dy * dy) - conics[g, 1] * dx * dy
                    alpha = min(ALPHA_MAX, opacity[g] * math.exp(power))
                    if alpha < ALPHA_MIN:
                        continue
                    t_next = t * (1.0 - alpha)
                    if t_next < T_MIN:
                        break
                    w = alpha * t
                    for c in range(d):
                        acc[c] += w * feats[g, c]
                    t = t_next
                for c in range(d):
                    out[py, px, c] = acc[c] + t * background[c]
                t_final[py, px] = t
    return out, t_final


@_compile(parallel=True)
def composite_backward(
    means2d, conics, feats, opacity, rects, offsets, ids, order, width, height, tile_size, out, t_final, grad_out,
    grad_t_final,
):
    """Gradient rows [I, 6 + D] per tile-Gaussian pair, in the order of ``ids``.

    Walks each pixel front to back again with the forward's exact decisions. With S = sum_c g_c out_c + g_T T_final
    and R_k the same sum over what Gaussians 0..k composited, dL/dalpha_k = T_k (g . f_k) - (S - R_k) / (1 - alpha_k).
    """
    d = feats.shape[1]
    tiles_x = (width + tile_size - 1) // tile_size
    grads = np.zeros((ids.shape[0], GEOM_GRADS + d))
    for k in prange(order.shape[0]):
        tile = order[k]
        ty = tile // tiles_x
        tx = tile - ty * tiles_x
        start = offsets[tile]
        end = offsets[tile + 1]
        for py in range(ty * tile_size, min((ty + 1) * tile_size, height)):
            cy = py + 0.5
            for px in range(tx * tile_size, min((tx + 1) * tile_size, width)):
                cx = px + 0.5
                g_t = grad_t_final[py, px]
                total = g_t * t_final[py, px]
                for c in range(d):
                    total += grad_out[py, px, c] * out[py, px, c]
                done = 0.0
                t = 1.0
                for e in range(start, end):
                    g = ids[e]
                    if px < rects[g, 0] or px > rects[g, 1] or py < rects[g, 2] or py > rects[g, 3]:
                        continue
                    dx = means2d[g, 0] - cx
                    dy = means2d[g, 1] - cy
                    a = conics[g, 0]
                    b = conics[g, 1]
                    cc = conics[g, 2]
                    power = -0.5 * (a * dx * dx + cc * dy * dy) - b * dx * dy
                    gauss = math.exp(power)
                    raw = opacity[g] * gauss
                    alpha = min(ALPHA_MAX, raw)
                    if alpha < ALPHA_MIN:
                        continue
                    t_next = t * (1.0 - alpha)
                    if t_next < T_MIN:
                        break
                    w = alpha * t
                    gf = 0.0
                    for c in range(d):
                        gc = grad_out[py, px, c]
                        gf += gc * feats[g, c]
                        grads[e, GEOM_GRADS + c] += gc * w
                    done += w * gf
                    if raw <= ALPHA_MAX:
                        d_alpha = t * gf - (total - done) / (1.0 - alpha)
                        grads[e, 5] += gauss * d_alpha
                        d_power = raw * d_alpha
                        grads[e, 0] -= d_power * (a * dx + b * dy)
                        grads[e, 1] -= d_power * (cc * dy + b * dx)
                        grads[e, 2] -= 0.5 * d_power * dx * dx
                        grads[e, 3] -= d_power * dx * dy
                        grads[e, 4] -= 0.5 * d_power * dy * dy
                    t = t_next
    return grads


@_compile(parallel=False)
def sum_by_gaussian(rows, ids, m):
    """Per-Gaussian sums [M, C] of per-intersection rows [I, C], added in the order of ``ids``."""
    total = np.zeros((m, rows.shape[1]))
    for e in range(ids.shape[0]):
        g = ids[e]
        for c in range(rows.shape[1]):
            total[g, c] += rows[e, c]
    return total
