"""Spatially separate parts of a working set, where a small object's mirror can be found on its own.

A mirror is significant when it covers a good share of the Gaussians searched; a small object beside a large one
never does in the whole scene, though it is symmetric through and through. Occupied voxels of a coarse grid, joined
with their 26 neighbours, split the working set into parts that no gap narrower than a voxel separates.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy import ndimage
from torch import Tensor

_MAX_CELLS = 128  # voxels along the longest side of the working set's box
CELL_SHARE = 0.02  # voxel side as a share of the robust radius, when the box allows it


def spatial_components(means: Tensor, radius: float, *, min_size: int) -> list[Tensor]:
    """Indices [M_k] of each spatially separate part of ``means`` [N, 3] with at least ``min_size`` points,
    largest first; empty when everything is one part (the whole working set already was searched)."""
    points = means.detach().to("cpu", torch.float64).numpy()
    if len(points) < 2 * min_size or not np.isfinite(points).all():
        return []
    lo, hi = points.min(axis=0), points.max(axis=0)
    cell = max(CELL_SHARE * radius, float((hi - lo).max()) / _MAX_CELLS, 1e-12)
    cells = np.floor((points - lo) / cell).astype(np.int64)
    grid = np.zeros(tuple(cells.max(axis=0) + 1), dtype=bool)
    grid[tuple(cells.T)] = True
    labels, count = ndimage.label(grid, structure=np.ones((3, 3, 3), dtype=bool))
    if count < 2:
        return []
    of_point = labels[tuple(cells.T)]
    sizes = np.bincount(of_point, minlength=count + 1)
    order = [label for label in np.argsort(-sizes) if label and sizes[label] >= min_size]
    return [torch.from_numpy(np.flatnonzero(of_point == label)).to(means.device) for label in order]
