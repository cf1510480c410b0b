"""The votes of candidate pairs: from pairs of Gaussians to accumulator cells in one compiled pass."""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import prange
from torch import Tensor

from ..compiled import compiled, compiled_parallel
from .grid import GridSpec
from .pairs import Axes

_PARTS = 16  # pairs are voted in this many parts, in parallel; any count gives the same votes


def cast_votes(
    x: Tensor, axes: Axes, i: Tensor, j: Tensor, spec: GridSpec, min_cos: float | None, max_d2: float
) -> tuple[Tensor, Tensor, Tensor]:
    """The votes of the pairs (i [P], j [P]) of points x [N, 3]: per vote its flat cell [V] and its pair (i [V],
    j [V]), all int32 on the CPU.

    A pair votes for its bisecting plane (``GridSpec.cells``: canonical hemisphere, a second vote near the seam,
    nothing outside the offset range) unless its points coincide, lie farther apart than sqrt(``max_d2``), or,
    with ``min_cos`` given, their distinct axes disagree: the reflection of one's axis u_i across the bisecting
    plane (normal d / |d|), H u_i . u_j = u_i . u_j - 2 (d . u_i)(d . u_j) / |d|^2, is farther than the angle of
    ``min_cos`` from the other's u_j (either sign), and neither is round. One pass over the pairs instead of a
    dozen array-wide ones, with no intermediate arrays.
    """
    p = x.detach().to(torch.float32).cpu().contiguous().numpy()
    u = axes.u.detach().to(torch.float32).cpu().contiguous().numpy()
    round_ = axes.round.detach().to(torch.float32).cpu().contiguous().numpy()
    a = i.cpu().numpy()
    b = j.cpu().numpy()
    count = a.shape[0]
    cells = np.empty(2 * count, dtype=np.int32)  # a pair votes at most twice; untouched pages cost nothing
    vi = np.empty(2 * count, dtype=np.int32)
    vj = np.empty(2 * count, dtype=np.int32)
    su, sv, sg = spec.shape
    sizes = np.array([spec.cell, spec.depth, spec.seam_z, max_d2, -1.0 if min_cos is None else min_cos])
    dims = np.array([spec.half_uv, spec.half_g, su, sv, sg], dtype=np.int64)
    step = -(-count // _PARTS)
    written = np.zeros(_PARTS, dtype=np.int64)
    _vote_kernel(p, u, round_, a, b, sizes, dims, step, cells, vi, vj, written)
    # Part k wrote its votes from 2 k step on: joined in order, they are the votes of the pairs in order.
    t = lambda v: torch.from_numpy(np.concatenate([v[2 * k * step :][: written[k]] for k in range(_PARTS)]))  # noqa: E731
    return t(cells), t(vi), t(vj)


@compiled
def _cell(n0, n1, n2, g, cell, depth, dims):  # noqa: ANN001, ANN202
    """``GridSpec._flat`` of one plane (unit normal with n2 > -1, offset g): its flat cell, or -1 outside the grid
    (dims: half_uv, half_g and the grid's shape)."""
    half_uv, half_g, su, sv, sg = dims[0], dims[1], dims[2], dims[3], dims[4]
    k = 1.0 / math.sqrt(max(0.5 + 0.5 * n2, 1e-12)) / cell  # Lambert: sqrt(2 / (1 + n_z))
    iu = int(math.floor(n0 * k + 0.5)) + half_uv
    iv = int(math.floor(n1 * k + 0.5)) + half_uv
    ig = int(math.floor(g / depth + 0.5)) + half_g
    if iu < 0 or iu >= su or iv < 0 or iv >= sv or ig < 0 or ig >= sg:
        return -1
    return (iu * sv + iv) * sg + ig


@compiled_parallel
def _vote_kernel(x, u, round_, a, b, sizes, dims, step, cells, vi, vj, written):  # noqa: ANN001, ANN202
    """``cast_votes`` into cells, vi, vj [2 P], in parts of ``step`` pairs run in parallel: part k writes the votes
    of pairs k step.. from position 2 k step on, and their count into written[k]."""
    for part in prange(written.shape[0]):
        first, stop = part * step, min((part + 1) * step, a.shape[0])
        written[part] = _vote_part(x, u, round_, a, b, first, stop, sizes, dims, cells, vi, vj)


@compiled
def _vote_part(x, u, round_, a, b, first, stop, sizes, dims, cells, vi, vj):  # noqa: ANN001, ANN202
    """The votes of pairs first..stop - 1 from position 2 first on; returns how many. sizes: cell, depth, seam_z,
    max_d2 and min_cos (negative: no pruning); dims: as ``_cell``."""
    cell, depth, seam_z, max_d2, min_cos = sizes[0], sizes[1], sizes[2], sizes[3], sizes[4]
    v = 2 * first
    for r in range(first, stop):
        p, q = a[r], b[r]
        d0 = float(x[p, 0]) - float(x[q, 0])
        d1 = float(x[p, 1]) - float(x[q, 1])
        d2 = float(x[p, 2]) - float(x[q, 2])
        length2 = d0 * d0 + d1 * d1 + d2 * d2
        if not (length2 > 1e-12 and length2 <= max_d2):
            continue  # coincident Gaussians define no plane
        if min_cos >= 0.0:
            ui0, ui1, ui2 = float(u[p, 0]), float(u[p, 1]), float(u[p, 2])
            uj0, uj1, uj2 = float(u[q, 0]), float(u[q, 1]), float(u[q, 2])
            cos = ui0 * uj0 + ui1 * uj1 + ui2 * uj2
            cos -= 2.0 * (d0 * ui0 + d1 * ui1 + d2 * ui2) * (d0 * uj0 + d1 * uj1 + d2 * uj2) / length2
            if abs(cos) + round_[p] + round_[q] < min_cos:
                continue
        inv = 1.0 / math.sqrt(length2)
        n0, n1, n2 = d0 * inv, d1 * inv, d2 * inv
        g = 0.5 * (n0 * (float(x[p, 0]) + float(x[q, 0])) + n1 * (float(x[p, 1]) + float(x[q, 1])))
        g += 0.5 * n2 * (float(x[p, 2]) + float(x[q, 2]))
        if n2 < 0.0:
            n0, n1, n2, g = -n0, -n1, -n2, -g
        c = _cell(n0, n1, n2, g, cell, depth, dims)
        if c >= 0:
            cells[v], vi[v], vj[v] = c, p, q
            v += 1
        if n2 < seam_z:  # near the seam: also as the flipped twin
            c = _cell(-n0, -n1, -n2, -g, cell, depth, dims)
            if c >= 0:
                cells[v], vi[v], vj[v] = c, p, q
                v += 1
    return v - 2 * first
