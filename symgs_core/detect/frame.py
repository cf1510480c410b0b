"""The normalised frame detection works in: centred at the median of the means, lengths in units of a robust radius."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..mirror import Plane


@dataclass(frozen=True)
class Frame:
    centre: Tensor  # [3] median of the means
    radius: float  # robust extent: a quantile of the distances to the centre

    def to_local(self, points: Tensor) -> Tensor:
        """Points [N, 3] in the normalised frame."""
        return (points - self.centre) / self.radius

    def plane_to_world(self, normal: Tensor, offset: float) -> tuple[Tensor, float]:
        """A plane n.x = offset of the normalised frame as (normal, offset) in the scene's own coordinates."""
        return normal, offset * self.radius + float(normal.to(self.centre.dtype) @ self.centre)

    def plane_to_local(self, plane: Plane) -> tuple[Tensor, float]:
        """A plane of the scene as (unit normal [3] float64, offset) in the normalised frame."""
        n = torch.tensor(plane.normal, dtype=torch.float64, device=self.centre.device)
        return n, (plane.offset - float(n @ self.centre.to(torch.float64))) / self.radius


def normalised_frame(means: Tensor, quantile: float) -> Frame | None:
    """The frame of ``means`` [N, 3], or None when the points have no extent (fewer than two distinct points)."""
    if means.shape[0] < 2:
        return None
    # torch's median (the lower middle value) per axis, by a partial sort of each column.
    m = means.detach().cpu().numpy()
    middle = (m.shape[0] - 1) // 2
    centre = torch.tensor([float(np.partition(m[:, a], middle)[middle]) for a in range(3)], dtype=means.dtype,
                          device=means.device)  # fmt: skip
    dist = (means - centre).norm(dim=1)
    k = min(max(int(round(quantile * dist.numel())), 1), dist.numel())
    radius = float(dist.kthvalue(k).values)
    if not radius > 0:
        radius = float(dist.max())  # most points coincide with the centre: fall back to the full extent
    if not (radius > 0 and math.isfinite(radius)):
        return None
    return Frame(centre, radius)
