"""The order in which the stored set is written: equal level-bit rows together, then a Morton curve inside each group.

Grouping by bit row (level 0 most significant) turns column l of the bit matrix into at most 2^(l+1) runs, so the
masks cost next to nothing; the Morton order keeps consecutive Gaussians close in space, which position coders
(deltas, quantisation in a space-filling-curve order) exploit. Reordering the stored set together with its bit
rows changes the expanded scene only by a permutation (see ``hierarchy.expand``).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..scene import GaussianScene

MORTON_BITS = 21  # per axis: 3 x 21 bits fill a non-negative int64


def _spread_bits(v: Tensor) -> Tensor:
    """Insert two zero bits above each of the low 21 bits of ``v`` [N] int64 (bit k -> bit 3k)."""
    v = v & 0x1FFFFF
    v = (v | (v << 32)) & 0x1F00000000FFFF
    v = (v | (v << 16)) & 0x1F0000FF0000FF
    v = (v | (v << 8)) & 0x100F00F00F00F00F
    v = (v | (v << 4)) & 0x10C30C30C30C30C3
    v = (v | (v << 2)) & 0x1249249249249249
    return v


def morton_codes(points: Tensor) -> Tensor:
    """Morton (Z-order) codes [N] int64 of ``points`` [N, 3] quantised to 21 bits per axis in their bounding box."""
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {tuple(points.shape)}")
    if len(points) == 0:
        return torch.zeros(0, dtype=torch.int64, device=points.device)
    p = points.detach().to(torch.float64)
    if not bool(torch.isfinite(p).all()):
        raise ValueError("points must be finite to be ordered along a space-filling curve")
    lo = p.min(dim=0).values
    extent = (p.max(dim=0).values - lo).clamp_min(torch.finfo(torch.float64).tiny)
    top = (1 << MORTON_BITS) - 1
    q = ((p - lo) / extent * top).round().clamp(0, top).to(torch.int64)
    return _spread_bits(q[:, 0]) | (_spread_bits(q[:, 1]) << 1) | (_spread_bits(q[:, 2]) << 2)


def coding_order(stored: GaussianScene, bits: Tensor) -> Tensor:
    """Permutation [|S|] int64 that groups equal rows of ``bits`` [|S|, L+1] and orders each group by Morton code.

    Groups come in lexicographic order of their rows, level 0 first; ties keep their input order, so the result is
    deterministic. Apply it to the stored set and the bit rows together (``ArchiveContents.permuted``).
    """
    n = len(stored)
    if bits.ndim != 2 or bits.shape[0] != n:
        raise ValueError(f"bits must have shape ({n}, L+1) for {n} stored Gaussians, got {tuple(bits.shape)}")
    levels = bits.shape[1]
    if levels > 62:
        raise ValueError(f"coding_order packs bit rows into int64 keys: at most 62 levels, got {levels}")
    codes = morton_codes(stored.means)
    weights = 1 << torch.arange(levels - 1, -1, -1, dtype=torch.int64, device=bits.device)
    groups = (bits.to(torch.int64) * weights).sum(dim=1).to(codes.device)
    by_curve = torch.argsort(codes, stable=True)
    return by_curve[torch.argsort(groups[by_curve], stable=True)]
