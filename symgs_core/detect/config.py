"""Settings of symmetry detection: one frozen object, passed down, never mutated."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any


@dataclass(frozen=True)
class DetectConfig:
    """How mirrors are searched for. Lengths are fractions of the scene radius R (a robust extent), angles radians.

    colour_bins, opacity_bins, scale_bins   clustering: bins per HSV channel of the DC colour, of the opacity, and
                                            of each sorted log-scale
    angle_res, offset_res                   accumulator cells: side of a normal cell (equal-area, about that many
                                            radians) and depth of an offset cell (fraction of R)
    radius_quantile                         R is this quantile of the distances to the median of the means
    pair_budget, pairs_per_gaussian          pairs voted per level: at most pair_budget, and at most
                                            pairs_per_gaussian per Gaussian of the working set; clusters whose
                                            pairs fit in ``enumerate_share`` of it are enumerated, the rest sampled
    max_pair_distance                       pairs farther apart do not vote (fraction of R; None: no limit), to
                                            favour local mirrors
    axis_tolerance                          a pair votes only if the reflected distinct axis (the shortest of a
                                            flat Gaussian, the longest of a needle) of one Gaussian is within this
                                            angle of the other's (None: no covariance pruning); loose by default,
                                            real twins differ
    axis_ratio                              an axis is distinct when its scale stands out by this factor
    refine_iters                            mean-shift steps refining the plane from the votes near the peak
    icp_iters                               then iterated-closest-point steps refitting it to the matched sides
    match_tolerance                         correspondence: a reflected Gaussian covers one within this many local
                                            spacings (distance to the nearest neighbour on its side)
    attribute_weight                        how much attribute agreement (colour, opacity, sizes, orientation) may
                                            shape the match score, 0..1 (0: geometry alone); scaled down by how
                                            often close matches agree at all (real captures' halves rarely do)
    min_coverage                            a mirror is reported only if (|left| + |right|) / working set >= this
    min_significance                        ... and this many times the share random planes match in the same
                                            working set (what matches by chance)
    max_mirrors                             levels searched; each repeats detection on left + out
    candidates                              peaks tried per level, best first, until one passes min_coverage
    min_votes                               peaks with fewer votes (3x3x3 cells) are noise, never tried
    min_gaussians                           a working set smaller than this is not searched
    seed                                    seed of the pair sampling
    """

    colour_bins: int = 8
    opacity_bins: int = 4
    scale_bins: int = 6
    angle_res: float = 0.01
    offset_res: float = 0.01
    radius_quantile: float = 0.99
    pair_budget: int = 4_000_000
    pairs_per_gaussian: float = 8.0
    enumerate_share: float = 0.5
    max_pair_distance: float | None = None
    axis_tolerance: float | None = 0.5
    axis_ratio: float = 1.5
    refine_iters: int = 6
    icp_iters: int = 8
    match_tolerance: float = 2.0
    attribute_weight: float = 0.6
    min_coverage: float = 0.15
    min_significance: float = 2.0
    max_mirrors: int = 4
    candidates: int = 3
    min_votes: int = 5
    min_gaussians: int = 32
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("colour_bins", "opacity_bins", "scale_bins", "pair_budget", "candidates", "min_votes"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        for name in ("angle_res", "offset_res"):
            if not 0 < getattr(self, name) < 1:
                raise ValueError(f"{name} must be in (0, 1), got {getattr(self, name)!r}")
        if not self.match_tolerance > 0:
            raise ValueError(f"match_tolerance must be positive, got {self.match_tolerance!r}")
        for name in ("radius_quantile", "enumerate_share"):
            if not 0 < getattr(self, name) <= 1:
                raise ValueError(f"{name} must be in (0, 1], got {getattr(self, name)!r}")
        for name in ("attribute_weight", "min_coverage"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)!r}")
        if self.max_pair_distance is not None and not self.max_pair_distance > 0:
            raise ValueError(f"max_pair_distance must be positive or None, got {self.max_pair_distance!r}")
        if self.axis_tolerance is not None and not 0 <= self.axis_tolerance <= 1.5708:
            raise ValueError(f"axis_tolerance must be in [0, pi/2] radians or None, got {self.axis_tolerance!r}")
        if not self.min_significance >= 0:
            raise ValueError(f"min_significance must be non-negative, got {self.min_significance!r}")
        if not self.axis_ratio >= 1:
            raise ValueError(f"axis_ratio must be >= 1, got {self.axis_ratio!r}")
        for name in ("refine_iters", "icp_iters", "max_mirrors"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        if self.min_gaussians < 2:
            raise ValueError(f"min_gaussians must be >= 2, got {self.min_gaussians!r}")

    @classmethod
    def with_overrides(cls, overrides: Mapping[str, Any]) -> DetectConfig:
        """The defaults with ``overrides``; ValueError names an unknown setting (and lists the known ones), a value of
        the wrong type or out of range."""
        known = {f.name: str(f.type) for f in fields(cls)}  # "int", "float" or "float | None"
        unknown = sorted(map(str, set(overrides) - set(known)))
        if unknown:
            raise ValueError(f"unknown detect settings {', '.join(unknown)}; known: {', '.join(known)}")
        for name, value in overrides.items():
            kind = known[name]
            if value is None and kind.endswith("| None"):
                continue
            if isinstance(value, bool) or not isinstance(value, int if kind == "int" else (int, float)):
                wanted = {"int": "an integer", "float": "a number"}.get(kind, "a number or None")
                raise ValueError(f"detect setting {name} must be {wanted}, got {value!r}")
        return cls(**overrides)
