"""Levels of mirrors and the expansion of a stored set through them.

The archive keeps a stored set S (an ordered list of Gaussians), the mirror planes M_0..M_L (M_0 the dominant one)
and a bit matrix B [|S|, L+1]: B[i, l] says that Gaussian i is *left* at level l (kept and reflected across M_l).
Decoding runs from level L down to 0: at level l the members of the current set whose bit l is set are reflected
across M_l and appended, in order, and each reflection inherits the bits of its source. So a reflection made at a
local level is mirrored again by every larger mirror its source belongs to. The expansion is exact, O(N) per level,
and needs no nearest-neighbour search.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .mirror import Plane, reflect
from .scene import GaussianScene


def expand(stored: GaussianScene, normals: Tensor, offsets: Tensor, bits: Tensor) -> tuple[GaussianScene, Tensor]:
    """Expand ``stored`` through the levels.

    normals [L+1, 3], offsets [L+1] (level 0 first), bits [|S|, L+1] bool.
    Returns the expanded scene and, for each of its Gaussians, the index [N_out] of the stored Gaussian it derives
    from. Differentiable in the stored attributes and in the planes.
    """
    levels = normals.shape[0]
    if tuple(offsets.shape) != (levels,) or tuple(bits.shape) != (len(stored), levels):
        raise ValueError(
            f"expand: normals {tuple(normals.shape)}, offsets {tuple(offsets.shape)} and bits "
            f"{tuple(bits.shape)} disagree with {len(stored)} stored Gaussians"
        )
    scene = stored
    cur_bits = bits.to(torch.bool)
    origin = torch.arange(len(stored), device=stored.device)
    for level in range(levels - 1, -1, -1):
        sel = cur_bits[:, level]
        if not bool(sel.any()):
            continue
        mirrored = reflect(scene.select(sel), normals[level], offsets[level])
        scene = GaussianScene.cat([scene, mirrored])
        cur_bits = torch.cat([cur_bits, cur_bits[sel]])
        origin = torch.cat([origin, origin[sel]])
    return scene, origin


def expand_planes(stored: GaussianScene, planes: list[Plane], bits: Tensor) -> GaussianScene:
    """``expand`` with planes given as ``Plane`` objects (level 0 first)."""
    if planes:
        normals = torch.tensor([p.normal for p in planes], dtype=stored.means.dtype, device=stored.device)
        offsets = torch.tensor([p.offset for p in planes], dtype=stored.means.dtype, device=stored.device)
    else:
        normals = torch.zeros(0, 3, dtype=stored.means.dtype, device=stored.device)
        offsets = torch.zeros(0, dtype=stored.means.dtype, device=stored.device)
    return expand(stored, normals, offsets, bits)[0]
