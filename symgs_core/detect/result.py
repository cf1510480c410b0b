"""A detected mirror and the membership of the working set it was found in."""

from __future__ import annotations

from dataclasses import dataclass, field

from torch import Tensor

from ..mirror import Plane


@dataclass
class Mirror:
    """One mirror, in the coordinates of the scene given to ``detect``.

    plane     n.x = offset, normal canonical (its largest-magnitude component positive)
    votes     votes in the 3x3x3 accumulator cells around the peak
    left      [L] indices of the Gaussians kept and reflected: the side of the plane with more matched Gaussians
              (on a tie, the side the normal points to)
    right     [R] indices of the Gaussians the reflected left ones cover (dropped)
    out       [O] the rest of this level's working set
    coverage  (|left| + |right|) / working set size
    level     0 for the first mirror; level l was searched in the left and out sets of level l - 1
    timings   seconds per step
    found_in  where it was found: "scene" (the whole working set), "part" (a spatially separate part of it) or
              "focus" (the ball the photographs' cameras look at)
    """

    plane: Plane
    votes: int
    left: Tensor
    right: Tensor
    out: Tensor
    coverage: float
    level: int = 0
    timings: dict[str, float] = field(default_factory=dict)
    found_in: str = "scene"

    @property
    def normal(self) -> tuple[float, float, float]:
        return self.plane.normal

    @property
    def offset(self) -> float:
        return self.plane.offset

    def summary(self) -> dict:
        """JSON-ready description; membership as counts."""
        return {
            "level": self.level,
            "normal": list(self.plane.normal),
            "offset": self.plane.offset,
            "votes": self.votes,
            "left": int(self.left.numel()),
            "right": int(self.right.numel()),
            "out": int(self.out.numel()),
            "coverage": self.coverage,
            "timings": dict(self.timings),
            "found_in": self.found_in,
        }
