"""What a render returns, whichever backend drew it."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from torch import Tensor


@dataclass
class RenderResult:
    """One rendered view.

    image  [H, W, 3]  colour over the background, clamped to [0, 1]
    alpha  [H, W]     accumulated opacity, 1 - final transmittance
    depth  [H, W]     expected camera-space z of what was composited (sum w z / sum w; 0 where nothing was)
    aux               ``radii`` [N] int32 pixel radius per scene Gaussian (0: culled), ``backend`` ("cpu" or
                      "gsplat"); the CPU backend adds ``num_intersections`` (tile-Gaussian pairs)
    """

    image: Tensor
    alpha: Tensor
    depth: Tensor
    aux: dict[str, Any] = field(default_factory=dict)

    @property
    def num_visible(self) -> int:
        """Gaussians drawn: counted when asked (on a GPU, counting waits for the render)."""
        return int((self.aux["radii"] > 0).sum())
