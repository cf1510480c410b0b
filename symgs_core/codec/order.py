"""The order in which the stored set is written: equal level-bit rows together, then equal step classes, then a Morton
curve inside each group.

Grouping by bit row (level 0 most significant) turns column l of the bit matrix into at most 2^(l+1) runs, so the
masks cost next to nothing, and grouping by step class (``classes``) does the same for the classes; the Morton order
keeps consecutive Gaussians close in space, which position coders (deltas, quantisation in a space-filling-curve
order) exploit. Reordering the stored set together with its bit
rows changes the expanded scene only by a permutation (see ``hierarchy.expand``).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ..scene import GaussianScene
from .morton import AXIS_BITS, fits, interleave


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
    top = (1 << AXIS_BITS) - 1
    q = ((p - lo) / extent * top).round().clamp(0, top).to(torch.int64)
    return torch.from_numpy(interleave(q.cpu().numpy())).to(points.device)


def coding_order(
    stored: GaussianScene, bits: Tensor, cells: np.ndarray | None = None, classes: Tensor | None = None
) -> Tensor:
    """Permutation [|S|] int64 that groups equal rows of ``bits`` [|S|, L+1], then equal ``classes`` [|S|] (step
    classes, ascending; None: one class), and orders each group by Morton code.

    ``cells`` [|S|, 3]: the grid cells a quantising position codec puts the stored set in (``fits`` the Morton
    range), each on its class's grid; the Morton codes are then theirs, so positions rise along the curve of their
    own grid within each group, as ``codec.morton`` codes them. Without, positions are placed on a 2^21 grid in
    their bounding box.

    Groups come in lexicographic order of their rows, level 0 first; ties keep their input order, so the result is
    deterministic. Apply it to the stored set, the bit rows and the classes together (``ArchiveContents.permuted``).
    """
    n = len(stored)
    if bits.ndim != 2 or bits.shape[0] != n:
        raise ValueError(f"bits must have shape ({n}, L+1) for {n} stored Gaussians, got {tuple(bits.shape)}")
    levels = bits.shape[1]
    if levels > 54:
        raise ValueError(f"coding_order packs bit rows and classes into int64 keys: at most 54 levels, got {levels}")
    if cells is not None and (cells.shape != (n, 3) or not fits(cells)):
        raise ValueError(f"cells must be [{n}, 3] grid cells in 0..2^{AXIS_BITS} - 1")
    if classes is not None and tuple(classes.shape) != (n,):
        raise ValueError(f"classes must have shape ({n},), got {tuple(classes.shape)}")
    codes = morton_codes(stored.means) if cells is None else torch.from_numpy(interleave(cells)).to(bits.device)
    weights = 1 << torch.arange(levels - 1, -1, -1, dtype=torch.int64, device=bits.device)
    groups = (bits.to(torch.int64) * weights).sum(dim=1)
    if classes is not None:  # classes below 2^8 (``codec.classes``) in the low byte of each group's key
        groups = groups * 256 + classes.to(device=bits.device, dtype=torch.int64)
    groups = groups.to(codes.device)
    by_curve = torch.argsort(codes, stable=True)
    return by_curve[torch.argsort(groups[by_curve], stable=True)]


def grid_cells(position_codec: object, means: np.ndarray, classes: np.ndarray | None = None) -> np.ndarray | None:
    """The cells [N, 3] a quantising position codec puts ``means`` [N, 3] float32 in (each on the grid of its step
    class, ``classes`` [N]), when they fit the Morton range; None for other codecs (float32 positions keep the
    bounding-box curve)."""
    cells = getattr(position_codec, "cells", None)
    if cells is None:
        return None
    grid = cells(means, classes)
    return grid if fits(grid) else None
